"""Exporting a bake as glTF: the garment's colours against the hybrid composition, the best-view partition of
two overlapping views, the file read back by trimesh and pygltflib, and ``garmentnerf export``'s refusals."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from garmentnerf.bake.settings import BakeSettings
from garmentnerf.bake.export import ALPHA_CUTOFF, ExportFrame, garment_mesh, glb_bytes, write_glb
from garmentnerf.bake.store import BakeFolder
from garmentnerf.bake.views import BakedFrame, BakedView, view_mesh
from garmentnerf.cli.main import main
from garmentnerf.conventions import Camera, look_at

PALETTE = np.array([[0.8, 0.2, 0.1], [0.1, 0.3, 0.9], [0.9, 0.7, 0.6]])  # two garment colours, the body's last
FOCAL = 60.0


def _plane_view(azimuth: float = 0.0, size=(48, 40), cell=4, seed=0, colors: int = 2) -> BakedView:
    """A view of the plane y = 0 from 3 m, ``azimuth`` degrees round the z axis from straight ahead (the
    camera on -y); the depth of each feature ray is where its centre meets the plane; random attributes
    (blend weights summing to 1), visibility 1."""
    W, H = size
    K = np.array([[FOCAL, 0, (W - 1) / 2], [0, FOCAL, (H - 1) / 2], [0, 0, 1]])
    a = math.radians(azimuth)
    R, t = look_at([3 * math.sin(a), -3 * math.cos(a), 1.0], [0.0, 0.0, 1.0])
    camera = Camera(K, R, t, W, H)
    u = (np.arange(W // cell) + 0.5) * cell - 0.5
    v = (np.arange(H // cell) + 0.5) * cell - 0.5
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([uu, vv, np.ones_like(uu)], -1) @ np.linalg.inv(K).T  # camera z = 1
    world_dir = rays @ camera.R  # R^T d
    depth = -camera.center[1] / world_dir[..., 1]
    rng = np.random.default_rng(seed)
    layers = rng.uniform(0.1, 0.9, (2 + colors, H, W, 4)).astype(np.float32)
    layers[0, ..., 3] = 1.0
    layers[1, ..., :colors] /= layers[1, ..., :colors].sum(-1, keepdims=True)
    return BakedView.from_values(camera, layers, depth.astype(np.float32), cell)


def _c_g(layers: np.ndarray, rows: np.ndarray, cols: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(N, 3) c_G = clamp(r * sum_i w_i (p_i + o_i), 0, 1) at pixels (rows, cols) of ``layers``."""
    r = layers[0, rows, cols, :3].astype(np.float64)
    total = np.zeros_like(r)
    for i in range(layers.shape[0] - 2):
        total += layers[1, rows, cols, i:i + 1] * (palette[i] + layers[2 + i, rows, cols, :3])
    return np.clip(r * total, 0.0, 1.0)


def _pixels(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uv = (points.astype(np.float64) @ camera.R.T + camera.t) @ camera.K.T
    return np.rint(uv[:, 1] / uv[:, 2]).astype(int), np.rint(uv[:, 0] / uv[:, 2]).astype(int)


def test_garment_colours_are_the_hybrid_composition_and_faint_triangles_go():
    plane = _plane_view(seed=3)
    layers = plane.layers
    layers[2, ..., :3] -= 0.5  # offsets of both signs, and radiance over 1: some colours clamp
    layers[0, ..., :3] *= 1.6
    layers[0, :, :10, 3] = 0.3  # the left ten columns show little garment
    view = BakedView.from_values(plane.camera, layers, plane.depth, plane.cell)
    mesh = garment_mesh(BakedFrame(0, (view,)), PALETTE)
    rows, cols = _pixels(view.camera, mesh.positions)
    assert np.abs(mesh.colors[:, :3] / 255.0 - _c_g(view.layers, rows, cols, PALETTE)).max() <= 0.5 / 255 + 1e-6
    assert np.abs(mesh.colors[:, 3] / 255.0 - view.layers[0, rows, cols, 3]).max() <= 0.5 / 255 + 1e-6
    assert _c_g(view.layers, rows, cols, PALETTE).max() == 1.0  # the clamp was exercised
    # a cell is kept when one of its corners shows garment: columns 9..46 of 47 cells a row
    H, W = view.layers.shape[1:3]
    assert len(mesh.faces) == 2 * (H - 1) * (W - 1 - 9)
    assert cols.min() == 9 and (view.layers[0, rows, cols, 3] >= ALPHA_CUTOFF).mean() < 1.0


def _inside(points: np.ndarray, tri: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(P, T) bool: 2D ``points (P, 2)`` inside triangles ``tri (T, 3, 2)`` (edges included)."""
    a, b, c = (tri[None, :, i] for i in range(3))

    def side(u, v, w):
        return (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (w[..., 0] - u[..., 0])

    out = []
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk, None]
        d1, d2, d3 = side(a, b, p), side(b, c, p), side(c, a, p)
        out.append(~(((d1 < -1e-12) | (d2 < -1e-12) | (d3 < -1e-12)) & ((d1 > 1e-12) | (d2 > 1e-12) | (d3 > 1e-12))))
    return np.concatenate(out)


def test_best_view_partition_keeps_each_part_of_a_plane_once():
    views = (_plane_view(0.0, seed=1), _plane_view(10.0, seed=2))
    mesh = garment_mesh(BakedFrame(0, views), PALETTE)
    # which view each kept triangle came from: its vertices are that view's
    owner = np.full(len(mesh.positions), -1)
    for k, view in enumerate(views):
        keys = {tuple(p) for p in view_mesh(view).positions.tolist()}
        owner[[tuple(p) in keys for p in mesh.positions.tolist()]] = k
    face_owner = owner[mesh.faces[:, 0]]
    assert np.all(owner[mesh.faces] == face_owner[:, None]) and set(face_owner.tolist()) == {0, 1}

    def reach(view, xz):  # a plane view's mesh spans the pixel centres of its image
        world = np.stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]], 1)
        uv = (world @ view.camera.R.T + view.camera.t) @ view.camera.K.T
        u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        return (u >= 0) & (u <= view.camera.width - 1) & (v >= 0) & (v <= view.camera.height - 1)

    def best(xz):  # the camera most aligned with the plane's normal (0, -1, 0), of those whose mesh reaches xz
        world = np.stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]], 1)
        aligned = np.stack([(world - v.camera.center)[:, 1] / np.linalg.norm(world - v.camera.center, axis=1)
                            for v in views])
        seen = np.stack([reach(v, xz) for v in views])
        return np.where(seen, aligned, -np.inf).argmax(0), seen.any(0)

    xs, zs = np.meshgrid(np.linspace(-1.5, 1.5, 97), np.linspace(-0.2, 2.2, 79))
    points = np.stack([xs.ravel(), zs.ravel()], 1) + 1e-4  # off the grids' lines
    want, reached = best(points)
    # clear of the seam and the edges: the same best view 10 cm (two triangles) away in four directions
    clear = reached.copy()
    for d in ([0.1, 0], [-0.1, 0], [0, 0.1], [0, -0.1]):
        there, seen = best(points + d)
        clear &= seen & (there == want)
    assert clear.sum() > 0.4 * len(points) and {0, 1} <= set(want[clear].tolist())
    assert (reach(views[0], points) & reach(views[1], points) & clear & (want == 1)).any()  # a seam in the overlap
    covers = _inside(points[clear], mesh.positions[mesh.faces][..., [0, 2]].astype(np.float64))
    owners = [set(face_owner[row].tolist()) for row in covers]  # a point on a cell's diagonal is in two triangles
    assert all(len(o) == 1 for o in owners), "a hole, or a point kept by both views"
    assert np.array_equal(np.array([o.pop() for o in owners]), want[clear])


def _frames(n: int = 3) -> list[ExportFrame]:
    out = []
    for i in range(n):
        view = _plane_view(5.0 * i, seed=i)
        body = np.array([[0, 0, 0], [0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.3]], np.float32) + 0.1 * i
        out.append(ExportFrame(10 + i, garment_mesh(BakedFrame(10 + i, (view,)), PALETTE), body))
    return out


BODY_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def _accessor(gltf, index: int) -> np.ndarray:
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc.type]
    data = np.frombuffer(gltf.binary_blob(), dtype, acc.count * width, view.byteOffset + (acc.byteOffset or 0))
    return data.reshape(acc.count, width) if width > 1 else data


def test_glb_reads_back_in_trimesh_and_pygltflib(tmp_path):
    import pygltflib
    import trimesh

    frames = _frames(3)
    path = write_glb(tmp_path / "clip.glb", frames, 25.0, BODY_FACES, PALETTE)
    scene = trimesh.load(path)
    counts = sorted(len(g.vertices) for g in scene.geometry.values())
    assert len(scene.geometry) == 2 * len(frames)
    assert counts == sorted([4] * 3 + [len(f.garment.positions) for f in frames])

    gltf = pygltflib.GLTF2.load(str(path))
    names = [n.name for n in gltf.nodes]
    assert names == ["clip", "frame_00010", "frame_00011", "frame_00012"]
    (animation,) = gltf.animations
    assert len(animation.channels) == 3
    for i, channel in enumerate(animation.channels):
        assert channel.target.node == i + 1 and channel.target.path == "scale"
        sampler = animation.samplers[channel.sampler]
        assert sampler.interpolation == "STEP"
        times = _accessor(gltf, sampler.input)
        scales = _accessor(gltf, sampler.output)[:, 0]
        want = [0.0, 1.0, 0.0][1 if i == 0 else 0:]
        want_times = ([] if i == 0 else [0.0]) + [i / 25.0, (i + 1) / 25.0]
        assert np.allclose(times, want_times) and np.array_equal(scales, want)
    # the garment's colours in the file: linear light of the sRGB c_G, alpha the visibility
    for node, frame in zip(gltf.nodes[1:], frames):
        body, garment = gltf.meshes[node.mesh].primitives
        assert np.allclose(_accessor(gltf, body.attributes.POSITION), frame.body_vertices)
        assert np.array_equal(_accessor(gltf, body.indices), BODY_FACES.ravel())
        rgba = _accessor(gltf, garment.attributes.COLOR_0) / 65535.0
        srgb = np.where(rgba[:, :3] <= 0.0031308, rgba[:, :3] * 12.92, 1.055 * rgba[:, :3] ** (1 / 2.4) - 0.055)
        assert np.abs(srgb - frame.garment.colors[:, :3] / 255.0).max() < 1e-3
        assert np.allclose(rgba[:, 3], frame.garment.colors[:, 3] / 255.0, atol=1e-4)
        assert np.array_equal(_accessor(gltf, garment.indices), frame.garment.faces.ravel())
        assert gltf.materials[garment.material].alphaMode == "MASK"
    skin = gltf.materials[0].pbrMetallicRoughness.baseColorFactor
    assert skin[0] == pytest.approx(((PALETTE[2, 0] + 0.055) / 1.055) ** 2.4)
    assert gltf.nodes[1].scale == [1.0, 1.0, 1.0] and gltf.nodes[2].scale == [0.0, 0.0, 0.0]
    # the body's normals point out of the tetrahedron
    normals = _accessor(gltf, gltf.meshes[0].primitives[0].attributes.NORMAL)
    centre = frames[0].body_vertices.mean(0)
    assert np.all(np.sum(normals * (frames[0].body_vertices - centre), axis=1) > 0)


def test_glb_without_a_body_holds_the_garment_alone():
    import pygltflib

    gltf = pygltflib.GLTF2.load_from_bytes(glb_bytes(_frames(1), 30.0, None, PALETTE))
    (primitive,) = gltf.meshes[0].primitives
    assert primitive.material == 1 and primitive.attributes.COLOR_0 is not None


# ---- garmentnerf export ------------------------------------------------------------------------------------
@pytest.fixture()
def bake(tmp_path):
    """A bake folder of a four-frame motion with frames 0 and 1 baked (one plane view each, two garment
    colours, a tetrahedron for a body)."""
    manifest = BakeFolder.manifest_for("m" * 32, "w" * 32, "walk", BakeSettings("custom", views=8, quality=0.5), 4,
                                       fps=30.0, palette=PALETTE)
    folder = BakeFolder.create(tmp_path / "bake", manifest, BODY_FACES)
    for f in _frames(2):
        folder.save_frame(BakedFrame(f.frame - 10, (_plane_view(seed=f.frame),), f.body_vertices))
    return folder


def test_export_writes_the_baked_frames_at_a_palette(bake, tmp_path, capfd):
    import pygltflib

    out = tmp_path / "clip.glb"
    assert main(["export", str(bake.root), "--out", str(out), "--palette", "#ff0000,-,#00ff00", "--no-progress"]) == 0
    line = capfd.readouterr().out.strip()
    assert line.startswith("export: 2 frames (0..1) of walk at 30 fps") and "palette #ff0000, #1a4de5, #00ff00" in line
    gltf = pygltflib.GLTF2.load(str(out))
    assert [n.name for n in gltf.nodes] == ["clip", "frame_00000", "frame_00001"]
    assert gltf.materials[0].pbrMetallicRoughness.baseColorFactor[:3] == [0.0, 1.0, 0.0]
    garment = gltf.meshes[0].primitives[1]
    view = bake.load_frame(0).views[0]
    positions = _accessor(gltf, garment.attributes.POSITION)
    rows, cols = _pixels(view.camera, positions)
    palette = np.array([[1.0, 0, 0], PALETTE[1], [0, 1.0, 0]])
    want = _c_g(view.layers, rows, cols, palette)
    rgba = _accessor(gltf, garment.attributes.COLOR_0) / 65535.0
    srgb = np.where(rgba[:, :3] <= 0.0031308, rgba[:, :3] * 12.92, 1.055 * rgba[:, :3] ** (1 / 2.4) - 0.055)
    assert np.abs(srgb - want).max() <= 0.5 / 255 + 1e-3
    before = out.read_bytes()
    assert main(["export", str(bake.root), "--out", str(out), "--frames", "1", "--overwrite", "--no-progress"]) == 0
    assert out.read_bytes() != before and len(pygltflib.GLTF2.load(str(out)).nodes) == 2


def _digest(root) -> dict:
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("argv, message", [
    (["{bake}", "--out", "{glb}"], "already exists (pass --overwrite"),
    (["{bake}", "--out", "{new}.gltf"], "name it FILE.glb"),
    (["{bake}", "--out", "{new}/sub/clip.glb"], "does not exist"),
    (["{new}", "--out", "{new}.glb"], "not a bake folder (no bake.json)"),
    (["{tmp}", "--out", "{new}.glb"], "not a bake folder (no bake.json)"),
    (["{bake}", "--out", "{new}.glb", "--frames", "0:9"], "--frames 0:9 is out of range for the bake of 'walk' (4 frames"),
    (["{bake}", "--out", "{new}.glb", "--frames", "0:4"], "--frames 0:4: 2 of its 4 frames are not baked yet (2..3; baked: 0..1)"),
    (["{bake}", "--out", "{new}.glb", "--palette", "#zz0000"], "not a hex color"),
    (["{bake}", "--out", "{new}.glb", "--palette", "#ff0000,-,-,#00ff00"], "--palette has 4 colors but the model's palette has 3"),
    (["{bake}", "--out", "{new}.glb", "--palette", "-"], "names no color"),
    (["{damaged}", "--out", "{new}.glb"], "00001.npz: not a readable bake frame"),
    (["{gappy}", "--out", "{new}.glb"], "the frames baked (0, 2) have gaps"),
])
def test_export_refuses_bad_input_in_one_line(bake, tmp_path, capfd, argv, message):
    (tmp_path / "taken.glb").write_bytes(b"the user's file\n")
    damaged = tmp_path / "damaged"
    gappy = tmp_path / "gappy"
    for name in (damaged, gappy):
        copy = BakeFolder.create(name, bake.manifest, BODY_FACES)
        for f in (0, 1):
            copy.save_frame(bake.load_frame(f))
    (damaged / "frames" / "00001.npz").write_bytes(b"PK not a frame")
    (gappy / "frames" / "00001.npz").rename(gappy / "frames" / "00002.npz")
    places = {"bake": str(bake.root), "glb": str(tmp_path / "taken.glb"), "new": str(tmp_path / "new"),
              "tmp": str(tmp_path), "damaged": str(damaged), "gappy": str(gappy)}
    before = _digest(tmp_path)
    code = main(["export", *[a.format(**places) for a in argv], "--no-progress"])
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("garmentnerf: error:"), err
    assert message in lines[0], lines[0]
    assert _digest(tmp_path) == before
