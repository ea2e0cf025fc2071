"""graphcal: factor-graph self-calibration and state estimation for legged robots.

Frames and units: see :mod:`graphcal.geometry` (``T_a_b`` maps b-coordinates to a, SE(3) tangent
order ``[omega, v]``, SI units inside the code).
"""

__version__ = "0.1.0"

