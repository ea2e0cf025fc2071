"""The catalogue of effects ``graphcal diagnose`` can name, as candidates and findings.

A :class:`Candidate` is one cause at one location (``joint_offset`` of ``lf_femur_joint``,
``extrinsic_change`` of ``depth`` from station 31, ...); a :class:`Finding` is a candidate the data
supports, with its estimated parameters, their sigma, the evidence and the held-out gain.

The names and parameters (SI units) are those of the catalogue table (docs/diagnosis.md) and of
the simulator's effects (the one list :data:`graphcal.models.effects.CAUSES`), so a finding can be compared with what
the simulator hid.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from graphcal.models.effects import CAUSES, cause_record

__all__ = ["CAUSES", "Candidate", "Finding", "relevant"]

@dataclass(frozen=True)
class Candidate:
    """One cause at one location.

    Attributes:
        cause: a name of :data:`CAUSES`.
        where: location in the catalogue's terms, as sorted (key, value) pairs: ``sensor``,
            ``session``, ``leg`` + ``joint``, ``station`` + ``sensor``, ``stations``.
        family_size: how many candidates of this cause were tested (the multiple-comparison count).
    """

    cause: str
    where: tuple = ()
    family_size: int = 1

    @property
    def where_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.where}

    def label(self) -> str:
        loc = ", ".join(f"{k}={v}" for k, v in self.where_dict.items())
        return f"{self.cause}({loc})" if loc else self.cause

    def get(self, key: str):
        return dict(self.where).get(key)


@dataclass(frozen=True)
class Evidence:
    """Evidence for a candidate against the current model.

    Attributes:
        test: ``"score"`` (Lagrange multiplier at the current fit) or ``"likelihood_ratio"``.
        statistic: chi-square statistic; dof: its degrees of freedom (the rank of the candidate's
            information after the current model's parameters are projected out).
        p_value: chi-square tail probability; p_family: times the family size (Bonferroni), capped at 1.
        log10_p_family: log10 of ``p_family`` (finite even where p underflows).
        delta_bic: ``statistic - dof * ln(n_rows)``: > 0 favours the extended model.
    """

    test: str
    statistic: float
    dof: int
    p_value: float
    p_family: float
    log10_p_family: float
    delta_bic: float

    def to_dict(self) -> dict:
        return {"test": self.test, "statistic": float(self.statistic), "dof": int(self.dof),
                "p_value": float(self.p_value), "p_family": float(self.p_family),
                "log10_p_family": float(self.log10_p_family), "delta_bic": float(self.delta_bic)}


@dataclass(frozen=True)
class Gain:
    """Held-out prediction of the sensors' measurements (whitened RMS, unitless) before and after,
    and the paired test over held-out stations (p_value: one-sided, that after predicts better)."""

    heldout_rms_before: float
    heldout_rms_after: float
    folds: int
    p_value: float = float("nan")  # one-sided paired Wilcoxon over held-out stations (heldout.paired_test)
    stations: int = 0

    @property
    def relative(self) -> float:
        return float(self.heldout_rms_after / self.heldout_rms_before) if self.heldout_rms_before > 0 else float("nan")

    def to_dict(self) -> dict:
        return {"heldout_rms_before": float(self.heldout_rms_before), "heldout_rms_after": float(self.heldout_rms_after),
                "relative": self.relative, "folds": int(self.folds), "p_value": float(self.p_value),
                "stations": int(self.stations)}


@dataclass(frozen=True)
class Finding:
    """A named cause the data supports, with the extended model's estimate.

    Attributes:
        candidate: the cause and its location.
        parameters, sigma: estimated parameters and their 1-sigma (SI, the catalogue's names).
        evidence: the likelihood-ratio test of the fitted extension (and the screening score).
        score: the screening score test that selected it.
        gain: held-out gain.
        supported: the held-out gain is significant (paired test over held-out stations); a finding
            that is not is reported as tentative and the diagnosis says structure remains.
    """

    candidate: Candidate
    parameters: dict
    sigma: dict
    evidence: Evidence
    score: Evidence
    gain: Gain | None = None
    notes: tuple = field(default=())
    supported: bool = True  # its held-out gain is significant (heldout.paired_test); else said "tentative"

    def to_dict(self) -> dict:
        return {
            "cause": self.candidate.cause,
            "where": self.candidate.where_dict,
            "parameters": {k: _plain(v) for k, v in self.parameters.items()},
            "sigma": {k: _plain(v) for k, v in self.sigma.items()},
            "evidence": {**self.evidence.to_dict(), "screening": self.score.to_dict()},
            "gain": self.gain.to_dict() if self.gain is not None else None,
            "supported": bool(self.supported),
            "notes": list(self.notes),
        }


def _plain(v):
    if isinstance(v, (list, tuple, np.ndarray)):
        return [float(x) for x in np.asarray(v).reshape(-1)]
    return float(v)


def relevant(cause: str, parameters: dict) -> bool:
    """Whether estimated ``parameters`` of ``cause`` reach the catalogue's minimum magnitude
    (:attr:`graphcal.models.effects.Cause.relevant_from`)."""
    return cause_record(cause).relevant(parameters)
