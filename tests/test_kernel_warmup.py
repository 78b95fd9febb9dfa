"""The kernel warm-up touches nothing a run reads (launch/kernel_warmup.py)."""

import pytest
import torch

from gaussian_atoms_method.launch import kernel_warmup


def test_warm_runs_every_operation_and_leaves_the_random_state():
    """Each operation of the list runs (on the CPU here; the GPU's are the same calls) and the
    global generator is where it was: the warm-up draws only from its own."""
    state = torch.random.get_rng_state()
    kernel_warmup.libraries("cpu")
    kernel_warmup.warm("cpu")
    assert torch.equal(state, torch.random.get_rng_state())


def test_begin_starts_no_thread_off_a_gpu(monkeypatch):
    monkeypatch.setattr(kernel_warmup, "_threads", {})
    kernel_warmup.begin("cpu")
    assert kernel_warmup._threads == {}
    kernel_warmup.wait()  # nothing to wait for


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_gpu_warm_up_runs_and_leaves_the_cuda_generator():
    """On the GPU the libraries' calls run (called here, not in the thread that hides their
    errors), and neither part draws from the CUDA generator."""
    state = torch.cuda.get_rng_state()
    kernel_warmup.libraries("cuda")
    kernel_warmup.begin("cuda", libraries_first=True)
    kernel_warmup.wait()
    assert torch.equal(state, torch.cuda.get_rng_state())
