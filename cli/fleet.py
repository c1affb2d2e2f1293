"""``randt replay``, ``randt simulate`` and ``randt demo``: vehicles (recorded or simulated) and a service."""

from __future__ import annotations

import json
import logging
import signal
import sys
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, cast

import typer

from randt.cli import interrupt
from randt.cli.errors import QUIET_INTERRUPT_ENV, ExitCode, fail

if TYPE_CHECKING:
    from collections.abc import Callable

    from randt.clients.fleet import FleetSettings, GnssMode
    from randt.clients.publisher import PublisherSettings
    from randt.clients.replay import ReplayResult


class VehicleMode(StrEnum):
    client = "client"
    peer = "peer"


def _publisher_settings(
    mode: VehicleMode | None,
    connect: list[str] | None,
    zenoh_config: Path | None = None,
    raw: bool = False,
) -> PublisherSettings:
    """``PublisherSettings`` from the flags, falling back to ``RANDT_VEHICLE_*`` and the defaults."""
    from randt.clients.publisher import PublisherSettings

    overrides: dict[str, Any] = {
        "mode": mode.value if mode else None,
        "connect": tuple(connect) if connect else None,
        "zenoh_config": zenoh_config,
        "raw": True if raw else None,  # no flag: RANDT_VEHICLE_RAW or the default (reduced)
    }
    return PublisherSettings(**{k: v for k, v in overrides.items() if v is not None})


#: The options of ``randt replay`` and ``randt simulate`` that override ``PublisherSettings`` fields.
PUBLISHER_OPTIONS = ("connect", "mode", "zenoh_config", "raw")
ConnectOption = Annotated[
    list[str] | None, typer.Option(help="Zenoh endpoint of the router or service, repeatable.")
]
ModeOption = Annotated[VehicleMode | None, typer.Option(help="Zenoh mode of the vehicle.")]
ZenohConfigOption = Annotated[
    Path | None,
    typer.Option(help="Native Zenoh JSON5 config file of the vehicle: TLS, password (docs/security.md)."),
]
GnssOption = Annotated[
    str,
    typer.Option(
        help="GNSS of the vehicles, cycled over the fleet: exact (an RTK fix with every scan), noisy "
        "(metres of noise and bias, one 15 s outage), none (the pose graph joins it to the shared "
        "map), comma separated: exact,noisy,none gives one of each.",
    ),
]
SharedRoutesOption = Annotated[
    bool,
    typer.Option(
        "--shared-routes/--own-routes",
        help="Every vehicle on one loop of the town, leaving one depot one after another (streets "
        "revisited and shared: loops and joins), or each on a loop of its own.",
    ),
]
RawOption = Annotated[
    bool,
    typer.Option(
        "--raw",
        help="Send every point as float32 (v1 scans, ~150 Mbit/s per vehicle) instead of the reduced, "
        "compressed v2 scans (~8 Mbit/s; docs/clients.md). Also RANDT_VEHICLE_RAW=1.",
    ),
]


def replay(
    path: Annotated[
        Path,
        typer.Argument(
            help="KITTI sequence folder, a folder of .bin/.pcd/.ply/.csv scans, or a ROS bag (rosbag2 "
            "folder with sqlite3 or MCAP, or ROS 1 .bag; needs randt-fleet[ros2])."
        ),
    ],
    vehicle: Annotated[str, typer.Option("--vehicle", help="Vehicle id on the wire.")],
    session: Annotated[str | None, typer.Option(help="Session id (default: the UTC time).")] = None,
    rate: Annotated[
        float | None,
        typer.Option(
            help="Scans per second (default: the recording's rate, else 10); 0 = send the next scan "
            "when the previous one is answered (no scan dropped)."
        ),
    ] = None,
    window: Annotated[int, typer.Option(min=1, help="With --rate 0: scans in flight at once.")] = 1,
    loop: Annotated[bool, typer.Option(help="Start again at the end (each pass a new session).")] = False,
    start: Annotated[int, typer.Option(help="First scan index.")] = 0,
    end: Annotated[int | None, typer.Option(help="Stop before this scan index.")] = None,
    topic: Annotated[
        str | None, typer.Option(help="A bag's PointCloud2 topic (default: its only one).")
    ] = None,
    connect: ConnectOption = None,
    mode: ModeOption = None,
    zenoh_config: ZenohConfigOption = None,
    raw: RawOption = False,
    out: Annotated[
        Path | None,
        typer.Option(help="Write the received poses_kitti.txt, poses_tum.txt, summary.json here."),
    ] = None,
    connect_timeout: Annotated[float, typer.Option(help="Seconds to wait for the service.")] = 15.0,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Replay a recorded drive into the service over Zenoh and report the poses it sends back.

    Exit code 0 when every scan got a pose, 11 when some were rejected, dropped or lost (the
    summary line says which), 10 when no service answered.
    """
    from randt.clients.replay import replay as do_replay

    settings = _publisher_settings(mode, connect, zenoh_config, raw)
    results = do_replay(
        path,
        vehicle,
        session=session,
        rate_hz=rate,
        window=window,
        loop=loop,
        start=start,
        end=end,
        topic=topic,
        settings=settings,
        connect_timeout_s=connect_timeout,
        progress=progress,
    )
    complete = True
    for k, r in enumerate(results):
        s = r.stats
        n_fallback = sum(p.status == "fallback" for p in r.poses.values())
        codes = "".join(f" {c}={n}" for c, n in sorted(s.rejected_codes.items()))
        typer.echo(
            f"{path} -> {r.vehicle}/{r.session}: {r.n_scans} scans, {s.sent} sent, {s.acknowledged} poses "
            f"({n_fallback} fallback), {s.rejected} rejected{codes}, {s.dropped} dropped, {s.lost} lost, "
            f"{len(r.skipped)} invalid, {r.wall_s:.1f} s"
        )
        for name in sorted({p.map for p in r.poses.values()}):
            own = (
                " (the session's own frame: its scans carried no prior pose)"
                if name == f"{r.vehicle}.{r.session}"
                else ""
            )
            typer.echo(
                f"  map {name}{own}: GET /maps/{name}/tiles on the service's HTTP address, "
                f"or randt tiles download {name} DIR"
            )
        complete &= s.acknowledged == r.n_scans
        if out is not None:
            _write_replay(out if k == 0 else out / f"pass{k}", r)
    if not complete:
        raise typer.Exit(ExitCode.INCOMPLETE)


def _write_replay(out: Path, result: ReplayResult) -> None:
    """poses_kitti.txt, poses_tum.txt (received poses, in scan order) and summary.json of one pass."""
    from dataclasses import asdict

    from randt.core.io import atomic_write_bytes, write_kitti_poses, write_tum

    out.mkdir(parents=True, exist_ok=True)
    seqs, poses = result.trajectory()
    if len(seqs):
        write_kitti_poses(out / "poses_kitti.txt", poses)
        write_tum(out / "poses_tum.txt", result.stamps_s(), poses)
    summary = {
        "vehicle": result.vehicle,
        "session": result.session,
        "scans": result.n_scans,
        "stats": asdict(result.stats),
        "poses": [
            {"seq": int(s), "status": result.poses[int(s)].status, "fitness": result.poses[int(s)].fitness}
            for s in seqs
        ],
        "errors": {str(k): v.code for k, v in result.errors.items()},
    }
    atomic_write_bytes(out / "summary.json", json.dumps(summary, indent=1).encode())


def simulate(
    vehicles: Annotated[int, typer.Option(min=1, help="Simulated vehicles, each its own session.")] = 3,
    duration: Annotated[
        float, typer.Option(min=0.1, help="Simulated seconds of driving per vehicle.")
    ] = 10.0,
    connect: ConnectOption = None,
    mode: ModeOption = None,
    zenoh_config: ZenohConfigOption = None,
    raw: RawOption = False,
    speed: Annotated[float, typer.Option(min=0.0, help="Mean speed, m/s.")] = 6.0,
    rate: Annotated[float, typer.Option(min=0.1, help="LiDAR sweeps per simulated second.")] = 10.0,
    azimuth: Annotated[
        int, typer.Option(min=100, help="Firings per revolution (2000: a real HDL-64E, ~120k points).")
    ] = 2000,
    window: Annotated[
        int, typer.Option(min=0, help="Unanswered scans per vehicle at most; 0 = real time, no flow control.")
    ] = 2,
    seed: Annotated[int, typer.Option(help="Seed of the routes.")] = 0,
    gnss: GnssOption = "exact",
    shared_routes: SharedRoutesOption = False,
    session: Annotated[
        str | None, typer.Option(help="Session id of every vehicle (default: UTC time).")
    ] = None,
    json_out: Annotated[Path | None, typer.Option(help="Also write the summary as JSON here.")] = None,
    connect_timeout: Annotated[float, typer.Option(help="Seconds to wait for the service.")] = 30.0,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Drive simulated vehicles through a procedural town, publish their scans, score their poses.

    A vehicle with GNSS (exact or noisy) sends it as its scans' prior poses and maps the shared
    map ``default``; one without starts a map of its own, which the service's pose graph joins to
    the shared map where their streets meet. The table gives each vehicle's errors against the
    simulator's exact poses (docs/clients.md). Exit code 11 when some scan got no pose, 10 when
    no service answered.
    """
    from randt.clients.fleet import FleetSettings, run_fleet, summary_table

    settings = _publisher_settings(mode, connect, zenoh_config, raw)
    fleet = FleetSettings(
        n_vehicles=vehicles,
        duration_s=duration,
        speed_mps=speed,
        rate_hz=rate,
        n_azimuth=azimuth,
        window=window,
        fleet_seed=seed,
        gnss=_gnss_modes(gnss),
        shared_routes=shared_routes,
    )
    runs = run_fleet(fleet, settings, session=session, progress=progress, connect_timeout_s=connect_timeout)
    summaries = [r.summary() for r in runs]
    doc = {"fleet": _fleet_dict(fleet), "vehicles": summaries}
    if json_out is not None:
        from randt.core.io import atomic_write_bytes

        atomic_write_bytes(json_out, json.dumps(doc, indent=1).encode())
    for line in summary_table(summaries):
        typer.echo(line)
    if any(s["stats"]["acknowledged"] < s["scans"] for s in summaries):
        raise typer.Exit(ExitCode.INCOMPLETE)


def _gnss_modes(text: str) -> tuple[GnssMode, ...]:
    """``--gnss``: comma-separated GNSS modes, cycled over the fleet."""
    from randt.clients.fleet import GNSS_MODES

    modes = tuple(m.strip() for m in text.split(","))
    bad = [m for m in modes if m not in GNSS_MODES]
    if bad:
        raise typer.BadParameter(
            f"{', '.join(map(repr, bad))}: each mode is one of {', '.join(GNSS_MODES)}", param_hint="--gnss"
        )
    return cast("tuple[GnssMode, ...]", modes)


def _fleet_dict(fleet: FleetSettings) -> dict[str, object]:
    """The fleet settings as a JSON-ready dict (with the derived number of scans)."""
    from dataclasses import asdict

    return {**asdict(fleet), "n_scans": fleet.n_scans}


# -- randt demo: the README's main job ----------------------------------------------------------


def _usable_port(port: int) -> tuple[int, bool]:
    """``(port, True)`` if it can be bound on 127.0.0.1, else ``(a free port, False)``; 0 = any."""
    import socket

    if port:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
                return port, True
            except OSError:
                pass
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1], port == 0


def _map_folder_stats(folder: Path, pdu_voxel_m: float) -> tuple[int, int, float | None]:
    """Tiles, points and PDU of an Autoware tile folder (the store's ``maps/<map>/``)."""
    import numpy as np

    from randt.core.io import read_cloud
    from randt.core.metrics.cloud import pdu

    files = sorted(folder.glob("*.pcd"))
    if not files:
        return 0, 0, None
    xyz = np.concatenate([read_cloud(f).xyz for f in files])
    return len(files), int(xyz.shape[0]), float(pdu(xyz, pdu_voxel_m))


#: How long the demo waits for the service's matcher processes to be warm (numba kernels compiled
#: or loaded) before it fails.
WARM_UP_TIMEOUT_S = 300.0


def _wait_warm(base: str) -> None:
    """Say that the matchers warm up, and wait for it (``/readyz``): the fleet's progress bar
    would otherwise sit at 0 while a first run compiles the kernels, with no word of why."""
    import time

    import httpx

    typer.echo(
        "warming up the matcher processes (numba kernels: about 20 s the first time on this machine, "
        "1-2 s once cached)...",
        nl=False,
    )
    tic = time.monotonic()
    while time.monotonic() - tic < WARM_UP_TIMEOUT_S:
        try:
            if httpx.get(f"{base}/readyz", timeout=5).json().get("ready"):
                typer.echo(f" ready in {time.monotonic() - tic:.0f} s")
                return
        except (httpx.HTTPError, ValueError):
            pass
        interrupt.sleep(0.2)
    typer.echo("")
    raise fail(TimeoutError(f"the service was not ready within {WARM_UP_TIMEOUT_S:.0f} s ({base}/readyz)"))


def _fleet_gnss(modes: tuple[str, ...], vehicles: int) -> str:
    """``sim000 exact, sim001 noisy, ...``: each simulated vehicle's GNSS."""
    return ", ".join(f"sim{v:03d} {modes[v % len(modes)]}" for v in range(vehicles))


def _settle(
    base: str, tiles_s: float, graph_idle: Callable[[float], bool] | None, timeout_s: float = 120.0
) -> None:
    """Wait until the matchers' queues are empty and the pose graph has processed every keyframe
    (it runs at the lowest priority, behind the matchers) and re-folded the tiles of those it moved
    (``graph_idle``: ServiceGraph.wait_idle; its re-folds otherwise wait for ``graph_refold_s``,
    20 s, and would change the tiles after the summary), then for the tiles' next save, and until
    map ``default`` on disk has as many tiles as in memory (a busy flusher saves later)."""
    import time

    import httpx

    deadline = time.monotonic() + timeout_s
    with httpx.Client(base_url=base, timeout=30) as http:
        while time.monotonic() < deadline:
            status = http.get("/status").json()
            if not any(status.get("queue_depths", {}).values()) and not status["graph"].get("pending"):
                break
            interrupt.sleep(0.5)
        if graph_idle is not None:
            graph_idle(max(deadline - time.monotonic(), 1.0))
        interrupt.sleep(tiles_s)  # (tiles are saved every tile_save_s, at a flush)
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            live = http.get("/status").json().get("maps", {}).get("default", {}).get("tiles")
            saved = http.get("/maps/default")
            if live is None or (saved.status_code == 200 and saved.json()["tiles"] == live):
                break
            interrupt.sleep(0.5)


def _print_summary(
    base: str, data: Path, data_dir: Path | None, fleet: dict[str, Any], wall: float, exit_: bool
) -> None:
    """The demo's summary: each vehicle's errors live and corrected, the pose graph's loops and
    joins, the map, and where to go next (no links to a service that stops with ``--exit``)."""
    import httpx

    from randt.clients.fleet import fleet_graph, graph_table, summary_table
    from randt.clients.rest import ApiError, MapClient

    total = sum(v["scans"] for v in fleet["vehicles"])
    typer.echo(
        f"\nfleet done in {wall:.0f} s ({total / max(wall, 1e-9):.1f} scans/s); errors against ground truth:"
    )
    for line in summary_table(fleet["vehicles"]):
        typer.echo(line)
    typer.echo(
        "(ATE: RMS position error in the shared map's frame, * after a rigid fit: a session without GNSS "
        "answers in its own frame; RPE: frame-to-frame error; drift: end-to-end error per distance)"
    )
    with MapClient(base) as client:
        try:
            graph = fleet_graph(client, fleet["vehicles"])
        except ApiError as exc:
            typer.echo(f"pose graph: none ({exc})")
        else:
            typer.echo("\nthe pose graph (loop closure, GNSS fusion, joins), per vehicle:")
            for line in graph_table(graph):
                typer.echo(line)
            typer.echo(
                "(corrected: trajectory?corrected=true, the poses moved with the graph's keyframes, in the "
                "shared map's frame)"
            )
    tiles_dir = data / "maps" / "default"
    n_tiles, n_points, map_pdu = _map_folder_stats(tiles_dir, 0.5)
    pdu_text = "n/a" if map_pdu is None else f"{map_pdu:.3f}"
    typer.echo(
        f"\nmap default: {n_tiles} tiles, {n_points} points, PDU {pdu_text} (0.5 m voxels; 1 = uniform)"
    )
    if data_dir is not None:
        typer.echo(f"tiles (Autoware layout): {tiles_dir}")
    elif exit_:
        typer.echo("tiles: removed with the temporary folder at exit (keep them with --data-dir)")
    else:
        typer.echo(f"tiles (Autoware layout, removed at exit): {tiles_dir}")
    if exit_:  # the service stops now: no link to it
        typer.echo("the service stops now (--exit); without --exit it serves the map on")
        return
    with httpx.Client(base_url=base, timeout=30) as http:
        paths = ["/status", "/sessions", "/maps", "/maps/default/graph", "/maps/default/tiles"]
        paths += ["/metrics", "/docs"]
        available = [p for p in paths if http.get(p).status_code == 200]
        viewer = http.get("/").status_code == 200
    typer.echo(f"viewer: {base}/" if viewer else "viewer: not available in this version")
    typer.echo(f"REST: {' '.join(base + p for p in available)}")
    typer.echo(f"download the map: randt tiles download default ./map --url {base}")


def demo(
    vehicles: Annotated[int, typer.Option(min=1, help="Simulated vehicles.")] = 3,
    duration: Annotated[
        float,
        typer.Option(
            min=0.5, help="Simulated seconds of driving per vehicle (45: a lap of the loop and more)."
        ),
    ] = 45.0,
    exit_: Annotated[
        bool, typer.Option("--exit", help="Stop after the summary instead of serving on.")
    ] = False,
    data_dir: Annotated[
        Path | None,
        typer.Option(help="Service data directory, kept (default: a temporary folder, removed at exit)."),
    ] = None,
    http_port: Annotated[int, typer.Option(help="HTTP port (a free one if taken; 0 = any).")] = 8080,
    zenoh_port: Annotated[int, typer.Option(help="Zenoh port (a free one if taken; 0 = any).")] = 7447,
    speed: Annotated[float, typer.Option(min=0.0, help="Mean speed of the vehicles, m/s.")] = 8.0,
    azimuth: Annotated[int, typer.Option(min=100, help="LiDAR firings per revolution.")] = 2000,
    gnss: GnssOption = "exact,noisy,none",
    shared_routes: SharedRoutesOption = True,
    raw: RawOption = False,
    progress: Annotated[bool, typer.Option(help="Show the fleet's progress bar.")] = True,
) -> None:
    """The fleet demo: the service, a simulated fleet, errors against ground truth, then the map.

    Starts the service on embedded defaults (Zenoh peer and HTTP on 127.0.0.1) and prints the
    viewer's URL (open it to watch the map grow), drives VEHICLES simulated vehicles for DURATION
    simulated seconds each (a child randt simulate, flow controlled so no scan is dropped): by
    default one with an exact GNSS, one with a noisy GNSS that drops out for 15 s, one with none,
    leaving one after another from the same depot on one loop of the town. Then it prints per
    vehicle the trajectory error against the simulator's ground truth, live and as the pose graph
    corrected it, the loops the graph closed and when the vehicle without GNSS joined the shared
    map, the map's PDU and where the tiles are, and keeps serving until Ctrl-C (or stops at once
    with --exit). Without --data-dir the data live in a temporary folder removed at exit.
    """
    import os
    import shutil
    import subprocess
    import tempfile
    import threading
    import time

    import uvicorn

    from randt.service.app import create_app
    from randt.service.settings import ServiceSettings
    from randt.service.store import check_data_dir_free

    modes = _gnss_modes(gnss)
    if data_dir is not None:
        check_data_dir_free(data_dir)
    data = data_dir or Path(tempfile.mkdtemp(prefix="randt-demo-"))
    try:  # (a Ctrl-C before the service runs leaves no temporary folder either)
        logging.getLogger("randt.core").setLevel(
            logging.ERROR
        )  # fallbacks are counted in the summary instead
        zport, z_ok = _usable_port(zenoh_port)
        hport, h_ok = _usable_port(http_port)
        for name, wanted, got, ok in (("Zenoh", zenoh_port, zport, z_ok), ("HTTP", http_port, hport, h_ok)):
            if not ok:
                typer.echo(f"randt demo: {name} port {wanted} is taken, using {got}", err=True)
        endpoint = f"tcp/127.0.0.1:{zport}"
        settings = ServiceSettings(
            data_dir=data,
            zenoh_mode="peer",
            listen=(endpoint,),
            connect=(),
            http_host="127.0.0.1",
            http_port=hport,
            # Every requested vehicle is admitted: the demo's vehicles wait for their answers
            # (clients/fleet.py's window), so they pace themselves instead of overloading (neither
            # the count cap nor the measured capacity, which real-time vehicles need, applies).
            max_sessions=0,
            capacity_target=0,
        )
        base = f"http://127.0.0.1:{hport}"
        app = create_app(settings)
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=hport, log_level="warning"))
        thread = threading.Thread(target=server.run, name="uvicorn", daemon=True)
        previous_sigterm = signal.getsignal(signal.SIGTERM)
        interrupt.install(signal.SIGTERM)
    except BaseException:
        if data_dir is None:
            shutil.rmtree(data, ignore_errors=True)
        raise

    def shutdown() -> None:
        server.should_exit = True
        if thread.is_alive():
            thread.join(60)  # uvicorn's lifespan stops the service: queues drained, tiles saved
        signal.signal(signal.SIGTERM, previous_sigterm)

    fleet_json = data / "demo-fleet.json"
    proc: subprocess.Popen[bytes] | None = None
    summarized = interrupted = False
    try:
        thread.start()
        deadline = time.monotonic() + 60
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                raise fail(ConnectionError(f"the service did not start on {base} (see the log above)"))
            interrupt.sleep(0.1)
        n_scans = max(1, round(duration * 10.0))
        kept = "" if data_dir is not None else " (temporary, removed at exit: keep one with --data-dir)"
        typer.echo(f"randt demo: service on Zenoh {endpoint} (peer) and {base}, data in {data}{kept}")
        typer.echo(f"viewer: {base}/  (open it now: the map grows as the fleet drives)")
        _wait_warm(base)
        typer.echo(
            f"simulating {vehicles} vehicles for {duration:g} s each: {n_scans} sweeps of a 64-beam LiDAR "
            f"({azimuth} firings a turn) at 10 Hz and {speed:g} m/s, GNSS {_fleet_gnss(modes, vehicles)}"
            f"{', leaving one after another from one depot' if shared_routes else ''}; each vehicle waits "
            "for its answers (at most 2 scans in flight), so no scan is dropped and simulated time runs "
            "slower than real time..."
        )
        cmd = [
            sys.executable, "-m", "randt.cli", "simulate",
            "--vehicles", str(vehicles), "--duration", str(duration), "--speed", str(speed),
            "--azimuth", str(azimuth), "--window", "2", "--connect", endpoint, "--mode", "client",
            "--gnss", ",".join(modes), "--shared-routes" if shared_routes else "--own-routes",
            "--session", f"demo-{time.strftime('%Y%m%d-%H%M%S')}", "--json-out", str(fleet_json),
            *([] if progress else ["--no-progress"]), *(["--raw"] if raw else []),
        ]  # fmt: skip
        tic = time.monotonic()
        # In a process group of its own: a Ctrl-C in the terminal reaches the demo alone, which
        # stops it (in the group, one arriving while its interpreter started printed a traceback).
        proc = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, env={**os.environ, QUIET_INTERRUPT_ENV: "1"}, process_group=0
        )
        while (rc := proc.poll()) is None:
            interrupt.sleep(0.2)
        if rc not in (0, ExitCode.INCOMPLETE) or not fleet_json.is_file():
            raise fail(RuntimeError(f"the simulated fleet failed (randt simulate exit code {rc})"))
        wall = time.monotonic() - tic
        fleet = json.loads(fleet_json.read_text())
        manager = app.state.service.sessions
        graph = None if manager is None else manager.graph
        idle = None if graph is None else graph.wait_idle
        _settle(base, settings.tile_save_s + 1.5 * settings.flush_interval_s, idle)
        _print_summary(base, data, data_dir, fleet, wall, exit_)
        summarized = True
        if not exit_:
            typer.echo("serving until Ctrl-C")
            while thread.is_alive():
                interrupt.check()
                thread.join(0.5)
    except KeyboardInterrupt:
        interrupted = True
        # a second Ctrl-C (or SIGTERM) must not cut the shutdown short with a traceback
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if proc is not None and proc.poll() is None:
            proc.terminate()  # (SIGTERM: it stops at once, without a word)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(30)
        typer.echo("\nrandt demo: stopping", err=True)
    finally:
        shutdown()
        if data_dir is None:
            shutil.rmtree(data, ignore_errors=True)
    # Everything is flushed and closed. Leave without interpreter finalization: Zenoh's native
    # threads may still release Python callbacks of the closed session, and one run in about ten
    # aborted there ("FATAL: exception not rethrown", exit 134) after a complete, correct summary.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(ExitCode.INTERRUPTED if interrupted or not summarized else 0)
