"""Solvers of graphcal's factor graphs (docs/solvers.md).

* :mod:`.closed_form` — initial extrinsics in closed form (Wahba by SVD, linear least squares),
  independent of the CAD prior except along directions the data does not determine;
* :mod:`.batch` — Levenberg–Marquardt driven from Python (no per-callback copy of ``Values``),
  per-factor chi-square and outlier lists;
* :mod:`.covariance` — marginal covariances that never crash (Cholesky -> QR -> pseudo-inverse),
  body-axis sigmas, named unobservable directions, NEES;
* :mod:`.point_to_plane` — the Gauss-Newton step of point-to-plane ICP along the well-constrained
  directions only (the EKF's keyframe ICP and the stairs' stitching).
"""

from __future__ import annotations

from graphcal.solvers.batch import (
    LMResult,
    UnderdeterminedError,
    indeterminate_key,
    key_name,
    outlier_factors,
    solve_lm,
    whitened_errors,
)
from graphcal.solvers.closed_form import (
    extrinsic_from_scan_points,
    project_to_so3,
    rotation_from_normals,
    translation_from_distances,
)
from graphcal.solvers.covariance import (
    MarginalCovariances,
    body_axis_sigmas,
    marginal_covariances,
    nees,
    unobservable_directions,
)

__all__ = [
    "LMResult",
    "UnderdeterminedError",
    "indeterminate_key",
    "key_name",
    "outlier_factors",
    "solve_lm",
    "whitened_errors",
    "extrinsic_from_scan_points",
    "project_to_so3",
    "rotation_from_normals",
    "translation_from_distances",
    "MarginalCovariances",
    "body_axis_sigmas",
    "marginal_covariances",
    "nees",
    "unobservable_directions",
]
