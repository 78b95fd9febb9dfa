"""How a launcher's process ends: a failure in one line, or a finished run without teardown.

Both launchers (``gaussian-atoms train`` on the engine, and nerfstudio's trainer) end this way;
neither imports nerfstudio here, so the engine's launcher stays free of it.
"""

from __future__ import annotations

import atexit
import os
import sys

from gaussian_atoms_method.launch.start_ahead import end_now


def fail(message: str, status: int) -> None:
    """Print ``message`` as one line on stderr and exit with ``status`` (no traceback; at once
    where a start begun ahead is still running, :func:`~gaussian_atoms_method.launch.start_ahead.end_now`)."""
    print(" ".join(str(message).split()), file=sys.stderr)
    end_now(status)
    raise SystemExit(status)


def exit_process(status: int = 0) -> None:
    """End the process with ``status`` once its outputs are complete: the exit handlers run
    (logging, wandb, comet, the viewer), the console flushed; then ``os._exit``, which skips the
    interpreter's and CUDA's teardown of the loaded libraries and the device's memory (about a
    second of every run on an H100).  Only the
    command line calls this, after a run that ended normally."""
    atexit._run_exitfuncs()  # what the interpreter's exit runs first
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):  # a closed pipe or stream, or none
            pass
    os._exit(status)
