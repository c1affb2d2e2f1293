"""Ctrl-C on ``randt demo`` at random moments with both cores busy (issue 33).

Run from the repository root::

    python -m bench.ctrl_c [--runs 20] [--seed 33] [--latest 4.5]

Each run starts ``randt demo`` (one vehicle, one simulated second, in its own process group with
SIGINT at its default, as a terminal starts it, and a temporary folder of its own as TMPDIR),
sends SIGINT to the whole group at a random moment in ``[0.2, --latest]`` seconds (the
interpreter's start, the service's start, the matchers' warm-up, the drive, the summary,
serving), with two CPU burners beside it, and checks: exit code 130 (or killed by SIGINT itself,
which a shell reports as 130: a Ctrl-C before the interpreter installed its handler), at most one
line on stderr and no traceback, no process of its group left running (zombies aside) ten seconds after it
exited, nothing left in its temporary folder. Prints one line per run and a summary; exits 1 if
any run failed.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _left_running(pgid: int, wait_s: float = 10.0) -> list[str]:
    """The processes of group ``pgid`` still running (not zombies), after up to ``wait_s``."""
    deadline = time.monotonic() + wait_s
    while True:
        ps = subprocess.run(["ps", "-o", "stat=,args=", "-g", str(pgid)], capture_output=True, text=True)
        running = [line.strip() for line in ps.stdout.splitlines() if not line.lstrip().startswith("Z")]
        if not running or time.monotonic() > deadline:
            return running
        time.sleep(0.2)


def _dump_stacks(pid: int) -> None:
    """A demo that did not end: every thread's stack on stderr (``py-spy dump``, when installed),
    to say where it hung before it is killed."""
    import shutil

    spy = shutil.which("py-spy")
    if spy is None:
        print(f"  (demo {pid} hung; install py-spy to see where)", file=sys.stderr, flush=True)
        return
    dump = subprocess.run([spy, "dump", "--pid", str(pid)], capture_output=True, text=True, check=False)
    print(
        f"  demo {pid} hung after Ctrl-C; its threads:\n{dump.stdout}{dump.stderr}",
        file=sys.stderr,
        flush=True,
    )


def one_run(at_s: float, tmp: Path) -> tuple[list[str], float]:
    """One interrupted demo: what was wrong with it (empty: nothing), and the seconds from the
    Ctrl-C to the demo's exit."""
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "randt.cli",
            "demo", "--vehicles", "1", "--duration", "1", "--azimuth", "500",
            "--no-progress", "--http-port", str(_free_port()), "--zenoh-port", str(_free_port()),
        ],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, "TMPDIR": str(tmp)},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # (as a terminal starts it)
    )  # fmt: skip
    time.sleep(at_s)
    os.killpg(proc.pid, signal.SIGINT)
    sent = time.monotonic()
    try:
        _, err = proc.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        _dump_stacks(proc.pid)
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
    stop_s = time.monotonic() - sent
    running = _left_running(proc.pid)
    if running:
        subprocess.run(["pkill", "-9", "-g", str(proc.pid)], check=False)
    lines = [line for line in err.splitlines() if line.strip()]
    problems = []
    # A SIGINT in the interpreter's first milliseconds, before Python installs its handler, ends
    # the process by the signal itself: a shell reports that as 130 too (128 + SIGINT).
    if proc.returncode not in (130, -signal.SIGINT):
        problems.append(f"exit {proc.returncode}")
    if len(lines) > 1 or (not lines and proc.returncode == 130) or "Traceback" in err:
        problems.append(f"stderr {lines[-6:]}")
    if running:
        problems.append(f"left running {running}")
    left = sorted(p.name for p in tmp.iterdir())
    if left:
        problems.append(f"left {left}")
    return problems, stop_s


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ctrl_c.py", description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--seed", type=int, default=33)
    parser.add_argument("--latest", type=float, default=4.5, help="latest Ctrl-C moment, s (default 4.5)")
    args = parser.parse_args(argv)
    rnd = random.Random(args.seed)
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    failed = 0
    stops: list[float] = []
    try:
        for run in range(args.runs):
            at = rnd.uniform(0.2, args.latest)
            with tempfile.TemporaryDirectory(prefix="randt-ctrl-c-") as tmp:
                problems, stop_s = one_run(at, Path(tmp))
            failed += bool(problems)
            stops.append(stop_s)
            verdict = "; ".join(problems) or "ok"
            print(f"run {run:2d}: Ctrl-C at {at:4.1f} s, exited {stop_s:4.1f} s later: {verdict}", flush=True)
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()
    print(f"{args.runs - failed} of {args.runs} runs clean")
    if stops:
        mean, median, most = np.mean(stops), np.median(stops), max(stops)
        print(f"exit after Ctrl-C: mean {mean:.1f} s, median {median:.1f} s, max {most:.1f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
