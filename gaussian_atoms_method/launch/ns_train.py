"""What the plugin does in the process of ``ns-train gaussian-atoms``, and only there.

``ns-train`` imports every method it knows before it parses its command line; where the
command line names this method, :func:`prepare` begins the run's start in a thread
(:mod:`.start_ahead`; the GPU's context with it, :mod:`.cuda_context`), keeps numpy's arrays on
ordinary pages and malloc's freed memory for the next array (:mod:`.host_pages`), leaves torch's compiler
and symbolic shapes unimported (:mod:`.lean_torch`) and has the command line's errors said in
one line (:func:`one_line_tyro_errors`), as ``gaussian-atoms train`` does in its own process.
Any other ``ns-train`` (another method, or one that only lists them) is left as it is.
"""

from __future__ import annotations

from pathlib import Path


def asks_for_this_method(argv: list[str]) -> bool:
    """Whether ``argv`` (``sys.argv``) is ``ns-train gaussian-atoms ...``."""
    return bool(argv) and Path(argv[0]).name == "ns-train" and argv[1:2] == ["gaussian-atoms"]


def prepare(argv: list[str]) -> bool:
    """Prepare the run ``argv`` asks for, where it is ``ns-train gaussian-atoms`` (see the
    module); returns whether it was."""
    if not asks_for_this_method(argv):
        return False
    from gaussian_atoms_method.launch import cuda_context
    from gaussian_atoms_method.launch.host_pages import keep_freed_memory, ordinary_pages
    from gaussian_atoms_method.launch.lean_torch import lean_torch
    from gaussian_atoms_method.launch.start_ahead import begin_for, runs_on_cuda, settle_imports

    ordinary_pages()
    keep_freed_memory()
    if runs_on_cuda(argv[2:]):
        cuda_context.begin()  # the GPU's context made while nerfstudio loads
    begin_for(argv[2:])
    settle_imports()  # nerfstudio goes on importing: not scipy's packages beside the thread's
    lean_torch()
    one_line_tyro_errors("ns-train gaussian-atoms")
    return True


def one_line_tyro_errors(prog: str) -> None:
    """Make every later ``tyro.cli`` call in this process parse inside
    :func:`~gaussian_atoms_method.parse_errors.one_line_errors` for ``prog``: ``ns-train``'s
    ``tyro.cli`` call is nerfstudio's own, made after the plugin is imported."""
    import functools

    import tyro

    from gaussian_atoms_method.parse_errors import one_line_errors

    parse = tyro.cli
    if getattr(parse, "one_line_errors", False):
        return

    @functools.wraps(parse)
    def cli(*args, **kwargs):
        with one_line_errors(prog):
            return parse(*args, **kwargs)

    cli.one_line_errors = True
    tyro.cli = cli
