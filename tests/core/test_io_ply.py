"""Tests for randt.core.io.ply: hand-written ASCII and big-endian files, round trips, files written by
Open3D, the shared real PLYs against reference values, and malformed input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from randt.core.errors import FormatError, NotFoundError
from randt.core.io import read_cloud
from randt.core.io.ply import read_ply_header, read_ply_vertices, write_ply_binary
from tests.data import require_data

# (PLY type name, numpy dtype) for both spellings of every PLY scalar type.
ALL_TYPES = [
    ("char", "i1"),
    ("uchar", "u1"),
    ("short", "i2"),
    ("ushort", "u2"),
    ("int", "i4"),
    ("uint", "u4"),
    ("float", "f4"),
    ("double", "f8"),
    ("int8", "i1"),
    ("uint8", "u1"),
    ("int16", "i2"),
    ("uint16", "u2"),
    ("int32", "i4"),
    ("uint32", "u4"),
    ("float32", "f4"),
    ("float64", "f8"),
]


def _extremes(dtype: np.dtype) -> np.ndarray:
    """Values that exercise a type's range: its limits, zero, one and (floats) inf and nan."""
    if dtype.kind == "f":
        info = np.finfo(dtype)
        values = [info.min, info.max, info.tiny, -0.0, 1.5, np.inf, -np.inf, np.nan]
    else:
        info = np.iinfo(dtype)
        values = [info.min, info.max, 0, 1, info.max // 3, info.min // 2, 7, 42]
    return np.array(values, dtype=dtype)


def _ascii_number(value: np.generic) -> str:
    return str(value.item()) if value.dtype.kind in "iu" else repr(float(value))


# --------------------------------------------------------------------------------------------
# round trip through write_ply_binary
# --------------------------------------------------------------------------------------------


def test_binary_round_trip_every_type(tmp_path: Path) -> None:
    fields = {f"p_{code}": _extremes(np.dtype(code)) for code in dict.fromkeys(c for _, c in ALL_TYPES)}
    path = tmp_path / "all.ply"
    write_ply_binary(path, fields)
    content = path.read_bytes()
    expected_header = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 8\n"
        b"property char p_i1\nproperty uchar p_u1\nproperty short p_i2\nproperty ushort p_u2\n"
        b"property int p_i4\nproperty uint p_u4\nproperty float p_f4\nproperty double p_f8\n"
        b"end_header\n"
    )
    assert content.startswith(expected_header)
    assert len(content) == len(expected_header) + 8 * (1 + 1 + 2 + 2 + 4 + 4 + 4 + 8)
    back = read_ply_vertices(path)
    assert list(back) == list(fields)
    for name, values in fields.items():
        assert back[name].dtype == values.dtype and back[name].flags.c_contiguous
        np.testing.assert_array_equal(back[name], values)


def test_header_of_written_file(tmp_path: Path) -> None:
    xyz = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    path = tmp_path / "xyz.ply"
    write_ply_binary(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    header = read_ply_header(path)
    assert header.format == "binary_little_endian"
    assert [(e.name, e.count) for e in header.elements] == [("vertex", 100)]
    assert [(p.name, p.type_code, p.is_list) for p in header.elements[0].properties] == [
        ("x", "f4", False),
        ("y", "f4", False),
        ("z", "f4", False),
    ]
    assert path.stat().st_size == header.data_offset + 100 * 12
    back = read_ply_vertices(path)
    np.testing.assert_array_equal(np.column_stack([back["x"], back["y"], back["z"]]), xyz)


def test_write_and_read_zero_vertices(tmp_path: Path) -> None:
    path = tmp_path / "empty.ply"
    write_ply_binary(path, {"x": np.zeros(0, np.float32), "k": np.zeros(0, np.uint16)})
    back = read_ply_vertices(path)
    assert back["x"].shape == (0,) and back["x"].dtype == np.float32
    assert back["k"].shape == (0,) and back["k"].dtype == np.uint16


def test_write_accepts_non_contiguous_and_big_endian_arrays(tmp_path: Path) -> None:
    table = np.arange(30, dtype=np.float64).reshape(10, 3)
    swapped = np.arange(10, dtype=">i4")
    path = tmp_path / "strided.ply"
    write_ply_binary(path, {"a": table[:, 1], "b": swapped})
    back = read_ply_vertices(path)
    np.testing.assert_array_equal(back["a"], table[:, 1])
    assert back["b"].dtype == np.dtype("i4")
    np.testing.assert_array_equal(back["b"], np.arange(10))
    assert b"property double a\nproperty int b\n" in path.read_bytes()


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({}, "no vertex fields"),
        ({"x": np.zeros((2, 3), np.float32)}, "1-D"),
        ({"x": np.zeros(2, np.int64)}, "no PLY type"),
        ({"x": np.zeros(2, bool)}, "no PLY type"),
        ({"x": np.zeros(2, np.float16)}, "no PLY type"),
        ({"a b": np.zeros(2, np.float32)}, "property name"),
        ({"": np.zeros(2, np.float32)}, "property name"),
        ({"x": np.zeros(2, np.float32), "y": np.zeros(3, np.float32)}, "differ in length"),
    ],
)
def test_write_rejects_bad_fields_and_writes_nothing(tmp_path: Path, fields: dict, match: str) -> None:
    path = tmp_path / "bad.ply"
    with pytest.raises(FormatError, match=match) as info:
        write_ply_binary(path, fields)
    assert str(path) in str(info.value)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# hand-written files
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("newline", ["\n", "\r\n"], ids=["lf", "crlf"])
def test_read_ascii_written_by_hand(tmp_path: Path, newline: str) -> None:
    """Every type name, comments and obj_info anywhere, elements before and after ``vertex``."""
    columns = {f"p{i}": _extremes(np.dtype(code)) for i, (_, code) in enumerate(ALL_TYPES)}
    header = [
        "ply",
        "comment written by hand",
        "format ascii 1.0",
        "obj_info scanner 1",
        "element camera 2",
        "property float view_x",
        "property list uchar int tags",
        "element vertex 8",
        *[f"property {name} p{i}" for i, (name, _) in enumerate(ALL_TYPES)],
        "comment between properties",
        "element face 3",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    camera = ["0.5 2 7 8", "1.5 0"]  # the list element before vertex: skipped by line count
    rows = [" ".join(_ascii_number(columns[name][i]) for name in columns) + " " for i in range(8)]
    faces = ["3 0 1 2", "0", "4 4 5 6 7"]
    path = tmp_path / "hand.ply"
    path.write_bytes(newline.join([*header, *camera, *rows, *faces, ""]).encode())
    back = read_ply_vertices(path)
    assert list(back) == list(columns)
    for name, values in columns.items():
        assert back[name].dtype == values.dtype
        np.testing.assert_array_equal(back[name], values)


def test_read_ascii_mesh_through_read_cloud(tmp_path: Path) -> None:
    path = tmp_path / "mesh.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float nx\nproperty float ny\nproperty float nz\n"
        "property uchar intensity\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n"
        "0.1 0.2 0.3 0 0 1 10\n1 2 3 0 1 0 20\n-1e-3 4.5 nan 1 0 0 255\n3 0 1 2\n"
    )
    cloud = read_cloud(path)
    np.testing.assert_array_equal(
        cloud.xyz, np.array([[0.1, 0.2, 0.3], [1, 2, 3], [-1e-3, 4.5, np.nan]], np.float32)
    )
    np.testing.assert_array_equal(cloud.normals, [[0, 0, 1], [0, 1, 0], [1, 0, 0]])
    np.testing.assert_array_equal(cloud.intensity, [10, 20, 255])


_BE_VERTEX_TYPES = [("float", "x"), ("float", "y"), ("float", "z"), ("ushort", "scalar_intensity")]


def _big_endian_file(path: Path, vertex: np.ndarray) -> None:
    """A binary_big_endian PLY: a scalar element before vertex, a list element after it."""
    header = (
        "ply\nformat binary_big_endian 1.0\ncomment by hand\n"
        "element sensor 2\nproperty double origin_x\nproperty ushort id\n"
        f"element vertex {len(vertex)}\n"
        + "".join(f"property {type_name} {name}\n" for type_name, name in _BE_VERTEX_TYPES)
        + "element face 2\nproperty list uchar uint vertex_indices\nend_header\n"
    )
    sensor = np.array([(1.25, 7), (-3.5, 65535)], dtype=[("origin_x", ">f8"), ("id", ">u2")])
    faces = b"\x03" + np.array([0, 1, 2], ">u4").tobytes() + b"\x02" + np.array([3, 4], ">u4").tobytes()
    path.write_bytes(header.encode() + sensor.tobytes() + vertex.tobytes() + faces)


def test_read_big_endian_written_by_hand(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    vertex = np.empty(50, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("scalar_intensity", ">u2")])
    for name in ("x", "y", "z"):
        vertex[name] = rng.normal(size=50)
    vertex["scalar_intensity"] = rng.integers(0, 65536, size=50)
    path = tmp_path / "be.ply"
    _big_endian_file(path, vertex)
    back = read_ply_vertices(path)
    for name in vertex.dtype.names:
        assert back[name].dtype.isnative
        np.testing.assert_array_equal(back[name], vertex[name])
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, np.column_stack([vertex["x"], vertex["y"], vertex["z"]]))
    np.testing.assert_array_equal(cloud.intensity, vertex["scalar_intensity"])


def test_binary_list_element_before_vertex_is_rejected_clearly(tmp_path: Path) -> None:
    path = tmp_path / "face_first.ply"
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
        b"element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        + b"\x03"
        + np.array([0, 0, 0], "<i4").tobytes()
        + np.zeros(3, "<f4").tobytes()
    )
    with pytest.raises(FormatError, match="'face' comes before 'vertex' and has list properties") as info:
        read_ply_vertices(path)
    assert str(path) in str(info.value)


# --------------------------------------------------------------------------------------------
# files written by Open3D
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("write_ascii", [True, False], ids=["ascii", "binary"])
def test_read_ply_written_by_open3d(tmp_path: Path, write_ascii: bool) -> None:
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(5)
    n = 300
    xyz = rng.uniform(-20.0, 20.0, size=(n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors_u8 = rng.integers(0, 256, size=(n, 3))
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(xyz)
    pcd.normals = o3d.utility.Vector3dVector(normals)
    pcd.colors = o3d.utility.Vector3dVector(colors_u8 / 255.0)
    path = tmp_path / "o3d.ply"
    assert o3d.io.write_point_cloud(str(path), pcd, write_ascii=write_ascii)
    assert read_ply_header(path).format == ("ascii" if write_ascii else "binary_little_endian")

    back = read_ply_vertices(path)
    assert list(back) == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    got_xyz = np.column_stack([back["x"], back["y"], back["z"]])
    got_normals = np.column_stack([back["nx"], back["ny"], back["nz"]])
    if write_ascii:  # Open3D prints 6 significant digits
        np.testing.assert_allclose(got_xyz, xyz, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(got_normals, normals, rtol=1e-5, atol=1e-6)
    else:
        assert back["x"].dtype == np.float64
        np.testing.assert_array_equal(got_xyz, xyz)
        np.testing.assert_array_equal(got_normals, normals)
    assert back["red"].dtype == np.uint8
    np.testing.assert_array_equal(np.column_stack([back["red"], back["green"], back["blue"]]), colors_u8)

    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, got_xyz)
    np.testing.assert_array_equal(cloud.normals, got_normals)
    assert cloud.intensity is None


# --------------------------------------------------------------------------------------------
# the shared real PLYs (reference values computed with the previous reader, plyfile 1.x)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "n", "rows"),
    [
        (
            "source.ply",
            69_792,
            {
                0: [0.0040451093, 2.5751946, -1.5272174, 70.0],
                12_345: [2.3129768, 1.1617891, 0.30268872, 28.0],
                69_791: [-0.004093722, 1.8042507, 0.33993924, 36.0],
            },
        ),
        (
            "target.ply",
            69_088,
            {
                0: [0.0031398917, 2.570035, -1.5241568, 68.0],
                12_345: [2.3754447, 1.1519173, 0.30872855, 27.0],
                69_087: [-0.004370204, 1.9261065, 0.3628981, 36.0],
            },
        ),
    ],
)
def test_read_small_gicp_binary_ply(name: str, n: int, rows: dict[int, list[float]]) -> None:
    root = require_data(f"pairs/small_gicp/{name}")
    path = root / "pairs/small_gicp" / name
    vertex = read_ply_vertices(path)
    assert list(vertex) == ["x", "y", "z", "scalar_intensity"]
    assert all(column.dtype == np.float32 and column.shape == (n,) for column in vertex.values())
    for i, expected in rows.items():
        np.testing.assert_array_equal([vertex[k][i] for k in vertex], np.array(expected, np.float32))
    cloud = read_cloud(path)
    assert cloud.n_points == n
    np.testing.assert_array_equal(cloud.intensity, vertex["scalar_intensity"])


def test_small_gicp_source_sums_match_reference() -> None:
    root = require_data("pairs/small_gicp/source.ply")
    vertex = read_ply_vertices(root / "pairs/small_gicp/source.ply")
    sums = {k: v.astype(np.float64).sum() for k, v in vertex.items()}
    np.testing.assert_allclose(
        [sums["x"], sums["y"], sums["z"], sums["scalar_intensity"]],
        [19072.490746340947, -75793.31267036847, -43291.99314745888, 2134792.0],
        rtol=1e-9,
    )


BUNNY_COUNTS = {
    "bun000.ply": 40_256,
    "bun045.ply": 40_097,
    "bun090.ply": 30_379,
    "bun180.ply": 40_251,
    "bun270.ply": 31_701,
    "bun315.ply": 35_336,
    "chin.ply": 37_738,
    "ear_back.ply": 32_193,
    "top2.ply": 38_298,
    "top3.ply": 36_023,
}


@pytest.mark.parametrize(("name", "n"), BUNNY_COUNTS.items())
def test_bunny_vertex_counts(name: str, n: int) -> None:
    root = require_data(f"objects/bunny/{name}")
    path = root / "objects/bunny" / name
    assert [(e.name, e.count) for e in read_ply_header(path).elements] == [
        ("vertex", n),
        ("range_grid", 204_800),
    ]
    vertex = read_ply_vertices(path)
    assert list(vertex) == ["x", "y", "z"]
    assert all(column.dtype == np.float32 and column.shape == (n,) for column in vertex.values())


@pytest.mark.parametrize(
    ("name", "rows", "sums"),
    [
        (
            "bun000.ply",
            {
                0: [-0.06325, 0.0359793, 0.0420873],
                12_345: [0.04325, 0.0713107, 0.0264444],
                40_255: [-0.018, 0.18794, -0.0197253],
            },
            [-966.9774997446511, 3888.1178691908717, 1434.3911359781523],
        ),
        (
            "top3.ply",
            {
                0: [0.07625, 0.0354029, 0.0870863],
                12_345: [-0.0055, 0.0774949, 0.0774268],
                36_022: [0.0375, 0.147242, 0.0505657],
            },
            [-314.1342499415914, 3245.786941342056, 2629.343587834155],
        ),
    ],
)
def test_bunny_values_match_reference(name: str, rows: dict[int, list[float]], sums: list[float]) -> None:
    root = require_data(f"objects/bunny/{name}")
    cloud = read_cloud(root / "objects/bunny" / name)
    for i, expected in rows.items():
        np.testing.assert_array_equal(cloud.xyz[i], np.array(expected, np.float32))
    np.testing.assert_allclose(cloud.xyz.sum(axis=0), sums, rtol=1e-9)


# --------------------------------------------------------------------------------------------
# malformed input
# --------------------------------------------------------------------------------------------

_XYZ = b"property float x\nproperty float y\nproperty float z\n"
_ASCII_HEAD = b"ply\nformat ascii 1.0\n"
_LE_HEAD = b"ply\nformat binary_little_endian 1.0\n"


_MALFORMED: list[tuple[bytes, str]] = [
    (b"", "not a PLY file"),
    (b"PLY\nformat ascii 1.0\nend_header\n", "not a PLY file"),
    (b"solid cube\nfacet normal 0 0 1\n", "not a PLY file"),
    (_ASCII_HEAD + b"element vertex 1\n" + _XYZ, "without 'end_header'"),
    (b"ply\nformat binary 1.0\nend_header\n", "expected 'format"),
    (b"ply\nformat ascii 2.0\nend_header\n", "unsupported PLY version"),
    (b"ply\nelement vertex 1\n" + _XYZ + b"end_header\n0 0 0\n", "no 'format' line"),
    (_ASCII_HEAD + b"format ascii 1.0\nend_header\n", "'format' must come once"),
    (_ASCII_HEAD + b"element vertex 1\nproperty float128 x\nend_header\n", "unknown type 'float128'"),
    (_ASCII_HEAD + b"element face 1\nproperty list float int v\nend_header\n", "not an integer type"),
    (_ASCII_HEAD + b"element face 1\nproperty list uchar v\nend_header\n", "property list"),
    (_ASCII_HEAD + b"element vertex 1\nproperty float\nend_header\n", "property <type> <name>"),
    (_ASCII_HEAD + b"property float x\nend_header\n", "before any 'element'"),
    (_ASCII_HEAD + b"element vertex -3\nend_header\n", "element <name> <count>"),
    (_ASCII_HEAD + b"element vertex many\nend_header\n", "element <name> <count>"),
    (_ASCII_HEAD + b"elemnt vertex 1\nend_header\n", "unknown header keyword 'elemnt'"),
    (_ASCII_HEAD + b"element vertex 1\nproperty float x\nproperty int x\nend_header\n", "twice"),
    (_ASCII_HEAD + b"element vertex 1\n" + _XYZ + b"element vertex 1\nend_header\n", "twice"),
    (_ASCII_HEAD + b"element face 1\nproperty list uchar int v\nend_header\n3 0 1 2\n", "no 'vertex'"),
    (
        _ASCII_HEAD + b"element vertex 1\nproperty list uchar float p\nend_header\n1 2\n",
        "vertex element has list properties",
    ),
    (_ASCII_HEAD + b"element vertex 1\nend_header\n\n", "vertex element has no properties"),
    (b"ply\nformat ascii 1.0\ncomment " + b"x" * 10_000 + b"\n", "longer than"),
    (b"ply\nformat ascii 1.0\n" + b"comment\n" * 1000, "first 1000 lines"),
    # binary data
    (_LE_HEAD + b"element vertex 2\n" + _XYZ + b"end_header\n" + b"\x00" * 20, "truncated PLY"),
    (
        _LE_HEAD
        + b"element cam 4\nproperty double t\nelement vertex 1\n"
        + _XYZ
        + b"end_header\n"
        + b"\x00" * 40,
        "truncated PLY",
    ),
    # ASCII data
    (_ASCII_HEAD + b"element vertex 3\n" + _XYZ + b"end_header\n1 2 3\n4 5 6\n", "truncated PLY"),
    (_ASCII_HEAD + b"element vertex 1\n" + _XYZ + b"end_header\n", "truncated PLY"),
    (
        _ASCII_HEAD + b"element cam 3\nproperty float t\nelement vertex 1\n" + _XYZ + b"end_header\n1\n",
        "elements before 'vertex' announce 3 lines",
    ),
    (_ASCII_HEAD + b"element vertex 2\n" + _XYZ + b"end_header\n1 2 3\n4 5\n", "malformed ASCII"),
    (_ASCII_HEAD + b"element vertex 1\n" + _XYZ + b"end_header\n1 two 3\n", "malformed ASCII"),
    (_ASCII_HEAD + b"element vertex 2\n" + _XYZ + b"end_header\n1 2\n3 4\n", "have 2 values"),
    (
        _ASCII_HEAD + b"element vertex 1\n" + _XYZ + b"property uchar red\nend_header\n1 2 3 256\n",
        "not uint8 integers",
    ),
    (
        _ASCII_HEAD + b"element vertex 1\n" + _XYZ + b"property int k\nend_header\n1 2 3 1.5\n",
        "not int32 integers",
    ),
]


@pytest.mark.parametrize(("content", "match"), _MALFORMED, ids=[match for _, match in _MALFORMED])
def test_malformed_files_raise_format_error_naming_the_path(
    tmp_path: Path, content: bytes, match: str
) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(FormatError, match=match) as info:
        read_ply_vertices(path)
    assert str(path) in str(info.value)


def test_missing_file_raises_not_found(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError, match=r"nothing\.ply"):
        read_ply_vertices(tmp_path / "nothing.ply")
    with pytest.raises(NotFoundError, match=r"nothing\.ply"):
        read_ply_header(tmp_path / "nothing.ply")


def test_directory_raises_format_error(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="cannot read"):
        read_ply_vertices(tmp_path)


def test_a_vertex_count_beyond_the_file_is_truncation_not_an_allocation(tmp_path: Path) -> None:
    """A header announcing 10^12 vertices (11 TiB) of a 120-byte body: FormatError naming both sizes,
    before numpy is asked for the memory (it raised MemoryError, so `randt register` crashed)."""
    path = tmp_path / "lies.ply"
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    path.write_bytes(header.encode() + np.zeros((10, 3), "<f4").tobytes())
    with pytest.raises(FormatError, match=r"announces 1000000000000 vertices.*the file holds 120"):
        read_cloud(path)
