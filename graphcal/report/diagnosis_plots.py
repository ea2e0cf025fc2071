"""Figures of a diagnosis: the residuals against the covariate that reveals each finding's cause,
before (nominal model) and after (extended model). matplotlib without pyplot, as report/plots.py.

=====================  =========================================================================
cause                  what is drawn
=====================  =========================================================================
sensor_range_scale     distance error e_d (mm) against the measured range d (m)
session_offset         e_d against the station number, coloured by session
ground_tilt            angle error theta (deg) against the station number, coloured by session
                       (the heading changes between sessions)
imu_misalignment       theta against the body tilt (deg)
joint_offset,          whitened stance-foot residual of the named leg against the station number,
link_length            the other legs in grey (foot_radius, joint_compliance: every leg)
structure remains      per group failing at physical noise: its whitened residual component
                       against the regressor it correlates with most (diagnosis/structure.py)
extrinsic_change       theta and e_d against the station number, the change marked
outlier_stations       whitened measurement residual against the station number, the stations marked
=====================  =========================================================================
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from graphcal.models.effects import cause_record
from graphcal.report.plots import AFTER_COLOR as _AFTER
from graphcal.report.plots import BEFORE_COLOR as _BEFORE
from graphcal.report.plots import MARK_COLOR as _MARK
from graphcal.report.plots import new_figure

__all__ = ["diagnosis_figures"]

#: axis labels: stations numbered as in stations.csv (as calibrate's plots); theta and e_d of the
#: plane predicted from the legs alone (residuals.py), not the fitted one
_STATION = "station (as in stations.csv)"
_THETA = "θ, legs' prediction [deg]"
_ED = "e_d, legs' prediction [mm]"


def _xy(records, x: str, y: str, sensor=None):
    r = [q for q in records if sensor is None or q.sensor == sensor]
    return np.array([getattr(q, x) for q in r], dtype=float), np.array([getattr(q, y) for q in r], dtype=float)


def _pair(fig, records_before, records_after, x, y, xlabel, ylabel, title, sensor=None, color_by=None):
    axes = fig.subplots(1, 2, sharey=True)
    for ax, recs, name, col in ((axes[0], records_before, "nominal model", _BEFORE),
                                (axes[1], records_after, "extended model", _AFTER)):
        xs, ys = _xy(recs, x, y, sensor)
        if color_by is not None:
            groups = [getattr(q, color_by) for q in recs if sensor is None or q.sensor == sensor]
            for k, g in enumerate(dict.fromkeys(groups)):
                m = np.array([gg == g for gg in groups])
                ax.plot(xs[m], ys[m], "o", ms=3.5, label=str(g), color=f"C{k}")
            ax.legend(fontsize=7, title=color_by, title_fontsize=7)
        else:
            ax.plot(xs, ys, "o", ms=3.5, color=col)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel(xlabel)
        ax.set_title(f"{name}", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(ylabel)
    fig.suptitle(title, fontsize=10)
    return axes


def _finding_figure(diag, f) -> tuple[str, Figure]:
    c = f.candidate
    fig = new_figure(9.0, 3.4)
    b, a = diag.residuals_before, diag.residuals_after
    label = c.label()
    if c.cause == "sensor_range_scale":
        _pair(fig, b, a, "range_m", "distance_mm", "measured plane distance d [m]", _ED, label, sensor=c.get("sensor"))
        cap = "distance error against the measured range: a range scale makes it grow with the range"
    elif c.cause == "session_offset":
        _pair(fig, b, a, "station", "distance_mm", _STATION, _ED, label, color_by="session")
        cap = "distance error per station, by session: one session's body height differs"
    elif c.cause == "ground_tilt":
        _pair(fig, b, a, "station", "angle_deg", _STATION, _THETA, label, color_by="session")
        cap = "angle error per station, by session: a tilted floor shows as the robot turns between sessions"
    elif c.cause == "imu_misalignment":
        _pair(fig, b, a, "tilt_deg", "angle_deg", "body tilt [deg]", _THETA, label)
        cap = "angle error against the body tilt"
    elif cause_record(c.cause).kinematic:
        axes = fig.subplots(1, 2, sharey=True)
        for ax, recs, name in ((axes[0], diag.stance_before, "nominal model"), (axes[1], diag.stance_after, "extended model")):
            for leg in dict.fromkeys(r.leg for r in recs):
                xs = [r.station for r in recs if r.leg == leg]
                ys = [r.whitened for r in recs if r.leg == leg]
                named = leg == c.get("leg")
                ax.plot(xs, ys, "o-" if named else ".", ms=3.5 if named else 2.5, lw=0.8,
                        color=_MARK if named else _BEFORE, label=leg if named else None, zorder=3 if named else 1)
            ax.set_xlabel(_STATION)
            ax.set_title(name, fontsize=9)
            ax.grid(alpha=0.3)
            if c.get("leg") is not None:  # a shared cause (foot radius, compliance) names no leg
                ax.legend(fontsize=7)
        axes[0].set_ylabel("stance-foot residual (whitened RMS)")
        fig.suptitle(label, fontsize=10)
        cap = "stance-foot residuals per station: the named leg against the others"
    elif c.cause == "extrinsic_change":
        # cameras: the plane's angle error; laser scans (no plane angle): the RMS range residual
        has_angle = any(np.isfinite(r.angle_deg) for r in b if r.sensor == c.get("sensor"))
        y, ylabel = ("angle_deg", _THETA) if has_angle else ("distance_mm", "range residual RMS [mm]")
        axes = _pair(fig, b, a, "station", y, _STATION, ylabel, label, sensor=c.get("sensor"))
        k = int(c.get("station"))
        if any(r.station == k for r in b):
            for ax in axes:
                ax.axvline(k - 0.5, color=_MARK, ls="--", lw=1.0)
        cap = "residual per station: the sensor moved at the dashed line"
    else:  # outlier stations
        axes = _pair(fig, b, a, "station", "whitened", _STATION, "measurement residual (whitened RMS)", label)
        bad = {int(s) for s in c.get("stations")}
        for ax, recs in zip(axes, (b, a)):
            xs = [r.station for r in recs if r.station in bad]
            ys = [r.whitened for r in recs if r.station in bad]
            ax.plot(xs, ys, "o", mfc="none", mec=_MARK, ms=9)
        cap = "measurement residual per station: the outlier stations circled"
    return f"{label}: {cap} (left: nominal model, right: with the findings)", fig


def structure_figures(diag) -> list[tuple[str, Figure]]:
    """(caption, figure) per measurement group of the final model that fails at physical noise: its
    whitened residual component against the regressor it correlates with most."""
    out = []
    for g in diag.groups:
        if not g.structure or not g.points:
            continue
        fig = new_figure(6.0, 3.4)
        ax = fig.subplots(1, 1)
        x, y = np.array(g.points).T
        ax.plot(x, y, ".", color=_MARK, ms=4)
        if np.std(x) > 0:
            k, c0 = np.polyfit(x, y, 1)
            xs = np.array([x.min(), x.max()])
            ax.plot(xs, k * xs + c0, "-", color=_BEFORE, lw=1.0)
        ax.set_xlabel(g.regressor)
        ax.set_ylabel(f"{g.group} residual, component {g.component} (whitened)")
        ax.grid(alpha=0.3)
        fig.suptitle(f"structure remains in {g.group}", fontsize=10)
        out.append((f"{g.group}: chi2/dof {g.ratio:.2f} at physical noise; its residuals against {g.regressor} "
                    f"(r = {g.correlation:+.2f}, p = {g.regressor_p:.2g})", fig))
    return out


def diagnosis_figures(diag) -> list[tuple[str, Figure]]:
    """(caption, figure) per finding and per group where structure remains; with neither, the
    residuals per station."""
    out = [_finding_figure(diag, f) for f in diag.findings] + structure_figures(diag)
    if not out:
        fig = new_figure(9.0, 3.4)
        _pair(fig, diag.residuals_before, diag.residuals_after, "station", "whitened", _STATION,
              "measurement residual (whitened RMS)", "no finding")
        out.append(("measurement residual per station (left: nominal model, right: final model)", fig))
    return out
