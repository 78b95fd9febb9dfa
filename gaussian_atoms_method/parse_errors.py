"""A command line's parse errors in one line.

tyro reports a malformed command line (an unknown option, a value that does not convert, a
missing one) in a box of several lines with the option's help text.  The package's rule for bad
input is one line naming the option and what was expected, then exit status 2:
:func:`one_line_errors` keeps tyro's first section (what was wrong) and drops the box, the help
text and the pointer to ``--help``, which the line names instead.  ``gaussian-atoms`` parses
inside it; ``ns-train gaussian-atoms``, whose parse is nerfstudio's, through
:func:`gaussian_atoms_method.launch.ns_train.one_line_tyro_errors`.
"""

from __future__ import annotations

import contextlib
import io
import re
import sys

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_BOX = "│╭╮╰╯┃"


def first_section(text: str) -> str:
    """What was wrong, from a tyro error in ``text``: the first section of its box (drawn with
    box characters on a terminal, or as a title and dashed rules where rich draws plain text),
    its lines joined; the text's last line where it has no sections."""
    lines = [line for line in (_ANSI.sub("", raw).strip() for raw in text.splitlines()) if line]

    def inner(line: str) -> str:
        return line.strip(_BOX).strip()

    def rule(line: str) -> bool:
        return line.startswith(("╭", "╰")) or (bool(inner(line)) and set(inner(line)) <= set("─━-"))

    if not any(rule(line) for line in lines):
        return lines[-1] if lines else ""
    start = 2 if len(lines) >= 2 and not rule(lines[0]) and rule(lines[1]) else 0  # a plain title, its rule
    body: list[str] = []
    for line in lines[start:]:
        if rule(line):
            if body:
                break
            continue
        if inner(line):
            body.append(inner(line))
    return " ".join(body) if body else lines[-1]


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
