"""torch_ampn.utils.threads: the package's loops run on the cores other processes leave free."""

import json
import os
import subprocess
import sys
import time

import pytest
import torch

from torch_ampn.utils import threads as th
from torch_ampn.utils import tuning
from torch_ampn.utils.threads import GOVERNOR, OtherLoad, ThreadGovernor, follow_free_cpu

STAT = """cpu  {total} 0 0 0 0 0 0 0 0 0
cpu0 {u0} {n0} {s0} {i0} 7 {irq0} 0 {st0} 0 0
cpu1 {u1} 0 {s1} {i1} 0 0 0 0 0 0
intr 123 4 5
procs_running 3
"""


class Clock:
    """A wall clock and a CPU-time clock that the test moves."""

    def __init__(self) -> None:
        self.now, self.cpu = 100.0, 10.0


def _write(path, **ticks):
    values = dict(total=0, u0=0, n0=0, s0=0, i0=0, irq0=0, st0=0, u1=0, s1=0, i1=0) | ticks
    path.write_text(STAT.format(**values))


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_other_load_is_the_busy_time_less_this_processs_own(tmp_path):
    stat, clock = tmp_path / "stat", Clock()
    load = OtherLoad(str(stat), cpus={0, 1}, clock=lambda: clock.now, own_time=lambda: clock.cpu)
    load.ticks_per_second = 100
    _write(stat, u0=1000, s0=100, i0=5000, u1=2000, s1=50, i1=4000)
    assert load() is None  # nothing to compare with yet
    # 2 s later: cpu0 busy 150 ticks (user 100, nice 20, irq 10, steal 20; iowait is free time), cpu1 250
    _write(stat, u0=1100, n0=20, s0=100, i0=5100, irq0=10, st0=20, u1=2200, s1=100, i1=4150)
    clock.now, clock.cpu = 102.0, 11.5  # this process used 1.5 s of CPU
    assert load() == pytest.approx((1.5 + 2.5 - 1.5) / 2.0)  # 4.0 busy s - 1.5 own s over 2 s: 1.25 cores


def test_other_load_counts_only_this_processs_cpus_and_says_when_it_cannot(tmp_path):
    stat, clock = tmp_path / "stat", Clock()
    _write(stat, u0=0, u1=0)
    load = OtherLoad(str(stat), cpus={1}, clock=lambda: clock.now, own_time=lambda: clock.cpu)
    load.ticks_per_second = 100  # the first sample: when it is made
    _write(stat, u0=100, u1=5)  # cpu0's 100 ticks are another CPU's
    clock.now += 0.05
    assert load() is None  # too short a window: it goes on
    _write(stat, u0=100, u1=50)
    clock.now += 0.95
    assert load() == pytest.approx(0.5)
    missing = OtherLoad(str(stat), cpus={0, 5}, clock=lambda: clock.now, own_time=lambda: clock.cpu)
    assert missing.busy_seconds() is None  # cpu5 is not in the file
    assert OtherLoad(str(tmp_path / "absent")).busy_seconds() is None
    # never below zero (this process's CPU time is exact, /proc/stat's ticks are sampled)
    _write(stat, u1=60)
    clock.now, clock.cpu = clock.now + 1.0, clock.cpu + 0.5
    assert load() == 0.0


def test_the_real_proc_stat_is_read():
    assert OtherLoad().busy_seconds() > 0


def test_a_compiling_call_runs_on_the_ceiling_and_its_time_is_not_looked_at(tmp_path, restore_threads):
    stat, clock = tmp_path / "stat", Clock()
    _write(stat, u0=0, u1=0)
    load = OtherLoad(str(stat), clock=lambda: clock.now, own_time=lambda: clock.cpu, cpus={0, 1})
    load.ticks_per_second = 100
    governor = ThreadGovernor(load, interval=0.25, clock=lambda: clock.now)
    torch.set_num_threads(2)
    before = governor.enter()
    torch.set_num_threads(1)  # as after a busy look
    with governor.at_ceiling():
        assert torch.get_num_threads() == 2
        _write(stat, u0=150, u1=150)  # the compiler's workers: 2 busy cores for 1.5 s
        clock.now += 1.5
    assert torch.get_num_threads() == 1
    _write(stat, u0=160, u1=150)  # then 0.1 s of this process's own work
    clock.now, clock.cpu = clock.now + 0.25, clock.cpu + 0.1
    governor.step()
    assert [round(others, 6) for _, others, _ in governor.looks] == [0.0]  # the compile's 1.5 s left out
    governor.exit(before)


@pytest.mark.parametrize(
    "cpus, ceiling, others, threads",
    [(2, 2, 0.0, 2), (2, 2, 0.3, 2), (2, 2, 0.31, 1), (2, 2, 0.67, 1), (2, 2, 1.9, 1), (2, 2, 3.0, 1),
     (8, 8, 2.5, 5), (8, 4, 1.0, 4), (8, 4, 6.0, 2), (8, 4, 7.5, 1), (2, 1, 0.0, 1)],
)  # fmt: skip
def test_the_target_is_one_thread_per_core_the_others_leave(cpus, ceiling, others, threads):
    load = OtherLoad(cpus=set(range(cpus)))
    governor = ThreadGovernor(load)
    governor.ceiling = ceiling
    assert governor.target(others) == threads  # cores - ceil(others - 0.3), in [1, ceiling]


class FakeLoad:
    """Others' use from a list, one value per look."""

    num_cpus = 2

    def __init__(self, values) -> None:
        self.values = list(values)
        self.looks = 0

    def __call__(self):
        self.looks += 1
        return self.values.pop(0) if self.values else None


def test_the_governor_drops_threads_at_once_and_adds_them_after_looks_that_agree(restore_threads):
    clock = Clock()
    load = FakeLoad([1.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    governor = ThreadGovernor(load, interval=0.25, confirm=2, clock=lambda: clock.now)
    torch.set_num_threads(2)
    before = governor.enter()
    assert (before, governor.ceiling) == (2, 2)
    seen = []
    for _ in range(7):
        governor.step()
        governor.step()  # within the interval: no look
        seen.append(torch.get_num_threads())
        clock.now += 0.25
    assert load.looks == 7
    # one look per interval, the first at the first step; a busy look takes a thread at once; a
    # single quiet look (a lull) does not bring it back, two in a row do
    assert seen == [1, 1, 1, 1, 2, 2, 2]
    assert [n for _, n in governor.history] == [1, 2]
    governor.exit(before)
    assert torch.get_num_threads() == 2


def test_loops_inside_one_another_share_the_ceiling_and_the_outermost_restores(restore_threads):
    clock = Clock()
    governor = ThreadGovernor(FakeLoad([1.0]), interval=0.0, clock=lambda: clock.now)
    torch.set_num_threads(2)
    outer = governor.enter()
    governor.step()
    assert torch.get_num_threads() == 1
    inner = governor.enter()  # e.g. a validation rollout inside a fit
    assert (inner, governor.ceiling) == (1, 2)
    with governor.at_ceiling():  # a call that compiles: every thread the loop may use
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == 1
    governor.exit(inner)
    assert torch.get_num_threads() == 1  # still inside the fit
    governor.exit(outer)
    assert torch.get_num_threads() == 2
    # a loop that starts soon after the last one ended takes its decision at once; a later one does not
    governor.enter()
    assert torch.get_num_threads() == 1
    governor.exit(2)
    clock.now += th.FRESH + 0.1
    governor.enter()
    assert torch.get_num_threads() == 2
    governor.exit(2)


def test_one_thread_and_no_statistics_change_nothing(restore_threads):
    load = FakeLoad([1.0] * 4)
    governor = ThreadGovernor(load, interval=0.0)
    torch.set_num_threads(1)
    governor.enter()
    governor.step()
    governor.step()
    assert load.looks == 0  # a ceiling of one: nothing to look at
    governor.exit(1)
    torch.set_num_threads(2)
    governor = ThreadGovernor(FakeLoad([]), interval=0.0)  # no /proc/stat: None at every look
    governor.enter()
    governor.step()
    governor.step()
    assert torch.get_num_threads() == 2
    governor.exit(2)


def test_follow_free_cpu_leaves_other_devices_and_off_alone(monkeypatch):
    monkeypatch.delenv("AMPN_THREADS", raising=False)
    monkeypatch.setattr(tuning, "_enabled", False)
    with follow_free_cpu("cpu") as threads:  # a library call: the process's threads are its owner's
        assert threads is not GOVERNOR and GOVERNOR.depth == 0
    tuning.enable_cpu_tuning()  # what the command-line programs do
    with follow_free_cpu("meta") as threads:
        assert threads is not GOVERNOR and GOVERNOR.depth == 0
    with follow_free_cpu("cpu") as threads:
        assert threads is GOVERNOR and GOVERNOR.depth == 1
    assert GOVERNOR.depth == 0
    monkeypatch.setenv("AMPN_THREADS", "off")
    with follow_free_cpu() as threads:
        assert threads is not GOVERNOR and GOVERNOR.depth == 0
    monkeypatch.setenv("AMPN_THREADS", "on")
    with pytest.raises(RuntimeError), follow_free_cpu():  # left on an error too
        raise RuntimeError
    assert GOVERNOR.depth == 0


@pytest.fixture
def busy_governor(monkeypatch, restore_threads):
    """The process's governor, told at every step that another process holds a core (CPU tuning on)."""
    monkeypatch.delenv("AMPN_THREADS", raising=False)
    monkeypatch.setattr(tuning, "_enabled", True)
    # per loop: busy, quiet, quiet
    monkeypatch.setattr(GOVERNOR, "load", FakeLoad([1.0, 0.0, 0.0] * 2))
    monkeypatch.setattr(GOVERNOR, "interval", 0.0)
    monkeypatch.setattr(GOVERNOR, "_decision", None)
    monkeypatch.setattr(GOVERNOR, "_streak", 0)
    monkeypatch.setattr(GOVERNOR, "_active", float("-inf"))
    torch.set_num_threads(2)
    return GOVERNOR


def test_the_simulator_and_the_rollouts_follow_at_every_step(monkeypatch, busy_governor):
    import importlib

    sim = importlib.import_module("torch_ampn.sim.simulate")  # the module, not the function
    from torch_ampn.data import HierarchyCache
    from torch_ampn.rollout import rollout

    counts = {"simulate": [], "rollout": []}
    real_refresh = sim.LaminateModel.refresh_pairs

    def refresh(model, x):  # called at every saved step of the simulator, after the look
        counts["simulate"].append(torch.get_num_threads())
        return real_refresh(model, x)

    def predictor(data):
        counts["rollout"].append(torch.get_num_threads())
        return torch.zeros_like(data["l0"].pos)

    monkeypatch.setattr(sim.LaminateModel, "refresh_pairs", refresh)
    traj = sim.simulate(sim.StampFormingConfig(ply_cells=4, num_steps=3, duration=0.25, stroke=15.0))
    assert torch.get_num_threads() == 2  # restored after each
    monkeypatch.setattr(GOVERNOR, "_decision", None)  # the rollout starts without the simulator's
    rollout(predictor, traj, HierarchyCache(None, max_levels=2)(traj))
    assert torch.get_num_threads() == 2
    assert counts["simulate"] == [1, 1, 2]  # busy: one thread at once; two quiet looks: two again
    assert counts["rollout"] == [1, 1, 2]


def test_the_fit_follows_at_every_batch(busy_governor):
    from types import SimpleNamespace

    from torch_ampn.training import NextStepLightningModule
    from torch_ampn.training.free_cpu import FollowFreeCpu

    module = NextStepLightningModule(hidden_channels=8, mlp_channels=8, num_levels=1)
    (callback,) = [c for c in module.configure_callbacks() if isinstance(c, FollowFreeCpu)]
    pl_module = SimpleNamespace(device=torch.device("cpu"))
    callback.on_train_start(None, pl_module)
    counts = []
    for i in range(3):
        callback.on_train_batch_start(None, pl_module, None, i)
        counts.append(torch.get_num_threads())
    assert counts == [1, 1, 2]
    callback.on_exception(None, pl_module, RuntimeError())  # an interrupted fit restores too
    assert torch.get_num_threads() == 2 and GOVERNOR.depth == 0
    callback.on_train_end(None, pl_module)  # once only
    assert GOVERNOR.depth == 0


def test_a_busy_process_beside_the_loop_takes_a_thread(monkeypatch, restore_threads):
    """The real /proc/stat: a loop of two threads beside a process that spins on a core drops to one."""
    monkeypatch.delenv("AMPN_THREADS", raising=False)
    if len(OtherLoad().cpus) != 2:
        pytest.skip("needs exactly 2 CPUs, so that one busy process takes one of them")
    governor = ThreadGovernor()
    spin = "import time\nend = time.time() + 30\nwhile time.time() < end: pass"
    busy = subprocess.Popen([sys.executable, "-c", spin])
    try:
        torch.set_num_threads(2)
        x = torch.randn(256, 256)
        before = governor.enter()
        end = time.monotonic() + 10
        while torch.get_num_threads() == 2 and time.monotonic() < end:
            governor.step()
            x @ x
        assert torch.get_num_threads() == 1
        governor.exit(before)
    finally:
        busy.kill()
        busy.wait()


LIBRARY_CALLS = """
import json, os, sys
import torch
torch.set_num_threads(2)
# third-party imports that set variables of their own (not the package's to judge): lightning
# PYTORCH_NVML_BASED_CUDA_CHECK and TORCHINDUCTOR_CACHE_DIR, scikit-learn KMP_DUPLICATE_LIB_OK
import lightning, sklearn
environment = dict(os.environ)
import torch_ampn.cli.train, torch_ampn.cli.data, torch_ampn.design, torch_ampn.rollout, torch_ampn.sim
from torch_ampn.data import HierarchyCache
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.rollout import FastRollout, rollout
from torch_ampn.utils.threads import GOVERNOR

seen = []
def predictor(data):
    seen.append((torch.get_num_threads(), GOVERNOR.depth))
    return torch.zeros_like(data["l0"].pos)

cfg = torch_ampn.sim.StampFormingConfig(ply_cells=4, punch_cells=(3, 3), die_cells=(3, 3), num_steps=2,
                                       duration=0.25, stroke=15.0)
traj = torch_ampn.sim.simulate(cfg)
rollout(predictor, traj, HierarchyCache(None, max_levels=2)(traj))
surrogate = AMPNSurrogate(num_components=traj.num_components, num_grippers=1, num_levels=2,
                          hidden_channels=8, mlp_channels=8)
fast = FastRollout(surrogate, HierarchyCache(None, max_levels=2)(traj), compile=False)
same_environment = dict(os.environ) == environment
print(json.dumps({"threads": torch.get_num_threads(), "seen": seen, "environment": same_environment,
                  "retain_heap": fast.retain_heap, "governed": GOVERNOR.depth or len(GOVERNOR.history)}))
"""


@pytest.mark.slow
def test_importing_and_calling_the_library_leaves_the_process_as_it_was():
    """Threads, environment and glibc's heap settings belong to the process's owner (a fresh interpreter)."""
    env = {k: v for k, v in os.environ.items() if k not in ("AMPN_THREADS", "OMP_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", LIBRARY_CALLS], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["threads"] == 2 and result["environment"] and result["governed"] == 0
    assert result["seen"] == [[2, 0], [2, 0]]  # the rollout ran on the caller's threads, ungoverned
    assert result["retain_heap"] is False  # no mallopt: glibc's adaptive thresholds stay
