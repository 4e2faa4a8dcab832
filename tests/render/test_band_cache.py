"""The garment's height band is measured once per scene, body and shape, and kept (render/band_cache.py)."""

from __future__ import annotations

import shutil

import pytest
import torch

from garmentnerf.data.scene import Scene
from garmentnerf.model import height_band
from garmentnerf.render import band_cache
from garmentnerf.render.band_cache import SCENE_BAND_FILE, band_key, load_band, save_band, scene_height_range


@pytest.fixture
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("GARMENTNERF_CACHE_DIR", str(folder))
    return folder / "height_band"


@pytest.fixture
def scene(tiny_scene, tmp_path):
    """A copy of the tiny scene (the tests change its files)."""
    root = tmp_path / "scene"
    shutil.copytree(tiny_scene.root, root, ignore=shutil.ignore_patterns("cache"))
    return Scene.load(root)


def _same(a, b):
    return a == b and torch.equal(a.vertex_h_max, b.vertex_h_max)


def test_the_band_is_measured_once_then_read_from_the_cache(scene, body, projector, cache, monkeypatch):
    measured = height_band.measure_height_range(scene, body, None, projector, margin_in=0.1)
    band = scene_height_range(scene, body, None, projector, margin_in=0.1)
    assert _same(band, measured)
    assert [p.name for p in cache.iterdir()] == [f"{band_key(scene, body, None, 0.1)}.safetensors"]

    def no_measuring(*args, **kwargs):
        raise AssertionError("measured again")

    monkeypatch.setattr(band_cache, "measure_height_range", no_measuring)
    assert _same(scene_height_range(scene, body, None, projector, margin_in=0.1), measured)
    # another margin, another key: measured
    with pytest.raises(AssertionError, match="measured again"):
        scene_height_range(scene, body, None, projector, margin_in=0.05)


def test_the_key_follows_the_garment_the_shape_and_the_settings(scene, body):
    key = band_key(scene, body)
    assert key == band_key(Scene.load(scene.root), body)  # the content, not the object
    assert key == band_key(scene, body, body.betas(scene.body.get("shape", "average")))  # None: the scene's shape
    assert key != band_key(scene, body, margin_in=0.2)
    assert key != band_key(scene, body, body.betas("average") + 0.1)
    name = scene.sequence_names("train")[0]
    garment = scene.garment_path(name)
    garment.write_bytes(garment.read_bytes() + b"\0")  # another file content: another key
    assert band_key(Scene.load(scene.root), body) != key


def test_a_scene_carries_its_band_and_a_stale_or_broken_file_is_ignored(scene, body, projector, cache, monkeypatch):
    key = band_key(scene, body)
    shipped = height_band.HeightRange(-0.2, 0.5, "shipped", torch.full((body.template_vertices.shape[0],), 0.3))
    save_band(scene.root / SCENE_BAND_FILE, shipped, key)
    assert _same(scene_height_range(scene, body, None, projector), shipped)  # the scene's own, nothing measured
    assert not cache.exists()
    # a band of another key (the garment changed since) is not used, nor is a damaged cache file
    save_band(scene.root / SCENE_BAND_FILE, shipped, "another key")
    cache.mkdir(parents=True)
    (cache / f"{key}.safetensors").write_bytes(b"not a safetensors file")
    assert load_band(cache / f"{key}.safetensors", key) is None
    band = scene_height_range(scene, body, None, projector)
    assert _same(band, height_band.measure_height_range(scene, body, None, projector))
    assert _same(load_band(cache / f"{key}.safetensors", key), band)  # rewritten


def test_an_unwritable_cache_only_means_measuring(scene, body, projector, tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("GARMENTNERF_CACHE_DIR", str(blocker))
    band = scene_height_range(scene, body, None, projector)
    assert _same(band, height_band.measure_height_range(scene, body, None, projector))
