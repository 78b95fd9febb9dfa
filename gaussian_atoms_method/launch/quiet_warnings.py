"""Third-party deprecation notes kept out of our launchers' console, in their own process only.

torch and nerfstudio announce their own deprecations (``torch.jit.script``,
``torch.cuda.amp.custom_fwd``, ``GradScaler(args...)``) as FutureWarnings raised inside their
modules; none is anything a user of ``gaussian-atoms train`` or ``ns-train gaussian-atoms`` can act
on, and they came before the run's first line of its own.  :func:`quiet_third_party_warnings`
hides them where those packages raise them: the same warnings raised by a user's own code (or
by ours) still show, and nothing of theirs is patched.  ``ga.reconstruct`` leaves the caller's
filters as they are.

``ns-train`` is nerfstudio's launcher, and nerfstudio raises ``torch.jit.script``'s note while
importing its cameras, before it loads any plugin.  So the install places a start-up hook,
``gaussian_atoms_quiet.pth`` (``setup.py``), at the root of site-packages, where Python runs it
as it starts: in a process whose command line is ``ns-train gaussian-atoms ...`` it calls
:func:`quiet_third_party_warnings`, and any other process it leaves as it was.
"""

from __future__ import annotations

import warnings

THIRD_PARTY = r"(torch|torchvision|nerfstudio|gsplat|tyro)(\.|$)"
"""The modules whose own deprecation notes :func:`quiet_third_party_warnings` hides."""


def quiet_third_party_warnings() -> None:
    """Hide FutureWarnings and DeprecationWarnings raised inside :data:`THIRD_PARTY`'s modules,
    for the rest of this process (a launcher's own, see the module)."""
    for category in (FutureWarning, DeprecationWarning):
        warnings.filterwarnings("ignore", category=category, module=THIRD_PARTY)
