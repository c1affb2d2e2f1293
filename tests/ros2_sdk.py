"""zenoh-ros2-sdk (PyPI, Apache-2.0; not ours) for the tests: an independent Python implementation
of rmw_zenoh's format, publishing and subscribing as a ROS 2 node would (docs/rmw_zenoh.md §5).

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
