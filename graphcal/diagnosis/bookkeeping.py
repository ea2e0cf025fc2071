"""Bookkeeping errors in measured data, found before the physical causes are looked for (issue 29).

Published and field data come with bookkeeping errors: a sensor frame filed under the wrong
station, two stations' sensor data exchanged, a sign lost in print, millimetres where metres are
expected, two legs' joint columns exchanged in the logger, the robot re-planted mid-session (a
height step) or its sensor knocked without anyone writing it down. Each distorts every physical
cause fitted after it (two exchanged legs read as coxa offsets of +87 and -86 deg), so
:func:`find_bookkeeping` looks for them first, on the nominal model, and hands the corrected
measurements to the diagnosis loop. Every correction is reported with its evidence (the chi-square
drop at physical noise, its p-value), its confidence against the next-best explanation, and the
value the data hold against the corrected one; nothing in the dataset is changed.

The finders, in the order they run (each sees the data as the previous ones corrected them):

1. :func:`graphcal.diagnosis.joint_columns.find_joint_columns` -- legs' joint columns exchanged;
2. :func:`graphcal.diagnosis.association.find_associations` -- sensor measurements under the wrong
   station (swaps, mislabels) and sign / convention / unit errors of single planes;
3. :func:`graphcal.diagnosis.segments.find_segments` -- undeclared segment boundaries (height steps,
   knocks), found by change-point segmentation over the station sequence, ends included.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from graphcal.diagnosis.correction import BOOKKEEPING_CAUSES, Correction

__all__ = ["BOOKKEEPING_CAUSES", "Correction", "BookkeepingResult", "find_bookkeeping"]


@dataclass(frozen=True, eq=False)
class BookkeepingResult:
    """What :func:`find_bookkeeping` found: the corrections, the corrected measurements
    (a :class:`graphcal.calibration.measurements.CalibrationData`) and notes for the report (what
    was suspected but could not be resolved, e.g. "station 52: an outlier or a knock at the last
    station -- one station cannot tell")."""

    corrections: tuple
    data: object
    notes: tuple = field(default=())
    #: (station, sensor) of measurements left out because no correction explains them (a plane
    #: distance beyond what a sensor sees): a warning in the diagnosis
    left_out: tuple = field(default=())


def find_bookkeeping(model, say, *, implausible=None, initial=None) -> BookkeepingResult:
    """Run the bookkeeping finders on the nominal ``model`` (a
    :class:`graphcal.diagnosis.model.DiagnosisModel` with its noise learned); ``say(msg)`` logs a
    progress line. Each finder has the signature ``finder(model, say, initial) -> (corrections, data,
    notes)`` and returns ``model.data`` unchanged when it finds nothing; ``initial`` (gtsam.Values,
    the nominal model's solution, or None) is where a finder's first solve starts. ``implausible(plane) ->
    bool``: planes no sensor can see (a distance beyond 100 m); those the association finder does
    not correct are taken out of the data before the segments finder (which would read one as a
    knock) and listed in ``left_out``."""
    import dataclasses

    from graphcal.diagnosis.association import find_associations
    from graphcal.diagnosis.joint_columns import find_joint_columns
    from graphcal.diagnosis.segments import find_segments

    corrections: list = []
    notes: list = []
    left_out: tuple = ()
    for finder in (find_joint_columns, find_associations, find_segments):
        if finder is find_segments and implausible is not None:
            left_out = tuple(sorted(k for k, pl in model.data.planes.items() if implausible(pl)))
            if left_out:
                planes = {k: v for k, v in model.data.planes.items() if k not in set(left_out)}
                model = dataclasses.replace(model, data=dataclasses.replace(model.data, planes=planes), findings=())
        found, data, said = finder(model, say, initial)
        corrections += list(found)
        notes += list(said)
        if data is not model.data:
            model = dataclasses.replace(model, data=data, findings=())
    return BookkeepingResult(tuple(corrections), model.data, tuple(notes), left_out)
