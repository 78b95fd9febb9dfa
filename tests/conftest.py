import subprocess
import sys
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _physics_sparse_notes_hidden():
    """The filter the physics installs at import (physics.quiet_sparse_notes), again in each
    test: pytest gives every test a fresh copy of the warning filters."""
    from gaussian_atoms_method.physics import quiet_sparse_notes

    quiet_sparse_notes()


@pytest.fixture
def shared_data() -> Path:
    """The project's shared public data (../shared/data beside the checkout)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def simulate_sphere():
    """``simulate_sphere(out, radius_A, tilts)``: ``gaussian-atoms simulate`` of a small Au sphere
    (Gaussian potential, noise 20) into ``out``, through the command line as a user runs it."""

    def simulate(out: Path, radius_A: float = 6, tilts: str = "-70:5:70") -> Path:
        command = [str(Path(sys.executable).parent / "gaussian-atoms"), "simulate", "--output", str(out)]
        command += ["--particle", "sphere", "--potential", "gaussian", "--radius-A", str(radius_A)]
        result = subprocess.run(
            command + ["--tilts", tilts, "--noise-std", "20"], capture_output=True, text=True, timeout=600
        )
        assert result.returncode == 0, result.stderr
        return out

    return simulate


@pytest.fixture
def fit_view_parameter():
    """``fit_view_parameter(model, outputs, atoms, sim, name, lr, steps, after_step=None)``: the
    model's Gaussians put at the true atoms (``atoms``, widths of ``sim.truth``), then the view
    parameter ``name`` and the amplitudes trained by Adam, one view a step in turn; returns the
    parameter, detached.  Atoms known, a view parameter read on its own."""
    import math

    import torch

    def fit(model, outputs, atoms, sim, name, lr, steps, after_step=None):
        norm = model.normalisation
        with torch.no_grad():
            model.gauss_params["means"].copy_(
                torch.as_tensor(norm.positions_from_A(atoms.positions), dtype=torch.float32)
            )
            model.gauss_params["log_sigmas"].fill_(math.log(sim.truth.sigmas[0] * norm.length_scale))
        optimiser = torch.optim.Adam(
            [
                {"params": [model.view_params[name]], "lr": lr},
                {"params": [model.gauss_params["log_amplitudes"]], "lr": 2e-2},
            ]
        )
        n_views = len(outputs.cameras)
        targets = [outputs.metadata["projections"][v][..., None] for v in range(n_views)]
        for step in range(steps):
            optimiser.zero_grad()
            v = step % n_views
            outputs_v = model.get_outputs(outputs.cameras[v : v + 1])
            model.get_loss_dict(outputs_v, {"image": targets[v]})["main_loss"].backward()
            optimiser.step()
            if after_step is not None:
                after_step()
        return model.view_params[name].detach()

    return fit
