"""zenoh-ros2-sdk (PyPI, Apache-2.0; not ours) for the tests: an independent Python implementation
of rmw_zenoh's format, publishing and subscribing as a ROS 2 node would (docs/rmw_zenoh.md §5);
and the PointCloud2 fields the tests publish, built with rosbags' message classes.

It fetches message definitions with git at first use unless it finds them in a local tree, and
there is no network here: :func:`message_tree` writes that tree from ``rosbags``' Jazzy type store
(the ``.msg`` text of each type and its dependencies), and :func:`load_sdk` hands it to the SDK
before anything else asks for its registry (a process-wide singleton: the first call wins), with
its git cache pointed at an empty folder so that a missing definition fails instead of cloning.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

#: The types the tests publish or receive (their dependencies are written too).
TYPES = (
    "sensor_msgs/msg/PointCloud2",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
    "std_msgs/msg/String",
    "sensor_msgs/msg/NavSatFix",
    "geometry_msgs/msg/PointStamped",
)


def message_tree(root: Path) -> Path:
    """``<root>/<pkg>/msg/<Name>.msg`` for :data:`TYPES` and what they use, from rosbags."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for name in TYPES:
        text, _ = store.generate_msgdef(name, ros_version=2)
        parts = re.split(r"\n?=+\nMSG: ", text)
        _write(root, name, parts[0])
        for part in parts[1:]:
            dep, body = part.split("\n", 1)
            if dep.count("/") == 1:
                pkg, base = dep.split("/")
                dep = f"{pkg}/msg/{base}"
            _write(root, dep, body)
    return root


def _write(root: Path, name: str, text: str) -> None:
    pkg, _, base = name.split("/")
    folder = root / pkg / "msg"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{base}.msg").write_text(text, encoding="utf-8")


_LOADED: Path | None = None


def load_sdk(root: Path) -> Any:
    """The ``zenoh_ros2_sdk`` module, its registry on a local tree (written under ``root`` once
    per process) and its git cache empty."""
    global _LOADED
    import zenoh_ros2_sdk
    from zenoh_ros2_sdk.message_registry import get_registry

    if _LOADED is None:
        os.environ["ZENOH_ROS2_SDK_CACHE"] = str(root / "no-git-cache")
        _LOADED = message_tree(root / "msgs")
        get_registry(str(_LOADED))
    return zenoh_ros2_sdk


#: The columns of the tests' clouds: float32 x, y, z, intensity and a Velodyne-style ``time``
#: (float32 seconds), 20 bytes a point.
FIELDS = ("x", "y", "z", "intensity", "time")


def cloud_fields(types: Any, xyz: np.ndarray, intensity: np.ndarray, offsets: np.ndarray) -> dict[str, Any]:
    """A PointCloud2's fields but its header (rosbags' ``types``), for the SDK's publish or the
    message class."""
    rows = np.empty(len(xyz), dtype=[(f, "<f4") for f in FIELDS])
    rows["x"], rows["y"], rows["z"] = xyz.T
    rows["intensity"], rows["time"] = intensity, offsets
    point = types["sensor_msgs/msg/PointField"]
    return {
        "height": 1,
        "width": len(rows),
        "fields": [point(name=f, offset=4 * i, datatype=7, count=1) for i, f in enumerate(FIELDS)],
        "is_bigendian": False,
        "point_step": 20,
        "row_step": 20 * len(rows),
        "data": rows.view(np.uint8),
        "is_dense": True,
    }


def header(types: Any, stamp_ns: int, frame: str = "velodyne") -> Any:
    """A ``std_msgs/msg/Header`` at ``stamp_ns``."""
    sec, nanosec = divmod(stamp_ns, 10**9)
    stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)
