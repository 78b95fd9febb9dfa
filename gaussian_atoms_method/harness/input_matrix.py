"""Run every broken and odd tilt series through the front door and print a table.

The catalogue's cases (gaussian_atoms_method/harness/input_cases.py, also in the tests) and
a few more that only this script tries.  Each runs as a user would:

    ns-train gaussian-atoms --data DIR --max-num-iterations 2 --machine.device-type cpu --vis tensorboard

A broken case passes when it exits non-zero with exactly one line of its own output (the
FutureWarnings torch and nerfstudio print on import are not ours), no traceback and no run
directory; an odd case passes when it trains and writes atoms.xyz.

    gaussian-atoms input-matrix [--launcher ns-train|gaussian-atoms] [--output outputs/input-matrix]
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from dataparsers.tilt_series_format import MANIFEST
from gaussian_atoms_method.harness.input_cases import BROKEN, ODD, edit_manifest, own_lines, valid_series, valid_then

BIN = Path(sys.executable).parent


def _tiff(out: Path) -> Path:
    import tifffile

    out = valid_series(out)
    tifffile.imwrite(out / "stack.tif", np.load(out / "projections.npy"))
    return edit_manifest(out, projections="stack.tif")


def _imod_mrc(out: Path) -> Path:
    import mrcfile

    out = valid_series(out)
    with mrcfile.new(out / "stack.mrc") as mrc:
        mrc.set_data(np.load(out / "projections.npy").astype(np.float32))
        mrc.voxel_size = 0.3
        mrc.add_label("newstack: Tilt axis angle = -86.0, binning = 1")
    return edit_manifest(out, projections="stack.mrc", pixel_size_A=None, tilt_axis=None)


def _npz_two(out: Path) -> Path:
    out = valid_series(out)
    p = np.load(out / "projections.npy")
    np.savez(out / "stack.npz", a=p, b=p)
    return edit_manifest(out, projections="stack.npz")


def _inf_angle(out: Path) -> Path:
    out = valid_series(out)
    (out / "angles.txt").write_text("\n".join(["-60", "-40", "-20", "0", "20", "40", "inf"]))
    return out


EXTRA_BROKEN = {
    "npz with two arrays, none named": (_npz_two, "name the one to use"),
    "projections entry is a directory": (
        lambda out: edit_manifest(valid_then(out, lambda d: (d / "sub").mkdir()), projections="sub"),
        "sub",
    ),
    "empty angles file": (lambda out: valid_then(out, lambda d: (d / "angles.txt").write_text("")), "angles"),
    "infinite angle": (_inf_angle, "NaN/Inf"),
    "zero pixel size": (
        lambda out: edit_manifest(valid_series(out), pixel_size_A=0),
        "pixel_size_A must be a positive",
    ),
    "manifest is a file path, not a directory": (lambda out: valid_series(out) / MANIFEST / "x", "not found"),
}
EXTRA_ODD = {"TIFF stack": _tiff, "IMOD MRC with its tilt-axis angle": _imod_mrc}


def run_case(launcher: list[str], data: Path, out: Path) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Train on ``data`` for two steps as a user would, with ``launcher`` (the command and, for
    ``ns-train``, the method), into ``out``; the process and its own output lines."""
    cmd = [
        *launcher,
        "--data",
        str(data),
        "--max-num-iterations",
        "2",
        "--machine.device-type",
        "cpu",
        "--vis",
        "tensorboard",
        "--output-dir",
        str(out),
        "--experiment-name",
        "m",
        "--timestamp",
        "t",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    return proc, own_lines(proc.stdout + proc.stderr)


def run_matrix(launcher: str = "ns-train", output: Path = Path("outputs/input-matrix")) -> list[dict]:
    """Run every case through ``launcher`` (``ns-train`` or ``gaussian-atoms``), print a table row
    for each as it ends, write ``input_matrix.json`` in ``output`` and return the rows."""
    command = (
        [str(BIN / "ns-train"), "gaussian-atoms"] if launcher == "ns-train" else [str(BIN / "gaussian-atoms"), "train"]
    )
    shutil.rmtree(output, ignore_errors=True)
    rows = []
    print(
        "| case | kind | in tests | exit | own lines | traceback | run dir left | passed | message |\n| --- | --- | "
        "--- | --- | --- | --- | --- | --- | --- |",
        flush=True,
    )
    cases = [(n, "broken", True, *c) for n, c in BROKEN.items()] + [
        (n, "broken", False, *c) for n, c in EXTRA_BROKEN.items()
    ]
    cases += [(n, "odd", True, w, "") for n, w in ODD.items()] + [
        (n, "odd", False, w, "") for n, w in EXTRA_ODD.items()
    ]
    for i, (name, kind, in_tests, write, fragment) in enumerate(cases):
        case_dir = output / f"case{i:02d}"
        data = write(case_dir / "data")
        out = case_dir / "out"
        proc, lines = run_case(command, data, out)
        traceback = "Traceback" in proc.stderr
        if kind == "broken":
            left = out.exists()
            ok = proc.returncode != 0 and len(lines) == 1 and not traceback and not left and fragment in lines[0]
            message = lines[-1] if lines else ""
        else:
            left = False
            ok = proc.returncode == 0 and (out / "m" / "gaussian-atoms" / "t" / "atoms.xyz").is_file()
            message = "trained" if ok else (lines[-1] if lines else "")
        rows.append(
            {
                "case": name,
                "kind": kind,
                "in_tests": in_tests,
                "exit": proc.returncode,
                "own_lines": len(lines),
                "traceback": traceback,
                "left": left,
                "passed": ok,
                "message": message,
            }
        )
        print(
            f"| {name} | {kind} | {'yes' if in_tests else 'no'} | {proc.returncode} | {len(lines)} | "
            f"{'yes' if traceback else 'no'} | {'yes' if left else 'no'} | {'yes' if ok else 'NO'} | "
            f"{message.replace('|', '/')[:110]} |",
            flush=True,
        )
    (output / "input_matrix.json").write_text(json.dumps(rows, indent=2) + "\n")
    return rows
