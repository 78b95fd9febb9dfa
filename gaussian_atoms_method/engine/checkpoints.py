"""Loading nerfstudio checkpoints of this method under torch >= 2.6.

torch >= 2.6 loads checkpoints with ``weights_only=True``, which refuses the numpy scalars
nerfstudio's learning-rate schedulers leave in every checkpoint (so ``ns-viewer
--load-config``, ``gaussian-atoms export`` and resuming would fail).  nerfstudio builds the
model before it loads a checkpoint (``Trainer.setup`` and ``eval_setup`` alike), so the model
calls :func:`allow_numpy_scalars_in_checkpoints` when it is built: the allowance is made where
checkpoints are loaded, not as a side effect of importing anything.

Checkpoints of earlier versions load too: :func:`with_background_terms`.
"""

from __future__ import annotations

import numpy as np
import torch


def numpy_checkpoint_globals() -> list:
    """The numpy globals a nerfstudio checkpoint holds: the scalar constructor and dtypes."""
    scalar = np.float64(0.0).__reduce__()[0]  # what pickles a numpy scalar, by its public protocol
    return [scalar, np.dtype] + [type(np.dtype(t)) for t in ("float64", "float32", "int64")]


def allow_numpy_scalars_in_checkpoints() -> None:
    """Allow exactly those harmless globals in ``torch.load(weights_only=True)`` (a no-op on
    torch versions without safe globals)."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is not None:
        add(numpy_checkpoint_globals())


def with_background_terms(state_dict: dict, background: torch.Tensor | None) -> dict:
    """``state_dict`` with a run's one background term a view widened to ``background``'s
    (V, 6): a smooth floor saved before it learned its quadratic correction had only its
    constant, and the correction it lacks is zero (its fixed frame surface)."""
    key = "view_params.background"
    old = state_dict.get(key)
    if background is None or old is None or old.shape[1] != 1 or background.shape[1] == 1:
        return state_dict
    return {**state_dict, key: torch.cat([old, old.new_zeros(old.shape[0], background.shape[1] - 1)], dim=1)}
