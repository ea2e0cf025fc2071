"""``graphcal diagnose``: what the model gets wrong on measured data, the cause, and the gain.

Modules: catalogue.py (causes, candidates, findings), model.py (the calibration graph extended by
findings), scores.py (score tests of every candidate at once), heldout.py (cross-validated gain),
diagnose.py (the loop), command.py (the command and its files). Method: docs/diagnosis.md.
"""

from graphcal.diagnosis.diagnose import Diagnosis, diagnose

__all__ = ["Diagnosis", "diagnose"]
