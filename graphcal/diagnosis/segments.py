"""Bookkeeping finder (graphcal/diagnosis/bookkeeping.py): undeclared segment boundaries (height steps, knocks) by change-point segmentation over the station sequence.

NOT YET IMPLEMENTED: finds nothing (issue 29 in progress).
"""

from __future__ import annotations

__all__ = ["find_segments"]


def find_segments(model, say) -> tuple:
    """(corrections, corrected data, notes) for the nominal ``model`` (a DiagnosisModel with its
    noise learned); see graphcal/diagnosis/bookkeeping.py."""
    return (), model.data, ()
