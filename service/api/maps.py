"""``/maps``: the tiled maps, their tile index, tile downloads, Autoware metadata and merged exports.

Everything is served from the tiles *as last saved* (:meth:`SessionManager.durable_map
<randt.service.live_maps.LiveMaps.durable>`, immutable tile snapshots kept in memory), never
from the live grid that runs up to ``flush_interval_s`` ahead of the store: a version seen here
is on disk, so after a crash it neither goes back nor comes again with other content.

Tile downloads carry a strong ``ETag: "<version>-<digest>-<format>"`` (``digest``: the first 16
hex digits of the SHA-256 of the tile's float32 x y z intensity table, as its tile update's
``digest``) and ``Cache-Control: no-cache``; a request whose ``If-None-Match`` holds that ETag
gets **304 Not Modified** without a body, so a client (or the viewer, through the browser's cache)
refetches only the tiles that changed. Weak or older ETags (``W/"7-pcd"``) never match.
"""

from __future__ import annotations

import math
import threading
from typing import Annotated, Any

import numpy as np
import yaml
from fastapi import APIRouter, Depends, Header, Query, Request, Response, status
from fastapi.responses import StreamingResponse

from randt.core.errors import InvalidRequestError, NotFoundError
from randt.core.io.autoware import AUTOWARE_METADATA_NAME, PROJECTOR_INFO_NAME
from randt.core.metrics.cloud import pdu
from randt.core.tiles import Tile, TileGrid, tile_id
from randt.service.api.deps import (
    WRITER_RESPONSES,
    MapName,
    TileIx,
    get_manager,
    require_reader,
    require_writer,
)
from randt.service.api.encoding import CLOUD_MEDIA_TYPES, CloudFormat, cloud_bytes, stream_cloud
from randt.service.api.models import (
    DeletedMap,
    ErrorBody,
    GraphEdge,
    GraphKeyframe,
    MapGraph,
    MapIndex,
    MapSummary,
    TileBoundsModel,
    TileIndex,
    TileInfo,
)
from randt.service.api.views import map_summary
from randt.service.live_maps import DurableMap
from randt.service.sessions import SessionManager

__all__ = ["PduCache", "parse_bbox", "router"]

router = APIRouter(prefix="/maps", tags=["maps"], dependencies=[Depends(require_reader)])
ManagerDep = Annotated[SessionManager, Depends(get_manager)]
FormatQuery = Annotated[CloudFormat, Query(description="pcd (binary), ply (binary) or las (1.4)")]
BboxQuery = Annotated[
    str | None,
    Query(
        description="x_min,y_min,x_max,y_max in map metres: only tiles (points) in this box",
        examples=["-40,-40,40,40"],
    ),
]
_404: dict[int | str, dict[str, Any]] = {404: {"model": ErrorBody, "description": "no such map or tile"}}
_422: dict[int | str, dict[str, Any]] = {422: {"model": ErrorBody, "description": "malformed coordinates"}}


class PduCache:
    """Per-tile PDU by ``(grid, tile id, version, voxel)``: a tile's PDU changes only with its version.

    Held by the app (``app.state.pdu_cache``) so that separate apps in one process never share
    entries. Bounded: cleared when it exceeds ``max_entries``.
    """

    def __init__(self, max_entries: int = 100_000) -> None:
        self._values: dict[tuple[int, str, int, float], float] = {}
        self._lock = threading.Lock()
        self._max = max_entries

    def get(self, grid: TileGrid, tile: Tile, voxel_m: float) -> float:
        key = (id(grid), tile.id, tile.version, voxel_m)
        with self._lock:
            value = self._values.get(key)
        if value is None:
            value = _tile_pdu(tile, voxel_m)
            with self._lock:
                if len(self._values) >= self._max:
                    self._values.clear()
                self._values[key] = value
        return value


def _tile_pdu(tile: Tile, voxel_m: float) -> float:
    """PDU of one tile at ``voxel_m``, voxels aligned to the tile's corner (as ``TileGrid.tile_pdu``)."""
    local = tile.points.astype(np.float64)
    local[:, :2] -= np.array(tile.bounds.cell_min_xy, dtype=np.float64)
    value = float(pdu(local, voxel_m))
    return value if math.isfinite(value) else 0.0


def parse_bbox(text: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """``"x0,y0,x1,y1"`` -> ``((x0, y0), (x1, y1))``; 422 unless four finite numbers with x0<=x1, y0<=y1."""
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InvalidRequestError(f"bbox must be four finite numbers x_min,y_min,x_max,y_max; got {text!r}")
    x0, y0, x1, y1 = values
    if x0 > x1 or y0 > y1:
        raise InvalidRequestError(f"bbox is inverted: ({x0:g}, {y0:g}) is not below ({x1:g}, {y1:g})")
    return (x0, y0), (x1, y1)


def _etag(tile: Tile, digest: str, fmt: str) -> str:
    """The strong ETag of a saved tile in one format: version, content digest, format."""
    return f'"{tile.version}-{digest}-{fmt}"'


def _matches(if_none_match: str | None, etag: str) -> bool:
    """Whether an ``If-None-Match`` header (a list, or ``*``) holds ``etag`` (RFC 9110: the weak
    comparison, but our ETags are strong and name the content, so a ``W/`` one never matches)."""
    if not if_none_match:
        return False
    for candidate in if_none_match.split(","):
        c = candidate.strip()
        if c == "*" or c == etag:
            return True
    return False


def _saved_map(mgr: SessionManager, name: str) -> DurableMap:
    """The map ``name`` as last saved (404 if there is no such map)."""
    saved = mgr.maps.durable(name)
    if saved is None:
        merged = mgr.maps.merged_into(name)
        if merged is not None:
            raise NotFoundError(
                f"map {name!r} was merged into map {merged[0]!r} when session {merged[1]} joined it",
                resource="map",
                ident=name,
            )
        raise NotFoundError(resource="map", ident=name)
    return saved


@router.get("", response_model=MapIndex)
def list_maps(mgr: ManagerDep) -> MapIndex:
    """Every map: ``default`` (sessions with prior poses) and ``<vehicle>.<session>`` ones."""
    running = mgr.sessions()
    return MapIndex(maps=[map_summary(n, m, running) for n, m in sorted(mgr.maps.all_durable().items())])


@router.get("/{map}", response_model=MapSummary, responses=_404)
def get_map(map: MapName, mgr: ManagerDep) -> MapSummary:
    """One map: tiles, points, tile and voxel size, extent, the sessions feeding it."""
    return map_summary(map, _saved_map(mgr, map), mgr.sessions())


@router.delete(
    "/{map}",
    response_model=DeletedMap,
    dependencies=[Depends(require_writer)],
    responses={
        **_404,
        **WRITER_RESPONSES,
        409: {"model": ErrorBody, "description": "running sessions fold scans into the map"},
    },
)
def delete_map(map: MapName, mgr: ManagerDep) -> DeletedMap:
    """Delete a map and its tiles from the store (needs the token).

    Refused with 409 while a running session folds scans into it: close those sessions first.
    The sessions' trajectories are kept. A later session with a prior pose starts a new
    ``default`` map.
    """
    return DeletedMap(map=map, tiles=mgr.delete_map(map))


@router.get("/{map}/graph", response_model=MapGraph, responses=_404)
def get_graph(map: MapName, mgr: ManagerDep) -> MapGraph:
    """The map's pose graph (docs/mapping.md): every keyframe with its live and optimized pose,
    and every loop verification (accepted ones are the graph's loop edges). 404 when the map has
    no graph (no keyframe yet, or the service runs with ``graph`` off)."""
    graph = mgr.graph
    state = None if graph is None else graph.snapshot(map)
    if state is None:
        raise NotFoundError(f"map {map!r} has no pose graph", resource="map", ident=map)
    keyframes = [
        GraphKeyframe(
            vehicle=vehicle,
            session=session,
            seq=kf.seq,
            index=kf.index,
            stamp_s=kf.stamp_s,
            live=kf.live.tolist(),
            pose=None if kf.optimized is None else kf.optimized.tolist(),
        )
        for (vehicle, session) in sorted(state.keyframes)
        for kf in state.session_keyframes((vehicle, session))
    ]
    return MapGraph(
        map=map,
        revision=state.revision,
        sessions=[f"{v}/{s}" for v, s in sorted(state.keyframes)],
        placed=[f"{v}/{s}" for v, s in sorted(state.placed)],
        keyframes=keyframes,
        loops=[
            GraphEdge(
                a=loop.a,
                b=loop.b,
                source=loop.source,  # type: ignore[arg-type]
                confident=loop.confident,
                accepted=loop.accepted,
                reason=loop.reason,
                n_inliers=loop.n_inliers,
            )
            for loop in state.loops
        ],
        refused_keyframes=state.n_refused,
        replaying=graph is not None and graph.replaying,
        joined={f"{v}/{s}": T.tolist() for (v, s), T in sorted(state.joined.items())},
    )


@router.get("/{map}/tiles", response_model=TileIndex, responses={**_404, **_422})
def tile_index(
    map: MapName,
    mgr: ManagerDep,
    request: Request,
    bbox: BboxQuery = None,
    x: Annotated[float | None, Query(description="radius query: centre x, map metres")] = None,
    y: Annotated[float | None, Query(description="radius query: centre y, map metres")] = None,
    radius: Annotated[float | None, Query(ge=0, description="radius query: metres (XY)")] = None,
    pdu_voxel_m: Annotated[float, Query(gt=0.05, le=20.0, description="voxel of the PDU")] = 0.5,
) -> TileIndex:
    """The map's tiles (ids, bounds, point counts, versions, PDU), optionally those a box or a circle touches.

    ``bbox=x_min,y_min,x_max,y_max`` selects the tiles whose cell meets the closed box;
    ``x=..&y=..&radius=..`` those whose cell comes within ``radius`` of ``(x, y)`` (Autoware's
    partial map loading). PDU is computed at ``pdu_voxel_m`` (0.5 m as ``randt map``; at the
    map's own voxel every tile would score 1 by construction).
    """
    saved = _saved_map(mgr, map)
    grid = saved.grid  # cell geometry only; the tiles listed are the saved ones
    query: dict[str, float] | None = None
    wanted: set[str] | None = None
    circle = (x, y, radius)
    if bbox is not None and any(v is not None for v in circle):
        raise InvalidRequestError("give either bbox or x, y and radius, not both")
    if bbox is not None:
        lo, hi = parse_bbox(bbox)
        wanted = set(grid.tiles_in_bbox(lo, hi))
        query = {"x_min": lo[0], "y_min": lo[1], "x_max": hi[0], "y_max": hi[1]}
    elif any(v is not None for v in circle):
        if x is None or y is None or radius is None:
            raise InvalidRequestError("a radius query needs x, y and radius")
        if not all(math.isfinite(v) for v in (x, y, radius)):
            raise InvalidRequestError("x, y and radius must be finite")
        wanted = set(grid.tiles_within_radius((x, y), radius))
        query = {"x": x, "y": y, "radius": radius}
    cache: PduCache = request.app.state.pdu_cache
    tiles = [t for t in saved.tiles() if wanted is None or t.id in wanted]
    return TileIndex(
        map=map,
        tile_size_m=grid.tile_size_m,
        voxel_size_m=grid.voxel_size_m,
        pdu_voxel_m=pdu_voxel_m,
        query=query,
        tiles=[
            TileInfo(
                id=t.id,
                ix=t.ix,
                iy=t.iy,
                version=t.version,
                points=t.n_points,
                bounds=TileBoundsModel(
                    cell_min_xy=t.bounds.cell_min_xy,
                    cell_max_xy=t.bounds.cell_max_xy,
                    min_xyz=t.bounds.min_xyz,
                    max_xyz=t.bounds.max_xyz,
                ),
                pdu=cache.get(grid, t, pdu_voxel_m),
                url=f"/maps/{map}/tiles/{t.ix}/{t.iy}",
            )
            for t in tiles
        ],
    )


@router.get(
    "/{map}/tiles/{ix}/{iy}",
    response_class=Response,
    responses={
        **_404,
        **_422,
        200: {"content": {t: {} for t in CLOUD_MEDIA_TYPES.values()}, "description": "the tile's points"},
        304: {"description": "If-None-Match matched the tile's current ETag"},
    },
)
def get_tile(
    map: MapName,
    ix: TileIx,
    iy: TileIx,
    mgr: ManagerDep,
    format: FormatQuery = "pcd",
    if_none_match: Annotated[str | None, Header(description="ETag(s) the client holds")] = None,
) -> Response:
    """One tile's points (float32 x y z intensity, map frame) as PCD, PLY or LAS, with its ETag."""
    saved = _saved_map(mgr, map)
    tid = tile_id(ix, iy)
    tile = saved.by_id.get(tid)
    if tile is None:  # tiles are never removed from a map; a new one appears once saved
        detail = f"tile {tid!r} of map {map!r} not found (holds no points, or not saved yet)"
        raise NotFoundError(detail, resource="tile", ident=tid)
    etag = _etag(tile, mgr.maps.tile_digest(map, tile), format)
    headers = {"ETag": etag, "Cache-Control": "no-cache", "X-Randt-Tile-Version": str(tile.version)}
    if _matches(if_none_match, etag):
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers=headers)
    headers["Content-Disposition"] = f'attachment; filename="{tile.id}.{format}"'
    body = cloud_bytes(format, tile.points, tile.intensity)
    return Response(body, media_type=CLOUD_MEDIA_TYPES[format], headers=headers)


@router.get(
    "/{map}/metadata.yaml",
    response_class=Response,
    responses={**_404, 200: {"content": {"application/yaml": {}}, "description": AUTOWARE_METADATA_NAME}},
)
def get_metadata(map: MapName, mgr: ManagerDep) -> Response:
    """Autoware's ``pointcloud_map_metadata.yaml``: resolutions, then ``<ix>_<iy>.pcd: [x_min, y_min]``.

    Download the tiles as ``<ix>_<iy>.pcd`` next to it and Autoware's ``pointcloud_map_loader``
    loads the map (the store holds exactly this layout under ``DATA/maps/<map>/``).
    """
    saved = _saved_map(mgr, map)
    size = saved.tile_size_m
    document: dict[str, object] = {"x_resolution": float(size), "y_resolution": float(size)}
    for t in saved.tiles():
        document[f"{t.id}.pcd"] = [int(t.ix) * size, int(t.iy) * size]
    text = yaml.safe_dump(document, sort_keys=False, default_flow_style=None)
    return Response(
        text,
        media_type="application/yaml",
        headers={"Content-Disposition": f'attachment; filename="{AUTOWARE_METADATA_NAME}"'},
    )


@router.get(
    "/{map}/map_projector_info.yaml",
    response_class=Response,
    responses={**_404, 200: {"content": {"application/yaml": {}}, "description": PROJECTOR_INFO_NAME}},
)
def get_projector_info(map: MapName, mgr: ManagerDep) -> Response:
    """Autoware's ``map_projector_info.yaml`` of a georeferenced map (``LocalCartesianUTM``: its
    geodetic origin, set by the first WGS84 prior; docs/mapping.md, "Georeferenced maps"); 404
    when the map has no geodetic origin (it is in a local frame)."""
    _saved_map(mgr, map)
    projection = mgr.projections.projection(map)
    if projection is None:
        raise NotFoundError(
            f"map {map!r} has no geodetic origin (a local frame: no WGS84 prior reached it)",
            resource="projection",
            ident=map,
        )
    text = yaml.safe_dump(projection.projector_info(), sort_keys=False, default_flow_style=False)
    return Response(
        text,
        media_type="application/yaml",
        headers={"Content-Disposition": f'attachment; filename="{PROJECTOR_INFO_NAME}"'},
    )


def _chunks(tiles: list[Tile], box: tuple[tuple[float, float], tuple[float, float]] | None) -> list[tuple]:
    """Per tile ``(xyz, intensity)``, cut to ``box`` when given (views of the snapshots otherwise)."""
    if box is None:
        return [(t.points, t.intensity) for t in tiles]
    lo, hi = np.asarray(box[0]), np.asarray(box[1])
    out = []
    for t in tiles:
        xy = t.points[:, :2].astype(np.float64)
        inside = np.all((xy >= lo) & (xy <= hi), axis=1)
        if inside.any():
            out.append((t.points[inside], t.intensity[inside]))
    return out


@router.get(
    "/{map}/export",
    response_class=StreamingResponse,
    responses={
        **_404,
        **_422,
        200: {"content": {t: {} for t in CLOUD_MEDIA_TYPES.values()}, "description": "the merged cloud"},
    },
)
def export_map(
    map: MapName, mgr: ManagerDep, format: FormatQuery = "pcd", bbox: BboxQuery = None
) -> Response:
    """The whole map (or the points in ``bbox``) as one cloud, streamed tile by tile.

    One consistent snapshot of the tiles is taken when the request arrives; later inserts are
    not in this download. Every format streams (LAS's bounds are computed from the snapshot
    first), so a download holds one tile's worth of output at a time.
    """
    saved = _saved_map(mgr, map)
    box = parse_bbox(bbox) if bbox is not None else None
    tiles = saved.tiles()
    if box is not None:
        keep = set(saved.grid.tiles_in_bbox(*box))
        tiles = [t for t in tiles if t.id in keep]
    chunks = _chunks(tiles, box)
    n_points = sum(xyz.shape[0] for xyz, _ in chunks)
    headers = {
        "Content-Disposition": f'attachment; filename="{map}.{format}"',
        "X-Randt-Points": str(n_points),
        "X-Randt-Tiles": str(len(tiles)),
    }
    return StreamingResponse(
        stream_cloud(format, n_points, chunks), media_type=CLOUD_MEDIA_TYPES[format], headers=headers
    )
