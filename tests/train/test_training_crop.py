"""Training on character windows (``ModelConfig.training_crop_density``) and fine-tuning from a
whole model (``--init-weights``): the window's placement, its camera and target against OpenCV and
the scene's own pixels, the density the renderer and the evaluation read back, and the run records."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from garmentnerf.conventions import project_points
from garmentnerf.model.config import ModelConfig
from garmentnerf.render.screen_rect import PixelRect
from garmentnerf.runs import load_run
from garmentnerf.train.frames import SceneFrames, character_window
from garmentnerf.train.settings import TrainConfig
from garmentnerf.train.trainer import Trainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def crop_config(density: float = 1.0):
    """The tiny model on 32 x 32 windows (8 x 8 rays) of the tiny scene's 64 x 64 images."""
    return ModelConfig.tiny().updated({"decoder.image_resolution": 32, "decoder.feature_image_resolution": 8, "schedule.training_crop_density": density})


# ---------------------------------------------------------------------------------------- placement
def test_character_window_centres_on_the_drawn_point_and_stays_inside():
    rect = PixelRect(100, 40, 200, 400)
    # inside: the centre is the point at the fractions of the rectangle, rounded to a pixel
    assert character_window(rect, (512, 512), 256, (0.5, 0.5)) == PixelRect(200 - 128, 240 - 128, 256, 256)
    assert character_window(rect, (512, 512), 64, (0.25, 0.75)) == PixelRect(150 - 32, 340 - 32, 64, 64)
    # at the image's edges it moves the least that keeps it inside
    assert character_window(rect, (512, 512), 256, (0.0, 0.0)) == PixelRect(0, 0, 256, 256)
    assert character_window(rect, (512, 512), 256, (0.999, 0.999)) == PixelRect(300 - 128, 512 - 256, 256, 256)
    # no rectangle (the box out of view): anywhere in the image
    assert character_window(None, (300, 200), 100, (0.5, 0.5)) == PixelRect(100, 50, 100, 100)
    # the whole image
    assert character_window(rect, (256, 256), 256, (0.3, 0.9)) == PixelRect(0, 0, 256, 256)
    with pytest.raises(ValueError, match="does not fit"):
        character_window(rect, (512, 200), 256, (0.5, 0.5))


# ---------------------------------------------------------------------------------------- camera and target
def test_window_camera_and_target_are_the_scene_pixels(tiny_scene, gl_context):
    from garmentnerf.data.scene_images import SceneImages

    cfg = crop_config(1.0)
    with SceneFrames(tiny_scene, cfg, gl_context) as frames:
        native = tiny_scene.camera("cam01").camera
        cam = frames.camera("cam01")
        assert (cam.width, cam.height) == (native.width, native.height) == (64, 64)
        box = torch.tensor([[-0.4, -0.3, 0.0], [0.4, 0.3, 1.7]], dtype=torch.float64)
        draws = []
        for seed in range(6):
            view, window = frames.training_view("cam01", box, torch.Generator().manual_seed(seed))
            assert (view.width, view.height) == (window.width, window.height) == (32, 32)
            assert 0 <= window.x0 <= 32 and 0 <= window.y0 <= 32
            draws.append((window.x0, window.y0))
            # the window camera sees a world point at its full-camera pixel minus the window's corner (OpenCV)
            pts = np.array([[0.1, -0.2, 1.1], [-0.3, 0.2, 0.4], [0.0, 0.0, 1.6]])
            rvec, _ = cv2.Rodrigues(np.asarray(native.R, np.float64))
            want, _ = cv2.projectPoints(pts, rvec, np.asarray(native.t, np.float64), np.asarray(native.K, np.float64),
                                        None)
            got, _ = project_points(view, torch.as_tensor(pts))
            np.testing.assert_allclose(got.numpy(), want[:, 0] - [window.x0, window.y0], atol=1e-6)
            # the target is the scene's own pixels of the window (density 1: no resampling)
            image, mask, garment = frames.target("train", "cam01", 1, window)
            with SceneImages(tiny_scene) as images:
                rgb, labels = images.image("train", "cam01", 1)
            rows, cols = window.slices()
            np.testing.assert_array_equal(image.permute(1, 2, 0).numpy(), rgb[rows, cols])
            np.testing.assert_array_equal(mask[0].numpy(), (labels[rows, cols] != 0).astype(np.float32))
            np.testing.assert_array_equal(garment[0].numpy(), (labels[rows, cols] == 2).astype(np.float32))
        assert len(set(draws)) > 1  # the generator moves the window
        # the same generator seed, the same window (an exact resume repeats it)
        a = frames.training_view("cam01", box, torch.Generator().manual_seed(3))[1]
        assert a == frames.training_view("cam01", box, torch.Generator().manual_seed(3))[1]


def test_half_density_target_is_the_area_downsampled_scene_image(tiny_scene, gl_context):
    from garmentnerf.data.scene_images import SceneImages

    cfg = ModelConfig.tiny().updated({"decoder.image_resolution": 16, "decoder.feature_image_resolution": 4, "schedule.training_crop_density": 0.5})
    with SceneFrames(tiny_scene, cfg, gl_context) as frames:
        assert (frames.camera("cam00").width, frames.camera("cam00").height) == (32, 32)
        box = torch.tensor([[-0.4, -0.3, 0.0], [0.4, 0.3, 1.7]], dtype=torch.float64)
        _, window = frames.training_view("cam00", box, torch.Generator().manual_seed(0))
        image, _, _ = frames.target("train", "cam00", 0, window)
    with SceneImages(tiny_scene) as images:
        rgb, _ = images.image("train", "cam00", 0)
    half = cv2.resize(rgb, (32, 32), interpolation=cv2.INTER_AREA)
    rows, cols = window.slices()
    np.testing.assert_allclose(image.permute(1, 2, 0).numpy(), half[rows, cols], atol=1e-6)


def test_whole_frame_training_is_unchanged(tiny_scene, gl_context):
    cfg = ModelConfig.tiny()
    with SceneFrames(tiny_scene, cfg, gl_context) as frames:
        box = torch.tensor([[-0.4, -0.3, 0.0], [0.4, 0.3, 1.7]], dtype=torch.float64)
        gen = torch.Generator().manual_seed(0)
        state = gen.get_state()
        view, window = frames.training_view("cam02", box, gen)
        assert window is None and torch.equal(gen.get_state(), state)  # draws nothing: old runs resume the same
        R = cfg.decoder.image_resolution
        np.testing.assert_allclose(view.K, tiny_scene.camera("cam02").camera.resized(R, R).K)


# ---------------------------------------------------------------------------------------- runs
def _tc(scene, out, **kw) -> TrainConfig:
    base = dict(scene=scene.root, out=out, model_config=ModelConfig.tiny(), iterations=2, generator_iterations=1,
                perceptual="none", progress=False, log_every=1, image_every=0, ckpt_every=100)
    base.update(kw)
    return TrainConfig(**base)


def test_crop_run_is_recorded_read_back_and_kept_on_resume(tiny_scene, gl_context, tmp_path):
    from garmentnerf.eval.evaluate import eval_size
    from garmentnerf.render.session import RenderSession

    out = tmp_path / "crop"
    tc = _tc(tiny_scene, out, model_config=crop_config(0.0), training_crop_density=1.0)
    with Trainer(tc, gl_context, log=lambda m: None) as tr:
        result = tr.train()
    assert result.finished and all(np.isfinite(h["total"]) for h in result.history)
    info = json.loads((out / "run.json").read_text())
    assert info["model_config"]["schedule"]["training_crop_density"] == 1.0
    assert info["train"]["preset"] is None  # 32 x 32 images: no preset's sizes
    run = load_run(out)
    native = tiny_scene.camera("held00").camera
    # the model was trained at the scene's own density: quality 1 renders a scene camera 1:1 ...
    assert eval_size(run.config, native, "model") == (64, 64)
    session = RenderSession(run, gl_context)
    try:
        assert session.render_scale(native, 1.0) == pytest.approx(1.0)
        assert session.render_scale(native.resized(128, 128), 0.5) == pytest.approx(0.25)
    finally:
        session.close()
    # ... where a whole-frame model of the same image size renders it at 32 / 64
    assert eval_size(ModelConfig.tiny().updated({"decoder.image_resolution": 32, "decoder.feature_image_resolution": 8}), native,
                     "model") == (32, 32)
    with pytest.raises(ValueError, match="--training-crop-density 0.5: the run .* was trained with 1"):
        Trainer(_tc(tiny_scene, out, model_config=None, iterations=None, generator_iterations=None, resume=True,
                    training_crop_density=0.5), gl_context, log=lambda m: None)


def test_init_weights_starts_the_nerf_stage_from_every_weight(tiny_scene, gl_context, tmp_path):
    from safetensors.torch import load_file

    donor_run = tmp_path / "donor"
    with Trainer(_tc(tiny_scene, donor_run), gl_context, log=lambda m: None) as tr:
        tr.train()
    donor = load_file(str(donor_run / "model.safetensors"))
    out = tmp_path / "tuned"
    messages = []
    tc = _tc(tiny_scene, out, init_weights=donor_run / "model.safetensors", seed=7, iterations=1)
    with Trainer(tc, gl_context, log=messages.append) as tr:
        assert tr.step == 1 and tr.stage == "nerf"
        state = tr.model.state_dict()
        assert all(torch.equal(state[k], v) for k, v in donor.items())  # every weight, not only G_img
        result = tr.train()
    assert result.finished and load_run(out).step == 2
    assert any("all weights from" in m for m in messages)
    # with a G_img pre-trained elsewhere (another garment's run as the start): G_img from that file, the rest
    # from the weights file
    from safetensors.torch import save_file
    generator = {k: v + 0.5 for k, v in donor.items() if k.startswith("image_generator.")}
    save_file(generator, str(tmp_path / "generator.safetensors"))
    tc = _tc(tiny_scene, tmp_path / "both", init_weights=donor_run / "model.safetensors",
             init_generator=tmp_path / "generator.safetensors", iterations=1)
    with Trainer(tc, gl_context, log=lambda m: None) as tr:
        state = tr.model.state_dict()
        assert generator and all(torch.equal(state[k], v) for k, v in generator.items())
        assert all(torch.equal(state[k], v) for k, v in donor.items() if k not in generator)
    with pytest.raises(ValueError, match="training_crop_density"):
        _tc(tiny_scene, tmp_path / "x", training_crop_density=-1.0).validate()


def test_init_weights_into_a_wider_mlp_computes_the_narrow_one_and_then_learns(tiny_scene, gl_context, tmp_path):
    """A config with a wider NeRF MLP fine-tunes a narrower one's weights: every other weight is
    the donor's, the MLP's density and zeta equal the donor MLP's on random samples (new units
    read nothing into old ones or the heads), and one step moves the heads' new columns off zero."""
    from safetensors.torch import load_file

    from garmentnerf.runs import build_model, load_weights

    donor_run = tmp_path / "donor"
    with Trainer(_tc(tiny_scene, donor_run), gl_context, log=lambda m: None) as tr:
        tr.train()
    donor = load_file(str(donor_run / "model.safetensors"))
    narrow = build_model(ModelConfig.tiny())
    load_weights(donor_run / "model.safetensors", narrow)
    width = ModelConfig.tiny().nerf.mlp_width
    cfg = ModelConfig.tiny().updated({"nerf.mlp_width": 2 * width})
    messages = []
    tc = _tc(tiny_scene, tmp_path / "wide", model_config=cfg, init_weights=donor_run / "model.safetensors",
             iterations=1)
    with Trainer(tc, gl_context, log=messages.append) as tr:
        state = tr.model.state_dict()
        same = [k for k in donor if tuple(donor[k].shape) == tuple(state[k].shape)]
        assert all(torch.equal(state[k], donor[k]) for k in same)
        grown = sorted(k for k in donor if k not in same)
        assert grown and all(k.startswith(("nerf.trunk.", "nerf.density_head.", "nerf.appearance_head."))
                             for k in grown)
        assert state["nerf.trunk.0.weight"].shape == (2 * width, narrow.nerf.input_dim)
        assert any("in this config" in m and "nerf.density_head.weight" in m for m in messages)
        gen = torch.Generator().manual_seed(0)
        n = 500
        args = (torch.randn(n, 3, generator=gen) * 0.3, torch.randn(n, generator=gen) * 0.05,
                torch.randn(n, narrow.nerf.detail_dim, generator=gen),
                torch.randn(n, narrow.nerf.dynamic_dim, generator=gen))
        with torch.no_grad():
            sigma_a, zeta_a = narrow.nerf(*args)
            sigma_b, zeta_b = tr.model.nerf(*args)
        torch.testing.assert_close(sigma_b, sigma_a, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(zeta_b, zeta_a, rtol=1e-5, atol=1e-6)
        result = tr.train()
    assert result.finished
    trained = load_file(str(tmp_path / "wide" / "model.safetensors"))
    assert trained["nerf.density_head.weight"][:, width:].abs().sum() > 0  # the new units learn
    # without the growth the shapes are refused (a run's own weights load strictly)
    with pytest.raises(ValueError, match="has shape"):
        load_weights(donor_run / "model.safetensors", build_model(cfg))
    # a narrower MLP cannot take a wider one's weights
    with pytest.raises(ValueError, match="has shape"):
        with Trainer(_tc(tiny_scene, tmp_path / "narrower", model_config=ModelConfig.tiny().updated({"nerf.mlp_width": width // 2}),
                         init_weights=donor_run / "model.safetensors"), gl_context, log=lambda m: None):
            pass


def test_cli_model_config_from_a_file_or_a_run_and_fine_tuning(tiny_scene, tmp_path, capsys):
    from garmentnerf.cli.main import main

    cfg = crop_config(1.0).updated({"schedule.lr": 3e-4, "schedule.lr_final": 1e-4, "loss.segmentation_start": 0})
    config_file = tmp_path / "config.json"
    config_file.write_text(json.dumps(cfg.to_dict()))
    common = ["--scene", str(tiny_scene.root), "--generator-iterations", "1", "--no-progress", "--threads", "1",
              "--perceptual", "none"]
    first = tmp_path / "first"
    assert main(["train", "--out", str(first), "--model-config", str(config_file), "--iterations", "1", *common]) == 0
    recorded = json.loads((first / "run.json").read_text())["model_config"]
    assert recorded == cfg.updated({"schedule.iterations": 1, "schedule.generator_iterations": 1}).to_dict()
    # the same recipe again from the run's run.json, fine-tuning the first run's weights
    second = tmp_path / "second"
    assert main(["train", "--out", str(second), "--model-config", str(first / "run.json"), "--iterations", "2",
                 "--init-weights", str(first / "model.safetensors"), *common]) == 0
    again = json.loads((second / "run.json").read_text())
    assert again["model_config"] == ModelConfig.from_dict(recorded).updated({"schedule.iterations": 2}).to_dict()
    assert again["step"] == 3
    capsys.readouterr()
    bad = tmp_path / "bad.json"
    bad.write_text('{"image_resolution": 32, "no_such_field": 1}')
    for args in (["--model-config", str(bad)], ["--model-config", str(tmp_path / "absent.json")],
                 ["--model-config", str(config_file), "--preset", "tiny"]):
        assert main(["train", "--out", str(tmp_path / "third"), "--iterations", "1", *args, *common]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "third").exists()
