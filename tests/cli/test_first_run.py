"""A new user's first run: Ctrl-C, busy ports and data directories, wrong paths, ``--help``, ``config``.

Each test runs ``randt`` as a user does (a subprocess) and checks the one line and the exit code
the README's table documents (``randt.cli.errors.ExitCode``).
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from randt.cli.errors import ExitCode
from tests.service.conftest import free_port

RANDT = [sys.executable, "-m", "randt.cli"]


def _randt(*args: str, timeout: float = 120, **kwargs: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*RANDT, *args], capture_output=True, text=True, timeout=timeout, **kwargs)


def _one_error_line(proc: subprocess.CompletedProcess[str]) -> str:
    """stderr must be exactly one ``randt: error: ...`` line; returns it."""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("randt: error: "), proc.stderr
    return lines[0]


@pytest.fixture
def busy_port() -> Iterator[int]:
    """A loopback TCP port with a listener on it (as another program would hold it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


# -- Ctrl-C ------------------------------------------------------------------------------------


def _wait_ready(base: str, proc: subprocess.Popen[str], timeout_s: float = 90) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[1]
        try:
            if httpx.get(f"{base}/readyz", timeout=1).json().get("ready"):
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    pytest.fail("randt serve did not become ready")


def test_ctrl_c_on_serve_prints_no_traceback_from_the_matcher_processes(tmp_path: Path) -> None:
    """Ctrl-C in a terminal signals the whole foreground process group: the matcher processes too."""
    hport, zport = free_port(), free_port()
    proc = subprocess.Popen(
        [*RANDT, "serve", "--data-dir", str(tmp_path / "data"), "--listen", f"tcp/127.0.0.1:{zport}",
         "--http-port", str(hport)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, "RANDT_MATCHER_PROCESSES": "2"},
    )  # fmt: skip
    try:
        _wait_ready(f"http://127.0.0.1:{hport}", proc)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "service randt-1 stopped" in err and "store closed" in err
    assert proc.returncode == ExitCode.OK, err


def test_sigterm_to_the_process_group_saves_every_session(tmp_path: Path) -> None:
    """systemd stops a service by SIGTERM to its whole control group (``kill -- -PGID`` alike): the
    matcher and graph processes get it too, and must leave the stopping to the service, which
    saves its sessions. Before, the matchers died first and no session was saved."""
    hport, zport = free_port(), free_port()
    data = tmp_path / "data"
    proc = subprocess.Popen(
        [*RANDT, "serve", "--data-dir", str(data), "--listen", f"tcp/127.0.0.1:{zport}",
         "--http-port", str(hport)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, "RANDT_MATCHER_PROCESSES": "2", "RANDT_CAPACITY_TARGET": "0"},
    )  # fmt: skip
    try:
        _wait_ready(f"http://127.0.0.1:{hport}", proc)
        drive = _randt(
            "simulate", "--vehicles", "2", "--duration", "1.5", "--connect", f"tcp/127.0.0.1:{zport}",
            "--azimuth", "500", "--no-progress", "--connect-timeout", "60", timeout=300,
        )  # fmt: skip
        assert drive.returncode == 0, drive.stderr[-2000:]
        sessions = httpx.get(f"http://127.0.0.1:{hport}/sessions", timeout=10).json()
        assert len(sessions) == 2 and all(s["state"] == "active" for s in sessions), sessions
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert "Traceback" not in err and "matcher process died" not in err and "not saved" not in err, err
    assert "service randt-1 stopped" in err and "store closed" in err
    # uvicorn raises the signal again once shut down: the status says SIGTERM (systemd's default
    # SuccessExitStatus counts it clean; docker shows 143)
    assert proc.returncode == -signal.SIGTERM, err
    saved = [json.loads(p.read_text()) for p in sorted(data.glob("sessions/*/*/session.json"))]
    assert len(saved) == 2 and all(s["n_scans"] == 15 for s in saved), saved


# -- busy ports, a data directory in use -------------------------------------------------------


def _serve_fails_before_starting(tmp_path: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], str]:
    data = tmp_path / "data"
    tic = time.monotonic()
    proc = _randt("serve", "--data-dir", str(data), *args, timeout=60)
    line = _one_error_line(proc)
    # checked before anything starts: no store opened (no lock file), no matcher process warmed up
    assert not (data / ".randt-store.lock").exists()
    assert time.monotonic() - tic < 15
    return proc, line


def test_busy_http_port_is_one_line_before_anything_starts(tmp_path: Path, busy_port: int) -> None:
    proc, line = _serve_fails_before_starting(
        tmp_path, "--http-port", str(busy_port), "--listen", f"tcp/127.0.0.1:{free_port()}"
    )
    assert proc.returncode == ExitCode.PORT_IN_USE
    assert f"HTTP port 127.0.0.1:{busy_port} is in use" in line and "--http-port" in line


def test_busy_zenoh_port_is_one_line_before_anything_starts(tmp_path: Path, busy_port: int) -> None:
    proc, line = _serve_fails_before_starting(
        tmp_path, "--http-port", str(free_port()), "--listen", f"tcp/127.0.0.1:{busy_port}"
    )
    assert proc.returncode == ExitCode.PORT_IN_USE
    assert f"Zenoh endpoint tcp/127.0.0.1:{busy_port} is in use" in line and "--listen" in line


def test_data_directory_in_use_is_one_line(tmp_path: Path) -> None:
    from randt.service.store import Store

    data = tmp_path / "data"
    store = Store(data)  # this test process holds the directory, as a running service would
    try:
        tic = time.monotonic()
        proc = _randt(
            "serve", "--data-dir", str(data), "--http-port", str(free_port()),
            "--listen", f"tcp/127.0.0.1:{free_port()}", timeout=60,
        )  # fmt: skip
        line = _one_error_line(proc)
        assert time.monotonic() - tic < 15
    finally:
        store.close()
    assert proc.returncode == ExitCode.DATA_DIR_IN_USE
    assert f"data directory {data.resolve()} is already open in another process" in line


# -- paths of the wrong kind -------------------------------------------------------------------


def test_a_directory_where_a_file_is_expected_says_so(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    cloud = tmp_path / "a.npy"
    import numpy as np

    np.save(cloud, np.random.default_rng(0).normal(size=(100, 3)))
    for args in (
        ("register", str(folder), str(cloud)),
        ("register", str(cloud), str(folder)),
        ("eval", "--reference", str(folder), "--estimate", str(cloud)),
    ):
        proc = _randt(*args)
        line = _one_error_line(proc)
        assert proc.returncode == ExitCode.WRONG_INPUT, args
        assert f"{folder} is a directory, expected a file" in line, args


def test_a_folder_without_scans_says_so(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.md").write_text("no scans here\n")
    for args in (
        ("map", str(empty), "--out", str(tmp_path / "out"), "--no-progress"),
        ("replay", str(empty), "--vehicle", "car1", "--connect-timeout", "1", "--no-progress"),
    ):
        proc = _randt(*args)
        line = _one_error_line(proc)
        assert proc.returncode == ExitCode.WRONG_INPUT, (args, proc.stderr)
        assert f"{empty}: no scan files" in line, args
    assert not (tmp_path / "out").exists()


# -- --help and randt config -------------------------------------------------------------------


def _all_commands() -> list[list[str]]:
    from typer.main import get_command

    from randt.cli.main import app

    group = get_command(app)
    found: list[list[str]] = [[]]

    def walk(cmd: object, path: list[str]) -> None:
        for name, sub in getattr(cmd, "commands", {}).items():
            found.append([*path, name])
            walk(sub, [*path, name])

    walk(group, [])
    return found


def test_every_help_shows_real_defaults_and_no_placeholders() -> None:
    from randt.service.settings import ServiceSettings

    commands = _all_commands()
    assert ["serve"] in commands and ["tiles", "export"] in commands and len(commands) >= 16
    helps = {}
    for path in commands:
        proc = _randt(*path, "--help", timeout=60, env={**os.environ, "COLUMNS": "200"})
        assert proc.returncode == 0, (path, proc.stderr)
        text = proc.stdout
        helps[" ".join(path)] = text
        assert "<bool>" not in text, path
        assert not re.search(r"\S \.(\s|$)", text), (path, re.findall(r".{30}\S \.(?:\s|$)", text))
        assert not re.search(r"\[env(?!\s+var:)", text), (path, "the env var is click's [env var: ...] only")
    serve = helps["serve"]
    defaults = ServiceSettings()
    for option, field in (
        ("--data-dir", "data_dir"),
        ("--zenoh-mode", "zenoh_mode"),
        ("--listen", "listen"),
        ("--connect", "connect"),
        ("--http-host", "http_host"),
        ("--http-port", "http_port"),
        ("--zenoh-config", "zenoh_config"),
    ):
        value = getattr(defaults, field)
        shown = ", ".join(value) if isinstance(value, tuple) else str(value or "")
        row = re.search(rf"^\s+{option} .*?(?=^\s+--)", serve, flags=re.M | re.S)
        assert row, (option, serve)
        text = " ".join(row[0].split())
        assert f"default: {shown or '(none)'}" in text, (option, text)
        assert f"env var: RANDT_{field.upper()}" in text, (option, text)
    for command in ("replay", "simulate"):
        text = " ".join(helps[command].split())
        assert "default: tcp/127.0.0.1:7447; env var: RANDT_VEHICLE_CONNECT" in text, command
        assert "default: client; env var: RANDT_VEHICLE_MODE" in text, command
        assert "default: (none); env var: RANDT_VEHICLE_ZENOH_CONFIG" in text, command
    top = " ".join(helps[""].split())
    for code in ExitCode:
        assert re.search(rf"\b{int(code)}\b", top), f"exit code {int(code)} is in randt --help"


def test_config_prints_every_settings_group_with_defaults_and_env_vars() -> None:
    from randt.clients.fleet import FleetSettings
    from randt.clients.publisher import PublisherSettings
    from randt.core.config import RegistrationSettings
    from randt.core.odometry import MATCHER_REGISTRATION, MatcherSettings
    from randt.service.settings import ServiceSettings

    proc = _randt("config", "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert {"registration", "matcher", "service", "publisher", "fleet"} <= doc.keys()
    assert doc["registration"]["defaults"] == json.loads(RegistrationSettings().model_dump_json())
    assert doc["matcher"]["defaults"]["keyframe_distance_m"] == MatcherSettings().keyframe_distance_m
    service = ServiceSettings()
    assert doc["service"]["defaults"]["http_port"] == service.http_port == 8080
    assert doc["service"]["env"]["data_dir"] == "RANDT_DATA_DIR"
    assert doc["service"]["env"]["max_sessions"] == "RANDT_MAX_SESSIONS"
    assert doc["publisher"]["env"]["connect"] == "RANDT_VEHICLE_CONNECT"
    assert doc["publisher"]["defaults"]["connect"] == list(PublisherSettings().connect)
    assert doc["service"]["env"]["zenoh_config"] == "RANDT_ZENOH_CONFIG"
    assert doc["publisher"]["env"]["zenoh_config"] == "RANDT_VEHICLE_ZENOH_CONFIG"
    assert doc["service"]["defaults"]["zenoh_config"] is None
    assert doc["fleet"]["defaults"]["n_azimuth"] == FleetSettings().n_azimuth and not doc["fleet"]["env"]
    text = _randt("config").stdout
    assert re.search(r"^\[service\]", text, flags=re.M) and re.search(r"^\[matcher\]", text, flags=re.M)
    assert re.search(r"^http_port\s+8080\s+RANDT_HTTP_PORT\b", text, flags=re.M), text
    assert re.search(r"^iqr_k\s+1\.5\s+-\s", text, flags=re.M), text  # randt register's: no env
    # The service's matcher registration starts from the matcher's defaults (Algorithms 1 and 3 off).
    served = doc["service.registration"]
    assert served["defaults"] == json.loads(MATCHER_REGISTRATION.model_dump_json())
    assert served["defaults"]["svd_refinement"] is False and doc["registration"]["defaults"]["svd_refinement"]
    assert served["env"]["iqr_k"] == "RANDT_REGISTRATION__IQR_K"


def test_config_groups_follow_the_models() -> None:
    """A group nested in a settings model later (e.g. the service's matcher) shows up by itself."""
    from pydantic import BaseModel, Field
    from pydantic_settings import BaseSettings, SettingsConfigDict

    from randt.cli.config import SettingRow, settings_groups

    class Inner(BaseModel):
        depth_m: float = Field(default=2.5, description="how deep")

    class Outer(BaseSettings):
        model_config = SettingsConfigDict(env_prefix="X_", env_nested_delimiter="__")
        name: str = "a"
        inner: Inner = Inner()

    groups = {g.name: g for g in settings_groups({"outer": Outer, "inner": Inner})}
    assert list(groups) == ["outer", "inner"], "a nested model is its own group, listed once"
    assert groups["outer"].rows == (SettingRow("name", "a", "X_NAME", ""),)
    assert groups["inner"].rows == (SettingRow("depth_m", 2.5, "X_INNER__DEPTH_M", "how deep"),)
    assert groups["inner"].env_note == "env prefix X_INNER__"


def test_the_readme_documents_every_exit_code() -> None:
    from randt.cli.errors import DESCRIPTIONS

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    rows = dict(re.findall(r"^\| (\d+) \| (.+?) \|$", readme, flags=re.M))
    assert {int(k): v for k, v in rows.items()} == {int(c): t for c, t in DESCRIPTIONS.items()}


def test_output_piped_into_a_reader_that_leaves_ends_quietly() -> None:
    """``randt config | head -1``: the reader has closed the pipe; no error line, code 141.

    The read end is closed right after the start, long before the interpreter has imported
    enough to print (a reader that takes one line first races with this small output)."""
    proc = subprocess.Popen(
        [*RANDT, "config"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=Path.cwd()
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()
    rc = proc.wait(timeout=60)
    err = proc.stderr.read()
    assert rc == ExitCode.BROKEN_PIPE == 141, err
    assert "error" not in err and "Traceback" not in err, err


def test_security_init_writes_a_deployment_and_serve_refuses_a_bad_zenoh_config(tmp_path: Path) -> None:
    """``randt security init`` (the recipe of docs/security.md) and a wrong ``--zenoh-config``."""
    target = tmp_path / "zenoh"
    proc = _randt("security", "init", str(target), "--vehicle", "car-01", "--host", "fleet.example.org")
    assert proc.returncode == 0, proc.stderr
    assert (target / "service.json5").is_file() and (target / "vehicle-car-01.json5").is_file()
    again = _randt("security", "init", str(target), "--vehicle", "car-01")
    assert again.returncode == ExitCode.INVALID_VALUE
    assert "is not empty" in _one_error_line(again)
    reserved = _randt("security", "init", str(tmp_path / "other"), "--vehicle", "ca")
    assert reserved.returncode == ExitCode.INVALID_VALUE and "reserved" in _one_error_line(reserved)
    bad = tmp_path / "bad.json5"
    bad.write_text("{transport: {link: {tls: {server_certificate: 1}}}}")
    for config, reason in ((tmp_path / "missing.json5", "does not exist"), (bad, "unknown field")):
        proc = _randt("serve", "--data-dir", str(tmp_path / "data"), "--zenoh-config", str(config))
        assert proc.returncode == ExitCode.INVALID_VALUE, proc.stderr
        line = _one_error_line(proc)
        assert "zenoh_config" in line and reason in line, line
    # the generated TLS-only config with a tcp endpoint: one line naming both (issue 32: exit 3
    # and a 52-line traceback from Zenoh's session)
    tls_only = target / "service.json5"
    proc = _randt("serve", "--data-dir", str(tmp_path / "data"), "--listen", "tcp/127.0.0.1:17447",
                  "--zenoh-config", str(tls_only))  # fmt: skip
    assert proc.returncode == ExitCode.INVALID_VALUE, proc.stderr
    line = _one_error_line(proc)
    assert "tcp/127.0.0.1:17447 uses tcp" in line and "tls/127.0.0.1:17447" in line, line
    assert not (tmp_path / "data").exists()  # refused before anything started
