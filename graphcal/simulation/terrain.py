"""Ground models for the simulator: level floor, bumpy floor, stairs (up, or up and down for the
walks: :func:`up_and_down_stairs`), box obstacles.

A terrain is a list of triangle meshes in the world frame (z up, nominal ground z = 0), each with a
label saying what it is (:data:`LABEL_GROUND`, ...). Ray casting and height queries go through
Open3D's ``RaycastingScene`` (Embree), so any mix of meshes is handled the same way; an untilted
staircase's height profile along x without it (:func:`stair_profile`).

Units: metres, radians.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import cross_batch, matrix_from_axis_angle

LABEL_GROUND = 0
LABEL_ROBOT = 1
LABEL_OBSTACLE = 2
LABEL_STAIRS = 3
LABEL_NAMES = {LABEL_GROUND: "ground", LABEL_ROBOT: "robot", LABEL_OBSTACLE: "obstacle", LABEL_STAIRS: "stairs"}

GROUND_KINDS = ("level", "bumpy-little", "bumpy-big", "stairs", "boxes")
#: the steps of the ``stairs`` terrain (Zhao 2020): rise and run (tread depth) of each step, width (m)
STAIR_RISE_M = 0.13
STAIR_RUN_M = 0.30
STAIR_WIDTH_M = 1.6


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in the world frame: ``vertices_world`` (V, 3) m, ``triangles`` (F, 3) int."""

    vertices_world: np.ndarray
    triangles: np.ndarray
    label: int

    def transformed(self, R_world_old: np.ndarray, t: np.ndarray | None = None) -> "Mesh":
        v = self.vertices_world @ np.asarray(R_world_old).T
        if t is not None:
            v = v + t
        return Mesh(v, self.triangles, self.label)


@dataclass(frozen=True)
class Stair:
    """One step: its tread spans x in [x_start, x_start + depth] at height z (m), width along y."""

    x_start_m: float
    depth_m: float
    height_m: float
    width_m: float


@dataclass(frozen=True)
class Terrain:
    """What the robot stands on and sees.

    Attributes:
        kind: one of :data:`GROUND_KINDS`.
        meshes: the world-frame meshes (tilt already applied).
        tilt_rad: ground tilt angle (rad) about a horizontal axis at azimuth ``tilt_axis_rad``.
        stairs: the steps, when ``kind == "stairs"`` (before tilt).
        bump_rms_m: RMS height of the bumps for the bumpy kinds.
    """

    kind: str
    meshes: tuple[Mesh, ...]
    tilt_rad: float = 0.0
    tilt_axis_rad: float = 0.0
    stairs: tuple[Stair, ...] = field(default=())
    bump_rms_m: float = 0.0

    @property
    def R_world_ground(self) -> np.ndarray:
        """Rotation of the (tilted) ground frame in the world frame."""
        return tilt_rotation(self.tilt_rad, self.tilt_axis_rad)

    @property
    def ground_normal_world(self) -> np.ndarray:
        """Unit normal of the nominal floor plane in the world frame."""
        return self.R_world_ground[:, 2]


def tilt_rotation(tilt_rad: float, axis_rad: float) -> np.ndarray:
    """Rotation by ``tilt_rad`` about the horizontal axis (cos axis_rad, sin axis_rad, 0)."""
    if tilt_rad == 0.0:
        return np.eye(3)
    return matrix_from_axis_angle([np.cos(axis_rad), np.sin(axis_rad), 0.0], tilt_rad)


def _quad_plane(half_size_m: float, z_m: float = 0.0, label: int = LABEL_GROUND) -> Mesh:
    s = half_size_m
    v = np.array([[-s, -s, z_m], [s, -s, z_m], [s, s, z_m], [-s, s, z_m]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    return Mesh(v, f, label)


def box_mesh(center_world, size_m, label: int = LABEL_OBSTACLE, yaw_rad: float = 0.0) -> Mesh:
    """An axis-aligned (up to yaw) box with centre (3,) and full sizes (3,) in metres."""
    sx, sy, sz = np.asarray(size_m, dtype=float) / 2.0
    corners = np.array(
        [[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)], dtype=float
    )
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    v = corners @ R.T + np.asarray(center_world, dtype=float)
    # vertex index = 4*ix + 2*iy + iz
    f = np.array(
        [
            [0, 1, 3], [0, 3, 2],  # x-
            [4, 6, 7], [4, 7, 5],  # x+
            [0, 4, 5], [0, 5, 1],  # y-
            [2, 3, 7], [2, 7, 6],  # y+
            [0, 2, 6], [0, 6, 4],  # z-
            [1, 5, 7], [1, 7, 3],  # z+
        ],
        dtype=np.int32,
    )
    return Mesh(v, f, label)


def cylinder_mesh(p0_world, p1_world, radius_m: float, label: int = LABEL_ROBOT, segments: int = 12) -> Mesh:
    """A closed cylinder between two points (m): used for the robot's leg segments."""
    p0, p1 = np.asarray(p0_world, dtype=float), np.asarray(p1_world, dtype=float)
    axis = p1 - p0
    length = np.linalg.norm(axis)
    if length < 1e-9:
        raise GraphcalError("cylinder_mesh: the two end points coincide")
    a = axis / length
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = cross_batch(a, helper)  # np.cross's arithmetic without its axis handling
    u /= np.linalg.norm(u)
    w = cross_batch(a, u)
    cos, sin, triangles = _cylinder_topology(int(segments))
    ring = radius_m * (cos[:, None] * u + sin[:, None] * w)
    v = np.vstack([p0 + ring, p1 + ring, p0, p1])
    return Mesh(v, triangles, label)


@functools.lru_cache(maxsize=8)
def _cylinder_topology(segments: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What every cylinder of ``segments`` sides shares (read-only): cos and sin (segments,) of its
    ring's angles (rad), and its triangles (4 segments, 3) over :func:`cylinder_mesh`'s vertices
    (ring at p0, ring at p1, p0, p1)."""
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    i = np.arange(segments)
    j = (i + 1) % segments
    side = np.vstack([np.c_[i, j, segments + j], np.c_[i, segments + j, segments + i]])
    c0, c1 = 2 * segments, 2 * segments + 1
    caps = np.vstack([np.c_[np.full(segments, c0), j, i], np.c_[np.full(segments, c1), segments + i, segments + j]])
    out = (np.cos(ang), np.sin(ang), np.vstack([side, caps]).astype(np.int32))
    for x in out:
        x.setflags(write=False)
    return out


def _heightfield(heights: np.ndarray, x0: float, y0: float, res_m: float, label: int) -> Mesh:
    ny, nx = heights.shape
    xs = x0 + res_m * np.arange(nx)
    ys = y0 + res_m * np.arange(ny)
    X, Y = np.meshgrid(xs, ys)
    v = np.c_[X.ravel(), Y.ravel(), heights.ravel()]
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    f = np.vstack([np.c_[a, b, d], np.c_[a, d, c]]).astype(np.int32)
    return Mesh(v, f, label)


def make_terrain(
    kind: str = "level",
    *,
    seed: int = 0,
    tilt_rad: float = 0.0,
    tilt_axis_rad: float = 0.0,
    extent_m: float = 12.0,
    bump_rms_m: float | None = None,
    stairs_start_x_m: float = 1.2,
    obstacles: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] | None = None,
) -> Terrain:
    """Build a terrain.

    Args:
        kind: ``level`` (the plane z = 0), ``bumpy-little`` / ``bumpy-big`` (Chai's little and big
            bumpiness: a smooth random height field of RMS 3 mm / 10 mm, 0.15 m correlation length,
            our choice), ``stairs`` (three 130 x 300 mm steps rising along +x from
            ``stairs_start_x_m``, Zhao 2020), ``boxes`` (level floor with box obstacles).
        seed: random seed of the bumps / box placement.
        tilt_rad, tilt_axis_rad: the whole terrain is rotated by ``tilt_rad`` about the horizontal
            world axis at azimuth ``tilt_axis_rad`` (the ``ground_tilt`` effect).
        extent_m: half size of the floor square.
        obstacles: boxes as ((cx, cy, cz), (sx, sy, sz)) in metres for ``boxes``; default: three boxes.
    """
    if kind not in GROUND_KINDS:
        raise GraphcalError(f"unknown ground kind {kind!r}; expected one of {', '.join(GROUND_KINDS)}")
    rng = np.random.default_rng(seed)
    meshes: list[Mesh] = []
    stairs: tuple[Stair, ...] = ()
    rms = 0.0
    if kind in ("bumpy-little", "bumpy-big"):
        from scipy.ndimage import gaussian_filter

        rms = bump_rms_m if bump_rms_m is not None else (0.003 if kind == "bumpy-little" else 0.010)
        res = 0.03
        half = min(extent_m, 6.0)
        n = int(2 * half / res) + 1
        h = gaussian_filter(rng.standard_normal((n, n)), sigma=0.15 / res, mode="wrap")
        h *= rms / h.std()
        meshes.append(_heightfield(h, -half, -half, res, LABEL_GROUND))
        # a flat skirt far away so that long rays still hit something
        skirt = _quad_plane(extent_m * 3, z_m=-0.001)
        meshes.append(skirt)
    else:
        meshes.append(_quad_plane(extent_m))
    if kind == "stairs":
        rise, run, width = STAIR_RISE_M, STAIR_RUN_M, STAIR_WIDTH_M
        steps = []
        for k in range(3):
            x0 = stairs_start_x_m + k * run
            depth = run if k < 2 else 1.5  # a landing on top
            top = (k + 1) * rise
            steps.append(Stair(x0, depth, top, width))
            meshes.append(box_mesh([x0 + depth / 2, 0.0, top / 2], [depth, width, top], LABEL_STAIRS))
        stairs = tuple(steps)
    if kind == "boxes":
        boxes = obstacles or (
            ((2.0, 0.5, 0.15), (0.3, 0.4, 0.3)),
            ((2.6, -0.6, 0.10), (0.4, 0.3, 0.2)),
            ((3.2, 0.2, 0.20), (0.3, 0.3, 0.4)),
        )
        for center, size in boxes:
            meshes.append(box_mesh(center, size, LABEL_OBSTACLE, yaw_rad=float(rng.uniform(-0.5, 0.5))))
    R = tilt_rotation(tilt_rad, tilt_axis_rad)
    if tilt_rad != 0.0:
        meshes = [m.transformed(R) for m in meshes]
    return Terrain(kind, tuple(meshes), float(tilt_rad), float(tilt_axis_rad), stairs, rms)


def up_and_down_stairs(stairs_start_x_m: float, extent_m: float) -> Terrain:
    """Three 130 x 300 mm steps up from ``stairs_start_x_m`` (make_terrain's stairs, 1.5 m landing)
    and three the same down after the landing (two more boxes, 260 and 130 mm high): the
    ``tripod-stairs`` walk's terrain; floor half size ``extent_m`` (m)."""
    base = make_terrain("stairs", stairs_start_x_m=stairs_start_x_m, extent_m=extent_m)
    rise, run = STAIR_RISE_M, STAIR_RUN_M
    up = base.stairs
    width = up[0].width_m
    x_down = up[-1].x_start_m + up[-1].depth_m
    meshes = list(base.meshes)
    down = []
    for k, top in enumerate((2 * rise, rise)):
        x0 = x_down + k * run
        down.append(Stair(x0, run, top, width))
        meshes.append(box_mesh([x0 + run / 2, 0.0, top / 2], [run, width, top], LABEL_STAIRS))
    return Terrain("stairs", tuple(meshes), 0.0, 0.0, tuple(up) + tuple(down), 0.0)


def stair_profile(stairs, x: np.ndarray) -> np.ndarray:
    """Ground height (m) under world x (N,) for points within the stairs' width (0 off the treads):
    an untilted staircase of :class:`Stair` records rising along +x, floor at z = 0."""
    x = np.asarray(x, dtype=float)
    h = np.zeros_like(x)
    for s in stairs:
        inside = (x >= s.x_start_m) & (x < s.x_start_m + s.depth_m)
        h = np.where(inside, np.maximum(h, s.height_m), h)
    return h


def stair_edges(stairs) -> np.ndarray:
    """The sorted world x (m) of every stair edge (each tread's front and back)."""
    xs = sorted({s.x_start_m for s in stairs} | {s.x_start_m + s.depth_m for s in stairs})
    return np.asarray(xs)


def build_scene(meshes):
    """An Open3D RaycastingScene holding ``meshes``; returns (scene, labels by geometry id)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    labels = {}
    for m in meshes:
        gid = scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(m.vertices_world, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(m.triangles, dtype=np.uint32)),
        )
        labels[int(gid)] = m.label
    return scene, labels


def terrain_height(terrain: Terrain, xy_world: np.ndarray, scene=None) -> np.ndarray:
    """Height z (m) of the terrain surface under each (x, y) world point (N, 2), by a vertical ray."""
    import open3d as o3d

    if scene is None:
        scene, _ = build_scene(terrain.meshes)
    xy = np.atleast_2d(np.asarray(xy_world, dtype=float))
    rays = np.zeros((len(xy), 6), dtype=np.float32)
    rays[:, 0:2] = xy
    top = max(float(m.vertices_world[:, 2].max()) for m in terrain.meshes) + 1.0
    rays[:, 2] = top
    rays[:, 5] = -1.0
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(float)
    if not np.all(np.isfinite(t)):
        raise GraphcalError("terrain_height: a query point lies outside the terrain")
    return top - t
