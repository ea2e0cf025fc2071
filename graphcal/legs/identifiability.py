"""Which parameters the data determine: column-scaled SVD and QR with column pivoting of the
stacked identification Jacobian, evaluated on the actual data.

Input: the whitened Jacobian ``A`` (m, p) of all residuals (each row divided by its noise) and a
scale per parameter, the error one expects a priori (e.g. 2 deg for a joint offset, 10 mm for a
link length, 1 rad / 1 m for an unknown motion-capture pose; given in SI, rad and m). Each
parameter comes out **identifiable**, **only in combination** (structural, or weakly determined by
these data; the combination in SI units per unit of the parameter) or **not identifiable**; the
free set is every identifiable parameter completed to the numerical rank by pivoted QR, the
others held at their nominal value.

The tolerances (:data:`RTOL`, :data:`S_MIN`, :data:`F_IDENTIFIABLE`) and the decision:
docs/legs.md, "Which parameters: identifiability".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

__all__ = [
    "RTOL",
    "S_MIN",
    "F_IDENTIFIABLE",
    "ParameterIdentifiability",
    "IdentifiabilityReport",
    "identifiability",
]

#: relative singular value below which a direction is exactly aliased (round-off level)
RTOL = 1e-8
#: absolute scaled singular value (noise standard deviations for an error of the a-priori size)
S_MIN = 3.0
#: largest null-space fraction of an identifiable parameter
F_IDENTIFIABLE = 0.05
#: smallest contribution |w_i| |B_i| (relative to the largest) of a parameter listed in a combination
_COMBO_MIN = 0.1

STATUSES = ("identifiable", "combination", "unidentifiable")


@dataclass(frozen=True)
class ParameterIdentifiability:
    """The verdict on one parameter.

    Attributes:
        name: parameter name.
        status: ``"identifiable"``, ``"combination"`` (only together with other parameters) or
            ``"unidentifiable"`` (no visible effect on the data).
        free: True when the solver estimates it; False when it is held at its nominal value.
        null_fraction: ``f_j`` (0: determined on its own, 1: entirely in the null space).
        effect: ``|B_j|``, noise standard deviations an error of the a-priori size causes.
        combination: for ``"combination"``: (name, coefficient) pairs of the null direction that
            involves this parameter, coefficients in SI units per unit of this parameter (this
            parameter first with 1.0): changing the parameters by ``coefficient * t`` together
            leaves every measurement (nearly) unchanged.
        structural: True when the combination is exact (singular value at round-off level: no
            data of this kind can separate the parameters, e.g. a first-joint offset and a
            rotation of the motion-capture frame); False when these data only determine it poorly
            (singular value below ``s_min``; more varied postures would separate them).
    """

    name: str
    status: str
    free: bool
    null_fraction: float
    effect: float
    combination: tuple[tuple[str, float], ...] = ()
    structural: bool = False

    @property
    def text(self) -> str:
        """One sentence for reports."""
        held = "estimated" if self.free else "held at its nominal value"
        if self.status == "identifiable":
            return f"{self.name}: identifiable ({held})"
        if self.status == "unidentifiable":
            return f"{self.name}: not identifiable: no visible effect on these data ({held})"
        others = ", ".join(n for n, _ in self.combination[1:]) or "other parameters"
        kind = ("exactly aliased: no data of this kind separates them" if self.structural
                else "weakly determined by these data: more varied postures would separate them")
        return (f"{self.name}: only in combination with {others} ({kind}; the data do not see a change along "
                f"{combination_text(self.combination)}; {held})")


def combination_text(combination) -> str:
    """``"a + 1.00 b - 0.047 c"`` of a combination's (name, coefficient) pairs."""
    parts = []
    for i, (n, c) in enumerate(combination):
        if i == 0:
            parts.append(n if c == 1.0 else f"{c:.3g} {n}")
            continue
        sign = "-" if c < 0 else "+"
        mag = abs(c)
        parts.append(f"{sign} {n}" if abs(mag - 1.0) < 5e-3 else f"{sign} {mag:.3g} {n}")
    return " ".join(parts)


@dataclass(frozen=True)
class IdentifiabilityReport:
    """Identifiability of p candidate parameters on one data set.

    Attributes:
        names: candidate parameter names (column order).
        scales: (p,) a-priori scales (SI units).
        singular_values: (p,) singular values of the scaled whitened Jacobian, descending (zeros
            appended when it has fewer rows than columns).
        threshold: ``max(rtol * s_max, s_min)``.
        rank: number of singular values at or above the threshold.
        parameters: one :class:`ParameterIdentifiability` per name.
        rtol, s_min, f_identifiable: the tolerances used.
    """

    names: tuple[str, ...]
    scales: np.ndarray
    singular_values: np.ndarray
    threshold: float
    rank: int
    parameters: tuple[ParameterIdentifiability, ...]
    rtol: float = RTOL
    s_min: float = S_MIN
    f_identifiable: float = F_IDENTIFIABLE

    def __getitem__(self, name: str) -> ParameterIdentifiability:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    @property
    def free(self) -> tuple[str, ...]:
        """Names of the parameters the solver estimates."""
        return tuple(p.name for p in self.parameters if p.free)

    @property
    def held(self) -> tuple[str, ...]:
        """Names of the parameters held at their nominal value."""
        return tuple(p.name for p in self.parameters if not p.free)

    def by_status(self, status: str) -> tuple[str, ...]:
        """Names with the given status."""
        return tuple(p.name for p in self.parameters if p.status == status)

    def lines(self) -> list[str]:
        """One sentence per parameter."""
        return [p.text for p in self.parameters]


def _sparse_alias(U: np.ndarray, j: int, candidates: list[int], tol: float = 1e-6) -> np.ndarray | None:
    """Orthogonal matching pursuit: ``w`` (p,) with ``w_j = 1`` and the fewest other non-zeros such
    that ``U w ~ 0`` (unit columns, relative residual below ``tol``), or None."""
    target = U[:, j]
    chosen: list[int] = []
    r = target
    c = np.zeros(0)
    for _ in range(len(candidates)):
        rest = [i for i in candidates if i not in chosen]
        if not rest:
            break
        chosen.append(rest[int(np.argmax(np.abs(U[:, rest].T @ r)))])
        c, *_ = np.linalg.lstsq(U[:, chosen], target, rcond=None)
        r = target - U[:, chosen] @ c
        if np.linalg.norm(r) < tol:
            w = np.zeros(U.shape[1])
            w[j] = 1.0
            w[chosen] = -c
            return w
    return None


def identifiability(
    A_whitened,
    names,
    scales,
    *,
    rtol: float = RTOL,
    s_min: float = S_MIN,
    f_identifiable: float = F_IDENTIFIABLE,
) -> IdentifiabilityReport:
    """Classify the parameters of a whitened Jacobian and choose the free set (see module docstring).

    Args:
        A_whitened: (m, p) Jacobian of the whitened residuals with respect to the p candidates,
            in SI units per parameter.
        names: p parameter names.
        scales: (p,) a-priori error scales, SI units (> 0).
        rtol, s_min, f_identifiable: tolerances.

    Returns:
        :class:`IdentifiabilityReport`.
    """
    A = np.asarray(A_whitened, dtype=float)
    names = tuple(str(n) for n in names)
    scales = np.asarray(scales, dtype=float).reshape(-1)
    if A.ndim != 2 or A.shape[1] != len(names) or scales.shape != (len(names),):
        raise ValueError(f"identifiability: A {A.shape}, {len(names)} names and {scales.shape} scales disagree")
    if not np.all(np.isfinite(A)) or not np.all(scales > 0):
        raise ValueError("identifiability: A must be finite and the scales positive")
    m, p = A.shape
    if m > p:  # only A^T A matters (column norms, singular values, null spaces): work on the R of A = QR
        A = np.linalg.qr(A, mode="r")
        m = p
    B = A * scales[None, :]
    if p == 0:
        return IdentifiabilityReport((), scales, np.zeros(0), float(s_min), 0, (), rtol, s_min, f_identifiable)

    def right_singular(M):
        Ms = M if m >= p else np.vstack([M, np.zeros((p - m, p))])  # square up: Vt is then (p, p)
        _, sv, Vt = np.linalg.svd(Ms, full_matrices=False)
        out = np.zeros(p)
        out[: sv.size] = sv
        return out, Vt

    effect = np.linalg.norm(B, axis=0)
    # structural (exact) aliasing: scale invariant, on unit columns
    colnorm = np.linalg.norm(A, axis=0)
    live = colnorm > 0
    U = np.where(live[None, :], A / np.where(live, colnorm, 1.0)[None, :], 0.0)
    s_u, Vt_u = right_singular(U)
    Nst = Vt_u[s_u < rtol * max(float(s_u[0]), 1e-300)].T
    frac_st = np.linalg.norm(Nst, axis=1) if Nst.size else np.zeros(p)
    # statistical: a-priori scaled columns, threshold at the noise level
    s_full, Vt = right_singular(B)
    s_max = float(s_full[0])
    thr = max(rtol * s_max, s_min)
    keep = s_full >= thr
    rank = int(keep.sum())
    Nul = Vt[~keep].T  # (p, p - rank)
    frac = np.linalg.norm(Nul, axis=1) if Nul.size else np.zeros(p)

    status, structural = [], []
    for j in range(p):
        structural.append(bool(frac_st[j] >= f_identifiable))
        if effect[j] < s_min:
            status.append("unidentifiable")
        elif structural[j] or frac[j] >= f_identifiable:
            status.append("combination")
        else:
            status.append("identifiable")
    ident = [j for j in range(p) if status[j] == "identifiable"]

    # free set: identifiable columns, then pivoted QR of the rest (identifiable part projected out)
    free = set(ident)
    need = rank - len(ident)
    rest = [j for j in range(p) if j not in free and status[j] != "unidentifiable"]
    if need > 0 and rest:
        R_rest = B[:, rest]
        if ident:
            Q, _ = np.linalg.qr(B[:, ident])
            R_rest = R_rest - Q @ (Q.T @ R_rest)
        _, _, piv = scipy.linalg.qr(R_rest, mode="economic", pivoting=True)
        for c in piv[:need]:
            free.add(rest[int(c)])

    params = []
    for j in range(p):
        combo: tuple[tuple[str, float], ...] = ()
        if status[j] == "combination":
            sparse = _sparse_alias(U, j, [i for i in range(p) if i != j and structural[i] and live[i]]) \
                if structural[j] else None
            if sparse is not None:  # the fewest partners that reproduce the column exactly
                w = sparse
                si = np.where(live, 1.0 / np.where(live, colnorm, 1.0), 0.0)  # SI per unit coordinate
                contrib = np.abs(w)
            elif structural[j]:
                w = Nst @ Nst[j]  # null direction closest to e_j, unit-column coordinates
                w = w / w[j]
                si = np.where(live, 1.0 / np.where(live, colnorm, 1.0), 0.0)
                contrib = np.abs(w)
            else:
                w = Nul @ Nul[j]  # scaled coordinates
                w = w / w[j]
                si = scales
                contrib = np.abs(w) * effect
            big = np.flatnonzero(contrib >= _COMBO_MIN * contrib.max())
            order = [j] + sorted((i for i in big if i != j), key=lambda i: -contrib[i])
            # SI units per unit of parameter j: delta_i = si_i w_i t, delta_j = si_j t
            combo = tuple((names[i], float(si[i] * w[i] / si[j])) for i in order)
        params.append(ParameterIdentifiability(names[j], status[j], j in free, float(max(frac[j], frac_st[j])),
                                               float(effect[j]), combo, structural[j]))
    return IdentifiabilityReport(names, scales, s_full, float(thr), rank, tuple(params), rtol, s_min, f_identifiable)
