"""The stress cases (gaussian-atoms stress), each run inside its test: float32 against float64
for extreme widths and amplitudes, atoms beyond the edge, coincident atoms, all-zero data,
SNR below 1, and 100k atoms against the dense float64 reference.  Tolerances are the
module's (gaussian_atoms_method/harness/stress.py: what float32 arithmetic can meet)."""

import pytest

from gaussian_atoms_method.harness.stress import CASES


@pytest.mark.parametrize("name", list(CASES))
def test_stress_case(name):
    case, _ = CASES[name]
    label, ok, detail = case()
    assert ok, f"{label}: {detail}"
