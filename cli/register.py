"""``randt register`` and ``randt demo-register``: two clouds, offline."""

from __future__ import annotations

import json
import os
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from randt.cli.errors import ExitCode, input_file
from randt.core.errors import FormatError, RandtError

if TYPE_CHECKING:
    import numpy as np

    from randt.core.io.clouds import PointCloud


class MethodChoice(StrEnum):
    randt = "randt"
    ndt = "ndt"
    icp_point = "icp-point"
    icp_plane = "icp-plane"


def _read_init(path: Path | None) -> np.ndarray | None:
    import numpy as np

    from randt.core.transforms import as_transform

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
    centroid_start: Annotated[
        bool,
        typer.Option(
            "--centroid-start",
            help="For object scans posed far apart: start from the translation that moves SOURCE's "
            "centroid onto TARGET's (randt.core.registration.centroid_start); not for LiDAR sweeps.",
        ),
    ] = False,
    fast_svd: Annotated[
        bool,
        typer.Option(
            "--fast-svd",
            help="The SVD step on the NDT solver's moving points with looser fences "
            "(randt.core.config.FAST_SVD_STEP): faster, less accurate on noisy clouds "
            "(docs/registration.md).",
        ),
    ] = False,
    dense_svd: Annotated[
        bool,
        typer.Option("--dense-svd", hidden=True, help="The default SVD step (kept for scripts)."),
    ] = False,
    global_: Annotated[
        bool,
        typer.Option(
            "--global",
            help="No initial guess: features, a robust solver, then NDT refinement "
            "(randt.core.global_registration); exit 15 when the pose is not to be trusted.",
        ),
    ] = False,
) -> None:
    """Register SOURCE to TARGET and print T_target_source, fitness and time."""
    if global_:
        if init is not None or centroid_start or method is not MethodChoice.randt:
            raise typer.BadParameter(
                "--global takes no --init or --centroid-start and refines with --method randt only"
            )
        _register_global(source, target, voxel, as_json, output)
        return

    from randt.core.config import FAST_SVD_STEP, RegistrationSettings
    from randt.core.io import read_cloud
    from randt.core.registration import register as do_register

    for flag, given in (("--fast-svd", fast_svd), ("--dense-svd", dense_svd)):
        if given and method is not MethodChoice.randt:
            raise typer.BadParameter(f"{flag} is RANDT's SVD step: use it with --method randt")
    if fast_svd and dense_svd:
        raise typer.BadParameter("--fast-svd and --dense-svd are two SVD steps: give one")
    if dense_svd:
        typer.echo("randt: note: --dense-svd is the default SVD step since 2026-11-26", err=True)
    if centroid_start and init is not None:
        raise typer.BadParameter("--centroid-start and --init are two initial guesses: give one")
    init_T = _read_init(None if init is None else input_file(init))
    src = read_cloud(input_file(source))
    tgt = read_cloud(input_file(target))
    if centroid_start:
        from randt.core.registration import centroid_start as start

        init_T = start(src.xyz, tgt.xyz)
    overrides: dict[str, object] = dict(FAST_SVD_STEP) if fast_svd else {}
    if voxel:
        overrides["voxel_sizes_m"] = tuple(voxel)
    settings = RegistrationSettings.for_method(method.value, **overrides)
    result = do_register(src.xyz, tgt.xyz, init_T, settings=settings)
    _report(
        src, result.T_target_source, output, result.to_dict() if as_json else None,
        f"method {result.method}  converged {result.converged}  iterations {result.iterations}\n"
        f"fitness (NVTL) {result.fitness:.4f}  transform probability "
        f"{result.transform_probability:.4f}  inlier ratio {result.inlier_ratio:.3f}\n"
        f"time {result.time_s:.3f} s  voxels {', '.join(f'{v:g}' for v in result.voxel_sizes_m)} m",
    )  # fmt: skip
    if not result.converged:
        typer.echo("randt: warning: registration did not converge", err=True)
        raise typer.Exit(ExitCode.NOT_CONVERGED)


def _report(
    src: PointCloud, T: np.ndarray, output: Path | None, as_json: dict[str, object] | None, summary: str
) -> None:
    """What both registrations print: SOURCE moved to ``output`` if given, then the JSON object
    (``as_json``) or the matrix and ``summary``."""
    from dataclasses import replace

    import numpy as np

    from randt.core.io import write_cloud
    from randt.core.transforms import transform_points

    if output is not None:
        write_cloud(output, replace(src, xyz=transform_points(T, src.xyz)))
    if as_json is not None:
        typer.echo(json.dumps(as_json))
        return
    with np.printoptions(precision=6, suppress=True):
        typer.echo(f"T_target_source =\n{T}")
    typer.echo(summary)


def _register_global(
    source: Path, target: Path, voxel: list[float] | None, as_json: bool, output: Path | None
) -> None:
    """``randt register --global``: :func:`randt.core.global_registration.register_global`."""

    from randt.core.config import RegistrationSettings
    from randt.core.global_registration import GlobalSettings, register_global
    from randt.core.io import read_cloud

    src = read_cloud(input_file(source))
    tgt = read_cloud(input_file(target))
    refine = RegistrationSettings(voxel_sizes_m=tuple(voxel)) if voxel else RegistrationSettings()
    settings = GlobalSettings(registration=refine)
    result = register_global(src.xyz, tgt.xyz, settings)
    _report(
        src, result.T_target_source, output, result.to_dict() if as_json else None,
        f"confident {result.confident}  consistent correspondences {result.n_inliers} of "
        f"{result.n_correspondences}  overlap {result.overlap:.2f}  NDT refinement kept "
        f"{result.refined}\ntime {result.time_s:.3f} s  feature voxel {result.voxel_m:g} m",
    )  # fmt: skip
    if not result.confident:
        typer.echo(f"randt: warning: the pose is not to be trusted: {result.reason}", err=True)
        raise typer.Exit(ExitCode.NOT_CONFIDENT)


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
    import numpy as np

    from randt.core.config import RegistrationSettings
    from randt.core.registration import register as do_register
    from randt.core.scenes import synthetic_room
    from randt.core.transforms import make_transform, transform_error, transform_points

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
    from randt.core.io import read_cloud

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
