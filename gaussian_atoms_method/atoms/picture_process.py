"""Pictures drawn in child processes, started before they are needed.

A run's last seconds go to its pictures (:mod:`.pictures`): matplotlib's import and its first
text (longer where its font cache is built) and two figures drawn
one after the other.  A
:class:`PictureProcess` is a child Python process that imports matplotlib and draws a first
text as soon as it starts (while the run's final stage works), then waits for one picture's
arrays on its standard input; one child per picture draws them side by side while the run
writes its atoms.  The arrays are written to the child from a thread: a pipe takes 64 KB before
the child reads it, and the child reads only once matplotlib is loaded, so a plain write made
the run wait for that import.
The child imports numpy and matplotlib, not torch.

Where the machine has no cores to spare (:func:`spare_cores`) the pictures are drawn in the
run's own process, as a child's imports would take the final stage's cores.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import threading

RUN_PICTURES = 3
"""The pictures a run draws (``classes.png``, ``rdf.png`` and ``slices.png``,
:func:`~gaussian_atoms_method.engine.results.write_results`), a child each where there are cores to
spare: with two, the third was drawn in the run's own process, matplotlib's import included (1.3 s
of a 15 s Au noise-200 run on an H100 machine)."""

STAGE_CORES = 2
"""The cores left to the final stage beside the children, whose torch work runs on two threads
on a CPU (on a 2-core machine the children's imports would take the final stage's cores)."""


def spare_cores(children: int) -> bool:
    """Whether this process may use a core for each of ``children`` and :data:`STAGE_CORES` more."""
    from gaussian_atoms_method.physics.devices import cores_given

    return cores_given() >= children + STAGE_CORES


class PictureProcess:
    """One child process that will draw one picture (:meth:`draw`), started now; it imports
    from this process's module path."""

    def __init__(self) -> None:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
        )
        self.picture: tuple | None = None
        """The picture handed to the child: (a function of :mod:`.pictures`, *its arguments);
        None while it waits for one."""
        self.error = ""
        """Why the child did not draw its picture (its last line), after :meth:`wait`."""
        self._sender: threading.Thread | None = None

    def draw(self, function, *args) -> bool:
        """Hand the child ``function`` (of :mod:`.pictures`: pickled by its name, so the child
        calls its own) and its arguments, written from a thread; False where the child is gone
        (the caller draws it itself)."""
        if self._process.poll() is not None:
            self.close()
            return False
        self.picture = (function, *args)
        payload = pickle.dumps(self.picture, protocol=pickle.HIGHEST_PROTOCOL)
        self._sender = threading.Thread(target=self._send, args=(payload,), daemon=True)
        self._sender.start()
        return True

    def _send(self, payload: bytes) -> None:
        try:
            self._process.stdin.write(payload)
            self._process.stdin.close()
        except (BrokenPipeError, OSError) as exc:  # the child is gone: wait() says so
            self.error = f"could not hand it the picture ({exc})"

    def wait(self) -> bool:
        """Wait for the child; whether it drew its picture (False with :attr:`error` where it
        failed: the caller draws the picture itself, so a child never fails a run)."""
        if self.picture is None:
            self.close()
            return False
        self._sender.join()
        err = self._process.stderr.read().decode(errors="replace")
        if self._process.wait() != 0 or self.error:
            self.error = self.error or (
                err.strip().splitlines()[-1] if err.strip() else f"exit status {self._process.returncode}"
            )
            return False
        return True

    def close(self) -> None:
        """End the child without a picture (a run that stopped before its pictures)."""
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait()
        if self._sender is not None:
            self._sender.join()
        for stream in (self._process.stdin, self._process.stderr):
            try:
                stream.close()
            except (BrokenPipeError, OSError):  # what the sender left unflushed: the child is gone
                pass


def start(count: int) -> list[PictureProcess] | None:
    """``count`` children where there are cores to spare (:func:`spare_cores`); None otherwise."""
    if not spare_cores(count):
        return None
    try:
        return [PictureProcess() for _ in range(count)]
    except OSError:  # no interpreter to start: the pictures are drawn in this process
        return None


def _serve() -> None:
    """The child: matplotlib imported and a first text drawn, then one picture from stdin."""
    from io import BytesIO

    from gaussian_atoms_method.atoms import pictures

    plt = pictures.pyplot()
    fig = plt.figure(figsize=(1, 1))
    fig.text(0.5, 0.5, "Å σ")  # loads the font: the first text of a process costs its font file
    fig.savefig(BytesIO(), format="png")
    plt.close(fig)
    data = sys.stdin.buffer.read()
    if not data:  # the run ended without pictures
        return
    function, *args = pickle.loads(data)
    function(*args)


if __name__ == "__main__":
    _serve()
