"""The bundled demo models: each loads, renders its garment where the ground truth has it, and recolors
only the garment, to the new hue (the issue's acceptance test, measured on the shipped weights; a demo whose
decoder learned its garment's colour as offsets over another palette colour keeps that colour through a
recolouring, and fails here)."""

from __future__ import annotations

import colorsys

import numpy as np
import pytest
import torch

from garmentnerf.demos import DEMO_NAMES, demo

SIZE = 128  # a quarter of the model's rays per side: fast on the CPU, enough for region statistics


@pytest.fixture(scope="module", params=DEMO_NAMES)
def rendered(request, gl_context):
    from garmentnerf.data.scene_images import SceneImages
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    run_dir = demo(request.param).run_dir
    if not (run_dir / "run.json").is_file():
        pytest.skip(f"the {request.param} demo is not installed")
    torch.set_num_threads(2)
    run = load_run(run_dir)
    camera = run.scene.camera("held00").camera.resized(SIZE, SIZE)  # an unseen view
    with RenderSession(run, gl_context, motion="train") as session, torch.no_grad():
        nf = session.render(20, camera, quality=1.0)
    with SceneImages(run.scene) as images:
        rgb, labels = images.image("train", "held00", 20)
    return run, nf, rgb, labels


def _downsample_labels(labels: np.ndarray, size: int) -> np.ndarray:
    f = labels.shape[0] // size
    blocks = labels[: size * f, : size * f].reshape(size, f, size, f)
    garment = (blocks >= 2).mean(axis=(1, 3))  # every garment layer (the dress's two: 2 and 3)
    body = (blocks == 1).mean(axis=(1, 3))
    out = np.zeros((size, size), np.uint8)
    out[body > 0.99] = 1
    out[garment > 0.99] = 2  # pure pixels only: borders are mixed in the ground truth too
    return out


def test_render_matches_ground_truth_regions(rendered):
    run, nf, rgb, labels = rendered
    image = nf.composite()
    lab = _downsample_labels(labels, SIZE)
    gt = torch.nn.functional.interpolate(torch.as_tensor(rgb).permute(2, 0, 1)[None].float(), size=(SIZE, SIZE),
                                         mode="area")[0].permute(1, 2, 0).numpy()
    assert np.isfinite(image).all()
    # background stays dark and the garment is the ground truth's colour
    assert image[lab == 0].mean() < 0.08
    g_pred, g_true = image[lab == 2].mean(axis=0), gt[lab == 2].mean(axis=0)
    assert np.abs(g_pred - g_true).max() < 0.12, (g_pred, g_true)
    mse = float(((image - gt) ** 2).mean())
    assert -10 * np.log10(mse) > 20.0  # PSNR on an unseen view, frame 20


RED, BLUE = (0.85, 0.15, 0.1), (0.1, 0.2, 0.85)


def _recolor(rendered):
    """The composite before and after every garment entry of the palette (all but the last, the body's) is
    set to red, or to blue for a garment rendered reddish (chosen by the image, not by the palette entry, which
    need not be the colour the garment shows); with the new colour's hue."""
    run, nf, rgb, labels = rendered
    before = nf.composite()
    lab = _downsample_labels(labels, SIZE)
    shown = before[lab == 2].mean(axis=0)
    new = BLUE if shown[0] > shown[2] else RED
    palette = nf.palette.clone()
    palette[:-1] = torch.tensor(new)
    return before, nf.composite(palette), lab, colorsys.rgb_to_hsv(*new)[0]


def test_recolor_leaves_everything_but_the_garment(rendered):
    before, after, lab, _ = _recolor(rendered)
    change = np.abs(after - before)[lab != 2].mean()
    assert change <= 2 / 255, change


def test_recolor_turns_the_garment_to_the_new_hue(rendered):
    before, after, lab, hue = _recolor(rendered)
    garment = after[lab == 2]
    hues = np.array([colorsys.rgb_to_hsv(*px)[0] for px in garment if px.max() > 0.05])
    apart = np.abs(hues - hue)
    near = np.minimum(apart, 1 - apart) < 0.08  # hue is circular
    assert near.mean() > 0.9, near.mean()
    # the folds stay: the garment's brightness pattern before and after is the same up to scale
    # (measured on the shipped models: correlation 0.98 for the skirt, 0.97 for the t-shirt and 0.998 for the
    # dress; 0.88 for the t-shirt bundled before, O1)
    lum_before, lum_after = before[lab == 2].sum(axis=1), garment.sum(axis=1)
    assert np.corrcoef(lum_before, lum_after)[0, 1] > 0.8


def test_the_culled_preset_keeps_the_tshirt_that_lies_under_the_skin(gl_context, monkeypatch):
    """The bundled t-shirt puts its chest's opacity 5 to 7 cm under the skin (a model trained in the box is
    never told where under the skin its density may go). The `full` preset's culls must keep it: with the
    data's 5 cm under the skin they cut it away and the chest shows holes (pixels far from the `reference`
    render, which culls nothing); with the margin for box-trained runs it matches the reference."""
    from garmentnerf.model.height_band import HEIGHT_MARGIN_IN
    from garmentnerf.render import presets
    from garmentnerf.render.cameras import cameras_for, parse_camera_spec
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    run_dir = demo("tshirt").run_dir
    if not (run_dir / "run.json").is_file():
        pytest.skip("the tshirt demo is not installed")
    torch.set_num_threads(2)
    run = load_run(run_dir)
    frame = 130

    def pixels_off() -> tuple[int, float]:
        """Pixels of the character more than 0.2 off the reference render, and the band's h_min."""
        with RenderSession(run, gl_context, motion="train") as session, torch.no_grad():
            camera = cameras_for(parse_camera_spec("orbit:0:10", run.scene), [frame], 384, run.scene,
                                 [session.body_center(frame)[:2]])[0]
            reference = session.render(frame, camera, preset="reference")
            full = session.render(frame, camera, preset="full")
            diff = np.abs(full.composite() - reference.composite()).max(axis=-1)
            return int((diff[reference.alpha() > 0.5] > 0.2).sum()), session.height_range.h_min

    now, h_min = pixels_off()
    monkeypatch.setattr(presets, "BOX_TRAINED_MARGIN_IN", HEIGHT_MARGIN_IN)
    before, h_min_before = pixels_off()
    # the t-shirt's lowest measured height is the skin (0): the band starts the margin under it
    assert h_min == pytest.approx(-0.10, abs=1e-6)
    assert h_min_before == pytest.approx(-HEIGHT_MARGIN_IN, abs=1e-6)
    assert before >= 10, (now, before)   # the holes: the chest's opacity cut away (15 pixels measured)
    assert now <= 2, (now, before)       # none measured
