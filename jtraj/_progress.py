"""How often progress bars redraw.

Where someone watches stderr (a terminal, a Jupyter kernel) a bar redraws live. Where
stderr goes to a file or a pipe (a batch job's log), it redraws once every
:data:`LOG_INTERVAL` seconds and at its end, so that an hour-long dataset build leaves
about sixty lines in its log instead of several per second.
"""

from __future__ import annotations

import sys

#: seconds between redraws where stderr is a file or a pipe
LOG_INTERVAL = 60.0


def live() -> bool:
    """Whether stderr is watched as it is written: a terminal, or a Jupyter kernel."""
    try:
        tty = bool(sys.stderr.isatty())
    except (AttributeError, ValueError):  # replaced or closed stderr
        tty = False
    return tty or "ipykernel" in sys.modules


def interval(live_seconds: float) -> float:
    """``live_seconds`` where stderr is watched live, else :data:`LOG_INTERVAL`."""
    return live_seconds if live() else LOG_INTERVAL
