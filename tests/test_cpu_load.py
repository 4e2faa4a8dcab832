"""Other processes' CPU load (garmentnerf.cpu_load): /proc/stat read by hand, the arithmetic, and a
real busy process told apart from this one's own work."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from garmentnerf.cpu_load import (
    BUSY_CORES,
    BusyWatch,
    CpuReading,
    OtherProcessesLoad,
    busy_machine_warning,
    cores_used_by_others,
    read_cpu,
)

LINUX = Path("/proc/stat").is_file()


def test_read_cpu_sums_the_busy_columns(tmp_path):
    stat = tmp_path / "stat"
    # user nice system idle iowait irq softirq steal guest guest_nice
    stat.write_text("cpu  100 20 30 9000 500 4 6 10 7 0\ncpu0 50 10 15 4500 250 2 3 5 3 0\nintr 1 2 3\n")
    reading = read_cpu(stat)
    hz = os.sysconf("SC_CLK_TCK")
    assert reading.machine_busy_s == pytest.approx((100 + 20 + 30 + 4 + 6 + 10) / hz)  # not idle, iowait or guest
    times = os.times()
    assert reading.own_s == pytest.approx(times.user + times.system, abs=0.05)
    assert read_cpu(tmp_path / "missing") is None
    (tmp_path / "odd").write_text("intr 1 2 3\n")
    assert read_cpu(tmp_path / "odd") is None


def test_cores_used_by_others_subtracts_this_process():
    start = CpuReading(machine_busy_s=100.0, own_s=5.0, wall_s=10.0)
    # 2 s of wall: the machine was busy 3.5 core-seconds, 1.5 of them this process's
    assert cores_used_by_others(start, CpuReading(103.5, 6.5, 12.0)) == pytest.approx(1.0)
    assert cores_used_by_others(start, CpuReading(100.2, 5.4, 12.0)) == 0.0  # clock-tick rounding: never < 0
    assert cores_used_by_others(start, CpuReading(101.0, 5.0, 10.05)) is None  # too short to tell


def test_busy_machine_warning_only_when_oversubscribed(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    assert busy_machine_warning(None, 2, "x") is None
    assert busy_machine_warning(BUSY_CORES, 4, "x") is None  # a trace of load is no warning
    assert busy_machine_warning(1.5, 2, "x") is None  # 1.5 + 2 threads fit in 4 cores
    text = busy_machine_warning(2.5, 2, "this training")
    assert text == ("other processes are using 2.5 of this machine's 4 cores: with 2 threads of its own, "
                    "this training will run slower until they stop")
    assert "with 1 thread of its own" in busy_machine_warning(3.9, 1, "x")


def _spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


@pytest.mark.skipif(not LINUX, reason="reads /proc/stat")
def test_a_busy_process_beside_counts_and_this_ones_own_work_does_not():
    with OtherProcessesLoad() as own_work:
        _spin(1.0)
    child = subprocess.Popen([sys.executable, "-c", "import time\nend = time.time() + 30\nwhile time.time() < end: pass"])
    try:
        time.sleep(0.3)  # the child is running
        with OtherProcessesLoad() as beside:
            time.sleep(1.0)
    finally:
        child.kill()
        child.wait()
    # one core kept busy by the child (less what the machine's scheduler gives others), none by our spin
    assert beside.cores - own_work.cores > 0.6, (beside.cores, own_work.cores)
    assert own_work.cores < beside.cores


def test_busy_watch_warns_once_each_time_the_machine_becomes_busy(tmp_path, monkeypatch):
    """A /proc/stat written by the test: stretches of two busy cores, then a quiet one, then busy again."""
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    hz = os.sysconf("SC_CLK_TCK")
    stat = tmp_path / "stat"
    busy_ticks = [0]

    def advance(cores: float, seconds: float = 0.2) -> None:
        """Sleep ``seconds`` while the file says ``cores`` cores were busy meanwhile."""
        time.sleep(seconds)
        busy_ticks[0] += round(cores * seconds * hz)
        stat.write_text(f"cpu  {busy_ticks[0]} 0 0 100000 0 0 0 0 0 0\n")

    advance(0.0, 0.0)
    watch = BusyWatch(1, "this work", stat)
    assert watch.check() is None  # less than 0.1 s: not judged, the stretch carries on
    advance(2.0)
    assert re.fullmatch(r"other processes are using (?:1\.[6-9]|2\.0) of this machine's 2 cores: with 1 thread of its own, "
                        r"this work will run slower until they stop", watch.check() or "")
    advance(2.0)
    assert watch.check() is None  # still busy: said once
    advance(0.0)
    assert watch.check() is None  # quiet again
    advance(1.5)
    assert watch.check() is not None  # busy once more: said again
