"""How much of the machine's CPU other processes used while this one worked.

Why
    On a machine of a few cores, a second CPU-heavy job changes every timing. On the project's 2-core
    machine, a training of two threads ran at 0.45 s a step alone and at 5.8 beside the test suite.
    Nothing said so: the figures simply came out wrong. :class:`OtherProcessesLoad` measures it. The
    benchmark commands record it beside their figures, and ``garmentnerf train`` prints it when it ends
    and warns (:class:`BusyWatch`) at its start and at a checkpoint when the machine has become busy.

How
    ``/proc/stat``'s first line counts the time every core spent busy (user, nice, system, irq,
    softirq, steal) since boot. This process's own CPU time (:func:`os.times`, all its threads) is
    taken out. What is left, over the wall time between two readings, is the number of cores other
    processes kept busy. Where ``/proc/stat`` is missing (not Linux), every figure is None.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["BUSY_CORES", "BusyWatch", "CpuReading", "OtherProcessesLoad", "busy_machine_warning", "cores_used_by_others",
           "load_report", "read_cpu"]

#: ``/proc/stat``'s columns (after the label) that count busy time: user, nice, system, irq,
#: softirq, steal. Not idle or iowait; guest time is already inside user.
_BUSY_COLUMNS = (0, 1, 2, 5, 6, 7)
#: Other processes' load, in cores, above which a timing is called disturbed.
BUSY_CORES = 0.5


@dataclass(frozen=True)
class CpuReading:
    """One reading of the machine's and this process's CPU time, in seconds."""

    machine_busy_s: float
    """Busy time of all cores together since boot."""
    own_s: float
    """This process's user + system time (all its threads; not its children's)."""
    wall_s: float
    """:func:`time.monotonic` when it was read."""


def read_cpu(stat_file: str | Path = "/proc/stat") -> CpuReading | None:
    """The machine's busy time and this process's CPU time now; None without ``stat_file``."""
    try:
        first = Path(stat_file).read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    if not first or first[0] != "cpu":
        return None
    ticks = [int(v) for v in first[1:]]
    busy = sum(ticks[i] for i in _BUSY_COLUMNS if i < len(ticks))
    own = os.times()
    return CpuReading(busy / os.sysconf("SC_CLK_TCK"), own.user + own.system, time.monotonic())


def cores_used_by_others(start: CpuReading, end: CpuReading) -> float | None:
    """Cores other processes kept busy on average between two readings (>= 0); None when less
    than 0.1 s passed (too few clock ticks to tell)."""
    wall = end.wall_s - start.wall_s
    if wall < 0.1:
        return None
    others = (end.machine_busy_s - start.machine_busy_s) - (end.own_s - start.own_s)
    return max(0.0, others / wall)


class OtherProcessesLoad:
    """Other processes' load over a stretch of work, in cores.

    ``with OtherProcessesLoad() as load: work()`` and then ``load.cores``, or :meth:`so_far` during
    the work. ``cores`` is None where the machine cannot be read, or over less than 0.1 s.
    """

    def __init__(self, stat_file: str | Path = "/proc/stat") -> None:
        self.stat_file = stat_file
        self.start = read_cpu(stat_file)
        self.cores: float | None = None

    def so_far(self) -> float | None:
        """Other processes' cores on average from the start until now."""
        now = read_cpu(self.stat_file)
        if self.start is None or now is None:
            return None
        return cores_used_by_others(self.start, now)

    def stop(self) -> float | None:
        """Ends the measurement; returns (and keeps in :attr:`cores`) its figure."""
        self.cores = self.so_far()
        return self.cores

    def __enter__(self) -> "OtherProcessesLoad":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def busy_machine_warning(cores: float | None, threads: int, what: str) -> str | None:
    """A one-line warning when other processes used more than :data:`BUSY_CORES` cores and, with
    ``threads`` of this process's own, the machine's cores are oversubscribed; else None."""
    total = os.cpu_count() or 1
    if cores is None or cores <= BUSY_CORES or cores + threads <= total:
        return None
    return (f"other processes are using {cores:.1f} of this machine's {total} cores: with {threads} thread"
            f"{'s' if threads != 1 else ''} of its own, {what} will run slower until they stop")


class BusyWatch:
    """Warns once each time other processes start to oversubscribe the machine during long work.

    Each :meth:`check` measures other processes' load since the previous one (or since the watch
    was made) and returns :func:`busy_machine_warning`'s line when that stretch was busy and the one
    before it was not; otherwise None. A stretch shorter than 0.1 s is not judged: it carries on
    into the next check.

    Args:
        threads: this process's own threads.
        what: the work, as the warning names it ("this training").
    """

    def __init__(self, threads: int, what: str, stat_file: str | Path = "/proc/stat") -> None:
        self.threads = int(threads)
        self.what = what
        self.stat_file = stat_file
        self._stretch = OtherProcessesLoad(stat_file)
        self._busy = False

    def check(self) -> str | None:
        cores = self._stretch.so_far()
        if cores is None:
            return None
        self._stretch = OtherProcessesLoad(self.stat_file)
        warning = busy_machine_warning(cores, self.threads, self.what)
        was_busy, self._busy = self._busy, warning is not None
        return None if was_busy else warning


def load_report(cores: float | None) -> str:
    """The line a benchmark prints under its figures: what other processes took of the machine
    while it ran, and whether that makes the figures slower than the machine's own."""
    if cores is None:
        return "other processes' load: not measured on this system"
    line = f"other processes used {cores:.2f} of this machine's {os.cpu_count() or 1} cores on average while it ran"
    if cores > BUSY_CORES:
        line += ": these figures are slower than the machine's own (measure again on a quiet machine)"
    return line
