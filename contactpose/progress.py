"""Long work made visible and bounded: tqdm bars on a terminal, and time budgets.

Bars appear only when stderr is a terminal and the work has run for PROGRESS_DELAY
seconds (``CONTACTPOSE_PROGRESS_DELAY`` overrides it), so scripts, CI logs and short
calls stay quiet. A :class:`Deadline` is a time budget that long stages check between
chunks of work; when it has passed they stop early and say so.
"""

from __future__ import annotations

import os
import sys
import time

#: Seconds of work before a bar appears.
PROGRESS_DELAY = 1.0


def progress_bar(total=None, desc="", unit="it", show=None):
    """A tqdm bar for ``total`` steps, shown on a terminal after PROGRESS_DELAY seconds.

    show : True / False force it on / off; None decides by the terminal.
    """
    visible = sys.stderr.isatty() if show is None else bool(show)
    if not visible:
        return _NO_BAR  # a tqdm object costs tens of microseconds even when disabled
    from tqdm.auto import tqdm

    delay = float(os.environ.get("CONTACTPOSE_PROGRESS_DELAY", PROGRESS_DELAY))
    return tqdm(total=total, desc=desc, unit=unit, disable=not visible, delay=delay, leave=False,
                file=sys.stderr, dynamic_ncols=True)


class _NoBar:
    """A bar that shows nothing: the same calls as tqdm's, doing nothing."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        pass

    def set_postfix(self, *args, **kwargs):
        pass

    def close(self):
        pass


_NO_BAR = _NoBar()


class Deadline:
    """A time budget of ``seconds`` from now (None or inf: unbounded).

    ``passed`` tells whether it ran out; ``hit`` stays True once a stage found it passed
    and stopped early, so the caller can report a truncated answer.
    """

    def __init__(self, seconds=None):
        self.seconds = None if seconds is None or seconds == float("inf") else float(seconds)
        self.end = None if self.seconds is None else time.perf_counter() + self.seconds
        self.hit = False

    @property
    def passed(self):
        """Whether the budget ran out (and remember that it did)."""
        if self.end is not None and time.perf_counter() >= self.end:
            self.hit = True
        return self.hit

    def remaining(self):
        """Seconds left (inf when unbounded, 0 when passed)."""
        return float("inf") if self.end is None else max(0.0, self.end - time.perf_counter())

