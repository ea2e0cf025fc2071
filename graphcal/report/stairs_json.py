"""``stairs.json`` (written by ``graphcal track``, docs/state_estimation.md): a
:class:`~graphcal.locomotion.stairs.StairsModel` as plain JSON-ready values. World frame (z up);
metres (keys ending ``_m``); planes as ``{n, d_m}`` with ``n . x + d = 0``; NaN written as null."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from graphcal.locomotion.stairs import StairsModel, TreadError

__all__ = ["stairs_to_json"]


def _finite_or_none(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def _plane(plane) -> dict:
    return {"n": [float(v) for v in plane[0]], "d_m": float(plane[1])}


def stairs_to_json(model: StairsModel, errors: Sequence[TreadError] | None = None) -> dict:
    """A JSON-ready dict of the model (metres, keys ending ``_m``); with ``errors`` (from
    :func:`graphcal.locomotion.stairs.tread_errors`) each tread also carries its errors and the dict
    the maxima."""
    treads = []
    by_index = {e.index: e for e in (errors or ())}
    for t in model.treads:
        d = {
            "index": t.index,
            "height_m": t.height_m,
            "depth_m": t.depth_m,
            "depth_complete": t.depth_complete,
            "width_m": t.width_m,
            "p_world_edge_m": [float(v) for v in t.p_world_edge],
            "edge_direction_world": [float(v) for v in t.edge_direction_world],
            "edge_from_riser": t.edge_from_riser,
            "plane_world": _plane(t.plane_world),
            "n_inliers": t.n_inliers,
        }
        if t.index in by_index:
            e = by_index[t.index]
            d["errors"] = {
                "true_index": e.true_index,
                "height_error_m": _finite_or_none(e.height_error_m),
                "depth_error_m": _finite_or_none(e.depth_error_m),
                "width_error_m": _finite_or_none(e.width_error_m),
                "edge_along_m": _finite_or_none(e.edge_along_m),
                "edge_height_m": _finite_or_none(e.edge_height_m),
            }
        treads.append(d)
    out = {
        "treads": treads,
        "risers": [
            {"s_m": r.s_m, "h_low_m": r.h_low_m, "h_high_m": r.h_high_m, "n_inliers": r.n_inliers,
             "plane_world": _plane(r.plane_world)}
            for r in model.risers
        ],
        "floor_plane_world": _plane(model.floor_plane_world),
        "T_world_stairs": [[float(v) for v in row] for row in model.T_world_stairs],
        "icp_fitness": list(model.icp_fitness),
        "icp_accepted": list(model.icp_accepted),
        "n_points": model.n_points,
    }
    if errors:
        def worst(attr):
            vals = [abs(getattr(e, attr)) for e in errors if np.isfinite(getattr(e, attr))]
            return max(vals) if vals else None

        out["max_abs_height_error_m"] = worst("height_error_m")
        out["max_abs_depth_error_m"] = worst("depth_error_m")
    return out
