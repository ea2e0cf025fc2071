"""Bookkeeping finder (graphcal/diagnosis/bookkeeping.py): sensor measurements under the wrong station, and sign / convention / unit errors of single planes.

NOT YET IMPLEMENTED: finds nothing (issue 29 in progress).
"""

from __future__ import annotations

__all__ = ["find_associations"]


def find_associations(model, say) -> tuple:
    """(corrections, corrected data, notes) for the nominal ``model`` (a DiagnosisModel with its
    noise learned); see graphcal/diagnosis/bookkeeping.py."""
    return (), model.data, ()
