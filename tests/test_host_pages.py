"""The launchers keep numpy's large arrays on ordinary pages in their own process (launch/host_pages.py)."""

import os
import subprocess
import sys
import textwrap


def _in_a_fresh_interpreter(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=env)


def test_the_launcher_turns_numpys_huge_page_request_off_unless_the_environment_says():
    done = _in_a_fresh_interpreter(
        """
        from numpy._core import multiarray
        from gaussian_atoms_method.launch.host_pages import VARIABLE, ordinary_pages

        multiarray._set_madvise_hugepage(True)
        kept = ordinary_pages({VARIABLE: "1"})  # the user's own choice stands
        asked_then = multiarray._get_madvise_hugepage()
        stopped = ordinary_pages({})
        print(kept, asked_then, stopped, multiarray._get_madvise_hugepage())
        """
    )
    assert done.stdout.split() == ["False", "True", "True", "False"], done.stderr


def test_the_command_line_runs_its_verbs_on_ordinary_pages():
    done = _in_a_fresh_interpreter(
        """
        import sys
        from numpy._core import multiarray
        from gaussian_atoms_method.cli import entrypoint

        multiarray._set_madvise_hugepage(True)
        try:
            entrypoint(["simulate", "--help"])
        except SystemExit:
            pass
        print("huge pages asked:", multiarray._get_madvise_hugepage(), file=sys.stderr)
        """
    )
    assert "--particle" in done.stdout, done.stderr  # the verb ran
    assert done.stderr.strip().splitlines()[-1] == "huge pages asked: False", done.stderr
