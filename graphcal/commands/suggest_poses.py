"""``graphcal suggest-poses DATASET``: the k body poses that most shrink the extrinsic's covariance
(:mod:`graphcal.calibration.suggest`), as a text table and optionally a stations-like CSV."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.calibration.graph import CalibrationOptions
from graphcal.calibration.suggest import MIN_SEPARATION_DEG, N_CANDIDATES, PoseInformationModel, SuggestedPose, suggest_with_model
from graphcal.errors import GraphcalError
from graphcal.geometry import xyz_quat_wxyz_from_pose

__all__ = ["run", "SuggestPosesResult", "POSE_FRAME_TEXT"]

#: the frame of the table's pose columns (suggest.py: ``T_stance_body``)
POSE_FRAME_TEXT = ("pose columns: the body in the dataset's world frame (that of stations.csv's body_* columns, "
                   "z up; a simulated dataset's first stance): roll, pitch, yaw as R = Rz(yaw) Ry(pitch) Rx(roll) "
                   "about its fixed axes (deg); height, x, y the body origin's z, x, y (m); sigma to 2 digits "
                   "(a prediction)")


@dataclass(frozen=True)
class SuggestPosesResult:
    """What ``graphcal suggest-poses`` suggested.

    Attributes:
        dataset: the dataset folder, as given.
        poses: the suggested stations (:class:`~graphcal.calibration.suggest.SuggestedPose`), by rank.
        k: the number asked for (with targets: the most).
        sensor, sensor_type: the camera planned for; ``others``: (name, type) of the sensors not planned for.
        noise_from: the ``calibration.yaml`` whose noise model predicted sigma, or None (the defaults).
        after_existing: the dataset's first session counted as done.
        n_existing, n_unseen, existing_sigma_rot_deg, existing_sigma_xyz_mm, visibility: with
            ``after_existing``: its stations with a plane, those outside the visibility model, the
            predicted sigma from them (deg, mm, body axes), the visibility model in words.
        sigma_target_deg, sigma_target_mm: (3,) targets (body x, y, z), or None.
        out: the CSV written, or None; ``files``: it, or nothing.
        warnings: the ``--noise-from`` file's mismatches (another robot's, other sensors).
        verdict: with targets, ``targets reached`` or ``targets not reached``; else None.
    """

    dataset: str
    poses: tuple[SuggestedPose, ...]
    k: int
    sensor: str
    sensor_type: str
    others: tuple[tuple[str, str], ...]
    noise_from: str | None
    after_existing: bool
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None
    out: Path | None = None
    n_existing: int = 0
    n_unseen: int = 0
    existing_sigma_rot_deg: tuple[float, ...] = ()
    existing_sigma_xyz_mm: tuple[float, ...] = ()
    visibility: str = ""
    sigma_target_deg: tuple[float, ...] | None = None
    sigma_target_mm: tuple[float, ...] | None = None

    def summary_text(self) -> str:
        """The noise model, the header, the table of poses (deg, m) with their predicted sigma."""
        lines = [*self._noise_lines(), *self._head_lines(), POSE_FRAME_TEXT,
                 f"{'rank':>4} {'roll':>7} {'pitch':>7} {'yaw':>7} {'height':>7} {'x':>7} {'y':>7}  "
                 f"{'sigma rot x/y/z (deg)':>23}  {'sigma xyz (mm)':>20}",
                 f"{'':>4} {'deg':>7} {'deg':>7} {'deg':>7} {'m':>7} {'m':>7} {'m':>7}"]
        for p in self.poses:
            x, y = p.T_stance_body[0, 3], p.T_stance_body[1, 3]
            lines.append(f"{p.rank:>4} {p.roll_deg:>7.2f} {p.pitch_deg:>7.2f} {p.yaw_deg:>7.2f} {p.height_m:>7.3f} "
                         f"{x:>7.3f} {y:>7.3f}  {' '.join(f'{v:7.2g}' for v in p.sigma_rot_deg)}  "
                         f"{' '.join(f'{v:6.2f}' for v in p.sigma_xyz_mm)}")
        if self.out is not None:
            lines.append(f"wrote {self.out}")
        return "\n".join(lines)

    def _noise_lines(self) -> list[str]:
        if self.noise_from is not None:
            lines = [f"noise model: learned by the calibration {self.noise_from}"]
            lines += [f"warning: {w}" for w in self.warnings]
        else:
            lines = ["noise model: graphcal's defaults (0.1 deg joints, 0.5 deg IMU, ...); a calibration learns its "
                     "own and reports sigma for it: --noise-from ITS/calibration.yaml predicts with that"]
        if self.others:  # e.g. the Messor's laser scanner beside its stereo camera
            lines.append(f"planned for {self.sensor} ({self.sensor_type}) alone; not for "
                         f"{', '.join(f'{name} ({kind})' for name, kind in self.others)} (the information model "
                         "covers one camera)")
        return lines

    def _head_lines(self) -> list[str]:
        n = len(self.poses)
        if self.after_existing:
            head = [f"the dataset's first session: {self.n_existing} station(s) with a plane of {self.sensor}, "
                    f"predicted sigma rot {' '.join(f'{v:.2g}' for v in self.existing_sigma_rot_deg)} deg, xyz "
                    f"{' '.join(f'{v:.2f}' for v in self.existing_sigma_xyz_mm)} mm"
                    + (f" ({self.n_unseen} more with a plane lie outside the visibility model, {self.visibility}: "
                       "not counted)" if self.n_unseen > 0 else ""),
                    f"suggested stations to add: {n} (greedy D-optimal; sigma = predicted 1-sigma of the extrinsic "
                    "from those stations and the suggested ones up to that rank, body axes)"]
        else:
            head = [f"suggested stations: {n} (greedy D-optimal; sigma = predicted 1-sigma of the extrinsic "
                    "from a new session of the stations up to that rank, body axes; the dataset's own stations "
                    "are not counted: --after-existing counts them)"]
        if self.sigma_target_deg is not None:
            head[-1] = head[-1].replace("(greedy D-optimal;", "(greedy, aiming at sigma rot "
                                        f"{' '.join(f'{v:g}' for v in self.sigma_target_deg)} deg, xyz "
                                        f"{' '.join(f'{v:g}' for v in self.sigma_target_mm)} mm, at most {self.k};")
            if self.poses:
                head.append(f"targets reached with {n} station(s)" if self.verdict == "targets reached" else
                            f"targets not reached with {self.k} station(s): raise -k, or the targets")
        return head


def _targets(sigma_target_deg, sigma_target_mm):
    """The targets as two (3,) arrays (deg, mm), or None; GraphcalError when malformed."""
    if (sigma_target_deg is None) != (sigma_target_mm is None):
        raise GraphcalError("--sigma-target-deg and --sigma-target-mm go together: give both or neither")
    if sigma_target_deg is None:
        return None
    targets = []
    for flag, v in (("--sigma-target-deg", sigma_target_deg), ("--sigma-target-mm", sigma_target_mm)):
        a = np.atleast_1d(np.asarray(v, dtype=float))
        if a.shape not in ((1,), (3,)) or not np.all(np.isfinite(a)) or np.any(a <= 0):
            raise GraphcalError(f"{flag} must be one or three finite numbers > 0 (body x, y, z), got {v}")
        targets.append(np.broadcast_to(a, (3,)).copy())
    return targets


def _write_poses(out, poses, robot) -> None:
    """The poses as a stations-like CSV (station, session, body pose, IK joint angles), atomically."""
    from graphcal.io.atomic import atomic_write_text, make_parent_folder
    from graphcal.io.dataset import Table, table_csv_text

    cols: dict[str, list] = {"station": [p.rank for p in poses], "session": ["suggested"] * len(poses)}
    for i, c in enumerate("xyz"):
        cols[f"body_{c}"] = [float(xyz_quat_wxyz_from_pose(p.T_stance_body)[0][i]) for p in poses]
    for i, c in enumerate(("qw", "qx", "qy", "qz")):
        cols[f"body_{c}"] = [float(xyz_quat_wxyz_from_pose(p.T_stance_body)[1][i]) for p in poses]
    if poses:
        for f in poses[0].q_by_foot:
            for j, name in enumerate(robot.leg(f).joint_names):
                cols[f"q_{name}"] = [float(p.q_by_foot[f][j]) for p in poses]
    make_parent_folder(out)
    atomic_write_text(out, table_csv_text(Table.from_columns(cols)), overwrite=False)


def run(dataset, k: int, out: str | Path | None = None, *, after_existing: bool = False,
        noise_from: str | Path | None = None, sigma_target_deg=None, sigma_target_mm=None) -> SuggestPosesResult:
    """The ``graphcal suggest-poses`` command: the k suggested poses (a :class:`SuggestPosesResult`,
    whose summary is a text table); with ``out`` also a stations-like CSV of the commanded poses
    (station, session, body pose, IK joint angles), written atomically (a missing parent folder is
    created); an existing ``out`` is never replaced (checked before the work).

    The sigma of each rank is that of a new session of the suggested stations up to that rank
    (it plans a calibration session), or with ``after_existing`` that of the dataset's first
    session plus the suggested stations up to that rank (it plans the stations to add). The noise
    model is graphcal's defaults, or with ``noise_from`` the one an earlier calibration learned (its
    ``calibration.yaml``, :func:`graphcal.calibration.noise_file.options_with_noise_from`).
    ``sigma_target_deg`` (deg) and ``sigma_target_mm`` (mm), one value or three (body x, y, z), both
    or neither: aim at these 1-sigma and stop as soon as every axis is at or below its target, k
    being then the most stations to suggest (:func:`suggest_poses`)."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise GraphcalError(f"-k (the number of poses) must be a whole number >= 1, got {k}")
    targets = _targets(sigma_target_deg, sigma_target_mm)
    if out is not None and (Path(out).exists() or Path(out).is_symlink()):
        from graphcal.errors import DatasetError

        raise DatasetError(out, "--out", "a file that does not exist yet (graphcal never overwrites it); "
                           "give another name")
    if out is not None:
        from graphcal.io.atomic import check_output_location

        check_output_location(out)  # before the work
    options = CalibrationOptions()
    if noise_from is not None:
        from graphcal.calibration.noise_file import options_with_noise_from

        options, _ = options_with_noise_from(noise_from, options)
    model = PoseInformationModel(dataset, None, options)
    warnings: tuple[str, ...] = ()
    if noise_from is not None:
        from graphcal.calibration.noise_file import noise_from_mismatch

        warnings = tuple(noise_from_mismatch(noise_from, model.robot.name, model.ds.sensors))
    existing: dict = {}
    if after_existing:
        Lam, n_done = model.existing_information()
        s_rot, s_xyz = model.sigmas(model.prior_information() + Lam)
        existing = {"n_existing": n_done, "n_unseen": len(model.existing_T) - n_done,
                    "existing_sigma_rot_deg": tuple(float(v) for v in s_rot),
                    "existing_sigma_xyz_mm": tuple(float(v) for v in s_xyz)}
        if existing["n_unseen"] > 0:
            existing["visibility"] = model.visibility_text()
    poses = suggest_with_model(model, k, candidates=None, n_candidates=N_CANDIDATES, seed=0,
                               min_separation_deg=MIN_SEPARATION_DEG,
                               sigma_target_deg=None if targets is None else targets[0],
                               sigma_target_mm=None if targets is None else targets[1],
                               after_existing=after_existing)
    verdict = None
    if targets is not None and poses:
        reached = np.all(poses[-1].sigma_rot_deg <= targets[0] * (1 + 1e-9)) and \
            np.all(poses[-1].sigma_xyz_mm <= targets[1] * (1 + 1e-9))
        verdict = "targets reached" if reached else "targets not reached"
    if out is not None:
        _write_poses(out, poses, model.robot)
    return SuggestPosesResult(
        dataset=str(dataset), poses=tuple(poses), k=int(k), sensor=model.sensor,
        sensor_type=model.ds.sensors[model.sensor].type,
        others=tuple((name, spec.type) for name, spec in model.ds.sensors.items() if name != model.sensor),
        noise_from=None if noise_from is None else str(noise_from), after_existing=after_existing,
        files=() if out is None else (Path(out),), warnings=warnings, verdict=verdict,
        out=None if out is None else Path(out),
        sigma_target_deg=None if targets is None else tuple(float(v) for v in targets[0]),
        sigma_target_mm=None if targets is None else tuple(float(v) for v in targets[1]), **existing)
