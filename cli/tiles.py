"""``randt tiles``: sessions, trajectories and map tiles of a running service, over HTTP."""

from __future__ import annotations

import json
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, cast

import typer

if TYPE_CHECKING:
    from randt.clients.rest import MapClient

UrlOption = Annotated[str, typer.Option("--url", envvar="RANDT_URL", help="The service's HTTP address.")]
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


class Projector(StrEnum):
    """A georeferenced map's projection, as Autoware's map projection loader names it."""

    LOCAL_CARTESIAN_UTM = "LocalCartesianUTM"
    MGRS = "MGRS"


def _client(url: str, token: str | None) -> MapClient:
    from randt.clients.rest import MapClient

    return MapClient(url, token=token)


def tiles_sessions(url: UrlOption = DEFAULT_URL, token: TokenOption = None) -> None:
    """List the service's sessions: id, state, map, scans, fallbacks."""
    with _client(url, token) as api:
        rows = api.sessions()
    typer.echo(f"{'id':<40} {'state':<8} {'map':<24} {'scans':>6} {'fallbacks':>9}")
    for s in rows:
        typer.echo(
            f"{s['id']:<40} {s['state']:<8} {s.get('map') or '-':<24} {s['scans']:>6} {s['fallbacks']:>9}"
        )


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
    with _client(url, token) as api:
        if fmt is TrajectoryOutFormat.json:
            stamps, poses = api.trajectory(vehicle, session)
            text = json.dumps({"stamps_s": stamps.tolist(), "poses": poses.tolist()})
        else:
            text_format = cast(Literal["kitti", "tum"], fmt.value)  # the members left once json is out
            text = api.trajectory_text(vehicle, session, text_format)
    if out is None:
        typer.echo(text, nl=not text.endswith("\n"))
    else:
        from randt.core.io import atomic_write_bytes

        atomic_write_bytes(out, text.encode())
        typer.echo(f"{len(text.splitlines())} lines -> {out}", err=True)


def tiles_maps(url: UrlOption = DEFAULT_URL, token: TokenOption = None) -> None:
    """List the maps: name, tiles, points."""
    with _client(url, token) as api:
        rows = api.maps()
    typer.echo(f"{'map':<32} {'tiles':>6} {'points':>10}")
    for m in rows:
        typer.echo(f"{m['name']:<32} {m['tiles']:>6} {m['points']:>10}")


def tiles_list(
    map_name: Annotated[str, typer.Argument(metavar="MAP", help="Map name.")] = "default",
    url: UrlOption = DEFAULT_URL,
    token: TokenOption = None,
) -> None:
    """List a map's tiles: id, points, version, PDU."""
    with _client(url, token) as api:
        index = api.tiles(map_name)
    typer.echo(f"{'tile':<12} {'points':>8} {'version':>8} {'pdu':>7}")
    for t in index["tiles"]:
        typer.echo(f"{t['id']:<12} {t['points']:>8} {t['version']:>8} {t['pdu']:>7.3f}")


def tiles_download(
    map_name: Annotated[str, typer.Argument(metavar="MAP", help="Map name, e.g. default.")],
    out: Annotated[Path, typer.Argument(help="Folder for <ix>_<iy>.pcd + pointcloud_map_metadata.yaml.")],
    projector: Annotated[
        Projector,
        typer.Option(
            help="a georeferenced map's projection (map_projector_info.yaml): as served, or moved into "
            "its MGRS square (the geo extra)"
        ),
    ] = Projector.LOCAL_CARTESIAN_UTM,
    url: UrlOption = DEFAULT_URL,
    token: TokenOption = None,
) -> None:
    """Download every tile of a map in Autoware's divided-map layout (only changed tiles again)."""
    with _client(url, token) as api:
        r = api.download_map(map_name, out, projector=projector.value)
    typer.echo(
        f"{r.tiles} tiles ({r.downloaded} downloaded, {r.unchanged} unchanged), {r.points} points -> {out}"
    )


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
    """Export the merged map (or a box of it) as one point cloud file; a georeferenced map's
    map_projector_info.yaml is written beside it (Autoware's map folder: the cloud, the yaml)."""
    from randt.clients.rest import PROJECTOR_INFO_FILE
    from randt.core.io.atomic import atomic_write_bytes

    box = None
    if bbox is not None:
        values = tuple(float(v) for v in bbox.split(","))
        if len(values) != 4:
            raise ValueError(f"--bbox needs four numbers x_min,y_min,x_max,y_max, got {bbox!r}")
        box = values
    with _client(url, token) as api:
        n = api.export(map_name, out, fmt.value if fmt else None, bbox=box)
        projector_info = api.projector_info_yaml(map_name)
    said = f"{n} points -> {out}"
    if projector_info is not None:
        atomic_write_bytes(out.parent / PROJECTOR_INFO_FILE, projector_info.encode())
        said += f", its projection -> {out.parent / PROJECTOR_INFO_FILE}"
    typer.echo(said)
