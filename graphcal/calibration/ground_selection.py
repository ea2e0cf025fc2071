"""Which of a station's planes is the floor the robot stands on.

A camera that sees stairs, a table or a low wall sees several planes; the one with most points is
not always the floor (on the simulated Octopus in front of stairs a tread had 923 points and the
floor 360: calibrate took the tread and was 4 deg and 480 mm off, exit 0). The floor is the plane
the stance feet stand on, so the kinematics predict it in the sensor frame: with ``u`` the ground's
up direction in the body frame and ``h`` the body origin's height above it (both from the feet),
and an extrinsic ``T_body_sensor = (R, t)``,

    n_sensor = R^T u,        d_sensor = h + u . t        (n . x + d = 0, n towards the sensor)

:func:`choose_ground_planes` takes, per sensor: (1) at every station the candidate nearest to the
plane predicted by the CAD prior (distance in prior sigmas); (2) the closed-form extrinsic of
those picks, with far-off stations trimmed; (3) at every station whose pick disagrees with that
extrinsic by more than ``GATE_ANGLE_RAD`` or ``GATE_D_M``, the candidate nearest to its
prediction, if it agrees. Where the data hold a single plane per station (planes.csv with one row,
or a cloud fitted for one plane) a ``refit`` callback may fit more planes to that station's cloud.
Stations where no candidate agrees keep their pick (the graph's outlier screen judges them).
"""

from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

#: a pick agrees with the closed-form extrinsic within this angle (rad) and distance (m): well
#: above a plane fit's error (0.01-0.2 deg, < 1 mm) and the kinematic body pose's (~0.3 deg and a
#: few mm with leg errors), well below a stair's 130 mm riser
GATE_ANGLE_RAD = float(np.radians(3.0))
GATE_D_M = 0.03
#: planes fitted to a station's cloud when its single plane disagrees (floor, treads, a wall)
REFIT_MAX_PLANES = 4
#: floors of the CAD prior's sigmas in the first pick's distance (a zero sigma: "known exactly")
MIN_SIGMA_RAD = float(np.radians(1.0))
MIN_SIGMA_M = 0.01


def predicted_plane(u_body: np.ndarray, height_m: float, T_body_sensor: np.ndarray) -> tuple[np.ndarray, float]:
    """The floor (n, d) in the sensor frame predicted from the ground's up direction ``u_body``
    (body frame, unit), the body origin's height above the floor ``height_m`` (m) and
    ``T_body_sensor`` (4x4, m)."""
    R, t = T_body_sensor[:3, :3], T_body_sensor[:3, 3]
    return R.T @ u_body, float(height_m + u_body @ t)


def _misfit(plane, n_pred: np.ndarray, d_pred: float) -> tuple[float, float]:
    """(angle between normals (rad), |d - d_pred| (m))."""
    return float(np.arccos(np.clip(plane.n @ n_pred, -1.0, 1.0))), abs(float(plane.d) - d_pred)


#: two fits of one plane (a cloud fitted again: Open3D's RANSAC is not bit-repeatable) agree within
#: this angle (rad) and distance (m), far below the gates and a stair's riser
SAME_PLANE_RAD = float(np.radians(0.05))
SAME_PLANE_M = 5e-4


def _same_plane(a, b) -> bool:
    """Whether two fits are of the same plane (:data:`SAME_PLANE_RAD`, :data:`SAME_PLANE_M`)."""
    ang, dd = _misfit(a, b.n, float(b.d))
    return ang <= SAME_PLANE_RAD and dd <= SAME_PLANE_M


def _consensus_extrinsic(picks: list, U: np.ndarray, H: np.ndarray, T_start: np.ndarray) -> np.ndarray:
    """Closed-form extrinsic from the picks that agree with most others: the distances' offsets
    ``d - h - u . t_start`` of the floor's picks cluster within the gate, a tread's lie a riser
    lower; the largest cluster (ties: the lowest plane) is kept."""
    from graphcal.solvers.closed_form import robust_closed_form_extrinsic

    N = np.array([p.n for p in picks])
    D = np.array([p.d for p in picks])
    r = D - H - U @ T_start[:3, 3]
    counts = (np.abs(r[:, None] - r[None, :]) <= GATE_D_M).sum(axis=1)
    best = max(range(len(r)), key=lambda i: (counts[i], r[i]))
    keep = np.abs(r - r[best]) <= GATE_D_M
    if keep.sum() < 3:
        keep[:] = True
    return robust_closed_form_extrinsic(U[keep], N[keep], D[keep], H[keep], T_start)


def choose_ground_planes(
    candidates: Mapping[tuple[int, str], list],
    u_body: Mapping[int, np.ndarray],
    height_m: Mapping[int, float],
    priors: Mapping[str, tuple[np.ndarray, float, float]],
    refit: Callable[[tuple[int, str]], list] | None = None,
) -> tuple[dict, dict]:
    """The floor among each station's planes.

    Args:
        candidates: (station, sensor) -> planes seen there (:class:`PlaneMeasurement`, sensor frame),
            largest first.
        u_body, height_m: station -> the ground's up direction in the body frame (unit) and the
            body origin's height above the ground (m), from the stance feet.
        priors: sensor -> (T_body_sensor CAD 4x4, sigma_m, sigma_rad) of dataset.yaml.
        refit: (station, sensor) -> up to ``REFIT_MAX_PLANES`` planes of that station's cloud (None:
            the candidates are all there is).

    Returns:
        ((station, sensor) -> the chosen plane, (station, sensor) -> how many planes it was chosen
        from, for every station where the chosen plane is not the largest).
    """
    chosen = {k: v[0] for k, v in candidates.items() if v}
    moved: dict = {}
    pool = {k: list(v) for k, v in candidates.items() if v}

    def more(key) -> list:
        if len(pool[key]) == 1 and refit is not None:
            extra = refit(key)
            if extra:
                pool[key] = list(extra)
        return pool[key]

    def nearest(key, T, s_rad, s_m, *, gate: bool):
        s = key[0]
        n_pred, d_pred = predicted_plane(u_body[s], height_m[s], T)
        best, best_cost = None, np.inf
        for p in pool[key]:
            ang, dd = _misfit(p, n_pred, d_pred)
            if gate and (ang > GATE_ANGLE_RAD or dd > GATE_D_M):
                continue
            cost = np.hypot(ang / s_rad, dd / s_m)
            if cost < best_cost:
                best, best_cost = p, cost
        return best

    for sensor, (T_cad, sigma_m, sigma_rad) in priors.items():
        keys = [k for k in chosen if k[1] == sensor and k[0] in u_body]
        if len(keys) < 3:
            continue
        s_rad, s_m = max(sigma_rad, MIN_SIGMA_RAD), max(sigma_m, MIN_SIGMA_M)
        # (1) nearest to the CAD prediction; a single plane 3 sigma off it: fit more planes there
        for k in keys:
            n_pred, d_pred = predicted_plane(u_body[k[0]], height_m[k[0]], T_cad)
            ang, dd = _misfit(chosen[k], n_pred, d_pred)
            if np.hypot(ang / s_rad, dd / s_m) > 3.0:
                more(k)
            chosen[k] = nearest(k, T_cad, s_rad, s_m, gate=False)
        # (2) the closed-form extrinsic of the picks that agree with most others, (3) re-pick where
        # the picks disagree with it
        T = T_cad
        for _ in range(2):
            T = _consensus_extrinsic([chosen[k] for k in keys], np.array([u_body[k[0]] for k in keys]),
                                     np.array([height_m[k[0]] for k in keys]), T)
            changed = False
            for k in keys:
                n_pred, d_pred = predicted_plane(u_body[k[0]], height_m[k[0]], T)
                ang, dd = _misfit(chosen[k], n_pred, d_pred)
                if ang <= GATE_ANGLE_RAD and dd <= GATE_D_M:
                    continue
                more(k)
                p = nearest(k, T, GATE_ANGLE_RAD, GATE_D_M, gate=True)
                if p is not None and p is not chosen[k]:
                    chosen[k], changed = p, True
            if not changed:
                break
        for k in keys:
            if not _same_plane(chosen[k], pool[k][0]):  # a refit's largest is the same plane, another object
                moved[k] = len(pool[k])
    return chosen, moved


def ground_choice_warnings(data) -> list[str]:
    """One warning per sensor of ``data`` (:class:`CalibrationData`) with stations where the floor
    taken is not the largest plane the camera saw (``data.ground_not_largest``)."""
    from graphcal.clouds.plane_table import stations_text

    moved = getattr(data, "ground_not_largest", {})
    out = []
    for sensor in sorted({k[1] for k in moved}):
        ids = sorted(k[0] for k in moved if k[1] == sensor)
        total = sum(1 for k in data.planes if k[1] == sensor)
        out.append(f"{sensor}: at {len(ids)} of {total} stations the largest plane the "
                   f"camera saw is not the floor (stairs, a wall or a table in view; stations {stations_text(ids)}): "
                   "the plane the stance feet and the extrinsic predict was taken instead")
    return out
