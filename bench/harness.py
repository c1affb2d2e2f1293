"""Plumbing of the reliability benchmarks (corpus runner, faults, soak): a live service, a listener
of its answers, a well-behaved vehicle, store hashes and the latency bound.

Everything runs on 127.0.0.1 with explicit endpoints and multicast scouting off
(:func:`randt.wire.zenoh_config.zenoh_config`), and every wait has a timeout.
"""

from __future__ import annotations

import hashlib
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: The latency bound of other sessions during a hostile case or a fault, from the well-behaved
#: vehicle's baseline p99 (seconds): p99 <= max(2 x baseline p99, baseline p99 + 1 s).
BOUND_FACTOR = 2.0
BOUND_SLACK_S = 1.0


def latency_bound(baseline_p99_s: float) -> float:
    """The p99 (s) another session may reach during a case: ``max(2 p99, p99 + 1 s)``."""
    return max(BOUND_FACTOR * baseline_p99_s, baseline_p99_s + BOUND_SLACK_S)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def p99(values: Iterable[float]) -> float:
    arr = np.asarray(list(values), dtype=float)
    # "higher": no interpolation, so an unanswered scan (inf) makes the p99 inf, never nan
    return float(np.percentile(arr, 99, method="higher")) if arr.size else float("nan")


# --------------------------------------------------------------------------------------------
# store hashes
# --------------------------------------------------------------------------------------------


def hash_store(data_dir: Path, exclude: Callable[[str], bool] = lambda rel: False) -> dict[str, str]:
    """sha256 of every file under ``data_dir/maps`` and ``data_dir/sessions`` (relative path -> hex).

    Only the store's content is hashed: ``maps/`` and ``sessions/``. The lock file and whatever else a
    service keeps at the top of its data directory (counters) may change legitimately; ``exclude``
    drops the paths (relative, ``/``-separated) a check allows to change.
    """
    out: dict[str, str] = {}
    for top in ("maps", "sessions"):
        root = data_dir / top
        if not root.is_dir():
            continue
        for path in sorted(root.rglob("*")):
            if not path.is_file():
                continue
            rel = path.relative_to(data_dir).as_posix()
            if exclude(rel):
                continue
            try:
                out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
            except FileNotFoundError:  # replaced by an atomic rename while we read: skip it
                continue
    return out


def diff_hashes(before: dict[str, str], after: dict[str, str]) -> list[str]:
    """Paths added, removed or changed."""
    keys = set(before) | set(after)
    return sorted(k for k in keys if before.get(k) != after.get(k))


# --------------------------------------------------------------------------------------------
# answers
# --------------------------------------------------------------------------------------------


@dataclass
class Answer:
    """A pose or an error received from the service."""

    kind: str  # "pose" or "error"
    vehicle: str
    session: str
    seq: int | None
    code: str | None
    t: float  # time.monotonic() at arrival
    pose: list[float] | None = None
    map: str | None = None
    stamp_ns: int | None = None


@dataclass
class TileSeen:
    map: str
    tile: str
    version: int
    t: float


class Listener:
    """Subscribes to every pose, error and tile update (a Zenoh session of its own)."""

    def __init__(self, connect: tuple[str, ...], mode: str = "peer") -> None:
        import zenoh

        from randt.wire.keys import ALL_ERRORS, ALL_POSES
        from randt.wire.zenoh_config import zenoh_config

        self.lock = threading.Lock()
        self.answers: list[Answer] = []
        self.tiles: list[TileSeen] = []
        self.session = zenoh.open(zenoh_config(mode, connect=connect))
        self._subs = [
            self.session.declare_subscriber(ALL_POSES, self._on_pose),
            self.session.declare_subscriber(ALL_ERRORS, self._on_error),
            self.session.declare_subscriber("randt/map/*/tile/*", self._on_tile),
        ]

    def _on_pose(self, sample: Any) -> None:
        from randt.wire.messages import decode_pose

        t = time.monotonic()
        try:
            m = decode_pose(sample.payload.to_bytes())
        except Exception:
            log.exception("undecodable pose")
            return
        with self.lock:
            self.answers.append(
                Answer("pose", m.vehicle, m.session, m.seq, None, t, list(m.pose), m.map, m.stamp_ns)
            )

    def _on_error(self, sample: Any) -> None:
        from randt.wire.messages import decode_error

        t = time.monotonic()
        try:
            m = decode_error(sample.payload.to_bytes())
        except Exception:
            log.exception("undecodable error")
            return
        with self.lock:
            self.answers.append(Answer("error", m.vehicle, m.session, m.seq, m.code, t))

    def _on_tile(self, sample: Any) -> None:
        from randt.wire.messages import decode_tile_update

        t = time.monotonic()
        try:
            m = decode_tile_update(sample.payload.to_bytes())
        except Exception:
            log.exception("undecodable tile update")
            return
        with self.lock:
            self.tiles.append(TileSeen(m.map, m.tile, m.version, t))

    def snapshot(self) -> list[Answer]:
        with self.lock:
            return list(self.answers)

    def of(self, vehicle: str, since: float = 0.0) -> list[Answer]:
        with self.lock:
            return [a for a in self.answers if a.vehicle == vehicle and a.t >= since]

    def wait(self, predicate: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.02)
        return predicate()

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)
        self.session.close()


# --------------------------------------------------------------------------------------------
# a well-behaved vehicle
# --------------------------------------------------------------------------------------------


@dataclass
class Sent:
    vehicle: str
    session: str
    seq: int
    t: float


@dataclass
class GoodVehicle:
    """Publishes scans of a static synthetic room at ``rate_hz`` until stopped, and records each send.

    ``payloads`` (optional) replaces the room: a list of ``(stamp_ns, xyz, prior)`` cycled through.
    """

    connect: tuple[str, ...]
    vehicle: str = "good"
    session: str = "drive"
    rate_hz: float = 5.0
    n_points: int = 3000
    mode: str = "peer"
    sent: list[Sent] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None
    _seq: int = 0

    def start(self) -> GoodVehicle:
        self._thread = threading.Thread(target=self._run, name=f"vehicle-{self.vehicle}", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        import zenoh

        from bench.corpus import room_points
        from randt.wire.keys import scan_key
        from randt.wire.messages import encode, scan_from_arrays
        from randt.wire.zenoh_config import zenoh_config

        xyz = room_points(self.n_points, seed=7).astype(np.float64)
        session = zenoh.open(zenoh_config(self.mode, connect=self.connect))
        pub = session.declare_publisher(
            scan_key(self.vehicle),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        start = time.monotonic()
        k = 0
        try:
            while not self._stop.is_set():
                delay = start + k / self.rate_hz - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                    if self._stop.is_set():
                        break
                seq = self._seq
                payload = encode(
                    scan_from_arrays(
                        self.vehicle, self.session, seq, 1_700_000_000_000_000_000 + seq * 10**8, xyz
                    )
                )
                self.sent.append(Sent(self.vehicle, self.session, seq, time.monotonic()))
                try:
                    pub.put(payload)
                except Exception:
                    log.warning("vehicle %s: put failed", self.vehicle, exc_info=True)
                self._seq += 1
                k += 1
        finally:
            time.sleep(0.5)
            session.close()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(30)


def latencies(
    sent: list[Sent], answers: list[Answer], t0: float, t1: float, *, grace_s: float = 0.0
) -> list[float]:
    """Latency (s) of every scan whose life overlaps ``[t0, t1]``: sent before ``t1`` and answered
    after ``t0``; a scan never answered counts as infinite if it was sent in ``[t0 - 2 s, t1]`` (in
    flight when the window began, or sent during it; an older one was charged to its own window).
    Scans sent in the last ``grace_s`` before now are left out (still in flight)."""
    by_key = {(a.vehicle, a.session, a.seq): a.t for a in answers}
    now = time.monotonic()
    out: list[float] = []
    for s in sent:
        if s.t > t1 or s.t > now - grace_s:
            continue
        t_ans = by_key.get((s.vehicle, s.session, s.seq))
        if t_ans is None:
            if s.t >= t0 - 2.0:
                out.append(float("inf"))
        elif t_ans >= t0:
            out.append(t_ans - s.t)
    return out


# --------------------------------------------------------------------------------------------
# a live service: Zenoh transport and a real uvicorn server
# --------------------------------------------------------------------------------------------


@dataclass
class LiveService:
    url: str
    port: int
    zenoh_endpoint: str
    service: Any  # randt.service.runtime.Service
    data_dir: Path


@contextmanager
def live_service(
    data_dir: Path,
    *,
    zenoh_mode: str = "peer",
    connect: tuple[str, ...] = (),
    warm_timeout: float = 600.0,
    **overrides: Any,
) -> Iterator[LiveService]:
    """``create_app`` with its Zenoh transport (peer listening on a free loopback port, or a client of
    ``connect``) served by uvicorn on a free loopback port; yields when the matchers are warm."""

    from randt.service.app import create_app
    from randt.service.settings import ServiceSettings

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listen = (endpoint,) if zenoh_mode == "peer" else ()
    settings = ServiceSettings(
        data_dir=data_dir,
        zenoh_mode=zenoh_mode,  # type: ignore[arg-type]
        listen=listen,
        connect=connect,
        **overrides,
    )
    app = create_app(settings, with_zenoh=True)
    port = free_port()
    server, thread = start_server(app, port, "uvicorn-bench")
    service = app.state.service
    if not service.sessions.wait_matchers(warm_timeout):
        raise RuntimeError("matcher processes did not warm up")
    try:
        yield LiveService(
            f"http://127.0.0.1:{port}", port, endpoint if listen else connect[0], service, data_dir
        )
    finally:
        stop_server(server, thread)


#: How long a server in a thread may take to start or to stop (drain, save, close) before that is
#: an error. Bounds against a hang only: a caller that goes on after a short join (60 s here
#: before) may restart on a data directory the first service still holds and leaves its processes
#: running, which a suite run beside two CPU burners showed (idle graph and matcher processes of
#: earlier services, then failures).
SERVER_START_S = 300.0
SERVER_STOP_S = 600.0


def start_server(app: Any, port: int, name: str) -> tuple[Any, threading.Thread]:
    """Serve ``app`` with uvicorn on ``127.0.0.1:port`` in a daemon thread called ``name``;
    returns ``(server, thread)`` once it has started (for :func:`stop_server`).

    Raises
    ------
    RuntimeError
        It had not started within :data:`SERVER_START_S`, or its thread ended first.
    """
    import uvicorn

    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, name=name, daemon=True)
    thread.start()
    deadline = time.monotonic() + SERVER_START_S
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    return server, thread


def stop_server(server: Any, thread: threading.Thread) -> None:
    """Ask a uvicorn ``server`` running in ``thread`` to exit and wait until it has (its
    lifespan shutdown stops the service: sessions drained and saved, processes ended).

    Raises
    ------
    RuntimeError
        It was still running after :data:`SERVER_STOP_S`.
    """
    server.should_exit = True
    thread.join(SERVER_STOP_S)
    if thread.is_alive():
        raise RuntimeError(f"the server did not stop within {SERVER_STOP_S:.0f} s")


def http_raw(
    port: int, method: str, target: str, *, timeout: float = 30.0, headers: dict[str, str] | None = None
) -> tuple[int, bytes]:
    """One HTTP/1.1 request sent byte for byte (no normalization of ``..`` or escapes): (status, body)."""
    lines = [f"{method} {target} HTTP/1.1", f"Host: 127.0.0.1:{port}", "Connection: close"]
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
    request = ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(request)
        chunks = []
        while True:
            data = s.recv(65536)
            if not data:
                break
            chunks.append(data)
    raw = b"".join(chunks)
    head, _, body = raw.partition(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1]) if head.startswith(b"HTTP/") else 0
    if b"transfer-encoding: chunked" in head.lower():
        body = _unchunk(body)
    return status, body


def _unchunk(body: bytes) -> bytes:
    out = bytearray()
    while body:
        size_line, _, rest = body.partition(b"\r\n")
        size = int(size_line.split(b";")[0] or b"0", 16)
        if size == 0:
            break
        out += rest[:size]
        body = rest[size + 2 :]
    return bytes(out)


def healthy(port: int) -> bool:
    """``GET /healthz`` answers 200 within 10 s."""
    try:
        status, _ = http_raw(port, "GET", "/healthz", timeout=10.0)
    except OSError:
        return False
    return status == 200
