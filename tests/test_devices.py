"""Where work runs: a run asked for the CPU keeps the helpers that pick their own device off a
GPU that torch sees, and leaves the choice as it found it."""

import pytest
import torch

from gaussian_atoms_method.physics import devices


def test_a_cpu_run_keeps_the_helpers_off_a_seen_gpu_and_restores_the_choice(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert devices.gpu() == torch.device("cuda") and devices.work_device(None) == torch.device("cuda")
    with devices.run_on("cpu"):
        assert devices.gpu() is None and devices.work_device(None) is None
        assert devices.default_device() == "cpu"
        with devices.run_on("cuda"):  # a nested GPU run (a sweep's) sees the GPU again
            assert devices.gpu() == torch.device("cuda")
        assert devices.gpu() is None
    assert devices.gpu() == torch.device("cuda")
    with pytest.raises(RuntimeError), devices.run_on("cpu"):
        raise RuntimeError("a failed run")
    assert devices.gpu() == torch.device("cuda")  # restored after a failure too


@pytest.mark.parametrize("setting, expected", [(None, 8), ("2", 2), ("16", 8), ("0", 8), ("many", 8)])
def test_the_threads_given_are_the_cores_at_most_the_omp_limit_set(monkeypatch, setting, expected):
    monkeypatch.setattr(devices, "cores_given", lambda: 8)
    if setting is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", setting)
    assert devices.threads_given() == expected


def test_a_film_task_on_a_one_thread_share_takes_one_thread(monkeypatch):
    from gaussian_atoms_method.film.runner import cores_per_task

    monkeypatch.setattr(devices, "cores_given", lambda: 8)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert cores_per_task(2) == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert cores_per_task(2) == 4


@pytest.mark.parametrize(
    "given, expected",
    [
        ({}, {"GOMP_SPINCOUNT": "5000"}),
        ({"OMP_WAIT_POLICY": "PASSIVE"}, {"OMP_WAIT_POLICY": "PASSIVE"}),
        ({"GOMP_SPINCOUNT": "0"}, {"GOMP_SPINCOUNT": "0"}),
    ],
)
def test_the_command_spins_its_idle_workers_briefly_unless_the_environment_says_how(given, expected):
    from gaussian_atoms_method.cli import IDLE_THREADS, spin_briefly

    environ = dict(given)
    spin_briefly(environ)
    assert environ == expected and IDLE_THREADS == ("GOMP_SPINCOUNT", "5000")
