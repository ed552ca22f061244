"""Choosing the number of compute threads from measured step times, for machines whose cores are shared.

On the project's 2-core machines a training step with 2 OpenMP threads is the fastest when the
machine is quiet (135 ms against 188 ms with 1 thread), and the slowest when another busy process
shares the cores (555 ms against 217 ms): a spinning thread waits for its partner, which the other
process has descheduled. A passive wait policy does not fix it (228 ms quiet, 284 ms loaded).
BENCHMARKS.md, "Threads on a shared machine", has the table.

``ThreadGovernor`` therefore measures instead of guessing: every ``period`` steps it times
``probe`` real steps at each candidate thread count and keeps the fastest until the next probe, or
probes again at once when ``slow_steps`` steps in a row take far longer than the last probe said they
would. A probe that confirms the choice before it doubles the wait before the next (up to
``max_period``), since under a lasting load every probe pays for its steps at the slow count; a
changed choice or a load change brings the wait back to ``period``. Within a probe, a candidate whose first step
takes ``cut_factor`` times the median of one already timed in full gets no more steps: under a load the 2-thread steps
are 2.6x slower, and each one a probe spends on them is lost. Nothing is run twice: the probe
steps are ordinary steps. The thread count changes float rounding (1 and 2 threads
give gradients ~1e-7 apart), so a run that uses it is not bit-reproducible; fixed counts are.
"""

from __future__ import annotations

import statistics
from typing import Callable


class ThreadGovernor:
    """Picks, among ``candidates``, the thread count whose recent steps were fastest.

    Call ``before_step()`` before each step (it sets the count) and ``after_step(seconds)`` after it.

    Args:
        candidates: thread counts to try, e.g. ``(1, 2)``.
        period: steps between two probes, at first and after a change.
        probe: steps timed per candidate in a probe (the median is compared).
        slow_factor: ``slow_steps`` steps in a row this many times slower than the chosen count's probe
            median start a new probe early (the machine's load changed).
        max_period: the longest wait between probes, reached by doubling ``period`` after each probe
            that keeps the choice (``period``: no backoff).
        slow_steps: consecutive slow steps that start an early probe (1: any single one, which a
            scheduler hiccup under load also gives).
        cut_factor: a probe's candidate whose first step is this many times slower than the median of a candidate
            already timed in full is not timed further (``None``: every candidate gets ``probe`` steps).
        set_threads: applies a count (``torch.set_num_threads`` by default; a test passes a fake).
    """

    def __init__(self, candidates: tuple[int, ...], period: int = 200, probe: int = 3, slow_factor: float = 2.0,
                 set_threads: Callable[[int], None] | None = None, max_period: int = 1600, slow_steps: int = 2,
                 cut_factor: float | None = 1.5) -> None:
        if not candidates or any(c <= 0 for c in candidates):
            raise ValueError(f"candidates must be positive thread counts, got {candidates}")
        if period <= 0 or probe <= 0 or slow_factor <= 1:
            raise ValueError(f"period and probe must be positive and slow_factor > 1, got {period}, {probe}, {slow_factor}")
        if max_period < period or slow_steps <= 0:
            raise ValueError(f"max_period must be at least period and slow_steps positive, got {max_period} and {slow_steps}")
        if cut_factor is not None and cut_factor <= 1:
            raise ValueError(f"cut_factor must be above 1 (or None), got {cut_factor}")
        if set_threads is None:
            import torch

            set_threads = torch.set_num_threads
        self.candidates = tuple(dict.fromkeys(candidates))
        self.period, self.probe, self.slow_factor = period, probe, slow_factor
        self.max_period, self.slow_steps, self.cut_factor = max_period, slow_steps, cut_factor
        # steps from one probe to the next, doubling while probes keep the choice; 0 before the first probe
        # and during an early one, so that the wait after it is `period`
        self._wait = 0
        self._slow = 0  # slow steps in a row
        self._set = set_threads
        self._times: dict[int, list[float]] = {}
        self._queue: list[int] = []  # the probe's remaining steps, one thread count each
        self.choice = self.candidates[-1]
        self._expected = float("inf")
        self._since_probe = 0
        self._current: int | None = None
        self.history: list[tuple[int, dict[int, float]]] = []
        """``(step index, {threads: median seconds})`` of every finished probe."""
        self._steps = 0
        self._start_probe()

    def _start_probe(self) -> None:
        self._times = {c: [] for c in self.candidates}
        self._queue = [c for c in self.candidates for _ in range(self.probe)]

    def _hopeless(self, seconds: float) -> bool:
        """Whether a first probe step of ``seconds`` is ``cut_factor`` times slower than a fully timed candidate."""
        done = [statistics.median(t) for t in self._times.values() if len(t) == self.probe]
        return self.cut_factor is not None and bool(done) and seconds > self.cut_factor * min(done)

    def before_step(self) -> int:
        """Set (and return) the thread count for the next step."""
        n = self._queue[0] if self._queue else self.choice
        if n != self._current:
            self._set(n)
            self._current = n
        return n

    def after_step(self, seconds: float) -> None:
        """Record the step just run (with the count ``before_step`` set)."""
        self._steps += 1
        if self._queue:
            n = self._queue.pop(0)
            self._times[n].append(seconds)
            if len(self._times[n]) == 1 and self._hopeless(seconds):
                self._queue = [c for c in self._queue if c != n]
            if not self._queue:
                medians = {c: statistics.median(t) for c, t in self._times.items()}
                choice = min(medians, key=medians.get)
                kept = self._wait > 0 and choice == self.choice
                self._wait = min(2 * self._wait, self.max_period) if kept else self.period
                self.choice = choice
                self._expected = medians[self.choice]
                self.history.append((self._steps, medians))
                self._since_probe = 0
                self._slow = 0
            return
        self._since_probe += 1
        self._slow = self._slow + 1 if seconds > self.slow_factor * self._expected else 0
        if self._slow >= self.slow_steps:  # the load changed: probe now, and wait `period` after it
            self._wait = 0
            self._start_probe()
        elif self._since_probe >= self._wait:
            self._start_probe()


def cpu_ticks(stat_text: str) -> tuple[int, int, int] | None:
    """``(cpus, total ticks, idle ticks)`` from the text of ``/proc/stat`` (idle counts iowait too); ``None`` if it is
    not in that format."""
    lines = stat_text.splitlines()
    head = lines[0].split() if lines else []
    if len(head) < 6 or head[0] != "cpu" or not all(v.isdigit() for v in head[1:9]):
        return None
    ticks = [int(v) for v in head[1:9]]
    cpus = sum(1 for line in lines if line.startswith("cpu") and line[3:4].isdigit())
    return cpus, sum(ticks), ticks[3] + ticks[4]


def busy_between(a: tuple[int, int, int], b: tuple[int, int, int]) -> float | None:
    """Cores kept busy between two ``cpu_ticks`` reads (``None`` if no time passed or the CPU count changed)."""
    if a[0] != b[0] or b[1] <= a[1]:
        return None
    total, idle = b[1] - a[1], b[2] - a[2]
    return a[0] * (total - idle) / total


def busy_cores(window_s: float = 0.1, stat: str = "/proc/stat") -> float | None:
    """How many of this machine's cores other processes kept busy over the next ``window_s`` seconds (this process
    sleeps meanwhile), from two reads of ``/proc/stat``; ``None`` where that cannot be read, or where it counts other
    cores than this process may run on (a container that sees the host's)."""
    import os
    import time

    def read() -> tuple[int, int, int] | None:
        try:
            with open(stat) as f:
                return cpu_ticks(f.read())
        except OSError:
            return None

    if not hasattr(os, "sched_getaffinity"):
        return None
    a = read()
    if a is None or a[0] != len(os.sched_getaffinity(0)):
        return None
    time.sleep(window_s)
    b = read()
    return None if b is None else busy_between(a, b)


def threads_for_load(cores: int, busy: float | None, default: int) -> int:
    """Compute threads for a command that starts now: ``default`` (torch's choice) on a quiet machine, fewer where other
    processes keep cores busy (``busy``, e.g. ``busy_cores()``), never under 1.

    A spinning OpenMP thread whose partner's core is taken waits for it: on this project's 2-core machines an
    evaluation with 2 threads beside a 2-thread training job ran up to 30x slower than alone (BENCHMARKS.md, "Threads
    on a shared machine"), where one thread would have taken the free share of the cores. So a command takes only
    the cores left free, rounded: with 2 cores, 2 threads while others keep under half a core busy, else 1.
    ``busy=None`` (unknown) keeps ``default``."""
    if busy is None:
        return default
    free = int(cores - busy + 0.5)
    return max(1, min(default, free))


follow_ceiling: int | None = None
"""The thread count a command may go back up to when the load falls (torch's own, recorded by the command line when it
took the free cores at its start); ``None``: the count is not followed (a library call, or a count set by
``PRISMONET_THREADS`` or ``OMP_NUM_THREADS``)."""


def follow_load(busy: Callable[[], float | None] | None = None) -> int | None:
    """Between long units of work (a distillation chunk): take the cores other processes leave free now
    (``threads_for_load``), up to ``follow_ceiling``, so that a command that started beside a busy process does not stay
    on one thread for hours after it ends. Returns the new count where it changed, else ``None`` (also where it is not
    followed). ``busy``: the load measure (``busy_cores`` by default)."""
    import os
    import time

    import torch

    if follow_ceiling is None or not hasattr(os, "sched_getaffinity"):
        return None
    wall, cpu = time.perf_counter(), time.process_time()
    load = (busy or busy_cores)()
    if load is None:
        return None
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    if busy is None and wall > 0:  # this process's own threads (OpenMP workers still spinning after a chunk) are not others'
        load = max(0.0, load - cpu / wall)
    n = threads_for_load(len(os.sched_getaffinity(0)), load, follow_ceiling)
    if n == torch.get_num_threads():
        return None
    torch.set_num_threads(n)
    return n


def use_free_cores(exit_on_error: bool = False) -> None:
    """Use only the cores other processes leave free (``threads_for_load``): two spinning threads beside a busy process
    are slower than one. ``PRISMONET_THREADS=N`` sets the count (``ValueError`` for anything but a positive whole
    number, or with ``exit_on_error`` one line on stderr and exit status 2, as a script should); with
    ``OMP_NUM_THREADS`` set, torch's count is left as it is. Every ``prismonet`` command calls it at its start, and so
    do the scripts that run models (``scripts/``); commands that choose their own count (``train``'s ``threads``,
    ``bench``) still do."""
    import os
    import sys

    import torch

    global follow_ceiling
    forced = os.environ.get("PRISMONET_THREADS", "").strip()
    if forced:
        if not forced.isdigit() or int(forced) < 1:
            message = f"PRISMONET_THREADS must be a positive whole number, got {forced!r}"
            if exit_on_error:
                print(f"{os.path.basename(sys.argv[0])}: error: {message}", file=sys.stderr)
                raise SystemExit(2)
            raise ValueError(message)
        torch.set_num_threads(int(forced))
        return
    if os.environ.get("OMP_NUM_THREADS"):
        return
    default = torch.get_num_threads()
    if default < 2:
        return
    follow_ceiling = default  # long commands follow the load up to it (follow_load)
    busy = busy_cores()  # None where it cannot be measured (no /proc/stat, or no sched_getaffinity): keep torch's count
    if busy is None:
        return
    n = threads_for_load(len(os.sched_getaffinity(0)), busy, default)
    if n < default:
        print(f"prismonet: other processes keep {busy:.1f} cores busy: running on {n} thread{'s' * (n > 1)} "
              f"(PRISMONET_THREADS=N to choose)", file=sys.stderr)
        torch.set_num_threads(n)
