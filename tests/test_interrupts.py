"""SIGINT/SIGTERM deferred over work that must finish (:mod:`garmentnerf.interrupts`): the signal
acts once the body ends, the handlers come back, and the body projection's threaded KD-tree query
(scipy joins its threads where a Ctrl-C could land, then frees arrays they still write: a
segfault the training kill test hit) runs whole before a Ctrl-C acts."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest
import torch
import trimesh

from garmentnerf.geometry.projection import SurfaceProjector
from garmentnerf.interrupts import Interrupted, deferred_interrupts, interrupting


@pytest.fixture(autouse=True)
def python_sigint():
    """SIGINT raising KeyboardInterrupt, as in a terminal, also where the suite was started with
    SIGINT ignored (a background job of a shell without job control)."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def busy_python(n: int = 20000) -> int:
    """Python bytecode to run, where a pending KeyboardInterrupt would otherwise be raised."""
    total = 0
    for i in range(n):
        total += i
    return total


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_in_the_body_acts_after_it(sig):
    def on_term(signum, frame):
        raise KeyboardInterrupt

    before_int, before_term = signal.getsignal(signal.SIGINT), signal.signal(signal.SIGTERM, on_term)
    try:
        finished = False
        with pytest.raises(KeyboardInterrupt):
            with deferred_interrupts():
                os.kill(os.getpid(), sig)
                busy_python()
                finished = True
        assert finished
        assert signal.getsignal(signal.SIGINT) is before_int and signal.getsignal(signal.SIGTERM) is on_term
        # nothing is left pending: the next block runs without an interrupt
        with deferred_interrupts():
            busy_python()
    finally:
        signal.signal(signal.SIGTERM, before_term)


def test_without_a_signal_and_off_the_main_thread_it_only_runs_the_body():
    with deferred_interrupts():
        assert busy_python(10) == 45
    results = []

    def worker():
        with deferred_interrupts():
            results.append(busy_python(10))

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert results == [45]


def test_a_ctrl_c_during_the_projections_search_acts_after_the_round_of_launches(monkeypatch):
    """A SIGINT sent while the search kernel runs (from inside warp's launch) is raised once that
    launch has returned, before the next round of points: the kernel is never abandoned
    half-written, and a long projection still stops within a round."""
    import warp

    from garmentnerf.geometry import face_bvh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    projector = SurfaceProjector(torch.as_tensor(mesh.faces), len(mesh.vertices), chunk_size=500, threads=1)
    surface = projector.bind(torch.as_tensor(mesh.vertices, dtype=torch.float32))
    points = torch.as_tensor(np.random.default_rng(0).normal(size=(2000, 3)), dtype=torch.float32)
    expected = surface.project(points).distance
    search = face_bvh._kernels().nearest_faces  # warp imported and the kernels defined before launch is wrapped
    launch, returned = warp.launch, []

    def signalling_launch(kernel, *args, **kwargs):  # a Ctrl-C as each launch of the search starts
        if kernel is not search:  # the walk order's codes, before the search
            return launch(kernel, *args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)
        result = launch(kernel, *args, **kwargs)
        returned.append(True)
        return result

    monkeypatch.setattr(warp, "launch", signalling_launch)
    with pytest.raises(KeyboardInterrupt):
        surface.project(points)
    assert len(returned) == 1  # the first round ran whole; the interrupt came after it, before the second
    monkeypatch.setattr(warp, "launch", launch)
    torch.testing.assert_close(surface.project(points).distance, expected)  # the surface still answers the same


#: A program whose SIGINT lands inside an ``exec()`` of a string (as in a lazy import that builds a
#: dataclass), which catches the interrupt and exits with 130: with Python's own handler
#: (``plain``) or under :func:`interrupting` (``ours``). Run with ``python -m``, as ``garmentnerf``
#: is (with ``-c`` or a script path, CPython exits before it looks at the mark).
EXEC_INTERRUPTED = textwrap.dedent("""
    import os, signal, sys
    from garmentnerf.interrupts import interrupting

    def work():
        try:
            exec("os.kill(os.getpid(), signal.SIGINT)\\nfor _ in range(10 ** 7): pass")
        except KeyboardInterrupt:
            return 130
        return 0

    if sys.argv[1] == "ours":
        with interrupting():
            status = work()
    else:
        status = work()
    sys.exit(status)
""")


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("handler, status", [("plain", -signal.SIGINT), ("ours", 130)])
def test_an_interrupt_caught_after_it_left_an_exec_ends_with_the_chosen_status(tmp_path, handler, status):
    """CPython ends a process by SIGINT at exit when a plain KeyboardInterrupt left an ``exec()``,
    even though the program caught it (``plain``: the reference behaviour, exit -2);
    :class:`Interrupted` keeps the status the program chose. ``garmentnerf train`` hit this."""
    (tmp_path / "exec_interrupted.py").write_text(EXEC_INTERRUPTED)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    proc = subprocess.run([sys.executable, "-m", "exec_interrupted", handler], capture_output=True, text=True,
                          timeout=120, preexec_fn=_default_sigint, env=env)
    assert proc.returncode == status, proc.stderr


def test_interrupting_raises_interrupted_and_restores_the_handlers():
    before_term = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted, match="SIGTERM"):
        with interrupting():
            os.kill(os.getpid(), signal.SIGTERM)
            busy_python()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.getsignal(signal.SIGTERM) is before_term
    # an ignored signal stays ignored
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with interrupting(signal.SIGINT):
        os.kill(os.getpid(), signal.SIGINT)
        assert busy_python(10) == 45
