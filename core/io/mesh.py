"""Triangle meshes: the OFF reader and area-weighted surface sampling.

Used for the ModelNet40 registration protocol: sample points uniformly on a CAD mesh, apply a
known transform, register. Only what that needs lives here; general mesh processing does not.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError

__all__ = ["read_off", "sample_surface"]

logger = logging.getLogger(__name__)

# "OFF", "COFF", "NOFF"... optionally glued to the counts, as in ModelNet's "OFF490 518 0".
_OFF_HEADER = re.compile(r"^\s*([A-Z]*OFF)\s*(.*)$")
# Blank and "#" comment lines, removed in one pass before numpy parses the rest.
_BLANK_OR_COMMENT_LINE = re.compile(r"^[ \t\r\f\v]*(?:#[^\n]*)?(?:\n|\Z)", re.MULTILINE)


def _fan_triangulate(indices: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons stored as rows of a padded index array.

    Parameters
    ----------
    indices:
        (F, K) int64, polygon ``f`` uses ``indices[f, :sizes[f]]``; the rest is padding.
    sizes:
        (F,) int64 vertex counts, each ``>= 3`` and ``<= K``.

    Returns
    -------
    np.ndarray
        (T, 3) int64 triangles ``(v0, v_i, v_i+1)``, in polygon order.
    """
    n_faces, width = indices.shape
    corner = np.arange(1, width - 1)  # (K-2,)
    triangles = np.stack(
        [
            np.broadcast_to(indices[:, :1], (n_faces, corner.size)),
            indices[:, corner],
            indices[:, corner + 1],
        ],
        axis=-1,
    )  # (F, K-2, 3)
    valid = corner[None, :] < (sizes[:, None] - 1)
    return np.ascontiguousarray(triangles[valid], dtype=np.int64)


def _parse_faces(lines: list[str], path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Parse OFF face lines into a padded (F, K) index array and (F,) polygon sizes."""
    try:
        # Fast path: every line has the same number of integer tokens (all-triangle meshes).
        table = np.loadtxt(lines, dtype=np.int64, ndmin=2)
    except ValueError:
        # Mixed polygon sizes or per-face colours: split line by line (faces, not points).
        rows = [line.split() for line in lines]
        try:
            sizes = np.array([int(row[0]) for row in rows], dtype=np.int64)
            width = int(sizes.max())
            if any(len(row) < 1 + int(n) for row, n in zip(rows, sizes, strict=True)):
                raise ValueError("a face line has fewer indices than its vertex count")
            indices = np.array(
                [row[1 : 1 + n] + ["0"] * (width - n) for row, n in zip(rows, sizes, strict=True)],
                dtype=np.int64,
            )
        except (ValueError, IndexError) as exc:
            raise FormatError(f"{path}: malformed OFF face line: {exc}") from exc
        return indices, sizes
    sizes = table[:, 0]
    width = int(sizes.max())
    if table.shape[1] < 1 + width:
        raise FormatError(f"{path}: a face line has fewer indices than its vertex count")
    return table[:, 1 : 1 + width], sizes


def read_off(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read an OFF mesh and fan-triangulate its polygons.

    Handles the ModelNet quirk where the counts are glued to the keyword (``"OFF490 518 0"``),
    ``#`` comment lines, blank lines and extra per-vertex or per-face columns (colours), which
    are ignored.

    Parameters
    ----------
    path:
        An ``.off`` file (ASCII).

    Returns
    -------
    vertices:
        (V, 3) float64.
    faces:
        (F', 3) int64 triangles indexing ``vertices``; a polygon with ``n`` corners becomes
        ``n - 2`` triangles, so ``F' >= F``.

    Raises
    ------
    NotFoundError
        ``path`` does not exist.
    FormatError
        Missing or malformed header, too few lines, bad numbers, polygons with fewer than three
        corners, or indices outside ``[0, V)``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii", errors="strict")
    except FileNotFoundError as exc:
        raise NotFoundError(f"{path}: no such file") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot read as ASCII OFF: {exc}") from exc

    lines = _BLANK_OR_COMMENT_LINE.sub("", text).splitlines()
    if not lines:
        raise FormatError(f"{path}: empty OFF file")
    match = _OFF_HEADER.match(lines[0])
    if match is None:
        raise FormatError(f"{path}: first line {lines[0][:40]!r} does not start with 'OFF'")
    if match.group(2).strip():  # ModelNet: "OFF490 518 0"
        counts_line, body = match.group(2), lines[1:]
    elif len(lines) > 1:
        counts_line, body = lines[1], lines[2:]
    else:
        raise FormatError(f"{path}: OFF header has no vertex/face counts")
    try:
        n_vertices, n_faces = (int(v) for v in counts_line.split()[:2])
    except ValueError as exc:
        raise FormatError(f"{path}: malformed OFF counts line {counts_line!r}") from exc
    if n_vertices < 0 or n_faces < 0:
        raise FormatError(f"{path}: negative OFF counts {n_vertices} {n_faces}")
    if len(body) < n_vertices + n_faces:
        raise FormatError(
            f"{path}: header announces {n_vertices} vertices and {n_faces} faces "
            f"but only {len(body)} data lines follow"
        )
    if n_vertices == 0 or n_faces == 0:
        raise FormatError(f"{path}: OFF mesh has {n_vertices} vertices and {n_faces} faces")

    try:
        vertices = np.loadtxt(body[:n_vertices], dtype=np.float64, usecols=(0, 1, 2), ndmin=2)
    except ValueError as exc:
        raise FormatError(f"{path}: malformed OFF vertex line: {exc}") from exc

    indices, sizes = _parse_faces(body[n_vertices : n_vertices + n_faces], path)
    if sizes.min() < 3:
        raise FormatError(f"{path}: a face has {int(sizes.min())} corners (need at least 3)")
    faces = _fan_triangulate(indices, sizes)
    if faces.min() < 0 or faces.max() >= n_vertices:
        raise FormatError(
            f"{path}: face index out of range [0, {n_vertices}): "
            f"min {int(faces.min())}, max {int(faces.max())}"
        )
    logger.debug("read %s: %d vertices, %d triangles", path, n_vertices, len(faces))
    return vertices, faces


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n_points: int, *, seed: int = 0) -> np.ndarray:
    """Sample points uniformly on a triangle mesh's surface.

    A triangle is chosen with probability proportional to its area, then a point is drawn
    uniformly inside it with the square-root trick (Osada et al., "Shape distributions", 2002,
    eq. 1): ``p = (1 - √r1)·a + √r1·(1 - r2)·b + √r1·r2·c`` with ``r1, r2 ~ U(0, 1)``.

    Parameters
    ----------
    vertices:
        (V, 3) vertex positions.
    faces:
        (F, 3) integer triangle indices into ``vertices``.
    n_points:
        Number of points to draw, ``>= 0``.
    seed:
        Seed of the :func:`numpy.random.default_rng` generator; equal seeds give equal points.

    Returns
    -------
    np.ndarray
        (n_points, 3) float64 points on the surface.

    Raises
    ------
    InvalidCloudError
        Wrong shapes, indices out of range, or a mesh of zero total area.
    ValueError
        ``n_points`` is negative.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise InvalidCloudError(f"vertices must be (V, 3) with V > 0, got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InvalidCloudError(f"faces must be (F, 3) with F > 0, got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise InvalidCloudError(f"faces must hold integers, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InvalidCloudError(f"face indices must lie in [0, {len(vertices)})")
    if n_points < 0:
        raise ValueError(f"n_points must be >= 0, got {n_points}")

    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)  # (F,)
    cdf = np.cumsum(areas)
    total = cdf[-1]
    if not np.isfinite(total) or total <= 0.0:
        raise InvalidCloudError(f"mesh has no usable surface area (total area {total})")

    rng = np.random.default_rng(seed)
    # side="right" never picks a zero-area triangle: its cdf interval is empty.
    chosen = np.searchsorted(cdf, rng.random(n_points) * total, side="right")
    chosen = np.minimum(chosen, len(faces) - 1)
    r1, r2 = rng.random((2, n_points, 1))
    s = np.sqrt(r1)
    points: np.ndarray = (1.0 - s) * a[chosen] + s * (1.0 - r2) * b[chosen] + s * r2 * c[chosen]
    return points
