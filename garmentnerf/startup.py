"""Seconds since the command started: the clock of ``garmentnerf view --bench``'s ``first_frame`` figures.

The command's start is the process's start (Linux: ``starttime`` in ``/proc/self/stat``, in clock
ticks since boot, against ``CLOCK_BOOTTIME``: the same clock), so the interpreter's own start-up and
every import count. Where ``/proc`` is missing the clock starts when this module is first imported,
which the command line does before anything else (:mod:`garmentnerf.cli.main`).

It also keeps one reading of the machine's CPU time taken then (:data:`START_CPU`), so a figure
measured from the start can say how busy other processes kept the machine meanwhile
(:func:`other_cores_since_start`).

No heavy import here: this module loads before torch and the window libraries.
"""

from __future__ import annotations

import os
import time

from garmentnerf.cpu_load import CpuReading, cores_used_by_others, read_cpu

#: :func:`time.monotonic` when this module was imported (the fallback start).
IMPORTED_AT = time.monotonic()
#: The machine's and this process's CPU time when this module was imported (None without /proc).
START_CPU: CpuReading | None = read_cpu()


def _process_age(stat_file: str = "/proc/self/stat") -> float | None:
    """Seconds since this process started, from ``/proc`` (None where it cannot be read)."""
    try:
        with open(stat_file, encoding="ascii") as f:
            text = f.read()
        # "pid (comm) state ppid ...": comm may hold spaces and parentheses, so split after the last ')'
        fields = text.rsplit(")", 1)[1].split()
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22, starttime
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - started)
    except (OSError, IndexError, ValueError, AttributeError):
        return None


#: How old the process was at import (None without /proc): the offset of the monotonic clock.
_AGE_AT_IMPORT = _process_age()


def seconds_since_start() -> float:
    """Seconds since the process started (since this module's import where ``/proc`` is missing)."""
    since_import = time.monotonic() - IMPORTED_AT
    return since_import + (_AGE_AT_IMPORT if _AGE_AT_IMPORT is not None else 0.0)


def other_cores_since_start() -> float | None:
    """Cores other processes kept busy on average since the start (None without ``/proc/stat``).
    The interval begins at this module's import, a fraction of a second after the process start."""
    now = read_cpu()
    if START_CPU is None or now is None:
        return None
    return cores_used_by_others(START_CPU, now)


__all__ = ["IMPORTED_AT", "START_CPU", "other_cores_since_start", "seconds_since_start"]
