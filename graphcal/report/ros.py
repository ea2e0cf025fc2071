"""ROS 2 (Humble and newer) ``static_transform_publisher`` commands for the calibrated extrinsics.

One line per sensor, with the named-argument syntax of Humble+::

    ros2 run tf2_ros static_transform_publisher --x 0.528 --y 0.033 --z 0.365 \\
        --qx -0.43 --qy 0.43 --qz -0.56 --qw 0.56 --frame-id body --child-frame-id depth

The transform published is ``T_parent_child`` (the child frame's pose in the parent frame, i.e.
``T_body_sensor``), which is what tf2 expects. Numbers are written with 9 significant digits.
"""

from __future__ import annotations

import shlex
from typing import Mapping

import numpy as np

from graphcal.geometry import quat_wxyz_from_matrix

__all__ = ["static_transform_publisher_command", "static_transforms_script"]


def _num(x: float) -> str:
    s = f"{float(x):.9g}"
    return "0" if s in ("0", "-0") else s


def static_transform_publisher_command(parent: str, child: str, T_parent_child, *, sep: str = " ") -> str:
    """The one-line ROS 2 command publishing ``T_parent_child`` (4x4, m) as a static transform.

    Frame names are shell-quoted only when they need it (plain names stay as they are). ``sep``
    joins its four parts (program, translation, quaternion, frames); ``" \\\n    "`` gives a
    shell command over four lines that fits a page.
    """
    T = np.asarray(T_parent_child, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_parent_child must be a finite 4x4 pose, got shape {T.shape}")
    w, x, y, z = quat_wxyz_from_matrix(T[:3, :3])
    t = T[:3, 3]
    parts = [
        "ros2 run tf2_ros static_transform_publisher",
        f"--x {_num(t[0])} --y {_num(t[1])} --z {_num(t[2])}",
        f"--qx {_num(x)} --qy {_num(y)} --qz {_num(z)} --qw {_num(w)}",
        f"--frame-id {shlex.quote(str(parent))} --child-frame-id {shlex.quote(str(child))}",
    ]
    return sep.join(parts)


def static_transforms_script(parent: str, sensors: Mapping[str, np.ndarray], *, dataset: str | None = None,
                             uncertainty: str = "") -> str:
    """A POSIX shell script running one static_transform_publisher per sensor until interrupted.

    Args:
        parent: the body frame (``base_frame`` of the calibration).
        sensors: sensor name -> ``T_body_sensor`` (4x4).
        dataset: dataset path named in the comment (provenance).
        uncertainty: a sentence on the sensors' 1-sigma, written as a comment line ("" none).
    """
    ds = " ".join(str(dataset).split()) if dataset is not None else "(unknown dataset)"
    lines = [
        "#!/bin/sh",
        f"# Static transforms {parent} -> sensor calibrated by graphcal calibrate from dataset {ds}.",
        "# ROS 2 Humble or newer: source your ROS setup first (e.g. . /opt/ros/humble/setup.sh), then run",
        "# this script; it publishes one static transform per sensor on /tf_static until Ctrl-C.",
        "# Do not also publish these transforms from robot_state_publisher (robot_calibrated.urdf holds",
        "# the same poses): use one or the other.",
        *([f"# {' '.join(uncertainty.split())}"] if uncertainty else []),
        "set -e",
        "trap 'trap - INT TERM; kill 0' INT TERM",
    ]
    for name, T in sensors.items():
        lines.append(static_transform_publisher_command(parent, str(name), T) + " &")
    lines.append("wait")
    return "\n".join(lines) + "\n"
