"""The deployment, for real: build the image, bring the compose stack up, map, restart, come back.

On this machine (and in CI) with Docker from Debian's packages (``tests/deploy/docker_env.py``
installs and starts what is missing, and stops only a daemon it started). The test runs a copy of
``docker/compose.yaml``, adapted only where this machine differs, and prints each adaptation:

- a project name of its own (``-p``), free host ports, and its own image tags, so that a real
  deployment on the same machine is not touched;
- Compose 1.29 (the one Debian ships) rejects the top-level ``name:`` key: removed (``-p`` names
  the project instead);
- images that cannot be pulled here: the Dockerfile's ``BASE_IMAGE`` build argument set to a
  Python 3.11 image built from Debian's packages, and the ``eclipse/zenoh`` router replaced by an
  equivalent router built on it (Zenoh's Python binding in router mode, same port and flags);
- the demo fleet shortened (2 vehicles, 3 simulated seconds instead of 3 x 60 s).

Then: a simulated vehicle on the host (through the published router port) and the fleet container
(through the router, inside the compose network) both get every scan answered; ``/readyz``,
``/maps``, ``/sessions`` and a tile download answer through the published HTTP port; the service
container restarted (SIGTERM: drained and flushed) keeps every tile byte for byte and every
session; ``down`` then ``up`` likewise, and both keep the pose graph of ``default`` (its
keyframes, placements and revision, the optimized poses within 1 mm; issue 33); the cluster
profile (a Ray head, one worker, the service recreated with ``RANDT_EXECUTOR=ray``) matches a
vehicle on the worker; finally ``down -v`` and the images it built removed.
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from tests.deploy import docker_env
from tests.service.conftest import free_port

REPO = docker_env.REPO
COMPOSE_FILE = REPO / "docker" / "compose.yaml"
HEALTHY_TIMEOUT_S = 240.0
#: The pose graph's re-fold interval in the test's copy, and how long the map must stay unchanged
#: before it is compared across a restart.
REFOLD_S = 2
SETTLE_QUIET_S = 3.0 * REFOLD_S + 2.0


@dataclass
class Stack:
    """The running copy of the compose stack."""

    project: str
    compose_file: Path
    http_port: int
    zenoh_port: int
    app_image: str
    router_image: str
    adaptations: list[str]
    timings: dict[str, float] = field(default_factory=dict)

    def compose(
        self, *args: str, timeout: float = 600.0, check: bool = True, env: dict[str, str] | None = None
    ) -> subprocess.CompletedProcess[str]:
        """``docker-compose`` on the copy; ``env``: variables the compose file interpolates."""
        argv = ["docker-compose", "-f", str(self.compose_file), "-p", self.project, *args]
        return docker_env.run(argv, timeout=timeout, check=check, env={**os.environ, **(env or {})})

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.http_port}{path}"

    def get(self, path: str, timeout: float = 30.0) -> tuple[int, bytes, dict[str, str]]:
        """(status, body, headers with lower-case names)."""
        try:
            with urllib.request.urlopen(self.url(path), timeout=timeout) as r:
                return r.status, r.read(), {k.lower(): v for k, v in r.headers.items()}
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read(), {k.lower(): v for k, v in exc.headers.items()}

    def json(self, path: str) -> Any:
        status, body, _ = self.get(path)
        assert status == 200, (path, status, body[:300])
        return json.loads(body)

    def container(self, service: str) -> str:
        return self.compose("ps", "-q", service).stdout.strip()

    def wait_healthy(self, service: str = "randt") -> float:
        """Seconds until compose's healthcheck reports the service healthy and /readyz answers 200."""
        t0 = time.monotonic()
        while True:
            cid = self.container(service)
            health = ""
            if cid:
                health = docker_env.run(
                    ["docker", "inspect", "--format", "{{.State.Health.Status}}", cid], check=False
                ).stdout.strip()
            if health == "healthy":
                try:
                    if self.get("/readyz", timeout=5)[0] == 200:
                        return time.monotonic() - t0
                except OSError:
                    pass
            if time.monotonic() - t0 > HEALTHY_TIMEOUT_S:
                logs = self.compose("logs", "--tail", "60", service, check=False).stdout
                pytest.fail(
                    f"{service} not healthy after {HEALTHY_TIMEOUT_S:.0f} s (health {health!r}):\n{logs}"
                )
            time.sleep(1.0)

    def snapshot(self) -> Snapshot:
        """Every map's tiles (id -> version, points), their downloaded bytes, and every session's
        (scans, last seq); None when a tile changed while it was read."""
        tiles: dict[str, tuple[int, int]] = {}
        data: dict[str, bytes] = {}
        for m in self.json("/maps")["maps"]:
            for t in self.json(f"/maps/{m['name']}/tiles")["tiles"]:
                key = f"{m['name']}/{t['id']}"
                tiles[key] = (t["version"], t["points"])
                status, body, headers = self.get(t["url"])
                assert status == 200 and body, (key, status)
                if int(headers.get("x-randt-tile-version", -1)) != t["version"]:
                    return None
                data[key] = body
        sessions = {s["id"]: (s["scans"], s["last_seq"]) for s in self.json("/sessions")}
        return tiles, data, sessions

    def settled(self, quiet_s: float = SETTLE_QUIET_S, timeout_s: float = 180.0) -> Snapshot:
        """The snapshot once it has not changed for ``quiet_s``: after the vehicles stop, the pose
        graph still re-folds tiles (every ``RANDT_GRAPH_REFOLD_S``)."""
        t0 = time.monotonic()
        last, since = None, time.monotonic()
        while True:
            now = self.snapshot()
            if now is None or now != last:
                last, since = now, time.monotonic()
            elif time.monotonic() - since >= quiet_s:
                return now
            assert time.monotonic() - t0 < timeout_s, f"the map did not settle in {timeout_s:.0f} s"
            time.sleep(1.0)


Snapshot = tuple[dict[str, tuple[int, int]], dict[str, bytes], dict[str, tuple[int, int]]] | None


def _graph(stack: Stack) -> dict[str, Any] | None:
    """``/maps/default/graph`` (None while it answers 404)."""
    status, body, _ = stack.get("/maps/default/graph")
    if status == 404:
        return None
    assert status == 200, (status, body[:300])
    graph: dict[str, Any] = json.loads(body)
    return graph


def _same_graph(stack: Stack, before: dict[str, Any], timeout_s: float = 180.0) -> None:
    """The restarted service's graph is the one it had: restored from its log (service/graph_log.py),
    whose keyframes its graph process takes again before it shows them optimized."""
    deadline = time.monotonic() + timeout_s
    while True:
        after = _graph(stack)
        if after is not None and after["revision"] >= before["revision"]:  # noqa: SIM102
            if all(k["pose"] is not None for k in after["keyframes"]):
                break
        assert time.monotonic() < deadline, f"the graph was not restored in {timeout_s:.0f} s: {after}"
        time.sleep(1.0)
    assert after is not None
    assert after["revision"] == before["revision"] and after["placed"] == before["placed"]
    assert after["joined"].keys() == before["joined"].keys()
    kb = {(k["vehicle"], k["session"], k["seq"]): k["pose"] for k in before["keyframes"]}
    ka = {(k["vehicle"], k["session"], k["seq"]): k["pose"] for k in after["keyframes"]}
    assert ka.keys() == kb.keys(), "the graph's keyframes changed"
    worst = max(float(np.abs(np.subtract(ka[key], kb[key])).max()) for key in kb)
    assert worst < 1e-3, f"an optimized keyframe pose moved by {worst:.4f}"


def _adapted_compose(
    tmp: Path,
    project: str,
    base: str,
    router_image: str | None,
    app_image: str,
    http_port: int,
    zenoh_port: int,
) -> tuple[dict[str, Any], list[str]]:
    """The copy of docker/compose.yaml this machine can run, and what was changed (module docstring)."""
    compose = yaml.safe_load(COMPOSE_FILE.read_text())
    out = copy.deepcopy(compose)
    notes = [
        f"project {project!r} (-p), host ports {zenoh_port} (Zenoh) and {http_port} (HTTP), image {app_image}"
    ]
    if "name" in out:
        del out["name"]
        notes.append("top-level `name:` removed: Compose 1.29 rejects it")
    services = out["services"]
    for service in services.values():
        if service.get("image") == compose["services"]["randt"]["image"]:
            service["image"] = app_image
    build = services["randt"]["build"]
    build["context"] = str(REPO)
    build["dockerfile"] = str(REPO / "docker" / "Dockerfile")
    if base != docker_env.OFFICIAL_BASE:
        build.setdefault("args", {})["BASE_IMAGE"] = base
        notes.append(f"build argument BASE_IMAGE={base}")
    if router_image is not None:
        official = services["zenoh"]["image"]
        services["zenoh"]["image"] = router_image
        notes.append(
            f"router {official} (cannot be pulled) replaced by {router_image}: Zenoh's Python"
            " binding in router mode, same flags"
        )
    services["zenoh"]["ports"] = [f"{zenoh_port}:7447"]
    notes.append(
        "the router's REST port (8000) not published: the stand-in has no REST plugin"
        if router_image
        else "the router's REST port not published"
    )
    services["randt"]["ports"] = [f"{http_port}:8080"]
    services["randt"]["environment"]["RANDT_GRAPH_REFOLD_S"] = str(REFOLD_S)
    services["randt"]["environment"]["RANDT_CAPACITY_TARGET"] = "0"
    notes.append(
        "RANDT_CAPACITY_TARGET=0: the smoke test's vehicles pace themselves (--window 1), as the demo's"
    )
    notes.append(
        f"RANDT_GRAPH_REFOLD_S={REFOLD_S} (default 20): the map settles sooner after the vehicles stop"
    )
    fleet = services["fleet"]["command"]
    fleet[fleet.index("--vehicles") + 1] = "2"
    fleet[fleet.index("--duration") + 1] = "3"
    fleet += ["--session", "compose-fleet", "--window", "1", "--azimuth", "1000"]
    notes.append(
        "demo fleet: 2 vehicles, 3 simulated seconds each, 1000 firings per revolution (was 3 x 60 s"
        " at 2000), session compose-fleet"
    )
    return out, notes


class Images:
    """Docker, a daemon and the stack's images (base, router stand-in, the project's image), built
    in a background thread from the moment the deployment tests are collected (``conftest.py``:
    they run last, and the build, mostly waiting on disk and the package index, overlaps the rest of
    the suite). Docker's daemon, when started here, runs at a lower priority (``nice``)."""

    def __init__(self) -> None:
        self.project = f"randtsmoke{os.getpid()}"
        self.app_image = f"randt-smoke/randt-fleet:{os.getpid()}"
        self.router_tag = f"randt-smoke/zenoh-router:{os.getpid()}"
        self.tmp = Path(tempfile.gettempdir())  # its own folder once started
        self.timings: dict[str, float] = {}
        self.notes: list[str] = []
        self.compose_notes: list[str] = []
        self.base = ""
        self.router_image: str | None = None
        self.error: BaseException | None = None
        self._built_base = False
        self._daemon = contextlib.ExitStack()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    def start(self) -> None:
        if self._thread is None:
            self.tmp = Path(tempfile.mkdtemp(prefix="randt-smoke-"))
            self._thread = threading.Thread(target=self._run, name="deploy-images", daemon=True)
            self._thread.start()

    def wait(self, timeout_s: float = 1800.0) -> None:
        """Until the images are built; raises what the build raised."""
        self.start()
        t = time.monotonic()
        if not self._done.wait(timeout_s):
            raise RuntimeError(f"the images were not built in {timeout_s:.0f} s")
        self.timings["waited for the images"] = time.monotonic() - t
        if self.error is not None:
            raise self.error

    def compose_file(self, http_port: int, zenoh_port: int) -> Path:
        """The adapted compose file (module docstring), with these host ports."""
        compose, notes = _adapted_compose(
            self.tmp, self.project, self.base, self.router_image, self.app_image, http_port, zenoh_port
        )
        path = self.tmp / "compose.yaml"
        path.write_text(yaml.safe_dump(compose, sort_keys=False))
        self.compose_notes = notes
        return path

    def _run(self) -> None:
        try:
            self._build()
        except BaseException as exc:  # handed to the fixture, which skips or fails
            self.error = exc
        finally:
            self._done.set()

    def _build(self) -> None:
        t0 = time.monotonic()
        installed = docker_env.ensure_tools()
        started = self._daemon.enter_context(docker_env.daemon(nice=10))
        self.timings["tools and daemon"] = time.monotonic() - t0
        t = time.monotonic()
        self.base, self._built_base, how = docker_env.base_image()
        self.timings["base image"] = time.monotonic() - t
        official_router = yaml.safe_load(COMPOSE_FILE.read_text())["services"]["zenoh"]["image"]
        if not docker_env.image_exists(official_router):
            t = time.monotonic()
            docker_env.build_router(self.base, official_router.split(":", 1)[1], self.router_tag)
            self.router_image = self.router_tag
            self.timings["router image"] = time.monotonic() - t
        self.notes += [
            *(["started dockerd at nice 10 (stopped at the end)"] if started else []),
            *([f"installed from Debian: {', '.join(installed)}"] if installed else []),
            f"base image: {how}",
        ]
        compose_file = self.compose_file(free_port(), free_port())  # the ports are not built in
        t = time.monotonic()
        argv = ["docker-compose", "-f", str(compose_file), "-p", self.project, "build"]
        docker_env.run(argv, timeout=900)
        self.timings["image build"] = time.monotonic() - t

    def close(self, timeout_s: float = 900.0) -> None:
        """Removes the images built here and stops a daemon started here (once; also at session end
        when the tests never ran); a build still running after ``timeout_s`` fails with the daemon."""
        if self._closed or self._thread is None:
            return
        self._closed = True
        self._done.wait(timeout_s)
        if docker_env.daemon_up():
            for tag in (
                self.app_image,
                self.router_tag,
                *((docker_env.LOCAL_BASE_TAG,) if self._built_base else ()),
            ):
                docker_env.run(["docker", "image", "rm", "-f", tag], check=False)
            # the Dockerfile's build stage, which the legacy builder keeps untagged
            docker_env.run(
                ["docker", "image", "prune", "-f", "--filter", "label=org.randt-fleet.stage=build"],
                check=False,
            )
        self._daemon.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


#: Started by ``conftest.py`` when deployment tests are collected; the fixture waits for it.
IMAGES = Images()


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    t0 = time.monotonic()
    try:
        IMAGES.wait()
    except (docker_env.DockerUnavailableError, RuntimeError, subprocess.TimeoutExpired) as exc:
        IMAGES.close()
        if os.environ.get("CI") == "true":
            pytest.fail(f"the deployment smoke test cannot run: {exc}")
        pytest.skip(f"Docker unavailable: {exc}")
    compose_file = IMAGES.compose_file(free_port(), free_port())
    compose = yaml.safe_load(compose_file.read_text())
    zenoh_port = int(compose["services"]["zenoh"]["ports"][0].split(":")[0])
    http_port = int(compose["services"]["randt"]["ports"][0].split(":")[0])
    notes = IMAGES.notes + IMAGES.compose_notes
    stack_ = Stack(
        IMAGES.project, compose_file, http_port, zenoh_port, IMAGES.app_image, IMAGES.router_tag,
        notes, IMAGES.timings,
    )  # fmt: skip
    print("\ndeployment smoke test, adapted to this machine:\n  - " + "\n  - ".join(notes), file=sys.stderr)
    try:
        t = time.monotonic()
        stack_.compose("up", "-d", "zenoh", "randt")
        stack_.wait_healthy()
        IMAGES.timings["up until healthy"] = time.monotonic() - t
        yield stack_
    finally:
        logs = stack_.compose("logs", "--tail", "30", check=False).stdout
        print(f"\nlast compose logs:\n{logs[-4000:]}", file=sys.stderr)
        stack_.compose("--profile", "cluster", "down", "-v", "--remove-orphans", timeout=300, check=False)
        IMAGES.close()
        IMAGES.timings["tests and teardown"] = time.monotonic() - t0
        print(
            "deployment smoke test timings (s): "
            + json.dumps({k: round(v, 1) for k, v in IMAGES.timings.items()}),
            file=sys.stderr,
        )


def _host_vehicle(stack: Stack, tmp_path: Path, session: str = "host") -> dict[str, Any]:
    summary = tmp_path / f"{session}.json"
    done = subprocess.run(
        [
            sys.executable, "-m", "randt.cli",
            "simulate", "--vehicles", "1", "--duration", "3", "--seed", "1",
            "--connect", f"tcp/127.0.0.1:{stack.zenoh_port}", "--session", session, "--window", "1",
            "--azimuth", "1000",
            "--json-out", str(summary), "--no-progress", "--connect-timeout", "60",
        ],
        capture_output=True, text=True, timeout=600, cwd=REPO,
    )  # fmt: skip
    assert done.returncode == 0, f"host vehicle: exit {done.returncode}\n{done.stderr[-3000:]}"
    return json.loads(summary.read_text())


def test_the_image_is_small_non_root_and_has_no_build_tools(stack: Stack) -> None:
    info = json.loads(docker_env.run(["docker", "image", "inspect", stack.app_image]).stdout)[0]
    size_mb = info["Size"] / 1e6
    print(f"\nimage {stack.app_image}: {size_mb:.0f} MB", file=sys.stderr)
    assert info["Config"]["User"] == "randt"
    tools = docker_env.run(
        ["docker", "run", "--rm", "--entrypoint", "sh", stack.app_image, "-c",
         "for t in gcc cc g++ make apt-get; do command -v $t; done; id -u"],
    ).stdout.split()  # fmt: skip
    assert tools[-1] == "10001" and [t for t in tools[:-1] if "apt-get" not in t] == [], tools
    assert size_mb < 2000, f"{size_mb:.0f} MB"


def test_vehicles_on_the_host_and_in_the_compose_network_reach_the_service(
    stack: Stack, tmp_path: Path
) -> None:
    t = time.monotonic()
    host = _host_vehicle(stack, tmp_path)
    stack.timings["host vehicle"] = time.monotonic() - t
    print(f"\nhost vehicle summary: {json.dumps(host)[:600]}", file=sys.stderr)
    t = time.monotonic()
    stack.compose("up", "-d", "fleet")  # started once compose's health check calls the service healthy
    cid = stack.compose("ps", "-a", "-q", "fleet").stdout.strip()
    code = int(docker_env.run(["docker", "wait", cid], timeout=900).stdout.strip())
    fleet_log = docker_env.run(["docker", "logs", cid], check=False)
    stack.timings["fleet container"] = time.monotonic() - t
    assert code == 0, f"fleet container exited {code}:\n{fleet_log.stdout[-2000:]}{fleet_log.stderr[-2000:]}"
    sessions = {s["id"]: s for s in stack.json("/sessions")}
    assert "sim000/host" in sessions, sorted(sessions)
    assert {"sim000/compose-fleet", "sim001/compose-fleet"} <= set(sessions), sorted(sessions)
    for sid in ("sim000/host", "sim000/compose-fleet", "sim001/compose-fleet"):
        s = sessions[sid]
        assert s["scans"] == 30 and s["last_seq"] == 29, s  # 3 s at 10 Hz, every scan answered
    maps = {m["name"]: m for m in stack.json("/maps")["maps"]}
    assert "default" in maps
    tiles = stack.json("/maps/default/tiles")["tiles"]
    assert len(tiles) >= 4 and sum(t["points"] for t in tiles) > 10_000
    status, body, headers = stack.get(tiles[0]["url"])
    assert status == 200 and b"FIELDS x y z" in body[:200], body[:80]  # a PCD file
    # the ETag names the version downloaded (the graph may have re-folded the tile since the index)
    assert headers.get("etag", "").startswith(f'"{headers["x-randt-tile-version"]}-'), headers


def test_restart_and_down_up_keep_every_tile_and_session(stack: Stack) -> None:
    before = stack.settled()
    assert before is not None and before[0] and before[2], "nothing mapped: the previous test did not run"
    graph = _graph(stack)
    assert graph is not None and len(graph["keyframes"]) >= 3, graph
    t = time.monotonic()
    stack.compose("restart", "randt", timeout=300)
    stack.wait_healthy()
    stack.timings["restart"] = time.monotonic() - t
    after = stack.snapshot()
    assert after is not None
    assert after[0] == before[0], "tiles (id -> version, points) changed across a restart"
    assert after[1] == before[1], "tile bytes changed across a restart"
    assert after[2] == before[2], "sessions changed across a restart"
    _same_graph(stack, graph)
    t = time.monotonic()
    stack.compose("down", timeout=300)
    stack.compose("up", "-d", "zenoh", "randt")
    stack.wait_healthy()
    stack.timings["down and up"] = time.monotonic() - t
    again = stack.snapshot()
    assert again == before, "down + up lost or changed a tile or a session"
    _same_graph(stack, graph)


def test_the_cluster_profile_matches_on_a_ray_worker(stack: Stack, tmp_path: Path) -> None:
    """Profile ``cluster``, for real: a Ray head (0 CPUs) and one worker, the service recreated
    with ``RANDT_EXECUTOR=ray`` (a Ray Client of the head); a vehicle on the host gets every scan
    answered, so its matcher ran on the worker (the only node with CPUs, so the only one with
    matcher hosts), and the sessions mapped before are still there."""
    before = {s["id"] for s in stack.json("/sessions")}
    t = time.monotonic()
    stack.compose("--profile", "cluster", "up", "-d", "ray-head", "ray-worker")
    stack.compose("up", "-d", "randt", env={"RANDT_EXECUTOR": "ray"})  # recreated: its environment changed
    stack.wait_healthy()
    stack.timings["cluster up"] = time.monotonic() - t
    t = time.monotonic()
    summary = _host_vehicle(stack, tmp_path, session="host-ray")
    stack.timings["vehicle through Ray"] = time.monotonic() - t
    (vehicle,) = summary["vehicles"]
    assert vehicle["stats"]["acknowledged"] == 30, vehicle["stats"]
    sessions = {s["id"]: s for s in stack.json("/sessions")}
    assert sessions["sim000/host-ray"]["scans"] == 30, sessions["sim000/host-ray"]
    assert before <= set(sessions)
    cid = stack.container("randt")
    env = docker_env.run(["docker", "inspect", "--format", "{{json .Config.Env}}", cid]).stdout
    assert "RANDT_EXECUTOR=ray" in env
    workers = stack.compose("--profile", "cluster", "ps", "-q", "ray-worker").stdout.split()
    assert len(workers) == 1
    # the worker node runs the matcher hosts (Ray's worker processes are named after the actor class)
    procs = docker_env.run(["docker", "top", workers[0], "-eo", "pid,args"]).stdout
    assert "_MatcherHost" in procs, procs[-2000:]
