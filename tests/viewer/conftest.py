"""Fixtures shared by the viewer tests (``test_viewer.py``, ``test_viewer_export.py``): an Xvfb server for
the real window, and the tiny untrained run the neural layer shows."""

from __future__ import annotations

import os
import shutil
import subprocess
import time

import pytest


@pytest.fixture(scope="session")
def xvfb():
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.skip("Xvfb is not installed (apt-get install xvfb; .ci/run installs it)")
    read_fd, write_fd = os.pipe()
    proc = subprocess.Popen([exe, "-displayfd", str(write_fd), "-screen", "0", "1280x1024x24", "-nolisten", "tcp",
                             "-noreset"], pass_fds=(write_fd,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write_fd)
    number = b""
    deadline = time.monotonic() + 20
    try:
        import select

        while not number.endswith(b"\n") and time.monotonic() < deadline:
            ready, _, _ = select.select([read_fd], [], [], 0.5)
            if ready:
                chunk = os.read(read_fd, 16)
                if not chunk:
                    break
                number += chunk
        if not number.strip():
            raise RuntimeError("Xvfb did not report its display number")
        display = f":{number.decode().strip()}"
        old = {k: os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY")}
        os.environ["DISPLAY"] = display
        os.environ.pop("WAYLAND_DISPLAY", None)
        yield display
    finally:
        os.close(read_fd)
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        for k, v in locals().get("old", {}).items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.fixture(scope="module")
def untrained_run(tiny_scene, tmp_path_factory):
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.runs import create_untrained_run

    return create_untrained_run(tmp_path_factory.mktemp("viewer_run") / "run", tiny_scene.root, ModelConfig.tiny())
