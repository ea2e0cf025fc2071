"""Leg kinematic identification from motion capture (Yuan et al.'s virtual fixed base, generalised).

Modules (docs/legs.md):

* the leg model (joint offsets, link lengths, 3-D joint origins; the vectorised kinematics of a
  marker on the foot with analytic Jacobians) is :mod:`graphcal.models.legs`, shared with calibration;
* :mod:`.virtual_base`    -- Yuan's virtual base from the four body markers (mean origin, orthonormal axes);
* :mod:`.mocap_data`      -- ``mocap.csv`` + joint values of a dataset as marker tracks;
* :mod:`.identifiability` -- which parameters the data determine (column-scaled SVD, pivoted QR);
* :mod:`.identify`        -- the graph, the identifiable set, LM to convergence, covariance;
* :mod:`.report`          -- legs.yaml, calibrated URDF, report.html (the page: :mod:`graphcal.report.legs_page`);
  the command ``graphcal identify-legs`` is :mod:`graphcal.commands.identify_legs`.

Nothing is imported here, so ``import graphcal.legs.identify`` imports only what it needs.
"""
