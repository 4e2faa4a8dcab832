"""Another garment's weights as a run's start (:mod:`garmentnerf.train.transfer`), checked through the
decoder the weights end up in: the start computes the file's radiance, mask and offsets, and its blend
weights in the file's proportions."""

import pytest
import torch

from garmentnerf.model.config import ModelConfig
from garmentnerf.runs import build_model, load_weights, save_weights
from garmentnerf.train.transfer import palette_channel_sources, transfer_garment_state

#: A layered garment's scene colours: inner layer, outer layer, body.
LAYERED_PALETTE = {"garment": [0.5, 0.35, 0.05], "body": [0.41, 0.32, 0.28],
                   "garment_layers": [[0.46, 0.31, 0.04], [0.55, 0.37, 0.05]]}


def test_palette_channel_sources():
    assert palette_channel_sources(2, 3) == [0, 0, 1]      # skirt -> dress: both layers from the garment
    assert palette_channel_sources(2, 2) == [0, 1]
    assert palette_channel_sources(3, 2) == [0, 2]         # dress -> skirt: the inner layer, the body
    assert palette_channel_sources(3, 4) == [0, 1, 1, 2]   # a third layer from the outer one
    with pytest.raises(ValueError, match="at least 2"):
        palette_channel_sources(1, 3)


def _decoded(model, features):
    with torch.no_grad():
        return model.decoder(features)


def test_a_one_layer_run_starts_a_layered_garment_with_shading_normals(tmp_path):
    torch.manual_seed(0)
    skirt = build_model(ModelConfig.tiny())
    with torch.no_grad():  # trained-looking weights: nothing zero or symmetric by chance
        for p in skirt.decoder.parameters():
            p.add_(0.3 * torch.randn_like(p))
    save_weights(tmp_path / "skirt.safetensors", skirt)
    dress_cfg = ModelConfig.tiny().updated({"decoder.palette_size": 3, "nerf.shading_normals": True})
    dress = build_model(dress_cfg, LAYERED_PALETTE)
    dress_palette = dress.palette.colors.detach().clone()
    with pytest.raises(ValueError, match="has shape"):  # without the adapter the shapes do not match
        load_weights(tmp_path / "skirt.safetensors", dress)

    changed = load_weights(tmp_path / "skirt.safetensors", dress, adapt=transfer_garment_state)
    assert {"decoder.head.weight", "decoder.head.bias", "palette.colors", "palette.initial"} <= set(changed)
    assert any(k.startswith("decoder.body.") for k in changed)  # the first conv's input columns

    features = torch.randn(2, ModelConfig.tiny().nerf.zeta_channels, 6, 5)
    normals = torch.randn(2, 3, 6, 5)
    a = _decoded(skirt, features)
    b = _decoded(dress, torch.cat([features, normals], dim=1))
    torch.testing.assert_close(b.radiance, a.radiance)
    torch.testing.assert_close(b.mask, a.mask)
    torch.testing.assert_close(b.offsets[:, 0], a.offsets[:, 0])   # inner layer: the skirt's garment
    torch.testing.assert_close(b.offsets[:, 1], a.offsets[:, 0])   # outer layer: the skirt's garment
    torch.testing.assert_close(b.offsets[:, 2], a.offsets[:, 1])   # body: the body
    # the blend weights: both layers the garment's, in the skirt's proportion to the body's
    torch.testing.assert_close(b.weights[:, 0], b.weights[:, 1])
    torch.testing.assert_close(b.weights[:, 0] / b.weights[:, 2], a.weights[:, 0] / a.weights[:, 1])
    # the colours are the dress scene's, not the skirt's
    torch.testing.assert_close(dress.palette.colors.detach(), dress_palette)
    torch.testing.assert_close(dress.palette.colors.detach()[0], torch.tensor(LAYERED_PALETTE["garment_layers"][0]))


def test_matching_weights_pass_unchanged():
    model = build_model(ModelConfig.tiny())
    own = model.state_dict()
    state = {k: v.clone() for k, v in own.items()}
    assert transfer_garment_state(state, own) == []
    for k, v in own.items():
        assert torch.equal(state[k], v), k


def test_another_garment_of_the_same_palette_size_takes_the_new_scene_colours():
    """The t-shirt from the skirt (two colours each): the file's palette is another garment's, so the new
    scene's colours replace it and the decoder is left as it is; a continuation of the same garment (its
    file packed in float16) keeps the colours it learned."""
    torch.manual_seed(1)
    skirt = build_model(ModelConfig.tiny(), {"garment": [0.03, 0.20, 0.35], "body": [0.41, 0.32, 0.28]})
    with torch.no_grad():
        skirt.palette.colors.add_(0.05)   # learned colours, away from the initial ones
    state = {k: v.detach().clone() for k, v in skirt.state_dict().items()}
    tshirt = build_model(ModelConfig.tiny(), {"garment": [0.44, 0.05, 0.06], "body": [0.41, 0.32, 0.28]})
    own = tshirt.state_dict()
    assert transfer_garment_state(state, own) == ["palette.colors", "palette.initial"]
    torch.testing.assert_close(state["palette.initial"][0], torch.tensor([0.44, 0.05, 0.06]))
    torch.testing.assert_close(state["palette.colors"], own["palette.colors"])
    assert torch.equal(state["decoder.head.weight"], skirt.state_dict()["decoder.head.weight"])

    continued = {k: v.detach().clone().half().float() for k, v in skirt.state_dict().items()}  # a packed demo
    again = build_model(ModelConfig.tiny(), {"garment": [0.03, 0.20, 0.35], "body": [0.41, 0.32, 0.28]})
    assert transfer_garment_state(continued, again.state_dict()) == []
    torch.testing.assert_close(continued["palette.colors"], skirt.palette.colors.detach().half().float())
    assert not torch.allclose(continued["palette.colors"], again.palette.colors.detach(), atol=1e-2)


def test_the_caller_says_which_garment_a_file_is_over_its_starting_colours():
    """A file whose run started from colours that are not its scene's (the bundled dress's) is the same
    garment when the caller says so, and keeps what it learned; a file whose starting colours match is
    another garment's when the caller says that."""
    torch.manual_seed(2)
    scene_colours = {"garment": [0.51, 0.35, 0.05], "body": [0.41, 0.32, 0.28]}
    first = build_model(ModelConfig.tiny(), {"garment": [0.96, 0.66, 0.08], "body": [0.41, 0.32, 0.28]})
    with torch.no_grad():
        first.palette.colors.mul_(1.5).clamp_(0, 1)
    state = {k: v.detach().clone() for k, v in first.state_dict().items()}
    own = build_model(ModelConfig.tiny(), scene_colours).state_dict()
    assert transfer_garment_state(dict(state), own) == ["palette.colors", "palette.initial"]  # colours alone
    kept = dict(state)
    assert transfer_garment_state(kept, own, same_garment=True) == []
    torch.testing.assert_close(kept["palette.colors"], first.palette.colors.detach())
    matching = {k: v.clone() for k, v in own.items()}
    assert transfer_garment_state(matching, own, same_garment=False) == ["palette.colors", "palette.initial"]


def test_run_garment_reads_the_scene_recorded_beside_the_weights(tiny_scene, tmp_path):
    from garmentnerf.runs import create_untrained_run, run_garment

    run = create_untrained_run(tmp_path / "run", tiny_scene.root, ModelConfig.tiny())
    assert run_garment(run) == tiny_scene.garment and run_garment(run)["kind"] == "skirt"
    assert run_garment(tmp_path) is None                     # no run.json
    (run / "run.json").write_text((run / "run.json").read_text().replace(
        '"scene": ', '"scene": "/nonexistent/scene", "was": '))
    assert run_garment(run) is None                          # a scene that is not there


def test_continuing_a_run_whose_palette_started_elsewhere_keeps_its_learned_colours(tiny_scene, gl_context, tmp_path):
    """The trainer's ``--init-weights`` on a file of the same scene whose ``palette.initial`` is not the
    scene's label colours (how the bundled dress's files are): the learned palette is kept. The same file
    without its run.json falls back to the colour test and takes the scene's colours."""
    import shutil

    from safetensors.torch import load_file, save_file

    from garmentnerf.train.settings import TrainConfig
    from garmentnerf.train.trainer import Trainer

    def config(out, init):
        return TrainConfig(scene=tiny_scene.root, out=out, model_config=ModelConfig.tiny(), iterations=2,
                           generator_iterations=1, perceptual="none", progress=False, log_every=1, image_every=0,
                           ckpt_every=100, init_weights=init)

    donor = tmp_path / "donor"
    with Trainer(config(donor, None), gl_context, log=lambda m: None) as tr:
        tr.train()
    weights = load_file(str(donor / "model.safetensors"))
    weights["palette.initial"] = torch.tensor([[0.96, 0.66, 0.08], [0.41, 0.32, 0.28]])
    learned = torch.tensor([[0.8, 0.5, 0.1], [0.45, 0.33, 0.3]])
    weights["palette.colors"] = learned
    save_file(weights, str(donor / "model.safetensors"))

    messages = []
    with Trainer(config(tmp_path / "continued", donor / "model.safetensors"), gl_context, log=messages.append) as tr:
        torch.testing.assert_close(tr.model.palette.colors.detach(), learned)
    assert any("the file's garment: skirt, this scene's" in m for m in messages)

    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(donor / "model.safetensors", alone / "model.safetensors")
    messages = []
    with Trainer(config(tmp_path / "reset", alone / "model.safetensors"), gl_context, log=messages.append) as tr:
        scene_colours = torch.tensor([tiny_scene.palette_init["garment"], tiny_scene.palette_init["body"]])
        torch.testing.assert_close(tr.model.palette.colors.detach(), scene_colours.float())
    assert any("decided by its palette's starting colours" in m for m in messages)
