"""The command line: real outputs, and one-line errors with a non-zero exit for bad input."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from garmentnerf.body.model import BodyModel
from garmentnerf.cli.main import main
from garmentnerf.motion.library import load_motion

REPO = Path(__file__).resolve().parents[1]


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_body_export_writes_the_posed_body(tmp_path, capsys):
    out = tmp_path / "body.ply"
    code, stdout, _ = run_cli(capsys, "body", "export", "--motion", "walk", "--frame", "10", "--shape", "round", "--out", str(out))
    assert code == 0 and "wrote" in stdout
    mesh = trimesh.load(out, process=False)
    body = BodyModel.default()
    betas = body.betas("round")
    expected = load_motion("walk", body, betas=betas).slice(10, 11).pose(body, betas).vertices[0].numpy()
    np.testing.assert_allclose(mesh.vertices, expected, atol=1e-5)
    assert mesh.faces.shape == (27420, 3)
    # never overwrite without being asked
    code, _, err = run_cli(capsys, "body", "export", "--motion", "walk", "--out", str(out))
    assert code == 2 and "already exists" in err and err.count("\n") == 1


def test_maps_command_writes_documented_keys(tmp_path, capsys):
    out = tmp_path / "maps.npz"
    code, _, _ = run_cli(capsys, "maps", "--motion", "walk", "--frame", "30", "--out", str(out), "--png", str(tmp_path / "m.png"))
    assert code == 0
    with np.load(out) as data:
        assert data["normal"].shape == (128, 128, 3) and data["normal"].dtype == np.float32
        assert data["velocity"].shape == (128, 128, 6)
        assert data["mask"].shape == (128, 128) and data["mask"].dtype == bool
        n = data["normal"][data["mask"]]
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)
        assert np.abs(data["velocity"][data["mask"]]).max() > 0.01  # walking: the body moves
    assert (tmp_path / "m.png").stat().st_size > 1000


def test_motion_list_shows_clips(capsys):
    code, out, _ = run_cli(capsys, "motion", "list")
    assert code == 0
    for name in ("walk", "run", "dance_a", "dance_b", "spinkick", "backflip"):
        assert name in out


@pytest.mark.parametrize("argv, message", [
    (["body", "export", "--motion", "moonwalk", "--out", "x.ply"], "unknown motion 'moonwalk'"),
    (["body", "export", "--motion", "walk", "--frame", "100000", "--out", "x.ply"], "out of range"),
    (["body", "export", "--motion", "walk", "--frame", "-1", "--out", "x.ply"], "out of range"),
    (["body", "export", "--shape", "chubby", "--out", "x.ply"], "unknown body shape 'chubby'"),
    (["body", "export", "--out", "x.stl"], "unsupported mesh format"),
    (["maps", "--history", "99", "--out", "m.npz"], "--history"),
])
def test_bad_input_gets_one_line_error(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli(capsys, *argv)
    assert code == 2
    assert message in err
    assert err.startswith("garmentnerf: error:") and err.count("\n") == 1


def test_corrupt_asset_and_bad_smpl_file_are_reported(tmp_path, capsys):
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 broken")
    code, _, err = run_cli(capsys, "body", "info", "--body", str(corrupt))
    assert code == 2 and "corrupt.npz" in err and err.count("\n") == 1
    smpl = tmp_path / "SMPL_BAD.npz"
    np.savez(smpl, v_template=np.zeros((10, 2)), f=np.zeros((4, 3), dtype=np.int64))
    code, _, err = run_cli(capsys, "body", "info", "--body", str(smpl))
    assert code == 2 and "SMPL_BAD.npz" in err and err.count("\n") == 1


def test_console_script_runs_without_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "body", "export", "--motion", "nope",
                           "--out", str(tmp_path / "b.ply")], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and "unknown motion 'nope'" in proc.stderr


def test_wheel_ships_shaders_and_assets(tmp_path):
    """A non-editable install must find the GLSL and the body asset."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path)], check=True)
    wheel = next(tmp_path.glob("garmentnerf-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    shaders = sorted(p.name for p in (REPO / "garmentnerf" / "shaders").iterdir() if p.suffix in (".vert", ".frag", ".glsl"))
    assert shaders and all(f"garmentnerf/shaders/{s}" in names for s in shaders)
    assert "garmentnerf/assets/anny_body_v1.npz" in names
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)], check=True)
    code = ("import garmentnerf, garmentnerf.gl.shaders as s, garmentnerf.body.asset as a;"
            "assert 'site' in garmentnerf.__file__, garmentnerf.__file__;"
            f"assert 'void main' in s.shader_source('{shaders[0]}');"
            "print(a.BodyAsset.load(a.default_asset_path()).num_vertices)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(site)})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "13718"


def test_smpl_like_motion_on_anny_body_is_rejected(tmp_path, capsys):
    amass = tmp_path / "clip.npz"
    np.savez(amass, poses=np.zeros((5, 72)), trans=np.zeros((5, 3)), mocap_framerate=np.array(30.0), betas=np.zeros(10))
    code, _, err = run_cli(capsys, "body", "export", "--motion", str(amass), "--out", str(tmp_path / "x.ply"))
    assert code == 2 and "smpl" in err and err.count("\n") == 1


def test_the_executable_reports_a_native_crash_with_the_python_stack():
    """``garmentnerf`` (:func:`~garmentnerf.cli.main.run`) turns Python's fault handler on: a crash
    in native code prints the Python stack it happened under; plain ``main()`` does not."""
    crash = ("import ctypes, sys; import garmentnerf.cli.main as cli; "
             "cli.main = lambda: ctypes.string_at(0); cli.{}()")
    for entry, reported in (("run", True), ("main", False)):
        proc = subprocess.run([sys.executable, "-c", crash.format(entry)], capture_output=True, text=True,
                              timeout=120, env={k: v for k, v in os.environ.items() if k != "PYTHONFAULTHANDLER"})
        assert proc.returncode < 0  # killed by the signal
        assert ("Fatal Python error: Segmentation fault" in proc.stderr) is reported, proc.stderr
        assert ("in <lambda>" in proc.stderr) is reported
