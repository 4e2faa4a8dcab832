"""Motions: the Motion container, DeepMimic retargeting, resampling/blending, AMASS, the library."""

from __future__ import annotations

import math

import numpy as np
import pytest
import roma
import torch
from scipy.spatial.transform import Rotation, Slerp

from garmentnerf.body.model import BodyModel
from garmentnerf.body.smpl import SMPL_JOINT_NAMES
from garmentnerf.motion.amass import AmassError, load_amass
from garmentnerf.motion.blend import concatenate, resample, slerp_rotvec, yaw_angle
from garmentnerf.motion.deepmimic import (
    DEEPMIMIC_CLIPS,
    DEFAULT_ARM_ABDUCTION_DEG,
    DeepMimicClip,
    a_pose_correction_deg,
    load_deepmimic,
    read_deepmimic,
    retarget_deepmimic,
)
from garmentnerf.motion.library import FrameRangeError, UnknownMotionError, available_motions, check_frame, load_motion
from garmentnerf.motion.motion import Motion
from garmentnerf.motion.procedural import PROCEDURAL_MOTIONS, procedural_motion


@pytest.fixture(scope="module")
def walk(body) -> Motion:
    return load_deepmimic("walk", body)


def joint_positions(body: BodyModel, motion: Motion) -> torch.Tensor:
    """(T, J, 3) posed joint positions."""
    posed = motion.pose(body)
    _, rest_j = body.rest()
    A = posed.joint_transforms
    return torch.einsum("tjab,jb->tja", A[..., :3], rest_j) + A[..., 3] + posed.translation[:, None]


def step_angles(motion: Motion) -> torch.Tensor:
    """(T-1, J) rotation angle between consecutive frames of every joint, radians."""
    R = roma.rotvec_to_rotmat(motion.rotations.double())
    return roma.rotmat_geodesic_distance(R[1:], R[:-1])


def random_motion(T=5, J=4, seed=0, name="rand", fps=30.0) -> Motion:
    g = torch.Generator().manual_seed(seed)
    rot = (torch.rand(T, J, 3, generator=g) - 0.5) * 2.0
    trans = torch.rand(T, 3, generator=g)
    return Motion(name, [f"j{i}" for i in range(J)], rot, trans, fps, "anny")


# ---- Motion ------------------------------------------------------------------------------------
def test_motion_validation_and_nan(body):
    m = random_motion()
    assert m.num_frames == 5 and m.duration == pytest.approx(5 / 30)
    bad = m.rotations.clone()
    bad[3, 1, 2] = float("nan")
    with pytest.raises(ValueError, match=r"motion 'rand'.*NaN.*frame 3"):
        Motion("rand", m.joint_names, bad, m.translation, 30.0)
    with pytest.raises(ValueError, match="fps"):
        Motion("rand", m.joint_names, m.rotations, m.translation, 0.0)
    with pytest.raises(ValueError, match="shape"):
        Motion("rand", m.joint_names[:3], m.rotations, m.translation, 30.0)
    with pytest.raises(ValueError, match="at least 1 frame"):
        Motion("rand", m.joint_names, m.rotations[:0], m.translation[:0], 30.0)


def test_motion_save_load_roundtrip_exact(tmp_path):
    m = random_motion(T=7, J=6, seed=3, fps=24.0)
    path = m.save(tmp_path / "clip.npz")
    back = Motion.load(path)
    assert back.name == m.name and back.joint_names == m.joint_names and back.skeleton == m.skeleton
    assert back.fps == m.fps
    assert torch.equal(back.rotations, m.rotations) and torch.equal(back.translation, m.translation)
    assert not list(tmp_path.glob(".*.tmp"))  # the atomic write left no temporary file


def test_motion_load_errors_name_file_and_field(tmp_path):
    p = tmp_path / "broken.npz"
    np.savez(p, name="x", joint_names=np.array(["a"]), rotations=np.zeros((2, 1, 3)),
             translation=np.zeros((3, 3)), fps=30.0, skeleton="anny")
    with pytest.raises(ValueError, match=r"broken\.npz.*translation"):
        Motion.load(p)
    np.savez(p, name="x", joint_names=np.array(["a"]), rotations=np.zeros((2, 1, 3)))
    with pytest.raises(ValueError, match=r"broken\.npz.*missing.*translation"):
        Motion.load(p)


def test_slice_and_check_frame(walk):
    part = walk.slice(5, 9)
    assert part.num_frames == 4 and torch.equal(part.rotations, walk.rotations[5:9])
    assert check_frame(walk, walk.num_frames - 1) == walk.num_frames - 1
    for bad in (walk.num_frames, -1):
        with pytest.raises(FrameRangeError, match=r"out of range for motion 'walk' \(39 frames: 0\.\.38\)"):
            check_frame(walk, bad)
    with pytest.raises(ValueError, match="empty"):
        walk.slice(10, 10)


def test_rotations_for_maps_by_name_and_rejects_foreign_skeleton(body):
    m = Motion("two", ["head", "not_a_joint"], torch.ones(2, 2, 3) * 0.1, torch.zeros(2, 3), 30.0)
    r = m.rotations_for(body)
    assert r.shape == (2, body.num_joints, 3)
    assert torch.allclose(r[:, body.joint_index["head"]], torch.full((2, 3), 0.1))
    assert r.abs().sum() == pytest.approx(2 * 3 * 0.1)
    smpl = Motion("x", list(SMPL_JOINT_NAMES), torch.zeros(1, 24, 3), torch.zeros(1, 3), 30.0, "smpl")
    with pytest.raises(ValueError, match="motion 'x' is for the smpl skeleton, body '.*' uses the anny skeleton"):
        smpl.rotations_for(body)
    other = Motion("y", ["hand_l", "hand_r"], torch.zeros(1, 2, 3), torch.zeros(1, 3), 30.0, "custom")
    with pytest.raises(ValueError, match="motion 'y' is for the custom skeleton, body '.*' has none of its joints"):
        other.rotations_for(body)


# ---- DeepMimic retargeting ---------------------------------------------------------------------
def test_deepmimic_clips_parse_and_retarget_finite(body):
    assert len(DEEPMIMIC_CLIPS) == 15
    for name in DEEPMIMIC_CLIPS:
        clip = read_deepmimic(name)
        assert clip.frames.shape[1] == 44 and np.all(np.diff(clip.times) > 0)
        rot, trans = retarget_deepmimic(clip, body)
        assert torch.isfinite(rot).all() and torch.isfinite(trans).all(), name


def test_walk_feet_on_ground_forward_upright(body, walk):
    """Tolerance: the lowest vertex of every frame within 2 cm of z = 0 (measured: -0.6..+0.3 cm)."""
    assert walk.fps == 30.0 and walk.num_frames == 39
    v = walk.pose(body).vertices
    assert torch.isfinite(v).all()
    lowest = v[..., 2].min(dim=1).values
    assert lowest.abs().max() < 0.02, lowest
    assert lowest.mean().abs() < 0.01
    # Walks forward, i.e. towards -Y (the way the character faces), about 1.2 m in 1.3 s.
    travel = walk.translation[-1] - walk.translation[0]
    assert travel[1] < -1.0 and travel[0].abs() < 0.1
    # Upright: the head stays high; the toes of the supporting (lower) foot point forward (-Y).
    # (The swinging foot may point down: DeepMimic's walk plantarflexes it by up to 80 degrees.)
    joints = joint_positions(body, walk)
    ix = body.joint_index
    assert (joints[:, ix["head"], 2] > 1.35).all()
    left_lower = joints[:, ix["foot.L"], 2] < joints[:, ix["foot.R"], 2]
    toe_dir = torch.where(left_lower[:, None], joints[:, ix["toe3-1.L"]] - joints[:, ix["foot.L"]],
                          joints[:, ix["toe3-1.R"]] - joints[:, ix["foot.R"]])
    assert (toe_dir[:, 1] < -0.05).all()


def test_run_feet_near_ground(body):
    """The run clip itself sinks its soles to -6.8 cm at landings; the retarget must not add much."""
    run = load_deepmimic("run", body)
    lowest = run.pose(body).vertices[..., 2].min(dim=1).values
    assert lowest.min() > -0.08 and lowest.mean().abs() < 0.03
    assert (run.translation[-1, 1] - run.translation[0, 1]) < -2.0


def test_knees_bend_backwards_elbows_forwards(body):
    run = load_deepmimic("run", body)
    J = joint_positions(body, run)
    ix = body.joint_index
    for s in "LR":
        hip, knee, ankle = J[:, ix[f"upperleg01.{s}"]], J[:, ix[f"lowerleg01.{s}"]], J[:, ix[f"foot.{s}"]]
        shoulder, elbow, wrist = J[:, ix[f"upperarm01.{s}"]], J[:, ix[f"lowerarm01.{s}"]], J[:, ix[f"wrist.{s}"]]
        # With the character facing -Y, a knee bent the right way sticks out towards -Y from the
        # hip-ankle line, and an elbow sticks out towards +Y from the shoulder-wrist line.
        knee_out = knee[:, 1] - 0.5 * (hip[:, 1] + ankle[:, 1])
        elbow_out = elbow[:, 1] - 0.5 * (shoulder[:, 1] + wrist[:, 1])
        assert knee_out.min() < -0.05 and knee_out.max() < 0.02, (s, knee_out)
        assert elbow_out.max() > 0.03 and elbow_out.min() > -0.02, (s, elbow_out)


def test_a_pose_correction_on_deepmimic_rest_pose(body):
    """DeepMimic's rest pose (all rotations identity) has vertical legs and arms hanging straight
    down; anny's A-pose arms are corrected by ~41.7 degrees (plus the default abduction)."""
    assert a_pose_correction_deg(body) == pytest.approx(41.7, abs=1.0)
    frames = np.zeros((1, 44))
    frames[:, [4, 8, 12, 16, 21, 25, 30, 35, 39]] = 1.0  # identity quaternions (w first)
    frames[:, 2] = 0.8814
    rest_clip = DeepMimicClip("rest", np.zeros(1), frames, "none", 30.0)
    rot, trans = retarget_deepmimic(rest_clip, body)
    m = Motion("dmrest", body.joint_names, rot.float(), trans.float(), 30.0)
    J = joint_positions(body, m)[0]
    ix = body.joint_index
    for s, sign in (("L", 1.0), ("R", -1.0)):
        arm = J[ix[f"lowerarm01.{s}"]] - J[ix[f"upperarm01.{s}"]]
        tilt = math.degrees(math.atan2(sign * float(arm[0]), -float(arm[2])))
        assert tilt == pytest.approx(DEFAULT_ARM_ABDUCTION_DEG, abs=0.5)
        assert abs(float(arm[1])) < 1e-4
        thigh = J[ix[f"lowerleg01.{s}"]] - J[ix[f"upperleg01.{s}"]]
        assert thigh[:2].norm() < 1e-4
    assert m.pose(body).vertices[0, :, 2].min().abs() < 0.01  # standing on the ground


# ---- resampling and blending -------------------------------------------------------------------
def test_resample_reproduces_frames_and_matches_independent_slerp(walk):
    up = resample(walk, 60.0)
    assert up.num_frames == 2 * walk.num_frames - 1  # the last frame at 38/30 s lies on the new grid
    assert torch.allclose(up.rotations[::2], walk.rotations, atol=1e-6)
    assert torch.allclose(up.translation[::2], walk.translation, atol=1e-6)
    # Halfway frames against roma's quaternion slerp (shortest arc), computed independently.
    q = roma.rotvec_to_unitquat(walk.rotations.double())
    for i in (0, 7, 20):
        half = roma.unitquat_slerp(q[i], q[i + 1], torch.tensor([0.5], dtype=torch.float64))[0]
        got = roma.rotvec_to_unitquat(up.rotations[2 * i + 1].double())
        dist = roma.rotmat_geodesic_distance(roma.unitquat_to_rotmat(half), roma.unitquat_to_rotmat(got))
        assert dist.max() < 1e-5
        assert torch.allclose(up.translation[2 * i + 1], 0.5 * (walk.translation[i] + walk.translation[i + 1]),
                              atol=1e-6)
    # And against scipy at an arbitrary rate: 30 -> 24 fps, frame k at k/24 s.
    down = resample(walk, 24.0)
    assert down.num_frames == math.floor(38 / 30 * 24) + 1
    j = body_joint = 50
    times = np.arange(walk.num_frames) / 30.0
    ref = Slerp(times, Rotation.from_rotvec(walk.rotations[:, body_joint].double().numpy()))
    want = ref(np.arange(down.num_frames) / 24.0)
    got = Rotation.from_rotvec(down.rotations[:, j].double().numpy())
    assert np.max((want.inv() * got).magnitude()) < 1e-5


def test_slerp_rotvec_endpoints_and_shortest_arc():
    r0 = torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64)
    r1 = torch.tensor([[0.0, 0.0, -3.0]], dtype=torch.float64)  # 0.28 rad apart through pi
    mid = slerp_rotvec(r0, r1, torch.tensor([0.5]))
    assert roma.rotvec_geodesic_distance(mid, torch.tensor([[0.0, 0.0, math.pi]], dtype=torch.float64)) < 1e-9


def test_concatenate_is_continuous_at_the_seam(body, walk):
    dance = resample(load_deepmimic("dance_a", body), 30.0)
    n = 10
    both = concatenate([walk, dance], blend_frames=n, body=body)
    assert both.num_frames == walk.num_frames + dance.num_frames - n
    seam = slice(walk.num_frames - n - 1, walk.num_frames)  # every step into, through and out of the fade
    steps = step_angles(both).max(dim=1).values
    typical = torch.cat([step_angles(walk).max(dim=1).values, step_angles(dance).max(dim=1).values])
    assert steps[seam].max() <= 1.2 * torch.quantile(typical, 0.95), (steps[seam], typical.max())
    root_steps = (both.translation[1:] - both.translation[:-1]).norm(dim=1)
    clip_root_steps = torch.cat([(m.translation[1:] - m.translation[:-1]).norm(dim=1) for m in (walk, dance)])
    assert root_steps[seam].max() <= 1.2 * clip_root_steps.max()
    # Heights are kept: after the fade the dance's root height is unchanged.
    assert torch.allclose(both.translation[walk.num_frames:, 2], dance.translation[n:, 2], atol=1e-6)


def test_concatenate_continues_position_and_heading(body, walk):
    # B = the walk turned by 90 degrees and moved away: concatenation must undo that.
    turn = torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64)
    Rz = roma.rotvec_to_rotmat(turn)
    rot = walk.rotations.double().clone()
    rot[:, 0] = roma.rotmat_to_rotvec(Rz @ roma.rotvec_to_rotmat(rot[:, 0]))
    trans = walk.translation.double() @ Rz.T + torch.tensor([5.0, -3.0, 0.0], dtype=torch.float64)
    turned = Motion("turned", walk.joint_names, rot.float(), trans.float(), walk.fps)
    both = concatenate([walk, turned], blend_frames=0, body=body)
    a_end = walk.num_frames - 1
    assert torch.allclose(both.translation[a_end + 1, :2], walk.translation[-1, :2], atol=1e-5)
    # The second walk goes on in the same direction (-Y) as the first (within 3 degrees).
    second = both.translation[a_end + 1:]
    d = second[-1] - second[0]
    assert d[1] < -1.0 and abs(math.degrees(math.atan2(float(d[0]), -float(d[1])))) < 3.0
    # A clip with a constant heading is aligned exactly.
    still = Motion("still", ["root"], torch.tensor([[[0.0, 0.0, 1.0]]]).repeat(3, 1, 1), torch.zeros(3, 3), 30.0)
    turned_still = Motion("t", ["root"], torch.tensor([[[0.0, 0.0, -2.0]]]).repeat(3, 1, 1),
                          torch.tensor([[1.0, 2.0, 0.5]]).repeat(3, 1), 30.0)
    joined = concatenate([still, turned_still], blend_frames=0)
    yaw = yaw_angle(roma.rotvec_to_rotmat(joined.rotations[:, 0].double()))
    assert torch.allclose(yaw, torch.ones(6, dtype=torch.float64), atol=1e-6)
    assert torch.allclose(joined.translation[3:], torch.tensor([[0.0, 0.0, 0.5]]).repeat(3, 1), atol=1e-6)


def test_concatenate_requires_matching_fps(body, walk):
    dance = load_deepmimic("dance_a", body)  # 60 fps
    with pytest.raises(ValueError, match="resample"):
        concatenate([walk, dance])


# ---- AMASS ---------------------------------------------------------------------------------------
def _write_amass(path, poses, trans, fps=120.0, **extra):
    np.savez(path, poses=poses, trans=trans, mocap_framerate=np.array(fps), betas=np.zeros(16), **extra)


def test_amass_axes_rotation_about_smpl_up_becomes_rotation_about_z(tmp_path):
    rng = np.random.default_rng(0)
    T = 6
    poses = rng.normal(scale=0.3, size=(T, 156))
    poses[:, 0:3] = [0.0, 0.5, 0.0]  # root: 0.5 rad about SMPL's y (up)
    spine = SMPL_JOINT_NAMES.index("spine1")
    poses[:, 3 * spine:3 * spine + 3] = [0.0, -0.25, 0.0]
    trans = rng.normal(size=(T, 3))
    path = tmp_path / "clip_poses.npz"
    _write_amass(path, poses, trans)
    m = load_amass(path)  # a Y-up world here (the root keeps SMPL's y up): conjugate everything
    assert m.skeleton == "smpl" and m.joint_names == list(SMPL_JOINT_NAMES) and m.fps == 120.0
    assert torch.allclose(m.rotations[:, 0], torch.tensor([0.0, 0.0, 0.5]), atol=1e-6)
    assert torch.allclose(m.rotations[:, spine], torch.tensor([0.0, 0.0, -0.25]), atol=1e-6)
    C = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)
    assert np.allclose(m.translation.numpy(), trans @ C.T, atol=1e-6)
    # Any joint: R' (C v) == C (R v).
    k = SMPL_JOINT_NAMES.index("left_elbow")
    R = Rotation.from_rotvec(poses[:, 3 * k:3 * k + 3]).as_matrix()
    R2 = Rotation.from_rotvec(m.rotations[:, k].double().numpy()).as_matrix()
    v = rng.normal(size=3)
    assert np.allclose(R2 @ (C @ v), (R @ v) @ C.T, atol=1e-5)
    # SMPL-H: the hand joints of SMPL's 24 stay zero.
    assert m.rotations[:, 22:].abs().max() == 0


def test_amass_z_up_world(tmp_path):
    """AMASS's own worlds are Z up: a standing subject's root is a quarter turn about X."""
    T = 3
    poses = np.zeros((T, 72))
    yaw = Rotation.from_rotvec([0.0, 0.0, 0.3])  # turned 0.3 rad about the world's up axis
    poses[:, 0:3] = (yaw * Rotation.from_rotvec([math.pi / 2, 0.0, 0.0])).as_rotvec()
    trans = np.tile([0.1, 0.2, 0.9], (T, 1))
    path = tmp_path / "zup.npz"
    _write_amass(path, poses, trans)
    m = load_amass(path)
    assert torch.allclose(m.rotations[:, 0], torch.tensor([0.0, 0.0, 0.3]), atol=1e-6)  # upright, turned
    assert torch.allclose(m.translation, torch.tensor(trans, dtype=torch.float32))
    forced = load_amass(path, up="y")  # the SMPL-convention reading lays the subject down
    assert forced.rotations[0, 0].norm() > 1.0


def test_amass_errors_name_file_and_field(tmp_path):
    path = tmp_path / "bad.npz"
    poses = np.zeros((4, 72))
    poses[2, 5] = np.nan
    _write_amass(path, poses, np.zeros((4, 3)))
    with pytest.raises(AmassError, match=r"bad\.npz.*'poses'.*NaN.*frame 2"):
        load_amass(path)
    np.savez(path, poses=np.zeros((4, 72)), mocap_framerate=60.0)
    with pytest.raises(AmassError, match=r"bad\.npz.*missing field 'trans'"):
        load_amass(path)
    _write_amass(path, np.zeros((4, 70)), np.zeros((4, 3)))
    with pytest.raises(AmassError, match=r"bad\.npz.*'poses'.*shape"):
        load_amass(path)
    _write_amass(path, np.zeros((4, 72)), np.zeros((5, 3)))
    with pytest.raises(AmassError, match=r"bad\.npz.*'trans'"):
        load_amass(path)
    np.savez(path, poses=np.zeros((4, 72)), trans=np.zeros((4, 3)))
    with pytest.raises(AmassError, match="mocap_framerate"):
        load_amass(path)


# ---- procedural and library ---------------------------------------------------------------------
def test_procedural_motions(body):
    for name in PROCEDURAL_MOTIONS:
        m = procedural_motion(name, body)
        again = procedural_motion(name, body)
        assert torch.equal(m.rotations, again.rotations)  # deterministic
        v = m.pose(body).vertices
        assert torch.isfinite(v).all()
        lowest = v[..., 2].min(dim=1).values
        assert lowest.min() > -0.02 and lowest.max() < 0.02, name
    assert procedural_motion("sway", body, fps=60.0).num_frames == 120  # same duration at any rate


def test_library_names_and_errors(body, tmp_path):
    infos = {i.name: i for i in available_motions()}
    assert set(DEEPMIMIC_CLIPS) <= set(infos) and set(PROCEDURAL_MOTIONS) <= set(infos)
    assert infos["walk"].frames == 39 and infos["walk"].fps == 30.0 and infos["walk"].source == "deepmimic"
    with pytest.raises(UnknownMotionError, match=r"unknown motion 'xyz' \(available: walk, run, "):
        load_motion("xyz", body)
    with pytest.raises(UnknownMotionError, match="unknown motion 'nope'"):
        load_motion("walk,nope", body)
    m = load_motion("walk+sway", body, fps=30.0)
    assert m.name == "walk,sway" and m.fps == 30.0
    assert m.num_frames == 39 + 60 - 10
    saved = random_motion(T=4, J=3).save(tmp_path / "m.npz")
    back = load_motion(str(saved), body, fps=15.0)
    assert back.fps == 15.0 and back.num_frames == 2
    with pytest.raises(FileNotFoundError):
        load_motion(str(tmp_path / "missing.npz"), body)
