"""The progress bars of a run: its training steps (in place of nerfstudio's table of steps) and
the evidence read for its atoms after them."""

from __future__ import annotations

import sys


class ProgressBar:
    """A progress bar of training steps that ends at the step the run stopped at: the step limit,
    or the step where the atoms converged (then it reads that step as 100%); with another ``unit``
    (the evidence's atoms) a count of them, moved by :meth:`add`.  ``in_logs`` False: drawn in a
    terminal only (a stage of a few seconds, whose line after it says what it took)."""

    def __init__(self, total: int, unit: str = "step", what: str = "gaussian-atoms", in_logs: bool = True) -> None:
        from tqdm.auto import tqdm

        # In a terminal the bar redraws in place; into a log (no terminal) each drawing is a line
        # of its own, so there it is drawn every tenth of the run.
        live = sys.stderr.isatty()
        self.bar = tqdm(
            total=total,
            desc=what,
            unit=unit,
            dynamic_ncols=True,
            disable=not (live or in_logs),
            **({} if live else {"miniters": max(total // 10, 1), "mininterval": 0.0}),
        )

    def reset(self) -> None:
        """Start over at 0 (a second pass; a bar still at 0 is not drawn again)."""
        if self.bar.n:
            self.bar.reset()

    def add(self, done: int) -> None:
        """Count ``done`` more."""
        self.bar.update(done)

    def count(self, step: int) -> None:
        """Count through ``step`` (after each step)."""
        self.bar.update(step + 1 - self.bar.n)

    def end_at(self, step: int) -> None:
        """Count through ``step`` and end the bar there (the run converged at it)."""
        if not self.bar.disable:
            self.bar.update(step + 1 - self.bar.n)
        self.close()

    def close(self) -> None:
        """End the bar at the step reached (once; the results print after it)."""
        if self.bar.disable:
            return
        if self.bar.n < self.bar.total:  # stopped early: the run's own end is 100%
            self.bar.total = self.bar.n
            self.bar.refresh()
        self.bar.close()
