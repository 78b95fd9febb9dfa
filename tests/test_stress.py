"""The stress cases pass (the float32/float64 agreement among them)."""

import pytest

from gaussian_atoms_method.harness.stress import low_snr_case, run_stress


@pytest.mark.parametrize("case", run_stress(include_slow=False), ids=lambda c: c[0])
def test_quick_stress_case(case):
    name, ok, detail = case
    assert ok, f"{name}: {detail}"


def test_training_at_snr_below_one_stays_finite():
    name, ok, detail = low_snr_case(steps=120)
    assert ok, f"{name}: {detail}"
