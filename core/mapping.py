"""Map building: the incremental matcher (Algorithm 2) feeding the tiled, density-equalized map.

One :class:`MapBuilder` per map and session stream offline (``randt map``); the service keeps one
matcher per session and folds them into one shared :class:`randt.core.tiles.TileGrid`.

Only sweeps whose pose was matched (or the first of a session) enter the map: a fallback pose is a
guess, and a guess must not write points into a shared map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from randt.core.config import RegistrationSettings
from randt.core.odometry import IncrementalMatcher, MatcherSettings, PosePrior, ScanResult
from randt.core.tiles import TileGrid
from randt.core.transforms import transform_points

__all__ = ["MapBuilder", "MapUpdate"]


@dataclass(frozen=True)
class MapUpdate:
    """One sweep's outcome: the matcher's result and the ids of the tiles it changed."""

    scan: ScanResult
    changed_tiles: tuple[str, ...]


class MapBuilder:
    """Feed sweeps in order; read poses from :attr:`poses` and the map from :attr:`tiles`.

    Parameters
    ----------
    tile_size_m : tile edge (integer metres; 20 as Autoware's divided maps).
    map_voxel_m : density-equalization voxel of the map.
    max_points_per_voxel : the equalization cap.
    """

    def __init__(
        self,
        matcher: MatcherSettings | None = None,
        registration: RegistrationSettings | None = None,
        *,
        tiles: TileGrid | None = None,
        tile_size_m: int = 20,
        map_voxel_m: float = 0.2,
        max_points_per_voxel: int = 1,
        period_s: float = 0.1,
    ) -> None:
        self.matcher = IncrementalMatcher(matcher, registration, period_s=period_s)
        self.tiles = tiles or TileGrid(
            tile_size_m=tile_size_m, voxel_size_m=map_voxel_m, max_points_per_voxel=max_points_per_voxel
        )

    @property
    def poses(self) -> list[np.ndarray]:
        return self.matcher.poses

    def add_scan(
        self,
        points_xyz: np.ndarray,
        *,
        intensity: np.ndarray | None = None,
        time_offset_s: np.ndarray | None = None,
        prior: PosePrior | None = None,
        stamp_s: float | None = None,
    ) -> MapUpdate:
        """Register one sweep and, if its pose is trusted, fold its points into the tiles.

        ``stamp_s`` is the sweep's time: with it a gap (skipped sweeps) is predicted as one.
        """
        result = self.matcher.register_scan(
            points_xyz, time_offset_s=time_offset_s, prior=prior, stamp_s=stamp_s
        )
        changed: list[str] = []
        if result.status != "fallback":
            world = transform_points(result.T_world_sensor, result.deskewed_xyz)
            inten = None if intensity is None else np.asarray(intensity, np.float32)[result.map_index]
            changed = self.tiles.insert(world, inten)
        return MapUpdate(scan=result, changed_tiles=tuple(changed))
