"""The diagnosis catalogue's model extensions: extra variables of the calibration graph.

:class:`ModelExtensions` is the :class:`~graphcal.calibration.graph.GraphExtension` the diagnosis
(model.py) passes to :func:`~graphcal.calibration.graph.build_problem`: a range scale per sensor, a
ground plane per session, gravity against the ground, the IMU mounting's prior, leg parameters with
their own sigmas and extrinsic segments (docs/diagnosis.md lists the causes they model).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from graphcal.calibration.graph import ExtensionKeys, GraphBuild, add_extrinsic_segments, add_range_scale_variables
from graphcal.errors import GraphcalError
from graphcal.factors.keys import G, M, W


@dataclass(frozen=True)
class ModelExtensions:
    """Extra variables of the diagnosis catalogue (graphcal/diagnosis) in the calibration graph.

    Each entry adds a variable with a zero-mean prior of the given sigma (SI units): a tiny sigma
    keeps the nominal model (the variable exists so that its Jacobian can be read), a large one lets
    the data estimate it. All default to absent.

    Attributes:
        range_scale: (sensor, sigma) -> C(k) = [scale] of sensor k (prior 1): its planes and scans
            read ``scale`` times the true range (factors/range_scale.py).
        session_offset: (session, sigma_m) -> G(1 + j), the ground plane the sensors see at the
            stations of session j, ``offset_m`` above the plane the feet (and the commanded poses)
            stand on: the feet sank by ``offset_m`` (d of the plane = -offset_m; its tilt is held).
        ground_tilt_sigma_rad: gravity against the ground: W(0) = R_ground_level (Rot3, prior
            identity with this sigma on the tilt, its yaw pinned) in every IMU factor
            (factors/gravity_tilt.py); needs the IMU mounting variable. The world stays the ground.
        imu_mounting_sigma_rad: sigma of the prior on the IMU mounting rotation M(0) about the
            dataset's prior (replaces ``max(dataset sigma, options.sigma_imu_mounting_rad)``).
        leg_sigmas: (foot, per-parameter sigmas) -> L(l) for that leg (the graph's ``legs`` switch
            then applies to the other legs only).
        extrinsic_segments: (sensor, station): from that station on (in station order), the sensor
            has a new extrinsic S(k + 1000 j) with the CAD prior (the sensor was knocked).
        foot_radius_sigma_m: R(0) = [r], one foot radius (m, prior 0) for every foot: the stance-foot
            factors become factors/stance_contact.py's (a contact sphere rolling with the lower leg).
        compliance: (joint index, sigma) -> Q(j) = [k] (rad per m of lever, prior 0): joint j of
            every leg flexes under the foot's load (factors/stance_contact.py).
        robot: the robot (its legs), needed by the foot radius and the compliance.

    It is the :class:`~graphcal.calibration.graph.GraphExtension` the diagnosis passes to
    :func:`~graphcal.calibration.graph.build_problem`; the variables' keys are recorded in the
    problem's ``extension_keys`` (``range_scale:<sensor>``, ``session_offset:<session>``,
    ``ground_tilt``, ``imu_mounting``, ``segment:<sensor>:<station>``) and their priors in
    ``extension_priors``.
    """

    range_scale: tuple[tuple[str, float], ...] = ()
    session_offset: tuple[tuple[str, float], ...] = ()
    ground_tilt_sigma_rad: float | None = None
    imu_mounting_sigma_rad: float | None = None
    leg_sigmas: tuple[tuple[str, tuple[float, ...]], ...] = ()
    extrinsic_segments: tuple[tuple[str, int], ...] = ()
    foot_radius_sigma_m: float | None = None
    compliance: tuple[tuple[int, float], ...] = ()
    robot: object = field(default=None, compare=False)

    def add_variables(self, build: GraphBuild) -> ExtensionKeys:
        """The range scales, gravity against the ground, extrinsic segments and session ground planes,
        each with its prior, added to ``build`` (after the sensors' extrinsics)."""
        from graphcal.factors.plane_prior import plane_prior_factor

        ds, values = build.ds, build.values
        ext_keys = build.extension_keys
        range_scale = add_range_scale_variables(build, self.range_scale)
        w_key = None
        if self.ground_tilt_sigma_rad is not None and ds.imu is not None:
            # gravity against the ground: W = R_ground_level, its rotation about the vertical pinned
            w_key = W(0)
            ext_keys["ground_tilt"] = w_key
            values.insert(w_key, gtsam.Rot3())
            sig = float(self.ground_tilt_sigma_rad)
            build.add_prior(gtsam.PriorFactorRot3(w_key, gtsam.Rot3(), gtsam.noiseModel.Diagonal.Sigmas(
                np.array([sig, sig, 1e-6]))), "ground_tilt")
        segments = add_extrinsic_segments(build, self.extrinsic_segments)
        session_planes = {}
        for s_name, sig in self.session_offset:
            if s_name not in build.sessions:
                raise GraphcalError(f"session_offset names session {s_name!r}; the sessions are "
                                    f"{', '.join(build.sessions)}")
            key = G(1 + build.sessions.index(s_name))
            ext_keys[f"session_offset:{s_name}"] = session_planes[s_name] = key
            values.insert(key, gtsam.OrientedPlane3(0.0, 0.0, 1.0, 0.0))
            build.add_prior(plane_prior_factor(key, [0.0, 0.0, 1.0, 0.0], 1e-6, float(sig)), f"session_offset:{s_name}")
        stance = self._contact_variables(build)
        return ExtensionKeys(range_scale=range_scale, ground_tilt=w_key, segments=segments,
                             session_planes=session_planes, leg_feet=frozenset(f for f, _ in self.leg_sigmas),
                             stance=stance)

    def _contact_variables(self, build: GraphBuild):
        """The foot radius R(0) and compliances Q(j) with their priors; returns the stance-foot factor
        hook (:attr:`ExtensionKeys.stance`) that uses them, or None."""
        from graphcal.factors.keys import Q, R

        if self.foot_radius_sigma_m is None and not self.compliance:
            return None
        r_key = None
        if self.foot_radius_sigma_m is not None:
            r_key = R(0)
            build.extension_keys["foot_radius"] = r_key
            build.values.insert(r_key, np.array([0.0]))
            build.add_prior(gtsam.PriorFactorVector(r_key, np.array([0.0]), gtsam.noiseModel.Isotropic.Sigma(
                1, float(self.foot_radius_sigma_m))), "foot_radius")
        k_keys = {}
        for j, sig in self.compliance:
            k_keys[int(j)] = Q(int(j))
            build.extension_keys[f"compliance:{int(j)}"] = Q(int(j))
            build.values.insert(Q(int(j)), np.array([0.0]))
            build.add_prior(gtsam.PriorFactorVector(Q(int(j)), np.array([0.0]), gtsam.noiseModel.Isotropic.Sigma(
                1, float(sig))), f"compliance:{int(j)}")
        return _ContactStance(self.robot, r_key, tuple(sorted(k_keys.items())))


    def leg_prior(self, foot: str, key: int, n_params: int):
        """The prior on leg ``foot``'s parameters with its sigmas of ``leg_sigmas`` (rad or m each)."""
        from graphcal.factors.priors import leg_offset_prior

        sig = np.asarray(dict(self.leg_sigmas)[foot], dtype=float)
        if sig.shape != (n_params,):
            raise GraphcalError(f"leg {foot}: {len(sig)} parameter sigmas for {n_params} parameters")
        return leg_offset_prior(key, n_params, sig)

    def imu_mounting_prior(self, R_body_imu: np.ndarray):
        """The prior on M(0) about ``R_body_imu`` (3x3, body <- IMU) with ``imu_mounting_sigma_rad``,
        or None (the graph's default prior)."""
        if self.imu_mounting_sigma_rad is None:
            return None
        return gtsam.PriorFactorRot3(M(0), gtsam.Rot3(R_body_imu), gtsam.noiseModel.Isotropic.Sigma(
            3, float(self.imu_mounting_sigma_rad)))


@dataclass(frozen=True, eq=False)
class _ContactStance:
    """The stance-foot factor hook of the foot radius and the compliances (factors/stance_contact.py).
    With several compliances in the model only the first joint's enters (one per model: the
    diagnosis names at most one compliant joint type)."""

    robot: object
    r_key: int | None
    k_keys: tuple

    def __call__(self, st, foot, x_key, f_key, cov_m2, leg_key, param):
        from graphcal.factors.stance_contact import lower_leg_direction, stance_contact_factor

        leg = self.robot.leg(foot)
        q = np.asarray(st.q_by_foot[foot], dtype=float)
        R_wb = st.T_world_body_cmd[:3, :3] if st.T_world_body_cmd is not None else np.eye(3)
        kw = {}
        if self.r_key is not None:
            kw.update(r_key=self.r_key, a_b=lower_leg_direction(leg, q))
        if self.k_keys:
            j, key = self.k_keys[0]
            if j < leg.n_joints:
                kw.update(k_key=key, joint_index=j, R_lever=R_wb)
        return stance_contact_factor(x_key, f_key, q, leg, cov_m2, l_key=leg_key, param=param, **kw)
