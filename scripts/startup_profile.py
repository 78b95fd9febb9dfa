"""Where the start-up of a run goes: imports, reading the tilt series, the back-projection
initialisation (on the CPU and, when there is one, the GPU), and building the model.

    python scripts/startup_profile.py DATA_DIR

Prints one line per phase with its wall time (the second GPU line is warm: CUDA's own start-up
is in the first).
"""

from __future__ import annotations

import sys
import time

t0 = time.perf_counter()
import nerfstudio.scripts.train  # noqa: E402,F401

import gaussian_atoms_method.config  # noqa: E402,F401

print(f"import nerfstudio + plugin: {time.perf_counter() - t0:.1f} s", flush=True)

import torch  # noqa: E402

from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig  # noqa: E402
from gaussian_atoms_method.initialise import backprojection_candidates  # noqa: E402
from gaussian_atoms_method.model import GaussianAtomsModelConfig  # noqa: E402


def timed(label, fn):
    t = time.perf_counter()
    out = fn()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    print(f"{label}: {time.perf_counter() - t:.1f} s", flush=True)
    return out


data = sys.argv[1]
outputs = timed("dataparser (read, normalise, cameras)", lambda: TiltSeriesDataParserConfig(data=data).setup().get_dataparser_outputs("train"))
s = outputs.metadata["tilt_series"]
args = (s.projections, s.angles_deg, s.pixel_size_A, s.tilt_axis, s.centre_px, 10000)
for device in (["cuda", "cuda"] if torch.cuda.is_available() else []) + ["cpu"]:
    timed(f"back-projection candidates on {device}", lambda: backprojection_candidates(*args, device=device))
timed("model construction (includes the candidates)", lambda: GaussianAtomsModelConfig().setup(scene_box=outputs.scene_box, num_train_data=s.n_views, metadata=outputs.metadata))
