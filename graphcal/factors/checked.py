"""Shape-checked GTSAM ``CustomFactor``: the only place graphcal builds a Python factor.

GTSAM does not check the Jacobians a Python ``CustomFactor`` returns: a wrong row count, a 1-D
array or an unset ``H[i]`` crashes the interpreter, and a wrong column count is accepted silently
and gives a wrong solution (docs/factors.md, engineering notes). :func:`checked_custom_factor`
wraps an error function that works on plain numpy inputs and checks every output before it
reaches GTSAM, raising :class:`FactorShapeError` (both an ``AssertionError`` and a
``ValueError``) that names the factor and the key.

Variable kinds and what the error function receives for each (tangent order and perturbation
side of the Jacobian columns it must return):

==================  =============================  ====  =============================================
kind                value passed                   dim   Jacobian column convention
==================  =============================  ====  =============================================
``Pose3``           4x4 ``T``                      6     ``T Exp([omega, v])`` (right, rotation first)
``Rot3``            3x3 ``R``                      3     ``R Exp(omega)``
``Point3``          (3,) ``p``                     3     ``p + dp``
``Vector``          (k,) ``x``                     k     ``x + dx``
``OrientedPlane3``  (4,) ``[nx, ny, nz, d]``       3     gtsam retract: ``n <- Unit3 retract along
                                                         n.basis()`` (2), ``d <- d + dd`` (1)
``Unit3``           (3,) unit ``n``                2     gtsam retract along ``n.basis()``
==================  =============================  ====  =============================================
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import gtsam
import numpy as np

__all__ = [
    "FactorShapeError",
    "checked_custom_factor",
    "KIND_DIMS",
    "tangent_basis",
    "world_plane",
    "with_robust",
]

#: tangent dimension of each supported variable kind (None: given by ``dims``)
KIND_DIMS: dict[str, int | None] = {
    "Pose3": 6,
    "Rot3": 3,
    "Point3": 3,
    "Vector": None,
    "OrientedPlane3": 3,
    "Unit3": 2,
}

_READERS: dict[str, Callable[[gtsam.Values, int], np.ndarray]] = {
    "Pose3": lambda v, k: v.atPose3(k).matrix(),
    "Rot3": lambda v, k: v.atRot3(k).matrix(),
    "Point3": lambda v, k: np.asarray(v.atPoint3(k), dtype=float),
    "Vector": lambda v, k: np.asarray(v.atVector(k), dtype=float),
    "OrientedPlane3": lambda v, k: np.asarray(v.atOrientedPlane3(k).planeCoefficients(), dtype=float),
    "Unit3": lambda v, k: np.asarray(v.atUnit3(k).point3(), dtype=float),
}


class FactorShapeError(AssertionError, ValueError):
    """A custom factor's error or Jacobian has the wrong type, shape or values (raised, never a crash)."""


def _key_text(key: int) -> str:
    try:
        return gtsam.DefaultKeyFormatter(key)
    except Exception:  # pragma: no cover - formatter absent in some builds
        return str(key)


_add_reduce = np.add.reduce  # the ufunc method itself: no Python-level wrapper per call


def _matrix_problem(M, shape: tuple[int, int]) -> str | None:
    """What is wrong with Jacobian ``M`` (None if it is a finite float64 array of ``shape``)."""
    if not isinstance(M, np.ndarray):
        return f"expected a numpy float64 array of shape {shape}, got {type(M).__name__}"
    if M.dtype != np.float64:
        return f"expected dtype float64, got {M.dtype}"
    if M.ndim != 2:
        return f"expected a 2-D array of shape {shape}, got {M.ndim}-D shape {M.shape}"
    if M.shape != shape:
        return f"expected shape {shape} (rows = error dim, cols = variable dim), got {M.shape}"
    if not np.isfinite(M).all():  # the method: np.all's dispatch costs ~4 us per call, per factor evaluation
        return "contains NaN or inf"
    return None


def checked_custom_factor(
    noise_model: gtsam.noiseModel.Base,
    keys: Sequence[int],
    error_fn: Callable,
    dims: Sequence[int],
    error_dim: int,
    *,
    kinds: Sequence[str],
    name: str = "custom factor",
) -> gtsam.CustomFactor:
    """A ``gtsam.CustomFactor`` whose error and Jacobians are checked before GTSAM sees them.

    Args:
        noise_model: noise model of dimension ``error_dim`` (Gaussian, diagonal, robust...).
        keys: the variable keys, in the order ``error_fn`` takes the values.
        error_fn: ``error_fn(*values, want_jacobians: bool) -> (error, jacobians)`` where each
            value is the plain numpy form of the variable (see module table), ``error`` is a
            float64 array of shape (error_dim,) and ``jacobians`` is ``None`` when
            ``want_jacobians`` is False, else a list of float64 2-D arrays of shapes
            ``(error_dim, dims[k])``, one per key, w.r.t. the perturbation of the module table.
        dims: tangent dimension of each variable.
        error_dim: dimension of the error vector.
        kinds: variable kind per key (``"Pose3"``, ``"Rot3"``, ``"Point3"``, ``"Vector"``,
            ``"OrientedPlane3"``, ``"Unit3"``).
        name: factor name used in error messages.

    Raises:
        FactorShapeError: at construction if the arguments disagree (lengths, dims of the kinds,
            noise model dimension); at evaluation (``error``, ``linearize``, inside an optimizer)
            if ``error_fn`` returns a wrong type, dtype, shape, a NaN, or a ``Vector`` variable
            has a length other than ``dims[k]``.
    """
    keys = [int(k) for k in keys]
    dims = [int(d) for d in dims]
    kinds = list(kinds)
    error_dim = int(error_dim)
    if not (len(keys) == len(dims) == len(kinds)):
        raise FactorShapeError(f"{name}: {len(keys)} keys, {len(dims)} dims and {len(kinds)} kinds: they must match")
    if len(set(keys)) != len(keys):
        raise FactorShapeError(f"{name}: a key appears twice in {[_key_text(k) for k in keys]}")
    for k, d, kind in zip(keys, dims, kinds):
        if kind not in KIND_DIMS:
            raise FactorShapeError(f"{name}: key {_key_text(k)}: unknown kind {kind!r}; known: {', '.join(KIND_DIMS)}")
        want = KIND_DIMS[kind]
        if (want is not None and d != want) or d < 1:
            raise FactorShapeError(f"{name}: key {_key_text(k)} of kind {kind} has dimension {want}, dims says {d}")
    if error_dim < 1:
        raise FactorShapeError(f"{name}: error_dim must be >= 1, got {error_dim}")
    if noise_model.dim() != error_dim:
        raise FactorShapeError(f"{name}: noise model has dimension {noise_model.dim()}, error_dim is {error_dim}")
    readers = [_READERS[kind] for kind in kinds]
    vector_slots = [i for i, kind in enumerate(kinds) if kind == "Vector"]
    n_keys = len(keys)
    shapes = [(error_dim, d) for d in dims]

    def _callback(this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
        # runs at every factor evaluation (tens of thousands per calibration): the common path is
        # kept to a few cheap checks; key names are only formatted for an error
        fkeys = this.keys()
        args = [read(values, k) for read, k in zip(readers, fkeys)]
        for i in vector_slots:
            if args[i].shape != (dims[i],):
                raise FactorShapeError(
                    f"{name}: variable {_key_text(fkeys[i])} has length {args[i].shape[0]}, the factor expects {dims[i]}"
                )
        want = H is not None
        out = error_fn(*args, want)
        if not isinstance(out, tuple) or len(out) != 2:
            raise FactorShapeError(f"{name}: error function must return (error, jacobians), got {type(out).__name__}")
        e, Hs = out
        if not isinstance(e, np.ndarray) or e.dtype != np.float64 or e.shape != (error_dim,):
            got = f"{e.dtype} {e.shape}" if isinstance(e, np.ndarray) else type(e).__name__
            raise FactorShapeError(f"{name}: error must be a float64 array of shape ({error_dim},), got {got}")
        # finiteness of everything at once: a sum of finite float64 numbers is finite (short of
        # overflow past 1e308, which the detailed checks below then clear)
        total = _add_reduce(e, axis=None)
        if want:
            if Hs is None or len(Hs) != n_keys:
                got = "None" if Hs is None else f"{len(Hs)}"
                raise FactorShapeError(f"{name}: expected {n_keys} Jacobians (one per key), got {got}")
            for i in range(n_keys):
                Hi = Hs[i]
                if type(Hi) is not np.ndarray or Hi.dtype != np.float64 or Hi.shape != shapes[i]:
                    problem = _matrix_problem(Hi, shapes[i])
                    if problem is not None:
                        raise FactorShapeError(f"{name}: Jacobian w.r.t. {_key_text(fkeys[i])} ({kinds[i]}): {problem}")
                total += _add_reduce(Hi, axis=None)
        if not math.isfinite(total):
            if not np.isfinite(e).all():
                raise FactorShapeError(f"{name}: error contains NaN or inf: {e}")
            for i in range(n_keys if want else 0):
                problem = _matrix_problem(Hs[i], shapes[i])
                if problem is not None:
                    raise FactorShapeError(f"{name}: Jacobian w.r.t. {_key_text(fkeys[i])} ({kinds[i]}): {problem}")
        if want:
            for i in range(n_keys):
                H[i] = Hs[i]
        return e

    return gtsam.CustomFactor(noise_model, keys, _callback)


# ----------------------------------------------------------------------------- shared helpers (numpy only)
def tangent_basis(n) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane orthogonal to the unit vector ``n``.

    Deterministic and identical to ``gtsam.Unit3(n).basis()`` (GTSAM's rule: cross ``n`` with the
    coordinate axis of smallest ``|n_i|``, first one on ties; ``b2 = n x b1``), so the same basis
    is used for a measured direction and for the retract of a Unit3 / OrientedPlane3 variable.
    Columns ``[b1, b2]`` with ``b1 x b2 = n``.
    """
    # scalar arithmetic: called per factor evaluation, where np.cross's generality cost ~60 us
    n0, n1, n2 = (float(v) for v in np.asarray(n, dtype=float).reshape(3))
    a0, a1, a2 = abs(n0), abs(n1), abs(n2)
    if a0 <= a1 and a0 <= a2:
        x, y, z = 0.0, n2, -n1  # n x e_x
    elif a1 <= a0 and a1 <= a2:
        x, y, z = -n2, 0.0, n0  # n x e_y
    else:
        x, y, z = n1, -n0, 0.0  # n x e_z
    s = math.sqrt(x * x + y * y + z * z)
    x, y, z = x / s, y / s, z / s
    u, v, w = n1 * z - n2 * y, n2 * x - n0 * z, n0 * y - n1 * x  # n x b1
    s = math.sqrt(u * u + v * v + w * w)
    return np.array([[x, u / s], [y, v / s], [z, w / s]])


def world_plane(plane_world) -> tuple[np.ndarray, float]:
    """(n_w unit (3,), d_w) from a world plane ``[nx, ny, nz, d]`` (n.x + d = 0); ``None`` = ground z = 0."""
    if plane_world is None:
        return np.array([0.0, 0.0, 1.0]), 0.0
    c = np.asarray(plane_world, dtype=float).reshape(-1)
    if c.shape != (4,) or not np.all(np.isfinite(c)):
        raise ValueError(f"plane_world must be 4 finite numbers [nx, ny, nz, d], got {plane_world!r}")
    norm = np.linalg.norm(c[:3])
    if norm < 1e-12:
        raise ValueError(f"plane_world has a zero normal: {plane_world!r}")
    return c[:3] / norm, float(c[3] / norm)


def with_robust(noise_model, robust):
    """``noise_model`` wrapped in ``gtsam.noiseModel.Robust`` with the mEstimator ``robust`` (None: unchanged)."""
    if robust is None:
        return noise_model
    if not isinstance(robust, gtsam.noiseModel.mEstimator.Base):
        raise TypeError(
            f"robust must be a gtsam.noiseModel.mEstimator (e.g. mEstimator.Huber.Create(1.345)), got {type(robust).__name__}"
        )
    return gtsam.noiseModel.Robust.Create(robust, noise_model)
