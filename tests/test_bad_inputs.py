"""Every command against a table of bad inputs, as a hostile tester would: each must end with exit
code 2, exactly one line on stderr that names the file or flag at fault, no traceback, and every
file that existed before byte-identical afterwards (nothing a user made is lost or overwritten).

Placeholders in the table are filled from a small world made once per module: ``{run}`` an
untrained run of the tiny scene, ``{scene}`` the scene, ``{file}`` / ``{json}`` / ``{md}`` /
``{png}`` / ``{ply}`` / ``{npz}`` existing files, ``{dir}`` an existing folder, ``{new}`` a path
that does not exist yet, ``{orphan}`` a run whose scene folder is gone, ``{nan_scene}`` a scene
whose camera K holds a NaN, ``{broken_scene}`` a scene with a sequence file that is not an npz,
``{taken}`` a render folder that already holds frame 0, ``{far}`` a motion file whose root is 1e20 m away
(float32 holds every vertex of the posed body as one point).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
import torch

from garmentnerf.cli.main import main
from garmentnerf.model.config import ModelConfig

CASES = [
    # --- render -------------------------------------------------------------------------------------
    (["render", "--run", "{run}", "--out", "{file}"], "--out"),
    (["render", "--run", "{run}", "--out", "{file}/sub"], "is a file, not a folder"),
    (["render", "--run", "{run}", "--device", "potato", "--out", "{new}"], "--device 'potato'"),
    (["render", "--run", "{run}", "--device", "cuda:7", "--out", "{new}"], "--device cuda:7"),
    (["render", "--run", "{run}", "--palette", ",", "--out", "{new}"], "--palette"),
    (["render", "--run", "{run}", "--palette", "#zz0000", "--out", "{new}"], "not a hex color"),
    (["render", "--run", "{run}", "--body-color", "blue", "--out", "{new}"], "--body-color"),
    (["render", "--run", "{run}", "--frames", "2:2", "--out", "{new}"], "--frames 2:2 selects no frame"),
    (["render", "--run", "{run}", "--frames", "1:999", "--out", "{new}"], "--frames 1:999 is out of range"),
    (["render", "--run", "{run}", "--frames", "x", "--out", "{new}"], "--frames"),
    (["render", "--run", "{run}", "--frames", "0:3:0", "--out", "{new}"], "--frames 0:3:0: the step must be at least 1"),
    (["render", "--run", "{run}", "--frames", "", "--out", "{new}"], "--frames is empty"),
    (["render", "--run", "{run}", "--palette", "", "--out", "{new}"], "--palette is empty"),
    (["render", "--run", "{run}", "--palette", "#ff0000,,-", "--out", "{new}"], "--palette '#ff0000,,-': an empty"),
    (["render", "--run", "{run}", "--size", "3", "--out", "{new}"], "--size"),
    (["render", "--run", "{run}", "--quality", "0", "--out", "{new}"], "--quality"),
    (["render", "--run", "{run}", "--fps", "0", "--out", "{new}"], "--fps"),
    (["render", "--run", "{run}", "--fps", "1e-300", "--video", "--out", "{new}"], "--fps must be in 0.1..1000"),
    (["render", "--run", "{run}", "--fps", "1e308", "--video", "--out", "{new}"], "--fps must be in 0.1..1000"),
    (["render", "--run", "{run}", "--quality", "1e-9", "--out", "{new}"], "--quality must be in 0.0625..4"),
    (["render", "--run", "{run}", "--preset", "warp", "--out", "{new}"], "unknown render preset 'warp'"),
    (["render", "--run", "{run}", "--camera", "nope", "--out", "{new}"], "unknown camera 'nope'"),
    (["render", "--run", "{run}", "--motion", "moonwalk", "--out", "{new}"], "moonwalk"),
    (["render", "--run", "{new}", "--out", "{new}"], "{new}"),
    (["render", "--run", "{orphan}", "--out", "{new}"], "scene"),
    (["render", "--run", "{run}", "--frames", "0", "--out", "{taken}"], "frame_0000.png: already exists"),
    (["render", "--run", "{run}", "--quality", "4", "--max-memory-gib", "0.25", "--out", "{new}"],
     "a render of 256x256 pixels at quality 4 needs about 0.9 GiB at its peak (estimated: 0.0655 million output"),
    (["render", "--run", "{run}", "--max-memory-gib", "1e9", "--out", "{new}"], "--max-memory-gib must be in"),
    # --- train --------------------------------------------------------------------------------------
    (["train", "--scene", "{scene}", "--out", "{file}"], "--out"),
    (["train", "--scene", "{scene}", "--out", "{file}/run"], "is a file, not a folder"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--device", "potato"], "--device 'potato'"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--threads", "0"], "--threads"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--cache-gib", "0"], "--cache-gib"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--cache-gib", "nan"], "--cache-gib"),
    (["train", "--out", "{new}"], "--scene"),
    (["train", "--scene", "{new}", "--out", "{new}/run"], "{new}"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--frames", "x"], "--frames"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--frames", "5:5"], "--frames"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--frames", "0:10:0"], "--frames 0:10:0: the step must be"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--frames=-2:2"], "no negative numbers"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--loss-weight", "w_mask"], "--loss-weight"),
    (["train", "--scene", "{scene}", "--out", "{new}", "--stop-after", "0"], "--stop-after must be at least 1"),
    # --- eval and report ----------------------------------------------------------------------------
    (["eval", "--run", "{run}", "--split", "nope"], "unknown split 'nope'"),
    (["eval", "--run", "{run}", "--split", "seen", "--json", "{json}"], "--json"),
    (["eval", "--run", "{run}", "--split", "seen", "--json", "{dir}"], "is a folder"),
    (["eval", "--run", "{run}", "--split", "seen", "--json", "{new}/e.json"], "does not exist"),
    (["eval", "--run", "{run}", "--split", "seen", "--baseline"], "--baseline"),
    (["eval", "--run", "{run}", "--split", "seen", "--device", "potato"], "--device 'potato'"),
    (["eval", "--run", "{run}", "--split", "seen", "--preset", "warp"], "--preset"),
    (["eval", "--run", "{run}", "--split", "seen", "--frames", "x"], "--frames"),
    (["eval", "--run", "{run}", "--split", "seen", "--quality", "100"], "--quality must be in 0.0625..4"),
    (["eval", "--run", "{run}", "--split", "seen", "--frames", "0:10:0"], "--frames 0:10:0: the step must be"),
    (["eval", "--run", "{run}", "--split", "seen", "--cameras", ","], "--cameras ',': an empty camera"),
    (["eval", "--run", "{run}", "--split", "seen", "--cameras", ""], "--cameras is empty"),
    (["eval", "--run", "{new}", "--split", "seen"], "{new}"),
    (["eval", "--run", "{run}", "--split", "seen", "--max-memory-gib", "0.25"],
     "evaluating views of 64x64 pixels needs about 0.9 GiB at its peak"),
    (["report", "--scene", "{scene}", "--out", "{md}"], "--out"),
    (["report", "--scene", "{scene}", "--out", "{new}.md", "--preset", "huge"], "unknown preset 'huge'"),
    (["report", "--scene", "{scene}", "--out", "{new}.md", "--device", "potato"], "--device 'potato'"),
    (["report", "--scene", "{scene}", "--out", "{new}.md", "--variants", ","], "--variants ',': an empty variant"),
    (["report", "--scene", "{scene}", "--out", "{new}.md", "--views", "4,,8"], "--views '4,,8': an empty"),
    (["report", "--scene", "{scene}", "--out", "{new}.md", "--history", "1,x"], "--history '1,x': number 'x'"),
    # --- data ---------------------------------------------------------------------------------------
    (["data", "make", "--garment", "skirt", "--out", "{file}"], "--out"),
    (["data", "make", "--garment", "skirt", "--out", "{file}/scene"], "is a file, not a folder"),
    (["data", "preview", "{scene}", "--out", "{png}"], "already exists"),
    (["data", "preview", "{new}", "--out", "{new}.png"], "{new}"),
    (["data", "preview", "{nan_scene}", "--out", "{new}.png"], "cameras[0].K[0][0]: NaN is not a finite number"),
    (["data", "preview", "{broken_scene}", "--out", "{new}.png"], "unreadable file {broken_scene}/sequences/"),
    # --- body, maps, bench, view --------------------------------------------------------------------
    (["body", "export", "--shape", "1e30", "--out", "{new}.ply"], "--shape 1e30"),
    (["body", "export", "--shape", "nan", "--out", "{new}.ply"], "--shape nan"),
    (["body", "export", "--shape", "giant", "--out", "{new}.ply"], "giant"),
    (["body", "export", "--shape", " , ,", "--out", "{new}.ply"], "--shape ', ,': an empty shape coefficient"),
    (["body", "export", "--shape", "0.5,x", "--out", "{new}.ply"], "shape coefficient 'x': not a number"),
    (["body", "export", "--out", "{ply}"], "already exists"),
    (["body", "export", "--out", "{new}.xyz"], "unsupported mesh format"),
    (["maps", "--motion", "walk", "--frame", "99999", "--out", "{new}.npz"], "out of range"),
    (["maps", "--out", "{npz}"], "already exists"),
    (["body", "export", "--motion", "{far}", "--frame", "1", "--out", "{new}.ply"],
     "--motion {far} frame 1: the posed body collapses to one point: its coordinates reach 1e+20"),
    (["maps", "--motion", "{far}", "--frame", "2", "--out", "{new}.npz"],
     "--motion {far} frame 0: the posed body collapses to one point"),  # the first frame of its history
    (["render", "--run", "{run}", "--motion", "{far}", "--frames", "0:2", "--out", "{new}"],
     "--motion {far} frame 0: the posed body collapses to one point"),
    (["bench", "--runs", "0"], "--runs"),
    (["bench", "--plot", "{new}.png"], "--plot needs --run"),
    (["bench", "--run", "{run}", "--frames", "0"], "--frames"),
    (["bench", "--run", "{run}", "--presets", ","], "--presets ',': an empty preset"),
    (["bench", "--run", "{run}", "--training", "--precisions", ""], "--precisions is empty"),
    (["bench", "--json", "{json}"], "--json"),
    (["bench", "--run", "{run}", "--plot", "{png}"], "--plot"),
    (["view", "--json", "{new}.json"], "--json needs --bench"),
    (["view", "--bench", "--json", "{json}"], "--json"),
    (["view", "--run", "{orphan}"], "scene"),
    # --- demo ---------------------------------------------------------------------------------------
    (["demo", "pack", "{run}", "--name", "nosuch"], "--name: unknown demo 'nosuch'; choose one of skirt"),
    (["demo", "table", "--out", "{md}"], "--out"),
]


def _tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def world(tmp_path_factory, tiny_scene):
    from garmentnerf.runs import create_untrained_run

    root = tmp_path_factory.mktemp("world")
    scene = root / "scene"
    shutil.copytree(tiny_scene.root, scene)
    cfg = ModelConfig.tiny().updated({"sampler.samples_per_ray": 4})
    run = create_untrained_run(root / "run", scene, cfg, seed=0)
    # a run whose scene folder has gone away
    orphan = root / "orphan"
    shutil.copytree(run, orphan)
    info = json.loads((orphan / "run.json").read_text())
    info["scene"] = str(root / "deleted_scene")
    (orphan / "run.json").write_text(json.dumps(info))
    # a scene whose first camera's K holds a NaN (JSON has no NaN: Python writes one anyway)
    nan_scene = root / "nan_scene"
    shutil.copytree(scene, nan_scene)
    meta = json.loads((nan_scene / "scene.json").read_text())
    meta["cameras"][0]["K"][0][0] = float("nan")
    (nan_scene / "scene.json").write_text(json.dumps(meta))
    # a scene one of whose sequence files is not an npz any more
    broken_scene = root / "broken_scene"
    shutil.copytree(scene, broken_scene)
    next(iter(sorted((broken_scene / "sequences").glob("*/garment.npz")))).write_bytes(b"not a zip file")
    files = {"file": "existing.bin", "json": "existing.json", "md": "existing.md", "png": "existing.png",
             "ply": "existing.ply", "npz": "existing.npz"}
    for key, name in files.items():
        (root / name).write_bytes(f"user data {key}\n".encode())
    (root / "folder").mkdir()
    taken = root / "taken"
    taken.mkdir()
    (taken / "frame_0000.png").write_bytes(b"a frame the user keeps\n")
    # a motion whose root translation float32 cannot hold beside a body's size: every vertex one point
    from garmentnerf.body.model import BodyModel
    from garmentnerf.motion.library import load_motion

    far = load_motion("walk", BodyModel.default()).slice(0, 3)
    far.translation[:] = 1e20
    far.save(root / "far.npz")
    places = {key: str(root / name) for key, name in files.items()}
    places.update(run=str(run), scene=str(scene), dir=str(root / "folder"), orphan=str(orphan),
                  nan_scene=str(nan_scene), broken_scene=str(broken_scene), taken=str(taken), new=str(root / "new"),
                  far=str(root / "far.npz"))
    return root, places


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(a[:3]) + f" #{i}" for i, (a, _) in enumerate(CASES)])
def test_bad_input_is_one_line_exit_2_and_nothing_changes(world, argv, message, capfd, monkeypatch):
    root, places = world
    if argv[:1] == ["view"]:
        monkeypatch.setenv("DISPLAY", ":987")  # the argument check comes before any window
    if "cuda" in " ".join(argv) and torch.cuda.is_available() and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    argv = [a.format(**places) for a in argv]
    message = message.format(**places)
    monkeypatch.chdir(root / "folder")
    before = _tree_digest(root)
    code = main(argv)
    out, err = capfd.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, (argv, code, err[-2000:])
    assert len(lines) == 1, (argv, err[-2000:])
    assert "Traceback" not in err and lines[0].startswith("garmentnerf: error:"), lines
    assert message in lines[0], (message, lines[0])
    assert not (root / "new").exists(), "a failed command created its output"
    after = _tree_digest(root)
    assert after == before, sorted(set(after.items()) ^ set(before.items()))[:5]


def test_table_covers_every_command_and_enough_kinds():
    commands = {tuple(a[:2]) if a[0] == "data" else (a[0],) for a, _ in CASES}
    assert {("render",), ("train",), ("eval",), ("report",), ("data", "make"), ("data", "preview"), ("body",),
            ("maps",), ("bench",), ("view",)} <= commands
    assert len(CASES) >= 40


def test_console_script_exits_2_without_traceback(world, tmp_path):
    import os
    import subprocess
    import sys

    root, places = world
    proc = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "render", "--run", places["run"],
                           "--device", "potato", "--out", str(tmp_path / "r")], capture_output=True, text=True,
                          env=dict(os.environ), timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "--device 'potato'" in proc.stderr


def test_view_names_the_display_it_cannot_open(tmp_path):
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "WAYLAND_DISPLAY"}
    env["DISPLAY"] = ":987"  # named, but no X server answers there
    proc = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "view", "--body-only",
                           "--snapshot-dir", str(tmp_path / "s")], capture_output=True, text=True, env=env,
                          timeout=300, cwd=tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr
    assert "DISPLAY=:987" in lines[0] and "unset" not in lines[0] and "garmentnerf render" in lines[0]
    assert not (tmp_path / "s").exists()


def test_render_interrupted_before_its_first_frame_reports_no_speed(world, tmp_path, capfd, monkeypatch):
    from garmentnerf.render.session import RenderSession

    root, places = world

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(RenderSession, "render", interrupted)
    code = main(["render", "--run", places["run"], "--frames", "0:2", "--out", str(tmp_path / "r"), "--no-progress"])
    out, err = capfd.readouterr()
    assert code == 130 and "0 frame(s)" in out and "no frame finished" in out and "nan" not in out
    assert err.strip() == "garmentnerf: interrupted after 0 of 2 frames"


class _FullDiskFile:
    """A file opened for writing on a disk that fills up: the first write stores half its bytes, then
    raises what ``write()`` raises there (ENOSPC, naming no file)."""

    def __init__(self, real):
        self._real = real

    def write(self, data):
        import errno

        self._real.write(bytes(data)[:len(data) // 2] if not isinstance(data, str) else data[:len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name):
        return getattr(self._real, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._real.close()


def full_disk(monkeypatch, folder: Path) -> None:
    """Make every file opened for writing under ``folder`` (by ``open``, ``io.open`` and so ``Path.write_text``)
    a :class:`_FullDiskFile`: the disk under ``folder`` is full."""
    import builtins
    import io

    real_open = io.open

    def opening(file, mode="r", *args, **kwargs):
        handle = real_open(file, mode, *args, **kwargs)
        inside = isinstance(file, (str, Path)) and Path(file).resolve().is_relative_to(folder.resolve())
        return _FullDiskFile(handle) if inside and any(m in mode for m in "wax+") else handle

    monkeypatch.setattr(builtins, "open", opening)
    monkeypatch.setattr(io, "open", opening)


@pytest.mark.parametrize("argv, written", [
    (["body", "export", "--out", "{disk}/body.ply"], "body.ply"),
    (["maps", "--out", "{disk}/maps.npz"], "maps.npz"),
    (["eval", "--run", "{run}", "--split", "seen", "--frames", "0", "--cameras", "{camera}", "--no-progress",
      "--json", "{disk}/eval.json"], "eval.json"),
])
def test_a_full_disk_is_one_line_naming_the_file_and_leaves_nothing(world, argv, written, tmp_path, capfd,
                                                                     monkeypatch):
    """Every command writes through the atomic writers of garmentnerf.io_utils, which name the file a full
    disk refused and remove their temporary (the half a full disk left)."""
    from garmentnerf.data.scene import Scene

    _, places = world
    disk = tmp_path / "disk"
    disk.mkdir()
    camera = Scene.load(places["scene"]).camera_names("train")[0]
    argv = [a.format(disk=disk, camera=camera, **places) for a in argv]
    full_disk(monkeypatch, disk)
    code = main(argv)
    err = capfd.readouterr().err
    # warp's notice that this machine has no CUDA is printed once per process, by whichever test loads it first
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("Warp CUDA warning")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err[-2000:]
    assert lines[0] == f"garmentnerf: error: {disk / written}: cannot write (No space left on device)"
    assert list(disk.iterdir()) == []  # no temporary, no half file


def test_output_checks_refuse_what_float_arithmetic_lost_naming_the_cause():
    import numpy as np

    from garmentnerf.output_checks import DegenerateOutputError, check_finite, check_points, check_varies

    body = np.random.default_rng(0).uniform(-0.3, 0.3, (500, 3)).astype(np.float32)
    body[:, 2] *= 3  # about 1.8 m tall
    for moved in (0.0, 1e3, 8e3):  # float32 keeps a millimetre here
        check_points(body + np.float32(moved), "the posed body", "--motion m frame 0")
    with pytest.raises(DegenerateOutputError, match=r"^--motion m frame 3: the posed body loses its shape: its "
                                                    r"coordinates reach 1e\+05, where float32 holds values 0.00781"):
        check_points(body + np.float32(1e5), "the posed body", "--motion m frame 3")
    with pytest.raises(DegenerateOutputError, match="collapses to one point"):
        check_points(body + np.float32(1e20), "the posed body", "m")
    check_points((body + 1e5).astype(np.float64), "the posed body", "m")  # float64 still holds it
    with pytest.raises(DegenerateOutputError, match=r"holds 1 of 1500 values that are not finite \(NaN\)"):
        bad = body.copy()
        bad[7, 1] = np.nan
        check_points(bad, "the posed body", "m")
    with pytest.raises(DegenerateOutputError, match=r"^frame 2: the image holds 2 of 12 values that are not finite "
                                                    r"\(NaN and infinity\); not written$"):
        check_finite(np.array([np.nan, np.inf] + [0.5] * 10), "the image", "frame 2")
    check_finite(np.zeros(4, np.uint8), "the image", "x")  # whole numbers are always finite
    with pytest.raises(DegenerateOutputError, match="the normal map is 0 throughout"):
        check_varies(np.zeros((4, 4, 3), np.float32), "the normal map", "m")
    check_varies(np.eye(3, dtype=np.float32), "the normal map", "m")


def test_render_refuses_an_image_that_is_not_finite_and_keeps_the_frames_before(world, tmp_path, capfd, monkeypatch):
    import numpy as np

    from garmentnerf.render.session import NeuralFrame

    _, places = world
    real = NeuralFrame.composite

    def nan_at_frame_1(self, *args, **kwargs):
        image = real(self, *args, **kwargs)
        if self.frame == 1:
            image[3, 4, 1] = np.nan  # what a diverged model gives
        return image

    monkeypatch.setattr(NeuralFrame, "composite", nan_at_frame_1)
    out = tmp_path / "r"
    code = main(["render", "--run", places["run"], "--frames", "0:3", "--size", "32", "--preset", "reference",
                 "--out", str(out), "--no-progress"])
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip() and not line.startswith("Warp CUDA")]
    assert code == 2 and len(err) == 1, err
    assert err[0] == ("garmentnerf: error: motion 'train' seen by camera turntable, frame 1: the rendered image holds "
                      "1 of 3072 values that are not finite (NaN); not written"), err
    assert sorted(p.name for p in out.iterdir()) == ["frame_0000.png"]  # the frame before stays; no temporary
