"""kill -9 fault injection: acknowledged poses and served tile versions survive every crash.

Run from the repository root::

    python -m bench.crash [--cycles 20] [--sessions 2] [--seed 0] [--data DIR]

prints a :class:`CrashReport` as JSON. Each cycle starts a worker process (``--worker``): a real
:class:`randt.service.runtime.Service` (without Zenoh: the crash is about the store) whose outbox is
replaced by lines on stdout, one per message, written before the message would go out. Its
``sessions`` vehicles stream a moving synthetic room (the first session with a prior pose, so it
folds into the shared map ``default``; the others in their own frames and maps), continuing
their sequence numbers from the store at each start. A sampler thread also asks the service for
random tiles as its Zenoh queryable would answer them (the HTTP API serves the same tiles).
The parent records, from the lines it got, every pose the service acknowledged and every
``(tile, version, digest)`` it served, kills the worker with SIGKILL at a random moment (0.5-4 s
after it is ready, or in every second cycle after its first tile was saved: a worker on a busy
machine may otherwise never get that far; during ingest, tile and session writes), then opens the
store and checks:

* every acknowledged pose is in the stored trajectory (same stamp) with identical values;
* every map loads, its metadata lists only tile files that exist and read (no torn tile);
* no tile is stored or served at a version below one served before (no regression);
* no ``(map, tile, version)`` is served or stored with two different contents (no reuse).

It imports neither pytest nor ``tests``; ``tests/service/test_durability.py`` runs a few cycles
and ``bench/reliability.py`` the full count.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from bench/
    sys.path.insert(0, str(REPO))

__all__ = ["CrashReport", "run_kill_cycles"]

#: A worker stops by itself after this long (should its parent vanish without killing it).
WORKER_LIFETIME_S = 120.0
#: Seconds between two scans of one session (the service answers each; some may be dropped).
SCAN_INTERVAL_S = 0.1


@dataclass
class CrashReport:
    """What :func:`run_kill_cycles` found (``docs/reliability.md`` reports it)."""

    cycles: int  # kill -9 cycles done
    acked_poses: int  # poses the service published (acknowledged) over all cycles
    acked_lost: int  # of those, missing or different in the store after restart
    tiles_checked: int  # (tile, version) observations checked
    tiles_torn: int  # tile files unreadable / metadata listing missing files
    tiles_regressed: int  # a tile served at a version lower than one served before
    version_reuses: int  # a (tile, version) pair served with two different contents
    seconds: float
    problems: list[str] = field(default_factory=list)  # the first few findings, for people


# ------------------------------------------------------------------------------------- worker


def _digest(points: bytes) -> str:
    """A tile content's name: what ``randt.wire.messages.points_digest`` computes (spelled out here so
    the harness also measures a service that does not send digests)."""
    return hashlib.sha256(points).hexdigest()[:16]


def _worker(data_dir: str, sessions: int, seed: int, matcher_processes: int, flush_s: float) -> None:
    """The crashing side: a Service whose outbox is stdout (one JSON line per message)."""
    from randt.core.scenes import synthetic_room
    from randt.core.transforms import make_transform, transform_points
    from randt.service.runtime import Service
    from randt.service.settings import ServiceSettings
    from randt.wire.messages import (
        ErrorMessage,
        PoseMessage,
        TileUpdateMessage,
        WireMessage,
        decode_tile_update,
        encode,
        scan_from_arrays,
    )

    out_lock = threading.Lock()

    def line(obj: dict[str, Any]) -> None:
        text = json.dumps(obj) + "\n"
        with out_lock:
            sys.stdout.write(text)
            sys.stdout.flush()

    def emit(msg: WireMessage) -> None:
        if isinstance(msg, PoseMessage):
            line(
                {
                    "k": "pose",
                    "veh": msg.vehicle,
                    "ses": msg.session,
                    "seq": msg.seq,
                    "stamp_ns": msg.stamp_ns,
                    "pose": list(msg.pose),
                }
            )
        elif isinstance(msg, TileUpdateMessage):
            line(
                {
                    "k": "tile",
                    "map": msg.map,
                    "tile": msg.tile,
                    "version": msg.version,
                    "digest": _digest(msg.points),
                }
            )
        elif isinstance(msg, ErrorMessage):
            line({"k": "error", "veh": msg.vehicle, "seq": msg.seq, "code": msg.code})

    settings = ServiceSettings(
        data_dir=Path(data_dir),
        flush_interval_s=flush_s,
        matcher_processes=matcher_processes,
        idle_expiry_s=3600,
    )
    service = Service(settings, with_zenoh=False, outbox=emit)
    service.start()
    mgr = service.sessions
    assert mgr is not None
    mgr.wait_matchers(600)
    records = mgr.records()
    room = synthetic_room(np.random.default_rng(0), 2500)
    rng = np.random.default_rng(seed)
    vehicles = [f"v{i}" for i in range(sessions)]
    seqs = {}
    for v in vehicles:
        rec = records.get((v, "d"))
        seqs[v] = 0 if rec is None else rec.last_seq + 1

    def sample() -> None:
        """Ask for random saved tiles as the queryable does; print what it answers."""
        while True:
            time.sleep(0.05)
            with out_lock:  # read and print in one step: printed versions never run backwards
                names = sorted(mgr.maps)
                if not names:
                    continue
                name = names[int(rng.integers(len(names)))]
                ids = sorted(mgr.maps[name].tile_ids())
                if not ids:
                    continue
                payload = service.tile_payload(name, ids[int(rng.integers(len(ids)))])
                if payload is None:
                    continue
                msg = decode_tile_update(payload)
                sys.stdout.write(
                    json.dumps(
                        {
                            "k": "served",
                            "map": msg.map,
                            "tile": msg.tile,
                            "version": msg.version,
                            "digest": _digest(msg.points),
                        }
                    )
                    + "\n"
                )
                sys.stdout.flush()

    threading.Thread(target=sample, daemon=True).start()
    line({"k": "ready"})
    deadline = time.monotonic() + WORKER_LIFETIME_S
    while time.monotonic() < deadline:
        for i, v in enumerate(vehicles):
            seq = seqs[v]
            x = 2.0 * np.sin(0.03 * seq + i)
            y = 1.5 * np.sin(0.02 * seq + 2 * i)
            T = make_transform(translation=(x, y, 0.0), rotvec=(0.0, 0.0, 0.1 * np.sin(0.01 * seq)))
            pts = transform_points(np.linalg.inv(T), room).astype(np.float32)
            prior = T if i == 0 and seq == 0 else None
            scan = scan_from_arrays(
                v,
                "d",
                seq,
                seq * 100_000_000,
                pts,
                prior_pose=prior,
                prior_covariance=None if prior is None else 0.01 * np.eye(6),
            )
            mgr.submit(v, encode(scan))
            seqs[v] = seq + 1
        time.sleep(SCAN_INTERVAL_S)
    service.stop()


# ------------------------------------------------------------------------------------- parent


@dataclass
class _Ledger:
    """What the service said, over all cycles."""

    acked: dict[tuple[str, str, int], tuple[int, tuple[float, ...]]] = field(default_factory=dict)
    # (map, tile, version) -> digest, from everything served or stored
    contents: dict[tuple[str, str, int], str] = field(default_factory=dict)
    highest: dict[tuple[str, str], int] = field(default_factory=dict)  # (map, tile) -> version
    lost: set[tuple[str, str, int]] = field(default_factory=set)
    checked: int = 0
    torn: int = 0
    regressed: int = 0
    reuses: int = 0
    problems: list[str] = field(default_factory=list)

    def note(self, text: str) -> None:
        if len(self.problems) < 20:
            self.problems.append(text)

    def observe(self, map_name: str, tile: str, version: int, digest: str | None, where: str) -> None:
        """One (tile, version, content) seen outside, in order."""
        self.checked += 1
        key = (map_name, tile)
        if version < self.highest.get(key, 0):
            self.regressed += 1
            self.note(f"{where}: {map_name}/{tile} at version {version} after {self.highest[key]}")
        self.highest[key] = max(version, self.highest.get(key, 0))
        if digest is None:
            return
        seen = self.contents.setdefault((map_name, tile, version), digest)
        if seen != digest:
            self.reuses += 1
            self.note(f"{where}: {map_name}/{tile} version {version} with content {digest}, before {seen}")


def _read_lines(stream: Any, into: list[str]) -> None:
    for text in stream:
        into.append(text)


def _start_worker(
    data: Path, sessions: int, seed: int, matcher_processes: int, flush_s: float
) -> subprocess.Popen[str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bench.crash",
            "--worker",
            str(data),
            "--sessions",
            str(sessions),
            "--seed",
            str(seed),
            "--matcher-processes",
            str(matcher_processes),
            "--flush-s",
            str(flush_s),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
    )


def _check_store(data: Path, ledger: _Ledger) -> None:
    """After a kill: maps whole, served versions not regressed or reused, acked poses stored."""
    import yaml

    from randt.core.io import read_cloud
    from randt.core.io.autoware import AUTOWARE_METADATA_NAME
    from randt.service.store import Store

    with Store(data) as store:
        contents = store.load_all()
        for problem in contents.problems:
            ledger.torn += problem.kind == "map"
            ledger.note(f"store: {problem.kind} {problem.name}: {problem.message}")
        for name, grid in contents.maps.items():
            map_dir = store.map_dir(name)
            meta = yaml.safe_load((map_dir / AUTOWARE_METADATA_NAME).read_text())
            for tile_file in (k for k in meta if str(k).endswith(".pcd")):
                path = map_dir / tile_file
                try:
                    ok = read_cloud(path).n_points > 0
                except Exception as exc:  # any failure to read is a torn tile
                    ok = False
                    ledger.note(f"store: {path}: {exc}")
                if not ok:
                    ledger.torn += 1
            for tile in grid.tiles():
                table = np.c_[tile.points, tile.intensity].astype("<f4").tobytes()
                ledger.observe(name, tile.id, tile.version, _digest(table), "after restart")
        for (name, tid), version in ledger.highest.items():
            stored_grid = contents.maps.get(name)
            if stored_grid is None or tid not in stored_grid:
                ledger.torn += 1
                ledger.note(f"store: {name}/{tid} was served at version {version} but is not stored")
        stored = {
            key: (np.round(np.asarray(loaded.stamps) * 1e9).astype(np.int64), np.asarray(loaded.poses))
            for key, loaded in contents.sessions.items()
        }
    for (veh, ses, seq), (stamp_ns, pose) in ledger.acked.items():
        stamps, poses = stored.get((veh, ses), (np.zeros(0, np.int64), np.zeros((0, 4, 4))))
        hit = np.flatnonzero(stamps == stamp_ns)
        good = hit.size == 1 and np.array_equal(poses[hit[0]].ravel(), np.asarray(pose))
        if not good and (veh, ses, seq) not in ledger.lost:
            ledger.lost.add((veh, ses, seq))
            ledger.note(f"pose {veh}/{ses} seq {seq}: {'different' if hit.size else 'missing'} after restart")


def run_kill_cycles(
    data_dir: Path,
    *,
    cycles: int = 20,
    sessions: int = 2,
    seed: int = 0,
    matcher_processes: int = 0,
    flush_s: float = 1.0,
) -> CrashReport:
    """``cycles`` times: start a worker on ``data_dir``, kill -9 it at a random moment, check the
    store against everything it acknowledged and served (module docstring).

    ``matcher_processes``: the service's ``RANDT_MATCHER_PROCESSES`` (0: matchers in the session
    threads, the quickest start; a killed service's matcher processes exit with their pipe).
    ``flush_s``: its ``flush_interval_s`` (1 s, the service's default).
    """
    data_dir = Path(data_dir)
    rnd = random.Random(seed)
    ledger = _Ledger()
    t0 = time.perf_counter()
    done = 0
    for cycle in range(cycles):
        proc = _start_worker(data_dir, sessions, seed + cycle, matcher_processes, flush_s)
        assert proc.stdout is not None
        lines: list[str] = []
        reader = threading.Thread(target=_read_lines, args=(proc.stdout, lines), daemon=True)
        reader.start()
        ready_by = time.monotonic() + 300
        while not any('"ready"' in s for s in lines) and proc.poll() is None and time.monotonic() < ready_by:
            time.sleep(0.01)
        if proc.poll() is not None or time.monotonic() >= ready_by:
            proc.kill()
            proc.wait(10)
            raise RuntimeError(f"cycle {cycle}: the worker did not start (exit code {proc.returncode})")
        if cycle % 2 == 1:  # (a condition, not a clock: beside two CPU burners no tile in 5 cycles)
            tile_by = time.monotonic() + 120
            while (
                not any('"tile"' in s for s in lines) and proc.poll() is None and time.monotonic() < tile_by
            ):
                time.sleep(0.01)
        time.sleep(rnd.uniform(0.5, 4.0))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        reader.join(30)
        for text in lines:
            if not text.endswith("\n"):
                continue  # a line cut by the kill was never acknowledged
            msg = json.loads(text)
            if msg["k"] == "pose":
                ledger.acked[(msg["veh"], msg["ses"], msg["seq"])] = (msg["stamp_ns"], tuple(msg["pose"]))
            elif msg["k"] in ("tile", "served"):
                ledger.observe(msg["map"], msg["tile"], msg["version"], msg["digest"], f"cycle {cycle}")
        _check_store(data_dir, ledger)
        done += 1
    return CrashReport(
        cycles=done,
        acked_poses=len(ledger.acked),
        acked_lost=len(ledger.lost),
        tiles_checked=ledger.checked,
        tiles_torn=ledger.torn,
        tiles_regressed=ledger.regressed,
        version_reuses=ledger.reuses,
        seconds=time.perf_counter() - t0,
        problems=ledger.problems,
    )


def append_cost(data_dir: Path, n: int = 300) -> dict[str, float]:
    """Milliseconds per :meth:`Store.append_pose` (write + fsync of one record): mean, median, max
    over ``n`` appends on ``data_dir``'s file system (``--append-cost``)."""
    from randt.service.store import PoseLogRecord, Store

    times = []
    with Store(data_dir) as store:
        for i in range(n):
            record = PoseLogRecord(i, i, i * 100_000_000, i * 0.1, np.eye(4), "ok")
            t = time.perf_counter()
            store.append_pose("bench", "append", record)
            times.append((time.perf_counter() - t) * 1e3)
    a = np.asarray(times)
    return {"n": n, "mean_ms": float(a.mean()), "median_ms": float(np.median(a)), "max_ms": float(a.max())}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="crash.py", description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=20, help="kill -9 cycles (default 20)")
    parser.add_argument("--sessions", type=int, default=2, help="vehicles streaming at once (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments (default 0)")
    parser.add_argument("--matcher-processes", type=int, default=0, help="RANDT_MATCHER_PROCESSES (0)")
    parser.add_argument("--flush-s", type=float, default=1.0, help="RANDT_FLUSH_INTERVAL_S (1.0)")
    parser.add_argument("--data", type=Path, default=None, help="data directory (default: a fresh temp)")
    parser.add_argument("--append-cost", action="store_true", help="only measure one pose-log append + fsync")
    parser.add_argument("--worker", metavar="DATA", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        _worker(args.worker, args.sessions, args.seed, args.matcher_processes, args.flush_s)
        return
    with tempfile.TemporaryDirectory(prefix="randt-crash-") as tmp:
        data = args.data if args.data is not None else Path(tmp) / "data"
        if args.append_cost:
            print(json.dumps(append_cost(data), indent=2))
            return
        report = run_kill_cycles(
            data,
            cycles=args.cycles,
            sessions=args.sessions,
            seed=args.seed,
            matcher_processes=args.matcher_processes,
            flush_s=args.flush_s,
        )
    print(json.dumps(dataclasses.asdict(report), indent=2))


if __name__ == "__main__":
    main()
