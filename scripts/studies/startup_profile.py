"""Where the start-up of a run goes: each launcher's imports and option parsing, reading the
tilt series, the back-projection start (on the CPU and, when there is one, the GPU), and
building the model.

    python scripts/studies/startup_profile.py DATA_DIR

Prints one line per phase with its wall time (the second GPU line is warm: CUDA's own start-up
is in the first).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

# Each launcher's import and command-line parsing, in a fresh interpreter (imports are cached
# within one): what ns-train and gaussian-atoms train do before the first line of training.
LAUNCHERS = {
    "ns-train gaussian-atoms: import nerfstudio's method list + plugin, parse": (
        "import tyro; from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion; "
        "tyro.cli(AnnotatedBaseConfigUnion, args=['gaussian-atoms', 'tilt-series', '--data', sys.argv[1]])"
    ),
    "gaussian-atoms train --vis viewer: import nerfstudio's trainer + plugin, parse": (
        "from gaussian_atoms_method.nerfstudio_layer.launch import build_config; build_config(['tilt-series', "
        "'--data', sys.argv[1]])"
    ),
    "gaussian-atoms train --vis tensorboard: import the engine, parse": (
        "import gaussian_atoms_method.engine.run; from gaussian_atoms_method.cli.train_command import parse; "
        "parse(['--vis', 'tensorboard', 'tilt-series', '--data', sys.argv[1]])"
    ),
}


def timed(label, fn):
    import torch

    t = time.perf_counter()
    out = fn()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    print(f"{label}: {time.perf_counter() - t:.1f} s", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data", help="a tilt-series directory (tilt_series.json)")
    data = parser.parse_args().data
    for label, code in LAUNCHERS.items():
        t = time.perf_counter()
        run = subprocess.run(
            [sys.executable, "-W", "ignore", "-c", "import sys; " + code, data], capture_output=True, text=True
        )
        if run.returncode != 0:  # e.g. ns-train where another installed method fails to import
            print(f"{label}: failed: {(run.stderr.strip().splitlines() or ['?'])[-1]}", flush=True)
            continue
        print(f"{label} (python start-up included): {time.perf_counter() - t:.1f} s", flush=True)

    t0 = time.perf_counter()
    import nerfstudio.engine.trainer  # noqa: F401

    import gaussian_atoms_method.nerfstudio_layer.config  # noqa: F401

    print(f"(in this process) import nerfstudio's trainer + plugin: {time.perf_counter() - t0:.1f} s", flush=True)
    import torch

    from dataparsers.tilt_series_dataparser import TiltSeriesDataParserConfig
    from gaussian_atoms_method.atoms.candidates import backprojection_candidates
    from gaussian_atoms_method.nerfstudio_layer.model import GaussianAtomsModelConfig

    outputs = timed(
        "dataparser (read, normalise, cameras)",
        lambda: TiltSeriesDataParserConfig(data=data).setup().get_dataparser_outputs("train"),
    )
    s = outputs.metadata["tilt_series"]
    args = (s.projections, s.angles_deg, s.pixel_size_A, s.tilt_axis, s.centre_px)
    for device in (["cuda", "cuda"] if torch.cuda.is_available() else []) + ["cpu"]:
        timed(
            f"back-projection candidates on {device}",
            lambda device=device: backprojection_candidates(
                *args, device=device, tilt_axis_angle_deg=s.tilt_axis_angle_deg
            ),
        )
    timed(
        "model construction (includes the candidates)",
        lambda: GaussianAtomsModelConfig().setup(
            scene_box=outputs.scene_box, num_train_data=s.n_views, metadata=outputs.metadata
        ),
    )


if __name__ == "__main__":
    main()
