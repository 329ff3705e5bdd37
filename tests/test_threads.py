"""torch_ampn.utils.threads: the OpenMP wait policy is set before torch starts, unless the user chose."""

import os
import subprocess
import sys

import pytest

from torch_ampn.utils.threads import WAIT_POLICY, configure_threads

SHOW = "import os, sys; {imports}; print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))"
CONTROLLED = ("AMPN_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def _run(imports, **env):
    clean = {k: v for k, v in os.environ.items() if k not in CONTROLLED}
    command = [sys.executable, "-c", SHOW.format(imports=imports)]
    out = subprocess.run(command, env={**clean, **env}, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_import_sets_the_wait_policy_before_torch():
    assert _run("import torch_ampn") == ["None", WAIT_POLICY]
    assert _run("import torch_ampn.cli.train") == ["None", WAIT_POLICY]  # the torch-ampn command
    assert _run("import torch; import torch_ampn") == ["None", "None"]  # too late: left alone


def test_the_users_choice_and_off_are_left_alone():
    assert _run("import torch_ampn", OMP_WAIT_POLICY="ACTIVE") == ["None", "ACTIVE"]
    assert _run("import torch_ampn", GOMP_SPINCOUNT="5") == ["5", "None"]
    assert _run("import torch_ampn", AMPN_THREADS="off") == ["None", "None"]


def test_configure_threads_reports_what_it_did(monkeypatch):
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    env = {}
    assert configure_threads(env) == f"wait={WAIT_POLICY}" and env == {"OMP_WAIT_POLICY": WAIT_POLICY}
    monkeypatch.setitem(sys.modules, "torch", object())  # torch imported: its pool has read its settings
    env = {}
    assert configure_threads(env) == "late" and env == {}
    assert configure_threads({"AMPN_THREADS": "OFF"}) == "off"
    assert configure_threads({"OMP_WAIT_POLICY": "ACTIVE"}) == "user"


def test_latency_bound_work_runs_on_one_thread_and_restores_the_count(monkeypatch):
    import torch

    from torch_ampn.utils.threads import LATENCY_BOUND_ELEMENTS, LATENCY_BOUND_THREADS, latency_bound_threads

    before = torch.get_num_threads()
    monkeypatch.delenv("AMPN_THREADS", raising=False)
    try:
        torch.set_num_threads(2)
        with latency_bound_threads("cpu"):
            assert torch.get_num_threads() == LATENCY_BOUND_THREADS == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError), latency_bound_threads():  # restored on an error too
            raise RuntimeError
        assert torch.get_num_threads() == 2
        with latency_bound_threads("meta"):  # not the CPU: left alone
            assert torch.get_num_threads() == 2
        with latency_bound_threads("cpu", elements=LATENCY_BOUND_ELEMENTS):  # small kernels: one thread
            assert torch.get_num_threads() == 1
        with latency_bound_threads("cpu", elements=LATENCY_BOUND_ELEMENTS + 1):  # bound by arithmetic
            assert torch.get_num_threads() == 2
        monkeypatch.setenv("AMPN_THREADS", "off")
        with latency_bound_threads("cpu"):
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_the_simulator_and_the_rollouts_run_on_one_thread(monkeypatch):
    import importlib

    import torch

    sim = importlib.import_module("torch_ampn.sim.simulate")  # the module, not the function
    from torch_ampn.data import HierarchyCache
    from torch_ampn.rollout import rollout

    before = torch.get_num_threads()
    monkeypatch.delenv("AMPN_THREADS", raising=False)
    counts = {"simulate": [], "rollout": []}
    real_refresh = sim.LaminateModel.refresh_pairs

    def refresh(model, x):  # called at every saved step of the simulator
        counts["simulate"].append(torch.get_num_threads())
        return real_refresh(model, x)

    def predictor(data):
        counts["rollout"].append(torch.get_num_threads())
        return torch.zeros_like(data["l0"].pos)

    monkeypatch.setattr(sim.LaminateModel, "refresh_pairs", refresh)
    try:
        torch.set_num_threads(2)
        traj = sim.simulate(sim.StampFormingConfig(ply_cells=4, num_steps=2))
        rollout(predictor, traj, HierarchyCache(None, max_levels=2)(traj))
        assert torch.get_num_threads() == 2  # restored after each
    finally:
        torch.set_num_threads(before)
    assert counts["simulate"] == [1, 1]  # every step of the simulator
    assert counts["rollout"] == [1, 1]  # every step of the rollout


def test_the_plain_rollout_sizes_a_surrogates_work_by_its_width():
    import functools

    from torch_ampn.baselines import static_plies
    from torch_ampn.forming import AMPNSurrogate
    from torch_ampn.rollout.plain import _width

    surrogate = AMPNSurrogate(hidden_channels=8, mlp_channels=8, num_levels=1)
    assert _width(surrogate.predict_residual) == 8
    assert _width(functools.partial(surrogate.predict_residual, generator=None)) == 8  # rollout_surrogate's
    assert _width(static_plies) == 1
