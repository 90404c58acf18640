"""Representations: encode -> decode round trips, HumanML3D compatibility, batching, gradients, stats."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from omg.errors import UsageError
from omg.io.bvh import read_bvh
from omg.motion import Clip, get_representation
from omg.motion.humanml3d263 import T2M_CHAINS, T2M_RAW_OFFSETS, gaussian_filter1d
from omg.registry import REPRESENTATIONS
from omg.rotations import axis_angle_to_quat, quat_mul, yaw_quat
from omg.skeleton import SMAL35, SMPL22, Skeleton

DATA = Path(__file__).parents[2] / "shared/data/motion"
MM = 1e-3

# Bandai-Namco joint for each SMPL-22 joint. Bandai has one joint (Chest) where SMPL has
# spine2 and spine3; spine2 is put halfway between Spine and Chest, because two joints at
# one point make a zero-length bone whose direction HumanML3D's IK cannot take.
BANDAI_TO_SMPL22 = (
    "Hips", "UpperLeg_L", "UpperLeg_R", "Spine", "LowerLeg_L", "LowerLeg_R", ("Spine", "Chest"),
    "Foot_L", "Foot_R", "Chest", "Toes_L", "Toes_R", "Neck", "Shoulder_L", "Shoulder_R", "Head",
    "UpperArm_L", "UpperArm_R", "LowerArm_L", "LowerArm_R", "Hand_L", "Hand_R",
)  # fmt: skip


def _bandai_files(n: int) -> list[Path]:
    files = sorted((DATA / "human/bandai1").glob("*.bvh"))
    if not files:
        pytest.skip(f"real motion data not found: {DATA / 'human/bandai1'} (see ../shared/data/motion/README.md)")
    return files[:: max(1, len(files) // n)][:n]


def _bandai_smpl22(path: Path) -> Clip:
    motion = read_bvh(path)
    positions = motion.positions()
    index = {name: j for j, name in enumerate(motion.names)}
    joints = [
        positions[:, [index[n] for n in name]].mean(1) if isinstance(name, tuple) else positions[:, index[name]]
        for name in BANDAI_TO_SMPL22
    ]
    return Clip(path.stem, SMPL22, motion.fps, np.stack(joints, axis=1).astype(np.float32))


def _synthetic(skeleton: Skeleton, T: int = 40, seed: int = 0) -> Clip:
    """Random smooth local rotations and a wandering, turning root; positions by FK."""
    g = torch.Generator().manual_seed(seed)
    J = skeleton.num_joints
    aa = 0.3 * torch.randn(1, J, 3, generator=g, dtype=torch.float64)
    aa = aa + 0.03 * torch.randn(T, J, 3, generator=g, dtype=torch.float64).cumsum(0)
    aa[:, 0] *= 0.3  # the body stays roughly upright ...
    rotations = axis_angle_to_quat(aa)
    yaw = 0.05 * torch.randn(T, generator=g, dtype=torch.float64).cumsum(0)
    rotations[:, 0] = quat_mul(yaw_quat(yaw), rotations[:, 0])  # ... and turns about +Y
    root = torch.from_numpy(skeleton.rest_offsets[0]).double() + torch.cumsum(
        0.02 * torch.randn(T, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.1, 1.0]), 0
    )
    positions = skeleton.forward_kinematics(rotations, root)
    return Clip(
        f"synthetic-{skeleton.name}-{seed}", skeleton, 20.0, positions.float().numpy(),
        rotations=rotations.float().numpy(), offsets=skeleton.rest_offsets,
    )  # fmt: skip


def _max_error(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1).max())


def test_registered():
    assert {"humanml3d263", "maa", "quatvel"} <= set(REPRESENTATIONS.names())
    assert get_representation("humanml3d263", "smpl22").dim == 263
    assert get_representation("maa", "smal35").dim == 36 * 6
    assert get_representation("quatvel", SMAL35).dim == 35 * 7
    with pytest.raises(UsageError, match="SMPL-22"):
        get_representation("humanml3d263", "smal35")


# ---------------------------------------------------------------- humanml3d263


def test_humanml3d263_constants_match_shared_facts():
    path = DATA / "skeletons.json"
    if not path.exists():
        pytest.skip(f"skeleton facts not found: {path}")
    facts = json.loads(path.read_text())["smpl22"]
    np.testing.assert_array_equal(T2M_RAW_OFFSETS, facts["t2m_raw_offsets"])
    assert [list(c) for c in T2M_CHAINS] == facts["t2m_kinematic_chain"]


def _check_humanml3d263(clip: Clip) -> dict:
    rep = get_representation("humanml3d263", "smpl22")
    features, meta = rep.encode(clip)
    assert features.shape == (len(clip) - 1, 263) and features.dtype == np.float32
    canonical = rep.canonicalize(clip.positions)  # (T, 22, 3)
    f = torch.from_numpy(features)

    assert meta == {}
    # the canonical motion: uniform skeleton, on the floor, starting at the origin, and
    # frame 0 facing +Z (the root rotation of frame 0 is the identity: module docstring)
    bones = np.linalg.norm(canonical[:, 1:] - canonical[:, list(SMPL22.parents[1:])], axis=-1)
    np.testing.assert_allclose(bones, np.broadcast_to(SMPL22.bone_lengths()[1:], bones.shape), atol=1e-6)
    assert abs(canonical[..., 1].min()) < 1e-9 and np.abs(canonical[0, 0, [0, 2]]).max() < 1e-9
    across = canonical[0, 2] - canonical[0, 1] + canonical[0, 17] - canonical[0, 16]  # right - left
    assert abs(np.arctan2(across[2], -across[0])) < 1e-6  # yaw from +Z of up x across

    errors = {"decode": _max_error(rep.decode(f), canonical[:-1])}
    # FK of the IK rotations on the uniform skeleton (HumanML3D's recover_from_rot) gives
    # the same positions, as frame 0's root rotation is the identity that decoding starts from
    errors["fk"] = _max_error(rep.positions_from_rotations(f).numpy(), canonical[:-1])
    # frame 0 by itself: its ric (and its rotations) are taken in the canonical frame
    errors["ric0"] = _max_error(features[0, 4:67].reshape(21, 3), canonical[0, 1:] - canonical[0, :1] * [1, 0, 1])
    assert errors["decode"] < MM and errors["fk"] < MM and errors["ric0"] < MM, errors

    contacts = rep.foot_contacts(f)
    assert contacts.shape == (len(clip) - 1, 4) and set(contacts.unique().tolist()) <= {0.0, 1.0}
    return errors


def test_humanml3d263_round_trip_synthetic():
    for seed in range(2):
        _check_humanml3d263(_synthetic(SMPL22, T=60, seed=seed))


def test_humanml3d263_round_trip_bandai():
    # measured on these 4 clips: decode and FK (HumanML3D's recover_from_rot) <= 1.2e-6 m
    for path in _bandai_files(4):
        _check_humanml3d263(_bandai_smpl22(path))


def test_finalize_stats():
    rep = get_representation("humanml3d263", "smpl22")
    data = np.concatenate([rep.encode(_synthetic(SMPL22, T=60, seed=s))[0] for s in range(3)])
    mean, std = rep.finalize_stats(data.mean(0), data.std(0))
    assert mean.shape == std.shape == (263,) and mean.dtype == std.dtype == np.float32
    assert np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()
    for a, b in ((0, 1), (1, 3), (3, 4), (4, 67), (67, 193), (193, 259), (259, 263)):
        np.testing.assert_allclose(std[a:b], max(data.std(0)[a:b].mean(), 1e-4), rtol=1e-5)
    _, biased = REPRESENTATIONS.get("humanml3d263")(SMPL22, feat_bias=5.0).finalize_stats(data.mean(0), data.std(0))
    np.testing.assert_allclose(biased[[0, 1, 3, 260]] * 5, std[[0, 1, 3, 260]], rtol=1e-5)
    np.testing.assert_allclose(biased[4:259], std[4:259])


# HumanML3D's process_file / recover_from_ric, ported line by line to numpy as an
# independent reference (their IK -> FK for the uniform skeleton, their quaternion code).

_FACE, _PARENTS = (2, 1, 17, 16), list(SMPL22.parents)


def _qmul(q, r):
    w1, x1, y1, z1 = np.moveaxis(q, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(r, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)  # fmt: skip


def _qinv(q):
    return q * np.array([1, -1, -1, -1])


def _qrot(q, v):
    uv = np.cross(q[..., 1:], v)
    return v + 2 * (q[..., :1] * uv + np.cross(q[..., 1:], uv))


def _qbetween(v0, v1):
    w = np.sqrt((v0**2).sum(-1, keepdims=True) * (v1**2).sum(-1, keepdims=True)) + (v0 * v1).sum(-1, keepdims=True)
    q = np.concatenate([w, np.cross(v0, v1)], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _ik(joints, smooth, sigma=20):
    scipy_ndimage = pytest.importorskip("scipy.ndimage")
    l_hip, r_hip, sdr_r, sdr_l = _FACE  # sic: common/skeleton.py unpacks them in this order
    across = _normalize(joints[:, r_hip] - joints[:, l_hip] + joints[:, sdr_r] - joints[:, sdr_l])
    forward = np.cross(np.array([[0, 1, 0]]), across, axis=-1)
    if smooth:
        forward = scipy_ndimage.gaussian_filter1d(forward, sigma, axis=0, mode="nearest")
    root = _qbetween(_normalize(forward), np.array([[0, 0, 1.0]]).repeat(len(joints), 0))
    root[0] = np.array([[1.0, 0.0, 0.0, 0.0]])
    quat = np.zeros(joints.shape[:-1] + (4,))
    quat[:, 0] = root
    for chain in T2M_CHAINS:
        R = root
        for a, b in zip(chain[:-1], chain[1:]):
            u = T2M_RAW_OFFSETS[b][None].repeat(len(joints), 0)
            quat[:, b] = _qmul(_qinv(R), _qbetween(u, _normalize(joints[:, b] - joints[:, a])))
            R = _qmul(R, quat[:, b])
    return quat


def _fk(quat, root_pos, offsets):
    joints = np.zeros(quat.shape[:-1] + (3,))
    joints[:, 0] = root_pos
    for chain in T2M_CHAINS:
        R = quat[:, 0]
        for i in range(1, len(chain)):
            R = _qmul(R, quat[:, chain[i]])
            joints[:, chain[i]] = (
                _qrot(R, np.broadcast_to(offsets[chain[i]], R.shape[:-1] + (3,))) + joints[:, chain[i - 1]]
            )
    return joints


def _process_file(positions, tgt_offsets, feet_thre=0.002, fps=20.0):
    """HumanML3D's process_file; its per-frame constants (made for 20 fps) scaled to ``fps``."""
    feet_thre, sigma = feet_thre * (20.0 / fps) ** 2, 20 * fps / 20.0
    src_offsets = T2M_RAW_OFFSETS * np.linalg.norm(positions[0] - positions[0][[0] + _PARENTS[1:]], axis=-1)[:, None]
    scale = (np.abs(tgt_offsets[5]).max() + np.abs(tgt_offsets[8]).max()) / (
        np.abs(src_offsets[5]).max() + np.abs(src_offsets[8]).max()
    )
    positions = _fk(_ik(positions, smooth=False), positions[:, 0] * scale, tgt_offsets)
    positions[:, :, 1] -= positions.min(axis=0).min(axis=0)[1]
    root_pos_init = positions[0]
    positions = positions - root_pos_init[0] * np.array([1, 0, 1])
    r_hip, l_hip, sdr_r, sdr_l = _FACE
    across = _normalize(root_pos_init[r_hip] - root_pos_init[l_hip] + root_pos_init[sdr_r] - root_pos_init[sdr_l])
    forward_init = _normalize(np.cross(np.array([[0, 1, 0]]), across, axis=-1))
    root_quat_init = np.ones(positions.shape[:-1] + (4,)) * _qbetween(forward_init, np.array([[0, 0, 1]]))
    positions = _qrot(root_quat_init, positions)
    global_positions = positions.copy()

    def contact(fid):
        return (((positions[1:, fid] - positions[:-1, fid]) ** 2).sum(-1) < feet_thre).astype(np.float64)

    feet_l, feet_r = contact([7, 10]), contact([8, 11])
    quat = _ik(positions, smooth=True, sigma=sigma)
    w, x, y, z = np.moveaxis(quat, -1, 0)
    mat = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                    2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                    2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)  # fmt: skip
    mat = mat.reshape(quat.shape[:-1] + (3, 3))  # quaternion_to_matrix
    cont6d = np.concatenate([mat[..., 0], mat[..., 1]], axis=-1)
    r_rot = quat[:, 0]
    velocity = _qrot(r_rot[1:], positions[1:, 0] - positions[:-1, 0])
    r_velocity = _qmul(r_rot[1:], _qinv(r_rot[:-1]))
    positions[..., 0] -= positions[:, 0:1, 0]
    positions[..., 2] -= positions[:, 0:1, 2]
    positions = _qrot(np.repeat(r_rot[:, None], 22, axis=1), positions)
    T = len(positions)
    root_data = np.concatenate([np.arcsin(r_velocity[:, 2:3]), velocity[:, [0, 2]], positions[:-1, 0, 1:2]], -1)
    local_vel = _qrot(np.repeat(r_rot[:-1, None], 22, axis=1), global_positions[1:] - global_positions[:-1])
    return np.concatenate(
        [root_data, positions[:-1, 1:].reshape(T - 1, -1), cont6d[:-1, 1:].reshape(T - 1, -1),
         local_vel.reshape(T - 1, -1), feet_l, feet_r], axis=-1,
    )  # fmt: skip


def _recover_from_ric(data):
    ang = np.cumsum(np.concatenate([[0.0], data[:-1, 0]]))
    r_rot_quat = np.stack([np.cos(ang), 0 * ang, np.sin(ang), 0 * ang], -1)
    r_pos = np.zeros((len(data), 3))
    r_pos[1:, [0, 2]] = data[:-1, 1:3]
    r_pos = np.cumsum(_qrot(_qinv(r_rot_quat), r_pos), axis=0)
    r_pos[:, 1] = data[:, 3]
    positions = _qrot(np.repeat(_qinv(r_rot_quat)[:, None], 21, 1), data[:, 4:67].reshape(-1, 21, 3))
    positions[..., 0] += r_pos[:, 0:1]
    positions[..., 2] += r_pos[:, 2:3]
    return np.concatenate([r_pos[:, None], positions], axis=1)


def _reference_clips() -> list[Clip]:
    clips = [_synthetic(SMPL22, T=60, seed=3)]
    files = sorted((DATA / "human/bandai1").glob("*walk_normal*.bvh"))
    return clips + [_bandai_smpl22(f) for f in files[:1]]


def test_humanml3d263_matches_reference_port():
    rep = get_representation("humanml3d263", "smpl22")
    for clip in _reference_clips():
        positions = clip.positions.astype(np.float64)
        reference = _process_file(positions, rep.target_offsets, fps=clip.fps)
        features, _ = rep.encode(clip)
        np.testing.assert_allclose(features, reference, atol=1e-4, err_msg=clip.id)
        decoded = rep.decode(torch.from_numpy(reference)).numpy()
        np.testing.assert_allclose(decoded, _recover_from_ric(reference), atol=1e-4, err_msg=clip.id)


GOLDEN = Path(__file__).resolve().parents[1].parent / "shared" / "golden" / "humanml3d263"


@pytest.mark.parametrize("n", range(3))
def test_humanml3d263_matches_official_golden(n):
    """HumanML3D's own process_file output (README.md in GOLDEN), frame 0 included."""
    positions, official = GOLDEN / f"clip{n}.positions.npy", GOLDEN / f"clip{n}.official_features.npy"
    if not (positions.exists() and official.exists()):
        pytest.skip(f"golden HumanML3D features not found at {GOLDEN} (the shared/ folder beside the checkout)")
    positions, official = np.load(positions), np.load(official)
    rep = get_representation("humanml3d263", "smpl22")
    features, _ = rep.encode(Clip(f"golden-{n}", SMPL22, 20.0, positions))
    assert features.shape == official.shape == (len(positions) - 1, 263)
    np.testing.assert_allclose(features, official, rtol=0, atol=1e-4, err_msg=f"clip{n}")


def test_gaussian_filter_matches_scipy():
    scipy_ndimage = pytest.importorskip("scipy.ndimage")
    x = np.random.default_rng(0).normal(size=(37, 3))  # shorter than the filter's radius of 80
    np.testing.assert_allclose(
        gaussian_filter1d(x, 20.0), scipy_ndimage.gaussian_filter1d(x, 20, axis=0, mode="nearest")
    )


# ---------------------------------------------------------------- maa, quatvel


def _decode(rep, features: np.ndarray, meta: dict) -> np.ndarray:
    f = torch.from_numpy(features)
    if rep.name == "quatvel":
        return rep.decode(f, torch.tensor(meta["offsets"]), torch.tensor(meta["root_start"])).numpy()
    return rep.decode(f, torch.tensor(meta["offsets"])).numpy()


def _round_trip_error(name: str, clip: Clip) -> float:
    rep = get_representation(name, clip.skeleton)
    features, meta = rep.encode(clip)
    assert features.shape == (len(clip) - rep.frames_dropped, rep.dim) and features.dtype == np.float32
    json.dumps(meta)  # stored beside the features
    return _max_error(_decode(rep, features, meta), clip.positions[: len(features)])


@pytest.mark.parametrize("name", ["maa", "quatvel"])
@pytest.mark.parametrize("skeleton", [SMPL22, SMAL35], ids=lambda s: s.name)
def test_round_trip_synthetic(name, skeleton):
    assert _round_trip_error(name, _synthetic(skeleton, T=50)) < MM


@pytest.mark.parametrize("name", ["maa", "quatvel"])
def test_round_trip_bvh(name):
    bandai = _bandai_files(1)[0]
    dogs = sorted((DATA / "quadruped/mann_dog").glob("*.bvh"))
    if not dogs:
        pytest.skip(f"real motion data not found: {DATA / 'quadruped/mann_dog'}")
    # Bandai's static joint_Root is folded into the moving hips (RigMotion.merge_root)
    for clip in (read_bvh(bandai).merge_root().to_clip(), read_bvh(dogs[0]).to_clip()):
        assert _round_trip_error(name, clip) < MM, clip.id  # measured <= 2e-6 m


@pytest.mark.parametrize("name", ["maa", "quatvel"])
def test_positions_only_clips_get_rotations_by_ik(name):
    """A clip with joint positions only (HumanML3D's new_joints) is encoded through inverse kinematics:
    decoding gives its positions back; a clip with neither rotations nor positions is one error."""
    for skeleton in (SMPL22, SMAL35):
        clip = _synthetic(skeleton)
        clip.rotations, clip.offsets = None, None
        rep = get_representation(name, skeleton)
        features, meta = rep.encode(clip)
        kwargs = {"root_start": torch.as_tensor(meta["root_start"])} if "root_start" in meta else {}
        joints = rep.decode(torch.from_numpy(features), torch.as_tensor(meta["offsets"]), **kwargs).numpy()
        assert np.abs(joints - clip.positions[: len(joints)]).max() < 5 * MM, (name, skeleton.name)
        clip.positions = clip.positions[:, :3]
        with pytest.raises(UsageError, match="neither local rotations nor"):
            rep.encode(clip)


@pytest.mark.parametrize("name", ["humanml3d263", "maa", "quatvel"])
def test_decode_batched_and_differentiable(name):
    skeleton = SMPL22
    rep = get_representation(name, skeleton)
    encoded = [rep.encode(_synthetic(skeleton, T=30, seed=s)) for s in range(2)]
    features = torch.from_numpy(np.stack([f for f, _ in encoded])).requires_grad_()  # (B, T, D)
    kwargs = {}
    if name != "humanml3d263":
        kwargs["offsets"] = torch.tensor([m["offsets"] for _, m in encoded]) * torch.tensor([[[1.0]], [[1.1]]])
    if name == "quatvel":
        kwargs["root_start"] = torch.tensor([m["root_start"] for _, m in encoded])
    positions = rep.decode(features, **kwargs)  # (B, T, J, 3)
    assert positions.shape == features.shape[:2] + (skeleton.num_joints, 3)
    for b in range(2):
        single = rep.decode(features[b], **{k: v[b] for k, v in kwargs.items()})
        torch.testing.assert_close(positions[b], single)
    positions.square().sum().backward()
    assert torch.isfinite(features.grad).all() and features.grad.abs().sum() > 0
