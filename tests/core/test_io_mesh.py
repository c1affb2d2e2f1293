"""Tests for randt.core.io.mesh: the OFF reader (ModelNet quirks) and area-weighted surface sampling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from randt.core.errors import FormatError, InvalidCloudError, NotFoundError
from randt.core.io import read_cloud, read_off, sample_surface
from tests.data import require_data

# A unit cube [0, 1]^3 as six quads (outward normals), to exercise fan triangulation.
CUBE_VERTICES = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=np.float64,
)
CUBE_QUADS = [
    [0, 3, 2, 1],  # z = 0
    [4, 5, 6, 7],  # z = 1
    [0, 1, 5, 4],  # y = 0
    [2, 3, 7, 6],  # y = 1
    [0, 4, 7, 3],  # x = 0
    [1, 2, 6, 5],  # x = 1
]


def write_cube_off(path: Path, *, glued_header: bool) -> None:
    header = "OFF8 6 0\n" if glued_header else "OFF\n# a comment\n8 6 0\n"
    vertices = "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in CUBE_VERTICES)
    faces = "".join("4 " + " ".join(map(str, quad)) + "\n" for quad in CUBE_QUADS)
    path.write_text(header + vertices + faces)


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest triangle whose interior its projection hits.

    A point whose projection falls inside no triangle gets ``inf``; for points sampled on the
    surface the result is the (tiny) distance to the triangle they were drawn on.
    """
    a, b, c = (vertices[faces[:, i]] for i in range(3))  # (F, 3)
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    rel = points[:, None, :] - a[None]  # (N, F, 3)
    plane = np.einsum("nfk,fk->nf", rel, normal)
    proj = rel - plane[..., None] * normal[None]
    e1, e2 = b - a, c - a
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    p1, p2 = np.einsum("nfk,fk->nf", proj, e1), np.einsum("nfk,fk->nf", proj, e2)
    det = d11 * d22 - d12**2
    u = (d22 * p1 - d12 * p2) / det
    v = (d11 * p2 - d12 * p1) / det
    inside = (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
    return np.where(inside, np.abs(plane), np.inf).min(axis=1)


# --------------------------------------------------------------------------------------------
# read_off
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("glued_header", [True, False], ids=["OFF8 6 0", "OFF newline"])
def test_read_off_cube_fan_triangulates_quads(tmp_path: Path, glued_header: bool) -> None:
    path = tmp_path / "cube.off"
    write_cube_off(path, glued_header=glued_header)
    vertices, faces = read_off(path)
    np.testing.assert_array_equal(vertices, CUBE_VERTICES)
    assert faces.dtype == np.int64 and faces.shape == (12, 3)
    expected = np.array([[q[0], q[1], q[2]] for q in CUBE_QUADS] + [[q[0], q[2], q[3]] for q in CUBE_QUADS])
    # fan order: (v0, v1, v2), (v0, v2, v3) for each quad, quad after quad
    np.testing.assert_array_equal(faces[0::2], expected[:6])
    np.testing.assert_array_equal(faces[1::2], expected[6:])
    areas = 0.5 * np.linalg.norm(
        np.cross(
            vertices[faces[:, 1]] - vertices[faces[:, 0]],
            vertices[faces[:, 2]] - vertices[faces[:, 0]],
        ),
        axis=1,
    )
    assert areas.sum() == pytest.approx(6.0)


def test_read_off_mixed_polygons_and_face_colours(tmp_path: Path) -> None:
    path = tmp_path / "mixed.off"
    path.write_text(
        "OFF\n5 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0.5 2 0\n"
        "3 0 1 2 255 0 0\n"  # a coloured triangle
        "5 0 1 2 4 3\n"  # a pentagon -> 3 triangles
    )
    _, faces = read_off(path)
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 1, 2], [0, 2, 4], [0, 4, 3]])


def test_read_modelnet_chair() -> None:
    root = require_data("objects/modelnet40/chair_0002.off")
    path = root / "objects/modelnet40/chair_0002.off"
    vertices, faces = read_off(path)
    assert vertices.shape == (192, 3) and faces.shape == (96, 3)
    lines = path.read_text().splitlines()
    np.testing.assert_array_equal(vertices[0], np.array(lines[2].split(), dtype=np.float64))
    np.testing.assert_array_equal(faces[-1], np.array(lines[-1].split()[1:], dtype=np.int64))
    assert faces.min() >= 0 and faces.max() < len(vertices)


def test_read_modelnet_airplane_counts() -> None:
    root = require_data("objects/modelnet40/airplane_0001.off")
    vertices, faces = read_off(root / "objects/modelnet40/airplane_0001.off")
    assert vertices.shape == (27_817, 3) and faces.shape == (54_303, 3)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("", "empty"),
        ("PLY\n3 1 0\n", "does not start with 'OFF'"),
        ("OFF\n", "no vertex/face counts"),
        ("OFF\nthree 1 0\n", "counts"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n", "data lines"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "out of range"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n2 0 1\n", "corners"),
        ("OFF\n3 1 0\n0 0 0\n1 x 0\n0 1 0\n3 0 1 2\n", "vertex line"),
    ],
)
def test_malformed_off_raises_format_error(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "bad.off"
    path.write_text(content)
    with pytest.raises(FormatError, match=match) as info:
        read_off(path)
    assert str(path) in str(info.value)


def test_read_off_missing_file(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError):
        read_off(tmp_path / "absent.off")


# --------------------------------------------------------------------------------------------
# sample_surface
# --------------------------------------------------------------------------------------------


def test_cube_sampling_is_area_uniform(tmp_path: Path) -> None:
    path = tmp_path / "cube.off"
    write_cube_off(path, glued_header=True)
    n = 60_000
    points = read_cloud(path, n_mesh_samples=n, seed=1).xyz
    assert points.shape == (n, 3)
    assert points.min() >= -1e-12 and points.max() <= 1.0 + 1e-12
    # every point lies on a face: some coordinate is exactly 0 or 1 (to rounding)
    on_face = np.minimum(np.abs(points), np.abs(points - 1.0)) < 1e-12  # (n, 3)
    assert on_face.any(axis=1).all()
    counts = np.array(
        [
            np.count_nonzero(np.abs(points[:, axis] - value) < 1e-12)
            for axis in range(3)
            for value in (0.0, 1.0)
        ]
    )
    # binomial(n, 1/6): sd = sqrt(n * 1/6 * 5/6) ~ 91 points; 1 % of n is more than 6 sd
    np.testing.assert_allclose(counts / n, 1.0 / 6.0, atol=0.01)


def test_triangle_samples_are_uniform_not_centre_biased() -> None:
    # Uniform on a triangle: mean = centroid, and the corner triangle x + y <= 1/2 holds 1/4 of
    # the points. Without the square root (p = (1-r1) a + r1 (1-r2) b + r1 r2 c) it gets 1/2.
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2]])
    points = sample_surface(vertices, faces, 40_000, seed=2)
    np.testing.assert_allclose(points.mean(axis=0), [1 / 3, 1 / 3, 0.0], atol=0.005)
    assert np.all(points[:, :2] >= 0.0) and np.all(points[:, :2].sum(axis=1) <= 1.0 + 1e-12)
    near_a = np.count_nonzero(points[:, :2].sum(axis=1) <= 0.5) / len(points)
    assert near_a == pytest.approx(0.25, abs=0.01)
    np.testing.assert_array_equal(points[:, 2], 0.0)


def test_triangles_are_chosen_in_proportion_to_area() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [3, 4, 5], [0, 0, 1]])  # areas 0.5, 1.5, 0 (degenerate)
    points = sample_surface(vertices, faces, 20_000, seed=3)
    share_big = np.count_nonzero(points[:, 0] >= 10.0) / len(points)
    assert share_big == pytest.approx(0.75, abs=0.015)


def test_modelnet_samples_lie_on_the_mesh() -> None:
    root = require_data("objects/modelnet40/chair_0002.off")
    vertices, faces = read_off(root / "objects/modelnet40/chair_0002.off")
    points = sample_surface(vertices, faces, 3000, seed=4)
    scale = np.ptp(vertices, axis=0).max()
    assert distance_to_mesh(points, vertices, faces).max() < 1e-9 * scale
    # and they cover the mesh: bounding boxes agree to a few per cent of its size
    np.testing.assert_allclose(points.min(axis=0), vertices.min(axis=0), atol=0.05 * scale)
    np.testing.assert_allclose(points.max(axis=0), vertices.max(axis=0), atol=0.05 * scale)


def test_sampling_is_reproducible_by_seed() -> None:
    vertices, faces = CUBE_VERTICES, np.array([[0, 1, 2], [0, 2, 3]])
    a = sample_surface(vertices, faces, 100, seed=9)
    np.testing.assert_array_equal(a, sample_surface(vertices, faces, 100, seed=9))
    assert not np.array_equal(a, sample_surface(vertices, faces, 100, seed=10))
    assert sample_surface(vertices, faces, 0).shape == (0, 3)


@pytest.mark.parametrize(
    ("vertices", "faces"),
    [
        (np.zeros((3, 2)), np.array([[0, 1, 2]])),
        (np.eye(3), np.array([[0, 1, 3]])),
        (np.eye(3), np.array([[0.0, 1.0, 2.0]])),
        (np.zeros((3, 3)), np.array([[0, 1, 2]])),  # zero area
    ],
)
def test_sample_surface_rejects_bad_meshes(vertices: np.ndarray, faces: np.ndarray) -> None:
    with pytest.raises(InvalidCloudError):
        sample_surface(vertices, faces, 10)
