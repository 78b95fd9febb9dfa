"""A command line's parse errors in one line.

tyro reports a malformed command line (an unknown option, a value that does not convert, a
missing one) in a box of several lines with the option's help text.  The package's rule for bad
input is one line naming the option and what was expected, then exit status 2:
:func:`one_line_errors` keeps tyro's first section (what was wrong) and drops the box, the help
text and the pointer to ``--help``, which the line names instead.
"""

from __future__ import annotations

import contextlib
import io
import re
import sys

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_BOX = "│╭╮╰╯┃"


def first_section(text: str) -> str:
    """The first section of a tyro error box in ``text`` (its lines joined), else the text's last
    non-empty line."""
    lines = [_ANSI.sub("", line).strip() for line in text.splitlines()]
    body: list[str] = []
    title = ""
    for line in lines:
        if line.startswith("╭"):
            title = line.strip("╭╮─ ")
            continue
        if line.startswith("╰"):
            break
        inner = line.strip(_BOX).strip()
        if not inner:
            continue
        if set(inner) <= {"─", "━"}:
            if body:
                break
            continue
        body.append(inner)
    if body:
        return " ".join(body)
    rest = [line for line in lines if line.strip(_BOX + "─ ")]
    return title or (rest[-1] if rest else "")


@contextlib.contextmanager
def one_line_errors(prog: str):
    """Run a parse inside; where it exits with a non-zero status after writing to standard
    error, write ``prog: error: <what was wrong> (prog --help lists the options)`` instead and
    exit 2.  What the parse writes otherwise (its help, exit 0) passes through."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            yield
    except SystemExit as exc:
        text = captured.getvalue()
        if exc.code in (0, None) or not text.strip():
            sys.stderr.write(text)
            raise
        print(f"{prog}: error: {first_section(text)} ({prog} --help lists the options)", file=sys.stderr)
        raise SystemExit(2) from None
    sys.stderr.write(captured.getvalue())
