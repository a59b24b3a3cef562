"""Per-frame pose corrections: the exponential, the moved samples, and recovering known pose errors.

The scene is an analytic room (metres): a 4 x 3 x 2.5 m box seen from inside with two boxes
and a sphere in it. Its depth images are ray-cast in closed form here (slab and quadratic
intersections), and its SDF is written here too, independent of the field code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.core.cameras import look_at
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.synthetic.pose_noise import pose_errors
from regnf.training.optim import lr_factor
from regnf.training.pose_refinement import PoseCorrections, PoseRefineConfig, per_frame, se3_exp
from regnf.training.training import RGBDTrainConfig, train_rgbd

ROOM = (np.array([-2.0, -1.5, 0.0]), np.array([2.0, 1.5, 2.5]))
BOXES = [  # (centre, half extents), metres
    (np.array([0.8, 0.6, 0.4]), np.array([0.4, 0.3, 0.4])),
    (np.array([-1.2, 0.9, 0.8]), np.array([0.25, 0.25, 0.8])),
]
SPHERE = (np.array([-0.7, -0.6, 0.5]), 0.45)
SCALE = 2.0
OFFSET = np.array([0.0, 0.0, 1.25])
"""Normalised -> metres: metres = 2 x normalised + (0, 0, 1.25)."""
W, H = 40, 30
K = np.array([[22.0, 0.0, W / 2], [0.0, 22.0, H / 2], [0.0, 0.0, 1.0]])
N_FRAMES = 12
PERTURBED = {  # frame -> (rotation vector direction, degrees, translation, metres)
    2: ((1.0, 0.5, -0.3), 1.0, (0.015, -0.01, 0.008)),
    5: ((-0.2, 1.0, 0.4), 1.0, (-0.008, 0.012, 0.012)),
    9: ((0.3, -0.4, 1.0), 1.0, (0.01, 0.01, -0.014)),
}


def _box_sdf(p: torch.Tensor, centre: np.ndarray, half: np.ndarray) -> torch.Tensor:
    q = (p - torch.as_tensor(centre, dtype=p.dtype)).abs() - torch.as_tensor(half, dtype=p.dtype)
    return q.clamp_min(0.0).norm(dim=-1) + q.max(-1).values.clamp_max(0.0)


def room_sdf_m(p: torch.Tensor) -> torch.Tensor:
    """Exact SDF (metres, positive in the room's free space) at points (n, 3) in metres."""
    lo, hi = ROOM
    out = -_box_sdf(p, (lo + hi) / 2, (hi - lo) / 2)
    for centre, half in BOXES:
        out = torch.minimum(out, _box_sdf(p, centre, half))
    c, r = SPHERE
    return torch.minimum(out, (p - torch.as_tensor(c, dtype=p.dtype)).norm(dim=-1) - r)


def true_poses_m() -> np.ndarray:
    """(N_FRAMES, 4, 4) OpenCV cam-to-world in metres: cameras at 1.2-1.6 m near the middle, each
    looking down into a corner (two walls and the floor: every frame's pose is constrained)."""
    corners = np.array([[2.0, 1.5], [-2.0, 1.5], [-2.0, -1.5], [2.0, -1.5]])
    poses = []
    for i in range(N_FRAMES):
        a = 2 * math.pi * i / N_FRAMES
        eye = np.array([0.5 * math.cos(a), 0.4 * math.sin(a), 1.2 + 0.2 * (i % 3)])
        target = np.array([*corners[i % 4] * 0.8, 0.3 + 0.2 * (i % 2)])
        poses.append(look_at(eye, target))
    return np.stack(poses)


def raycast_depth(c2w: np.ndarray) -> np.ndarray:
    """(H, W) z-depth (metres) of the room seen from ``c2w`` (metres), in closed form."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    d = cam @ c2w[:3, :3].T  # z = 1 in the camera: t along d is the z-depth
    o = c2w[:3, 3]
    with np.errstate(divide="ignore"):
        inv = 1.0 / d
    lo, hi = ROOM
    t_room = np.minimum((lo - o) * inv, (hi - o) * inv).max(-1), np.maximum((lo - o) * inv, (hi - o) * inv).min(-1)
    t = t_room[1]  # inside the room: where the ray leaves it
    for bc, bh in BOXES:
        t0 = np.minimum((bc - bh - o) * inv, (bc + bh - o) * inv).max(-1)
        t1 = np.maximum((bc - bh - o) * inv, (bc + bh - o) * inv).min(-1)
        t = np.where((t1 >= t0) & (t0 > 0), np.minimum(t, t0), t)
    c, r = SPHERE
    a2 = (d * d).sum(-1)
    b = (d * (o - c)).sum(-1)
    disc = b * b - a2 * (((o - c) ** 2).sum() - r * r)
    ts = (-b - np.sqrt(np.maximum(disc, 0.0))) / a2
    t = np.where((disc > 0) & (ts > 0), np.minimum(t, ts), t)
    return t.reshape(H, W)


def perturbation(frame: int) -> np.ndarray:
    """(4, 4) rigid error of a perturbed frame, applied on the world side about the camera centre."""
    axis, deg, dt = PERTURBED[frame]
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis) / np.linalg.norm(axis)).as_matrix()
    out[:3, 3] = dt
    return out


def perturbed_poses_m(true: np.ndarray) -> np.ndarray:
    """The poses a SLAM system might report: PERTURBED frames turned about their centres and moved."""
    out = true.copy()
    for i in PERTURBED:
        E = perturbation(i)
        out[i, :3, :3] = E[:3, :3] @ true[i, :3, :3]
        out[i, :3, 3] = true[i, :3, 3] + E[:3, 3]
    return out


def to_normalised(c2w_m: np.ndarray) -> np.ndarray:
    out = c2w_m.copy()
    out[..., :3, 3] = (c2w_m[..., :3, 3] - OFFSET) / SCALE
    return out


def to_metres(c2w_n: np.ndarray) -> np.ndarray:
    out = c2w_n.copy()
    out[..., :3, 3] = c2w_n[..., :3, 3] * SCALE + OFFSET
    return out


def backproject(depth: np.ndarray, c2w_n: np.ndarray) -> np.ndarray:
    """(H*W, 3) normalised points of a metric z-depth image seen from normalised pose ``c2w_n``."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    return (cam * (depth.reshape(-1, 1) / SCALE)) @ c2w_n[:3, :3].T + c2w_n[:3, 3]


# -- the exponential ---------------------------------------------------------------------------


def test_exp_at_zero_is_identity():
    R, t = se3_exp(torch.zeros(4, 6))
    assert torch.equal(R, torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
    assert torch.equal(t, torch.zeros(4, 3, dtype=torch.float64))
    # The series branch keeps the gradient finite (and exact) at 0.
    xi = torch.zeros(1, 6, requires_grad=True)
    R, t = se3_exp(xi)
    (R[0, 2, 1] + t[0, 0]).backward()
    assert torch.allclose(xi.grad, torch.tensor([[1.0, 0, 0, 1.0, 0, 0]]))


@pytest.mark.parametrize("angle", [1e-3, 0.05, 0.7, 2.5])
def test_exp_matches_axis_angle(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    C = 1 - c
    # Rotation about a unit axis, written out entry by entry.
    expected = np.array([
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ])
    u = np.array([0.1, 0.2, -0.3])
    R, t = se3_exp(torch.tensor([[*(angle * axis), *u]], dtype=torch.float64))
    assert np.allclose(R[0].numpy(), expected, atol=1e-12)
    # The translation is the one of the matrix exponential of the twist.
    twist = np.zeros((4, 4))
    twist[:3, :3] = [[0, -z, y], [z, 0, -x], [-y, x, 0]]
    twist[:3, :3] *= angle
    twist[:3, 3] = u
    assert np.allclose(t[0].numpy(), expm(twist)[:3, 3], atol=1e-12)


@torch.no_grad()
def test_points_follow_the_corrected_camera():
    rng = np.random.default_rng(1)
    c2w = to_normalised(true_poses_m()[:4])
    corr = PoseCorrections(torch.from_numpy(c2w), SCALE)  # the common motion taken out, too
    corr.delta.copy_(torch.from_numpy(rng.normal(scale=0.05, size=(4, 6))))
    fixed = corr.camtoworld().numpy()
    frame = torch.from_numpy(rng.integers(0, 4, 200))
    cam = rng.normal(size=(200, 3)) + [0, 0, 3]  # points in each camera's own axes
    f = frame.numpy()
    world = np.einsum("nij,nj->ni", c2w[f, :3, :3], cam) + c2w[f, :3, 3]
    moved = corr.points(torch.from_numpy(world), frame).numpy()
    # Same camera coordinates, seen from the corrected pose.
    assert np.allclose(moved, np.einsum("nij,nj->ni", fixed[f, :3, :3], cam) + fixed[f, :3, 3], atol=1e-9)
    # The corrected centre's displacement is the translation in metres, over the scale.
    assert np.allclose(np.linalg.norm(fixed[:, :3, 3] - c2w[:, :3, 3], axis=1),
                       np.linalg.norm(se3_exp(corr.applied())[1].numpy(), axis=1) / SCALE, atol=1e-12)
    # A point on a ray stays on the corrected ray, at the same distance.
    o = torch.from_numpy(c2w[f, :3, 3])
    d = torch.nn.functional.normalize(torch.from_numpy(world) - o, dim=-1)
    s = torch.from_numpy(rng.uniform(0.1, 3.0, 200))
    o2, d2 = corr.rays(o, d, frame)
    assert torch.allclose(corr.points(o + s[:, None] * d, frame), o2 + s[:, None] * d2, atol=1e-12)
    assert torch.allclose(d2.norm(dim=-1), torch.ones(200, dtype=torch.float64), atol=1e-12)
    assert np.allclose(o2.numpy(), fixed[f, :3, 3], atol=1e-12)
    # Back from the corrected to the given pose (a view's free-space test sees points there).
    assert torch.allclose(corr.points_back(torch.from_numpy(moved), frame), torch.from_numpy(world), atol=1e-12)


def test_report_in_metres_and_degrees():
    corr = PoseCorrections(torch.from_numpy(to_normalised(true_poses_m()[:3])), SCALE,
                           PoseRefineConfig(keep_mean_pose=False))
    with torch.no_grad():
        corr.delta[1] = torch.tensor([0.0, math.radians(2.0), 0.0, 0.03, 0.0, 0.04])
        corr.delta[2] = torch.tensor([math.radians(0.5), 0.0, 0.0, 0.0, 0.01, 0.0])
    rep = corr.report()
    # Translations are in metres: 5 cm and 1 cm (the exponential's V barely bends them).
    assert rep.worst_cm == pytest.approx(5.0, rel=1e-3)
    assert rep.median_cm == pytest.approx(1.0, rel=1e-3)
    assert rep.worst_deg == pytest.approx(2.0, rel=1e-5)
    assert rep.median_deg == pytest.approx(0.5, rel=1e-5)
    assert rep.frames == 3


@torch.no_grad()
def test_a_common_motion_of_every_camera_is_not_applied():
    """Turning and shifting every camera together (about their mean centre) is what the field could
    follow unseen: with ``keep_mean_pose`` such corrections apply as none; what is left of any
    corrections has world turns and centre shifts of mean zero."""
    c2w = to_normalised(true_poses_m())
    corr = PoseCorrections(torch.from_numpy(c2w), SCALE)
    turn, shift = np.array([0.004, -0.002, 0.003]), np.array([0.01, 0.02, -0.015])  # rad, metres
    arm = (c2w[:, :3, 3] - c2w[:, :3, 3].mean(0)) * SCALE
    world = np.concatenate([np.broadcast_to(turn, arm.shape), np.cross(turn, arm) + shift], 1)
    # In each camera's own axes: R^T of the world vectors.
    local = np.einsum("nji,nkj->nki", c2w[:, :3, :3], world.reshape(-1, 2, 3)).reshape(-1, 6)
    corr.delta.copy_(torch.from_numpy(local))
    assert corr.applied().abs().max() < 1e-7  # float32 storage of delta
    rng = np.random.default_rng(3)
    corr.delta.copy_(torch.from_numpy(rng.normal(scale=0.01, size=(N_FRAMES, 6))))
    applied = corr.applied().numpy()
    R = c2w[:, :3, :3]
    assert np.allclose(np.einsum("nij,nj->ni", R, applied[:, :3]).mean(0), 0.0, atol=1e-12)
    assert np.allclose(np.einsum("nij,nj->ni", R, applied[:, 3:]).mean(0), 0.0, atol=1e-12)
    # Without it, the corrections are applied as they are.
    corr.config = PoseRefineConfig(keep_mean_pose=False)
    assert torch.equal(corr.applied(), corr.delta.double())


def test_config_mode():
    assert PoseRefineConfig().enabled(True) and not PoseRefineConfig().enabled(False)
    assert PoseRefineConfig(mode="on").enabled(False)
    assert not PoseRefineConfig(mode="off").enabled(True)
    with pytest.raises(ValueError, match="auto, on or off"):
        PoseRefineConfig(mode="yes")


# -- recovering known pose errors against the exact SDF ----------------------------------------


def test_recovers_a_known_perturbation_against_the_exact_sdf():
    true_m = true_poses_m()
    given_m = perturbed_poses_m(true_m)
    depths = [raycast_depth(c) for c in true_m]
    given_n = to_normalised(given_m)
    pts = torch.from_numpy(np.concatenate([backproject(d, c) for d, c in zip(depths, given_n)])).float()
    frame = torch.arange(N_FRAMES).repeat_interleave(W * H)
    errors_before = pose_errors(given_m, true_m)
    assert errors_before[0][list(PERTURBED)].min() > 0.015 and errors_before[1][list(PERTURBED)].min() > 0.99

    # The exact SDF fixes the scene's frame: nothing to keep the mean pose against.
    cfg = PoseRefineConfig(mode="on", keep_mean_pose=False)
    corr = PoseCorrections(torch.from_numpy(given_n), SCALE, cfg)
    opt = torch.optim.AdamW([corr.param_group()], betas=(0.9, 0.99), eps=1e-15)
    steps, ell = 300, 0.01
    gen = torch.Generator().manual_seed(0)
    for step in range(steps):
        opt.param_groups[0]["lr"] = cfg.lr * lr_factor(step, steps)
        i = torch.randint(pts.shape[0], (4096,), generator=gen)
        moved = corr.points(pts[i], frame[i])
        loss = (room_sdf_m(moved * SCALE + torch.from_numpy(OFFSET).float()) / SCALE).abs().mean() / ell
        loss = loss + corr.regulariser()
        opt.zero_grad()
        loss.backward()
        opt.step()

    fixed_m = to_metres(corr.camtoworld().detach().numpy())
    pos, rot = pose_errors(fixed_m, true_m)
    bad = list(PERTURBED)
    good = [i for i in range(N_FRAMES) if i not in PERTURBED]
    print("perturbed frames: mm", pos[bad] * 1000, "deg", rot[bad])
    print("other frames: worst mm", pos[good].max() * 1000, "deg", rot[good].max())
    assert (pos[bad] < 0.2 * errors_before[0][bad]).all() and (rot[bad] < 0.2 * errors_before[1][bad]).all()
    assert pos[good].max() < 0.002 and rot[good].max() < 0.05
    rep = corr.report()
    assert rep.worst_cm == pytest.approx(100 * np.linalg.norm(
        se3_exp(corr.delta.detach())[1].numpy(), axis=1).max(), rel=1e-6)


# -- jointly with a field -----------------------------------------------------------------------


def test_training_refines_the_perturbed_poses(tmp_path):
    """A tiny room field trained on the capture with 3 perturbed frames (auto: the capture says its
    poses are estimates) moves those frames towards their true poses."""
    true_m = true_poses_m()
    given_m = perturbed_poses_m(true_m)
    worldtogt = np.diag([SCALE, SCALE, SCALE, 1.0])
    worldtogt[:3, 3] = OFFSET
    depths = [raycast_depth(c) for c in true_m]
    rgbs = [np.full((H, W, 3), 128, np.uint8) for _ in depths]
    write_capture(tmp_path, rgbs, depths, given_m, K, worldtogt, meta={"poses": "estimated"})
    capture = load_capture(tmp_path)
    assert capture.poses_estimated
    arch = NeuralSDFConfig(levels=4, features_per_level=2, base_resolution=16, finest_resolution=48,
                           hidden_dim=32, color_hidden_dim=32, inside_out=True, init_radius=0.9)
    cfg = RGBDTrainConfig(steps=300, batch_surface=1024, batch_free=512, batch_empty=512, batch_eikonal=256,
                          w_color=0.0, visibility_resolution=0, architecture=arch)
    field, log = train_rgbd(capture, cfg, progress=False)

    fixed_m = to_metres(log.corrected_poses)
    pos0, rot0 = pose_errors(given_m, true_m)
    pos, rot = pose_errors(fixed_m, true_m)
    bad = list(PERTURBED)
    good = [i for i in range(N_FRAMES) if i not in PERTURBED]
    print("perturbed frames: mm", pos[bad] * 1000, "deg", rot[bad])
    print("other frames: worst mm", pos[good].max() * 1000, "deg", rot[good].max())
    # The applied corrections point from the given towards the true poses...
    moved = fixed_m[bad, :3, 3] - given_m[bad, :3, 3]
    needed = true_m[bad, :3, 3] - given_m[bad, :3, 3]
    cos = (moved * needed).sum(1) / np.linalg.norm(moved, axis=1) / np.linalg.norm(needed, axis=1)
    turned = Rotation.from_matrix(fixed_m[bad, :3, :3] @ np.swapaxes(given_m[bad, :3, :3], 1, 2)).as_rotvec()
    needed_turn = Rotation.from_matrix(true_m[bad, :3, :3] @ np.swapaxes(given_m[bad, :3, :3], 1, 2)).as_rotvec()
    cos_r = (turned * needed_turn).sum(1) / np.linalg.norm(turned, axis=1) / np.linalg.norm(needed_turn, axis=1)
    print("cosines: translation", cos, "rotation", cos_r)
    assert (cos > 0.7).all() and (cos_r > 0.7).all()
    # ...and cut their error (to 0.25-0.45 of it here), while the exact frames stay within a few
    # millimetres (the perturbations' own mean is spread over every frame: keep_mean_pose).
    assert (pos[bad] < 0.6 * pos0[bad]).all() and (rot[bad] < 0.6 * rot0[bad]).all()
    assert pos[good].max() < 0.01 and rot[good].max() < 0.5
    # What training reports and records is what it applied.
    rep = log.pose_refinement
    assert rep.frames == N_FRAMES
    assert rep.worst_cm == pytest.approx(100 * np.linalg.norm(fixed_m[:, :3, 3] - given_m[:, :3, 3], axis=1).max(),
                                         rel=1e-4)
    assert field.info.provenance["pose_refinement"]["worst_cm"] == pytest.approx(rep.worst_cm, abs=1e-4)


def test_per_frame_rows_and_their_gradient_repeat_bit_for_bit() -> None:
    """The rows are exactly the indexed ones; their gradient is each frame's sum of its samples'
    gradients (checked against a float64 sum), the same bit for bit on every run at a
    training batch's size."""
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(40, 3, 3, generator=gen)
    frame = torch.randint(40, (60_000,), generator=gen)
    upstream = torch.randn(60_000, 3, 3, generator=gen)
    assert torch.equal(per_frame(x, frame), x[frame])
    grads = []
    for _ in range(4):
        leaf = x.clone().requires_grad_(True)
        (per_frame(leaf, frame) * upstream).sum().backward()
        grads.append(leaf.grad)
    assert all(torch.equal(grads[0], g) for g in grads[1:])
    truth = torch.zeros(40, 3, 3, dtype=torch.float64).index_add_(0, frame, upstream.double())
    torch.testing.assert_close(grads[0].double(), truth, rtol=1e-5, atol=1e-3)
