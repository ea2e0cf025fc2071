"""graphcal's progress bar: tqdm without its monitor thread.

tqdm starts a monitor thread with its first bar, and it lives as long as the process; with another
thread alive graphcal does not fork its plane-fitting workers (:mod:`graphcal.clouds.plane_table`)
and fits on threads instead. The class attribute is set on graphcal's own subclass, so importing
graphcal changes nothing in tqdm for the rest of a program."""

from __future__ import annotations

from tqdm import tqdm

__all__ = ["ProgressBar"]


class ProgressBar(tqdm):
    """:class:`tqdm.tqdm` with ``monitor_interval = 0`` (no monitor thread); same arguments."""

    monitor_interval = 0
