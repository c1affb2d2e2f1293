"""What one call costs: a multiprocessing pipe (the local executor's) against a Ray actor call.

A float32 sweep of ``--points`` points goes to another process, which answers with an array of
``--answer`` points (by default what a 64-beam sweep and its kept points weigh: 630 kB and 448 kB).
Reported per call: the wall time, the caller's CPU, the callee's CPU. The Ray side uses the
service's per-call settings (``randt.service.ray_executor.RAY_ENV``) unless ``--ray-defaults``.

    unshare -n sh -c "ip link set lo up && python -m bench.ray_call"

(Ray binds the machine's external address; alone in a network namespace it uses 127.0.0.1.)
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Client, Connection
from typing import Any

import numpy as np


def _echo(conn: Connection, n_answer: int) -> None:
    answer = {"points": np.ones((n_answer, 3), np.float32), "T": np.eye(4)}
    conn.recv()
    conn.send(answer)  # the warm-up call
    start = time.process_time()
    while True:
        msg = conn.recv()
        if msg is None:
            conn.send(time.process_time() - start)
            return
        conn.send(answer)


def bench_pipe(n_points: int, n_answer: int, calls: int) -> tuple[float, float, float]:
    ctx = mp.get_context("spawn")
    here, there = ctx.Pipe()
    proc = ctx.Process(target=_echo, args=(there, n_answer))
    proc.start()
    sweep = np.random.default_rng(0).random((n_points, 3)).astype(np.float32)
    here.send(sweep)
    here.recv()
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(calls):
        here.send(sweep)
        here.recv()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    here.send(None)
    callee = here.recv()  # the child's CPU time after the warm-up call
    proc.join()
    return wall / calls, cpu / calls, callee / calls


class _Echo:
    """The callee of a Ray call: the same answer to every sweep."""

    def __init__(self, n_answer: int) -> None:
        self.answer = {"points": np.ones((n_answer, 3), np.float32), "T": np.eye(4)}

    def call(self, sweep: np.ndarray) -> dict[str, Any]:
        return self.answer

    def cpu(self) -> float:
        return time.process_time()

    def pid(self) -> int:
        return os.getpid()

    def listen(self, authkey: bytes) -> tuple[str, int]:
        """Serve the same answer over a socket of its own (``multiprocessing.connection``, the
        local executor's pipe protocol), on a thread; returns the address."""
        from multiprocessing.connection import Listener

        listener = Listener(("127.0.0.1", 0), authkey=authkey)

        def serve() -> None:
            conn = listener.accept()
            while True:
                try:
                    conn.recv()
                except EOFError:
                    return
                conn.send(self.answer)

        threading.Thread(target=serve, daemon=True).start()
        host, port = listener.address
        return str(host), int(port)


def _ray_echo(n_answer: int, defaults: bool) -> tuple[Any, Any]:
    """A local Ray (with the service's RAY_ENV unless ``defaults``) and an :class:`_Echo` actor."""
    if not defaults:
        from randt.service.ray_executor import RAY_ENV

        for name, value in RAY_ENV.items():
            os.environ.setdefault(name, value)
    import ray

    ray.init(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    return ray, ray.remote(num_cpus=0)(_Echo).remote(n_answer)


def bench_ray(n_points: int, n_answer: int, calls: int, defaults: bool) -> tuple[float, float, float]:
    ray, echo = _ray_echo(n_answer, defaults)
    sweep = np.random.default_rng(0).random((n_points, 3)).astype(np.float32)
    ray.get(echo.call.remote(sweep))
    a0 = ray.get(echo.cpu.remote())
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(calls):
        ray.get(echo.call.remote(sweep))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    a1 = ray.get(echo.cpu.remote())
    ray.shutdown()
    return wall / calls, cpu / calls, (a1 - a0) / calls


def _cpu_of(pid: int) -> Callable[[], float]:
    """The CPU seconds process ``pid`` has used so far, read on each call."""
    import psutil  # type: ignore[import-untyped]  # (a dependency of ray)

    proc = psutil.Process(pid)

    def cpu() -> float:
        t = proc.cpu_times()
        return float(t.user + t.system)

    return cpu


def _timed(one_call: Callable[[], object], callee_cpu: Callable[[], float], calls: int) -> tuple[float, ...]:
    """Per call (wall, caller CPU, callee CPU) over ``calls`` calls after a warm-up call, and the
    callee's CPU per second over 2 s of waiting for the next call."""
    one_call()
    a0 = callee_cpu()
    time.sleep(2.0)
    idle = (callee_cpu() - a0) / 2.0
    a0 = callee_cpu()
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(calls):
        one_call()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return wall / calls, cpu / calls, (callee_cpu() - a0) / calls, idle


def bench_ray_compiled(n_points: int, n_answer: int, calls: int) -> tuple[float, ...]:
    """The same call through a Ray compiled graph (shared-memory channels): per call (wall,
    caller CPU, callee CPU), and the callee's CPU per second while it waits for the next call."""
    from ray.dag import InputNode

    ray, echo = _ray_echo(n_answer, False)
    callee_cpu = _cpu_of(ray.get(echo.pid.remote()))
    with InputNode() as sweep_in:
        dag = echo.call.bind(sweep_in)
    compiled = dag.experimental_compile(_buffer_size_bytes=max(1 << 20, 2 * 12 * max(n_points, n_answer)))
    sweep = np.random.default_rng(0).random((n_points, 3)).astype(np.float32)
    result = _timed(lambda: ray.get(compiled.execute(sweep)), callee_cpu, calls)
    compiled.teardown()
    ray.shutdown()
    return result


def bench_ray_socket(n_points: int, n_answer: int, calls: int) -> tuple[float, ...]:
    """The sweep over a socket straight to the Ray actor (Ray only starts and places it; the
    local executor's pipe protocol): per call (wall, caller CPU, callee CPU), and the callee's CPU
    per second while idle."""
    ray, echo = _ray_echo(n_answer, False)
    callee_cpu = _cpu_of(ray.get(echo.pid.remote()))
    key = os.urandom(16)
    conn = Client(ray.get(echo.listen.remote(key)), authkey=key)
    sweep = np.random.default_rng(0).random((n_points, 3)).astype(np.float32)

    def one_call() -> object:
        conn.send(sweep)
        return conn.recv()

    result = _timed(one_call, callee_cpu, calls)
    conn.close()
    ray.shutdown()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(prog="ray_call.py", description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=52_500, help="the sweep's points (float32 xyz)")
    parser.add_argument("--answer", type=int, default=37_333, help="the answer's points")
    parser.add_argument("--calls", type=int, default=400)
    parser.add_argument("--ray-defaults", action="store_true", help="Ray's own settings, not RAY_ENV")
    parser.add_argument(
        "--compiled", action="store_true", help="also through a Ray compiled graph (and its idle CPU)"
    )
    parser.add_argument(
        "--socket",
        action="store_true",
        help="also over a socket straight to the Ray actor (and its idle CPU)",
    )
    args = parser.parse_args()
    kb_in, kb_out = args.points * 12 / 1e3, args.answer * 12 / 1e3
    print(f"{args.calls} calls, {kb_in:.0f} kB there, {kb_out:.0f} kB back")
    for name, (wall, cpu, callee) in (
        ("pipe", bench_pipe(args.points, args.answer, args.calls)),
        ("ray", bench_ray(args.points, args.answer, args.calls, args.ray_defaults)),
    ):
        print(
            f"{name:5s} {wall * 1e3:6.2f} ms per call; CPU per call: caller {cpu * 1e3:.2f} ms, "
            f"callee {callee * 1e3:.2f} ms"
        )
    if args.compiled:
        wall, cpu, callee, idle = bench_ray_compiled(args.points, args.answer, args.calls)
        print(
            f"ray compiled graph {wall * 1e3:6.2f} ms per call; CPU per call: caller {cpu * 1e3:.2f} ms, "
            f"callee {callee * 1e3:.2f} ms; callee CPU while idle: {idle:.2f} s per second"
        )
    if args.socket:
        wall, cpu, callee, idle = bench_ray_socket(args.points, args.answer, args.calls)
        print(
            f"socket to a Ray actor {wall * 1e3:6.2f} ms per call; CPU per call: caller {cpu * 1e3:.2f} ms, "
            f"callee {callee * 1e3:.2f} ms; callee CPU while idle: {idle:.2f} s per second"
        )


if __name__ == "__main__":
    main()
