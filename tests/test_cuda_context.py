"""CUDA's context made through the driver while the launcher imports torch
(gaussian_atoms_method.launch.cuda_context): begun only for a run on CUDA, harmless where no
driver is, the one torch then uses where a GPU is."""

import ctypes
import subprocess
import sys

import pytest
import torch

from gaussian_atoms_method.launch import cuda_context, start_ahead


@pytest.mark.parametrize(
    "argv, begun",
    [
        (["--data", "series"], True),
        (["--machine.device-type", "cuda", "--data", "series"], True),
        (["--machine.device-type", "cpu", "--data", "series"], False),
        (["--machine.device_type=cpu"], False),
        (["--machine.device-type=mps"], False),
        (["--machine.device-type"], False),
        (["--help"], False),
        (["tilt-series", "-h"], False),
    ],
)
def test_begun_only_for_a_run_on_cuda(argv, begun):
    assert start_ahead.runs_on_cuda(argv) is begun


def test_the_module_imports_no_torch():
    """Begun before the launcher imports torch: importing it must not import torch."""
    code = "import sys, gaussian_atoms_method.launch.cuda_context; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_without_an_nvidia_driver_nothing_happens(monkeypatch):
    monkeypatch.setattr(cuda_context, "LIBRARY", "libno-such-driver.so.1")
    assert cuda_context._retain(0) is False


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs an NVIDIA GPU")
def test_torch_uses_the_context_made_ahead():
    """The primary context retained through the driver is the one current in torch's thread."""
    assert cuda_context._retain(0) is True
    torch.zeros(1, device="cuda:0").add_(1)
    driver = ctypes.CDLL(cuda_context.LIBRARY)
    device, primary, current = ctypes.c_int(), ctypes.c_void_p(), ctypes.c_void_p()
    assert driver.cuDeviceGet(ctypes.byref(device), 0) == 0
    assert driver.cuDevicePrimaryCtxRetain(ctypes.byref(primary), device) == 0
    assert driver.cuCtxGetCurrent(ctypes.byref(current)) == 0
    assert current.value == primary.value
    driver.cuDevicePrimaryCtxRelease(device)
