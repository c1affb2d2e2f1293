"""PDU against the voxel it is measured at: why the paper's 0.92 depends on a choice it does not state.

Run from the repository root::

    python bench/pdu_scale.py [--markdown]

The RANDT map of KITTI 00 frames 0-10 (``../shared/data/kitti00``, the service's defaults:
density equalization at 0.2 m voxels, one point per voxel) and the raw sweeps accumulated at the
same poses, scored with the plain reading of the paper's index, ``PDU = 1 - sigma / mean`` of the
point counts of the occupied voxels (:func:`randt.core.metrics.cloud.pdu`), at measurement voxels from
the equalization voxel up. Equalization makes every occupied 0.2 m voxel hold one point, so the
map's PDU at exactly 0.2 m (the same grid) is 1 by construction; on any other grid a voxel holds
as many equalized points as the surfaces it cuts, and the index falls. Also: the voxel at which
the map's PDU crosses the paper's 0.92 (by linear interpolation between measured voxels).
Issue 18 (the paper, checked) builds on this; it is one piece of it.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from common import git_line, heading, machine_line, progress, table  # first: one BLAS thread

from randt.core.io import read_cloud
from randt.core.mapping import MapBuilder
from randt.core.metrics.cloud import pdu
from randt.core.shared_data import data_root
from randt.core.transforms import transform_points

#: Measurement voxels, metres: the equalization voxel, just above it, then coarser.
VOXELS_M = (0.2, 0.201, 0.205, 0.21, 0.22, 0.25, 0.3, 0.4, 0.5, 0.75, 1.0, 1.5, 2.0)
PAPER_PDU = 0.92


def crossing(voxels: list[float], values: list[float], level: float) -> float | None:
    """The first voxel at which ``values`` falls below ``level`` (linear between samples)."""
    for i in range(len(voxels) - 1):
        p0, p1 = values[i], values[i + 1]
        if p0 >= level > p1:
            return voxels[i] + (p0 - level) / (p0 - p1) * (voxels[i + 1] - voxels[i])
    return None


def main() -> None:
    parser = argparse.ArgumentParser(prog="pdu_scale.py", description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    files = sorted((data_root() / "kitti00" / "velodyne").glob("*.bin"))
    if not files:
        sys.exit(f"no KITTI 00 sweeps in {data_root() / 'kitti00/velodyne'} (set RANDT_SHARED_DATA)")
    print(heading("PDU against the measurement voxel (KITTI 00, frames 0-10)", args.markdown))
    print(machine_line({}))
    print(git_line())
    builder = MapBuilder()
    raw = []
    for f in files:
        cloud = read_cloud(f)
        builder.add_scan(cloud.xyz)
        raw.append(transform_points(builder.poses[-1], cloud.xyz))
        progress(f"{f.name} mapped")
    raw_xyz = np.vstack(raw)
    map_xyz = np.vstack([t.points for t in builder.tiles.tiles()]).astype(np.float64)
    voxels = list(VOXELS_M)
    on_map = [pdu(map_xyz, v) for v in voxels]
    on_raw = [pdu(raw_xyz, v) for v in voxels]
    rows = [[f"{v:g}", f"{a:.3f}", f"{b:.3f}"] for v, a, b in zip(voxels, on_map, on_raw, strict=True)]
    print(
        f"map: {len(map_xyz)} points (equalized at {builder.tiles.voxel_size_m:g} m, "
        f"{builder.tiles.max_points_per_voxel} per voxel); raw: {len(raw_xyz)} points"
    )
    print(table(["voxel m", "PDU map", "PDU raw sweeps"], rows, args.markdown))
    at = crossing(voxels, on_map, PAPER_PDU)
    where = "never below it" if at is None else f"below it from {at:.4f} m on"
    print(f"\nThe map's PDU against the paper's {PAPER_PDU}: {where}.")


if __name__ == "__main__":
    main()
