"""What the store keeps about a driving session (:class:`SessionRecord`, ``session.json``) and
what it hands back: a loaded session and a resume sweep.

Types only, so that modules that read records (the API's views, the session table) need not load
the store.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Literal, NamedTuple

import numpy as np
from pydantic import (
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from randt.wire.ids import validate_id

__all__ = ["LoadedSession", "ResumeSweep", "SessionFrame", "SessionRecord", "SessionState", "utcnow"]

SessionState = Literal["active", "closed", "expired"]
SessionFrame = Literal["map", "session"]


def utcnow() -> datetime:
    return datetime.now(UTC)


class SessionRecord(BaseModel):
    """What the store keeps about one driving session (``session.json``).

    Attributes
    ----------
    vehicle, session:
        Names (ids, :mod:`randt.wire.ids`); the session lives in ``sessions/<vehicle>/<session>/``.
    map:
        The map the session's scans go into, or ``None``.
    state:
        ``"active"`` (scans may still arrive), ``"closed"`` (ended by the vehicle) or
        ``"expired"`` (timed out by the service).
    created, updated:
        Timezone-aware times (ISO 8601 in the file). :meth:`Store.save_session` keeps ``created``
        from the session's first save and sets ``updated`` to the time of the save.
    last_seq:
        Sequence number of the last scan processed; -1 before any.
    n_scans:
        Scans in the trajectory (one pose each, fallbacks included).
    n_fallbacks:
        Scans whose pose fell back to the prediction or a prior (<= ``n_scans``).
    frame:
        ``"map"`` if the poses are in the map's frame, ``"session"`` if in the session's own
        (its first scan's) frame.
    localize_only:
        The session only localizes on the shared map (its first scan asked), never adds to it.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    vehicle: str
    session: str
    map: str | None = None
    state: SessionState = "active"
    created: AwareDatetime = Field(default_factory=utcnow)
    updated: AwareDatetime = Field(default_factory=utcnow)
    last_seq: int = Field(default=-1, ge=-1)
    n_scans: int = Field(default=0, ge=0)
    n_fallbacks: int = Field(default=0, ge=0)
    frame: SessionFrame = "session"
    localize_only: bool = False

    @property
    def key(self) -> tuple[str, str]:
        """``(vehicle, session)``."""
        return self.vehicle, self.session

    @field_validator("vehicle", "session", "map")
    @classmethod
    def _safe_name(cls, value: str | None, info: ValidationInfo) -> str | None:
        assert info.field_name is not None  # a field validator's, always set
        return None if value is None else validate_id(value, info.field_name)

    @model_validator(mode="after")
    def _fallbacks_within_scans(self) -> SessionRecord:
        if self.n_fallbacks > self.n_scans:
            raise ValueError(f"n_fallbacks ({self.n_fallbacks}) exceeds n_scans ({self.n_scans})")
        return self


class ResumeSweep(NamedTuple):
    """A recent sweep of a session (:meth:`Store.save_resume_sweep`): its pose's index in the
    trajectory, that pose (4, 4) and its points (N, 3) float32 in the sensor frame."""

    pose_index: int
    pose: np.ndarray
    points: np.ndarray


class LoadedSession(NamedTuple):
    """A session as :meth:`Store.load_session` restores it.

    Attributes
    ----------
    record:
        The session's record.
    stamps:
        (N,) float64 scan times, seconds.
    poses:
        (N, 4, 4) float64 ``T_frame_sensor`` (``record.frame`` names the frame).
    state:
        The matcher state as saved (name -> array), for
        :meth:`IncrementalMatcher.load_state_dict <randt.core.odometry.IncrementalMatcher.load_state_dict>`.
    """

    record: SessionRecord
    stamps: np.ndarray
    poses: np.ndarray
    state: dict[str, np.ndarray]
