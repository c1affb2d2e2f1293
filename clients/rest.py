"""HTTP client of the service's REST API (``docs/api.md``): sessions, trajectories, map tiles.

``randt tiles ...`` is a thin shell over :class:`MapClient`. ::

    from randt.clients.rest import MapClient

    with MapClient("http://127.0.0.1:8080") as api:
        api.sessions()                                   # [{"id": "car-07/2024-05-01.a", ...}]
        stamps, poses = api.trajectory("car-07", "2024-05-01.a")  # (M,), (M, 4, 4)
        api.download_map("default", "map/")              # map/<ix>_<iy>.pcd + pointcloud_map_metadata.yaml
        api.export("default", "default.ply")             # one merged cloud (pcd, ply or las)

Endpoints used: ``GET /status``, ``GET /sessions``, ``GET /sessions/{vehicle}/{session}``,
``GET /sessions/{vehicle}/{session}/trajectory?format=json|kitti|tum``, ``GET /maps``,
``GET /maps/{map}/tiles``, ``GET /maps/{map}/tiles/{ix}/{iy}?format=pcd`` (with ETags),
``GET /maps/{map}/metadata.yaml``, ``GET /maps/{map}/export?format=pcd|ply|las``. Read endpoints
may be protected by the service's bearer token (``RANDT_API_TOKEN``): pass ``token``.

Downloads are incremental: :meth:`MapClient.download_map` remembers each tile's ETag in
``.randt-tile-etags.json`` next to the tiles and asks again with ``If-None-Match``, so a second
download of a growing map fetches only the tiles that changed. Every file is written atomically
(temporary file, rename) and the metadata file last, so a folder never lists a tile it lacks.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import httpx
import numpy as np

from randt.core.errors import NotFoundError, RandtError
from randt.core.io import atomic_write_bytes

__all__ = ["ApiError", "ApiNotFoundError", "DownloadResult", "MapClient"]

DEFAULT_URL = "http://127.0.0.1:8080"
ETAGS_FILE = ".randt-tile-etags.json"
METADATA_FILE = "pointcloud_map_metadata.yaml"
#: A georeferenced map's projection, as Autoware's map projection loader reads it.
PROJECTOR_INFO_FILE = "map_projector_info.yaml"
#: Where ``download_map(projector="MGRS")`` keeps the map as served (LocalCartesianUTM).
MGRS_SOURCE_DIR = ".randt-local-cartesian-utm"

CloudFormat = Literal["pcd", "ply", "las"]


class ApiError(RandtError):
    """The service answered with an HTTP error; ``status`` and the body's ``detail`` are kept."""

    def __init__(self, status: int, detail: str, url: str) -> None:
        super().__init__(f"HTTP {status} from {url}: {detail}")
        self.status = status
        self.detail = detail
        self.url = url


class ApiNotFoundError(ApiError, NotFoundError):
    """404: the session, map or tile does not exist."""


@dataclass(frozen=True)
class DownloadResult:
    """What :meth:`MapClient.download_map` did."""

    directory: Path
    tiles: int
    downloaded: int
    unchanged: int
    points: int


class MapClient:
    """A small synchronous client of the REST API (module docstring).

    Parameters
    ----------
    base_url:
        The service's HTTP address (``randt serve``'s default ``http://127.0.0.1:8080``).
    token:
        Bearer token, when the service protects reads (``RANDT_API_TOKEN``).
    timeout_s:
        Per-request timeout (connect and read) in seconds.
    transport:
        An ``httpx`` transport (tests pass ``httpx.MockTransport`` or an ASGI transport).
    """

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        *,
        token: str | None = None,
        timeout_s: float = 30.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.base_url = base_url.rstrip("/")
        self._http = httpx.Client(
            base_url=self.base_url, headers=headers, timeout=timeout_s, transport=transport
        )

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> MapClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ plumbing
    def _get(self, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.get(path, **kwargs)
        except httpx.TransportError as exc:
            raise ConnectionError(f"cannot reach the service at {self.base_url}: {exc}") from exc
        self._check(response)
        return response

    @staticmethod
    def _check(response: httpx.Response) -> None:
        if response.status_code < 400:
            return
        try:
            detail = str(response.json().get("detail", response.text))
        except (ValueError, AttributeError):
            detail = response.text[:200]
        url = str(response.request.url)
        cls = ApiNotFoundError if response.status_code == 404 else ApiError
        raise cls(response.status_code, detail, url)

    # ------------------------------------------------------------------ resources
    def status(self) -> dict[str, Any]:
        """``GET /status``: instance, uptime, sessions, counters, maps."""
        return self._get("/status").json()

    def sessions(self, state: str | None = None) -> list[dict[str, Any]]:
        """``GET /sessions``: every running and stored session (``state`` filters)."""
        return self._get("/sessions", params={"state": state} if state else None).json()

    def session(self, vehicle: str, session: str) -> dict[str, Any]:
        """``GET /sessions/{vehicle}/{session}``: one session in detail."""
        return self._get(f"/sessions/{vehicle}/{session}").json()

    def trajectory(
        self, vehicle: str, session: str, *, corrected: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """A session's trajectory: (M,) stamps in seconds and (M, 4, 4) ``T_frame_sensor``; with
        ``corrected`` as the pose graph corrected it (:meth:`trajectory_json` says in which map)."""
        poses = self.trajectory_json(vehicle, session, corrected=corrected).get("poses", [])
        stamps = np.array([p["stamp_s"] for p in poses], dtype=np.float64)
        mats = np.array([p["pose"] for p in poses], dtype=np.float64).reshape(-1, 4, 4)
        return stamps, mats

    def trajectory_json(self, vehicle: str, session: str, *, corrected: bool = False) -> dict[str, Any]:
        """``GET /sessions/{vehicle}/{session}/trajectory`` as JSON: frame, map, whether corrected,
        the poses."""
        params = {"format": "json", **({"corrected": "true"} if corrected else {})}
        return self._get(f"/sessions/{vehicle}/{session}/trajectory", params=params).json()

    def graph(self, map_name: str = "default") -> dict[str, Any]:
        """``GET /maps/{map}/graph``: the map's pose graph (keyframes, loop verifications, joins)."""
        return self._get(f"/maps/{map_name}/graph").json()

    def trajectory_text(self, vehicle: str, session: str, fmt: Literal["kitti", "tum"] = "kitti") -> str:
        """A session's trajectory as the KITTI or TUM text file ``randt map`` also writes."""
        return self._get(f"/sessions/{vehicle}/{session}/trajectory", params={"format": fmt}).text

    def maps(self) -> list[dict[str, Any]]:
        """``GET /maps``: name, tiles, points, extent of every map."""
        return self._get("/maps").json()["maps"]

    def tiles(self, map_name: str = "default") -> dict[str, Any]:
        """``GET /maps/{map}/tiles``: the tile index (ids, bounds, points, versions, PDU)."""
        return self._get(f"/maps/{map_name}/tiles").json()

    def tile(
        self, map_name: str, ix: int, iy: int, fmt: CloudFormat = "pcd", etag: str | None = None
    ) -> tuple[bytes | None, str | None]:
        """One tile's file and ETag; ``(None, etag)`` when ``etag`` is still current (304)."""
        headers = {"If-None-Match": etag} if etag else None
        r = self._get(f"/maps/{map_name}/tiles/{ix}/{iy}", params={"format": fmt}, headers=headers)
        if r.status_code == 304:
            return None, etag
        return r.content, r.headers.get("ETag")

    def metadata_yaml(self, map_name: str = "default") -> str:
        """Autoware's ``pointcloud_map_metadata.yaml`` of the map."""
        return self._get(f"/maps/{map_name}/metadata.yaml").text

    def projector_info_yaml(self, map_name: str = "default") -> str | None:
        """Autoware's ``map_projector_info.yaml`` of a georeferenced map; ``None`` when the map has
        no geodetic origin (raises :class:`ApiNotFoundError` when there is no such map)."""
        self._get(f"/maps/{map_name}")  # (a missing map is an error, a map without an origin is not)
        try:
            return self._get(f"/maps/{map_name}/map_projector_info.yaml").text
        except ApiNotFoundError:
            return None

    # ------------------------------------------------------------------ bulk
    def download_map(
        self,
        map_name: str,
        directory: str | os.PathLike[str],
        *,
        on_tile: Callable[[str, bool], None] | None = None,
        projector: Literal["LocalCartesianUTM", "MGRS"] = "LocalCartesianUTM",
    ) -> DownloadResult:
        """Download every tile of ``map_name`` into ``directory`` in Autoware's divided-map layout.

        Writes ``<ix>_<iy>.pcd`` per tile, ``map_projector_info.yaml`` when the map has a geodetic
        origin, and ``pointcloud_map_metadata.yaml`` last; tiles whose
        ETag has not changed since the last download into the same folder are not fetched again.
        ``on_tile(tile_id, downloaded)`` is called after each tile (for progress bars).

        ``projector="MGRS"``: a georeferenced map in Autoware's MGRS projection instead (the map
        as served is kept in ``directory/.randt-local-cartesian-utm`` for the next download, and
        written moved into its MGRS square: :func:`randt.core.geo.write_mgrs_map`, the ``geo`` extra).
        """
        if projector == "MGRS":
            from randt.core.geo import write_mgrs_map  # (pyproj, mgrs: the geo extra)

            local = Path(directory) / MGRS_SOURCE_DIR
            result = self.download_map(map_name, local, on_tile=on_tile)
            write_mgrs_map(local, Path(directory))
            return replace(result, directory=Path(directory))
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        etag_path = out / ETAGS_FILE
        try:
            etags: dict[str, str] = json.loads(etag_path.read_text()) if etag_path.is_file() else {}
        except ValueError:
            etags = {}
        index = self.tiles(map_name)
        downloaded = unchanged = points = 0
        for t in index["tiles"]:
            tid = t["id"]
            path = out / f"{tid}.pcd"
            known = etags.get(tid) if path.is_file() else None
            body, etag = self.tile(map_name, int(t["ix"]), int(t["iy"]), "pcd", etag=known)
            if body is None:
                unchanged += 1
            else:
                atomic_write_bytes(path, body)
                downloaded += 1
            if etag:
                etags[tid] = etag
            points += int(t.get("points", 0))
            if on_tile is not None:
                on_tile(tid, body is not None)
        atomic_write_bytes(etag_path, json.dumps(etags, indent=1, sort_keys=True).encode())
        projector_info = self.projector_info_yaml(map_name)  # (a georeferenced map's origin)
        if projector_info is None:
            (out / PROJECTOR_INFO_FILE).unlink(missing_ok=True)
        else:
            atomic_write_bytes(out / PROJECTOR_INFO_FILE, projector_info.encode())
        atomic_write_bytes(out / METADATA_FILE, self.metadata_yaml(map_name).encode())
        return DownloadResult(out, len(index["tiles"]), downloaded, unchanged, points)

    def export(
        self,
        map_name: str,
        path: str | os.PathLike[str],
        fmt: CloudFormat | None = None,
        *,
        bbox: tuple[float, float, float, float] | None = None,
    ) -> int:
        """Stream the merged map (or the points in ``bbox`` = x_min, y_min, x_max, y_max) into ``path``.

        The format defaults to ``path``'s suffix (``.pcd``, ``.ply``, ``.las``). Returns the point
        count the service announced (``X-Randt-Points``; -1 if it did not).
        """
        dest = Path(path)
        fmt = fmt or dest.suffix.lstrip(".").lower()  # type: ignore[assignment]
        if fmt not in ("pcd", "ply", "las"):
            raise ValueError(f"{dest}: export format must be pcd, ply or las (from --format or the suffix)")
        params: dict[str, str] = {"format": str(fmt)}
        if bbox is not None:
            params["bbox"] = ",".join(f"{v:g}" for v in bbox)
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", dir=dest.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                try:
                    with self._http.stream("GET", f"/maps/{map_name}/export", params=params) as r:
                        if r.status_code >= 400:
                            r.read()
                            self._check(r)
                        for chunk in r.iter_bytes():
                            fh.write(chunk)
                        n_points = int(r.headers.get("X-Randt-Points", -1))
                except httpx.TransportError as exc:
                    raise ConnectionError(f"cannot reach the service at {self.base_url}: {exc}") from exc
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, dest)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return n_points
