"""Custom GTSAM factors of graphcal, one small module each (error, analytic Jacobians, and a test
against numerical derivatives). Populated by the calibration-graph work; the package exists so that
`pip install` provides it from the start."""
