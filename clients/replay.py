"""Replay a recorded drive into the service: ``randt replay`` is a thin shell over :func:`replay`.

Sources are those of :func:`randt.core.datasets.open_scans` (a KITTI sequence folder, a folder of
scan files, a ROS bag's PointCloud2 topic). ``rate_hz > 0`` sends at that rate, as the sensor
produced them (the service may drop scans it cannot keep up with); ``rate_hz == 0`` is flow
control, ``window`` scans in flight, so every scan is matched. A scan the service refuses with
``retry_after_s`` (admission: no room for the session yet) is sent again after that pause, the
replay held meanwhile (recorded data can wait; a live sensor could not). Stamps are the replay's start time
plus each scan's recorded time; with ``loop=True`` each pass is a new session ``<session>.<pass>``
(the matcher would see a jump back to the start otherwise). Options and outputs:
docs/clients.md, "Replaying a recorded drive".
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from randt.clients.publisher import PublisherSettings, PublisherStats, VehiclePublisher, default_session_id
from randt.core.datasets import Scans, open_scans
from randt.core.errors import BadMessageError
from randt.core.io import PointCloud
from randt.wire.messages import ErrorMessage, PoseMessage

__all__ = ["ReplayResult", "replay", "sequence_rate_hz"]

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 10.0


@dataclass
class ReplayResult:
    """What one pass of a replay produced.

    Attributes
    ----------
    vehicle, session:
        Ids the scans were published under.
    n_scans:
        Scans read from the source in this pass.
    stats:
        The publisher's final counters (sent, acknowledged, rejected, dropped, lost...).
    poses:
        The service's poses by ``seq`` (``seq`` = scan index within the pass).
    errors:
        The service's errors by ``seq``.
    skipped:
        Scans not sent because their arrays were invalid (logged), by index.
    wall_s:
        Wall time of the pass, seconds.
    """

    vehicle: str
    session: str
    n_scans: int
    stats: PublisherStats
    poses: dict[int, PoseMessage] = field(default_factory=dict)
    errors: dict[int, ErrorMessage] = field(default_factory=dict)
    skipped: list[int] = field(default_factory=list)
    wall_s: float = 0.0

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """``(seqs, poses)``: (M,) scan indices that got a pose and (M, 4, 4) ``T_map_sensor``."""
        seqs = np.array(sorted(self.poses), dtype=np.int64)
        if seqs.size == 0:
            return seqs, np.zeros((0, 4, 4))
        return seqs, np.stack([self.poses[int(s)].matrix() for s in seqs])

    def stamps_s(self) -> np.ndarray:
        """(M,) stamps of the poses of :meth:`trajectory`, seconds since the Unix epoch."""
        return np.array([self.poses[s].stamp_ns * 1e-9 for s in sorted(self.poses)])


def sequence_rate_hz(seq: Scans) -> float | None:
    """The scan rate implied by the sequence's stamps (median interval), or None without stamps."""
    if seq.stamps_s is None or len(seq.stamps_s) < 2:
        return None
    dt = float(np.median(np.diff(seq.stamps_s)))
    return 1.0 / dt if dt > 0 else None


def _relative_times(seq: Scans, rate_hz: float) -> np.ndarray:
    """(N,) seconds of each scan after the first: from the stamps if they increase, else index/rate."""
    if seq.stamps_s is not None and len(seq.stamps_s) == len(seq) and np.all(np.diff(seq.stamps_s) > 0):
        return np.asarray(seq.stamps_s, dtype=np.float64) - float(seq.stamps_s[0])
    return np.arange(len(seq)) / (rate_hz if rate_hz > 0 else DEFAULT_RATE_HZ)


def _returns_only(cloud: PointCloud) -> PointCloud:
    """The cloud without "no return" points (NaN or Inf coordinates or intensity), which the wire refuses."""
    finite = np.isfinite(cloud.xyz).all(axis=1)
    if cloud.intensity is not None:
        finite &= np.isfinite(cloud.intensity)
    return cloud if finite.all() else cloud.select(finite)


class _Retries:
    """The scans of a pass the service refused with ``retry_after_s``, to send again after it
    (their clouds kept until they are answered otherwise)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._unanswered: dict[int, tuple[PointCloud, int]] = {}
        self._refused: dict[int, float] = {}  # seq -> retry_after_s

    def sent(self, seq: int, cloud: PointCloud, stamp_ns: int) -> None:
        with self._lock:
            self._unanswered[seq] = (cloud, stamp_ns)

    def refused(self, msg: ErrorMessage) -> bool:
        """An error answer: True when it is a refusal to send again (then not a final answer)."""
        assert msg.seq is not None
        with self._lock:
            if msg.retry_after_s is not None and msg.seq in self._unanswered:
                self._refused[msg.seq] = msg.retry_after_s
                return True
            self._unanswered.pop(msg.seq, None)
            return False

    def answered(self, seq: int) -> None:
        with self._lock:
            self._unanswered.pop(seq, None)

    def send_again(self, pub: VehiclePublisher, timeout_s: float, refresh: Callable[[], None]) -> float:
        """Wait each refusal's ``retry_after_s``, send the refused scans again (their own seq),
        until none is refused or ``timeout_s`` has passed; the seconds waited."""
        tic = time.monotonic()
        while time.monotonic() - tic < timeout_s:
            with self._lock:
                batch, self._refused = sorted(self._refused.items()), {}
            if not batch:
                break
            pause = max(after for _, after in batch)
            log.info("%d scans refused for now: sent again in %.1f s", len(batch), pause)
            time.sleep(min(pause, max(0.0, timeout_s - (time.monotonic() - tic))))
            for s, _ in batch:
                with self._lock:
                    cloud, stamp_ns = self._unanswered[s]
                pub.publish(
                    cloud.xyz, stamp_ns, intensity=cloud.intensity, time_offset_s=cloud.time_offset_s, seq=s
                )
            deadline = time.monotonic() + timeout_s
            while not pub.flush(timeout=0.5) and time.monotonic() < deadline:
                refresh()
        return time.monotonic() - tic


def replay(
    path: str | Path,
    vehicle: str,
    *,
    session: str | None = None,
    rate_hz: float | None = None,
    window: int = 1,
    loop: bool = False,
    max_passes: int | None = None,
    start: int = 0,
    end: int | None = None,
    topic: str | None = None,
    settings: PublisherSettings | None = None,
    connect_timeout_s: float = 15.0,
    answer_timeout_s: float = 120.0,
    progress: bool = True,
    on_pose: Callable[[PoseMessage], object] | None = None,
) -> list[ReplayResult]:
    """Publish a recorded sequence as ``vehicle`` (module docstring) and collect the answers.

    Parameters
    ----------
    path:
        KITTI sequence folder, folder of scan files, or ROS bag.
    vehicle:
        Vehicle id on the wire.
    session:
        Session id of the first pass (default: the UTC time, ``20260501-142233``).
    rate_hz:
        Scans per second; ``None`` = the sequence's own rate (10 Hz without stamps); ``0`` = flow
        control with ``window`` scans in flight.
    window:
        With ``rate_hz == 0``: most scans queued or unanswered at once (>= 1).
    loop, max_passes:
        Replay again and again (each pass a new session) until interrupted, or ``max_passes``.
    start, end:
        Scan index range of the source, as ``randt map``.
    settings:
        How to reach the service (default: ``PublisherSettings()``, i.e. ``RANDT_VEHICLE_*``).
    connect_timeout_s:
        How long to wait for a service to subscribe before the first scan; ConnectionError after.
    answer_timeout_s:
        How long to wait for the last answers of a pass (and for each answer under flow control).
    progress:
        Show a tqdm bar on stderr: scans sent, acknowledged (pose), rejected (error), lost.
    on_pose:
        Called with every pose (from the publisher's dispatcher thread).

    Returns
    -------
    list[ReplayResult]
        One per pass.

    Raises
    ------
    NotFoundError, FormatError
        The source folder is missing or holds no scans.
    ConnectionError
        No service subscribed to ``randt/fleet/<vehicle>/scan`` within ``connect_timeout_s``.
    """
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    seq = open_scans(path, topic=topic, start=start, end=end)
    recorded_hz = sequence_rate_hz(seq)
    rate = (recorded_hz or DEFAULT_RATE_HZ) if rate_hz is None else float(rate_hz)
    if rate < 0:
        raise ValueError(f"rate must be >= 0 Hz, got {rate}")
    stamp_t = _relative_times(seq, rate)  # the recorded times: they become the stamps
    send_t = stamp_t * (recorded_hz / rate) if (rate > 0 and recorded_hz) else stamp_t  # the pacing
    base_session = session or default_session_id()
    settings = settings or PublisherSettings()
    results: list[ReplayResult] = []
    n_pass = 0
    while True:
        sess = base_session if n_pass == 0 else f"{base_session}.{n_pass}"
        results.append(
            _one_pass(
                seq,
                stamp_t,
                send_t,
                vehicle=vehicle,
                session=sess,
                rate=rate,
                window=window,
                settings=settings,
                connect_timeout_s=connect_timeout_s,
                answer_timeout_s=answer_timeout_s,
                progress=progress,
                on_pose=on_pose,
                n_pass=n_pass,
            )
        )
        n_pass += 1
        if not loop or (max_passes is not None and n_pass >= max_passes):
            return results


def _one_pass(
    seq: Scans,
    stamp_t: np.ndarray,
    send_t: np.ndarray,
    *,
    vehicle: str,
    session: str,
    rate: float,
    window: int,
    settings: PublisherSettings,
    connect_timeout_s: float,
    answer_timeout_s: float,
    progress: bool,
    on_pose: Callable[[PoseMessage], object] | None,
    n_pass: int,
) -> ReplayResult:
    """Publish the sequence once as ``vehicle/session``; the arguments are :func:`replay`'s."""
    from tqdm import tqdm

    result = ReplayResult(vehicle, session, len(seq), PublisherStats())

    def pose_cb(msg: PoseMessage) -> None:
        retries.answered(msg.seq)
        result.poses[msg.seq] = msg
        if on_pose is not None:
            on_pose(msg)

    def error_cb(msg: ErrorMessage) -> None:
        if msg.seq is not None and not retries.refused(msg):
            result.errors[msg.seq] = msg

    retries = _Retries()
    tic = time.monotonic()
    pub = VehiclePublisher(
        vehicle,
        session,
        settings=settings,
        answer_timeout_s=max(answer_timeout_s, settings.answer_timeout_s),
        on_pose=pose_cb,
        on_error=error_cb,
    )
    bar = tqdm(
        total=len(seq),
        unit="scan",
        desc=f"{vehicle}/{session}",
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
    )

    def refresh() -> None:
        s = pub.stats()
        bar.set_postfix(
            sent=s.sent, ack=s.acknowledged, rejected=s.rejected, dropped=s.dropped, lost=s.lost, refresh=True
        )

    try:
        if not pub.wait_connected(connect_timeout_s):
            raise ConnectionError(
                f"no service subscribed to {pub.scan_key} within {connect_timeout_s:g} s "
                f"(Zenoh {settings.mode}, connect {list(settings.connect)}): is `randt serve` running?"
            )
        t0_wall = time.monotonic()
        stamp0_ns = time.time_ns()
        for i, recorded in enumerate(seq):  # one pass: a bag is opened once, not per sweep
            if rate > 0:
                delay = t0_wall + send_t[i] - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            cloud = _returns_only(recorded)
            stamp_ns = stamp0_ns + round(stamp_t[i] * 1e9)
            try:
                pub.publish(cloud.xyz, stamp_ns, intensity=cloud.intensity, time_offset_s=cloud.time_offset_s)
                retries.sent(i, cloud, stamp_ns)
            except BadMessageError as exc:
                log.warning("%s: scan %d not sent: %s", seq.label(i), i, exc)
                result.skipped.append(i)  # its seq stays unused: seq == scan index throughout
            bar.update()
            if rate == 0:
                deadline = time.monotonic() + answer_timeout_s
                while not pub.wait_pending(window - 1, timeout=0.5) and time.monotonic() < deadline:
                    refresh()
            t0_wall += retries.send_again(pub, answer_timeout_s, refresh)  # (the pacing waits too)
            refresh()
        deadline = time.monotonic() + answer_timeout_s
        while not pub.flush(timeout=0.5) and time.monotonic() < deadline:
            refresh()
        retries.send_again(pub, answer_timeout_s, refresh)
        refresh()
    finally:
        bar.close()
        result.stats = pub.close(timeout=0.5)
        result.wall_s = time.monotonic() - tic
    log.info("pass %d of %s done: %s", n_pass, seq.root, result.stats)
    return result
