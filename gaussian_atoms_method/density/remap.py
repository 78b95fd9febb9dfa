"""Change the set of Gaussians during training without breaking the optimiser.

Pruning, duplication and merging all map old Gaussians to new ones.  A remap ``(src, dst,
n_out)`` says that new Gaussian ``dst[k]`` takes (the mean of) old Gaussian ``src[k]``; it is
applied to every per-Gaussian parameter and to the optimiser's per-Gaussian state (Adam's
moment estimates), so surviving Gaussians keep their moments and merged ones get the mean of
their members'.  No nerfstudio import: parameters are a mapping name -> ``nn.Parameter`` and
optimisers a mapping name -> ``torch.optim.Optimizer``.
"""

from __future__ import annotations

from typing import Mapping, MutableMapping

import torch

from gaussian_atoms_method.atoms.merge import scatter_mean


def apply_remap(
    params: MutableMapping[str, torch.nn.Parameter],
    optimizers: Mapping[str, torch.optim.Optimizer],
    src: torch.Tensor,
    dst: torch.Tensor,
    n_out: int,
    new_values: Mapping[str, torch.Tensor] | None = None,
    param_lists: MutableMapping[str, list] | None = None,
) -> None:
    """Replace every parameter in ``params`` by its remapped version, in place.

    Parameters
    ----------
    params : name -> (N, ...) Parameter
    optimizers : name -> optimiser holding exactly that parameter (missing names are skipped)
    src, dst : (K,) long tensors; n_out : int
    new_values : name -> (n_out, ...) tensor, optional
        Values to use instead of the scatter-mean of the old values (e.g. a mass-conserving
        amplitude); optimiser state is still scatter-averaged.
    param_lists : name -> list of parameters, optional
        A second registry of the parameters (nerfstudio's ``Optimizers.parameters``) to update.
    """
    new_values = new_values or {}
    for name in list(params.keys()):
        old = params[name]
        data = new_values[name] if name in new_values else scatter_mean(old.data, src, dst, n_out)
        new = torch.nn.Parameter(data.detach().to(old.dtype).contiguous(), requires_grad=old.requires_grad)
        opt = optimizers.get(name)
        if opt is not None:
            state = opt.state.pop(old, None)
            for group in opt.param_groups:
                group["params"] = [new if p is old else p for p in group["params"]]
            if state is not None:
                opt.state[new] = {
                    k: scatter_mean(v, src, dst, n_out)
                    if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == old.shape[0]
                    else v
                    for k, v in state.items()
                }
        if param_lists is not None and name in param_lists:
            param_lists[name] = [new if p is old else p for p in param_lists[name]]
        params[name] = new


def keep_remap(keep: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Remap that keeps the Gaussians where the boolean mask ``keep`` is true."""
    src = torch.nonzero(keep).flatten()
    return src, torch.arange(len(src), device=keep.device), len(src)


def duplicate_remap(n: int, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Remap that keeps all ``n`` Gaussians and appends copies of those in ``idx``."""
    src = torch.cat([torch.arange(n, device=idx.device), idx])
    return src, torch.arange(len(src), device=idx.device), len(src)


def merge_remap(labels: torch.Tensor, n_clusters: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Remap that merges every cluster (``labels``: cluster of each Gaussian) into one Gaussian."""
    return torch.arange(len(labels), device=labels.device), labels, n_clusters
