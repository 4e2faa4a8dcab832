"""Camera paths: keyframes hit exactly, C1 between them (finite differences), no flips, the Catmull-Rom
tangents against Barry-Goldman's pyramid, constant speed, the JSON round trip, nerfstudio's files
(checked by projecting with OpenGL's convention by hand), and bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial.transform import Rotation, Slerp

from garmentnerf.conventions import look_at, orbit_camera, project_points
from garmentnerf.render.camera_path import (
    CameraPath,
    Keyframe,
    catmull_rom_tangents,
    load_camera_path,
    path_from_json,
    path_to_json,
    save_camera_path,
)


def _orbit_path(constant_speed=False, frames=(0, 12, 20, 41, 55)) -> CameraPath:
    """A dolly around the character: azimuth, elevation, distance and field of view all change."""
    views = [(0, 5, 3.0, 40), (80, 15, 2.5, 35), (150, 10, 3.2, 45), (230, 25, 2.2, 30), (300, 0, 3.5, 40)]
    keys = [Keyframe.from_camera(orbit_camera(a, e, r, (0.1, -0.2, 0.9), 320, 240, fov), f)
            for (a, e, r, fov), f in zip(views, frames)]
    return CameraPath(tuple(keys), 320, 240, 30.0, constant_speed)


def _pose_vector(path: CameraPath, frames) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rotations, positions, fovs = path.interpolator.poses(np.asarray(frames, dtype=np.float64))
    return rotations, positions, fovs


def test_every_keyframe_is_hit_exactly_at_its_frame():
    path = _orbit_path()
    cameras = path.cameras([k.frame for k in path.keyframes])
    for key, cam in zip(path.keyframes, cameras):
        reference = key.camera(320, 240)
        np.testing.assert_allclose(cam.R, reference.R, atol=1e-12)
        np.testing.assert_allclose(cam.center, key.position, atol=1e-12)
        np.testing.assert_allclose(cam.K, reference.K, atol=1e-9)


def test_keyframe_from_camera_round_trips_the_camera():
    cam = orbit_camera(33, 12, 2.7, (0.0, 0.0, 1.0), 640, 360, 37.5)
    back = Keyframe.from_camera(cam, 4).camera(640, 360)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-12)
    np.testing.assert_allclose(back.t, cam.t, atol=1e-12)
    np.testing.assert_allclose(back.K, cam.K, atol=1e-9)


def _jumps(values, frames: np.ndarray, h: float) -> np.ndarray:
    """|left derivative - right derivative| at each of ``frames``, from one-sided differences of
    ``values(x)``, relative to the curve's mean slope between the first and last of ``frames``."""
    span = frames[-1] - frames[0] if len(frames) > 1 else 1.0
    scale = max(1e-9, np.abs(values(frames[-1]) - values(frames[0])).max() / span)
    out = []
    for f in frames:
        left = (values(f) - values(f - h)) / h
        right = (values(f + h) - values(f)) / h
        out.append(np.abs(left - right).max() / scale)
    return np.array(out)


@pytest.mark.parametrize("constant_speed", [False, True])
def test_the_path_is_c1_across_its_keyframes(constant_speed):
    path = _orbit_path(constant_speed)
    interior = np.array([k.frame for k in path.keyframes[1:-1]])  # frames 12, 20, 41
    h = 1e-4

    def position(f):
        return path.interpolator.poses([f])[1][0]

    def rotation_vector(f):  # the rotation relative to the one at the keyframe, as a vector
        return Rotation.from_matrix(path.interpolator.poses([f])[0][0]).as_rotvec()

    def fov(f):
        return path.interpolator.poses([f])[2]

    assert _jumps(position, interior, h).max() < 1e-2
    assert _jumps(rotation_vector, interior, h).max() < 1e-2
    assert _jumps(fov, interior, h).max() < 1e-2
    # the same check sees the kink of piecewise-linear interpolation of the same keyframes
    keys = np.array([k.position for k in path.keyframes])
    knots = np.array([k.frame for k in path.keyframes])

    def linear(f):
        return np.array([np.interp(f, knots, keys[:, d]) for d in range(3)])

    assert _jumps(linear, knots[1:-1], h).min() > 0.1


def test_catmull_rom_tangents_match_barry_goldmans_pyramid():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(4, 3))
    knots = np.array([0.0, 0.7, 2.1, 2.6])

    def pyramid(t):  # Barry and Goldman's recursive evaluation of the segment between points 1 and 2
        p, k = points, knots

        def lerp(a, b, ta, tb):
            return (tb - t) / (tb - ta) * a + (t - ta) / (tb - ta) * b

        a1, a2, a3 = lerp(p[0], p[1], k[0], k[1]), lerp(p[1], p[2], k[1], k[2]), lerp(p[2], p[3], k[2], k[3])
        b1, b2 = lerp(a1, a2, k[0], k[2]), lerp(a2, a3, k[1], k[3])
        return lerp(b1, b2, k[1], k[2])

    spline = CubicHermiteSpline(knots, points, catmull_rom_tangents(knots, points), axis=0)
    for t in np.linspace(knots[1], knots[2], 9):
        np.testing.assert_allclose(spline(t), pyramid(t), atol=1e-12)
    even = np.arange(4.0)
    np.testing.assert_allclose(catmull_rom_tangents(even, points)[1:3], (points[2:] - points[:-2]) / 2, atol=1e-12)


def test_two_keyframes_move_straight_and_turn_as_slerp():
    a = Keyframe.from_camera(orbit_camera(0, 0, 3.0, (0, 0, 1), 64, 64, 40), 0)
    b = Keyframe.from_camera(orbit_camera(70, 20, 3.0, (0, 0, 1), 64, 64, 40), 10)
    path = CameraPath((a, b), 64, 64)
    frames = np.linspace(0, 10, 11)
    rotations, positions, _ = path.interpolator.poses(frames)
    expected = a.position + (frames[:, None] / 10) * (b.position - a.position)
    np.testing.assert_allclose(positions, expected, atol=1e-12)
    slerp = Slerp([0, 10], Rotation.from_matrix(np.stack([a.camera_to_world[:3, :3], b.camera_to_world[:3, :3]])))
    np.testing.assert_allclose(rotations, slerp(frames).as_matrix(), atol=1e-9)


def _turn_keyframe(yaw_degrees: float, frame: float, position=(0.0, 0.0, 1.5)) -> Keyframe:
    yaw = np.radians(yaw_degrees)
    forward = np.array([np.sin(yaw), np.cos(yaw), 0.0])  # yaw 0 looks along +Y, level
    R, t = look_at(position, np.asarray(position) + forward)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R.T, position
    return Keyframe(m, 40.0, frame)


@pytest.mark.parametrize("yaw", [180.0, -180.0, 179.0])
def test_a_half_turn_between_two_keyframes_does_not_flip(yaw):
    path = CameraPath((_turn_keyframe(0.0, 0), _turn_keyframe(yaw, 30)), 64, 64)
    rotations = path.interpolator.poses(np.linspace(0, 30, 301))[0]
    up = -rotations[:, :, 1]  # the image's up in the world
    forward = rotations[:, :, 2]
    assert up[:, 2].min() > 1.0 - 1e-9  # the horizon stays level: no roll, no upside-down frame
    heading = np.unwrap(np.arctan2(forward[:, 0], forward[:, 1]))
    steps = np.diff(heading)
    assert np.all(steps > 0) or np.all(steps < 0)  # turns one way, at an even rate
    assert abs(abs(heading[-1] - heading[0]) - np.radians(abs(yaw))) < 1e-6
    np.testing.assert_allclose(steps, steps.mean(), atol=1e-9)


def test_constant_speed_moves_evenly_and_still_passes_every_keyframe():
    path = _orbit_path(constant_speed=True)
    interp = path.interpolator
    frames = np.linspace(path.first_frame, path.last_frame, 2001)
    rotations, positions, _ = interp.poses(frames)
    travel = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    turn = Rotation.from_matrix(rotations[:-1]).inv() * Rotation.from_matrix(rotations[1:])
    speed = np.hypot(travel, turn.magnitude())
    assert speed.std() / speed.mean() < 0.02
    key_rotations, key_positions, key_fovs = interp.poses_at_parameter(interp.knots)
    for i, key in enumerate(path.keyframes):
        np.testing.assert_allclose(key_positions[i], key.position, atol=1e-12)
        np.testing.assert_allclose(key_rotations[i], key.camera_to_world[:3, :3], atol=1e-9)
        assert key_fovs[i] == pytest.approx(key.fov_y)
    # timed by frame, the same keyframes move at very different speeds
    timed = _orbit_path(constant_speed=False).interpolator.poses(frames)[1]
    timed_travel = np.linalg.norm(np.diff(timed, axis=0), axis=1)
    assert timed_travel.std() / timed_travel.mean() > 0.1


def test_outside_its_span_the_path_holds_its_end_cameras():
    path = _orbit_path()
    before, first = path.cameras([-5.0, path.first_frame])
    after, last = path.cameras([path.last_frame + 7, path.last_frame])
    np.testing.assert_array_equal(before.R, first.R)
    np.testing.assert_array_equal(after.t, last.t)


def test_the_json_file_round_trips(tmp_path):
    path = _orbit_path(constant_speed=True)
    file = save_camera_path(path, tmp_path / "path.json")
    back = load_camera_path(file)
    assert (back.width, back.height, back.fps, back.constant_speed) == (320, 240, 30.0, True)
    for a, b in zip(path.keyframes, back.keyframes):
        np.testing.assert_array_equal(a.camera_to_world, b.camera_to_world)
        assert (a.fov_y, a.frame) == (b.fov_y, b.frame)
    frames = np.linspace(0, 55, 23)
    for a, b in zip(path.cameras(frames), back.cameras(frames)):
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)
    with pytest.raises(FileExistsError):
        save_camera_path(path, file)
    save_camera_path(path.with_keyframes(path.keyframes[:2]), file, overwrite=True)
    assert len(load_camera_path(file).keyframes) == 2


def test_a_nerfstudio_camera_path_loads_in_opengl_convention(tmp_path):
    # nerfstudio's cameras look down -z with +y up; build two such poses by hand
    def gl_pose(eye, target):
        back = np.asarray(eye, float) - np.asarray(target, float)
        back /= np.linalg.norm(back)
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
        return m

    poses = [gl_pose((0.0, -3.0, 1.2), (0.0, 0.0, 0.9)), gl_pose((2.0, -2.0, 1.6), (0.0, 0.0, 0.9))]
    data = {"camera_type": "perspective", "render_width": 200, "render_height": 100, "fps": 24, "seconds": 2 / 24,
            "camera_path": [{"camera_to_world": p.reshape(-1).tolist(), "fov": 50.0, "aspect": 2.0} for p in poses]}
    file = tmp_path / "camera_path.json"
    file.write_text(json.dumps(data))
    path = load_camera_path(file)
    assert (path.width, path.height, path.fps) == (200, 100, 24.0)
    assert [k.frame for k in path.keyframes] == [0.0, 1.0]
    point = np.array([[0.3, 0.2, 1.1]])
    for pose, cam in zip(poses, path.cameras([0, 1])):
        # OpenGL projection by hand: camera coordinates, then pixels with y up and depth along -z
        x, y, z = (np.linalg.inv(pose) @ np.append(point[0], 1.0))[:3]
        f = 0.5 * 100 / np.tan(np.radians(50.0) / 2)
        expected = np.array([(200 - 1) / 2 + f * x / -z, (100 - 1) / 2 - f * y / -z])
        import torch

        uv, depth = project_points(cam, torch.tensor(point))
        np.testing.assert_allclose(uv.numpy()[0], expected, atol=1e-9)
        assert float(depth[0]) == pytest.approx(-z)


def _path_text(**changes) -> str:
    data = {"format": "garmentnerf-camera-path", "version": 1, "width": 64, "height": 48, "fps": 24.0,
            "constant_speed": False, "keyframes": [{"frame": 0, "fov_y": 40, "camera_to_world": np.eye(4).tolist()},
                                                   {"frame": 2, "fov_y": 40, "camera_to_world": np.eye(4).tolist()}]}
    text = json.dumps(data)
    for key, value in changes.items():  # raw JSON text, so that NaN and Infinity can be written
        text = text.replace(f'"{key}": {json.dumps(data[key])}', f'"{key}": {value}', 1)
    return text


@pytest.mark.parametrize("content, message", [
    ("{not json", "not valid JSON"),
    (_path_text(width="Infinity"), "width: Infinity is not a finite number"),
    (_path_text(version="Infinity"), "version: Infinity is not a finite number"),
    (_path_text(fps="NaN"), "fps: NaN is not a finite number"),
    (_path_text(fps="1e999"), "fps: 1e999 is not a finite number"),
    (_path_text(fps="1e308"), "fps must be in 0.1..1000"),
    (_path_text(fps="1e-300"), "fps must be in 0.1..1000"),
    (_path_text(constant_speed='"false"'), "constant_speed must be true or false, got 'false'"),
    (_path_text(width="true"), "width must be a number, got True"),
    (_path_text(width="0"), "width must be a whole number in 8..8192"),
    (_path_text(keyframes='[{"frame": 0, "fov_y": 40, "camera_to_world": [[1, 0, 0, 1e200], [0, 1, 0, 0], '
                          '[0, 0, 1, 0], [0, 0, 0, 1]]}]'), "m from the world's origin"),
    (_path_text(keyframes='[{"frame": 0, "fov_y": 40, "camera_to_world": [["1", 0, 0, 0], [0, 1, 0, 0], '
                          '[0, 0, 1, 0], [0, 0, 0, 1]]}]'), "camera_to_world's entries must be a number"),
    (json.dumps({"camera_path": [{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 40}], "render_width": 0}),
     "render_width must be a whole number in 8..8192"),
    (json.dumps({"camera_path": [{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 40}]}).replace(
        '"fov": 40', '"fov": -Infinity'), "camera_path[0].fov: -Infinity is not a finite number"),
    (json.dumps({"format": "garmentnerf-camera-path", "keyframes": []}), "no keyframes"),
    (json.dumps({"camera_path": []}), "no keyframes"),
    (json.dumps({"something": 1}), "not a camera path"),
    (json.dumps({"format": "garmentnerf-camera-path", "keyframes": [
        {"frame": 0, "fov_y": 40, "camera_to_world": (np.diag([2.0, 1.0, 1.0, 1.0])).tolist()}]}), "not rigid"),
    (json.dumps({"format": "garmentnerf-camera-path", "keyframes": [
        {"frame": 0, "fov_y": 40, "camera_to_world": (np.diag([1.0, 1.0, -1.0, 1.0])).tolist()}]}), "not rigid"),
    (json.dumps({"format": "garmentnerf-camera-path", "keyframes": [
        {"frame": 3, "fov_y": 40, "camera_to_world": np.eye(4).tolist()},
        {"frame": 3, "fov_y": 40, "camera_to_world": np.eye(4).tolist()}]}), "frames must increase"),
    (json.dumps({"format": "garmentnerf-camera-path", "keyframes": [{"frame": 0, "fov_y": 40}]}),
     "no 'camera_to_world'"),
    (json.dumps({"format": "garmentnerf-camera-path", "keyframes": [
        {"frame": 0, "fov_y": 200, "camera_to_world": np.eye(4).tolist()}]}), "fov_y"),
])
def test_bad_path_files_give_one_line_naming_the_file(tmp_path, content, message):
    file = tmp_path / "bad.json"
    file.write_text(content)
    with pytest.raises(ValueError) as info:
        load_camera_path(file)
    text = str(info.value)
    assert message in text and str(file) in text and "\n" not in text


def test_a_keyframe_outside_the_motion_is_refused():
    path = _orbit_path()
    path.check_motion(56)
    with pytest.raises(ValueError, match="keyframe 4 is at frame 55, outside walk \\(50 frames"):
        path.check_motion(50, "walk")
    assert path_from_json(path_to_json(path)).frames() == list(range(0, 56))


def test_a_folder_or_a_missing_file_is_named_as_such(tmp_path):
    with pytest.raises(IsADirectoryError, match=f"{tmp_path}: is a folder, not a camera path file"):
        load_camera_path(tmp_path)
    with pytest.raises(FileNotFoundError, match="no such camera path file"):
        load_camera_path(tmp_path / "nope.json")


def test_a_path_between_two_frames_renders_nothing_and_says_so():
    path = path_from_json(json.loads(_path_text()))
    between = path.with_keyframes([Keyframe(k.camera_to_world, k.fov_y, f) for k, f in zip(path.keyframes, (0.2, 0.8))])
    assert between.frames() == []
    with pytest.raises(ValueError, match=r"its keyframes \(frames 0.2..0.8\) span no whole motion frame"):
        between.render_frames()


# ---- any file: a path or one line (Hypothesis) -----------------------------------------------------------
_json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**400, 10**400) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=5),
    max_leaves=20)
_matrices = st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True) | st.integers(-3, 3), min_size=3,
                              max_size=5), min_size=3, max_size=5)
_keyframes = st.fixed_dictionaries({}, optional={
    "frame": _json_values | st.floats(-5, 60), "fov_y": _json_values | st.floats(-10, 200),
    "camera_to_world": _json_values | _matrices | st.just(np.eye(4).tolist())})
_ours = st.fixed_dictionaries({"format": st.just("garmentnerf-camera-path")}, optional={
    "version": _json_values | st.integers(0, 3), "width": _json_values | st.integers(-5, 9000),
    "height": _json_values | st.integers(-5, 9000), "fps": _json_values | st.floats(-1, 2000),
    "constant_speed": _json_values, "keyframes": st.lists(_keyframes, max_size=4) | _json_values})
_nerfstudio = st.fixed_dictionaries({"camera_path": st.lists(st.fixed_dictionaries({}, optional={
    "camera_to_world": _json_values | st.just(np.eye(4).ravel().tolist()), "fov": _json_values | st.floats(0, 180)}),
    max_size=3) | _json_values}, optional={"render_width": _json_values | st.integers(0, 9000),
                                          "render_height": _json_values, "fps": _json_values,
                                          "seconds": _json_values})


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(_ours, _nerfstudio, _json_values).map(lambda v: json.dumps(v)) | st.text(max_size=40))
def test_any_file_gives_a_path_or_one_line(tmp_path_factory, text):
    file = tmp_path_factory.mktemp("paths") / "path.json"
    file.write_text(text)
    try:
        path = load_camera_path(file)
    except ValueError as exc:
        message = str(exc)
        assert message.startswith(f"{file}: ") and "\n" not in message, message
        return
    assert isinstance(path, CameraPath) and 8 <= path.width <= 8192 and 0.1 <= path.fps <= 1000
    frames = np.linspace(path.first_frame, path.last_frame, 5)
    for camera in path.cameras(frames, (16, 12)):
        assert np.all(np.isfinite(camera.K)) and np.all(np.isfinite(camera.R)) and np.all(np.isfinite(camera.t))
