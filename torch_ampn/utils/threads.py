"""Intra-op threads that follow the CPU other processes leave free.

torch's CPU kernels run on an OpenMP pool (GNU libgomp in the Linux wheels) whose idle threads
spin before they sleep. On a quiet machine that is the fastest way to run many small kernels;
when another process holds a core, a thread that spins at a barrier burns the core its partner
needs, and a job runs tens of times slower (a quickstart training step 68x beside one busy
process on 2 cores; benchmarks/README.md, "Speed under load"). Sleeping threads
(``OMP_WAIT_POLICY=PASSIVE``) hold up under load but pay a wake-up per parallel region, which a
rollout step pays hundreds of times (1.5-3.2x its quiet time, depending on the host).

The package's loops (training steps, rollouts, the simulator's sub-steps) therefore keep torch's
spinning threads and change their number instead: inside :func:`follow_free_cpu` every
:data:`INTERVAL` seconds the busy time of this process's cores (``/proc/stat``) is compared with
the process's own CPU time, and the loop runs on one thread per core that other processes leave
free (at least one; at most the count torch had when the loop started). A lone thread waits for
no other, so under load the work keeps its share of the CPU, and on a quiet machine it runs as
torch does. Fewer threads are taken at the first busy look, more only after :data:`CONFIRM`
quiet ones; looks happen between steps, and a loop's first step looks at once (at the time since
the previous sample). Without ``/proc/stat`` (not Linux) nothing changes. It is process-wide
state, so it happens only where the process's owner asked for it
(:func:`torch_ampn.utils.tuning.enable_cpu_tuning`: the command-line programs and the
benchmarks do) or with ``AMPN_THREADS=on``; ``AMPN_THREADS=off`` leaves torch's thread count
alone everywhere.

Compiled code: Inductor builds a CPU kernel for the thread count in use when it compiles. Built
on all the cores' count, its parallel regions take their size from torch's count at run time;
built on one thread, it stays serial. So the package's calls that compile run on the ceiling's
count (:meth:`ThreadGovernor.at_ceiling`). Where torch's count differs from ``os.cpu_count()``
(a container's CPU set, ``OMP_NUM_THREADS``), Inductor writes the count into the kernel, and
compiled kernels keep it.

Results: a different thread count sums some reductions in another order, so the last bits of a
fit or rollout can depend on when other processes ran. For bit-identical reruns use one thread
(``OMP_NUM_THREADS=1``) or ``AMPN_THREADS=off`` on a machine nothing else uses.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch

from torch_ampn.utils.tuning import cpu_tuning_enabled

#: Seconds between two looks at the CPU (a sample of ``/proc/stat``: 50 clock ticks on 2 cores).
INTERVAL = 0.25
#: Cores other processes may use before one of ours counts as taken (system daemons, ``/proc/stat``'s
#: tick sampling): a busy process sharing 2 cores with 2 spinning threads gets about 0.67 of one.
TOLERANCE = 0.3
#: Consecutive looks that must agree before the count grows, so that a lull of the other
#: processes does not bring back threads that would spin against them. It shrinks at the first
#: look: one step with too few threads costs a little, one with too many can cost 40x.
CONFIRM = 2
#: Seconds between loops (a rollout after a training step) for which the last decision holds.
FRESH = 2.0
#: The fields of a ``/proc/stat`` CPU line that count as busy: user nice system irq softirq steal
#: (guest time is part of user already; idle and iowait are free).
BUSY_FIELDS = (0, 1, 2, 5, 6, 7)


def following_free_cpu() -> bool:
    """Whether the package's loops adapt torch's thread count: CPU tuning on, or ``AMPN_THREADS=on``."""
    setting = os.environ.get("AMPN_THREADS", "").lower()
    if setting in ("off", "on"):
        return setting == "on"
    return cpu_tuning_enabled()


class OtherLoad:
    """Cores that other processes used between two calls, from ``/proc/stat``.

    Busy time of the CPUs this process may run on, less this process's own CPU time (all its
    threads), per second of wall time. Steal time (a VM's host running something else) counts
    as other processes' use.

    Args:
        stat: The kernel's CPU statistics file.
        cpus: CPU numbers to count (default: this process's affinity).
        clock: Wall clock (seconds).
        own_time: This process's CPU time (seconds, all threads).
        min_window: Shortest wall time (seconds) a value is given for: a shorter window holds
            too few clock ticks, and is extended to the next call instead.

    The first sample is taken when it is made (at import for the package's governor), so that
    a loop's first look sees the time since then.
    """

    def __init__(
        self,
        stat: str = "/proc/stat",
        cpus: set[int] | None = None,
        clock: Callable[[], float] = time.monotonic,
        own_time: Callable[[], float] = time.process_time,
        min_window: float = 0.1,
    ) -> None:
        self.stat = stat
        self.cpus = set(os.sched_getaffinity(0) if cpus is None else cpus)
        self.clock, self.own_time, self.min_window = clock, own_time, min_window
        self.ticks_per_second = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self._last: tuple[float, float, float] | None = self._sample()

    @property
    def num_cpus(self) -> int:
        """CPUs counted."""
        return len(self.cpus)

    def busy_seconds(self) -> float | None:
        """Busy seconds of :attr:`cpus` since boot (``None``: unreadable, or a CPU missing)."""
        try:
            with open(self.stat) as f:
                lines = f.read().splitlines()
        except OSError:
            return None
        busy, seen = 0, 0
        for line in lines:
            name, _, rest = line.partition(" ")
            if not name.startswith("cpu") or name == "cpu" or int(name[3:]) not in self.cpus:
                continue
            fields = [int(v) for v in rest.split()]
            busy += sum(fields[i] for i in BUSY_FIELDS if i < len(fields))
            seen += 1
        return busy / self.ticks_per_second if seen == len(self.cpus) else None

    def _sample(self) -> tuple[float, float, float] | None:
        busy = self.busy_seconds()
        return None if busy is None else (self.clock(), busy, self.own_time())

    def restart(self) -> None:
        """Start a new window now (the time before it is not counted)."""
        self._last = self._sample()

    def __call__(self) -> float | None:
        """Cores the others used since the previous sample.

        ``None`` where there is none yet, the window is shorter than ``min_window`` (it goes on
        to the next call) or the statistics cannot be read.
        """
        last = self._last
        if last is not None and self.clock() - last[0] < self.min_window:
            return None
        sample = self._last = self._sample()
        if sample is None or last is None:
            return None
        wall, busy, own = (a - b for a, b in zip(sample, last, strict=True))
        return max(0.0, (busy - own) / wall)


class ThreadGovernor:
    """Sets torch's intra-op thread count to the cores other processes leave free.

    :meth:`step` is called once per step of a loop (cheap: a clock read between looks); every
    ``interval`` seconds it looks at :class:`OtherLoad` and sets ``torch.set_num_threads`` to
    ``cores - ceil(others - tolerance)``, clamped to ``[1, ceiling]``: fewer threads at once,
    more after ``confirm`` looks that agree. The ceiling is torch's count when the outermost
    loop starts (the user's choice, ``OMP_NUM_THREADS`` or the core count); a governor with a
    ceiling of one does nothing.

    Args:
        load: Where the others' use comes from.
        interval: Seconds between looks.
        tolerance: Cores others may use before one counts as taken.
        confirm: Looks that must agree before the count grows.
        clock: Wall clock (seconds).
    """

    def __init__(
        self,
        load: Callable[[], float | None] | None = None,
        interval: float = INTERVAL,
        tolerance: float = TOLERANCE,
        confirm: int = CONFIRM,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.load = OtherLoad() if load is None else load
        self.interval, self.tolerance, self.confirm, self.clock = interval, tolerance, confirm, clock
        self.ceiling = 1
        self.depth = 0  # loops inside one another: the outermost sets the ceiling and restores
        #: Counts chosen, ``(wall time, threads)``, last one current (a test's and a benchmark's record).
        self.history: deque[tuple[float, int]] = deque(maxlen=1000)
        #: The looks, ``(wall time, others' cores, threads in use)`` (a benchmark's record).
        self.looks: deque[tuple[float, float, int]] = deque(maxlen=1000)
        self._next_look = -math.inf
        self._streak = 0  # looks in a row that asked for more threads
        self._decision: int | None = None  # the last look's choice
        self._active = -math.inf  # when a loop last stepped or ended

    @property
    def num_cpus(self) -> int:
        """CPUs the load is counted over."""
        return int(getattr(self.load, "num_cpus", os.cpu_count() or 1))

    def target(self, others: float) -> int:
        """Threads for ``others`` cores used by other processes."""
        taken = max(0, math.ceil(others - self.tolerance))
        return max(1, min(self.ceiling, self.num_cpus - taken))

    def step(self) -> int:
        """Look at the CPU if ``interval`` has passed; the thread count in use."""
        now = self._active = self.clock()
        if self.ceiling <= 1 or now < self._next_look:
            return torch.get_num_threads()
        self._next_look = now + self.interval
        others = self.load()
        if others is None:
            return torch.get_num_threads()
        want = self._decision = self.target(others)
        current = torch.get_num_threads()
        self.looks.append((now, others, current))
        self._streak = self._streak + 1 if want > current else 0
        if want < current or self._streak >= self.confirm:
            self._set(want)
            self._streak = 0
        return torch.get_num_threads()

    def _set(self, threads: int) -> None:
        if threads != torch.get_num_threads():
            torch.set_num_threads(threads)
            self.history.append((self.clock(), threads))

    def enter(self) -> int:
        """Start a loop: the outermost takes torch's count as the ceiling.

        Soon after another loop (within :data:`FRESH` seconds) it starts on that loop's last
        decision; else its first step looks at once, at the time since the last sample (the
        import or an earlier loop). Returns the count to restore at :meth:`exit`.
        """
        before = torch.get_num_threads()
        self.depth += 1
        if self.depth > 1:
            return before
        self.ceiling = before
        if before <= 1:
            return before
        now = self.clock()
        if now - self._active <= FRESH and self._decision is not None:
            self._set(min(self._decision, self.ceiling))
        else:
            self._next_look = -math.inf
            self._streak = 0
        self._active = now
        return before

    def exit(self, before: int) -> None:
        """End a loop; the outermost restores torch's count from before it."""
        self.depth -= 1
        self._active = self.clock()
        if self.depth == 0 and torch.get_num_threads() != before:
            torch.set_num_threads(before)

    @contextmanager
    def at_ceiling(self) -> Iterator[None]:
        """Run the block on the ceiling's count.

        For a call that compiles: Inductor builds its C++ kernels for the count in use, and a
        kernel built for one thread stays serial. The next look counts from the block's end, so
        that the compiler's worker processes do not count as others.
        """
        if self.depth == 0:
            yield
            return
        current = torch.get_num_threads()
        if current < self.ceiling:
            torch.set_num_threads(self.ceiling)
        try:
            yield
        finally:
            if current < self.ceiling:
                torch.set_num_threads(current)
            restart = getattr(self.load, "restart", None)
            if restart is not None:
                restart()
                self._next_look = self.clock() + self.interval


#: The process's governor: every loop of the package shares its looks and decisions.
GOVERNOR = ThreadGovernor()


class _Idle:
    """What :func:`follow_free_cpu` yields where nothing is followed."""

    def step(self) -> int:
        return torch.get_num_threads()

    @contextmanager
    def at_ceiling(self) -> Iterator[None]:
        yield


@contextmanager
def follow_free_cpu(device: Any = None) -> Iterator[ThreadGovernor | _Idle]:
    """Run a loop on the threads other processes leave free; call ``.step()`` once per step.

    Yields the process's :data:`GOVERNOR` (``.step()``, ``.at_ceiling()``); torch's count is
    restored when the outermost such block ends. Nothing changes unless the process asked for it
    (:func:`following_free_cpu`), nor for a ``device`` other than the CPU.

    Example::

        with follow_free_cpu() as threads:
            for batch in batches:
                threads.step()
                train_step(batch)
    """
    if not following_free_cpu() or not (device is None or torch.device(device).type == "cpu"):
        yield _Idle()
        return
    before = GOVERNOR.enter()
    try:
        yield GOVERNOR
    finally:
        GOVERNOR.exit(before)
