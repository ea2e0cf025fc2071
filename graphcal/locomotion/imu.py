"""IMU preintegration between filter updates (vectorised over the whole timeseries).

The filter updates at "events" (stance updates, support switches, keyframes); between two events
the IMU samples are preintegrated (Lupton & Sukkarieh 2012; Forster et al. 2017) with zero bias,
all chunks at once (one numpy pass per position inside a chunk), together with the first-order
Jacobians of the preintegrated quantities with respect to the biases. The filter then applies a
chunk with its current bias estimate in a handful of 3x3 operations, and the per-sample
trajectory inside each chunk is reconstructed afterwards, again vectorised.

For interval i of a chunk (rate w_i and specific force a_i in the body frame, held over dt_i;
tau_i the time from the chunk start to the end of interval i):

    dR_i = dR_{i-1} Exp(w_i dt_i)
    dv_i = dv_{i-1} + dR_{i-1} a_i dt_i
    dp_i = dp_{i-1} + dv_{i-1} dt_i + dR_{i-1} a_i dt_i^2 / 2

With a bias b (body frame): dR_i(b) ~ dR_i Exp(-b_g tau_i) (chunks are a few ms: the rotation
inside one is small), dv_i(b) ~ dv_i + Jvg_i b_g + Jva_i b_a, dp_i(b) ~ dp_i + Jpg_i b_g + Jpa_i b_a.
The state at the end of interval i from the chunk-start state (p, v, R):

    R_i = R dR_i(b),  v_i = v + g tau_i + R dv_i(b),  p_i = p + v tau_i + g tau_i^2 / 2 + R dp_i(b).

Units: s, rad/s, m/s^2, m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.geometry import skew_batch, so3_exp_batch

__all__ = ["Preintegration", "preintegrate", "reconstruct"]


@dataclass(frozen=True, eq=False)
class Preintegration:
    """Zero-bias preintegrated IMU, per sample (the value at the end of that sample's interval,
    counted from its chunk's start). Sample 0 and chunk starts are identity/zero.

    Attributes:
        start: (N,) index of the chunk-start sample (the event before) of each sample.
        tau: (N,) time since the chunk start, s.
        dR: (N, 3, 3). dv, dp: (N, 3).
        Jvg, Jva, Jpg, Jpa: (N, 3, 3) Jacobians of dv and dp w.r.t. the gyro and accel biases
            (body frame).
    """

    start: np.ndarray
    tau: np.ndarray
    dR: np.ndarray
    dv: np.ndarray
    dp: np.ndarray
    Jvg: np.ndarray
    Jva: np.ndarray
    Jpg: np.ndarray
    Jpa: np.ndarray


def preintegrate(w_body: np.ndarray, a_body: np.ndarray, dts: np.ndarray, events: np.ndarray) -> Preintegration:
    """Preintegrate every chunk between consecutive ``events``.

    Args:
        w_body: (N, 3) rate of interval (k-1, k] held over it, body frame, rad/s (row 0 unused).
        a_body: (N, 3) specific force of that interval, body frame, m/s^2 (row 0 unused).
        dts: (N,) interval lengths t_k - t_{k-1}, s (row 0 unused).
        events: increasing sample indices > 0 that end a chunk (the last one should be N - 1).
    """
    N = len(dts)
    ev = np.asarray(events, dtype=np.int64)
    start = np.zeros(N, dtype=np.int64)
    bounds = np.r_[0, ev]
    chunk_of = np.searchsorted(ev, np.arange(N), side="left")  # sample k in (bounds[c], bounds[c+1]]
    chunk_of = np.minimum(chunk_of, len(ev) - 1)
    start = bounds[chunk_of]
    start[0] = 0
    pos = np.arange(N) - start  # 1.. within the chunk; 0 for sample 0
    dR = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    dv = np.zeros((N, 3))
    dp = np.zeros((N, 3))
    Jvg = np.zeros((N, 3, 3))
    Jva = np.zeros((N, 3, 3))
    Jpg = np.zeros((N, 3, 3))
    Jpa = np.zeros((N, 3, 3))
    tau = np.zeros(N)
    inc = so3_exp_batch(w_body * dts[:, None])
    ax = skew_batch(a_body)
    for j in range(1, int(pos.max()) + 1 if N else 1):
        k = np.flatnonzero(pos == j)
        if len(k) == 0:
            continue
        d = dts[k][:, None]
        d3 = d[:, :, None]
        if j == 1:  # the chunk's first interval starts from identity / zeros
            Rp = np.broadcast_to(np.eye(3), (len(k), 3, 3))
            dv_p = dp_p = np.zeros((len(k), 3))
            Jva_p = Jpa_p = Jvg_p = Jpg_p = np.zeros((len(k), 3, 3))
            tp = np.zeros(len(k))
        else:
            km = k - 1
            Rp, dv_p, dp_p, tp = dR[km], dv[km], dp[km], tau[km]
            Jva_p, Jpa_p, Jvg_p, Jpg_p = Jva[km], Jpa[km], Jvg[km], Jpg[km]
        Ra = np.einsum("nij,nj->ni", Rp, a_body[k])
        dv[k] = dv_p + Ra * d
        dp[k] = dp_p + dv_p * d + 0.5 * Ra * d * d
        Jva[k] = Jva_p - Rp * d3
        Jpa[k] = Jpa_p + Jva_p * d3 - 0.5 * Rp * d3 * d3
        RpAx = Rp @ ax[k] * (tp[:, None, None] * d3)
        Jvg[k] = Jvg_p + RpAx
        Jpg[k] = Jpg_p + Jvg_p * d3 + 0.5 * RpAx * d3
        dR[k] = Rp @ inc[k]
        tau[k] = tp + dts[k]
    return Preintegration(start, tau, dR, dv, dp, Jvg, Jva, Jpg, Jpa)


def reconstruct(pre: Preintegration, p0: np.ndarray, v0: np.ndarray, R0: np.ndarray, bg: np.ndarray,
                ba: np.ndarray, gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-sample nominal states from the chunk-start states.

    Args:
        pre: the preintegration.
        p0, v0: (N, 3), R0: (N, 3, 3), bg, ba: (N, 3) body-frame biases: the filter state at the
            chunk START of each sample (rows indexed like the samples: row k holds the state at
            sample ``pre.start[k]``).
        gravity: (3,) world gravity, m/s^2.

    Returns:
        p (N, 3), v (N, 3), R (N, 3, 3) at the end of each sample's interval (before any update
        at that sample).
    """
    tau = pre.tau[:, None]
    dRc = pre.dR @ so3_exp_batch(-bg * tau)
    dv = pre.dv + np.einsum("nij,nj->ni", pre.Jvg, bg) + np.einsum("nij,nj->ni", pre.Jva, ba)
    dp = pre.dp + np.einsum("nij,nj->ni", pre.Jpg, bg) + np.einsum("nij,nj->ni", pre.Jpa, ba)
    R = R0 @ dRc
    v = v0 + gravity * tau + np.einsum("nij,nj->ni", R0, dv)
    p = p0 + v0 * tau + 0.5 * gravity * tau * tau + np.einsum("nij,nj->ni", R0, dp)
    return p, v, R
