"""Figures of a calibration (matplotlib, no pyplot: thread-safe, no display needed).

Every ``plot_*`` function draws into the ``Axes`` it is given (evo style), so callers compose their
own figures; :func:`report_figures` builds the set the HTML report shows, :func:`figure_png`
renders one with the Agg canvas.

* :func:`plot_angle_errors` -- Chai 2015 Fig. 17: per-station angle theta between the measured and
  the predicted ground, before and after calibration, mean and max marked.
* :func:`plot_distance_errors` -- Chai 2015 Fig. 18: distance error ``e_d = |d_T - d_M|`` (mm).
* :func:`plot_residual_histogram` -- histograms of theta or e_d, before and after.
* :func:`plot_covariance_ellipse` / :func:`plot_sensor_covariance` -- 1-sigma and 3-sigma ellipses
  of pairs of body axes (x-y, x-z, y-z in mm; the small rotations about body x, y, z in deg: not
  the roll/pitch/yaw Euler angles of the pose table).
* :func:`plot_incremental_sigma` -- the incremental solver's 1-sigma per station.
"""

from __future__ import annotations

import io
from typing import Iterable, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse
from matplotlib.ticker import FuncFormatter, NullFormatter

from graphcal.report.calibration_yaml import body_axis_covariance

__all__ = [
    "ELLIPSE_PAIRS",
    "plot_angle_errors",
    "plot_distance_errors",
    "plot_residual_histogram",
    "plot_covariance_ellipse",
    "plot_sensor_covariance",
    "plot_incremental_sigma",
    "report_figures",
    "figure_png",
    "new_figure",
    "BEFORE_COLOR",
    "AFTER_COLOR",
    "MARK_COLOR",
]

#: (row, column) index pairs into the body-axis vector [rx, ry, rz, x, y, z], and axis labels.
ELLIPSE_PAIRS: tuple[tuple[int, int], ...] = ((3, 4), (3, 5), (4, 5), (0, 1), (0, 2), (1, 2))
#: small rotations about the body axes (not the roll/pitch/yaw angles of the pose table: those are
#: Euler angles of the sensor's orientation)
_AXIS_LABELS = ("rotation about body x [deg]", "rotation about body y [deg]", "rotation about body z [deg]",
                "along body x [mm]", "along body y [mm]", "along body z [mm]")
#: the one plot style of every report: before (nominal / prior) in grey, after (estimated) in blue,
#: marked samples (outliers, a change, a finding's stations) in red
BEFORE_COLOR = "#999999"
AFTER_COLOR = "#1f77b4"
MARK_COLOR = "#d62728"
_BEFORE = BEFORE_COLOR
_AFTER = AFTER_COLOR
_OUTLIER = MARK_COLOR
_BOX = {"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "none", "alpha": 0.8}


def _rows(residuals, sensor: str | None):
    return [r for r in residuals if sensor is None or r.sensor == sensor]


def _split(rows, outliers: Iterable[int]):
    outl = {int(s) for s in outliers}
    bad = np.array([bool(r.outlier or int(r.station) in outl) for r in rows], dtype=bool)
    return bad


def _mark_stats(ax, values: np.ndarray, color: str, label: str, unit: str, span: float | None = None,
                log: bool = False) -> None:
    """Mean (dashed) and max (dotted) lines with their labels, written right of the axes (never over
    the points); one label for both when they are closer than 6 % of ``span`` (the y range; with
    ``log``, the ratio of its ends), so the two never overlap."""
    if values.size == 0:
        return
    mean, vmax = float(values.mean()), float(values.max())
    ax.axhline(mean, color=color, linestyle="--", linewidth=1.0)
    ax.axhline(vmax, color=color, linestyle=":", linewidth=1.0)
    if log:
        close = span is not None and mean > 0 and np.log10(vmax / mean) < 0.06 * np.log10(span)
    else:
        close = span is not None and vmax - mean < 0.06 * span
    style = dict(xycoords=("axes fraction", "data"), xytext=(4, 0), textcoords="offset points", ha="left",
                 va="center", fontsize=7, color=color)
    if close:
        ax.annotate(f"{label} mean {mean:.3g}{unit},\nmax {vmax:.3g}{unit}", xy=(1.0, vmax), **style)
        return
    ax.annotate(f"{label} mean {mean:.3g}{unit}", xy=(1.0, mean), **style)
    ax.annotate(f"{label} max {vmax:.3g}{unit}", xy=(1.0, vmax), **style)


#: "after" values below this share of the "before" ones are drawn on a log axis (on a linear one
#: they lay flat on zero: 0.002 deg after against 0.6 deg before on the Octopus demo)
LOG_AXIS_RATIO = 0.1


def _per_station(ax, residuals, sensor, outliers, before_attr, after_attr, unit, ylabel, title):
    rows = sorted(_rows(residuals, sensor), key=lambda r: int(r.station))
    if not rows:
        ax.text(0.5, 0.5, "no residuals", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(title)
        return
    st = np.array([int(r.station) for r in rows])
    before = np.abs([float(getattr(r, before_attr)) for r in rows])
    after = np.abs([float(getattr(r, after_attr)) for r in rows])
    bad = _split(rows, outliers)
    ax.plot(st, before, "o-", color=_BEFORE, markersize=3, linewidth=0.8, label="before (CAD prior)")
    ax.plot(st, after, "o-", color=_AFTER, markersize=3, linewidth=0.8, label="after calibration")
    if bad.any():
        ax.plot(st[bad], after[bad], "x", color=_OUTLIER, markersize=7, label="outlier (not in mean/max)")
    finite = np.concatenate([before, after])
    finite = finite[np.isfinite(finite)]
    top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    positive = finite[finite > 0]
    after_top = np.nanmax(after) if np.isfinite(after).any() else np.nan
    log = bool(positive.size and np.isfinite(after_top) and after_top < LOG_AXIS_RATIO * top)
    if log:
        bottom = float(positive.min()) / 1.5
        ax.set_yscale("log")
        ax.set_ylim(bottom, 1.5 * top)
        span = 1.5 * top / bottom
        ylabel += " (log scale)"
    else:
        ax.set_ylim(0.0, 1.15 * top)
        span = 1.15 * top
    _mark_stats(ax, before[~bad], _BEFORE, "before", unit, span=span, log=log)
    _mark_stats(ax, after[~bad], _AFTER, "after", unit, span=span, log=log)
    ax.set_xlabel("station")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    # below the axes: a legend inside hid the first stations' points
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)


def plot_angle_errors(ax, residuals, *, sensor: str | None = None, outliers: Iterable[int] = (), title: str | None = None) -> None:
    """Per-station angle error theta (deg) before and after, mean (dashed) and max (dotted) marked
    over the non-outlier stations; outliers crossed (Chai 2015 Fig. 17)."""
    _per_station(
        ax, residuals, sensor, outliers, "angle_before_deg", "angle_after_deg", "°",
        "angle error θ [deg]", title or f"Angle error θ per station{f' ({sensor})' if sensor else ''}",
    )  # fmt: skip


def plot_distance_errors(ax, residuals, *, sensor: str | None = None, outliers: Iterable[int] = (), title: str | None = None) -> None:
    """Per-station distance error ``e_d = |d_T - d_M|`` (mm) before and after, mean and max marked
    (Chai 2015 Fig. 18)."""
    _per_station(
        ax, residuals, sensor, outliers, "distance_before_mm", "distance_after_mm", " mm",
        "distance error e_d [mm]", title or f"Distance error e_d per station{f' ({sensor})' if sensor else ''}",
    )  # fmt: skip


def plot_residual_histogram(
    ax, residuals, *, kind: str = "angle", sensor: str | None = None, outliers: Iterable[int] = (), bins: int = 20
) -> None:
    """Histogram of theta (``kind="angle"``, deg) or e_d (``kind="distance"``, mm), before and after,
    non-outlier stations."""
    if kind not in ("angle", "distance"):
        raise ValueError(f"kind must be 'angle' or 'distance', got {kind!r}")
    rows = _rows(residuals, sensor)
    bad = _split(rows, outliers) if rows else np.zeros(0, dtype=bool)
    b_attr, a_attr, xlabel = (
        ("angle_before_deg", "angle_after_deg", "θ [deg]") if kind == "angle" else ("distance_before_mm", "distance_after_mm", "e_d [mm]")
    )
    before = np.abs([float(getattr(r, b_attr)) for r in rows])[~bad] if rows else np.zeros(0)
    after = np.abs([float(getattr(r, a_attr)) for r in rows])[~bad] if rows else np.zeros(0)
    both = np.concatenate([before, after])
    both = both[np.isfinite(both)]
    if both.size == 0:
        ax.text(0.5, 0.5, "no residuals", ha="center", va="center", transform=ax.transAxes)
    else:
        hi = float(both.max()) if both.max() > 0 else 1.0
        positive = both[both > 0]
        a_fin = after[np.isfinite(after)]
        # "after" far below "before": log-spaced bins on a log axis (on a linear one every "after"
        # station fell into the first bin, at zero)
        log = bool(positive.size and a_fin.size and a_fin.max() < LOG_AXIS_RATIO * hi)
        if log:
            edges = np.geomspace(float(positive.min()) / 1.0001, hi * 1.0001, bins + 1)
            ax.set_xscale("log")
            xlabel += " (log scale)"
        else:
            edges = np.linspace(0.0, hi * 1.0001, bins + 1)
        ax.hist(np.clip(before[np.isfinite(before)], edges[0], None), bins=edges, color=_BEFORE, alpha=0.6,
                label="before")
        ax.hist(np.clip(a_fin, edges[0], None), bins=edges, color=_AFTER, alpha=0.6, label="after")
        ax.legend(fontsize=7)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("stations")
    ax.set_title(f"{'Angle' if kind == 'angle' else 'Distance'} residuals{f' ({sensor})' if sensor else ''}")
    ax.grid(True, alpha=0.3)


def plot_covariance_ellipse(ax, cov2, *, center=(0.0, 0.0), n_sigmas: Sequence[float] = (1.0, 3.0), color: str = _AFTER) -> bool:
    """Draw the ``n``-sigma ellipses of a 2x2 covariance around ``center``; returns False (and
    draws nothing) when the covariance is not finite positive semi-definite."""
    C = np.asarray(cov2, dtype=float)
    if C.shape != (2, 2) or not np.all(np.isfinite(C)):
        return False
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    if w[0] < -1e-12 * max(1.0, abs(w[1])):
        return False
    w = np.clip(w, 0.0, None)
    angle = float(np.degrees(np.arctan2(V[1, 1], V[0, 1])))
    styles = ("-", "--", ":", "-.")
    for i, k in enumerate(n_sigmas):
        ax.add_patch(
            Ellipse(
                center, 2 * k * np.sqrt(w[1]), 2 * k * np.sqrt(w[0]), angle=angle, fill=False,
                edgecolor=color, linestyle=styles[i % len(styles)], linewidth=1.2, label=f"{k:g}-σ",
            )
        )  # fmt: skip
    return True


def plot_sensor_covariance(axes, estimate, *, pairs: Sequence[tuple[int, int]] = ELLIPSE_PAIRS) -> None:
    """1-sigma and 3-sigma ellipses of ``estimate`` (a SensorEstimate) for each pair of body axes,
    one pair per Axes in ``axes`` (deviation from the estimate, mm and deg)."""
    C = body_axis_covariance(estimate.T_body_sensor, estimate.covariance)
    scale = np.array([np.rad2deg(1.0)] * 3 + [1000.0] * 3)
    C = C * np.outer(scale, scale)
    for ax, (i, j) in zip(np.ravel(axes), pairs):
        sub = C[np.ix_([i, j], [i, j])]
        ok = plot_covariance_ellipse(ax, sub)
        if ok:
            r = 3.6 * float(np.sqrt(max(sub[0, 0], sub[1, 1], 1e-30)))
            ax.set_xlim(-r, r)
            ax.set_ylim(-r, r)
            ax.set_aspect("equal", adjustable="box")
            ax.plot([0.0], [0.0], "+", color="black", markersize=6)
            ax.legend(fontsize=6, loc="upper right")
        else:
            ax.text(0.5, 0.5, "not determined\n(infinite or invalid σ)", ha="center", va="center",
                    transform=ax.transAxes, fontsize=8, color=_OUTLIER)  # fmt: skip
        ax.set_xlabel(_AXIS_LABELS[i], fontsize=8)
        ax.set_ylabel(_AXIS_LABELS[j], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)


def plot_incremental_sigma(ax_rot, ax_xyz, history, *, sensor: str | None = None) -> None:
    """1-sigma about/along the body axes after each station of the incremental solver (deg on
    ``ax_rot``, mm on ``ax_xyz``); detected changes marked with vertical lines."""
    steps = sorted((h for h in history if sensor is None or h.sensor == sensor), key=lambda h: int(h.station))
    st = np.array([int(h.station) for h in steps])
    for ax, attr, labels, unit in (
        (ax_rot, "sigma_rot_deg", ("about x", "about y", "about z"), "deg"),
        (ax_xyz, "sigma_xyz_mm", ("along x", "along y", "along z"), "mm"),
    ):
        if steps:
            vals = np.array([np.asarray(getattr(h, attr), dtype=float) for h in steps])
            for k in range(3):
                ax.plot(st, vals[:, k], "-", marker=".", markersize=3, label=f"σ {labels[k]}")
            for h in steps:
                if h.change_detected:
                    ax.axvline(int(h.station), color=_OUTLIER, linestyle="--", linewidth=1.0)
            if np.isfinite(vals).any() and np.all(vals[np.isfinite(vals)] > 0):
                ax.set_yscale("log")
                ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
                ax.yaxis.set_minor_formatter(NullFormatter())
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, "no incremental steps", ha="center", va="center", transform=ax.transAxes)
        ax.set_ylabel(f"1-σ [{unit}]")
        ax.grid(True, alpha=0.3)
    ax_xyz.set_xlabel("station")
    ax_rot.set_title(f"Incremental σ per station{f' ({sensor})' if sensor else ''}")


# ----------------------------------------------------------------------------- figure sets
def new_figure(w: float, h: float) -> Figure:
    """A figure of every report: ``w`` x ``h`` inches at 100 dpi, constrained layout (labels never
    overlap), drawn with the Agg canvas (no display, no pyplot)."""
    fig = Figure(figsize=(w, h), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


_fig = new_figure


def report_figures(result) -> list[tuple[str, Figure]]:
    """The figures of the HTML report, as (caption, Figure): per sensor with residuals the angle
    and distance errors per station and the histograms; per sensor the covariance ellipses; per
    sensor of the incremental history its sigma per station."""
    out: list[tuple[str, Figure]] = []
    sensors = list(result.sensors)
    with_res = [s for s in sensors if any(r.sensor == s for r in result.residuals)]
    with_res += sorted({r.sensor for r in result.residuals} - set(sensors))
    for s in with_res:
        fig = _fig(8.0, 3.4)
        plot_angle_errors(fig.add_subplot(1, 1, 1), result.residuals, sensor=s, outliers=result.outliers)
        out.append((f"{s}: angle error θ per station, before and after (cf. Chai 2015 Fig. 17)", fig))
        fig = _fig(8.0, 3.4)
        plot_distance_errors(fig.add_subplot(1, 1, 1), result.residuals, sensor=s, outliers=result.outliers)
        out.append((f"{s}: distance error e_d per station, before and after (cf. Chai 2015 Fig. 18)", fig))
        fig = _fig(8.0, 3.0)
        a1, a2 = fig.subplots(1, 2)
        plot_residual_histogram(a1, result.residuals, kind="angle", sensor=s, outliers=result.outliers)
        plot_residual_histogram(a2, result.residuals, kind="distance", sensor=s, outliers=result.outliers)
        out.append((f"{s}: residual histograms (non-outlier stations)", fig))
    for s in sensors:
        fig = _fig(8.0, 5.4)
        axes = fig.subplots(2, 3)
        plot_sensor_covariance(axes, result.sensors[s])
        out.append((f"{s}: 1-σ and 3-σ uncertainty ellipses about the estimate: translation along and small "
                    "rotation about the body axes (mm, deg; not the roll/pitch/yaw angles of the pose table)", fig))
    for s in sensors:
        if any(h.sensor == s for h in result.history):
            fig = _fig(8.0, 5.0)
            a1, a2 = fig.subplots(2, 1, sharex=True)
            plot_incremental_sigma(a1, a2, result.history, sensor=s)
            out.append((f"{s}: incremental solver, 1-σ after each station (dashed: change detected)", fig))
    return out


def figure_png(fig: Figure) -> bytes:
    """PNG bytes of ``fig``: drawn once on the Agg canvas and encoded by Pillow (the pixels of
    ``savefig``'s PNG, which draws a constrained-layout figure twice: 26 % slower on calibrate's figures)."""
    from PIL import Image

    if fig.canvas is None or not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    buf = io.BytesIO()
    Image.fromarray(np.asarray(fig.canvas.buffer_rgba())).save(buf, format="png")
    return buf.getvalue()
