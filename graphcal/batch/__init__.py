"""Running many independent tasks (one per dataset, or one per Monte Carlo seed) on a
``concurrent.futures.Executor``: a local process pool by default, or a Dask distributed cluster
(:mod:`graphcal.batch.executor`); the task loop with results as they arrive, retries of tasks whose
worker died, and a progress bar (:mod:`graphcal.batch.run`); the statistics of a fleet of robots'
calibrations (:mod:`graphcal.batch.fleet`). The commands that use them: ``graphcal batch`` and
``graphcal study`` (graphcal/commands/batch.py, study.py); docs/batch.md."""
