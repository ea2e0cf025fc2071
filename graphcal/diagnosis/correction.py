"""A bookkeeping error found in measured data and its correction (graphcal/diagnosis/bookkeeping.py):
the cause names and the record every bookkeeping finder returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BOOKKEEPING_CAUSES", "Correction"]

#: The bookkeeping causes (docs/diagnosis.md, "Bookkeeping errors"); each is a :class:`Correction`'s cause.
BOOKKEEPING_CAUSES = (
    "stations_exchanged",  # two stations' sensor data exchanged
    "station_mislabelled",  # a sensor measurement belongs to another station
    "normal_sign",  # one component of a plane normal printed/logged with the wrong sign
    "plane_convention",  # a plane in the opposite (n, d) convention
    "distance_unit",  # a plane distance in millimetres (or cm) where metres are expected
    "legs_exchanged",  # two legs' joint columns exchanged
    "height_step",  # an undeclared session boundary: the feet re-planted at another height
    "extrinsic_knock",  # an undeclared extrinsic change (reported through extrinsic_change)
)


@dataclass(frozen=True)
class Correction:
    """One bookkeeping error found in the data, with the correction applied.

    Attributes:
        cause: a name of :data:`BOOKKEEPING_CAUSES`.
        where: location as sorted (key, value) pairs (``sensor``, ``station``, ``stations``,
            ``legs``, ``from_station``, ``until_station``: the first station no longer affected), the stations' ids as in stations.csv.
        corrected: what the data say and what the correction makes of them, as (key, value)
            pairs in SI units (e.g. ``("d_given_m", 1050.0), ("d_corrected_m", 1.05)``).
        statistic: chi-square drop of the corrected against the uncorrected data, at physical
            noise; dof: its degrees of freedom; p_value: its tail probability.
        confidence: how much better this correction explains the data than the next-best one
            (chi-square difference; ``inf`` when there is no alternative).
        alternatives: other corrections the data cannot tell from this one (labels), if any.
        note: one sentence for the report.
    """

    cause: str
    where: tuple
    corrected: tuple = ()
    statistic: float = float("nan")
    dof: int = 0
    p_value: float = float("nan")
    confidence: float = float("inf")
    alternatives: tuple = ()
    note: str = ""

    def get(self, key: str):
        return dict(self.where).get(key)

    def label(self) -> str:
        loc = ", ".join(f"{k}={list(v) if isinstance(v, tuple) else v}" for k, v in self.where)
        return f"{self.cause}({loc})"

    def to_dict(self) -> dict:
        def plain(v):
            if isinstance(v, (tuple, list, np.ndarray)):
                return [plain(x) for x in v]
            if isinstance(v, (np.floating, np.integer)):
                return v.item()
            return v

        return {"cause": self.cause, "where": {k: plain(v) for k, v in self.where},
                "corrected": {k: plain(v) for k, v in self.corrected}, "statistic": float(self.statistic),
                "dof": int(self.dof), "p_value": float(self.p_value), "confidence": float(self.confidence),
                "alternatives": list(self.alternatives), "note": self.note}
