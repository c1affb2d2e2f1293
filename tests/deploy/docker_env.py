"""What the deployment smoke test (``tests/deploy/test_compose_smoke.py``) needs from the machine:
Docker and Compose (installed from Debian's packages when absent), a running daemon (started, and
later stopped, only when none runs), and base images where no registry can be reached.

Images the test cannot pull are built locally:

- ``python:3.11-slim``: ``../shared/tools/docker-local-base.sh`` builds a stand-in from Debian's
  packages (``RANDT_DOCKER_BASE`` names another image to use instead);
- ``eclipse/zenoh:<version>``: a router image built on that base with Zenoh's Python binding, in
  router mode, taking the official image's flags (``--listen``, ``--no-multicast-scouting``;
  ``--rest-http-port`` is accepted but the REST plugin is not in the Python binding).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
LOCAL_BASE_SCRIPT = REPO.parent / "shared" / "tools" / "docker-local-base.sh"
LOCAL_BASE_TAG = "randt-local/python:3.11-slim"
OFFICIAL_BASE = "python:3.11-slim"


class DockerUnavailableError(Exception):
    """Docker cannot be set up on this machine (the reason is the message)."""


def run(
    argv: list[str], *, timeout: float = 600.0, check: bool = True, **kw: object
) -> subprocess.CompletedProcess[str]:
    """A command with its output captured; on failure the error names the command and its stderr."""
    done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kw)  # type: ignore[call-overload]
    if check and done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(argv)} exited {done.returncode}:\n{done.stderr[-3000:]}{done.stdout[-2000:]}"
        )
    return done


def daemon_up() -> bool:
    """Whether a Docker daemon answers (False also when the CLI is missing)."""
    if shutil.which("docker") is None:
        return False
    return subprocess.run(["docker", "info"], capture_output=True, timeout=60).returncode == 0


def ensure_tools() -> list[str]:
    """Docker's CLI and daemon, Compose and debootstrap; installed with apt-get when absent (as
    root). Returns what was installed."""
    missing = [p for p, exe in (("docker.io", "dockerd"), ("docker-compose", "docker-compose"),
                                ("debootstrap", "debootstrap")) if shutil.which(exe) is None]  # fmt: skip
    if missing:
        if shutil.which("apt-get") is None or os.geteuid() != 0:
            raise DockerUnavailableError(f"{', '.join(missing)} missing and apt-get (as root) unavailable")
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        run(["apt-get", "update", "-qq"], env=env)
        run(["apt-get", "install", "-y", "-qq", *missing], env=env)
    return missing


@contextlib.contextmanager
def daemon(nice: int = 0) -> Iterator[bool]:
    """A running Docker daemon; yields whether this process started it (then it is stopped after).
    ``nice``: the priority of one started here, and so of its builds and containers."""
    if daemon_up():
        yield False
        return
    if os.geteuid() != 0:
        raise DockerUnavailableError("no Docker daemon runs and only root can start one")
    log = tempfile.NamedTemporaryFile(prefix="randt-dockerd-", suffix=".log", delete=False)  # noqa: SIM115
    proc = subprocess.Popen(
        ["nice", "-n", str(nice), "dockerd"], stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 60.0
        while not daemon_up():
            if proc.poll() is not None or time.monotonic() > deadline:
                raise DockerUnavailableError(f"dockerd did not start: {Path(log.name).read_text()[-2000:]}")
            time.sleep(0.5)
        yield True
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
        os.unlink(log.name)


def image_exists(tag: str) -> bool:
    return (
        subprocess.run(["docker", "image", "inspect", tag], capture_output=True, timeout=60).returncode == 0
    )


def base_image() -> tuple[str, bool, str]:
    """(tag, built here, how): ``RANDT_DOCKER_BASE``, else the official image when this machine has
    it, else the local stand-in (built now unless it exists)."""
    override = os.environ.get("RANDT_DOCKER_BASE")
    if override:
        return override, False, f"RANDT_DOCKER_BASE={override}"
    if image_exists(OFFICIAL_BASE):
        return OFFICIAL_BASE, False, f"the official {OFFICIAL_BASE}"
    if image_exists(LOCAL_BASE_TAG):
        return LOCAL_BASE_TAG, False, f"{LOCAL_BASE_TAG} (already built from Debian's packages)"
    if not LOCAL_BASE_SCRIPT.is_file():
        raise DockerUnavailableError(
            f"{OFFICIAL_BASE} cannot be pulled here and {LOCAL_BASE_SCRIPT} is missing"
        )
    run(["nice", "-n", "10", "bash", str(LOCAL_BASE_SCRIPT), LOCAL_BASE_TAG], timeout=900)
    return (
        LOCAL_BASE_TAG,
        True,
        f"{LOCAL_BASE_TAG}, built now from Debian's packages ({OFFICIAL_BASE} cannot be pulled)",
    )


ROUTER_SCRIPT = '''\
"""A Zenoh router taking eclipse/zenoh's flags (the smoke test's stand-in for the official image)."""
import argparse, json, signal, threading
import zenoh

parser = argparse.ArgumentParser()
parser.add_argument("--listen", action="append", default=[])
parser.add_argument("--no-multicast-scouting", action="store_true")
parser.add_argument("--rest-http-port")  # the REST plugin is not in the Python binding
args = parser.parse_args()
config = zenoh.Config()
config.insert_json5("mode", '"router"')
config.insert_json5("listen/endpoints", json.dumps(args.listen))
config.insert_json5("scouting/multicast/enabled", json.dumps(not args.no_multicast_scouting))
session = zenoh.open(config)
print("router listening on", args.listen, flush=True)
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
signal.signal(signal.SIGINT, lambda *_: stop.set())
stop.wait()
session.close()
'''


def build_router(base: str, zenoh_version: str, tag: str) -> None:
    """The router stand-in: ``base`` with ``eclipse-zenoh==zenoh_version`` in router mode."""
    with tempfile.TemporaryDirectory(prefix="randt-router-") as tmp:
        Path(tmp, "router.py").write_text(ROUTER_SCRIPT)
        Path(tmp, "Dockerfile").write_text(
            f"FROM {base}\n"
            "ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1\n"
            f'RUN python -m venv /opt/zenoh && /opt/zenoh/bin/pip install "eclipse-zenoh=={zenoh_version}"\n'
            "COPY router.py /router.py\n"
            'ENTRYPOINT ["/opt/zenoh/bin/python", "-u", "/router.py"]\n'
        )
        run(["docker", "build", "-q", "-t", tag, tmp], timeout=600)
