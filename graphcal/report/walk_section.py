"""The report's "Walk" section for a calibration from a walk: what the walk gave (frames, stations,
each camera's time offset) and two figures: the floor's fit over log time, and each time
offset's chi-square profile (docs/calibration.md, "Calibrating from a walk")."""

from __future__ import annotations

import numpy as np
from markupsafe import Markup, escape

__all__ = ["walk_section"]


def _offset_text(s) -> str:
    if s.time_offset_source == "estimated":
        return f"{1e3 * s.time_offset_s:+.2f} ± {1e3 * s.time_offset_sigma_s:.2f} ms (estimated)"
    return f"{1e3 * s.time_offset_s:+.2f} ms ({s.time_offset_source})"


def _residuals_over_time(result, walk):
    """Figure: each camera's floor angle error before and after against log time (s)."""
    from graphcal.report.plots import new_figure

    times = walk["station_times_s"]
    fig = new_figure(8.0, 3.2)
    ax = fig.add_subplot(1, 1, 1)
    for name in result.sensors:
        rows = [r for r in result.residuals if r.sensor == name and int(r.station) in times]
        t = np.array([times[int(r.station)] for r in rows])
        ax.semilogy(t, [max(r.angle_before_deg, 1e-6) for r in rows], ".", color="0.6", ms=3,
                    label=f"{name}: before (CAD prior, offset 0)")
        ax.semilogy(t, [max(r.angle_after_deg, 1e-6) for r in rows], ".", ms=3, label=f"{name}: after")
    ax.set_xlabel("log time [s]")
    ax.set_ylabel("floor angle error θ [deg]")
    ax.set_title("The floor the camera sees against the one the legs predict, over the walk")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def _profiles(walk):
    """Figure: chi-square against each estimated camera's time offset (ms)."""
    from graphcal.report.plots import new_figure

    fig = new_figure(8.0, 3.0)
    ax = fig.add_subplot(1, 1, 1)
    for name, prof in walk.get("profiles", {}).items():
        for stage, style in (("coarse", "o--"), ("fine", "o-")):
            d = np.array([p[0] for p in prof if p[2] == stage])
            c = np.array([p[1] for p in prof if p[2] == stage])
            if len(c):
                ax.semilogy(1e3 * d, c - c.min() + 1.0, style, ms=3, label=f"{name}, {stage}")
    ax.set_xlabel("time offset tried [ms] (stamp minus capture)")
    ax.set_ylabel("χ² − min + 1")
    ax.set_title("Time offset profiles (coarse: every third frame, the noise given; fine: every frame, "
                 "the noise learned)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def walk_section(result) -> list:
    """The section's parts (HTML and figures), or [] for a calibration from stations."""
    from graphcal.report.page import figure

    walk = getattr(result, "walk", None)
    if not walk:
        return []
    frames = "; ".join(f"<code>{escape(s)}</code>: {n} of {walk['frames_in_log'][s]} frames used"
                       for s, n in walk["frames"].items())
    offsets = "".join(f"<li><code>{escape(n)}</code>: time offset {escape(_offset_text(s))}</li>"
                      for n, s in result.sensors.items() if getattr(s, "time_offset_s", None) is not None)
    parts = [Markup(f"<p>Calibrated from a walk of {walk['duration_s']:.1f} s: {frames} (taken with at least three "
                    f"feet standing); {int(walk['stations'])} stations, the frames and one per change of stance. "
                    "The stations' numbers below run in time order.</p>"),
             Markup(f"<ul>{offsets}</ul>"),
             figure(_residuals_over_time(result, walk), "floor angle error against log time, before and after"),
             ]
    if walk.get("profiles"):
        parts.append(figure(_profiles(walk), "chi-square profile of each camera's time offset, each stage against "
                                             "its own minimum"))
    return parts
