"""The bundled demos (:mod:`garmentnerf.demos`): the registry, ``--demo`` on the commands, and
``garmentnerf demo pack`` / ``list``."""

import json
import os

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from garmentnerf.cli.main import main
from garmentnerf.demos import (
    DEFAULT_DEMO,
    DEMO_NAMES,
    demo,
    demo_run_dir,
    installed_demos,
    pack_demo,
    pack_weights,
    results_table,
)
from garmentnerf.model.config import ModelConfig
from garmentnerf.render.band_cache import SCENE_BAND_FILE, band_key, load_band
from garmentnerf.render.presets import BOX_TRAINED_MARGIN_IN, height_range_for_run
from garmentnerf.runs import create_untrained_run, load_run


@pytest.fixture(scope="module")
def untrained_run(tiny_scene, tmp_path_factory):
    run_dir = create_untrained_run(tmp_path_factory.mktemp("demo_run") / "run", tiny_scene.root, ModelConfig.tiny(), seed=1)
    (run_dir / "TRAINING.md").write_text("how it was trained\n")
    (run_dir / "recipe.json").write_text("{}\n")
    (run_dir / "eval_unseen_view.json").write_text(json.dumps({
        "means": {"fg_psnr": 23.5, "garment_psnr": 21.25, "silhouette_iou": 0.95}, "margin_db": {"fg_psnr": 8.5}}))
    return run_dir


def files_size(folder):
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, names in os.walk(folder) for f in names)


def test_the_registry_names_the_papers_garments_and_refuses_the_rest(tmp_path):
    assert DEMO_NAMES == ("skirt", "tshirt", "dress") and DEFAULT_DEMO == "skirt"
    with pytest.raises(ValueError, match="unknown demo 'coat'; choose one of skirt, tshirt, dress"):
        demo("coat")
    assert installed_demos(tmp_path) == []
    with pytest.raises(FileNotFoundError, match="the dress demo is not installed \\(installed demos: none\\)"):
        demo_run_dir("dress", tmp_path)


def test_pack_makes_a_loadable_demo_in_float16_beside_its_scene(untrained_run, tiny_scene, tmp_path):
    root = tmp_path / "demo"
    packed = pack_demo(untrained_run, "tshirt", root)
    assert packed.run_dir == root / "run_tshirt" and packed.installed
    assert [d.name for d in installed_demos(root)] == ["tshirt"] and demo_run_dir("tshirt", root) == packed.run_dir
    assert json.loads((packed.run_dir / "run.json").read_text())["scene"] == "../tshirt"
    assert packed.scene_dir == (root / "tshirt").resolve()
    # the scene's shipped files, not its rendered cache, and the garment's height band measured on them
    shipped = sorted(p.relative_to(root / "tshirt").as_posix() for p in (root / "tshirt").rglob("*") if p.is_file())
    expected = sorted([SCENE_BAND_FILE] + [p.relative_to(tiny_scene.root).as_posix() for p in tiny_scene.root.rglob("*")
                      if p.is_file() and p.relative_to(tiny_scene.root).parts[0] in ("scene.json", "sequences")])
    assert shipped == expected and not (root / "tshirt" / "cache").exists()
    loaded = load_run(packed.run_dir)
    key = band_key(loaded.scene, loaded.model.body, loaded.betas, BOX_TRAINED_MARGIN_IN)
    shipped_band = load_band(root / "tshirt" / SCENE_BAND_FILE, key)  # the packed scene's own key
    assert shipped_band is not None and shipped_band == height_range_for_run(load_run(untrained_run))
    # float32 weights stored as float16: the same values to float16's rounding (numpy's cast)
    source, weights = load_file(str(untrained_run / "model.safetensors")), load_file(str(packed.run_dir / "model.safetensors"))
    assert weights.keys() == source.keys()
    for key, value in source.items():
        assert weights[key].dtype == (torch.float16 if value.dtype == torch.float32 else value.dtype)
        np.testing.assert_array_equal(weights[key].numpy(), value.numpy().astype(weights[key].numpy().dtype))
    assert (packed.run_dir / "TRAINING.md").read_text() == "how it was trained\n"
    assert (packed.run_dir / "recipe.json").read_text() == "{}\n"  # a recipe folder's: trains the demo again
    assert packed.size_bytes() == files_size(packed.run_dir) + files_size(root / "tshirt")
    assert packed.figures() == {"unseen_view": {"fg_psnr": 23.5, "garment_psnr": 21.25, "silhouette_iou": 0.95,
                                                "fg_margin_db": 8.5}}
    run = load_run(packed.run_dir)
    assert run.scene is not None and sorted(run.scene.sequences) == sorted(tiny_scene.sequences)
    # nothing is replaced without overwrite, and no staging folder is left behind
    with pytest.raises(FileExistsError, match="pass --overwrite to replace the tshirt demo"):
        pack_demo(untrained_run, "tshirt", root)
    pack_demo(untrained_run, "tshirt", root, overwrite=True)
    assert sorted(p.name for p in root.iterdir()) == ["run_tshirt", "tshirt"]


def test_pack_weights_keeps_non_float32_tensors(tmp_path):
    from safetensors.torch import save_file

    save_file({"a": torch.tensor([1.0, 1.0 / 3.0]), "n": torch.tensor([3, 4])}, str(tmp_path / "w.safetensors"))
    size = pack_weights(tmp_path / "w.safetensors", tmp_path / "p.safetensors")
    out = load_file(str(tmp_path / "p.safetensors"))
    assert size == (tmp_path / "p.safetensors").stat().st_size
    assert out["a"].dtype == torch.float16 and float(out["a"][1]) == float(np.float16(1.0 / 3.0))
    assert out["n"].dtype == torch.int64 and out["n"].tolist() == [3, 4]
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "p.safetensors").stat().st_mode & 0o777 == 0o666 & ~umask  # what open() would give


@pytest.mark.parametrize("argv, message", [
    (["eval", "--split", "unseen_view"], "eval needs --run DIR or --demo NAME"),
    (["eval", "--demo", "coat", "--split", "unseen_view"], "unknown demo 'coat'"),
    (["eval", "--demo", "skirt", "--run", "x", "--split", "unseen_view"], "--run and --demo: give one of them"),
    (["render", "--demo", "skirt", "--run", "x", "--out", "frames"], "--run and --demo: give one of them"),
    (["bench", "--demo", "coat"], "unknown demo 'coat'"),
    (["view", "--demo", "coat"], "unknown demo 'coat'"),  # before the display is looked for
])
def test_demo_flags_fail_in_one_line(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_demo_list_prints_each_installed_demo_with_its_figures(capsys):
    assert main(["demo", "list"]) == 0
    out = capsys.readouterr().out
    for d in installed_demos():
        row = next(line for line in out.splitlines() if line.startswith(d.name + " "))
        assert f"{d.size_bytes() / 1e6:.1f}" in row
        for split in d.figures().values():
            assert f"{split['fg_psnr']:.2f}" in row and f"{split['silhouette_iou']:.3f}" in row


def test_the_results_table_puts_each_split_beside_the_papers_table_1(untrained_run, tmp_path):
    from garmentnerf.demos import PAPER_TABLE_1, results_table

    packed = pack_demo(untrained_run, "dress", tmp_path / "demo")
    report = {"means": {"psnr": 30.123, "ssim": 0.9712, "stlpips_alex": 0.0254, "tof": 0.6004, "fg_psnr": 22.5,
                        "garment_psnr": 21.0, "silhouette_iou": 0.951}, "margin_db": {"psnr": 9.25, "fg_psnr": 8.25}}
    (packed.run_dir / "eval_unseen_view.json").write_text(json.dumps(report))
    lines = results_table([packed]).splitlines()
    assert len(lines) == 2 + 3 and lines[0].count("|") == lines[2].count("|") == 9
    held_out = next(line for line in lines if "held-out cameras" in line)
    assert "30.12 / 0.971 / 0.025 / 0.600" in held_out and "22.50 / 21.00" in held_out
    assert "9.25 (8.25) dB" in held_out  # full frame as the paper's margin, then over the character
    paper = PAPER_TABLE_1["dress"]
    assert f"{paper['unseen_view'][0]:.2f} / {paper['unseen_view'][1]:.3f}" in held_out
    assert f"{paper['unseen_view'][0] - paper['nearest view'][0]:.2f} dB" in held_out  # 11.54
    assert "not evaluated" in next(line for line in lines if "training cameras" in line)
    assert "not evaluated" in next(line for line in lines if "held-out motion" in line)


def test_pack_refuses_figures_measured_with_a_body_appearance_the_run_no_longer_has(tiny_scene, tmp_path, capfd,
                                                                                    monkeypatch):
    """A run's eval_*.json measured with composition raster_body needs its body_appearance.safetensors: packed
    without it, the demo would list figures of a picture it does not draw. Refused in one line naming the
    missing file, nothing written; a demo installed that way by hand lists those figures as not evaluated."""
    import functools
    import shutil

    from garmentnerf.cli import demo_cmd
    from garmentnerf.demos import BODY_APPEARANCE_FILE as named_here
    from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE

    assert named_here == BODY_APPEARANCE_FILE
    run_dir = create_untrained_run(tmp_path / "run", tiny_scene.root, ModelConfig.tiny(), seed=2)
    measured = {"split": "unseen_view", "composition": "raster_body",
                "means": {"fg_psnr": 24.0, "garment_psnr": 22.0, "silhouette_iou": 0.97}}
    (run_dir / "eval_unseen_view.json").write_text(json.dumps(measured))
    root = tmp_path / "demo"
    monkeypatch.setattr(demo_cmd, "pack_demo", functools.partial(pack_demo, root=root))
    assert main(["demo", "pack", str(run_dir), "--name", "skirt"]) == 2
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip() and not line.startswith("Warp CUDA")]
    assert len(err) == 1 and err[0].startswith(f"garmentnerf: error: {run_dir / BODY_APPEARANCE_FILE}: missing, but "
                                               f"eval_unseen_view.json was measured with it"), err
    assert not root.exists()
    # measured without it (the network draws the body): packed, and listed
    (run_dir / "eval_unseen_view.json").write_text(json.dumps(dict(measured, composition="nerf")))
    assert main(["demo", "pack", str(run_dir), "--name", "skirt"]) == 0
    packed = demo("skirt", root)
    assert packed.figures() == {"unseen_view": {"fg_psnr": 24.0, "garment_psnr": 22.0, "silhouette_iou": 0.97}}
    # a raster_body evaluation copied in by hand is not the demo's: not evaluated, in the list and the table
    shutil.copy(run_dir / "eval_unseen_view.json", packed.run_dir / "eval_unseen_motion.json")
    (packed.run_dir / "eval_unseen_view.json").write_text(json.dumps(measured))
    assert packed.figures() == {"unseen_motion": {"fg_psnr": 24.0, "garment_psnr": 22.0, "silhouette_iou": 0.97}}
    assert "not evaluated" in next(line for line in results_table([packed]).splitlines() if "held-out cameras" in line)


def test_pack_is_refused_while_another_process_writes_the_demos(untrained_run, tmp_path):
    """demo pack holds the demos folder's writer lock while it checks and replaces a demo: a second pack
    at once is refused naming the first's PID, before anything changes."""
    import subprocess
    import sys
    import textwrap

    from garmentnerf.folder_lock import FolderBusyError

    root = tmp_path / "demo"
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import sys, time
        from garmentnerf.folder_lock import lock_folder
        lock = lock_folder(sys.argv[1], "garmentnerf demo pack --name dress")
        print("held", flush=True)
        time.sleep(600)
    """), str(root)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderBusyError, match=rf"PID {holder.pid}, 'garmentnerf demo pack --name dress'"):
            pack_demo(untrained_run, "tshirt", root)
        assert sorted(p.name for p in root.iterdir()) == [".garmentnerf-writer.lock"]
    finally:
        holder.kill()
        holder.wait()
    pack_demo(untrained_run, "tshirt", root)
    assert sorted(p.name for p in root.iterdir()) == ["run_tshirt", "tshirt"]
