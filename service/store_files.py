"""The store's housekeeping of its files: the temporary files interrupted writes leave behind,
the ``.deleted-*`` directories of interrupted deletes and copies, a directory copied in one
visible step, and how a file that cannot be read is reported (:class:`StoreProblem`).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import time
import weakref
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from randt.core.errors import RandtError
from randt.core.io.atomic import fsync_directory
from randt.service.capacity_record import CAPACITY_FILENAME
from randt.service.counter_totals import COUNTERS_FILENAME

__all__ = [
    "DELETED_PREFIX",
    "OpenCheck",
    "ProblemKind",
    "StoreProblem",
    "copy_tree_durably",
    "remove_temp_files",
    "report_problem",
]

logger = logging.getLogger(__name__)

ProblemKind = Literal["map", "session", "entry"]

# randt.core.io.atomic names its temporary files tempfile.mkstemp(prefix=f".{target}.", suffix=".tmp"),
# in the target's directory. No name the store writes starts with a dot (ids, fixed names).
_TEMP_FILE_RE = re.compile(r"^\..+\.tmp$")
DELETED_PREFIX = ".deleted-"  # maps/.deleted-<name>-...: a delete_map that did not finish


@dataclass(frozen=True)
class StoreProblem:
    """A map, session or directory entry that was skipped because it could not be read.

    Attributes
    ----------
    kind:
        ``"map"``, ``"session"`` or ``"entry"`` (an unexpected directory entry).
    name:
        The map name, ``"<vehicle>/<session>"``, or the entry's relative path.
    path:
        The file or directory at fault.
    message:
        Why it was skipped.
    """

    kind: ProblemKind
    name: str
    path: Path
    message: str


def report_problem(problems: list[StoreProblem], kind: ProblemKind, name: str, path: Path, msg: str) -> None:
    """Log a skipped map, session or entry and add it to ``problems``."""
    logger.error("skipping %s %s: %s", kind, name, msg)
    problems.append(StoreProblem(kind=kind, name=name, path=path, message=msg))


def remove_temp_files(root: Path, maps: Path, trees: Iterable[Path]) -> int:
    """Delete leftover ``.<name>.<random>.tmp`` files in ``root`` (``DATA``: ``counters.json``,
    ``capacity.json``) and under ``trees`` (``maps/``, ``sessions/`` and ``map-versions/``), and the
    ``maps/.deleted-*`` directories of an interrupted :meth:`Store.delete_map
    <randt.service.store.Store.delete_map>` (or map-name migration). Returns how many."""
    removed = 0
    for entry in maps.iterdir():
        if entry.name.startswith(DELETED_PREFIX) and entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
            removed += 1
    # The data directory's own files (counters.json, capacity.json) are written atomically too:
    # their leftovers sit in DATA itself, among files that may not be ours (only ours are removed).
    ours = (f".{COUNTERS_FILENAME}.", f".{CAPACITY_FILENAME}.")
    top_level = [(str(root), [e.name for e in root.iterdir() if e.name.startswith(ours)])]
    walks = [(d, f) for top in trees for d, _, f in os.walk(top)]
    for dirpath, filenames in top_level + walks:  # os.walk does not follow symlinks
        for name in filenames:
            path = Path(dirpath) / name
            if not _TEMP_FILE_RE.match(name) or path.is_symlink() or not path.is_file():
                continue
            try:
                path.unlink()
            except OSError as exc:
                logger.warning("cannot remove leftover temporary file %s: %s", path, exc)
                continue
            logger.debug("removed leftover temporary file %s", path)
            removed += 1
    return removed


def copy_tree_durably(source: Path, target: Path, parent: Path) -> None:
    """Copy the directory ``source`` to ``target`` (in ``parent``) in one visible step: copy into
    ``parent/.deleted-copy-*`` (removed on the next open if this is interrupted), fsync every file
    and the directory, then rename it to ``target``."""
    scratch = parent / f"{DELETED_PREFIX}copy-{target.name}-{os.getpid()}-{time.time_ns()}"
    shutil.copytree(source, scratch)
    for path in scratch.rglob("*"):
        if path.is_file():
            with path.open("rb+") as fh:
                os.fsync(fh.fileno())
    fsync_directory(scratch)
    os.replace(scratch, target)


class OpenCheck:
    """Raises once the store is closed: what the store's parts call before each read and write.

    It holds the store's finalizer, not the store: a reference from the parts back to the store
    would keep a store that is dropped unclosed (and its lock) alive until the garbage collector
    runs.
    """

    def __init__(self, finalizer: weakref.finalize, root: Path) -> None:
        self._finalizer, self._root = finalizer, root

    def __call__(self) -> None:
        if not self._finalizer.alive:
            raise RandtError(f"the store at {self._root} is closed")
