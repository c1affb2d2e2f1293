"""``randt map`` and ``randt eval``: a map and poses from a recorded sequence, and their errors."""

from __future__ import annotations

import json
import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer

from randt.cli.errors import input_file
from randt.core.errors import FormatError


def map_sequence(
    dataset_dir: Annotated[
        Path,
        typer.Argument(
            help="KITTI sequence folder, a folder of scan files, or a ROS bag (rosbag2 folder with "
            "sqlite3 or MCAP, or ROS 1 .bag; needs randt-fleet[ros2])."
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="Output folder (created).")],
    topic: Annotated[
        str | None,
        typer.Option(help="A bag's PointCloud2 topic (default: its only one)."),
    ] = None,
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
    import numpy as np
    from tqdm import tqdm

    from randt.core.datasets import open_scans
    from randt.core.io import atomic_write_bytes, write_kitti_poses, write_tum
    from randt.core.mapping import MapBuilder
    from randt.core.metrics.cloud import pdu

    seq = open_scans(dataset_dir, topic=topic, start=start, end=end)
    builder = MapBuilder(tile_size_m=tile_size, map_voxel_m=map_voxel)
    scans = []
    bar = tqdm(total=len(seq), unit="scan", disable=not progress, file=sys.stderr)
    for i, cloud in enumerate(seq):  # one pass: a bag is opened once, not per sweep
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
    summary: dict[str, Any] = {
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
    n_ok = sum(s["status"] != "fallback" for s in scans)
    typer.echo(
        f"{len(scans)} scans ({n_ok} matched), {summary['map']['tiles']} tiles, "
        f"{summary['map']['points']} map points, PDU {summary['map']['pdu']:.3f} -> {out}"
    )


class TrajectoryFormat(StrEnum):
    kitti = "kitti"
    tum = "tum"


def eval_trajectory(
    reference: Annotated[Path, typer.Option("--reference", help="Reference trajectory file.")],
    estimate: Annotated[Path, typer.Option("--estimate", help="Estimated trajectory file.")],
    fmt: Annotated[TrajectoryFormat, typer.Option("--format", help="File format of both.")] = (
        TrajectoryFormat.kitti
    ),
    calib: Annotated[
        Path | None,
        typer.Option(
            help="KITTI calib.txt (or its sequence folder): REFERENCE is KITTI ground truth in the left "
            "camera's frame and is converted to the LiDAR frame with its Tr, the frame randt map writes. "
            "Default: a calib.txt found next to REFERENCE (DIR/poses.txt) or in KITTI's layout "
            "(poses/NN.txt, sequences/NN/calib.txt)."
        ),
    ] = None,
    no_calib: Annotated[
        bool, typer.Option("--no-calib", help="Compare both files as given, even if a calib.txt is found.")
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print exactly one JSON object.")] = False,
) -> None:
    """ATE, RPE and KITTI relative errors of ESTIMATE against REFERENCE, in the frames it prints.

    KITTI's ground truth (poses.txt) holds left-camera poses while randt map writes LiDAR poses: with
    a calib.txt (--calib, or found next to REFERENCE) the reference is converted (inv(Tr) P Tr)
    before comparing; the output says which frames were compared.
    """
    from randt.core.io import kitti_velodyne_poses, read_kitti_calib, read_kitti_poses, read_tum
    from randt.core.metrics.trajectory import evaluate_trajectory

    if calib is not None and no_calib:
        raise ValueError("--calib and --no-calib exclude each other")
    if fmt is TrajectoryFormat.kitti:
        ref, est = read_kitti_poses(input_file(reference)), read_kitti_poses(input_file(estimate))
    else:
        ref, est = read_tum(input_file(reference))[1], read_tum(input_file(estimate))[1]
    if len(ref) != len(est):
        raise ValueError(f"{reference} has {len(ref)} poses but {estimate} has {len(est)}")
    calib_file, found = (None, False) if no_calib else _calib_file(calib, reference)
    if calib_file is not None:
        ref = kitti_velodyne_poses(ref, _velodyne_to_cam0(read_kitti_calib(calib_file), calib_file))
        how = "given" if not found else "found next to the reference"
        frames: dict[str, str | None] = {
            "reference": "lidar (KITTI left camera poses converted with Tr: inv(Tr) P Tr)",
            "estimate": "as given",
            "calib": str(calib_file),
        }
        said = (
            f"frames: reference converted from KITTI's left camera to the LiDAR with Tr of {calib_file} "
            f"({how})"
        )
    else:
        frames = {"reference": "as given", "estimate": "as given", "calib": None}
        said = (
            "frames: both as given"
            + (" (--no-calib)" if no_calib else "")
            + "; KITTI ground truth is in the left camera's frame: against randt map's LiDAR poses, "
            "pass --calib calib.txt"
        )
    report = evaluate_trajectory(ref, est)
    if as_json:
        typer.echo(json.dumps({**report, "frames": frames}))
        return
    ate, rpe = report["ate"], report["rpe"]
    typer.echo(said)
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


def _calib_file(calib: Path | None, reference: Path) -> tuple[Path | None, bool]:
    """The calib.txt to use and whether it was found (not given): ``--calib``, else next to REFERENCE."""
    if calib is not None:
        return (calib / "calib.txt" if calib.is_dir() else calib), False
    for candidate in (
        reference.parent / "calib.txt",  # a sequence folder: DIR/poses.txt, DIR/calib.txt
        reference.parent.parent / "sequences" / reference.stem / "calib.txt",  # poses/00.txt
    ):
        if candidate.is_file():
            return candidate, True
    return None, False


def _velodyne_to_cam0(calib: dict[str, Any], path: Path) -> Any:
    """``Tr`` (odometry calib.txt) or ``Tr_velo_to_cam`` (object calib) of a KITTI calibration."""
    for key in ("Tr", "Tr_velo_to_cam"):
        if key in calib:
            return calib[key]
    raise FormatError(f"{path}: no Tr (velodyne to camera 0) line")
