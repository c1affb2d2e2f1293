"""The stand-in executor of bench/main_process.py: the service's matchers replaced by prepared
answers handed over at once, so that the service process's own cost shows alone.

Kept apart from bench/main_process.py so that the service process imports it without the
benchmarks' ``common`` (which sets one-thread BLAS variables the service sets itself).
"""

from __future__ import annotations

import pickle
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from randt.service.matchers import TRAJECTORY_LENGTH_KEY, Registered, with_trajectory
from randt.wire.messages import WireLimits, peek_seq


class StandInMatcher:
    """A session's matcher that answers each sweep at once with its prepared answer (by the
    sweep's seq, read from the payload's header)."""

    def __init__(self, owner: StandIn, answers: dict[str, Any]) -> None:
        self._owner, self._registered, self._state = owner, answers["registered"], answers["state"]
        self.poses: list[np.ndarray] = []

    def register_payload(
        self,
        payload: bytes,
        *,
        limits: WireLimits | None = None,
        behind: bool = False,
        keyframe_voxel_m: float | None = None,
        frame: Any = None,
    ) -> Registered:
        registered: Registered = self._registered[peek_seq(payload)]
        if keyframe_voxel_m is None and registered.keyframe_xyz is not None:
            registered = replace(registered, keyframe_xyz=None, keyframe_index=None, keyframe_intensity=None)
        elif keyframe_voxel_m is not None and registered.keyframe_xyz is None:
            self._owner.missing_keyframes += 1
        if registered.result.index != len(self.poses):  # sweeps were dropped: number on, as a matcher does
            registered = replace(registered, result=replace(registered.result, index=len(self.poses)))
        self.poses.append(registered.result.T_world_sensor)
        return registered

    def update_model(self) -> float:
        return 0.0

    def state_dict(self) -> dict[str, np.ndarray]:
        return with_trajectory(self.snapshot_state(), np.array(self.poses).reshape(-1, 4, 4))

    def snapshot_state(self) -> dict[str, np.ndarray]:
        """The matcher's state after the vehicle's last sweep, for as many poses as answered so far
        (the store checks the count against its pose log)."""
        return {**self._state, TRAJECTORY_LENGTH_KEY: np.array(len(self.poses), dtype=np.int64)}

    def close(self) -> None:
        pass


class StandIn:
    """The stand-in executor (:class:`randt.service.matchers.MatcherExecutor`): every session's matcher
    is a :class:`StandInMatcher` over its vehicle's prepared answers."""

    ready = True

    def __init__(self, answers_path: Path) -> None:
        with open(answers_path, "rb") as f:
            self._answers: dict[str, Any] = pickle.load(f)
        self.missing_keyframes = 0

    def wait_ready(self, timeout: float | None = None) -> bool:
        return True

    def open(self, key: tuple[str, str], state: Any = None, grid: Any = None, *args: Any) -> StandInMatcher:
        vehicle = key[0] if key[0] in self._answers else key[0].rsplit("-r", 1)[0]  # (a replay)
        return StandInMatcher(self, self._answers[vehicle])

    def close(self) -> None:
        pass
