"""graphcal: factor-graph self-calibration and state estimation for legged robots.

Frames and units: see :mod:`graphcal.geometry` (``T_a_b`` maps b-coordinates to a, SE(3) tangent
order ``[omega, v]``, SI units inside the code).
"""

__version__ = "0.1.0"


def _no_tqdm_monitor_thread() -> None:
    """tqdm starts a monitor thread with its first progress bar, and it lives as long as the process;
    with another thread alive graphcal does not fork its plane-fitting workers
    (graphcal.clouds.plane_table) and fits on threads instead. graphcal's bars need no monitor."""
    import tqdm

    tqdm.tqdm.monitor_interval = 0


_no_tqdm_monitor_thread()
