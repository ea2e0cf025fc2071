"""What an import needs from the robot's URDF before a log is read: the URDF text (a file the map
names, relative to the map's folder, ``--urdf``, or a built-in model), its links and moving
joints (to refuse a map naming frames the robot does not have) and the fixed transform from the
base to a link (the IMU's mount, ``T_body_imu``). Lengths in metres, angles in radians."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError, ModelError
from graphcal.geometry import invert_pose, pose_from_xyz_rpy
from graphcal.io.dataset.model import PosePrior

__all__ = ["UrdfFrames", "check_robot", "resolve_map_path", "IMU_LINK_SIGMA_MM", "IMU_LINK_SIGMA_RPY_DEG"]

#: the default sigmas of an IMU mount read from the URDF: a CAD value, the board placed to a few mm
IMU_LINK_SIGMA_MM = 2.0
IMU_LINK_SIGMA_RPY_DEG = 1.0


def resolve_map_path(value: str, map_path: Path | None) -> Path:
    """A path written in a map: absolute as it is, relative against the map file's folder."""
    p = Path(value).expanduser()
    if p.is_absolute() or map_path is None:
        return p
    return Path(map_path).parent / p


def _origin(joint, source: str) -> np.ndarray:
    o = joint.find("origin")
    if o is None:
        return np.eye(4)
    try:
        xyz = [float(x) for x in (o.get("xyz") or "0 0 0").split()]
        rpy = [float(x) for x in (o.get("rpy") or "0 0 0").split()]
        return pose_from_xyz_rpy(xyz, rpy)
    except ValueError:
        raise DatasetError(source, f"joint {joint.get('name')} origin", "three numbers in xyz and in rpy",
                           f"xyz {o.get('xyz')!r}, rpy {o.get('rpy')!r}") from None


def check_robot(frames: UrdfFrames, base: str, feet, joints, map_file) -> None:
    """The base frame, the feet and the mapped joints are the URDF's (a frame: a link or a joint;
    a joint: a moving one); DatasetError naming the map key otherwise."""
    frames.check_link(base, map_file, "robot.base_frame", joints_too=True)
    for foot in feet:
        frames.check_link(foot, map_file, "robot.feet", joints_too=True)
    for j in joints:
        if j not in frames.moving_joints:
            shown = ", ".join(frames.moving_joints[:24]) + (", ..." if len(frames.moving_joints) > 24 else "")
            raise DatasetError(map_file, f"joints.columns.{j}", f"a moving joint of the URDF {frames.source} ({shown})",
                               j)


class UrdfFrames:
    """The link tree of a URDF: ``links``, ``moving_joints``, :meth:`fixed_transform`.

    ``source`` names the URDF in errors (its file, the topic, or ``model a1``)."""

    def __init__(self, urdf_xml: str, source: str):
        from graphcal.models.urdf_xml import parse_urdf

        try:
            root = parse_urdf(urdf_xml)
        except ModelError as exc:
            raise DatasetError(source, "URDF", "a valid URDF", str(exc)) from None
        self.source = source
        self.links = tuple(e.get("name") for e in root.findall("link"))
        self._up: dict[str, tuple[str, object]] = {}  # child link -> (parent link, joint element)
        for j in root.findall("joint"):
            parent, child = j.find("parent"), j.find("child")
            if parent is not None and child is not None:
                self._up[child.get("link")] = (parent.get("link"), j)
        self.joints = tuple(j.get("name") for j in root.findall("joint"))
        self.moving_joints = tuple(j.get("name") for j in root.findall("joint") if j.get("type") != "fixed")

    @property
    def root(self) -> str:
        """The root link ("" for a URDF without links)."""
        return next((lk for lk in self.links if lk not in self._up), "")

    @property
    def feet_guess(self) -> tuple[str, ...]:
        """The leaf links named like feet (``*foot*``, ``*toe*``)."""
        parents = {parent for parent, _ in self._up.values()}
        return tuple(lk for lk in self.links if lk not in parents and ("foot" in lk.lower() or "toe" in lk.lower()))

    def check_link(self, link, map_file, key: str, *, joints_too: bool = False) -> None:
        """DatasetError naming the map key and the URDF's links when ``link`` is not one of them
        (``joints_too``: a joint's frame will do as well, as for a base or a foot frame)."""
        if link not in self.links and not (joints_too and link in self.joints):
            shown = ", ".join(self.links[:30]) + (", ..." if len(self.links) > 30 else "")
            raise DatasetError(map_file, key, f"a link of the URDF {self.source} ({shown})", link)

    def _chain(self, link: str) -> list[str]:
        out = [link]
        while out[-1] in self._up and len(out) <= len(self.links):
            out.append(self._up[out[-1]][0])
        return out

    def _T_root(self, chain: list[str], stop: str, map_file, key: str) -> np.ndarray:
        """T_stop_link along ``chain`` (link first, up to ``stop``); every joint on it fixed."""
        T = np.eye(4)
        for child in chain[: chain.index(stop)]:
            parent, joint = self._up[child]
            if joint.get("type") != "fixed":
                raise DatasetError(map_file, key, f"a link fixed to the base in {self.source} (fixed joints only)",
                                   f"{chain[0]}, behind the {joint.get('type')} joint {joint.get('name')}")
            T = _origin(joint, self.source) @ T
        return T

    def fixed_transform(self, base: str, link: str, map_file, key: str) -> np.ndarray:
        """T_base_link (4x4, m): the URDF's fixed joints composed from ``base`` to ``link``."""
        self.check_link(base, map_file, "robot.base_frame")
        self.check_link(link, map_file, key)
        up_link, up_base = self._chain(link), self._chain(base)
        common = next(x for x in up_link if x in up_base) if set(up_link) & set(up_base) else None
        if common is None:
            raise DatasetError(map_file, key, f"a link in the tree of {base} in {self.source}", link)
        T_c_link = self._T_root(up_link, common, map_file, key)
        T_c_base = self._T_root(up_base, common, map_file, key)
        return invert_pose(T_c_base) @ T_c_link

    def imu_prior(self, base: str, spec: dict, map_file, key: str = "imu.link") -> PosePrior:
        """``T_body_imu`` prior from the link the map's ``imu`` entry names (``spec["link"]``),
        sigmas ``spec["sigma_mm"]`` (2 mm) and ``spec["sigma_rpy_deg"]`` (1 deg) unless given."""
        T = self.fixed_transform(base, spec["link"], map_file, key)
        sig_mm = _sigma(spec, "sigma_mm", IMU_LINK_SIGMA_MM, map_file)
        sig_deg = _sigma(spec, "sigma_rpy_deg", IMU_LINK_SIGMA_RPY_DEG, map_file)
        return PosePrior.from_matrix(T, 1e-3 * sig_mm, np.radians(sig_deg))

    def imu_guess(self) -> str | None:
        """The URDF's one link named like an IMU (``*imu*``), else None."""
        named = [lk for lk in self.links if "imu" in lk.lower()]
        return named[0] if len(named) == 1 else None


def _sigma(spec: dict, key: str, default: float, map_file) -> float:
    v = spec.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
        raise DatasetError(map_file, f"imu.{key}", "a number >= 0", v)
    return float(v)
