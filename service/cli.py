"""The ``randt`` command: a thin shell over ``core``, ``service`` and ``clients``.

Subcommands import what they need lazily so ``randt --help`` stays fast. Errors from the project's
exception tree become a one-line message on stderr and a non-zero exit code (the one place that
maps them, :data:`EXIT_CODES`).
"""

from __future__ import annotations

import json
import logging
import signal
import sys
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from core.errors import (
    DegenerateProblemError,
    FormatError,
    InvalidCloudError,
    NotFoundError,
    RandtError,
    RegistrationFailedError,
)

if TYPE_CHECKING:
    from clients.fleet import FleetSettings
    from clients.publisher import PublisherSettings
    from clients.replay import ReplayResult
    from clients.rest import MapClient

app = typer.Typer(
    name="randt",
    help="randt-fleet: RANDT scan matching and fleet map building.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

#: Exit codes by error class (first match wins); 0 is success, 1 is an unexpected crash.
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
    (ConnectionError, 10),
    (FileNotFoundError, 2),
    (NotFoundError, 2),
    (FormatError, 3),
    (InvalidCloudError, 4),
    (DegenerateProblemError, 5),
    (RegistrationFailedError, 6),
    (RandtError, 7),
    (ValueError, 8),
)
#: Exit code when registration finished but did not converge (the result is still printed).
EXIT_NOT_CONVERGED = 9


def _fail(exc: BaseException) -> typer.Exit:
    code = next((c for cls, c in EXIT_CODES if isinstance(exc, cls)), 1)
    msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    typer.echo(f"randt: error: {msg}", err=True)
    return typer.Exit(code)


class MethodChoice(StrEnum):
    randt = "randt"
    ndt = "ndt"
    icp_point = "icp-point"
    icp_plane = "icp-plane"


@app.callback()
def _main(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log debug messages.")] = False,
) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def _read_init(path: Path | None):
    import numpy as np

    from core.transforms import as_transform

    if path is None:
        return None
    try:
        T = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: cannot read a 4x4 matrix: {exc}") from exc
    if T.size == 12:
        T = np.vstack([T.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    try:
        return as_transform(T.reshape(4, 4) if T.size == 16 else T, name=f"--init {path}")
    except ValueError as exc:
        raise FormatError(str(exc)) from exc


@app.command()
def register(
    source: Annotated[Path, typer.Argument(help="Moving cloud (.bin .pcd .ply .csv .txt .npy .off).")],
    target: Annotated[Path, typer.Argument(help="Reference cloud, any supported format.")],
    init: Annotated[
        Path | None, typer.Option(help="Initial T_target_source: 4x4 or 3x4 text matrix.")
    ] = None,
    method: Annotated[MethodChoice, typer.Option(help="Registration method.")] = MethodChoice.randt,
    voxel: Annotated[
        list[float] | None,
        typer.Option(help="NDT voxel size in metres, repeat coarse to fine (default: derived)."),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print exactly one JSON object.")] = False,
    output: Annotated[
        Path | None, typer.Option(help="Write SOURCE moved into TARGET's frame (.pcd or .ply).")
    ] = None,
) -> None:
    """Register SOURCE to TARGET and print T_target_source, fitness and time."""
    try:
        from core.config import RegistrationSettings
        from core.io import read_cloud, write_cloud
        from core.registration import register as do_register
        from core.transforms import transform_points

        init_T = _read_init(init)
        src = read_cloud(source)
        tgt = read_cloud(target)
        settings = RegistrationSettings.for_method(
            method.value, **({"voxel_sizes_m": tuple(voxel)} if voxel else {})
        )
        result = do_register(src.xyz, tgt.xyz, init_T, settings=settings)
        if output is not None:
            from dataclasses import replace

            write_cloud(output, replace(src, xyz=transform_points(result.T_target_source, src.xyz)))
    except (RandtError, OSError, ValueError) as exc:
        raise _fail(exc) from exc
    if as_json:
        typer.echo(json.dumps(result.to_dict()))
    else:
        import numpy as np

        with np.printoptions(precision=6, suppress=True):
            typer.echo(f"T_target_source =\n{result.T_target_source}")
        typer.echo(
            f"method {result.method}  converged {result.converged}  iterations {result.iterations}\n"
            f"fitness (NVTL) {result.fitness:.4f}  transform probability "
            f"{result.transform_probability:.4f}  inlier ratio {result.inlier_ratio:.3f}\n"
            f"time {result.time_s:.3f} s  voxels {', '.join(f'{v:g}' for v in result.voxel_sizes_m)} m"
        )
    if not result.converged:
        typer.echo("randt: warning: registration did not converge", err=True)
        raise typer.Exit(EXIT_NOT_CONVERGED)


@app.command("demo-register")
def demo_register(
    data_dir: Annotated[
        Path | None,
        typer.Option(help="Shared real data (default: $RANDT_SHARED_DATA or ./../shared/data if present)."),
    ] = None,
) -> None:
    """Offline registration demo: every method on a known transform, then on real pairs if present.

    Needs nothing but the installed package: a synthetic room is registered under a known
    transform; when the shared real data set is found, its scan pairs are registered too and
    compared with their reference transforms.
    """
    import os

    import numpy as np

    from core.config import RegistrationSettings
    from core.protocol import synthetic_room
    from core.registration import register as do_register
    from core.transforms import make_transform, transform_error, transform_points

    rng = np.random.default_rng(0)
    target = synthetic_room(rng)
    T_true = make_transform(euler_deg=(2.0, -1.0, 8.0), translation=(0.8, -0.4, 0.1))
    source = transform_points(np.linalg.inv(T_true), synthetic_room(rng))
    source += rng.normal(0.0, 0.01, source.shape)  # 1 cm range noise
    typer.echo("synthetic room, known transform (0.9 m, 8.3 deg), from the identity:")
    for method in ("randt", "ndt", "icp-point", "icp-plane"):
        r = do_register(source, target, settings=RegistrationSettings.for_method(method))
        e_m, e_deg = transform_error(r.T_target_source, T_true)
        typer.echo(f"  {method:10s} error {e_m * 100:6.2f} cm {e_deg:6.3f} deg  time {r.time_s:6.3f} s")

    root = data_dir or Path(os.environ.get("RANDT_SHARED_DATA", Path.cwd().parent / "shared" / "data"))
    if not (root / "pairs").is_dir():
        typer.echo(f"(no real data at {root}: set --data-dir or RANDT_SHARED_DATA to try the real pairs)")
        return
    from core.io import read_cloud

    pairs = {
        "small_gicp (indoor)": (
            "pairs/small_gicp/source.ply",
            "pairs/small_gicp/target.ply",
            "pairs/small_gicp/T_target_source.txt",
        ),
        "argoverse2 (street)": (
            "pairs/argoverse2/315966265360032000.bin",
            "pairs/argoverse2/315966265259836000.bin",
            "pairs/argoverse2/T_a_b.txt",
        ),
    }
    typer.echo(f"real scan pairs from {root}, RANDT from the identity:")
    for name, (s, t, ref) in pairs.items():
        try:
            r = do_register(read_cloud(root / s).xyz, read_cloud(root / t).xyz)
        except RandtError as exc:
            typer.echo(f"  {name}: {exc}")
            continue
        e_m, e_deg = transform_error(r.T_target_source, np.loadtxt(root / ref))
        typer.echo(
            f"  {name:20s} error {e_m * 100:6.2f} cm {e_deg:6.3f} deg  fitness {r.fitness:.3f}  "
            f"time {r.time_s:.3f} s"
        )


@app.command("map")
def map_sequence(
    dataset_dir: Annotated[Path, typer.Argument(help="KITTI sequence folder or a folder of scan files.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder (created).")],
    start: Annotated[int, typer.Option(help="First scan index.")] = 0,
    end: Annotated[int | None, typer.Option(help="Stop before this scan index.")] = None,
    tile_size: Annotated[int, typer.Option(help="Map tile edge in metres (Autoware: 20).")] = 20,
    map_voxel: Annotated[float, typer.Option(help="Density-equalization voxel of the map, m.")] = 0.2,
    pdu_voxel: Annotated[float, typer.Option(help="Voxel for the PDU index, m.")] = 0.5,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Build poses and a tiled map from a scan sequence (the paper's Algorithm 2, offline).

    Writes OUT/poses_kitti.txt, OUT/poses_tum.txt, OUT/map/*.pcd with
    OUT/map/pointcloud_map_metadata.yaml, and OUT/summary.json.
    """
    try:
        import numpy as np
        from tqdm import tqdm

        from core.datasets import open_sequence
        from core.io import atomic_write_bytes, write_kitti_poses, write_tum
        from core.mapping import MapBuilder
        from core.metrics.cloud import pdu

        seq = open_sequence(dataset_dir, start=start, end=end)
        builder = MapBuilder(tile_size_m=tile_size, map_voxel_m=map_voxel)
        scans = []
        bar = tqdm(total=len(seq), unit="scan", disable=not progress, file=sys.stderr)
        for i in range(len(seq)):
            cloud = seq.read(i)
            update = builder.add_scan(cloud.xyz, intensity=cloud.intensity, time_offset_s=cloud.time_offset_s)
            r = update.scan
            scans.append(
                {
                    "index": i + start,
                    "time_s": r.time_s,
                    "fitness": r.fitness,
                    "converged": r.converged,
                    "status": r.status,
                    "inlier_ratio": r.inlier_ratio,
                    "message": r.message,
                }
            )
            bar.set_postfix(status=r.status, tiles=len(builder.tiles), refresh=False)
            bar.update()
        bar.close()
        out.mkdir(parents=True, exist_ok=True)
        poses = np.array(builder.poses)
        write_kitti_poses(out / "poses_kitti.txt", poses)
        stamps = seq.stamps_s if seq.stamps_s is not None else np.arange(len(poses)) * 0.1
        write_tum(out / "poses_tum.txt", stamps, poses)
        builder.tiles.export_autoware(out / "map")
        map_points = builder.tiles.to_cloud().xyz.astype(np.float64)
        summary = {
            "scans": scans,
            "map": {
                "pdu": pdu(map_points, pdu_voxel) if len(map_points) else None,
                "pdu_voxel_m": pdu_voxel,
                "tiles": len(builder.tiles),
                "points": int(builder.tiles.n_points),
                "tile_pdu": builder.tiles.tile_pdu(pdu_voxel),
            },
        }
        atomic_write_bytes(out / "summary.json", json.dumps(summary, indent=1).encode())
    except (RandtError, OSError, ValueError) as exc:
        raise _fail(exc) from exc
    n_ok = sum(s["status"] != "fallback" for s in scans)
    typer.echo(
        f"{len(scans)} scans ({n_ok} matched), {summary['map']['tiles']} tiles, "
        f"{summary['map']['points']} map points, PDU {summary['map']['pdu']:.3f} -> {out}"
    )


class TrajectoryFormat(StrEnum):
    kitti = "kitti"
    tum = "tum"


@app.command("eval")
def eval_trajectory(
    reference: Annotated[Path, typer.Option("--reference", help="Reference trajectory file.")],
    estimate: Annotated[Path, typer.Option("--estimate", help="Estimated trajectory file.")],
    fmt: Annotated[TrajectoryFormat, typer.Option("--format", help="File format of both.")] = (
        TrajectoryFormat.kitti
    ),
    as_json: Annotated[bool, typer.Option("--json", help="Print exactly one JSON object.")] = False,
) -> None:
    """ATE, RPE and KITTI relative errors of ESTIMATE against REFERENCE."""
    try:
        from core.io import read_kitti_poses, read_tum
        from core.metrics.trajectory import evaluate_trajectory

        if fmt is TrajectoryFormat.kitti:
            ref, est = read_kitti_poses(reference), read_kitti_poses(estimate)
        else:
            ref, est = read_tum(reference)[1], read_tum(estimate)[1]
        if len(ref) != len(est):
            raise ValueError(f"{reference} has {len(ref)} poses but {estimate} has {len(est)}")
        report = evaluate_trajectory(ref, est)
    except (RandtError, OSError, ValueError) as exc:
        raise _fail(exc) from exc
    if as_json:
        typer.echo(json.dumps(report))
        return
    ate, rpe = report["ate"], report["rpe"]
    typer.echo(f"poses {report['n_poses']}  path {report['path_length_m']:.1f} m")
    typer.echo(f"ATE (se3 aligned) rmse {ate['translation_m']['rmse']:.4f} m")
    typer.echo(
        f"RPE (1 frame) translation rmse {rpe['translation_m']['rmse']:.4f} m, "
        f"rotation rmse {rpe['rotation_deg']['rmse']:.4f} deg"
    )
    kitti = report.get("kitti")
    if kitti:
        typer.echo(
            f"KITTI relative error {kitti['translation_pct']:.3f} %, "
            f"{kitti['rotation_deg_per_100m']:.4f} deg/100 m"
        )
    else:
        typer.echo(f"KITTI relative error: n/a ({'; '.join(report.get('notes', []))})")


class ZenohMode(StrEnum):
    peer = "peer"
    client = "client"


@app.command()
def serve(
    data_dir: Annotated[Path | None, typer.Option(help="Data directory [env RANDT_DATA_DIR].")] = None,
    zenoh_mode: Annotated[ZenohMode | None, typer.Option(help="Zenoh mode [env RANDT_ZENOH_MODE].")] = None,
    listen: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to listen on, repeatable [env RANDT_LISTEN].")
    ] = None,
    connect: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to connect to, repeatable [env RANDT_CONNECT].")
    ] = None,
    http_host: Annotated[str | None, typer.Option(help="HTTP bind address [env RANDT_HTTP_HOST].")] = None,
    http_port: Annotated[int | None, typer.Option(help="HTTP port [env RANDT_HTTP_PORT].")] = None,
) -> None:
    """Run the fleet mapping service (Zenoh ingest + HTTP) until SIGTERM or Ctrl-C."""
    import uvicorn
    from pydantic import ValidationError

    from service.app import create_app
    from service.settings import ServiceSettings

    overrides = {
        "data_dir": data_dir,
        "zenoh_mode": zenoh_mode.value if zenoh_mode else None,
        "listen": tuple(listen) if listen else None,
        "connect": tuple(connect) if connect else None,
        "http_host": http_host,
        "http_port": http_port,
    }
    try:
        settings = ServiceSettings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        first = exc.errors()[0]
        raise _fail(ValueError(f"{'.'.join(map(str, first['loc']))}: {first['msg']}")) from exc
    logging.getLogger().setLevel(logging.INFO)
    app_ = create_app(settings)
    typer.echo(
        f"randt serve: zenoh {settings.zenoh_mode} listen {list(settings.listen)} connect "
        f"{list(settings.connect)}; http://{settings.http_host}:{settings.http_port}; "
        f"data {settings.data_dir}",
        err=True,
    )
    uvicorn.run(app_, host=settings.http_host, port=settings.http_port, log_level="info")


# ----------------------------------------------------------------------------------------------
# clients: replay, simulate, tiles, and the fleet demo
# ----------------------------------------------------------------------------------------------

#: Exit code of ``randt replay`` / ``randt simulate`` when some scan got no pose (summary printed).
EXIT_INCOMPLETE = 11
#: Exit code after Ctrl-C.
EXIT_INTERRUPTED = 130


class VehicleMode(StrEnum):
    client = "client"
    peer = "peer"


def _publisher_settings(mode: VehicleMode | None, connect: list[str] | None) -> PublisherSettings:
    """``PublisherSettings`` from the flags, falling back to ``RANDT_VEHICLE_*`` and the defaults."""
    from pydantic import ValidationError

    from clients.publisher import PublisherSettings

    overrides = {"mode": mode.value if mode else None, "connect": tuple(connect) if connect else None}
    try:
        return PublisherSettings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        first = exc.errors()[0]
        raise _fail(ValueError(f"{'.'.join(map(str, first['loc']))}: {first['msg']}")) from exc


ConnectOption = Annotated[
    list[str] | None,
    typer.Option(
        help="Zenoh endpoint of the router or service, repeatable "
        "[env RANDT_VEHICLE_CONNECT; default tcp/127.0.0.1:7447]."
    ),
]
ModeOption = Annotated[
    VehicleMode | None,
    typer.Option(help="Zenoh mode of the vehicle [env RANDT_VEHICLE_MODE; default client]."),
]


@app.command()
def replay(
    path: Annotated[
        Path, typer.Argument(help="KITTI sequence folder or a folder of .bin/.pcd/.ply/.csv scans.")
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
    connect: ConnectOption = None,
    mode: ModeOption = None,
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
    from clients.replay import replay as do_replay

    settings = _publisher_settings(mode, connect)
    try:
        results = do_replay(
            path,
            vehicle,
            session=session,
            rate_hz=rate,
            window=window,
            loop=loop,
            start=start,
            end=end,
            settings=settings,
            connect_timeout_s=connect_timeout,
            progress=progress,
        )
    except KeyboardInterrupt:
        typer.echo("randt replay: interrupted", err=True)
        raise typer.Exit(EXIT_INTERRUPTED) from None
    except (RandtError, OSError, ValueError) as exc:
        raise _fail(exc) from exc
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
        complete &= s.acknowledged == r.n_scans
        if out is not None:
            _write_replay(out if k == 0 else out / f"pass{k}", r)
    if not complete:
        raise typer.Exit(EXIT_INCOMPLETE)


def _write_replay(out: Path, result: ReplayResult) -> None:
    """poses_kitti.txt, poses_tum.txt (received poses, in scan order) and summary.json of one pass."""
    from dataclasses import asdict

    from core.io import atomic_write_bytes, write_kitti_poses, write_tum

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


@app.command()
def simulate(
    vehicles: Annotated[int, typer.Option(min=1, help="Simulated vehicles, each its own session.")] = 3,
    duration: Annotated[
        float, typer.Option(min=0.1, help="Simulated seconds of driving per vehicle.")
    ] = 10.0,
    connect: ConnectOption = None,
    mode: ModeOption = None,
    speed: Annotated[float, typer.Option(min=0.0, help="Mean speed, m/s.")] = 6.0,
    rate: Annotated[float, typer.Option(min=0.1, help="LiDAR sweeps per simulated second.")] = 10.0,
    azimuth: Annotated[
        int, typer.Option(min=100, help="Firings per revolution (2000: a real HDL-64E, ~120k points).")
    ] = 2000,
    window: Annotated[
        int, typer.Option(min=0, help="Unanswered scans per vehicle at most; 0 = real time, no flow control.")
    ] = 2,
    seed: Annotated[int, typer.Option(help="Seed of the routes.")] = 0,
    session: Annotated[
        str | None, typer.Option(help="Session id of every vehicle (default: UTC time).")
    ] = None,
    json_out: Annotated[Path | None, typer.Option(help="Also write the summary as JSON here.")] = None,
    connect_timeout: Annotated[float, typer.Option(help="Seconds to wait for the service.")] = 30.0,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Drive simulated vehicles through a procedural town, publish their scans, score their poses.

    Each vehicle's first scan carries its true pose as a prior, so the fleet shares the map
    ``default``; the table gives each vehicle's errors against the simulator's exact poses
    (docs/clients.md). Exit code 11 when some scan got no pose, 10 when no service answered.
    """
    from clients.fleet import FleetSettings, run_fleet, summary_table

    settings = _publisher_settings(mode, connect)
    fleet = FleetSettings(
        n_vehicles=vehicles,
        duration_s=duration,
        speed_mps=speed,
        rate_hz=rate,
        n_azimuth=azimuth,
        window=window,
        fleet_seed=seed,
    )
    try:
        runs = run_fleet(
            fleet, settings, session=session, progress=progress, connect_timeout_s=connect_timeout
        )
    except KeyboardInterrupt:
        typer.echo("randt simulate: interrupted", err=True)
        raise typer.Exit(EXIT_INTERRUPTED) from None
    except (RandtError, OSError, ValueError) as exc:
        raise _fail(exc) from exc
    summaries = [r.summary() for r in runs]
    doc = {"fleet": _fleet_dict(fleet), "vehicles": summaries}
    if json_out is not None:
        from core.io import atomic_write_bytes

        atomic_write_bytes(json_out, json.dumps(doc, indent=1).encode())
    for line in summary_table(summaries):
        typer.echo(line)
    if any(s["stats"]["acknowledged"] < s["scans"] for s in summaries):
        raise typer.Exit(EXIT_INCOMPLETE)


def _fleet_dict(fleet: FleetSettings) -> dict[str, object]:
    """The fleet settings as a JSON-ready dict (with the derived number of scans)."""
    from dataclasses import asdict

    return {**asdict(fleet), "n_scans": fleet.n_scans}


# -- randt tiles: the HTTP client ---------------------------------------------------------------

tiles_app = typer.Typer(
    help="Sessions, trajectories and map tiles from a running service, over HTTP.",
    no_args_is_help=True,
)
app.add_typer(tiles_app, name="tiles")

UrlOption = Annotated[
    str, typer.Option("--url", envvar="RANDT_URL", help="The service's HTTP address [env RANDT_URL].")
]
TokenOption = Annotated[
    str | None,
    typer.Option("--token", envvar="RANDT_API_TOKEN", help="Bearer token if reads are protected."),
]
DEFAULT_URL = "http://127.0.0.1:8080"


class TrajectoryOutFormat(StrEnum):
    kitti = "kitti"
    tum = "tum"
    json = "json"


class CloudOutFormat(StrEnum):
    pcd = "pcd"
    ply = "ply"
    las = "las"


def _client(url: str, token: str | None) -> MapClient:
    from clients.rest import MapClient

    return MapClient(url, token=token)


@tiles_app.command("sessions")
def tiles_sessions(url: UrlOption = DEFAULT_URL, token: TokenOption = None) -> None:
    """List the service's sessions: id, state, map, scans, fallbacks."""
    try:
        with _client(url, token) as api:
            rows = api.sessions()
    except (RandtError, OSError) as exc:
        raise _fail(exc) from exc
    typer.echo(f"{'id':<40} {'state':<8} {'map':<24} {'scans':>6} {'fallbacks':>9}")
    for s in rows:
        typer.echo(
            f"{s['id']:<40} {s['state']:<8} {s.get('map') or '-':<24} {s['scans']:>6} {s['fallbacks']:>9}"
        )


@tiles_app.command("trajectory")
def tiles_trajectory(
    vehicle: Annotated[str, typer.Argument(help="Vehicle id.")],
    session: Annotated[str, typer.Argument(help="Session id.")],
    fmt: Annotated[
        TrajectoryOutFormat, typer.Option("--format", help="File format.")
    ] = TrajectoryOutFormat.kitti,
    out: Annotated[Path | None, typer.Option(help="Write to this file instead of stdout.")] = None,
    url: UrlOption = DEFAULT_URL,
    token: TokenOption = None,
) -> None:
    """Fetch a session's trajectory (KITTI, TUM or JSON) from the service."""
    try:
        with _client(url, token) as api:
            if fmt is TrajectoryOutFormat.json:
                stamps, poses = api.trajectory(vehicle, session)
                text = json.dumps({"stamps_s": stamps.tolist(), "poses": poses.tolist()})
            else:
                text = api.trajectory_text(vehicle, session, fmt.value)
        if out is None:
            typer.echo(text, nl=not text.endswith("\n"))
        else:
            from core.io import atomic_write_bytes

            atomic_write_bytes(out, text.encode())
            typer.echo(f"{len(text.splitlines())} lines -> {out}", err=True)
    except (RandtError, OSError) as exc:
        raise _fail(exc) from exc


@tiles_app.command("maps")
def tiles_maps(url: UrlOption = DEFAULT_URL, token: TokenOption = None) -> None:
    """List the maps: name, tiles, points."""
    try:
        with _client(url, token) as api:
            rows = api.maps()
    except (RandtError, OSError) as exc:
        raise _fail(exc) from exc
    typer.echo(f"{'map':<32} {'tiles':>6} {'points':>10}")
    for m in rows:
        typer.echo(f"{m['name']:<32} {m['tiles']:>6} {m['points']:>10}")


@tiles_app.command("list")
def tiles_list(
    map_name: Annotated[str, typer.Argument(metavar="MAP", help="Map name.")] = "default",
    url: UrlOption = DEFAULT_URL,
    token: TokenOption = None,
) -> None:
    """List a map's tiles: id, points, version, PDU."""
    try:
        with _client(url, token) as api:
            index = api.tiles(map_name)
    except (RandtError, OSError) as exc:
        raise _fail(exc) from exc
    typer.echo(f"{'tile':<12} {'points':>8} {'version':>8} {'pdu':>7}")
    for t in index["tiles"]:
        typer.echo(f"{t['id']:<12} {t['points']:>8} {t['version']:>8} {t['pdu']:>7.3f}")


@tiles_app.command("download")
def tiles_download(
    map_name: Annotated[str, typer.Argument(metavar="MAP", help="Map name, e.g. default.")],
    out: Annotated[Path, typer.Argument(help="Folder for <ix>_<iy>.pcd + pointcloud_map_metadata.yaml.")],
    url: UrlOption = DEFAULT_URL,
    token: TokenOption = None,
) -> None:
    """Download every tile of a map in Autoware's divided-map layout (only changed tiles again)."""
    try:
        with _client(url, token) as api:
            r = api.download_map(map_name, out)
    except (RandtError, OSError) as exc:
        raise _fail(exc) from exc
    typer.echo(
        f"{r.tiles} tiles ({r.downloaded} downloaded, {r.unchanged} unchanged), {r.points} points -> {out}"
    )


@tiles_app.command("export")
def tiles_export(
    map_name: Annotated[str, typer.Argument(metavar="MAP", help="Map name, e.g. default.")],
    out: Annotated[Path, typer.Argument(help="Output file (.pcd, .ply or .las).")],
    fmt: Annotated[CloudOutFormat | None, typer.Option("--format", help="Default: OUT's suffix.")] = None,
    bbox: Annotated[
        str | None, typer.Option(help="Only points in x_min,y_min,x_max,y_max (map metres).")
    ] = None,
    url: UrlOption = DEFAULT_URL,
    token: TokenOption = None,
) -> None:
    """Export the merged map (or a box of it) as one point cloud file."""
    try:
        box = None
        if bbox is not None:
            values = tuple(float(v) for v in bbox.split(","))
            if len(values) != 4:
                raise ValueError(f"--bbox needs four numbers x_min,y_min,x_max,y_max, got {bbox!r}")
            box = values
        with _client(url, token) as api:
            n = api.export(map_name, out, fmt.value if fmt else None, bbox=box)  # type: ignore[arg-type]
    except (RandtError, OSError, ValueError) as exc:
        raise _fail(exc) from exc
    typer.echo(f"{n} points -> {out}")


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


def _raise_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _map_folder_stats(folder: Path, pdu_voxel_m: float) -> tuple[int, int, float | None]:
    """Tiles, points and PDU of an Autoware tile folder (the store's ``maps/<map>/``)."""
    import numpy as np

    from core.io import read_cloud
    from core.metrics.cloud import pdu

    files = sorted(folder.glob("*.pcd"))
    if not files:
        return 0, 0, None
    xyz = np.concatenate([read_cloud(f).xyz for f in files])
    return len(files), int(xyz.shape[0]), float(pdu(xyz, pdu_voxel_m))


@app.command()
def demo(
    vehicles: Annotated[int, typer.Option(min=1, help="Simulated vehicles.")] = 3,
    duration: Annotated[
        float, typer.Option(min=0.5, help="Simulated seconds of driving per vehicle.")
    ] = 10.0,
    exit_: Annotated[
        bool, typer.Option("--exit", help="Stop after the summary instead of serving on.")
    ] = False,
    data_dir: Annotated[
        Path | None, typer.Option(help="Service data directory (default: a new temporary folder).")
    ] = None,
    http_port: Annotated[int, typer.Option(help="HTTP port (a free one if taken; 0 = any).")] = 8080,
    zenoh_port: Annotated[int, typer.Option(help="Zenoh port (a free one if taken; 0 = any).")] = 7447,
    speed: Annotated[float, typer.Option(min=0.0, help="Mean speed of the vehicles, m/s.")] = 6.0,
    azimuth: Annotated[int, typer.Option(min=100, help="LiDAR firings per revolution.")] = 2000,
    progress: Annotated[bool, typer.Option(help="Show the fleet's progress bar.")] = True,
) -> None:
    """The fleet demo: the service, a simulated fleet, errors against ground truth, then the map.

    Starts the service on embedded defaults (Zenoh peer and HTTP on 127.0.0.1), drives VEHICLES
    simulated vehicles for DURATION simulated seconds each (a child ``randt simulate``, flow
    controlled so no scan is dropped), prints per vehicle the trajectory error against the
    simulator's ground truth, the map's PDU, where the tiles are and the viewer's URL, and keeps
    serving until Ctrl-C (or stops at once with --exit).
    """
    import os
    import subprocess
    import tempfile
    import threading
    import time

    import httpx
    import uvicorn
    from pydantic import ValidationError

    from clients.fleet import summary_table
    from service.app import create_app
    from service.settings import ServiceSettings

    data = data_dir or Path(tempfile.mkdtemp(prefix="randt-demo-"))
    logging.getLogger("core").setLevel(logging.ERROR)  # fallbacks are counted in the summary instead
    zport, z_ok = _usable_port(zenoh_port)
    hport, h_ok = _usable_port(http_port)
    for name, wanted, got, ok in (("Zenoh", zenoh_port, zport, z_ok), ("HTTP", http_port, hport, h_ok)):
        if not ok:
            typer.echo(f"randt demo: {name} port {wanted} is taken, using {got}", err=True)
    endpoint = f"tcp/127.0.0.1:{zport}"
    try:
        settings = ServiceSettings(
            data_dir=data,
            zenoh_mode="peer",
            listen=(endpoint,),
            connect=(),
            http_host="127.0.0.1",
            http_port=hport,
            # Every requested vehicle is admitted: the demo's vehicles wait for their answers
            # (clients/fleet.py's window), so they pace themselves instead of overloading.
            max_sessions=0,
        )
    except ValidationError as exc:
        raise _fail(ValueError(str(exc.errors()[0]["msg"]))) from exc
    base = f"http://127.0.0.1:{hport}"
    server = uvicorn.Server(
        uvicorn.Config(create_app(settings), host="127.0.0.1", port=hport, log_level="warning")
    )
    thread = threading.Thread(target=server.run, name="uvicorn", daemon=True)
    previous_sigterm = signal.signal(signal.SIGTERM, _raise_interrupt)

    def shutdown() -> None:
        server.should_exit = True
        if thread.is_alive():
            thread.join(60)  # uvicorn's lifespan stops the service: queues drained, tiles saved
        signal.signal(signal.SIGTERM, previous_sigterm)

    fleet_json = data / "demo-fleet.json"
    proc: subprocess.Popen[bytes] | None = None
    summarized = False
    try:
        thread.start()
        deadline = time.monotonic() + 60
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                raise _fail(ConnectionError(f"the service did not start on {base} (see the log above)"))
            time.sleep(0.1)
        n_scans = max(1, round(duration * 10.0))
        typer.echo(f"randt demo: service on Zenoh {endpoint} (peer) and {base}, data in {data}")
        typer.echo(
            f"simulating {vehicles} vehicles for {duration:g} s each: {n_scans} sweeps of a 64-beam LiDAR "
            f"({azimuth} firings a turn) at 10 Hz and {speed:g} m/s; each vehicle waits for its answers "
            "(at most 2 scans in flight), so no scan is dropped and simulated time runs slower than real "
            "time..."
        )
        cmd = [
            sys.executable, "-m", "service.cli", "simulate",
            "--vehicles", str(vehicles), "--duration", str(duration), "--speed", str(speed),
            "--azimuth", str(azimuth), "--window", "2", "--connect", endpoint, "--mode", "client",
            "--session", f"demo-{time.strftime('%Y%m%d-%H%M%S')}", "--json-out", str(fleet_json),
            *([] if progress else ["--no-progress"]),
        ]  # fmt: skip
        tic = time.monotonic()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
        rc = proc.wait()
        if rc not in (0, EXIT_INCOMPLETE) or not fleet_json.is_file():
            raise _fail(RuntimeError(f"the simulated fleet failed (randt simulate exit code {rc})"))
        wall = time.monotonic() - tic
        fleet = json.loads(fleet_json.read_text())
        with httpx.Client(base_url=base, timeout=30) as http:
            # wait until the matcher queues are empty and the flusher has written the tiles
            for _ in range(120):
                depths = http.get("/status").json().get("queue_depths", {})
                if not any(depths.values()):
                    break
                time.sleep(0.5)
            time.sleep(2.5 * settings.flush_interval_s)
            available = [
                p
                for p in ("/status", "/sessions", "/maps", "/maps/default/tiles", "/metrics", "/docs")
                if http.get(p).status_code == 200
            ]
            viewer = http.get("/").status_code == 200
        tiles_dir = data / "maps" / "default"
        n_tiles, n_points, map_pdu = _map_folder_stats(tiles_dir, 0.5)
        total = sum(v["scans"] for v in fleet["vehicles"])
        typer.echo(
            f"\nfleet done in {wall:.0f} s ({total / max(wall, 1e-9):.1f} scans/s); "
            "errors against ground truth:"
        )
        for line in summary_table(fleet["vehicles"]):
            typer.echo(line)
        typer.echo(
            "(ATE: RMS position error in the shared map frame; RPE: frame-to-frame error; drift: end-to-end "
            "translation error per distance driven)"
        )
        pdu_text = "n/a" if map_pdu is None else f"{map_pdu:.3f}"
        typer.echo(
            f"map default: {n_tiles} tiles, {n_points} points, PDU {pdu_text} (0.5 m voxels; 1 = uniform)"
        )
        typer.echo(f"tiles (Autoware layout): {tiles_dir}")
        typer.echo(f"viewer: {base}/" if viewer else "viewer: not available in this version")
        typer.echo(f"REST: {' '.join(base + p for p in available)}")
        typer.echo(f"download the map: randt tiles download default ./map --url {base}")
        summarized = True
        if not exit_:
            typer.echo("serving until Ctrl-C")
            while thread.is_alive():
                thread.join(0.5)
    except KeyboardInterrupt:
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
        typer.echo("\nrandt demo: stopping", err=True)
    finally:
        shutdown()
    # Everything is flushed and closed. Leave without interpreter finalization: Zenoh's native
    # threads may still release Python callbacks of the closed session, and one run in about ten
    # aborted there ("FATAL: exception not rethrown", exit 134) after a complete, correct summary.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0 if summarized else EXIT_INTERRUPTED)


@app.command("config")
def show_config() -> None:
    """Print the default registration settings as JSON."""
    from core.config import RegistrationSettings

    typer.echo(RegistrationSettings().model_dump_json(indent=2))


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
