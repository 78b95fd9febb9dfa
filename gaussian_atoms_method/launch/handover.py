"""The interpreter's lock handed between threads more often while a thread launches GPU work
beside Python code.

A torch operation releases the interpreter's lock while it runs; the thread that launched it
then waits for the lock to come back, and a thread running Python code (a launcher importing
modules) keeps it for up to the switch interval, 5 ms by default.  A thread launching a few
hundred small operations beside the imports would wait about as long as the imports take.
:func:`quick_handover` lowers the interval while any such thread runs (threads may nest it) and
puts the interpreter's own back after the last.
"""

from __future__ import annotations

import sys
import threading
from contextlib import contextmanager

HANDOVER_S = 0.0005
"""The switch interval while a thread launches GPU work beside Python code: a tenth of Python's
default, under a small operation's launch and first use (tens of microseconds to tens of ms), so
the imports beside it lose only the extra hand-overs."""

_lock = threading.Lock()
_users = 0
_saved: float | None = None


@contextmanager
def quick_handover(interval_s: float = HANDOVER_S):
    """Within it, the interpreter switches threads every ``interval_s`` at most (its own interval
    if shorter); the interval in force before the first of nested or concurrent users comes back
    after the last."""
    global _users, _saved
    with _lock:
        if _users == 0:
            own = sys.getswitchinterval()
            # set only when shorter: the interpreter keeps whole microseconds, so setting its own
            # value again would shorten it by one
            _saved = own if interval_s < own else None
            if _saved is not None:
                sys.setswitchinterval(interval_s)
        _users += 1
    try:
        yield
    finally:
        with _lock:
            _users -= 1
            if _users == 0 and _saved is not None:
                sys.setswitchinterval(_saved)
