"""``gaussian-atoms train --help``: this method's options in groups, each with its default and
the first sentence of its docstring in plain text (nerfstudio's trainer options, which the
command also takes, are listed by ``ns-train gaussian-atoms --help``).

The docstrings are read from the options' own source
(:func:`~gaussian_atoms_method.engine.options.field_docs`)."""

from __future__ import annotations

import dataclasses
import re
import textwrap

from gaussian_atoms_method.engine.options import field_docs

WIDTH = 100
"""Columns of the help text."""


def plain(text: str) -> str:
    """``text``'s first sentence without Sphinx markup: a role's target by its last name, literals
    without their backquotes, one line."""
    text = re.sub(r":\w+:`~?([^`<]*?)(?:\s*<[^>]*>)?`", lambda m: m.group(1).rsplit(".", 1)[-1], text)
    text = re.sub(r"``([^`]*)``", r"\1", text).replace("::", ":")
    text = " ".join(text.split())
    match = re.search(r"(?<![.\w]\w)(?<!e\.g)(?<!i\.e)\.\s", text + " ")
    return text[: match.start() + 1] if match else text


def option_lines(cls, prefix: str) -> list[str]:
    """One entry per option of dataclass ``cls``: ``--prefix.name DEFAULT`` and its sentence."""
    docs, lines = field_docs(cls), []
    for f in dataclasses.fields(cls):
        if f.name.startswith("_") or not f.init:
            continue
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            continue
        lines.append(f"  --{prefix}{f.name.replace('_', '-')} {default}")
        if f.name in docs:
            lines += textwrap.wrap(plain(docs[f.name]), WIDTH, initial_indent=" " * 6, subsequent_indent=" " * 6)
    return lines


def train_help() -> str:
    """The text ``gaussian-atoms train --help`` prints."""
    from dataparsers.tilt_series_options import TiltSeriesOptions
    from gaussian_atoms_method.cli.train_command import SUBCOMMAND, TrainOptions
    from gaussian_atoms_method.engine.options import FitOptions

    run = [
        "  --output-dir outputs, --experiment-name (the series' directory), --timestamp {timestamp}",
        "      Where the run goes: OUTPUT-DIR/EXPERIMENT-NAME/gaussian-atoms/TIMESTAMP.",
        f"  --max-num-iterations {TrainOptions.max_num_iterations}",
        "      The step limit; a run stops sooner once its atoms have settled.",
        "  --machine.device-type cpu|cuda (the GPU where torch sees one)",
        "  --vis tensorboard|viewer",
        "      viewer: train under nerfstudio's viewer, which keeps serving after training (Ctrl-C).",
    ]
    return "\n".join(
        [
            f"usage: gaussian-atoms train [OPTIONS] {SUBCOMMAND} --data DIR [SERIES OPTIONS]",
            "",
            "Fit one isotropic 3D Gaussian per atom to a tilt series (the same run as `ns-train gaussian-atoms`).",
            "nerfstudio's trainer options (loggers, --load-config, ...) are taken too: "
            "`ns-train gaussian-atoms --help` lists them.",
            "",
            "the run:",
            *run,
            "",
            f"the tilt series ({SUBCOMMAND} ...):",
            *option_lines(TiltSeriesOptions, ""),
            "",
            "the fit (--pipeline.model.NAME VALUE; booleans take True or False):",
            *option_lines(FitOptions, "pipeline.model."),
        ]
    )
