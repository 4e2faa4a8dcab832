"""Garments, cloth simulation (newton VBD on the CPU) and garment-sequence storage.

The simulation tests share one short run of the skirt on the walk clip (module fixture). The
first run on a machine compiles newton's warp kernels (about a minute, cached afterwards); all
tests use the same solver configuration so that happens once.
"""

from __future__ import annotations

import numpy as np
import pytest

from garmentnerf.data.garment_sequence import GarmentSequence, GarmentSequenceError, load_sequence, save_sequence
from garmentnerf.data.garments import (
    GARMENT_KINDS,
    MIN_CLEARANCE,
    GarmentError,
    body_collision_faces,
    garment_clearance,
    make_garment,
)

newton = pytest.importorskip("newton", reason="cloth simulation needs newton==1.8.0")

from garmentnerf.data.simulate import PENETRATION_BOUND_M, SimSettings, SimulationResumeError, simulate  # noqa: E402

SKIN_TONE = np.array([0.80, 0.63, 0.53])
#: Short settle and small chunks: a few frames exercise settling, chunking and resuming.
FAST = SimSettings(settle_hold_frames=2, settle_frames=4, chunk_frames=3)
FRAMES = 6


_GARMENTS = {}


def garment_of(body, kind, shape="average"):
    if (kind, shape) not in _GARMENTS:
        _GARMENTS[kind, shape] = make_garment(kind, body, shape)
    return _GARMENTS[kind, shape]


@pytest.fixture(scope="module")
def walk(body):
    from garmentnerf.motion.library import load_motion

    return load_motion("walk", body, "average", fps=30)


@pytest.fixture(scope="module")
def uninterrupted(body, walk, tmp_path_factory):
    """The skirt on the first frames of walk, simulated in one go (into a folder)."""
    out = tmp_path_factory.mktemp("sim_full")
    g = garment_of(body, "skirt")
    return g, simulate(g, body, walk, settings=FAST, out_dir=out, progress=False, max_frames=FRAMES), out


# ------------------------------------------------------------------------------------------------
# Garments
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", ["average", "round"])
@pytest.mark.parametrize("kind", GARMENT_KINDS)
def test_garment_outside_rest_body_and_clean(body, kind, shape):
    g = garment_of(body, kind, shape)
    assert g.kind == kind and g.name == kind
    assert 2000 <= g.num_vertices <= 4000
    rest = body.rest(body.betas(shape))[0].numpy()
    faces = body_collision_faces(body)
    # every vertex clearly outside the body (exact closest points with trimesh)
    sd = garment_clearance(g.vertices, rest, faces)
    assert sd.min() >= MIN_CLEARANCE, f"{kind}/{shape}: a vertex is {sd.min() * 1000:.1f} mm from the body"
    mesh = g.to_trimesh()
    # clean triangulation: no degenerate faces, no duplicate vertices, manifold, consistent winding
    assert mesh.is_winding_consistent
    edges = np.sort(np.concatenate([g.faces[:, [0, 1]], g.faces[:, [1, 2]], g.faces[:, [2, 0]]]), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert uses.max() <= 2
    assert np.unique(g.vertices.round(6), axis=0).shape[0] == g.num_vertices
    assert g.edge_lengths().min() > 0.003
    assert mesh.area_faces.min() > 1e-6
    # outward normals: the face normals point away from the body on the whole
    import trimesh

    centroids = mesh.triangles_center
    closest, _, _ = trimesh.proximity.closest_point(trimesh.Trimesh(rest, faces, process=False), centroids)
    assert (np.einsum("ij,ij->i", mesh.face_normals, centroids - closest) > 0).mean() > 0.95
    # uv and color
    assert g.uv.shape == (g.num_vertices, 2) and g.uv.min() >= 0 and g.uv.max() <= 1
    assert np.linalg.norm(g.color - SKIN_TONE) > 0.3
    # pins: skirts at the waistband (the top), the t-shirt at the collar (near the neck)
    assert g.pinned.size > 0
    top = g.vertices[:, 2].max()
    assert np.all(g.vertices[g.pinned, 2] > top - 0.1)


def test_tshirt_sleeves_follow_the_arms(body):
    g = garment_of(body, "tshirt")
    _, joints = body.rest(None)
    for part, side in ((1, "L"), (2, "R")):
        sleeve = g.vertices[g.part == part]
        assert sleeve.shape[0] > 100
        sh = joints[body.joint_index[f"upperarm01.{side}"]].numpy()
        el = joints[body.joint_index[f"lowerarm01.{side}"]].numpy()
        axis = (el - sh) / np.linalg.norm(el - sh)
        rel = sleeve - sh
        radial = np.linalg.norm(rel - (rel @ axis)[:, None] * axis, axis=1)
        # the sleeve is a tube around the upper arm's axis (A-pose: about 48 deg below horizontal)
        assert np.degrees(np.arcsin(-axis[2])) == pytest.approx(48, abs=8)
        assert np.median(radial) < 0.12
        assert (rel @ axis).max() > 0.12


def test_dress_has_two_layers(body):
    g = garment_of(body, "dress")
    assert set(np.unique(g.layer).tolist()) == {0, 1}
    inner, outer = g.vertices[g.layer == 0], g.vertices[g.layer == 1]
    assert inner[:, 2].min() < outer[:, 2].min() - 0.1  # the outer tier is shorter
    mesh = g.to_trimesh()
    assert len(mesh.split(only_watertight=False)) == 2


def test_make_garment_rejects_unknown_kind(body):
    with pytest.raises(GarmentError, match="unknown garment kind 'cape'.*skirt"):
        make_garment("cape", body)


# ------------------------------------------------------------------------------------------------
# Simulation
# ------------------------------------------------------------------------------------------------
def test_short_walk_simulation(body, walk, uninterrupted):
    g, result, _ = uninterrupted
    assert result.vertices.shape == (FRAMES, g.num_vertices, 3)
    assert result.vertices.dtype == np.float32
    assert np.isfinite(result.vertices).all()
    assert result.penetration_max_m.shape == (FRAMES,)
    assert result.penetration_max_m.max() <= PENETRATION_BOUND_M
    assert result.seconds_per_frame > 0 and result.fps == 30
    # The garment moved (gravity, motion) but stayed on the body: no vertex flew off.
    posed = walk.slice(0, FRAMES).pose(body, "average").vertices.numpy()
    last = result.vertices[-1]
    assert np.abs(last - g.vertices).max() > 0.01
    faces = body_collision_faces(body)
    sd = garment_clearance(last, posed[-1], faces)  # an independent check of the penetration
    assert sd.min() >= -PENETRATION_BOUND_M
    assert sd.max() < 0.5
    # pinned vertices ride on the waist: they keep their distance to the body (skinned)
    sd_rest = garment_clearance(g.vertices[g.pinned], body.rest(body.betas("average"))[0].numpy(), faces)
    assert np.abs(sd[g.pinned] - sd_rest).max() < 0.006


def test_resume_equals_uninterrupted(body, walk, uninterrupted, tmp_path):
    g, full, _ = uninterrupted
    out = tmp_path / "sim"
    with pytest.raises(KeyboardInterrupt):
        simulate(g, body, walk, settings=FAST, out_dir=out, progress=False, max_frames=FRAMES,
                 _stop_after_chunks=1)
    assert (out / "chunk_000000.npz").is_file() and not (out / "chunk_000001.npz").exists()
    resumed = simulate(g, body, walk, settings=FAST, out_dir=out, progress=False, max_frames=FRAMES)
    assert resumed.frames_computed == FRAMES - FAST.chunk_frames
    np.testing.assert_array_equal(resumed.vertices, full.vertices)
    np.testing.assert_array_equal(resumed.penetration_max_m, full.penetration_max_m)
    # everything on disk: nothing recomputed
    again = simulate(g, body, walk, settings=FAST, out_dir=out, progress=False, max_frames=FRAMES)
    assert again.frames_computed == 0
    np.testing.assert_array_equal(again.vertices, full.vertices)


def test_resume_refuses_other_inputs(body, walk, uninterrupted):
    g, _, out = uninterrupted
    other = SimSettings(settle_hold_frames=2, settle_frames=4, chunk_frames=3, friction=0.5)
    with pytest.raises(SimulationResumeError, match="settings"):
        simulate(g, body, walk, settings=other, out_dir=out, progress=False, max_frames=FRAMES)


def test_simulate_rejects_garment_of_other_shape(body, walk):
    g = garment_of(body, "skirt")
    with pytest.raises(ValueError, match="another body shape"):
        simulate(g, body, walk, betas="round", settings=FAST, progress=False, max_frames=2)


def test_settings_validation_and_roundtrip():
    s = SimSettings(substeps=12, friction=0.4, self_contact=False)
    assert SimSettings.from_dict(s.to_dict()) == s
    with pytest.raises(ValueError, match="substeps"):
        SimSettings(substeps=0)
    with pytest.raises(ValueError, match="friction"):
        SimSettings(friction=-1.0)
    with pytest.raises(ValueError, match="unknown simulation settings: bogus"):
        SimSettings.from_dict({"bogus": 1})


@pytest.mark.slow
@pytest.mark.timeout(1200)
@pytest.mark.parametrize("kind", GARMENT_KINDS)
def test_each_kind_walk_and_dance_slow(body, kind):
    """All three garments with the default settling on walk followed by dance_a (2 to 9 min each:
    the fast frames take more substeps)."""
    from garmentnerf.motion.library import load_motion

    motion = load_motion("walk,dance_a", body, "average", fps=30)
    g = garment_of(body, kind)
    result = simulate(g, body, motion, progress=False, max_frames=40)
    assert np.isfinite(result.vertices).all()
    assert result.penetration_max_m.max() <= PENETRATION_BOUND_M


# ------------------------------------------------------------------------------------------------
# Storage
# ------------------------------------------------------------------------------------------------
def test_sequence_roundtrip_within_quantisation_error(body, uninterrupted, tmp_path):
    g, result, _ = uninterrupted
    seq = GarmentSequence.from_simulation(g, result, motion="walk")
    path = seq.save(tmp_path / "skirt_walk.npz")
    back = load_sequence(path)
    extent = result.vertices.reshape(-1, 3).max(0) - result.vertices.reshape(-1, 3).min(0)
    bound = extent.max() / (2 * 65535)
    assert back.max_quantization_error == pytest.approx(bound, rel=1e-6)
    assert bound < 0.05e-3  # 0.05 mm for boxes up to 6.5 m
    err = np.abs(back.vertices.astype(np.float64) - result.vertices.astype(np.float64)).max()
    assert err <= bound + 1e-6  # plus float32 rounding
    np.testing.assert_array_equal(back.faces, g.faces)
    np.testing.assert_array_equal(back.color, g.color)
    np.testing.assert_array_equal(back.penetration_max_m, result.penetration_max_m)
    np.testing.assert_array_equal(back.uv, g.uv)
    np.testing.assert_array_equal(back.betas, g.betas)
    np.testing.assert_array_equal(back.layer, g.layer)
    assert back.kind == "skirt" and back.name == "skirt" and back.motion == "walk" and back.fps == 30
    assert SimSettings.from_dict(back.settings) == FAST
    # uint16 + deflate: smaller than the float32 vertices alone, faces and uv included
    assert path.stat().st_size < result.vertices.nbytes


def _synthetic_sequence(T=4, V=50):
    rng = np.random.default_rng(1)
    return dict(vertices=rng.random((T, V, 3)).astype(np.float32) * 2, faces=rng.integers(0, V, (80, 3)),
                color=(0.1, 0.4, 0.7), kind="skirt", penetration_max_m=np.zeros(T), fps=30.0,
                settings={"substeps": 10})


def test_truncated_sequence_rejected(tmp_path):
    fields = _synthetic_sequence(T=40, V=500)
    path = save_sequence(tmp_path / "seq.npz", fields.pop("vertices"), fields.pop("faces"), **fields)
    raw = path.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(GarmentSequenceError, match=r"cut\.npz: field 'vertices_q': truncated"):
        load_sequence(cut)
    cut.write_bytes(raw[:10])
    with pytest.raises(GarmentSequenceError, match=r"cut\.npz"):
        load_sequence(cut)
    with pytest.raises(FileNotFoundError):
        load_sequence(tmp_path / "missing.npz")


def test_sequence_wrong_shapes_rejected(tmp_path):
    f = _synthetic_sequence()
    with pytest.raises(GarmentSequenceError, match="field 'penetration_max_m'"):
        save_sequence(tmp_path / "a.npz", f["vertices"], f["faces"], color=f["color"], kind="skirt",
                      penetration_max_m=np.zeros(3), fps=30.0)
    with pytest.raises(GarmentSequenceError, match="field 'faces'"):
        save_sequence(tmp_path / "a.npz", f["vertices"], f["faces"] + 100, color=f["color"], kind="skirt",
                      penetration_max_m=f["penetration_max_m"], fps=30.0)
    # a file whose arrays disagree: rewrite one member with the wrong length
    path = save_sequence(tmp_path / "b.npz", f["vertices"], f["faces"], color=f["color"], kind="skirt",
                         penetration_max_m=f["penetration_max_m"], fps=30.0)
    with np.load(path) as data:
        members = {k: data[k] for k in data.files}
    members["penetration_max_m"] = np.zeros(7, np.float32)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **members)
    with pytest.raises(GarmentSequenceError, match=r"bad\.npz: field 'penetration_max_m'.*\(4,\)"):
        load_sequence(bad)
    members["vertices_q"] = members["vertices_q"].astype(np.int32)
    np.savez(bad, **members)
    with pytest.raises(GarmentSequenceError, match=r"field 'vertices_q': must be uint16"):
        load_sequence(bad)
    del members["color"]
    np.savez(bad, **members)
    with pytest.raises(GarmentSequenceError, match=r"field 'color': missing"):
        load_sequence(bad)
    assert issubclass(GarmentSequenceError, ValueError)


# ------------------------------------------------------------------------------------------------
# Substeps per frame
# ------------------------------------------------------------------------------------------------
def test_frame_substeps_follow_the_skin_near_the_cloth():
    """Analytic cases: the step limit of the default settings, and the skin's travel near the
    cloth (within NEAR_CLOTH_M) divided by it, between ``substeps`` and MAX_SUBSTEP_FACTOR times it."""
    from garmentnerf.data.simulate import MAX_SUBSTEP_FACTOR, NEAR_CLOTH_M, cloth_step_limit, frame_substeps

    settings = SimSettings()
    limit = cloth_step_limit(settings)
    assert limit == pytest.approx(min(settings.contact_gap,
                                      0.43 * (settings.self_contact_margin + settings.self_contact_gap)))
    assert cloth_step_limit(SimSettings(self_contact=False)) == settings.contact_gap
    cloth = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    skin = np.array([[0.0, 0.0, 0.02], [5.0, 0.0, 0.0]])  # one point 2 cm from the cloth, one far away
    still = frame_substeps(skin, skin, cloth, settings)
    assert still == settings.substeps
    arm = skin + np.array([[0.0, 0.15, 0.0], [0.0, 0.0, 0.0]])  # the near point travels 15 cm
    assert frame_substeps(skin, arm, cloth, settings) == int(np.ceil(0.15 / limit))  # 24 with the defaults
    hand = skin + np.array([[0.0, 0.0, 0.0], [0.0, 0.35, 0.0]])  # only the far point moves
    assert frame_substeps(skin, hand, cloth, settings) == settings.substeps
    beyond = skin + np.array([[0.0, 0.0, NEAR_CLOTH_M - 0.02 + 1e-3], [0.0, 0.0, 0.0]])  # now just out of reach
    assert frame_substeps(beyond, beyond + np.array([[0.0, 0.15, 0.0], [0.0, 0.0, 0.0]]), cloth, settings) == \
        settings.substeps
    thrown = skin + np.array([[0.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    assert frame_substeps(skin, thrown, cloth, settings) == settings.substeps * MAX_SUBSTEP_FACTOR
