"""The ``randt`` command: a thin shell over ``core``, ``service`` and ``clients``.

Subcommands import what they need lazily so ``randt --help`` stays fast. Errors from the project's
exception tree become a one-line message on stderr and a non-zero exit code (the one place that
maps them, :data:`EXIT_CODES`).
"""

from __future__ import annotations

import json
import logging
import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from core.errors import (
    DegenerateProblemError,
    FormatError,
    InvalidCloudError,
    NotFoundError,
    RandtError,
    RegistrationFailedError,
)

app = typer.Typer(
    name="randt",
    help="randt-fleet: RANDT scan matching and fleet map building.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

#: Exit codes by error class (first match wins); 0 is success, 1 is an unexpected crash.
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
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


@app.command()
def demo(
    data_dir: Annotated[
        Path | None,
        typer.Option(help="Shared real data (default: $RANDT_DATA_DIR or ./../shared/data if present)."),
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

    root = data_dir or Path(os.environ.get("RANDT_DATA_DIR", Path.cwd().parent / "shared" / "data"))
    if not (root / "pairs").is_dir():
        typer.echo(f"(no real data at {root}: set --data-dir or RANDT_DATA_DIR to try the real pairs)")
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
        from core.metrics import pdu

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
        from core.metrics import evaluate_trajectory

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
