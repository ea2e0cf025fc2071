"""Bookkeeping finder (graphcal/diagnosis/bookkeeping.py): two legs' joint columns exchanged in the logger.

NOT YET IMPLEMENTED: finds nothing (issue 29 in progress).
"""

from __future__ import annotations

__all__ = ["find_joint_columns"]


def find_joint_columns(model, say) -> tuple:
    """(corrections, corrected data, notes) for the nominal ``model`` (a DiagnosisModel with its
    noise learned); see graphcal/diagnosis/bookkeeping.py."""
    return (), model.data, ()
