"""The launchers keep numpy's large arrays on ordinary pages in their own process (launch/host_pages.py)."""

import os
import subprocess
import sys
import textwrap


def _in_a_fresh_interpreter(code: str) -> subprocess.CompletedProcess:
    env = {
        k: v
        for k, v in os.environ.items()
        if k != "NUMPY_MADVISE_HUGEPAGE" and not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"
    }
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


_CYCLES = """
    import resource
    import numpy as np
    from numpy._core import multiarray

    multiarray._set_madvise_hugepage(False)  # pages of 4 KB, as the launcher keeps them (above)

    def faults_of_ten_64_MB_arrays():
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(10):
            a = np.ones(8 << 20)  # 64 MB, every page touched
            del a
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
"""


def test_the_launcher_keeps_freed_memory_for_the_next_large_array_unless_the_environment_says():
    """A 64 MB array takes 16,384 pages of 4 KB.  glibc maps each such array afresh, so ten made
    and freed in turn fault on all their pages, ten times; with the heap kept, the first array's
    pages serve the nine after it (under two arrays' worth of faults in all).  A malloc setting
    in the environment stands: nothing is set."""
    done = _in_a_fresh_interpreter(
        textwrap.dedent(_CYCLES)
        + textwrap.dedent(
            """
        from gaussian_atoms_method.launch.host_pages import keep_freed_memory

        plain = faults_of_ten_64_MB_arrays()
        kept = (
            keep_freed_memory({"MALLOC_TRIM_THRESHOLD_": "1"}),
            keep_freed_memory({"GLIBC_TUNABLES": "glibc.malloc.mmap_max=0"}),
        )
        set_here = keep_freed_memory({})
        print(plain, *kept, set_here, faults_of_ten_64_MB_arrays())
        """
        )
    )
    plain, kept_a, kept_b, set_here, after = done.stdout.split()
    assert (kept_a, kept_b, set_here) == ("False", "False", "True"), done.stderr
    assert int(plain) > 9 * 16384 and int(after) < 2 * 16384, done.stdout


def test_the_command_line_keeps_freed_memory_in_its_own_process():
    done = _in_a_fresh_interpreter(
        textwrap.dedent(_CYCLES)
        + textwrap.dedent(
            """
        import sys
        from gaussian_atoms_method.cli import entrypoint

        try:
            entrypoint(["simulate", "--help"])
        except SystemExit:
            pass
        print("faults:", faults_of_ten_64_MB_arrays(), file=sys.stderr)
        """
        )
    )
    assert "--particle" in done.stdout, done.stderr
    assert int(done.stderr.strip().splitlines()[-1].split()[-1]) < 2 * 16384, done.stderr
