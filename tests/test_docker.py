"""The docker deployment (``docker/``) agrees with the Compose spec, the project's CLI, settings and app.

No Docker daemon is used (the build machine has none): ``docker/compose.yaml`` is validated against
the official Compose JSON schema (``../shared/schemas/compose-spec.json`` or
``$RANDT_COMPOSE_SCHEMA``; absent, the test skips, or fails under ``CI=true``); every ``randt``
command line the deployment runs is parsed by the real click command and its settings built;
every ``RANDT_*`` variable it sets is a ``ServiceSettings`` field that accepts the value; the
HEALTHCHECKs are run against the real app; ``.dockerignore`` sends what ``pip install .`` needs.
"""

from __future__ import annotations

import copy
import json
import os
import re
import shlex
import subprocess
import sys
from enum import Enum
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import typer
import yaml
from typer.main import get_command

from randt.cli.main import app as randt_app
from randt.cli.serve import SETTINGS_OPTIONS, with_ros2
from randt.clients.publisher import PublisherSettings
from randt.service.app import create_app
from randt.service.settings import ServiceSettings
from randt.wire.zenoh_config import zenoh_config
from tests.service.api_server import live_server
from tests.service.conftest import free_port

REPO = Path(__file__).resolve().parents[1]
COMPOSE_FILE = REPO / "docker" / "compose.yaml"
DOCKERFILE = REPO / "docker" / "Dockerfile"
SCHEMA_ENV_VAR = "RANDT_COMPOSE_SCHEMA"
#: click's UsageError, whichever click typer runs on (its own copy since typer 0.2x, else click).
USAGE_ERROR = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")
#: A value for variables the compose file passes through from the host (``KEY:`` with no value).
PASS_THROUGH = {"RANDT_API_TOKEN": "a-token-of-at-least-16-chars"}


# -- reading the files -----------------------------------------------------------------------------


def _compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE_FILE.read_text())


def _dockerfile_stages() -> tuple[dict[str, str], list[list[tuple[str, str]]]]:
    """Global ``ARG`` defaults and each stage's ``(INSTRUCTION, arguments)``, continuations joined."""
    lines: list[str] = []
    pending = ""
    for raw in DOCKERFILE.read_text().splitlines():
        if raw.lstrip().startswith("#") or not raw.strip():
            continue  # comments may sit inside continuations too
        pending += raw.rstrip()
        if pending.endswith("\\"):
            pending = pending[:-1] + " "
            continue
        lines.append(pending.strip())
        pending = ""
    global_args: dict[str, str] = {}
    stages: list[list[tuple[str, str]]] = []
    for line in lines:
        word, _, rest = line.partition(" ")
        word = word.upper()
        if word == "FROM":
            stages.append([])
        if stages:
            stages[-1].append((word, rest.strip()))
        elif word == "ARG":
            name, _, default = rest.strip().partition("=")
            global_args[name] = default
    return global_args, stages


def _final_stage() -> dict[str, Any]:
    """What the image runs with: ENV, EXPOSE, VOLUME, HEALTHCHECK, CMD of the last stage."""
    _, stages = _dockerfile_stages()
    out: dict[str, Any] = {"env": {}, "expose": [], "volumes": [], "healthcheck": None, "cmd": None}
    for word, rest in stages[-1]:
        if word == "ENV":
            for token in shlex.split(rest):
                key, eq, value = token.partition("=")
                assert eq, f"ENV {rest!r}: use the KEY=VALUE form"
                out["env"][key] = value
        elif word == "EXPOSE":
            out["expose"] += [int(p.split("/")[0]) for p in rest.split()]
        elif word == "VOLUME":
            out["volumes"] += json.loads(rest) if rest.startswith("[") else rest.split()
        elif word == "HEALTHCHECK":
            _, cmd, exec_form = rest.partition(" CMD ")
            assert cmd, f"HEALTHCHECK {rest!r}: expected options then CMD [...]"
            out["healthcheck"] = json.loads(exec_form)
        elif word == "CMD":
            out["cmd"] = json.loads(rest)
        assert word != "ENTRYPOINT", "the image has no ENTRYPOINT: compose commands start with `randt`"
    return out


def _our_services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Services running the image built from docker/Dockerfile (built here or by another service)."""
    services = compose["services"]
    built = {s["image"] for s in services.values() if "build" in s}
    return {name: s for name, s in services.items() if "build" in s or s.get("image") in built}


def _argv(service: dict[str, Any]) -> list[str]:
    command = service.get("command", _final_stage()["cmd"])
    return shlex.split(command) if isinstance(command, str) else [str(a) for a in command]


def _environment(service: dict[str, Any], choices: dict[str, str] | None = None) -> dict[str, str]:
    """The container's RANDT_* environment: the image's ENV, then the service's (pass-through
    filled; interpolated variables from ``choices`` or their defaults)."""
    choices = choices or {}
    env = {k: v for k, v in _final_stage()["env"].items() if k.startswith("RANDT_")}
    declared = service.get("environment") or {}
    if isinstance(declared, list):
        declared = dict(item.split("=", 1) if "=" in item else (item, None) for item in declared)
    for key, value in declared.items():
        if value is None:
            assert key in PASS_THROUGH, f"{key} is passed through from the host: give the test a value"
            env[key] = PASS_THROUGH[key]
        else:
            assert not isinstance(value, bool), f"{key}: quote booleans in compose environments"
            env[key] = _interpolated(key, str(value), choices)
    return env


def _interpolated(key: str, value: str, choices: dict[str, str]) -> str:
    """``value`` as Compose hands it over: ``${KEY:-default}`` (the only interpolation allowed, of
    the variable itself, with a default) is ``choices[KEY]`` when given, else the default."""
    m = re.fullmatch(r"\$\{(\w+):-([^}]+)\}", value)
    if m is None:
        assert "$" not in value, f"{key}: only ${{{key}:-default}} (an unset ${{VAR:-}} is an empty value)"
        return value
    assert m.group(1) == key, f"{key}: interpolate {key} itself, not {m.group(1)}"
    return choices.get(key, m.group(2))


def _set_environment(monkeypatch: pytest.MonkeyPatch, env: dict[str, str]) -> None:
    for key in list(os.environ):
        if key.startswith("RANDT_"):
            monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, value)


def _parse(argv: list[str]) -> tuple[str, dict[str, Any]]:
    """Parse a ``randt ...`` command line with the real click command, without running it."""
    assert argv[0] == "randt", f"expected a randt command line, got {argv}"
    group = get_command(randt_app)
    ctx = group.make_context("randt", argv[1:])
    protected = ctx._protected_args if hasattr(ctx, "_protected_args") else ctx.protected_args
    rest = [*protected, *ctx.args]
    name, command, args = group.resolve_command(ctx, rest)
    assert command is not None and not hasattr(command, "resolve_command"), f"not a command: {argv}"
    sub = command.make_context(name, args, parent=ctx)
    return str(name), sub.params


def _flags(params: dict[str, Any], *names: str) -> dict[str, Any]:
    """The given options as the CLI hands them to the settings: only those set (an empty list is
    unset), lists as tuples, enums as their values."""
    out = {}
    for name in names:
        value = params[name]
        if value is None or (isinstance(value, list | tuple) and not value):
            continue
        if isinstance(value, list | tuple):
            value = tuple(value)
        out[name] = value.value if isinstance(value, Enum) else value
    return out


def _router_port(compose: dict[str, Any]) -> tuple[str, int]:
    """The router service's name and the TCP port it listens on (``--listen tcp/0.0.0.0:PORT``)."""
    (name, router), *others = [
        (n, s) for n, s in compose["services"].items() if "zenoh" in s.get("image", "")
    ]
    assert not others, "one router"
    argv = router["command"]
    endpoint = argv[argv.index("--listen") + 1]
    m = re.fullmatch(r"tcp/0\.0\.0\.0:(\d+)", endpoint)
    assert m, f"the router listens on every interface: {endpoint}"
    return name, int(m.group(1))


# -- (a) the Compose specification ----------------------------------------------------------------


def _schema() -> dict[str, Any]:
    override = os.environ.get(SCHEMA_ENV_VAR)
    path = Path(override) if override else REPO.parent / "shared" / "schemas" / "compose-spec.json"
    if not path.is_file():
        message = (
            f"Compose JSON schema missing: {path} does not exist (set {SCHEMA_ENV_VAR}; without it the "
            "default is <repo root>/../shared/schemas/compose-spec.json)"
        )
        if os.environ.get("CI") == "true":
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    return json.loads(path.read_text())


def test_compose_file_is_valid_against_the_compose_spec() -> None:
    schema = _schema()
    assert "draft-07" in schema.get("$schema", ""), "the Compose spec is a draft-07 JSON schema"
    jsonschema.Draft7Validator.check_schema(schema)
    validator = jsonschema.Draft7Validator(schema)
    compose = _compose()
    errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(compose)]
    assert not errors, errors
    # the schema has teeth: a misspelt key and a wrong type are refused
    broken = copy.deepcopy(compose)
    broken["services"]["randt"]["restrat"] = "always"
    assert not validator.is_valid(broken)
    broken = copy.deepcopy(compose)
    broken["services"]["randt"]["depends_on"] = {"zenoh": {"condition": "service_ready"}}
    assert not validator.is_valid(broken)
    assert set(compose["services"]) == {"zenoh", "randt", "fleet", "ray-head", "ray-worker"}
    assert compose["services"]["fleet"]["profiles"] == ["demo"]
    assert compose["services"]["ray-head"]["profiles"] == compose["services"]["ray-worker"]["profiles"]
    assert compose["services"]["ray-head"]["profiles"] == ["cluster"]
    assert "profiles" not in compose["services"]["randt"] and "profiles" not in compose["services"]["zenoh"]


def test_build_context_and_zenoh_versions_agree() -> None:
    compose = _compose()
    build = compose["services"]["randt"]["build"]
    context = (COMPOSE_FILE.parent / build["context"]).resolve()
    assert context == REPO
    assert (context / build["dockerfile"]).resolve() == DOCKERFILE
    assert (context / ".dockerignore").is_file()
    global_args, stages = _dockerfile_stages()
    # every stage on the base image argument, the official Python 3.11 image by default
    assert global_args["BASE_IMAGE"] == "python:3.11-slim"
    assert all(rest.split()[0] == "${BASE_IMAGE}" for word, rest in (s[0] for s in stages))
    # the router image, the build argument and the Dockerfile's default pin the same Zenoh 1.x
    image = compose["services"]["zenoh"]["image"]
    assert image.startswith("eclipse/zenoh:"), image
    tag = image.split(":", 1)[1]
    assert re.fullmatch(r"1\.\d+\.\d+", tag), f"pin a released 1.x tag, not {tag!r}"
    assert build["args"]["ZENOH_VERSION"] == tag == global_args["ZENOH_VERSION"]
    from importlib.metadata import version

    assert version("eclipse-zenoh").split(".")[0] == tag.split(".")[0], "the project's binding is Zenoh 1.x"


def test_the_images_zenoh_pin_meets_the_projects_bounds() -> None:
    """The image installs the project with ``eclipse-zenoh==ZENOH_VERSION``: a pin outside
    pyproject's bounds (raised there only after the tests pass on it) would not install."""
    import tomllib

    from packaging.requirements import Requirement

    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    bounds = {r.name: r.specifier for r in map(Requirement, deps)}
    pinned = _dockerfile_stages()[0]["ZENOH_VERSION"]
    assert bounds["eclipse-zenoh"].contains(pinned), (pinned, str(bounds["eclipse-zenoh"]))
    for name in ("eclipse-zenoh", "numpy", "numba"):  # bounded from above (pyproject's comment)
        assert any(s.operator == "<" for s in bounds[name]), name


# -- (b) the command lines and the environment ----------------------------------------------------


def test_every_randt_command_line_parses_with_the_real_cli(monkeypatch: pytest.MonkeyPatch) -> None:
    compose = _compose()
    router, port = _router_port(compose)
    ours = _our_services(compose)
    assert set(ours) == {"randt", "fleet", "ray-head", "ray-worker"}
    seen = set()
    for name, service in ours.items():
        if _argv(service)[0] == "ray":
            continue  # the Ray nodes: test_the_cluster_profile_runs_a_ray_head_and_workers
        _set_environment(monkeypatch, _environment(service))
        command, params = _parse(_argv(service))
        seen.add(command)
        if command == "serve":  # (as cli/serve.py builds them: its settings options, then --ros2)
            settings = ServiceSettings(**_flags(params, *SETTINGS_OPTIONS))
            if params["ros2"] or params["ros2_connect"]:
                settings = with_ros2(settings, params["ros2_connect"])
            assert settings.zenoh_mode == "client", name
        elif command == "simulate":
            assert params["vehicles"] == 3 and params["duration"] == 60.0
            settings = PublisherSettings(**_flags(params, "mode", "connect"))
            assert settings.mode == "client"
            assert settings.connect == (f"tcp/{router}:{port}",), "the fleet publishes through the router"
        else:
            pytest.fail(f"{name}: no check for `randt {command}`")
    assert seen == {"serve", "simulate"}
    # a wrong flag is refused by the same parser (the check is real)
    with pytest.raises(USAGE_ERROR):
        _parse(["randt", "simulate", "--vehicle", "3"])
    with pytest.raises(typer.BadParameter):
        _parse(["randt", "serve", "--zenoh-mode", "router"])


def test_every_randt_variable_is_a_setting_and_valid(monkeypatch: pytest.MonkeyPatch) -> None:
    compose = _compose()
    router, port = _router_port(compose)
    fields = set(ServiceSettings.model_fields)
    image_env = {k: v for k, v in _final_stage()["env"].items() if k.startswith("RANDT_")}
    # the image on its own (docker run): a standalone peer reachable from outside the container
    for key in image_env:
        assert key.removeprefix("RANDT_").lower() in fields, (
            f"Dockerfile ENV {key} is not a ServiceSettings field"
        )
    _set_environment(monkeypatch, image_env)
    alone = ServiceSettings()
    assert (alone.zenoh_mode, alone.listen, alone.http_host) == ("peer", ("tcp/0.0.0.0:7447",), "0.0.0.0")

    service = compose["services"]["randt"]
    env = _environment(service)
    for key in service["environment"]:
        assert key.startswith("RANDT_"), key
        assert key.removeprefix("RANDT_").lower() in fields, (
            f"compose sets {key}: not a ServiceSettings field"
        )
    _set_environment(monkeypatch, env)
    settings = ServiceSettings()
    assert settings.zenoh_mode == "client"
    assert settings.listen == (), "a client opens no listener"
    assert settings.connect == (f"tcp/{router}:{port}",), "the service connects to the router service"
    assert settings.http_host == "0.0.0.0"
    assert settings.api_token == PASS_THROUGH["RANDT_API_TOKEN"]
    volume_targets = {v.split(":")[1] for v in service["volumes"]}
    assert str(settings.data_dir) in volume_targets and str(settings.data_dir) in _final_stage()["volumes"]
    named = service["volumes"][0].split(":")[0]
    assert named in compose["volumes"], "the data live in a named volume"
    # Zenoh accepts the configuration built from these settings (opening it needs the router)
    zenoh_config(settings.zenoh_mode, settings.listen, settings.connect)
    assert settings.executor == "local", "the local worker processes unless RANDT_EXECUTOR=ray"
    # the token is optional: unset on the host, it is absent in the container and the service starts
    monkeypatch.delenv("RANDT_API_TOKEN")
    assert ServiceSettings().api_token is None
    # (an empty RANDT_API_TOKEN would not be: the reason the compose file passes it through unset)
    monkeypatch.setenv("RANDT_API_TOKEN", "")
    with pytest.raises(ValueError):
        ServiceSettings()


def _ray_argv(argv: list[str]) -> dict[str, Any]:
    """Parse a ``ray start ...`` command line with Ray's own click command, without running it."""
    from ray.scripts.scripts import cli as ray_cli

    assert argv[:2] == ["ray", "start"], f"expected `ray start`, got {argv}"
    group = ray_cli.make_context("ray", argv[1:], resilient_parsing=False)
    name, command, args = ray_cli.resolve_command(group, argv[1:])
    assert command is not None
    return dict(command.make_context(str(name), args, parent=group).params)


def test_the_cluster_profile_runs_a_ray_head_and_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    """Profile ``cluster``: a head that schedules (0 CPUs: no matcher host lands on it), workers
    that join it (one host per CPU), both with the per-call settings of a local Ray (sweeps
    inline, no task events), and the service a Ray Client of the head once ``RANDT_EXECUTOR=ray``."""
    from randt.service.ray_executor import RAY_ENV

    compose = _compose()
    head, worker = compose["services"]["ray-head"], compose["services"]["ray-worker"]
    h, w = _ray_argv(_argv(head)), _ray_argv(_argv(worker))
    assert h["head"] and h["block"] and h["num_cpus"] == 0, h
    assert h["include_dashboard"] is not False, "Ray Client sessions fail to start without it (ray 2.60)"
    assert not w["head"] and w["block"] and w["num_cpus"] is None, w
    host, _, gcs_port = w["address"].partition(":")
    assert host == "ray-head" and int(gcs_port) == h["port"]
    for node in (head, worker):
        assert node["environment"] == {**RAY_ENV, "RAY_AUTH_MODE": "disabled"}
        assert node["image"] == compose["services"]["randt"]["image"], "one image: the same Ray everywhere"
    assert "ray-head" in worker["depends_on"]
    # a wrong flag is refused by the same parser (the check is real)
    with pytest.raises(Exception, match="--num-cpu"):
        _ray_argv(["ray", "start", "--num-cpu=0"])
    # the service: local by default, a Ray Client of the head with RANDT_EXECUTOR=ray
    service = compose["services"]["randt"]
    _set_environment(monkeypatch, _environment(service, {"RANDT_EXECUTOR": "ray"}))
    settings = ServiceSettings()
    assert settings.executor == "ray"
    assert settings.ray_address == f"ray://ray-head:{h['ray_client_server_port']}"
    _set_environment(monkeypatch, _environment(service, {"RANDT_EXECUTOR": "rya"}))
    with pytest.raises(ValueError, match="executor"):
        ServiceSettings()
    # the image has Ray, the geodetic projections and ROS 2's CDR: it installs those extras
    _, stages = _dockerfile_stages()
    installs = [rest for stage in stages for word, rest in stage if word == "RUN" and "pip install" in rest]
    assert any('".[ray,geo,ros2]"' in rest for rest in installs), installs


def test_the_tls_override_mounts_what_randt_security_init_writes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``docker/compose.tls.yaml``: valid against the Compose spec; the router runs the
    ``router.json5`` and the service the ``service-client.json5`` that ``randt security init``
    writes into the directory both containers mount (at the same path, as the configs name their
    files by absolute path); the service dials the router by its compose name over TLS on the
    port the router listens on and publishes; the settings accept it all."""
    from randt.wire.zenoh_security import write_deployment

    override = yaml.safe_load((REPO / "docker" / "compose.tls.yaml").read_text())
    validator = jsonschema.Draft7Validator(_schema())
    errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(override)]
    assert not errors, errors
    compose = _compose()
    router, port = _router_port(compose)
    zenoh, randt = override["services"][router], override["services"]["randt"]
    (mount,) = {v.rsplit(":", 1)[0] for v in zenoh["volumes"]} & {
        v.rsplit(":", 1)[0] for v in randt["volumes"]
    }
    host_dir, container_dir = mount.split(":")
    assert host_dir == container_dir, "configs name their files by absolute path: mount at the same path"
    # the files, written where the override expects them (a temporary stand-in for the directory)
    deployment = write_deployment(tmp_path, ["car-01"], hosts=(router, "fleet.example.org"))
    argv = zenoh["command"]
    assert argv[0] == "-c" and Path(argv[1]).parent == Path(container_dir)
    router_cfg = json.loads(  # (JSON, a subset of JSON5)
        (tmp_path / Path(argv[1]).name).read_text()
    )
    assert router_cfg["mode"] == "router"
    assert router_cfg["listen"]["endpoints"] == [f"tls/[::]:{port}"], "the port the router publishes"
    env = {
        **_environment(compose["services"]["randt"]),
        **{k: str(v) for k, v in randt["environment"].items()},
    }
    config_in_container = Path(env["RANDT_ZENOH_CONFIG"])
    assert config_in_container.parent == Path(container_dir)
    assert (tmp_path / config_in_container.name) == deployment.service_client_config
    env["RANDT_ZENOH_CONFIG"] = str(deployment.service_client_config)
    _set_environment(monkeypatch, env)
    settings = ServiceSettings()
    assert settings.connect == (f"tls/{router}:{port}",)
    assert settings.zenoh_mode == "client" and settings.listen == ()


# -- (c) health checks, ports, the app ---------------------------------------------------------------


def _run_healthcheck(argv: list[str], port: int) -> int:
    assert argv[0] == "python", argv
    env = {"PATH": os.environ.get("PATH", ""), "RANDT_HTTP_PORT": str(port)}
    return subprocess.run([sys.executable, *argv[1:]], env=env, capture_output=True, timeout=30).returncode


def test_healthchecks_and_ports_match_the_app(tmp_path: Path) -> None:
    compose = _compose()
    image = _final_stage()
    service = compose["services"]["randt"]
    test = service["healthcheck"]["test"]
    assert test[0] == "CMD"
    checks = {"Dockerfile": image["healthcheck"], "compose": test[1:]}
    for where, argv in checks.items():
        assert "/healthz" in argv[-1], f"{where} HEALTHCHECK probes /healthz"
    paths = create_app(ServiceSettings(data_dir=tmp_path), with_zenoh=False).openapi()["paths"]
    assert "get" in paths["/healthz"], "the app serves GET /healthz"
    # the HTTP port: the app's setting, the EXPOSEd port and the published container port agree
    http_port = int(_environment(service)["RANDT_HTTP_PORT"])
    assert http_port == ServiceSettings.model_fields["http_port"].default == 8080
    assert http_port in image["expose"]
    published = {int(str(p).rsplit(":", 1)[1]) for p in service["ports"]}
    assert published == {http_port}
    router, port = _router_port(compose)
    assert f"{port}:{port}" in compose["services"][router]["ports"], "vehicles reach the router"
    # both health checks pass against the real app and fail when nothing answers
    with live_server(tmp_path / "data", matcher_processes=0) as server:
        live = int(server.url.rsplit(":", 1)[1])
        for where, argv in checks.items():
            assert _run_healthcheck(argv, live) == 0, f"{where} HEALTHCHECK fails against a healthy app"
    for where, argv in checks.items():
        assert _run_healthcheck(argv, free_port()) != 0, f"{where} HEALTHCHECK passes with no server"


# -- the build context ----------------------------------------------------------------------------


def _dockerignore_regexes() -> list[tuple[re.Pattern[str], bool]]:
    """``.dockerignore`` as (regex, excludes) in order, with Docker's pattern rules."""
    rules = []
    for raw in (REPO / ".dockerignore").read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        include = line.startswith("!")
        pattern = os.path.normpath(line.lstrip("!").strip()).lstrip("/")
        regex = ""
        i = 0
        while i < len(pattern):
            if pattern.startswith("**/", i):
                regex, i = regex + "(?:.*/)?", i + 3
            elif pattern.startswith("**", i):
                regex, i = regex + ".*", i + 2
            elif pattern[i] == "*":
                regex, i = regex + "[^/]*", i + 1
            elif pattern[i] == "?":
                regex, i = regex + "[^/]", i + 1
            elif pattern[i] == "[":
                end = pattern.index("]", i)
                regex, i = regex + pattern[i : end + 1], end + 1
            else:
                regex, i = regex + re.escape(pattern[i]), i + 1
        rules.append((re.compile(regex), not include))
    return rules


def _sent(path: str, rules: list[tuple[re.Pattern[str], bool]]) -> bool:
    """Whether the build context includes ``path`` (the last rule matching it or a parent decides)."""
    parts = path.split("/")
    candidates = ["/".join(parts[: n + 1]) for n in range(len(parts))]
    excluded = False
    for regex, excludes in rules:
        if any(regex.fullmatch(c) for c in candidates):
            excluded = excludes
    return not excluded


def test_dockerignore_sends_the_sources_and_nothing_else() -> None:
    rules = _dockerignore_regexes()
    _, stages = _dockerfile_stages()
    copied = [shlex.split(rest)[:-1] for stage in stages for word, rest in stage if word == "COPY"]
    sources = [src for args in copied if not any(a.startswith("--from") for a in args) for src in args]
    assert {
        "pyproject.toml",
        "README.md",
        "randt",
        "core",
        "wire",
        "sim",
        "service",
        "clients",
        "cli",
    } <= set(sources)
    needed = []
    for src in sources:
        p = REPO / src
        files = (
            [p] if p.is_file() else [f for f in p.rglob("*") if f.is_file() and "__pycache__" not in f.parts]
        )
        assert files, src
        needed += [f.relative_to(REPO).as_posix() for f in files]
    assert any(f.startswith("service/static/") for f in needed), "the map viewer's files are package data"
    missing = [f for f in needed if not _sent(f, rules)]
    assert not missing, f"the Dockerfile copies files .dockerignore leaves out: {missing[:5]}"
    for path in (
        ".git/HEAD",
        ".venv-ci/bin/python",
        "build/lib/core/ndt.py",
        "randt_fleet.egg-info/PKG-INFO",
        "core/__pycache__/ndt.cpython-311.pyc",
        "service/api/__pycache__/health.cpython-311.pyc",
        ".pytest_cache/v/cache",
        ".ruff_cache/CACHEDIR.TAG",
        "tests/test_docker.py",
        "randt-data/maps/default/0_0.pcd",
    ):
        assert not _sent(path, rules), f"{path} is sent to the Docker build"
