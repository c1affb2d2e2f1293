"""Keyframe arrays in bounded memory: the newest in RAM, every one on disk (issue 33).

A pose graph keeps each keyframe's points for as long as the map lives: a loop closure or a
placement vote may register any two keyframes, and a re-fold of the map's tiles needs the points
of every keyframe behind them. At a keyframe every 10 m and some 20-30 thousand points each, that
is about 100 MB per kilometre of road in RAM: a city's map would not fit a node.
:class:`KeyframeCache` keeps the ``capacity`` keyframes used last in memory and every keyframe's
arrays in one ``.npy`` file per array under ``directory`` (written once, when the keyframe comes;
read again when it is needed and no longer in memory). Without a directory it is a plain dict
(everything in RAM).

The files are a cache of what the caller can rebuild (the service's graph log holds every
keyframe): they are not fsync'd, and a cache opened on a directory clears it first.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from collections import OrderedDict
from collections.abc import Hashable, Iterator
from pathlib import Path

import numpy as np

__all__ = ["KeyframeCache"]


class KeyframeCache:
    """``key -> tuple of arrays``, at most ``capacity`` keys in memory (module docstring).

    Parameters
    ----------
    directory:
        Where every keyframe's arrays are written (cleared at open); ``None``: in memory only.
    capacity:
        Keyframes kept in memory when there is a directory (the least recently used leave).
    """

    def __init__(self, directory: str | os.PathLike[str] | None = None, capacity: int = 128) -> None:
        if capacity < 1:
            raise ValueError("KeyframeCache: capacity must be >= 1")
        self.directory = None if directory is None else Path(directory)
        self.capacity = capacity
        self._hot: OrderedDict[Hashable, tuple[np.ndarray, ...]] = OrderedDict()
        self._arity: dict[Hashable, int] = {}
        self.loads = 0  # arrays read back from disk (misses)
        if self.directory is not None:
            shutil.rmtree(self.directory, ignore_errors=True)
            self.directory.mkdir(parents=True, exist_ok=True)

    def __contains__(self, key: object) -> bool:
        return key in self._arity

    def __len__(self) -> int:
        return len(self._arity)

    def __iter__(self) -> Iterator[Hashable]:
        return iter(self._arity)

    @property
    def in_memory(self) -> int:
        """Keyframes whose arrays are in RAM now."""
        return len(self._hot)

    def _path(self, key: Hashable, i: int) -> Path:
        assert self.directory is not None
        name = hashlib.sha1(repr(key).encode()).hexdigest()
        return self.directory / f"{name}.{i}.npy"

    def put(self, key: Hashable, *arrays: np.ndarray) -> None:
        """Keep ``arrays`` under ``key`` (replacing what it held)."""
        arrays = tuple(np.ascontiguousarray(a) for a in arrays)
        if self.directory is not None:
            for i, a in enumerate(arrays):
                np.save(self._path(key, i), a, allow_pickle=False)
        self._arity[key] = len(arrays)
        self._hot[key] = arrays
        self._hot.move_to_end(key)
        self._trim()

    def get(self, key: Hashable) -> tuple[np.ndarray, ...]:
        """The arrays under ``key`` (read back from disk when they left memory); KeyError if none."""
        arrays = self._hot.get(key)
        if arrays is not None:
            self._hot.move_to_end(key)
            return arrays
        n = self._arity[key]
        arrays = tuple(np.load(self._path(key, i), allow_pickle=False) for i in range(n))
        self.loads += 1
        self._hot[key] = arrays
        self._trim()
        return arrays

    def drop(self, key: Hashable) -> None:
        """Forget ``key`` (its files too)."""
        n = self._arity.pop(key, 0)
        self._hot.pop(key, None)
        if self.directory is not None:
            for i in range(n):
                self._path(key, i).unlink(missing_ok=True)

    def clear(self) -> None:
        """Forget every key, and remove the directory."""
        self._hot.clear()
        self._arity.clear()
        if self.directory is not None:
            shutil.rmtree(self.directory, ignore_errors=True)

    def _trim(self) -> None:
        if self.directory is None:
            return
        while len(self._hot) > self.capacity:
            self._hot.popitem(last=False)
