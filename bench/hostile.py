"""Run the hostile-input corpus (``tests/corpus/``, written by ``python -m bench.corpus``).

Run from the repository root::

    python -m bench.hostile [--surface wire http file] [--case NAME ...] [--json]

How each surface is run:

* ``wire``: a real :class:`randt.service.runtime.Service` (through ``create_app``: its Zenoh transport,
  a peer listening on a free 127.0.0.1 port, multicast scouting off) receives each payload from a
  second Zenoh session publishing on ``randt/fleet/<key>/scan``: the real transport callback, not a
  shortcut into the session manager. A third session listens to every pose and error. During all
  wire and HTTP cases a well-behaved vehicle (``good``, 3000-point scans at 5 Hz) streams.
* ``http``: the same service's FastAPI app served by uvicorn on a free 127.0.0.1 port; each request
  is written byte for byte on a socket (no client normalizes ``..`` or percent escapes).
* ``file``: the ``randt`` command in a subprocess (``python -m randt.cli ...``) on the case's file.

Checks per case (all must hold):

* ``outcome``: the documented answer (wire: the error code on the vehicle's error key, or a pose,
  or, when no valid key exists to answer on, the rejection counter ``randt_scans_rejected_total``
  by code; http: the status and the shape of the error body; file: the exit code and a one-line
  ``randt: error:`` message, no traceback);
* ``alive``: the service still answers ``GET /healthz`` (file: the command did not crash, exit
  code not 1);
* ``store``: no byte changed under the data directory's ``maps/`` and ``sessions/`` (sha256 of every
  file before and after the case). Allowed to change: the well-behaved vehicle's session folder
  and map, and the session folder and map of a case whose setup scans were accepted (their saves
  are the protocol working). File cases: the input folder is unchanged;
* ``latency``: the well-behaved vehicle's scans in flight during the case (sent before it ended,
  answered after it began; unanswered ones count as infinite) have p99 <= max(2 x baseline p99,
  baseline p99 + 1 s), the baseline measured over 8 s before the first case.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.corpus import DEFAULT_OUT, HOSTILE, build_payload
from bench.harness import (
    GoodVehicle,
    Listener,
    diff_hashes,
    hash_store,
    healthy,
    http_raw,
    latencies,
    latency_bound,
    live_service,
    p99,
)

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
BASELINE_S = 8.0
ANSWER_TIMEOUT_S = 120.0


@dataclass
class CaseResult:
    name: str
    surface: str
    passed: bool
    checks: dict[str, bool]
    detail: str
    seconds: float
    latency_p99_s: float | None = None
    latency_samples: int = 0


@dataclass
class CorpusReport:
    results: list[CaseResult] = field(default_factory=list)
    baseline_p99_s: float | None = None
    bound_s: float | None = None
    seconds: float = 0.0

    def failed(self) -> list[CaseResult]:
        return [r for r in self.results if not r.passed]

    def by_surface(self) -> dict[str, tuple[int, int]]:
        """surface -> (passed, total)."""
        out: dict[str, tuple[int, int]] = {}
        for r in self.results:
            p, t = out.get(r.surface, (0, 0))
            out[r.surface] = (p + int(r.passed), t + 1)
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "baseline_p99_s": self.baseline_p99_s,
            "bound_s": self.bound_s,
            "seconds": self.seconds,
            "results": [asdict(r) for r in self.results],
        }


def load_cases(corpus: Path = DEFAULT_OUT) -> list[dict[str, Any]]:
    return list(json.loads((corpus / "cases.json").read_text(encoding="utf-8"))["cases"])


def payload_of(case: dict[str, Any], corpus: Path) -> bytes:
    spec = case["payload"]
    if "file" in spec:
        return (corpus / spec["file"]).read_bytes()
    return build_payload(spec["recipe"])


# --------------------------------------------------------------------------------------------
# wire and http
# --------------------------------------------------------------------------------------------


def _rejected(service: Any, code: str) -> float:
    return float(
        service.metrics.registry.get_sample_value("randt_scans_rejected_total", {"reason": code}) or 0.0
    )


def _run_wire(case: dict[str, Any], corpus: Path, ctx: _Ctx) -> tuple[dict[str, bool], str, float, float]:
    """Checks and detail of one wire case; returns (checks, detail, t_start, t_end)."""
    import zenoh

    from randt.wire.keys import scan_key

    expect = case["expect"]
    session = case["session"]
    pub = ctx.publisher.declare_publisher(
        scan_key(case["key"]),
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )
    detail = []
    checks: dict[str, bool] = {}
    try:
        for step in case["setup"]:
            t = time.monotonic()
            pub.put(build_payload(step))
            seq, since = int(step["seq"]), t

            def posed(seq: int = seq, since: float = since) -> bool:
                return any(
                    a.kind == "pose" and a.session == session and a.seq == seq
                    for a in ctx.listener.of(HOSTILE, since)
                )

            ok = ctx.listener.wait(posed, ANSWER_TIMEOUT_S)
            if not ok:
                seen = [(a.kind, a.seq, a.code) for a in ctx.listener.of(HOSTILE, t)]
                return (
                    {"setup": False},
                    f"setup scan seq {seq} got no pose: {seen}",
                    t,
                    time.monotonic(),
                )
        if case["setup"]:
            _flushed(ctx)  # the accepted setup saved before hashing
        if expect["answer"] in ("pose", "pose_or_error"):
            ctx.allowed_sessions.add(session)  # an accepted scan is saved: the protocol working
        before = hash_store(ctx.data_dir, ctx.exclude)
        payload = payload_of(case, corpus)
        repeat = int(case["payload"].get("recipe", {}).get("repeat", 1))
        codes = expect.get("codes", [])
        counted0 = {c: _rejected(ctx.service, c) for c in codes}
        t_start = time.monotonic()
        for _ in range(repeat):
            pub.put(payload)
        vehicle = case["key"]
        if expect["answer"] == "none":
            ok = ctx.listener.wait(
                lambda: sum(_rejected(ctx.service, c) - counted0[c] for c in codes) >= repeat,
                ANSWER_TIMEOUT_S,
            )
            t_end = time.monotonic()
            stray = ctx.listener.of(vehicle, t_start)
            checks["outcome"] = ok and not stray
            detail.append(
                f"counted {sum(_rejected(ctx.service, c) - counted0[c] for c in codes):g} x {codes}"
                + (f", unexpected answers {[(a.kind, a.code) for a in stray]}" if stray else "")
            )
        else:
            ok = ctx.listener.wait(lambda: len(ctx.listener.of(vehicle, t_start)) >= repeat, ANSWER_TIMEOUT_S)
            t_end = time.monotonic()
            got = ctx.listener.of(vehicle, t_start)
            kinds = [(a.kind, a.code) for a in got]
            if expect["answer"] == "error":
                good = ok and len(got) == repeat and all(a.kind == "error" and a.code in codes for a in got)
            elif expect["answer"] == "pose":
                good = ok and len(got) == 1 and got[0].kind == "pose"
            else:  # pose_or_error
                good = ok and len(got) == 1 and (got[0].kind == "pose" or got[0].code in codes)
            checks["outcome"] = good
            counts: dict[str, int] = {}
            for kind, code in kinds:
                label = kind if code is None else f"{kind} {code}"
                counts[label] = counts.get(label, 0) + 1
            summary = ", ".join(f"{n} x {label}" if n > 1 else label for label, n in counts.items())
            detail.append(f"answered: {summary}" if kinds else f"no answer in {ANSWER_TIMEOUT_S:.0f} s")
        checks["alive"] = healthy(ctx.port)
        _flushed(ctx)  # a wrong write is on disk by now
        after = hash_store(ctx.data_dir, ctx.exclude)
        changed = diff_hashes(before, after)
        if case["setup"] or expect["answer"] in ("pose", "pose_or_error"):
            # From now on this session's files may change (its close saves it): not this case's
            # doing. It is closed so that later cases never meet a per-vehicle session limit.
            ctx.allowed_sessions.add(session)
            try:
                ctx.service.sessions.close(HOSTILE, session)
            except Exception:
                log.warning("closing %s/%s failed", HOSTILE, session, exc_info=True)
        checks["store"] = not changed
        if changed:
            detail.append(f"store changed: {changed[:5]}")
        return checks, "; ".join(detail), t_start, t_end
    finally:
        pub.undeclare()


_BODY_OK = {
    "validation": lambda b: isinstance(b, dict) and isinstance(b.get("detail"), list),
    "not_found": lambda b: isinstance(b, dict) and isinstance(b.get("detail"), str),
    "detail": lambda b: isinstance(b, dict) and isinstance(b.get("detail"), str),
}


def _flushed(ctx: _Ctx) -> None:
    """Whatever the case changed, on disk now: one flush of the service, as its flusher runs them
    (``SessionManager.flush``, serialized with the flusher's), instead of waiting for the flusher
    (two intervals per case took 70 of the corpus's 146 s in CI)."""
    ctx.service.sessions.flush()


def _run_http(case: dict[str, Any], ctx: _Ctx) -> tuple[dict[str, bool], str, float, float]:
    target = (
        case["target"]
        .replace("{map}", ctx.good_map)
        .replace("{vehicle}", ctx.good_vehicle)
        .replace("{session}", ctx.good_session)
    )
    before = hash_store(ctx.data_dir, ctx.exclude)
    t_start = time.monotonic()
    status, body = http_raw(ctx.port, case["method"], target)
    t_end = time.monotonic()
    try:
        doc = json.loads(body) if body else None
    except ValueError:
        doc = None
    expect = case["expect"]
    leak = b"root:" in body  # /etc/passwd's first line: a traversal that worked
    checks = {
        "outcome": status == expect["status"] and _BODY_OK[expect["body"]](doc) and not leak,
        "alive": healthy(ctx.port),
    }
    _flushed(ctx)
    changed = diff_hashes(before, hash_store(ctx.data_dir, ctx.exclude))
    checks["store"] = not changed
    detail = f"{status} {body[:120]!r}" + (f"; store changed: {changed[:5]}" if changed else "")
    return checks, detail, t_start, t_end


@dataclass
class _Ctx:
    service: Any
    port: int
    data_dir: Path
    listener: Listener
    publisher: Any
    flush_s: float
    good_vehicle: str
    good_session: str
    good_map: str
    allowed_sessions: set[str] = field(default_factory=set)

    def exclude(self, rel: str) -> bool:
        from randt.wire.ids import session_map_name

        parts = rel.split("/")
        if parts[0] == "sessions" and len(parts) > 2:
            if parts[1] == self.good_vehicle:
                return True
            if parts[1] == HOSTILE and parts[2] in self.allowed_sessions:
                return True
        if parts[0] == "maps" and len(parts) > 1:
            allowed = {self.good_map} | {session_map_name(HOSTILE, s) for s in self.allowed_sessions}
            return parts[1] in allowed
        return False


def run_service_cases(
    cases: list[dict[str, Any]], corpus: Path, report: CorpusReport, *, progress: bool = False
) -> None:
    """Wire and HTTP cases against one live service, with the well-behaved vehicle streaming."""
    import zenoh

    from randt.wire.zenoh_config import zenoh_config

    if not cases:
        return
    flush_s = 0.3
    with tempfile.TemporaryDirectory(prefix="randt-hostile-") as tmp:
        data_dir = Path(tmp)
        # (no admission limit: the cases open many one-scan sessions; admission has its own tests)
        with live_service(
            data_dir, flush_interval_s=flush_s, max_sessions=0, capacity_target=0, queue_size=8
        ) as live:
            listener = Listener((live.zenoh_endpoint,))
            publisher = zenoh.open(zenoh_config("peer", connect=(live.zenoh_endpoint,)))
            good = GoodVehicle((live.zenoh_endpoint,)).start()
            try:
                time.sleep(BASELINE_S)
                base = [
                    x
                    for x in latencies(good.sent[3:], listener.snapshot(), 0.0, time.monotonic(), grace_s=2.0)
                ]
                report.baseline_p99_s = p99(base)
                report.bound_s = latency_bound(report.baseline_p99_s)
                good_map = next(
                    (a.map for a in listener.snapshot() if a.vehicle == good.vehicle and a.map), "good.drive"
                )
                ctx = _Ctx(
                    live.service,
                    live.port,
                    data_dir,
                    listener,
                    publisher,
                    flush_s,
                    good.vehicle,
                    good.session,
                    good_map,
                )
                for k, case in enumerate(cases):
                    t0 = time.monotonic()
                    try:
                        if case["surface"] == "wire":
                            checks, detail, ts, te = _run_wire(case, corpus, ctx)
                        else:
                            checks, detail, ts, te = _run_http(case, ctx)
                    except Exception as exc:  # a harness failure is a failed case, with its reason
                        log.exception("case %s", case["name"])
                        checks, detail, ts, te = (
                            {"harness": False},
                            f"{type(exc).__name__}: {exc}",
                            t0,
                            time.monotonic(),
                        )

                    # the good vehicle's scans in flight during the case: wait for their answers
                    def settled(ts: float = ts, te: float = te) -> bool:
                        return all(
                            any(
                                a.vehicle == s.vehicle and a.seq == s.seq for a in listener.of(s.vehicle, s.t)
                            )
                            for s in good.sent
                            if ts - 2.0 <= s.t <= te
                        )

                    listener.wait(
                        settled,
                        30.0,
                    )
                    lat = latencies(good.sent, listener.snapshot(), ts, te)
                    worst = p99(lat) if lat else None
                    checks["latency"] = worst is None or worst <= report.bound_s
                    passed = all(checks.values())
                    report.results.append(
                        CaseResult(
                            case["name"],
                            case["surface"],
                            passed,
                            checks,
                            (
                                ""
                                if worst is None
                                else f"good vehicle p99 {worst:.3f} s over {len(lat)} scans; "
                            )
                            + detail,
                            time.monotonic() - t0,
                            worst,
                            len(lat),
                        )
                    )
                    if progress:
                        mark = "ok  " if passed else "FAIL"
                        print(
                            f"  {mark} {k + 1}/{len(cases)} {case['name']}: {report.results[-1].detail}",
                            file=sys.stderr,
                            flush=True,
                        )
            finally:
                good.stop()
                publisher.close()
                listener.close()


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------


def _tree_hash(root: Path) -> dict[str, str]:
    import hashlib

    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def run_file_case(case: dict[str, Any], corpus: Path) -> CaseResult:
    from bench.corpus import room_points
    from randt.core.io.clouds import PointCloud, write_pcd

    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="randt-file-") as tmp_s:
        tmp = Path(tmp_s)
        inputs = tmp / "in"
        rel = Path(*Path(case["file"]).parts[2:])  # files/<case>/<path>
        path = inputs / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes((corpus / case["file"]).read_bytes())
        good = inputs / "good.pcd"
        write_pcd(good, PointCloud(xyz=room_points(3000, seed=3).astype(np.float64)))
        case_dir = inputs / rel.parts[0] if len(rel.parts) > 2 else path.parent
        argv = [
            a.replace("{case_dir}", str(case_dir))
            .replace("{case}", str(path))
            .replace("{good}", str(good))
            .replace("{tmp}", str(tmp))
            for a in case["argv"]
        ]
        before = _tree_hash(inputs)
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        try:
            done = subprocess.run(
                [sys.executable, "-m", "randt.cli", *argv],
                capture_output=True,
                text=True,
                timeout=300,
                cwd=tmp,
                env=env,
            )
            code, err = done.returncode, done.stderr
        except subprocess.TimeoutExpired:
            code, err = -1, "timed out after 300 s"
        after = _tree_hash(inputs)
    expect = case["expect"]["exit"]
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    checks = {
        "outcome": code == expect and bool(lines) and lines[-1].startswith("randt: error:"),
        "alive": code not in (1, -1) and "Traceback" not in err,
        "store": before == after,
    }
    detail = f"exit {code}: {lines[-1][:160] if lines else '(no message)'}"
    return CaseResult(case["name"], "file", all(checks.values()), checks, detail, time.monotonic() - t0)


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------


def run_corpus(
    corpus: Path = DEFAULT_OUT,
    *,
    surfaces: tuple[str, ...] = ("wire", "http", "file"),
    names: list[str] | None = None,
    progress: bool = False,
) -> CorpusReport:
    """Run the selected cases; every case gets a :class:`CaseResult`."""
    t0 = time.monotonic()
    cases = [c for c in load_cases(corpus) if c["surface"] in surfaces and (not names or c["name"] in names)]
    report = CorpusReport()
    run_service_cases(
        [c for c in cases if c["surface"] in ("wire", "http")], corpus, report, progress=progress
    )
    for case in (c for c in cases if c["surface"] == "file"):
        report.results.append(run_file_case(case, corpus))
        if progress:
            r = report.results[-1]
            print(
                f"  {'ok  ' if r.passed else 'FAIL'} {case['name']}: {r.detail}", file=sys.stderr, flush=True
            )
    report.seconds = time.monotonic() - t0
    return report


def main() -> None:
    parser = argparse.ArgumentParser(prog="hostile.py", description=__doc__.splitlines()[0])
    parser.add_argument("--corpus", type=Path, default=DEFAULT_OUT)
    parser.add_argument(
        "--surface", nargs="+", default=["wire", "http", "file"], choices=["wire", "http", "file"]
    )
    parser.add_argument("--case", nargs="+", default=None, help="only these case names")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    report = run_corpus(args.corpus, surfaces=tuple(args.surface), names=args.case, progress=True)
    if args.json:
        print(json.dumps(report.to_json(), indent=1))
    else:
        for surface, (ok, total) in report.by_surface().items():
            print(f"{surface}: {ok}/{total} passed")
        print(f"baseline p99 {report.baseline_p99_s}, bound {report.bound_s}")
        for r in report.failed():
            print(f"FAIL {r.name}: {r.checks} {r.detail}")
    sys.exit(1 if report.failed() else 0)


if __name__ == "__main__":
    main()
