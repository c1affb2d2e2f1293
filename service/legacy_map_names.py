"""Sessions' own maps under their legacy names (``<vehicle>.<session>``, which collided), moved to
the injective ones (:func:`randt.wire.ids.session_map_name`) when the store loads everything.
"""

from __future__ import annotations

import logging
import os

from randt.core.errors import RandtError
from randt.core.io.atomic import fsync_directory
from randt.service.session_record import SessionRecord
from randt.service.session_store import SessionStore
from randt.service.store_files import copy_tree_durably
from randt.service.tile_store import TileStore
from randt.wire.ids import legacy_session_map_name, session_map_name

__all__ = ["migrate_map_names"]

logger = logging.getLogger(__name__)


def migrate_map_names(
    tiles: TileStore, sessions: SessionStore, records: list[SessionRecord]
) -> list[tuple[str, str, str]]:
    """Rename the maps of sessions without priors to their injective names (run by
    :meth:`Store.load_all <randt.service.store.Store.load_all>`); ``records``: every stored session's.

    Before, a session's own map was ``<vehicle>.<session>``, which collided (vehicle ``col.a``
    + session ``b`` and vehicle ``col`` + session ``a.b`` shared ``col.a.b``). Each stored
    session in its own frame whose record names that legacy map
    (:func:`randt.wire.ids.legacy_session_map_name`) moves to :func:`randt.wire.ids.session_map_name`:

    1. the map directory is renamed (one atomic step) when this session is its only user,
       else copied (into a temporary directory, fsync'd, renamed): a map two sessions were
       fused into stays fused, and each of them keeps a copy;
    2. the session's record is saved with the new name;
    3. a legacy map no record names any more is deleted.

    Every step can be interrupted: the next open redoes what is left (an interrupted copy is
    a ``.deleted-*`` directory, removed on open). Names that need no change (ids of letters,
    digits and dashes) are untouched, so usually there is nothing to do.

    Returns
    -------
    list[tuple[str, str, str]]
        ``("<vehicle>/<session>", old map, new map)`` for each session moved.
    """
    moves = [
        (r, session_map_name(r.vehicle, r.session))
        for r in records
        if r.frame == "session"
        and r.map is not None
        and r.map == legacy_session_map_name(r.vehicle, r.session)
        and r.map != session_map_name(r.vehicle, r.session)
    ]
    done: list[tuple[str, str, str]] = []
    for record, new in moves:
        old = record.map
        assert old is not None  # filtered above
        users = sum(r.map == old for r in records)
        old_dir, new_dir = tiles.map_dir(old), tiles.map_dir(new)
        try:
            with tiles.map_lock(old), tiles.map_lock(new):
                if old_dir.is_dir() and not new_dir.exists():
                    if users == 1:
                        os.replace(old_dir, new_dir)
                    else:
                        copy_tree_durably(old_dir, new_dir, tiles.maps_dir)
                    fsync_directory(tiles.maps_dir)
            with sessions.session_lock(record.vehicle, record.session):
                loaded = sessions.load_session(record.vehicle, record.session)
                sessions.save_session(
                    loaded.record.model_copy(update={"map": new}),
                    loaded.poses,
                    loaded.stamps,
                    loaded.state,
                )
        except (RandtError, OSError, ValueError) as exc:
            logger.error(
                "store: could not move map %s of session %s/%s to %s: %s",
                old,
                record.vehicle,
                record.session,
                new,
                exc,
            )
            continue
        records = [r for r in records if r.key != record.key] + [record.model_copy(update={"map": new})]
        done.append((f"{record.vehicle}/{record.session}", old, new))
        logger.warning(
            "store: session %s/%s's map %s is now %s (injective session-map names)%s",
            record.vehicle,
            record.session,
            old,
            new,
            "" if users == 1 else f"; {users} sessions were fused in {old}: each keeps a copy",
        )
    named = {r.map for r in records}
    for old in {old for _, old, _ in done} - named:
        tiles.delete_map(old)
    return done
