"""Next-best poses: which body poses to command, in the dataset's stance, so that k stations
determine a camera's extrinsic best.

Candidates are random poses the robot can hold with its feet planted where the dataset's first
session planted them (:func:`graphcal.models.kinematics.ik_leg`) and from which the camera sees the
ground. Each is scored with a linear-Gaussian information model of the batch graph's factors
(:class:`PoseInformationModel`: the extrinsic, the planted feet, the IMU mounting; the body pose
eliminated), and the greedy choice is D-optimal (or, with sigma targets, the largest sigma /
target ratio). Poses are ``T_stance_body``: the body in the dataset's world frame (that of its
commanded poses); angles in degrees, positions in metres at the interface, rad / m inside.

The candidates, the information model and the criterion: docs/incremental.md, "Next-best poses".
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from graphcal.calibration.graph import DEFAULT_PLANE_COV, CalibrationOptions
from graphcal.errors import GraphcalError
from graphcal.geometry import invert_pose, pose_from_xyz_rpy, xyz_rpy_from_pose
from graphcal.models.sensors import sensor_type

__all__ = ["SuggestedPose", "suggest_poses", "predict_sigmas", "PoseInformationModel", "suggest_with_model", "MIN_GROUND_RAYS"]

#: rays of the strided pixel grid that must hit the ground for a pose to count as a measurement
MIN_GROUND_RAYS = 30
_RAY_GRID = (48, 36)  # pixel grid used to predict a plane's covariance (the scale c absorbs it)
#: random candidate poses drawn, and the rotation within which a chosen pose's neighbours are dropped (deg).
#: More candidates reach a target with fewer stations, at a cost that grows with their number
#: (docs/incremental.md, "Measured (Chai's 52 poses vs suggestions)")
N_CANDIDATES = 2000
MIN_SEPARATION_DEG = 2.0
_BODY_UNITS = np.r_[[np.degrees(1.0)] * 3, [1e3] * 3]  # rad, m -> deg, mm


@dataclass(frozen=True, eq=False)
class SuggestedPose:
    """One suggested station.

    Attributes:
        rank: 1 = chosen first (the most informative given the prior), 2 = next given the first...
        T_stance_body: (4, 4) commanded body pose in the stance frame (m).
        roll_deg, pitch_deg, yaw_deg: its ROS roll/pitch/yaw (deg); height_m: body height (m).
        sigma_rot_deg, sigma_xyz_mm: (3,) predicted 1-sigma of the extrinsic about / along the body
            axes after the stations of rank <= this one (and the dataset's own with
            ``after_existing``; information model, module docstring).
        q_by_foot: foot -> (n,) joint angles that hold the pose with the feet planted (IK).
    """

    rank: int
    T_stance_body: np.ndarray
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    height_m: float
    sigma_rot_deg: np.ndarray
    sigma_xyz_mm: np.ndarray
    q_by_foot: dict


class PoseInformationModel:
    """The information model of one dataset and camera (module docstring)."""

    def __init__(self, dataset, sensor: str | None, options: CalibrationOptions):
        from graphcal.calibration.graph import build_problem
        from graphcal.calibration.measurements import calibration_data
        from graphcal.io.dataset import Dataset, load_dataset_robot, read_dataset
        from graphcal.models.sensors import sensor_for_type

        ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
        self.ds, self.options = ds, options
        self.robot = load_dataset_robot(ds)
        data = calibration_data(ds, self.robot)
        cams = [n for n, s in ds.sensors.items() if sensor_type(s.type).fits_planes]
        if sensor is None:
            if not cams:
                raise GraphcalError("suggest_poses: the dataset has no camera (depth or stereo); laser scanners "
                                    "are not supported by the plane information model")
            sensor = cams[0]
        if sensor not in ds.sensors:
            raise GraphcalError(f"suggest_poses: no sensor {sensor!r}; the dataset has {', '.join(ds.sensors)}")
        if not sensor_type(ds.sensors[sensor].type).fits_planes:
            raise GraphcalError(f"suggest_poses: {sensor!r} is a {ds.sensors[sensor].type}; only cameras are supported")
        self.sensor = sensor
        plain = replace(options, robust=False)
        problem = build_problem(ds, self.robot, data, plain)
        if sensor not in problem.sensor_keys:
            raise GraphcalError(f"suggest_poses: {sensor!r} has no plane at any station of the dataset")
        self.T_ext = problem.initial_extrinsics[sensor]
        T_cad, sig_m, sig_rad = problem.sensor_priors[sensor]
        self.prior_sigmas = np.r_[[max(sig_rad, 1e-9)] * 3, [max(sig_m, 1e-6)] * 3]

        # the first session's stance: planted feet (world), seed joint angles, nominal pose
        first = data.stations[0].session
        st1 = [st for st in data.stations if st.session == first]
        self.feet = [f for f in self.robot.feet if all(f in st.q_by_foot for st in st1)]
        if len(self.feet) < 3:
            raise GraphcalError("suggest_poses: fewer than 3 legs with joint angles in the first session")
        from graphcal.calibration.kinematic_pose import feet_in_body

        feet_world = []
        for f in self.feet:
            pts = [problem.initial_body[st.station][:3, :3] @ feet_in_body(self.robot, {f: st.q_by_foot[f]})[0]
                   + problem.initial_body[st.station][:3, 3] for st in st1]
            p = np.mean(pts, axis=0)
            p[2] = 0.0
            feet_world.append(p)
        self.feet_world = np.array(feet_world)
        self.q_seed = {f: np.asarray(st1[0].q_by_foot[f], dtype=float) for f in self.feet}
        T1 = np.array([problem.initial_body[st.station] for st in st1])
        # the first session's stations with a plane of this camera: what the dataset has already measured
        seen = {station for (station, name) in data.planes if name == sensor}
        done = [i for i, st in enumerate(st1) if st.station in seen]
        self.existing_T = T1[done]
        self.existing_q = {f: np.array([st1[i].q_by_foot[f] for i in done], dtype=float).reshape(len(done), -1)
                           for f in self.feet}
        self.xy0 = T1[:, :2, 3].mean(axis=0)
        self.yaw0 = float(np.median([xyz_rpy_from_pose(T)[1][2] for T in T1]))
        self.height0 = float(np.median(T1[:, 2, 3]))

        self.imu = ds.imu is not None and any(st.imu_accel is not None for st in data.stations)
        self.mounting = self.imu and bool(getattr(options, "estimate_imu_mounting", False))
        self.R_bi = ds.imu.T_body_imu_prior.matrix[:3, :3] if ds.imu is not None else np.eye(3)
        self.mount_sigma = (max(ds.imu.T_body_imu_prior.sigma_rad, options.sigma_imu_mounting_rad)
                            if self.mounting else 0.0)
        nf = len(self.feet)
        self.dim = 6 + 3 * nf + (3 if self.mounting else 0)

        cam = sensor_for_type(ds.sensors[sensor].type)
        if hasattr(cam, "noise_focal_px"):
            cam = replace(cam, noise_focal_px=cam.focal_px)
        self.camera = replace(cam, width_px=_RAY_GRID[0], height_px=_RAY_GRID[1])
        self.rays = self.camera.ray_directions()
        # calibrate the predicted plane covariance to the dataset's own plane fits
        ratios = []
        from graphcal.factors.plane_observation import plane_cov3

        for (station, name), p in data.planes.items():
            if name != sensor:
                continue
            H = self._plane_information(problem.initial_body[station] @ self.T_ext)
            if H is None:
                continue
            # a plane without a covariance has the default calibrate gives it (planes.csv without cov_)
            C = plane_cov3(p.n, p.cov if p.cov is not None else DEFAULT_PLANE_COV)
            ratios.append(float(np.trace(H @ C)) / 3.0)
        if not ratios:
            raise GraphcalError(f"suggest_poses: no plane of {sensor!r} lies where the visibility model "
                                f"({self.visibility_text()}) sees the ground: nothing to calibrate the noise model on")
        # and to the sensor's plane noise scale (learned by a calibration: --noise-from)
        self.cov_scale = float(np.median(ratios)) * options.plane_scale(sensor) ** 2

    def visibility_text(self) -> str:
        """The camera model that decides where the ground is seen, in words."""
        c = self.camera
        return (f"a {c.hfov_deg:g} x {c.vfov_deg:g} deg camera seeing {c.min_range_m:g}-{c.max_range_m:g} m"
                if hasattr(c, "hfov_deg") else type(c).__name__)

    # -- pieces
    def _plane_information(self, T_world_sensor: np.ndarray):
        """(3, 3) information of the plane fit (unscaled) at a sensor pose, in the error's
        coordinates ``[B^T n, d]`` (B = tangent_basis(n)), or None when the ground is not seen."""
        from graphcal.factors.checked import tangent_basis

        R, t = T_world_sensor[:3, :3], T_world_sensor[:3, 3]
        n = R.T @ np.array([0.0, 0.0, 1.0])  # ground normal in the sensor frame (towards the sensor)
        d = float(t[2])
        if d <= 0:
            return None
        u = self.rays
        nu = u @ n
        hit = nu < -1e-6
        s = np.where(hit, -d / np.where(hit, nu, -1.0), 0.0)
        x = u * s[:, None]
        z = x[:, 2]
        keep = hit & (z >= self.camera.min_range_m) & (z <= self.camera.max_range_m)
        if keep.sum() < MIN_GROUND_RAYS:
            return None
        x, uk, z = x[keep], u[keep], z[keep]
        sig = self.camera.sigma_along_axis(z) * np.abs(uk @ n) / uk[:, 2]
        B = tangent_basis(n)
        J = np.column_stack([x @ B[:, 0], x @ B[:, 1], np.ones(len(x))])
        return (J / sig[:, None] ** 2).T @ J

    def reachable(self, T_world_body: np.ndarray):
        """(ok (N,), q_by_foot {foot: (N, n)}) for a batch (N, 4, 4) of body poses."""
        from graphcal.models.kinematics import ik_leg

        T = np.asarray(T_world_body, dtype=float)
        Tinv = invert_pose(T)
        ok = np.ones(len(T), dtype=bool)
        qs = {}
        for k, f in enumerate(self.feet):
            leg = self.robot.leg(f)
            p_body = np.einsum("nij,j->ni", Tinv[:, :3, :3], self.feet_world[k]) + Tinv[:, :3, 3]
            q, good = ik_leg(leg, p_body, self.q_seed[f])
            inside = np.all((q >= leg.lower - 1e-9) & (q <= leg.upper + 1e-9), axis=1)
            ok &= good & inside
            qs[f] = q
        return ok, qs

    def station_information(self, T: np.ndarray, q_by_foot: dict):
        """(D, D) information one station at body pose T (joint angles ``q_by_foot``) adds on
        theta (X eliminated), or None when the camera does not see the ground from there."""
        return self.station_informations(np.asarray(T, dtype=float)[None],
                                         {f: np.asarray(q, dtype=float)[None] for f, q in q_by_foot.items()})[0]

    def station_informations(self, T: np.ndarray, q_by_foot: dict) -> list:
        """:meth:`station_information` for a batch: T (N, 4, 4), q_by_foot foot -> (N, n)."""
        from graphcal.factors.imu_attitude import imu_attitude_error, imu_attitude_misaligned_error
        from graphcal.factors.plane_observation import plane_observation_error
        from graphcal.geometry import skew
        from graphcal.models.kinematics import leg_jacobian

        o = self.options
        N = len(T)
        nX, nf = 6, len(self.feet)
        D = nX + self.dim
        R, t = T[:, :3, :3], T[:, :3, 3]
        # stance feet, batched over the poses: e = FK(q) - R^T (F - t), H_X = [-[p_b]x, I],
        # H_F = -R^T (factors/stance_foot.py), covariance joint_noise_covariance's formula
        stance = []
        for k, f in enumerate(self.feet):
            p_b = np.einsum("nji,nj->ni", R, self.feet_world[k] - t)
            Jq = leg_jacobian(self.robot.leg(f), q_by_foot[f])
            cov = o.sigma_joint_rad**2 * Jq @ np.swapaxes(Jq, 1, 2) + o.sigma_contact_m**2 * np.eye(3)
            Li = np.linalg.inv(np.linalg.cholesky(cov))
            stance.append((k, p_b, Li))
        cmd_w = 1.0 / np.r_[[o.sigma_commanded_rad] * 3, [o.sigma_commanded_m] * 3]
        out = []
        for i in range(N):
            H_plane = self._plane_information(T[i] @ self.T_ext)
            if H_plane is None:
                out.append(None)
                continue
            rows = []
            for k, p_b, Li in stance:
                A = np.zeros((3, D))
                A[:, :3] = -skew(p_b[i])
                A[:, 3:6] = np.eye(3)
                A[:, nX + 6 + 3 * k:nX + 9 + 3 * k] = -R[i].T
                rows.append(Li[i] @ A)
            if self.imu:
                f_imu = (R[i] @ self.R_bi).T @ np.array([0.0, 0.0, 9.81])
                A = np.zeros((2, D))
                if self.mounting:
                    _, (H_X, H_M) = imu_attitude_misaligned_error(T[i], self.R_bi, f_imu)
                    A[:, nX + 6 + 3 * nf:] = H_M
                else:
                    _, (H_X,) = imu_attitude_error(T[i], f_imu, self.R_bi)
                A[:, :6] = H_X
                rows.append(A / o.sigma_imu_rad)
            A = np.zeros((6, D))
            A[:, :6] = np.diag(cmd_w)
            rows.append(A)
            T_ws = T[i] @ self.T_ext
            n_s = T_ws[:3, :3].T @ np.array([0.0, 0.0, 1.0])
            _, (H_X, H_S, _) = plane_observation_error(T[i], self.T_ext, n_s, float(T_ws[2, 3]))
            A = np.zeros((3, D))
            A[:, :6] = H_X
            A[:, nX:nX + 6] = H_S
            rows.append(np.linalg.cholesky(H_plane / self.cov_scale).T @ A)  # whitened by cov3^-1/2
            A = np.vstack(rows)
            Lam = A.T @ A
            Lxx, Lxt, Ltt = Lam[:nX, :nX], Lam[:nX, nX:], Lam[nX:, nX:]
            info = Ltt - Lxt.T @ np.linalg.solve(Lxx, Lxt)
            out.append(0.5 * (info + info.T))
        return out

    def prior_information(self) -> np.ndarray:
        """(D, D): the CAD prior of S, foot-on-ground of every foot (height), the IMU-mounting
        prior; a negligible 10 m prior on the feet's x, y (the gauge the commanded poses fix)."""
        P = np.zeros((self.dim, self.dim))
        P[:6, :6] = np.diag(1.0 / self.prior_sigmas**2)
        for k in range(len(self.feet)):
            i = 6 + 3 * k
            P[i:i + 3, i:i + 3] = np.diag([1e-2, 1e-2, 1.0 / self.options.sigma_ground_m**2])
        if self.mounting:
            i = 6 + 3 * len(self.feet)
            P[i:i + 3, i:i + 3] = np.eye(3) / self.mount_sigma**2
        return P

    def existing_information(self) -> tuple[np.ndarray, int]:
        """((D, D) information, count) of the dataset's own stations of the first session that have
        a plane of the camera, at their kinematic body poses with their measured joint angles
        (stations of other sessions stood on other feet: not counted)."""
        Lam = np.zeros((self.dim, self.dim))
        n = 0
        for info in self.station_informations(self.existing_T, self.existing_q) if len(self.existing_T) else ():
            if info is not None:
                Lam += info
                n += 1
        return Lam, n

    def sigmas(self, Lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body-axis 1-sigma (deg, mm) of the extrinsic from an information matrix on theta."""
        from graphcal.solvers.covariance import body_axis_sigmas

        cov = np.linalg.inv(Lam)[:6, :6]
        s_rot, s_xyz, _, _ = body_axis_sigmas(self.T_ext, 0.5 * (cov + cov.T))
        return np.asarray(s_rot), np.asarray(s_xyz)


def _target_score(model: "PoseInformationModel", Lam: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Targeted criterion for a batch (N, D, D): minus the soft maximum (8-norm) of the body-axis
    sigma / target ratios of the extrinsic (larger is better)."""
    R = model.T_ext[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    cov = np.linalg.inv(Lam)[..., :6, :6]
    var = np.einsum("ij,njk,ik->ni", J, cov, J)
    ratio = np.sqrt(np.clip(var, 0.0, None)) * _BODY_UNITS / target
    return -np.sum(ratio**8, axis=-1) ** (1.0 / 8.0)


def _logdet_marginal(Lam: np.ndarray) -> np.ndarray:
    """log det of the first 6x6 block's marginal information, for a batch (N, D, D):
    ``log det(Lam) - log det(Lam_rest)``."""
    return np.linalg.slogdet(Lam)[1] - np.linalg.slogdet(Lam[..., 6:, 6:])[1]


def _candidates(model: PoseInformationModel, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    roll = rng.uniform(-25.0, 25.0, n)
    pitch = rng.uniform(-25.0, 25.0, n)
    yaw = rng.uniform(-15.0, 15.0, n)
    h = model.height0 * rng.uniform(0.85, 1.15, n)
    xy = model.xy0 + rng.uniform(-0.03, 0.03, (n, 2))
    return np.array([pose_from_xyz_rpy([xy[i, 0], xy[i, 1], h[i]],
                                       np.radians([roll[i], pitch[i], model.yaw0 + yaw[i]])) for i in range(n)])


def suggest_poses(
    dataset,
    k: int,
    *,
    candidates=None,
    n_candidates: int = N_CANDIDATES,
    seed: int = 0,
    sensor: str | None = None,
    options: CalibrationOptions = CalibrationOptions(),
    min_separation_deg: float = MIN_SEPARATION_DEG,
    sigma_target_deg=None,
    sigma_target_mm=None,
    after_existing: bool = False,
) -> list[SuggestedPose]:
    """The k body poses that, commanded in the dataset's stance, determine the camera's extrinsic
    best (greedy D-optimal; see the module docstring).

    Args:
        dataset: a dataset folder or :class:`graphcal.io.dataset.Dataset` (robot, stance, camera,
            its current extrinsic and plane noise).
        k: number of stations to suggest.
        candidates: (M, 4, 4) poses ``T_stance_body`` to choose from (default: ``n_candidates``
            random reachable ones, see the module docstring); unreachable ones are dropped.
        n_candidates, seed: the random candidates.
        sensor: the camera (default: the dataset's first depth or stereo camera).
        options: the noise model (the calibration's :class:`CalibrationOptions`).
        min_separation_deg: drop candidates within this rotation and 2 cm of a chosen pose.
        sigma_target_deg, sigma_target_mm: targets of the body-axis 1-sigma (scalars or (3,) per
            axis; both or neither). With targets the greedy step minimises the largest
            sigma / target ratio (a soft maximum) instead of maximising the D-criterion, and the
            selection stops as soon as every sigma is at or below its target (the stop rule of
            the incremental calibration, planned ahead).
        after_existing: count the dataset's own stations of its first session as done
            (:meth:`PoseInformationModel.existing_information`): the k stations to add to them, with sigmas of
            them all; no station when the targets are met already. False: a new session.

    Returns:
        At most k :class:`SuggestedPose` in the order chosen (fewer when the targets are met
        earlier or the candidates run out).

    Raises:
        GraphcalError: k < 1, no camera, no reachable candidate.
    """
    return suggest_with_model(PoseInformationModel(dataset, sensor, options), k, candidates=candidates,
                              n_candidates=n_candidates, seed=seed, min_separation_deg=min_separation_deg,
                              sigma_target_deg=sigma_target_deg, sigma_target_mm=sigma_target_mm,
                              after_existing=after_existing)


def suggest_with_model(model: PoseInformationModel, k: int, *, candidates, n_candidates: int, seed: int, min_separation_deg: float,
             sigma_target_deg, sigma_target_mm, after_existing: bool) -> list[SuggestedPose]:
    """:func:`suggest_poses` on a built model."""
    if k < 1:
        raise GraphcalError(f"suggest_poses: k must be >= 1, got {k}")
    C = _candidates(model, n_candidates, seed) if candidates is None else np.asarray(candidates, dtype=float)
    if C.ndim != 3 or C.shape[1:] != (4, 4):
        raise GraphcalError(f"suggest_poses: candidates must be (M, 4, 4) poses, got shape {C.shape}")
    ok, qs = model.reachable(C)
    idx = np.flatnonzero(ok)
    infos, poses, q_of = [], [], []
    for i, info in zip(idx, model.station_informations(C[idx], {f: q[idx] for f, q in qs.items()})):
        if info is not None:
            infos.append(info)
            poses.append(C[i])
            q_of.append({f: qs[f][i] for f in model.feet})
    if not infos:
        raise GraphcalError("suggest_poses: no candidate pose is reachable with the feet planted and sees the ground")
    infos = np.array(infos)
    poses = np.array(poses)
    if (sigma_target_deg is None) != (sigma_target_mm is None):
        raise GraphcalError("suggest_poses: give both sigma_target_deg and sigma_target_mm, or neither")
    target = None
    if sigma_target_deg is not None:
        target = np.r_[np.broadcast_to(np.asarray(sigma_target_deg, dtype=float), (3,)),
                       np.broadcast_to(np.asarray(sigma_target_mm, dtype=float), (3,))]
        if not np.all(target > 0):
            raise GraphcalError(f"suggest_poses: sigma targets must be > 0, got {target.tolist()}")
    alive = np.ones(len(poses), dtype=bool)
    Lam = model.prior_information()
    if after_existing:
        Lam = Lam + model.existing_information()[0]
        if target is not None and np.all(np.concatenate(model.sigmas(Lam)) <= target):
            return []
    out: list[SuggestedPose] = []
    for rank in range(1, k + 1):
        if not alive.any():
            break
        score = np.full(len(poses), -np.inf)
        if target is None:
            score[alive] = _logdet_marginal(Lam[None] + infos[alive])
        else:
            score[alive] = _target_score(model, Lam[None] + infos[alive], target)
        best = int(np.argmax(score))
        Lam = Lam + infos[best]
        T = poses[best]
        s_rot, s_xyz = model.sigmas(Lam)
        xyz, rpy = xyz_rpy_from_pose(T)
        out.append(SuggestedPose(rank, T.copy(), *map(float, np.degrees(rpy)), float(xyz[2]), s_rot, s_xyz,
                                 {f: q.copy() for f, q in q_of[best].items()}))
        # drop the chosen pose and its near-duplicates
        dR = np.einsum("ij,nik->njk", T[:3, :3], poses[:, :3, :3])
        ang = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1)))
        near = (ang < min_separation_deg) & (np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1) < 0.02)
        alive &= ~near
        alive[best] = False
        if target is not None and np.all(np.r_[s_rot, s_xyz] <= target):
            break
    return out


def predict_sigmas(dataset, poses, *, sensor: str | None = None,
                   options: CalibrationOptions = CalibrationOptions()) -> tuple[np.ndarray, np.ndarray]:
    """(sigma_rot_deg (3,), sigma_xyz_mm (3,)) the information model predicts for the extrinsic
    after stations at ``poses`` ((N, 4, 4) ``T_stance_body``) in the dataset's stance, e.g. to
    compare a station program with :func:`suggest_poses`. Poses the legs cannot reach within the
    joint limits are evaluated anyway (joint angles from IK without limits)."""
    model = PoseInformationModel(dataset, sensor, options)
    P = np.asarray(poses, dtype=float)
    _, qs = model.reachable(P)
    Lam = model.prior_information()
    for info in model.station_informations(P, qs):
        if info is not None:
            Lam = Lam + info
    return model.sigmas(Lam)
