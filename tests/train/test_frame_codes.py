"""Per-frame codes (``ModelConfig.frame_code_resolution``): one learned residual of E's output per
training frame, trained with the run, resumed exactly, recorded in the run, and used by a render of
the run's own training sequence only."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from train.test_train import assert_same_steps, make_tc, run

from garmentnerf.model.config import DYNAMIC_FEATURE_DIM, ModelConfig
from garmentnerf.runs import frame_code_offset, load_run

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def codes_config(changes: dict | None = None) -> ModelConfig:
    return ModelConfig.tiny().updated({"frame_codes.resolution": 4, "frame_codes.lr_scale": 20.0, **(changes or {})})


def test_a_run_trains_one_code_per_training_frame_and_resumes_exactly(tiny_scene, gl_context, tmp_path):
    from garmentnerf.train.trainer import Trainer, param_groups

    cfg = codes_config({"schedule.iterations": 4})
    full, full_state = run(make_tc(tiny_scene, tmp_path / "a", generator_iterations=0, iterations=4,
                                   model_config=cfg), gl_context)
    n = tiny_scene.num_frames("train")
    codes = full_state["frame_codes.codes"]
    assert codes.shape == (n, DYNAMIC_FEATURE_DIM, 4, 4)
    assert (codes.flatten(1).abs().amax(dim=1) > 0).any()  # visited frames' codes moved from zero
    loaded = load_run(tmp_path / "a")
    assert loaded.config.frame_codes.count == n and loaded.model.frame_codes.codes.shape[0] == n
    record = json.loads((tmp_path / "a" / "run.json").read_text())["frame_codes"]
    assert record["offsets"] == {"train": 0} and len(record["scene"]) == 16
    with Trainer(make_tc(tiny_scene, tmp_path / "g", generator_iterations=0, model_config=cfg), gl_context,
                 log=lambda m: None) as tr:
        groups = param_groups(tr.model, list(tr.model.parameters()), tr.cfg.frame_codes.lr_scale)
        scaled = [g for g in groups if any(p is tr.model.frame_codes.codes for p in g["params"])]
        assert len(scaled) == 1 and scaled[0]["lr_scale"] == 20.0 and len(scaled[0]["params"]) == 1
        assert tr.code_index("train", 2) == 2 and tr.code_index("test", 0) is None
    # interrupted after two steps and resumed: the same steps and the same codes
    part, _ = run(make_tc(tiny_scene, tmp_path / "b", generator_iterations=0, iterations=4, model_config=cfg,
                          stop_after=2), gl_context)
    rest, rest_state = run(make_tc(tiny_scene, tmp_path / "b", resume=True, generator_iterations=0, iterations=4),
                           gl_context)
    assert [h["step"] for h in rest.history] == [3, 4]
    assert_same_steps(full.history[2:], rest.history, full_state, rest_state)


def test_the_code_is_added_to_e_upsampled_and_only_for_the_runs_training_sequence(tiny_scene, gl_context, tmp_path):
    from garmentnerf.render.session import RenderSession

    run(make_tc(tiny_scene, tmp_path / "r", generator_iterations=0, iterations=1, model_config=codes_config({"schedule.iterations": 1})),
        gl_context)
    loaded = load_run(tmp_path / "r")
    model = loaded.model
    with torch.no_grad():
        model.frame_codes.codes.zero_()
        model.frame_codes.codes[1] = 2.5  # a constant code: upsampled bilinearly it stays 2.5 everywhere
        ramp = torch.arange(4.0).view(1, 4).expand(4, 4)  # along x: a linear ramp stays one between texel centres
        model.frame_codes.codes[2] = ramp
    with RenderSession(loaded, gl_context, motion="train") as session:
        assert session._code_offset == 0
        inputs = session.builder.build(session.posed, 1, session.fps)
        with torch.no_grad():
            plain = model.prepare_frame(inputs).dynamic_features
        coded, _ = session.frame_features(1)
        torch.testing.assert_close(coded.dynamic_features - plain, torch.full_like(plain, 2.5), atol=1e-5, rtol=0)
        R = plain.shape[-1]
        up = model.frame_code(2, R)[0].detach()
        x = (np.arange(R) + 0.5) * 4 / R - 0.5  # texel centres of R in the code's 4 texels (align_corners=False)
        np.testing.assert_allclose(up[0].numpy(), np.clip(x, 0, 3), atol=1e-5)
    with RenderSession(loaded, gl_context, motion="walk") as session:  # a library motion: no codes
        assert session._code_offset is None
        inputs = session.builder.build(session.posed, 1, session.fps)
        feats, _ = session.frame_features(1)
        with torch.no_grad():
            torch.testing.assert_close(feats.dynamic_features, model.prepare_frame(inputs).dynamic_features)
    # another scene (a copy with another scene.json) does not get the codes of this one's "train"
    other = tmp_path / "other_scene"
    shutil.copytree(tiny_scene.root, other)
    info = json.loads((other / "scene.json").read_text())
    info["garment"]["color"] = [0.1, 0.2, 0.3]
    (other / "scene.json").write_text(json.dumps(info))
    from garmentnerf.data.scene import Scene

    assert frame_code_offset(loaded.info, tiny_scene, "train") == 0
    assert frame_code_offset(loaded.info, Scene.load(other), "train") is None
    assert frame_code_offset(loaded.info, tiny_scene, "test") is None
    with pytest.raises(ValueError, match="out of range"):
        model.frame_code(tiny_scene.num_frames("train"), 8)


def test_codes_start_from_weights_trained_without_them(tiny_scene, gl_context, tmp_path):
    """``--init-weights`` of a run without codes into a config with codes: the codes start at zero, so
    the first step's model computes what the weights' own model computes (the same first loss)."""
    plain, plain_state = run(make_tc(tiny_scene, tmp_path / "plain", generator_iterations=0, iterations=1), gl_context)
    both = {}
    for name, cfg in (("again", ModelConfig.tiny()), ("codes", codes_config())):
        result, _ = run(make_tc(tiny_scene, tmp_path / name, generator_iterations=0, iterations=1, model_config=cfg,
                                init_weights=tmp_path / "plain" / "model.safetensors"), gl_context)
        both[name] = result.history[0]
    assert both["codes"]["total"] == pytest.approx(both["again"]["total"], abs=1e-6)


def test_a_codes_stage_holds_every_other_weight_exactly_and_resumes_exactly(tiny_scene, gl_context, tmp_path):
    """``trained_parameters=("frame_codes.",)`` on weights trained without codes: after the stage every
    weight but the codes is the starting one to the bit, no gradient was computed for them, and an
    interrupted stage resumes exactly."""
    from garmentnerf.train.trainer import Trainer

    _, plain_state = run(make_tc(tiny_scene, tmp_path / "plain", generator_iterations=0, iterations=1), gl_context)
    start = tmp_path / "plain" / "model.safetensors"
    cfg = codes_config({"schedule.iterations": 4, "schedule.trained_parameters": ("frame_codes.",)})
    tc = make_tc(tiny_scene, tmp_path / "codes", generator_iterations=0, iterations=4, model_config=cfg,
                 init_weights=start)
    with Trainer(tc, gl_context, log=lambda m: None) as tr:
        full = tr.train()
        held = [(name, p) for name, p in tr.model.named_parameters() if not name.startswith("frame_codes.")]
        assert held and all(p.grad is None and not p.requires_grad for _, p in held)
        state = {k: v.detach().clone() for k, v in tr.model.state_dict().items()}
    assert plain_state.keys() == state.keys() - {"frame_codes.codes"}
    assert all(torch.equal(state[k], v) for k, v in plain_state.items())
    assert (state["frame_codes.codes"].flatten(1).abs().amax(dim=1) > 0).any()
    run(make_tc(tiny_scene, tmp_path / "part", generator_iterations=0, iterations=4, model_config=cfg,
                init_weights=start, stop_after=2), gl_context)
    rest, rest_state = run(make_tc(tiny_scene, tmp_path / "part", resume=True, generator_iterations=0, iterations=4),
                           gl_context)
    assert_same_steps(full.history[2:], rest.history, state, rest_state)


def test_a_trained_parameters_prefix_the_model_lacks_is_refused(tiny_scene, gl_context, tmp_path):
    from garmentnerf.train.trainer import Trainer

    cfg = ModelConfig.tiny().updated({"schedule.iterations": 1, "schedule.trained_parameters": ("frame_codes.",)})  # no codes in this model
    with pytest.raises(ValueError, match=r"trained_parameters: no parameter of the model starts with 'frame_codes\.'"):
        with Trainer(make_tc(tiny_scene, tmp_path / "x", generator_iterations=0, iterations=1, model_config=cfg),
                     gl_context, log=lambda m: None) as tr:
            tr.train()
    with pytest.raises(ValueError, match="empty prefix"):
        ModelConfig.tiny().updated({"schedule.trained_parameters": ("",)})


def test_sparse_codes_hold_the_garments_footprint_start_from_dense_ones_and_resume_exactly(tiny_scene, gl_context,
                                                                                         tmp_path):
    """``frame_code_support_margin``: a new run's codes are held on the texels its garment's closest body
    points read over the training frames (grown by the margin) and start from a dense-codes file's codes
    resampled to their resolution; the support goes with the weights into the run and its checkpoints,
    a resumed run takes the same steps, and the codes stay zero off the support."""
    from safetensors.torch import load_file

    from garmentnerf.data.scene import read_garment_arrays
    from garmentnerf.model.frame_codes import garment_texels, grow_texels, resample_codes
    from garmentnerf.train.trainer import Trainer

    run(make_tc(tiny_scene, tmp_path / "dense", generator_iterations=0, iterations=1,
                model_config=codes_config({"schedule.iterations": 1})), gl_context)
    start = tmp_path / "dense" / "model.safetensors"
    cfg = codes_config({"schedule.iterations": 4, "frame_codes.resolution": 8, "frame_codes.support_margin": 1})
    with Trainer(make_tc(tiny_scene, tmp_path / "s", generator_iterations=0, model_config=cfg, init_weights=start),
                 gl_context, log=lambda m: None) as tr:
        held = tr.model.frame_codes
        expected = resample_codes(load_file(start)["frame_codes.codes"], 8).flatten(2)[:, :, held.support.flatten()]
        torch.testing.assert_close(held.codes.detach(), expected)
    full, full_state = run(make_tc(tiny_scene, tmp_path / "a", generator_iterations=0, iterations=4,
                                   model_config=cfg, init_weights=start), gl_context)
    support = full_state["frame_codes.support"]
    loaded = load_run(tmp_path / "a")
    hit = torch.zeros(8, 8, dtype=torch.bool)
    vertices = read_garment_arrays(tiny_scene.garment_path("train")).vertices
    posed = tiny_scene.load_motion("train").pose(loaded.model.body, loaded.info.get("body", {}).get("shape"))
    for frame in range(len(vertices)):
        uv = loaded.model.projector.project(torch.from_numpy(np.asarray(vertices[frame], np.float32)),
                                            posed.vertices[frame].float()).uv
        hit |= garment_texels(uv, 8)
    assert torch.equal(support, grow_texels(hit, 1)) and 0 < int(support.sum()) < 64
    assert full_state["frame_codes.codes"].shape == (tiny_scene.num_frames("train"), DYNAMIC_FEATURE_DIM,
                                                     int(support.sum()))
    assert torch.equal(loaded.model.frame_codes.support, support)
    torch.testing.assert_close(loaded.model.frame_codes.codes.detach(), full_state["frame_codes.codes"])
    # interrupted after two steps and resumed: the same steps, the same support and codes
    run(make_tc(tiny_scene, tmp_path / "b", generator_iterations=0, iterations=4, model_config=cfg,
                init_weights=start, stop_after=2), gl_context)
    rest, rest_state = run(make_tc(tiny_scene, tmp_path / "b", resume=True, generator_iterations=0, iterations=4),
                           gl_context)
    assert_same_steps(full.history[2:], rest.history, full_state, rest_state)
    for i in range(tiny_scene.num_frames("train")):
        assert torch.count_nonzero(loaded.model.frame_codes.dense(i)[:, ~support]) == 0
    with pytest.raises(ValueError, match="frame_codes.support_margin needs codes"):
        ModelConfig.tiny().updated({"frame_codes.support_margin": 0})
    with pytest.raises(ValueError, match="frame_codes.support_margin must be -1"):
        codes_config({"frame_codes.support_margin": -2})
