"""A session's snapshot files: the commit (``matcher.npz``: the matcher state, the record and the
poses the commit holds itself) and its views for people and other tools (``trajectory.tum``,
``session.json``), read, checked and written.

The pose log is :mod:`randt.service.pose_log`'s; the order of the writes of a snapshot, and why, is
:mod:`randt.service.store`'s module docstring (Crash safety).
"""

from __future__ import annotations

import io
import logging
import re
import zipfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError, RandtError
from randt.core.io import atomic_write_bytes, read_tum, write_tum
from randt.core.io.atomic import atomic_open
from randt.service.pose_log import Poses
from randt.service.session_record import ResumeSweep, SessionRecord

__all__ = [
    "KEY_FIRST",
    "KEY_POSES",
    "KEY_RECORD",
    "KEY_STAMPS",
    "MATCHER_FILENAME",
    "RESUME_FILENAME",
    "SESSION_FILENAME",
    "TRAJECTORY_FILENAME",
    "checked_state",
    "checked_trajectory",
    "read_commit",
    "read_record",
    "read_resume_sweep",
    "record_json",
    "repair_views",
    "tum_rows",
    "write_commit",
    "write_resume_sweep",
    "write_trajectory",
]

logger = logging.getLogger(__name__)

SESSION_FILENAME = "session.json"
TRAJECTORY_FILENAME = "trajectory.tum"
MATCHER_FILENAME = "matcher.npz"
RESUME_FILENAME = "resume.npz"

# Keys of matcher.npz that belong to the store, not to the matcher state.
_RESERVED_PREFIX = "_store_"
KEY_RECORD = "_store_record"
KEY_STAMPS = "_store_stamps"
KEY_POSES = "_store_poses"
KEY_FIRST = "_store_first"  # index of the commit's own first pose (absent: 0, the whole trajectory)
_STATE_KEY_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
# Views (trajectory.tum) agree with the commit record within this (TUM rounds stamps to 1 ns).
_VIEW_TOLERANCE = 1e-6
_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])
# What np.load / zipfile raise on a damaged archive.
_NPZ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile)


def record_json(record: SessionRecord) -> bytes:
    return (record.model_dump_json(indent=2) + "\n").encode("utf-8")


def write_trajectory(path: Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """``write_tum``, or no file at all for an empty trajectory (a TUM file needs a row)."""
    if stamps.size:
        write_tum(path, stamps, poses)
    elif path.exists():
        try:
            path.unlink()
        except OSError as exc:
            raise FormatError(f"cannot remove {path}: {exc}") from exc


def checked_trajectory(poses: np.ndarray, stamps: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) and (N,) float64 copies, finite, homogeneous (N may be 0)."""
    poses = np.array(poses, dtype=np.float64)
    stamps = np.array(stamps, dtype=np.float64)
    if poses.size == 0 and poses.ndim < 3:
        poses = poses.reshape(0, 4, 4)  # np.array([]) for "no poses yet"
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InvalidCloudError(f"{what}: poses must be (N, 4, 4), got {poses.shape}")
    if stamps.shape != (poses.shape[0],):
        raise InvalidCloudError(
            f"{what}: stamps must be ({poses.shape[0]},) to match poses, got {stamps.shape}"
        )
    if not (np.isfinite(poses).all() and np.isfinite(stamps).all()):
        raise InvalidCloudError(f"{what}: poses and stamps must be finite")
    if poses.size and np.abs(poses[:, 3, :] - _BOTTOM_ROW).max() > 1e-9:
        raise InvalidCloudError(f"{what}: poses are not homogeneous (bottom row != [0 0 0 1])")
    return poses, stamps


def checked_state(matcher_state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The matcher state as arrays that ``np.load(allow_pickle=False)`` can read back."""
    arrays: dict[str, np.ndarray] = {}
    for key, value in matcher_state.items():
        if not isinstance(key, str) or not _STATE_KEY_RE.fullmatch(key) or key.startswith(_RESERVED_PREFIX):
            raise FormatError(
                f"matcher state key {key!r} is not usable: keys are names from A-Z a-z 0-9 _ . - and "
                f"must not start with {_RESERVED_PREFIX!r}"
            )
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise FormatError(f"matcher state {key!r} is an object array; only plain arrays can be saved")
        arrays[key] = array
    return arrays


def read_record(path: Path, vehicle: str, session: str) -> SessionRecord:
    """Only the commit record of ``matcher.npz`` (the archive's other members are not read)."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            text = str(npz[KEY_RECORD][()])
    except FileNotFoundError as exc:
        raise NotFoundError(f"session {vehicle}/{session} does not exist") from exc
    except _NPZ_ERRORS as exc:
        raise FormatError(f"{path}: cannot read the session's commit: {exc}") from exc
    return _parse_record(text, path, vehicle, session)


def _parse_record(text: str, path: Path, vehicle: str, session: str) -> SessionRecord:
    try:
        record = SessionRecord.model_validate_json(text)
    except ValueError as exc:
        raise FormatError(f"{path}: invalid session record: {exc}") from exc
    if (record.vehicle, record.session) != (vehicle, session):
        raise FormatError(f"{path}: holds session {record.vehicle}/{record.session}, not {vehicle}/{session}")
    return record


def read_commit(
    path: Path, vehicle: str, session: str, *, state: bool = True
) -> tuple[SessionRecord, dict[str, np.ndarray], Poses]:
    """``matcher.npz``, checked: its record, the matcher state (unless ``state`` is false: then
    ``{}``, and the state's arrays are not read) and the commit's own poses."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files if state or key.startswith(_RESERVED_PREFIX)}
    except FileNotFoundError as exc:
        raise NotFoundError(f"session {vehicle}/{session} does not exist") from exc
    except _NPZ_ERRORS as exc:
        raise FormatError(f"{path}: cannot read the session's commit: {exc}") from exc
    missing = [k for k in (KEY_RECORD, KEY_STAMPS, KEY_POSES) if k not in arrays]
    if missing:
        raise FormatError(f"{path}: not a session commit (missing {', '.join(missing)})")
    record = _parse_record(str(arrays.pop(KEY_RECORD)[()]), path, vehicle, session)
    first_array = arrays.pop(KEY_FIRST, None)
    try:
        first = 0 if first_array is None else int(first_array)
        poses, stamps = checked_trajectory(arrays.pop(KEY_POSES), arrays.pop(KEY_STAMPS), str(path))
    except (InvalidCloudError, ValueError, TypeError) as exc:
        raise FormatError(f"{path}: invalid trajectory: {exc}") from exc
    if first < 0 or first + poses.shape[0] != record.n_scans:
        raise FormatError(
            f"{path}: record says {record.n_scans} scans, its trajectory has poses {first}.."
            f"{first + poses.shape[0] - 1}"
        )
    matcher_state = {k: v for k, v in arrays.items() if not k.startswith(_RESERVED_PREFIX)}
    return record, matcher_state, Poses.given(first, stamps, poses)


def write_commit(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``matcher.npz``, atomically (written straight into the temporary file)."""
    try:
        with atomic_open(path, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]  # mypy binds **arrays to allow_pickle: bool too
    except OSError as exc:
        raise FormatError(f"cannot write {path}: {exc}") from exc


def tum_rows(stamps: np.ndarray, poses: np.ndarray) -> str:
    """Rows of a TUM trajectory as :func:`randt.core.io.write_tum` writes them (``%.9f`` stamps, 17
    significant digits, canonical quaternions), to append to one."""
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat(canonical=True)  # (x, y, z, w)
    buffer = io.StringIO()
    np.savetxt(buffer, np.column_stack([stamps, poses[:, :3, 3], quats]), fmt=["%.9f"] + ["%.17g"] * 7)
    return buffer.getvalue()


def repair_views(directory: Path, record: SessionRecord, trajectory: Poses) -> None:
    """Rewrite ``session.json`` / ``trajectory.tum`` where they disagree with the commit
    (``record``, and ``trajectory``: the poses it covers)."""
    name = f"{record.vehicle}/{record.session}"
    json_path = directory / SESSION_FILENAME
    try:
        current: SessionRecord | None = SessionRecord.model_validate_json(json_path.read_bytes())
    except (OSError, ValueError) as exc:
        logger.warning("session %s: %s unreadable (%s)", name, SESSION_FILENAME, exc)
        current = None
    if current != record:
        logger.warning("session %s: rewriting %s from %s", name, SESSION_FILENAME, MATCHER_FILENAME)
        atomic_write_bytes(json_path, record_json(record))

    tum_path = directory / TRAJECTORY_FILENAME
    if len(trajectory) == 0:
        agrees = not tum_path.exists()
    else:
        try:
            stamps, poses = read_tum(tum_path)
            agrees = (
                stamps.shape == trajectory.stamps.shape
                and np.allclose(stamps, trajectory.stamps, rtol=0.0, atol=_VIEW_TOLERANCE)
                and np.allclose(poses, trajectory.poses, rtol=0.0, atol=_VIEW_TOLERANCE)
            )
        except RandtError as exc:
            logger.warning("session %s: %s unreadable (%s)", name, TRAJECTORY_FILENAME, exc)
            agrees = False
    if not agrees:
        logger.warning("session %s: rewriting %s from the stored trajectory", name, TRAJECTORY_FILENAME)
        write_trajectory(tum_path, trajectory.stamps, trajectory.poses)


def write_resume_sweep(directory: Path, sweep: ResumeSweep) -> None:
    """Replace ``directory/resume.npz`` by ``sweep``, atomically (:meth:`SessionStore.save_resume_sweep
    <randt.service.session_store.SessionStore.save_resume_sweep>`).

    Raises
    ------
    FormatError
        It could not be written.
    """
    try:
        with atomic_open(directory / RESUME_FILENAME, "wb") as fh:
            np.savez(
                fh,
                pose_index=np.array(sweep.pose_index, dtype=np.int64),
                pose=np.asarray(sweep.pose, dtype=np.float64).reshape(4, 4),
                points=np.asarray(sweep.points, dtype=np.float32).reshape(-1, 3),
            )
    except OSError as exc:
        raise FormatError(f"cannot write {directory / RESUME_FILENAME}: {exc}") from exc


def read_resume_sweep(path: Path, vehicle: str, session: str) -> ResumeSweep | None:
    """The sweep in ``path`` (``resume.npz``); None when there is none or it cannot be read (with a
    warning)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            pose, points = np.array(z["pose"], dtype=np.float64), np.array(z["points"])
            sweep = ResumeSweep(int(z["pose_index"]), pose, points)
        if sweep.pose.shape != (4, 4) or sweep.points.ndim != 2 or sweep.points.shape[1] != 3:
            raise ValueError(f"pose {sweep.pose.shape}, points {sweep.points.shape}")
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        logger.warning("session %s/%s: %s unreadable, not used: %s", vehicle, session, path, exc)
        return None
    return sweep
