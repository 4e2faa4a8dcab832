"""Training on the tiny rigged scene: overfitting, checkpoints, exact resume, Ctrl-C, the run folder, the CLI."""

from __future__ import annotations

import json
import math
import os
import socket

import pytest
import torch

from garmentnerf.model.config import ModelConfig
from garmentnerf.runs import build_model, create_untrained_run, load_run, load_weights
from garmentnerf.train.checkpoints import latest_checkpoint
from garmentnerf.train.settings import TrainConfig
from garmentnerf.train.trainer import Trainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # bit-equal resumes need one thread


def make_tc(scene, out, **kw) -> TrainConfig:
    base = dict(scene=scene.root, out=out, model_config=ModelConfig.tiny(), iterations=3, generator_iterations=2,
                perceptual="none", progress=False, log_every=1, image_every=2, ckpt_every=100)
    base.update(kw)
    return TrainConfig(**base)


def run(tc, gl_context, callback=None):
    with Trainer(tc, gl_context, log=lambda m: None) as tr:
        tr.step_callback = callback
        return tr.train(), {k: v.detach().clone() for k, v in tr.model.state_dict().items()}


def assert_same_steps(full_history, rest_history, full_state, rest_state) -> None:
    """A resumed run's steps and final weights equal the uninterrupted run's."""
    for a, b in zip(full_history, rest_history):
        assert a.keys() == b.keys()
        for key in a:
            if key != "stage":
                assert a[key] == pytest.approx(b[key], abs=1e-6, rel=0), (a["step"], key)
    for key, value in full_state.items():
        torch.testing.assert_close(rest_state[key], value, atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------------------- the scene
def test_rigged_scene(tiny_scene):
    from garmentnerf.data.garment_sequence import load_sequence

    assert tiny_scene.camera_names("train") == ["cam00", "cam01", "cam02"]
    assert set(tiny_scene.camera_names("reference")) == {"ref_front", "ref_back"}
    assert tiny_scene.palette_init["garment"] is not None and tiny_scene.palette_init["body"] is not None
    seq = load_sequence(tiny_scene.garment_path("train"))
    assert seq.vertices.shape[0] == 3 and not seq.penetration_max_m.any()
    assert seq.settings["simulated"] is False
    assert (seq.vertices[2] - seq.vertices[0]).__abs__().max() > 0.01  # the garment moves with the body


# ---------------------------------------------------------------------------------------- training
def test_overfit_one_frame(tiny_scene, gl_context, tmp_path):
    tc = make_tc(tiny_scene, tmp_path / "run", iterations=30, generator_iterations=0, frames=(1,),
                 cameras=("cam00",), model_config=ModelConfig.tiny().updated({"schedule.lr": 2e-3, "schedule.lr_final": 1e-3}))
    result, _ = run(tc, gl_context)
    totals = [h["total"] for h in result.history]
    assert len(totals) == 30 and all(h["stage"] == "nerf" for h in result.history)
    first, last = sum(totals[:5]) / 5, sum(totals[-5:]) / 5
    assert last < 0.7 * first, (first, last)
    assert result.history[-1]["psnr"] > result.history[0]["psnr"]
    assert result.finished and not result.interrupted


def test_resume_equals_uninterrupted_and_ctrl_c(tiny_scene, gl_context, tmp_path, monkeypatch):
    # Uninterrupted: 2 G_img steps, then 3 NeRF steps.
    full, full_state = run(make_tc(tiny_scene, tmp_path / "a"), gl_context)
    assert [h["stage"] for h in full.history] == ["generator"] * 2 + ["nerf"] * 3
    # The same run, Ctrl-C in the middle of step 4 (the second NeRF step).
    original = Trainer._nerf_step

    def interrupting(self, step, index, gen):
        if step == 3:
            raise KeyboardInterrupt
        return original(self, step, index, gen)

    monkeypatch.setattr(Trainer, "_nerf_step", interrupting)
    part, _ = run(make_tc(tiny_scene, tmp_path / "b"), gl_context)
    monkeypatch.setattr(Trainer, "_nerf_step", original)
    assert part.interrupted and part.step == 3 and not part.finished
    ckpt = latest_checkpoint(tmp_path / "b")
    assert ckpt is not None and ckpt[0] == 3
    loaded = load_run(tmp_path / "b")  # a loadable run at the interrupted step
    assert loaded.step == 3 and loaded.info["perceptual"] == "none"
    # Resume: steps 4 and 5 equal the uninterrupted run's.
    rest, rest_state = run(make_tc(tiny_scene, tmp_path / "b", resume=True), gl_context)
    assert [h["step"] for h in rest.history] == [4, 5]
    assert_same_steps(full.history[3:], rest.history, full_state, rest_state)
    # Checkpoint round trip: the newest checkpoint and model.safetensors hold the final weights.
    step, weights, _ = latest_checkpoint(tmp_path / "b")
    assert step == 5
    model = build_model(ModelConfig.tiny())
    load_weights(weights, model)
    for key, value in model.state_dict().items():
        assert torch.equal(value, rest_state[key].cpu()), key
    final = load_run(tmp_path / "b")
    assert final.step == 5 and final.info["nerf_step"] == 3 and final.info["generator_iterations"] == 2
    for key, value in final.model.state_dict().items():
        assert torch.equal(value, rest_state[key]), key
    assert final.palette().shape == (2, 3)
    assert final.scene is not None and final.scene.root.resolve() == tiny_scene.root.resolve()
    # only the newest 2 checkpoints are kept; TensorBoard logs exist
    names = sorted(p.name for p in (tmp_path / "b" / "checkpoints").iterdir())
    assert names == ["ckpt_3.safetensors", "ckpt_3.state.pt", "ckpt_5.safetensors", "ckpt_5.state.pt"]
    assert any((tmp_path / "b" / "tb").iterdir())


def test_a_batch_is_the_mean_loss_of_its_images_drawn_in_the_single_image_order(tiny_scene, gl_context, tmp_path):
    """cfg.schedule.batch_size 2: step s trains on the (frame, camera) pairs that single-image steps 2s and
    2s + 1 would draw (so an epoch still visits every pair once), and the gradients accumulated
    image by image equal those of the two images' mean loss backpropagated as one graph."""
    from garmentnerf.train.trainer import _seed_of

    single = make_tc(tiny_scene, tmp_path / "single", generator_iterations=0)
    batched = make_tc(tiny_scene, tmp_path / "batched", generator_iterations=0,
                      model_config=ModelConfig.tiny().updated({"schedule.batch_size": 2}))
    with Trainer(single, gl_context, log=lambda m: None) as tr:
        n = len(tr.pairs)
        order = [tr._pick(tr.pairs, s, 2) for s in range(2 * n)]
    with Trainer(batched, gl_context, log=lambda m: None) as tr:
        assert [tr._pick(tr.pairs, s, 2, i) for s in range(n) for i in range(2)] == order
        assert sorted(order[:n]) == sorted(tr.pairs)  # one epoch: every pair once

        step = 1
        tr._enter_stage("nerf")
        tr.optimizer.zero_grad(set_to_none=True)
        values, _ = tr._backward_batch(step, "nerf")
        accumulated = [p.grad.clone() for p in tr.params]

        tr.optimizer.zero_grad(set_to_none=True)
        gen = torch.Generator().manual_seed(_seed_of(tr.tc.seed, 0, step))
        terms = [tr._nerf_step(step, i, gen)[0] for i in range(2)]
        ((terms[0]["total"] + terms[1]["total"]) / 2).backward()
        assert values["total"] == pytest.approx(float((terms[0]["total"] + terms[1]["total"]).detach()) / 2, rel=1e-6)
        assert float(terms[0]["total"].detach()) != pytest.approx(float(terms[1]["total"].detach()), rel=1e-3)  # two images
        for p, grad in zip(tr.params, accumulated):
            torch.testing.assert_close(grad, p.grad, atol=1e-7, rtol=1e-5)
        assert sum(float(g.abs().sum()) for g in accumulated) > 0


def test_frame_codes_learn_at_their_own_rate():
    """The per-frame codes form their own Adam group at ``frame_codes.lr_scale``; a first Adam step, which
    moves every weight by the rate (m / sqrt(v) = sign(g)), moves theirs that many times as far."""
    from garmentnerf.train.trainer import param_groups

    cfg = ModelConfig.tiny().updated({"frame_codes.resolution": 4, "frame_codes.count": 3})
    model = build_model(cfg)
    model.set_image_generator_frozen(True)
    params = [p for mod in model.trainable_modules().values() for p in mod.parameters() if p.requires_grad]
    codes = {id(p) for p in model.frame_codes.parameters()}
    assert codes and len(codes) < len(params)
    groups = param_groups(model, params, 10.0)
    assert [g["lr_scale"] for g in groups] == [1.0, 10.0]
    assert {id(p) for p in groups[1]["params"]} == codes
    plain = param_groups(build_model(ModelConfig.tiny()), params, 10.0)  # no codes: one group
    assert [g["lr_scale"] for g in plain] == [1.0] and len(plain[0]["params"]) == len(params)

    lr = 1e-3
    optimizer = torch.optim.Adam([{**g, "lr": lr * g["lr_scale"]} for g in groups], lr=lr)
    before = [p.detach().clone() for p in params]
    for p in params:
        p.grad = torch.full_like(p, 0.5)
    optimizer.step()
    for p, old in zip(params, before):
        expected = lr * (10.0 if id(p) in codes else 1.0)
        torch.testing.assert_close(old - p.detach(), torch.full_like(old, expected), rtol=1e-4, atol=0)

def test_refuses_non_empty_run_dir(tiny_scene, gl_context, tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty.*--resume"):
        Trainer(make_tc(tiny_scene, out), gl_context)
    with pytest.raises(FileNotFoundError, match="run.json"):
        Trainer(make_tc(tiny_scene, out, resume=True), gl_context)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


# ---------------------------------------------------------------------------------------- run folder
def test_run_folder_errors(tiny_scene, tmp_path):
    run_dir = create_untrained_run(tmp_path / "r", tiny_scene.root, ModelConfig.tiny(), seed=3)
    info = json.loads((run_dir / "run.json").read_text())
    assert info["format"] == "garmentnerf-run" and info["version"] == 1 and info["step"] == 0
    assert not os.path.isabs(info["scene"])
    loaded = load_run(run_dir)
    torch.testing.assert_close(loaded.palette(), torch.tensor([tiny_scene.palette_init["garment"],
                                                               tiny_scene.palette_init["body"]]))
    (run_dir / "model.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="model.safetensors"):
        load_run(run_dir)
    (run_dir / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="model.safetensors"):
        load_run(run_dir)
    (run_dir / "run.json").write_text("{broken")
    with pytest.raises(ValueError, match="run.json"):
        load_run(run_dir)
    with pytest.raises(FileNotFoundError, match="no such run folder"):
        load_run(tmp_path / "nothing")


def test_mismatched_weights_and_checkpoints_are_rejected(tiny_scene, gl_context, tmp_path, capsys):
    from garmentnerf.cli.main import main

    run_dir = create_untrained_run(tmp_path / "r", tiny_scene.root, ModelConfig.tiny(), seed=3)
    wider = build_model(ModelConfig.tiny().updated({"nerf.mlp_width": 48}))
    with pytest.raises(ValueError, match=r"model\.safetensors: .* has shape .*the model config expects"):
        load_weights(run_dir / "model.safetensors", wider)
    no_detail = build_model(ModelConfig.tiny().updated({"encoder.detail_feature": False}))
    with pytest.raises(ValueError, match=r"weights do not match the model config \((missing|unexpected)"):
        load_weights(run_dir / "model.safetensors", no_detail)
    # a run whose run.json was edited to another size: one line naming the file, exit 2
    info = json.loads((run_dir / "run.json").read_text())
    info["model_config"]["nerf"]["mlp_width"] = 48
    (run_dir / "run.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="has shape"):
        load_run(run_dir)
    assert main(["render", "--run", str(run_dir), "--camera", "held00", "--frames", "0:1",
                 "--out", str(tmp_path / "frames")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model.safetensors" in err[0] and "Traceback" not in err[0], err
    # a damaged checkpoint state: resume refuses with the file's name
    out = tmp_path / "t"
    run(make_tc(tiny_scene, out, generator_iterations=0, iterations=3, stop_after=1), gl_context)
    step, _, state_file = latest_checkpoint(out)
    state_file.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match=r"ckpt_1\.state\.pt: unreadable checkpoint state"):
        run(make_tc(tiny_scene, out, generator_iterations=0, iterations=3, resume=True), gl_context)


# ---------------------------------------------------------------------------------------- CLI
def test_cli_train(tiny_scene, tmp_path, capsys):
    from garmentnerf.cli.main import main

    out = tmp_path / "cli_run"
    args = ["train", "--scene", str(tiny_scene.root), "--out", str(out), "--preset", "tiny", "--iterations", "3",
            "--generator-iterations", "1", "--no-progress", "--threads", "1"]
    assert main(args) == 0
    loaded = load_run(out)
    assert loaded.step == 4 and loaded.info["perceptual"] == "stlpips_alex"
    assert main(args) == 2  # the folder is not empty now
    assert "not empty" in capsys.readouterr().err


def test_cli_init_generator_skips_pretraining_with_the_same_g_img(tiny_scene, tmp_path, capsys):
    from safetensors.torch import load_file

    from garmentnerf.cli.main import main

    first, second = tmp_path / "first", tmp_path / "second"
    common = ["--scene", str(tiny_scene.root), "--preset", "tiny", "--generator-iterations", "2",
              "--no-progress", "--threads", "1", "--perceptual", "none"]
    assert main(["train", "--out", str(first), "--iterations", "1", *common]) == 0
    donor = load_file(str(first / "model.safetensors"))
    args = ["train", "--out", str(second), "--iterations", "2", "--stop-after", "3",
            "--init-generator", str(first / "model.safetensors"), *common]
    assert main(args) == 0
    assert "pre-training skipped, starting at step 2" in capsys.readouterr().err
    trained = load_file(str(second / "model.safetensors"))
    g_keys = [k for k in donor if k.startswith("image_generator.")]
    assert g_keys and all(torch.equal(donor[k], trained[k]) for k in g_keys)  # frozen in stage 2
    assert load_run(second).step == 3
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a weights file")
    assert main(["train", "--out", str(tmp_path / "third"), "--iterations", "1", "--init-generator", str(bad),
                 *common]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "Traceback" not in err


# ---------------------------------------------------------------------------------------- DDP
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank: int, world: int, port: int, scene_root: str, out: str, result_dir: str) -> None:
    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(world), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    tc = TrainConfig(scene=scene_root, out=out, model_config=ModelConfig.tiny(), iterations=2, generator_iterations=1,
                     perceptual="none", progress=False, ckpt_every=100)
    with Trainer(tc, log=lambda m: None) as tr:
        picks = [tr._pick(tr.pairs, s, 2) for s in range(1, 3)]
        result = tr.train()
        flat = torch.cat([p.detach().reshape(-1) for p in tr.model.parameters()])
    torch.save({"params": flat, "picks": picks, "steps": result.step}, os.path.join(result_dir, f"rank{rank}.pt"))


@pytest.mark.slow
def test_ddp_two_processes_gloo(tiny_scene, tmp_path):
    import torch.multiprocessing as mp

    out, results = tmp_path / "ddp", tmp_path / "results"
    results.mkdir()
    mp.spawn(_ddp_worker, args=(2, _free_port(), str(tiny_scene.root), str(out), str(results)), nprocs=2, join=True)
    r0, r1 = (torch.load(results / f"rank{r}.pt", weights_only=False) for r in range(2))
    assert r0["steps"] == r1["steps"] == 3
    assert r0["picks"] != r1["picks"]  # each rank trains on its own share of the views
    assert torch.equal(r0["params"], r1["params"])  # averaged gradients keep the replicas identical
    assert load_run(out).step == 3  # rank 0 wrote the run


def test_training_targets_carry_the_garment_share(tiny_scene, gl_context):
    import cv2
    import numpy as np

    from garmentnerf.data.scene_images import SceneImages
    from garmentnerf.train.frames import SceneFrames

    cfg = ModelConfig.tiny()
    with SceneFrames(tiny_scene, cfg, gl_context) as frames:
        image, mask, garment = frames.target("train", "cam01", 1)
    with SceneImages(tiny_scene) as images:
        _, labels = images.image("train", "cam01", 1)
    R = cfg.decoder.image_resolution
    want_garment = cv2.resize((labels == 2).astype(np.float32), (R, R), interpolation=cv2.INTER_AREA)
    want_mask = cv2.resize((labels != 0).astype(np.float32), (R, R), interpolation=cv2.INTER_AREA)
    assert garment.shape == mask.shape == (1, R, R) and garment.max() > 0.5
    np.testing.assert_allclose(garment[0].numpy(), want_garment, atol=1e-5)
    np.testing.assert_allclose(mask[0].numpy(), want_mask, atol=1e-5)
    assert bool((garment <= mask + 1e-6).all())  # the garment is part of the foreground


def test_a_layered_garment_trains_one_palette_color_per_layer(tmp_path, gl_context):
    """The dress: its labels tell its two layers apart (2 inner, 3 outer), the scene's palette init has
    a color per layer, the targets carry each layer's share, and a three-color palette trains with
    the segmentation term holding each layer's weight to its share."""
    import cv2
    import numpy as np

    from garmentnerf.data.scene_images import SceneImages
    from garmentnerf.data.synthetic import make_rigged_scene
    from garmentnerf.train.frames import SceneFrames

    scene = make_rigged_scene(tmp_path / "dress", garment="dress", motion="walk", frames=2, views=3, size=64,
                              held_out_views=1, gl_context=gl_context)
    assert len(scene.palette_init["garment_layers"]) == 2
    cfg = ModelConfig.tiny().updated({"decoder.palette_size": 3, "loss.segmentation": 1.0, "loss.segmentation_start": 0})
    with SceneFrames(scene, cfg, gl_context) as frames:
        _, mask, layers = frames.target("train", "cam00", 1)
    with SceneImages(scene) as images:
        _, labels = images.image("train", "cam00", 1)
    assert (labels == 2).sum() > 20 and (labels == 3).sum() > 20
    R = cfg.decoder.image_resolution
    assert layers.shape == (2, R, R)
    for k in range(2):
        want = cv2.resize((labels == 2 + k).astype(np.float32), (R, R), interpolation=cv2.INTER_AREA)
        np.testing.assert_allclose(layers[k].numpy(), want, atol=1e-5)
    tc = make_tc(scene, tmp_path / "run", iterations=4, generator_iterations=0, model_config=cfg)
    result, state = run(tc, gl_context)
    seg = [h["segmentation"] for h in result.history if "segmentation" in h]
    assert len(seg) == 4 and all(0.0 < v <= 2.0 for v in seg)
    assert state["palette.colors"].shape == (3, 3)
    torch.testing.assert_close(state["palette.initial"][:2],
                               torch.tensor(scene.palette_init["garment_layers"], dtype=torch.float32))


def test_segmentation_term_is_trained_and_logged(tiny_scene, gl_context, tmp_path):
    tc = make_tc(tiny_scene, tmp_path / "run", iterations=20, generator_iterations=0, frames=(1,),
                 cameras=("cam00",), model_config=ModelConfig.tiny().updated({"schedule.lr": 1e-2, "schedule.lr_final": 5e-3, "loss.segmentation": 1.0, "loss.segmentation_start": 3}))
    result, _ = run(tc, gl_context)
    assert all("segmentation" not in h for h in result.history[:3])  # not before segmentation_start
    seg = [h["segmentation"] for h in result.history[3:]]
    assert len(seg) == 17 and all(0.0 <= s <= 1.0 for s in seg)
    # trained through the weight head alone (measured: 0.50 at the start, 0.37-0.40 after 14 steps)
    assert min(seg[10:]) < 0.85 * seg[0], seg


def test_a_run_of_an_older_flat_config_resumes_unless_it_trained_with_a_removed_setting(tiny_scene, gl_context,
                                                                                          tmp_path):
    """A run.json written before the component configs: its flat config converts, and the run resumes; one
    that trained with a setting this version no longer has is refused (its render would still load)."""
    from garmentnerf.model.config import FLAT_NAMES

    out = tmp_path / "run"
    run(make_tc(tiny_scene, out, generator_iterations=0, iterations=4, stop_after=2), gl_context)
    info = json.loads((out / "run.json").read_text())
    paths = {dotted: flat for flat, dotted in FLAT_NAMES.items()}
    flat = {paths[f"{name}.{key}"]: value for name, part in info["model_config"].items() for key, value in part.items()}
    (out / "run.json").write_text(json.dumps({**info, "model_config": flat}))
    assert load_run(out).config == ModelConfig.from_dict(info["model_config"])
    (out / "run.json").write_text(json.dumps({**info, "model_config": {**flat, "w_occupancy": 0.1}}))
    assert load_run(out).config == ModelConfig.from_dict(info["model_config"])
    with pytest.raises(ValueError, match="trained with w_occupancy, which this version no longer has"):
        run(make_tc(tiny_scene, out, resume=True, iterations=4, generator_iterations=0), gl_context)
    (out / "run.json").write_text(json.dumps({**info, "model_config": flat}))
    rest, _ = run(make_tc(tiny_scene, out, resume=True, iterations=4, generator_iterations=0), gl_context)
    assert rest.step == 4


def test_loss_weights_change_on_resume_and_are_recorded(tiny_scene, gl_context, tmp_path):
    out = tmp_path / "run"
    base = ModelConfig.tiny().updated({"loss.segmentation": 0.0, "loss.segmentation_start": 0})
    first, _ = run(make_tc(tiny_scene, out, generator_iterations=0, iterations=4, stop_after=2, model_config=base),
                   gl_context)
    assert first.step == 2 and all("segmentation" not in h for h in first.history)
    rest, _ = run(make_tc(tiny_scene, out, generator_iterations=0, iterations=4, resume=True,
                          loss_weights={"segmentation": 0.25}), gl_context)
    assert [h["step"] for h in rest.history] == [3, 4]
    for h in rest.history:  # the new term is in the objective with its new weight
        weighted = sum(getattr(base.updated({"loss.segmentation": 0.25}).loss, k) * v
                       for k, v in h.items() if k not in ("step", "stage", "total", "psnr"))
        assert h["total"] == pytest.approx(weighted, rel=1e-5)
    info = json.loads((out / "run.json").read_text())
    assert info["model_config"]["loss"]["segmentation"] == 0.25
    assert info["loss_weight_changes"] == [{"step": 2, "segmentation": [0.0, 0.25]}]
    with pytest.raises(ValueError, match="unknown loss weight 'bogus'"):
        make_tc(tiny_scene, out, resume=True, loss_weights={"bogus": 1.0}).validate()
    with pytest.raises(ValueError, match="must be a finite number >= 0"):
        make_tc(tiny_scene, out, resume=True, loss_weights={"mask": -1.0}).validate()


def test_training_composes_with_the_rasterised_body(tiny_scene, gl_context, tmp_path):
    """--body-appearance: a step's image is the hybrid composition (with the garment made invisible it is
    the rasterised body in its palette color, where the plain composition would be empty), the
    appearance is copied into the run folder, where load_run finds it, and a resume keeps it."""
    from garmentnerf.model.body_appearance import BodyAppearance, save_body_appearance

    source = save_body_appearance(tmp_path / "body.safetensors", BodyAppearance(texture_size=8))
    out = tmp_path / "run"
    tc = make_tc(tiny_scene, out, iterations=3, generator_iterations=0, stop_after=1, body_appearance=source)
    probe = make_tc(tiny_scene, tmp_path / "probe", iterations=3, generator_iterations=0, body_appearance=source)
    with Trainer(probe, gl_context, log=lambda m: None) as tr:
        with torch.no_grad():  # the decoder's mask -> 0: no garment anywhere
            tr.model.decoder.head.bias[-1] = -40.0
        _, shown = tr._nerf_step(tr.generator_iterations, 0, torch.Generator())
        pred, target = shown["pred"].detach(), shown["target"]
        body_color = tr.model.palette().detach()[-1].view(3, 1, 1)
        tr.body_appearance = None
        _, plain = tr._nerf_step(tr.generator_iterations, 0, torch.Generator())
    assert float(plain["pred"].detach().abs().max()) < 1e-6  # the network alone draws nothing
    drawn = pred.sum(dim=0) > 1e-3
    character = target.sum(dim=0) > 1e-3
    assert drawn.sum() > 20 and (drawn & character).sum() >= 0.9 * drawn.sum()
    assert bool((pred <= body_color + 1e-5).all())  # coverage x p_body, nothing brighter
    inside = pred[:, drawn & (pred.sum(dim=0) >= 0.999 * float(body_color.sum()))]
    assert inside.shape[1] > 0 and torch.allclose(inside, body_color.view(3, 1).expand_as(inside), atol=1e-5)

    first, _ = run(tc, gl_context)
    assert first.step == 1 and (out / "body_appearance.safetensors").is_file()
    assert load_run(out).body_appearance is not None
    info = json.loads((out / "run.json").read_text())
    assert info["train"]["body_appearance"] == str(source)
    rest, _ = run(make_tc(tiny_scene, out, iterations=3, generator_iterations=0, resume=True), gl_context)
    assert rest.step == 3
    other = save_body_appearance(tmp_path / "other.safetensors", BodyAppearance(texture_size=8))
    with pytest.raises(ValueError, match="--body-appearance"):
        run(make_tc(tiny_scene, out, iterations=3, generator_iterations=0, resume=True, body_appearance=other),
            gl_context)


def test_a_run_with_shading_normals_trains_saves_and_loads_with_the_wider_first_conv(tiny_scene, gl_context,
                                                                                    tmp_path):
    """``nerf.shading_normals``: the decoder takes 3 more input channels; a run trains, saves and loads with them."""
    module, channels = "decoder", lambda cfg: cfg.nerf.zeta_channels
    cfg = ModelConfig.tiny().updated({"nerf.shading_normals": True})
    result, state = run(make_tc(tiny_scene, tmp_path / "r", generator_iterations=0, iterations=2, model_config=cfg),
                        gl_context)
    first_conv = [v for k, v in state.items() if k.startswith(module + ".") and v.ndim == 4][0]
    assert first_conv.shape[1] == channels(cfg) == channels(ModelConfig.tiny()) + 3
    assert all(math.isfinite(h["total"]) for h in result.history)
    loaded = load_run(tmp_path / "r")
    assert loaded.config.nerf.shading_normals
    convs = [m for m in loaded.model.get_submodule(module).modules() if isinstance(m, torch.nn.Conv2d)]
    assert convs[0].in_channels == channels(cfg)


def _spinning_processes(count: int) -> list:
    """``count`` Python processes that each keep a core busy for up to a minute (end them with ``_end``)."""
    import subprocess
    import sys

    spin = "import time\nend = time.time() + 60\nwhile time.time() < end: pass"
    return [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(count)]


def _end(processes: list) -> None:
    for process in processes:
        process.kill()
        process.wait()

def test_a_busy_machine_is_named_once_and_its_load_at_the_end(tiny_scene, tmp_path, gl_context):
    """Other processes filling every core while the trainer sets up: a one-line warning names their
    load, at the start (or, when the set-up took under 0.1 s, too short to judge, at a checkpoint
    after it), and the last line gives their share over the training."""
    import re
    import time

    if not os.path.isfile("/proc/stat"):
        pytest.skip("the machine's load is read from /proc/stat")
    children = _spinning_processes(os.cpu_count() or 1)
    lines: list[str] = []

    def log(message: str) -> None:
        lines.append(message)
        if message.startswith("warning"):  # seen: let the training itself run on a quiet machine
            for child in children:
                child.kill()

    try:
        time.sleep(0.5)  # the children are running
        with Trainer(make_tc(tiny_scene, tmp_path / "run"), gl_context, log=log) as tr:
            tr.train()
    finally:
        _end(children)
    warning = [m for m in lines if m.startswith("warning")]
    assert len(warning) == 1 and re.fullmatch(
        r"warning(?: at step \d)?: other processes are using \d+\.\d of this machine's \d+ cores: with 1 thread of its own, "
        r"this training will run slower until they stop", warning[0]), lines
    assert re.search(r"finished at step 5/5 \(\d+\.\d\d s/step; other processes used \d+\.\d of \d+ cores\)", lines[-1]), lines


def test_a_machine_that_becomes_busy_is_named_at_the_next_checkpoint(tiny_scene, tmp_path, gl_context):
    """Other processes filling every core from step 2 on: the checkpoint at step 4 says so, once."""
    import re
    import time

    from garmentnerf.cpu_load import BUSY_CORES, OtherProcessesLoad

    if not os.path.isfile("/proc/stat"):
        pytest.skip("the machine's load is read from /proc/stat")
    with OtherProcessesLoad() as before:
        time.sleep(0.5)
    if before.cores > BUSY_CORES:
        pytest.skip(f"the machine is busy already ({before.cores:.1f} cores): no change to see")
    children: list = []
    lines: list[str] = []

    def log(message: str) -> None:
        lines.append(message)
        if message.startswith("warning"):
            for child in children:
                child.kill()

    def start_at_step_2(step: int, terms: dict) -> None:
        if step == 2:
            children.extend(_spinning_processes(os.cpu_count() or 1))
            time.sleep(0.5)  # they spin

    try:
        with Trainer(make_tc(tiny_scene, tmp_path / "run", ckpt_every=2), gl_context, log=log) as tr:
            tr.step_callback = start_at_step_2
            tr.train()
    finally:
        _end(children)
    warnings = [m for m in lines if m.startswith("warning")]
    assert len(warnings) == 1 and re.fullmatch(
        r"warning at step 4: other processes are using \d+\.\d of this machine's \d+ cores: with 1 thread of its "
        r"own, this training will run slower until they stop", warnings[0]), lines
