"""The pose graph's log in the service: each keyframe appended and fsync'd before the graph
process gets it, and taken again from the log by every (re)started process.

:class:`GraphJournal` is the writer thread and the restore (service/graph_log.py is the file);
what it moves goes through the queue (service/graph_queue.py). docs/mapping.md, "In the service":
"The graph is durable".
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

from randt.core.errors import RandtError
from randt.service.graph_log import GraphLog
from randt.service.graph_queue import GraphQueue, Item
from randt.service.graph_state import GraphView
from randt.service.metrics import ServiceMetrics

__all__ = ["GraphJournal", "replayable"]

log = logging.getLogger(__name__)


def replayable(records: list[tuple[float, Item]]) -> list[tuple[float, Item]]:
    """The logged keyframes the graph is to take again, in order: every one offered, but those a
    ``drop`` record names (dropped by a full queue, or in flight at two deaths of the process: the
    graph never took them)."""
    dropped = {tuple(item[1:5]) for _, item in records if item[0] == "drop"}
    return [
        (stamp, item) for stamp, item in records if item[0] == "keyframe" and tuple(item[1:5]) not in dropped
    ]


class GraphJournal:
    """The durable side of the graph (module docstring); with no ``log_dir`` the graph lives in
    memory only and every method but :meth:`restore` is unused."""

    def __init__(
        self,
        log_dir: str | os.PathLike[str] | None,
        queue: GraphQueue,
        view: GraphView,
        metrics: ServiceMetrics,
    ) -> None:
        self.log: GraphLog | None = None if log_dir is None else GraphLog(log_dir)
        #: Where the graph process keeps the keyframes' points (rebuilt from the log at each start).
        self.spill: Path | None = None if log_dir is None else Path(log_dir) / "spill"
        #: Held by the writer while it appends one keyframe, and by whoever rewrites the log or
        #: the queue's keyframes (a deleted map, a dead process): they wait between two keyframes.
        self.writing = threading.Lock()
        self._queue = queue
        self._view = view
        self._metrics = metrics

    @property
    def durable(self) -> bool:
        return self.log is not None

    def restore(self) -> bool:
        """A (re)started service: the keyframes the graph took before, as it took them, queued
        first (the process rebuilds the graph from them before it takes new ones); the service's
        side (each keyframe's live pose, the sessions' maps) set up. True if any were queued."""
        if self.log is None:
            return False
        try:
            floors = self.log.floors()
        except RandtError as exc:
            log.error("pose graph: %s: the revisions of maps deleted before may start lower", exc)
            floors = {}
        self._view.bases = {name: (revision, 0) for name, revision in floors.items()}
        records = replayable(self.log.read())
        if not records:
            return False
        self._view.restore(records)
        log.info("pose graph: %d keyframes to take again from %s", len(records), self.log.path)
        self._queue.replay([item for _, item in records])
        return True

    def replay(self) -> None:
        """Queue the log's keyframes again, first (a new process after a death)."""
        assert self.log is not None
        self._queue.replay([item for _, item in replayable(self.log.read())])

    def write_loop(self) -> None:
        """The writer: each offered keyframe appended to the log and fsync'd, in the order offered,
        then queued for the process (so the graph takes them in the log's order, and shows
        nothing made of a keyframe before it is durable). One that cannot be written is not
        given to the graph (counted; logged)."""
        q = self._queue
        while True:
            with q.cond:
                q.cond.wait_for(lambda: q.closed or bool(q.unlogged))
                if q.closed:
                    return
            with self.writing:
                with q.cond:
                    if not q.unlogged:  # (taken out by forget_map meanwhile)
                        continue
                    item = q.unlogged[0]
                ok = self.append(self._stamp_of(item), item)
                with q.cond:
                    if q.unlogged and q.unlogged[0] is item:
                        q.unlogged.pop(0)
                    if not ok:
                        q.not_logged()
                    dropped = q.enqueue(item) if ok else None
                if not ok:
                    self._view.forget_keyframe(item[1], (item[2], item[3]), item[4])
                elif dropped is not None:  # logged before: the graph never took it
                    self.drop(dropped)

    def append(self, stamp_s: float, item: Item) -> bool:
        assert self.log is not None
        try:
            self.log.append((stamp_s, item))
        except RandtError:
            self._metrics.store_errors.inc()
            log.exception("pose graph: %s %s/%s seq %d not made durable", item[0], item[2], item[3], item[4])
            return False
        return True

    def drop(self, item: Item) -> None:
        """A logged keyframe the graph never took: a ``drop`` record, so no replay takes it."""
        self.append(0.0, ("drop", *item[1:5]))

    def forget_map(self, map_name: str, revision: int) -> None:
        """A deleted map out of the log (:meth:`GraphLog.without_map`: a restart never brings it
        back); its revision stays the floor of a later map of the same name (called with
        :attr:`writing` held).

        Raises
        ------
        FormatError
            The log could not be rewritten (the graph is then as it was).
        """
        if self.log is None:
            return
        self.log.set_floor(map_name, revision)
        gone = self.log.without_map(map_name)
        log.info("pose graph of map %s deleted (%d records out of its log)", map_name, gone)

    def _stamp_of(self, item: Item) -> float:
        """The stamp of a keyframe item (the service keeps it beside, in its ``Keyframe``)."""
        _, map_name, vehicle, session, _seq, index = item[:6]
        return self._view.stamp_of(map_name, (vehicle, session), index)
