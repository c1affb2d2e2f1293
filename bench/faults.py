"""Fault injection against a live service: full disk, read-only data directory, the Zenoh router
vanishing and returning, a vehicle flooding at 10x its rate. (kill -9: ``bench/crash.py``.)

Run from the repository root (as root: the disk faults mount in a private mount namespace)::

    python -m bench.faults [--fault full_disk read_only router flood] [--json]

Each fault runs a real service (``create_app`` with its Zenoh transport and uvicorn, everything on
127.0.0.1) with a well-behaved vehicle streaming, injects the fault, lifts it, stops the service
and checks, on the data directory after the stop (a restart's view, read with the store's own
readers):

* ``acked_kept``: every pose a vehicle received is in the store, same stamp and same pose (the
  promise: an answered scan is durable; docs/wire-format.md). Zero acknowledged poses lost;
* ``tiles_intact``: the store opens with no problem reported, every tile file listed by a map's
  metadata exists and reads (``randt.core.io``), and no tile's stored version is below the highest
  version a tile update announced on the wire (``tiles_regressed``);
* ``loud``: while the fault lasted, the service said so (disk faults: an ERROR log line and the
  ``randt_store_errors_total`` counter or error answers; router: the vehicles' scans went
  unanswered and resumed; flood: every flooding scan answered, each one not given a pose
  answered ``dropped``; a service fast enough to pose them all has no excess to announce);
* ``recovered``: after the fault was lifted the well-behaved vehicle got poses again and
  ``/healthz`` answered;
* ``restarted``: a second service starts on the same data directory and answers ``/readyz``;
* ``latency`` (flood): the well-behaved vehicle's p99 during the flood stays within
  ``max(2 x baseline p99, baseline p99 + 1 s)`` (bench/harness.py).

The disk faults run in a child process started with ``unshare -m`` (a private mount namespace,
so the tmpfs and the read-only bind mount vanish with it and nothing leaks to the machine). Under
``CI=true`` a fault that cannot be set up (no ``unshare``, not root) is a failure, never a skip.
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import (
    Answer,
    GoodVehicle,
    Listener,
    TileSeen,
    free_port,
    healthy,
    http_raw,
    latencies,
    latency_bound,
    live_service,
    p99,
)

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
FAULTS = ("full_disk", "read_only", "router", "flood")


@dataclass
class FaultResult:
    name: str
    survived: bool = False
    checks: dict[str, bool] = field(default_factory=dict)
    acked: int = 0
    acked_lost: int = 0
    tiles_checked: int = 0
    tiles_torn: int = 0
    tiles_regressed: int = 0
    detail: str = ""
    seconds: float = 0.0

    def finish(self) -> FaultResult:
        self.survived = bool(self.checks) and all(self.checks.values())
        return self


class SetupError(RuntimeError):
    """The fault could not be set up (no mount namespace, not root...)."""


# --------------------------------------------------------------------------------------------
# the checks after a restart
# --------------------------------------------------------------------------------------------


@dataclass
class StoreCheck:
    acked: int
    lost: list[str]
    tiles_checked: int
    torn: list[str]
    regressed: list[str]


def check_store(data_dir: Path, answers: list[Answer], tiles_seen: list[TileSeen]) -> StoreCheck:
    """Open the store (the service is stopped) and check every acknowledged pose and every tile."""
    from randt.core.io.autoware import AUTOWARE_METADATA_NAME, read_metadata
    from randt.core.io.clouds import read_cloud
    from randt.service.store import Store

    store = Store(data_dir)
    try:
        contents = store.load_all()
        lost: list[str] = []
        poses = [a for a in answers if a.kind == "pose"]
        by_session: dict[tuple[str, str], list[Answer]] = {}
        for a in poses:
            by_session.setdefault((a.vehicle, a.session), []).append(a)
        for key, acked in by_session.items():
            loaded = contents.sessions.get(key)
            if loaded is None:
                lost += [f"{key[0]}/{key[1]}#{a.seq} (no session)" for a in acked]
                continue
            stamps = np.asarray(loaded.stamps, dtype=float)
            stored = np.asarray(loaded.poses, dtype=float).reshape(-1, 4, 4)
            for a in acked:
                assert a.stamp_ns is not None and a.pose is not None
                k = np.flatnonzero(np.abs(stamps - a.stamp_ns * 1e-9) < 1e-5)
                if k.size == 0:
                    lost.append(f"{key[0]}/{key[1]}#{a.seq} (missing)")
                elif not np.allclose(stored[k[0]], np.reshape(a.pose, (4, 4)), atol=1e-6):
                    lost.append(f"{key[0]}/{key[1]}#{a.seq} (different pose)")
        torn = [f"{p.kind} {p.name}: {p.message}" for p in contents.problems]
        checked = 0
        for map_dir in sorted((data_dir / "maps").glob("*")):
            if not (map_dir / AUTOWARE_METADATA_NAME).exists():
                continue
            try:
                _, files = read_metadata(map_dir)
            except Exception as exc:
                torn.append(f"{map_dir.name}: metadata unreadable ({exc})")
                continue
            for name in files:
                checked += 1
                try:
                    read_cloud(map_dir / name)
                except Exception as exc:
                    torn.append(f"{map_dir.name}/{name}: {exc}")
        highest: dict[tuple[str, str], int] = {}
        for t in tiles_seen:
            highest[(t.map, t.tile)] = max(highest.get((t.map, t.tile), 0), t.version)
        regressed = []
        for (map_name, tid), version in sorted(highest.items()):
            grid = contents.maps.get(map_name)
            ix, iy = (int(v) for v in tid.split("_", 1)) if "_" in tid[1:] else (0, 0)
            stored_version = grid.tile(ix, iy).version if grid is not None and tid in grid else 0
            if stored_version < version:
                regressed.append(f"{map_name}/{tid}: served v{version}, stored v{stored_version}")
        return StoreCheck(len(poses), lost, checked, torn, regressed)
    finally:
        store.close()


def _apply(result: FaultResult, check: StoreCheck) -> None:
    result.acked, result.acked_lost = check.acked, len(check.lost)
    result.tiles_checked, result.tiles_torn, result.tiles_regressed = (
        check.tiles_checked,
        len(check.torn),
        len(check.regressed),
    )
    result.checks["acked_kept"] = not check.lost
    result.checks["tiles_intact"] = not check.torn and not check.regressed
    for what, items in (("lost", check.lost), ("torn", check.torn), ("regressed", check.regressed)):
        if items:
            result.detail += f"; {what}: {items[:4]}{' ...' if len(items) > 4 else ''}"


def _restart(data_dir: Path, result: FaultResult, **overrides: Any) -> None:
    """A second service on the same data directory starts and answers /readyz."""
    try:
        with live_service(data_dir, warm_timeout=300, **overrides) as live:
            # (ready once the pose graph has taken its log again, too: seconds after the warm-up)
            deadline = time.monotonic() + 120
            while (status := http_raw(live.port, "GET", "/readyz")[0]) != 200 and time.monotonic() < deadline:
                time.sleep(0.2)
            result.checks["restarted"] = status == 200
            if status != 200:
                result.detail += f"; restart: /readyz {status}"
    except Exception as exc:
        result.checks["restarted"] = False
        result.detail += f"; restart failed: {type(exc).__name__}: {exc}"


class _Errors(logging.Handler):
    """Collects ERROR records of the service (the 'loud' evidence)."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.name}: {record.getMessage()}"[:200])


def _poses_after(listener: Listener, vehicle: str, t: float) -> int:
    return sum(1 for a in listener.of(vehicle, t) if a.kind == "pose")


# --------------------------------------------------------------------------------------------
# disk faults (inside a private mount namespace)
# --------------------------------------------------------------------------------------------


def _mount(*args: str) -> None:
    done = subprocess.run(["mount", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise SetupError(f"mount {' '.join(args)}: {done.stderr.strip()}")


def _fill(path: Path) -> int:
    """Write zeros to ``path`` until the file system is full; returns the bytes written."""
    written = 0
    chunk = b"\x00" * (64 * 1024)
    try:
        fh = open(path, "wb", buffering=0)  # noqa: SIM115 (closed below; the open itself may find the disk full)
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
        return 0
    with fh:
        while True:
            try:
                n = fh.write(chunk)
                written += n or 0
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
                if len(chunk) == 1:
                    break
                chunk = chunk[: len(chunk) // 4] or b"\x00"
        os.fsync(fh.fileno())
    return written


def _disk_fault_inner(kind: str, root: Path) -> FaultResult:
    """Runs inside ``unshare -m``: mounts, streams, injects, lifts, restarts, checks."""
    result = FaultResult(kind)
    t0 = time.monotonic()
    _mount("--make-rprivate", "/")
    data_dir = root / "data"
    data_dir.mkdir(parents=True)
    if kind == "full_disk":
        _mount("-t", "tmpfs", "-o", "size=24m", "tmpfs", str(data_dir))
    errors = _Errors()
    logging.getLogger().addHandler(errors)
    flush_s = 0.3
    answers: list[Answer] = []
    tiles: list[TileSeen] = []
    try:
        with live_service(data_dir, flush_interval_s=flush_s) as live:
            listener = Listener((live.zenoh_endpoint,))
            good = GoodVehicle((live.zenoh_endpoint,), rate_hz=5.0).start()
            ballast = data_dir / "ballast"

            def inject() -> None:
                if kind == "full_disk":
                    _fill(ballast)
                else:
                    # A read-only bind mount stacked on the data directory: the service holds files
                    # open for writing (its lock), so the directory's own mount cannot be remounted
                    # read-only (EBUSY); every path the service opens from now on is read-only.
                    # Made read-only aside and moved into place in one step: remounting it where
                    # the service writes raced with the service's own opens (EBUSY, once, in CI).
                    staging = root / f"ro-staging-{time.monotonic_ns()}"
                    staging.mkdir()
                    _mount("--bind", str(data_dir), str(staging))
                    _mount("-o", "remount,bind,ro", str(staging))
                    _mount("--move", str(staging), str(data_dir))

            def lift() -> None:
                if kind == "full_disk":
                    ballast.unlink()
                else:
                    done = subprocess.run(["umount", "-l", str(data_dir)], capture_output=True, text=True)
                    if done.returncode != 0:
                        raise SetupError(f"umount {data_dir}: {done.stderr.strip()}")

            def store_errors() -> float:
                value = live.service.metrics.registry.get_sample_value("randt_store_errors_total")
                return value or 0.0

            def loud_since(t: float, n_err: int) -> bool:  # ERROR lines, and the store or vehicle told
                codes = {a.code for a in listener.of(good.vehicle, t) if a.kind == "error" and a.code}
                return len(errors.lines) > n_err and (store_errors() > 0 or bool(codes))

            def told(t: float) -> bool:  # the vehicle answered an error since t
                return any(a.kind == "error" for a in listener.of(good.vehicle, t))

            try:
                # conditions, not clocks: each stage waits for what it checks (a busy machine only
                # makes it slower)
                listener.wait(
                    lambda: _poses_after(listener, good.vehicle, 0.0) >= 5 and bool(listener.tiles), 60.0
                )
                ok_before = _poses_after(listener, good.vehicle, 0.0)
                n_err0 = len(errors.lines)
                if kind == "full_disk":
                    used = shutil.disk_usage(data_dir).used / 2**20
                    result.detail += f"a 24 MiB tmpfs, {used:.1f} MiB used before the fault; "
                inject()
                t_fault = time.monotonic()
                listener.wait(lambda: told(t_fault) and loud_since(t_fault, n_err0), 30.0)
                during = [a for a in listener.of(good.vehicle, t_fault)]
                err_codes = sorted({a.code for a in during if a.kind == "error" and a.code})
                ready_status, _ = http_raw(live.port, "GET", "/readyz")
                loud_lines = errors.lines[n_err0:]
                result.checks["loud"] = loud_since(t_fault, n_err0)
                result.detail += (
                    f"before: {ok_before} poses; during ({kind}): "
                    f"{sum(a.kind == 'pose' for a in during)} poses, "
                    f"error codes {err_codes}, store errors {store_errors():g}, /readyz {ready_status}, "
                    f"{len(loud_lines)} ERROR lines (first: {loud_lines[0] if loud_lines else '-'})"
                )
                lift()
                t_lift = time.monotonic()
                listener.wait(lambda: _poses_after(listener, good.vehicle, t_lift + 1.0) > 0, 60.0)
                result.checks["recovered"] = _poses_after(
                    listener, good.vehicle, t_lift + 1.0
                ) > 0 and healthy(live.port)
                # The fault again, and the service stops while it lasts: every pose a vehicle
                # received must still be in the store (durable before acknowledged).
                n_err1 = len(errors.lines)
                inject()
                t_second = time.monotonic()
                listener.wait(lambda: len(errors.lines) > n_err1, 30.0)
                result.detail += (
                    f"; second fault: {_poses_after(listener, good.vehicle, t_second)} poses, "
                    "then the service stopped during it"
                )
            finally:
                good.stop()
                time.sleep(1.0)
                answers = listener.snapshot()
                tiles = list(listener.tiles)
                listener.close()
        ballast = data_dir / "ballast"
    finally:
        logging.getLogger().removeHandler(errors)
    if kind == "full_disk":
        ballast.unlink(missing_ok=True)
    else:
        subprocess.run(["umount", "-l", str(data_dir)], capture_output=True, check=True)
    _apply(result, check_store(data_dir, answers, tiles))
    _restart(data_dir, result)
    if kind == "read_only":
        # and a service started on a read-only data directory refuses to start, naming the problem
        ro_dir = root / "read-only"
        (ro_dir / "maps").mkdir(parents=True)
        _mount("--bind", str(ro_dir), str(ro_dir))
        _mount("-o", "remount,bind,ro", str(ro_dir))
        from randt.service.runtime import Service
        from randt.service.settings import ServiceSettings

        svc = Service(ServiceSettings(data_dir=ro_dir, listen=(f"tcp/127.0.0.1:{free_port()}",)))
        try:
            svc.start()
        except Exception as exc:
            result.checks["refuses_read_only_start"] = "read-only" in str(exc).lower()
            result.detail += f"; start on a read-only directory: {type(exc).__name__}: {str(exc)[:160]}"
        else:
            result.checks["refuses_read_only_start"] = False
            result.detail += "; a service started on a read-only directory without an error"
        finally:
            svc.stop()
    result.seconds = time.monotonic() - t0
    return result.finish()


def run_disk_fault(kind: str) -> FaultResult:
    """Run a disk fault in a child process in a private mount namespace (``unshare -m``)."""
    t0 = time.monotonic()
    if shutil.which("unshare") is None or os.geteuid() != 0:
        raise SetupError("the disk faults need root and unshare(1) (a private mount namespace)")
    with tempfile.TemporaryDirectory(prefix=f"randt-{kind}-") as tmp:
        out = Path(tmp) / "result.json"
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        done = subprocess.run(
            [
                "unshare",
                "-m",
                sys.executable,
                "-m",
                "bench.faults",
                "--inner",
                kind,
                "--root",
                tmp,
                "--out",
                str(out),
            ],
            capture_output=True,
            text=True,
            timeout=900,
            cwd=REPO,
            env=env,
        )
        if not out.exists():
            tail = (done.stderr or "").strip().splitlines()[-5:]
            if any("SetupError" in line for line in tail):
                raise SetupError("; ".join(tail))
            return FaultResult(
                kind,
                False,
                {"ran": False},
                detail=f"child exited {done.returncode}: {tail}",
                seconds=time.monotonic() - t0,
            )
        return FaultResult(**json.loads(out.read_text()))


# --------------------------------------------------------------------------------------------
# the router vanishing and returning
# --------------------------------------------------------------------------------------------

_ROUTER = """
import sys, time, zenoh
sys.path.insert(0, sys.argv[2])
from randt.wire.zenoh_config import zenoh_config
s = zenoh.open(zenoh_config("router", listen=(sys.argv[1],)))
print("ready", flush=True)
while True:
    time.sleep(3600)
"""


def _start_router(endpoint: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-c", _ROUTER, endpoint, str(REPO)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if line.strip() != "ready":
        proc.kill()
        raise SetupError(f"the Zenoh router did not start on {endpoint}")
    return proc


def run_router_fault() -> FaultResult:
    result = FaultResult("router")
    t0 = time.monotonic()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = _start_router(endpoint)
    answers: list[Answer] = []
    tiles: list[TileSeen] = []
    try:
        with tempfile.TemporaryDirectory(prefix="randt-router-") as tmp:
            data_dir = Path(tmp)
            with live_service(
                data_dir, zenoh_mode="client", connect=(endpoint,), flush_interval_s=0.3
            ) as live:
                listener = Listener((endpoint,), mode="client")
                good = GoodVehicle((endpoint,), rate_hz=5.0, mode="client").start()
                try:
                    listener.wait(lambda: _poses_after(listener, good.vehicle, 0.0) >= 5, 60.0)
                    before = _poses_after(listener, good.vehicle, 0.0)
                    router.send_signal(signal.SIGKILL)
                    router.wait(10)
                    t_kill = time.monotonic()
                    time.sleep(4.0)
                    during = _poses_after(listener, good.vehicle, t_kill + 0.5)
                    alive = healthy(live.port)
                    router = _start_router(endpoint)
                    t_back = time.monotonic()
                    resumed = listener.wait(lambda: _poses_after(listener, good.vehicle, t_back) >= 5, 60.0)
                    t_resume = next(
                        (a.t for a in listener.of(good.vehicle, t_back) if a.kind == "pose"), float("nan")
                    )
                    result.checks["loud"] = (
                        during == 0
                    )  # nothing answered while no router: visible to the vehicle
                    result.checks["recovered"] = resumed and alive and healthy(live.port)
                    result.detail = (
                        f"poses before {before}, while the router was gone {during}, /healthz while gone "
                        f"{'200' if alive else 'no'}; first pose {t_resume - t_back:.1f} s after the "
                        "router returned"
                    )
                finally:
                    good.stop()
                    time.sleep(1.0)
                    answers = listener.snapshot()
                    tiles = list(listener.tiles)
                    listener.close()
            _apply(result, check_store(data_dir, answers, tiles))
            _restart(data_dir, result, zenoh_mode="client", connect=(endpoint,))
    finally:
        if router.poll() is None:
            router.send_signal(signal.SIGKILL)
            router.wait(10)
    result.seconds = time.monotonic() - t0
    return result.finish()


# --------------------------------------------------------------------------------------------
# a vehicle flooding at 10x its rate
# --------------------------------------------------------------------------------------------


def run_flood_fault(seconds: float = 10.0) -> FaultResult:
    result = FaultResult("flood")
    t0 = time.monotonic()
    answers: list[Answer] = []
    tiles: list[TileSeen] = []
    with tempfile.TemporaryDirectory(prefix="randt-flood-") as tmp:
        data_dir = Path(tmp)
        with live_service(data_dir, flush_interval_s=0.3) as live:
            listener = Listener((live.zenoh_endpoint,))
            good = GoodVehicle((live.zenoh_endpoint,), rate_hz=5.0).start()
            try:
                time.sleep(8.0)
                base = latencies(good.sent[3:], listener.snapshot(), 0.0, time.monotonic(), grace_s=2.0)
                base_p99 = p99(base)
                bound = latency_bound(base_p99)
                # the flooding vehicle: 20k-point scans at 10 x 5 Hz
                flood = GoodVehicle(
                    (live.zenoh_endpoint,), vehicle="flood", rate_hz=50.0, n_points=20_000
                ).start()
                t_flood = time.monotonic()
                time.sleep(seconds)
                flood.stop()
                t_end = time.monotonic()
                sent = len(flood.sent)
                listener.wait(lambda: len(listener.of("flood")) >= sent, 120.0)
                got = listener.of("flood")
                codes: dict[str, int] = {}
                for a in got:
                    key = "pose" if a.kind == "pose" else str(a.code)
                    codes[key] = codes.get(key, 0) + 1
                listener.wait(
                    lambda: all(
                        any(a.seq == s.seq for a in listener.of("good", s.t))
                        for s in good.sent
                        if s.t <= t_end
                    ),
                    30.0,
                )
                lat = latencies(good.sent, listener.snapshot(), t_flood, t_end)
                worst = p99(lat)
                result.checks["latency"] = bool(lat) and worst <= bound
                answered = codes.get("pose", 0) + codes.get("dropped", 0)
                result.checks["loud"] = len(got) == sent and answered == sent
                result.checks["recovered"] = healthy(live.port)
                result.detail = (
                    f"flood sent {sent} scans in {seconds:g} s, answers {codes}; good vehicle p99 "
                    f"{worst:.3f} s over {len(lat)} scans (baseline {base_p99:.3f} s, bound {bound:.3f} s)"
                )
            finally:
                good.stop()
                time.sleep(1.0)
                answers = listener.snapshot()
                tiles = list(listener.tiles)
                listener.close()
        _apply(result, check_store(data_dir, answers, tiles))
        _restart(data_dir, result)
    result.seconds = time.monotonic() - t0
    return result.finish()


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------


def run_fault(name: str) -> FaultResult:
    """Run one fault; a fault that cannot be set up raises :class:`SetupError`."""
    if name in ("full_disk", "read_only"):
        return run_disk_fault(name)
    if name == "router":
        return run_router_fault()
    if name == "flood":
        return run_flood_fault()
    raise ValueError(f"unknown fault {name!r} (known: {', '.join(FAULTS)})")


def run_faults(names: tuple[str, ...] = FAULTS) -> list[FaultResult]:
    """Every fault; one that cannot be set up is a failed result naming why."""
    out = []
    for name in names:
        try:
            out.append(run_fault(name))
        except SetupError as exc:
            out.append(FaultResult(name, False, {"set_up": False}, detail=f"could not set up: {exc}"))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(prog="faults.py", description=__doc__.splitlines()[0])
    parser.add_argument("--fault", nargs="+", default=list(FAULTS), choices=FAULTS)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--inner", help=argparse.SUPPRESS)
    parser.add_argument("--root", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.inner:
        res = _disk_fault_inner(args.inner, args.root)
        args.out.write_text(json.dumps(asdict(res)))
        return
    results = run_faults(tuple(args.fault))
    if args.json:
        print(json.dumps([asdict(r) for r in results], indent=1))
    else:
        for r in results:
            print(f"{r.name}: {'survived' if r.survived else 'FAILED'} {r.checks}\n  {r.detail}")
    sys.exit(0 if all(r.survived for r in results) else 1)


if __name__ == "__main__":
    main()
