"""Retargeting every real clip onto smpl22 / smal35, joint-map detection, user YAML maps,
unmappable rigs, Z-up sources and height normalisation."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import TINY_BVH
from omg.errors import UsageError
from omg.io.read import read_motion
from omg.io.rig import RigMotion
from omg.kinematics import ground_contacts
from omg.retarget import detect_joint_map, get_joint_map, retarget
from omg.rotations import quat_mul


def _read(root: Path, entry: dict) -> RigMotion:
    options = {}
    if entry["format"] == "deepmimic_json":
        options["character"] = root / entry["skeleton_file"]
    return read_motion(root / entry["path"], **options)


@pytest.fixture(scope="session")
def retargeted() -> list:
    """(manifest entry, source motion, clip at 20 fps) for every real clip."""
    from helpers import SHARED_MOTION

    if not (SHARED_MOTION / "manifest.json").exists():
        pytest.skip(f"real motion data not found at {SHARED_MOTION}")
    out = []
    for entry in json.loads((SHARED_MOTION / "manifest.json").read_text())["clips"]:
        motion = _read(SHARED_MOTION, entry)
        target = "smpl22" if entry["domain"] == "human" else "smal35"
        out.append((entry, motion, retarget(motion, target, fps=20, id=entry["id"])))
    return out


# the tests of every real clip share the `retargeted` fixture's retargets: under xdist they run on one worker
@pytest.mark.xdist_group("retarget")
def test_every_real_clip_retargets(retargeted):
    assert len(retargeted) == 88
    maps = {}
    for entry, motion, clip in retargeted:
        folder = Path(entry["path"]).parent.name
        maps.setdefault(folder, set()).add(detect_joint_map(motion).name)
        P, skel = clip.positions, clip.skeleton
        assert clip.fps == 20.0 and np.isfinite(P).all() and len(clip) >= 2
        # constant bone lengths (0.1 %), and rotations + offsets reproduce the positions
        bones = np.stack([np.linalg.norm(P[:, j] - P[:, p], axis=-1) for j, p in enumerate(skel.parents) if p >= 0], 1)
        assert (np.ptp(bones, 0) <= 1e-3 * bones.mean(0) + 1e-6).all(), entry["id"]
        np.testing.assert_allclose(np.linalg.norm(clip.offsets[1:], axis=-1), bones[0], rtol=1e-4)
        offsets = torch.from_numpy(clip.offsets)
        fk = skel.forward_kinematics(torch.from_numpy(clip.rotations), torch.from_numpy(P[:, 0]), offsets)
        np.testing.assert_allclose(fk.numpy(), P, atol=1e-4)
        # feet in contact rest on the floor
        contact = ground_contacts(torch.from_numpy(P).double(), skel.feet, clip.fps).numpy()
        low = np.where(contact, P[:, list(skel.feet), 1], np.inf).min(1)
        if np.isfinite(low).sum() >= 3:
            assert abs(np.median(low[np.isfinite(low)])) < 0.02, (entry["id"], np.median(low[np.isfinite(low)]))
        # Y up: the pelvis above the feet, sizes of a person or a dog
        feet_y = np.median(P[:, list(skel.feet), 1])
        assert np.median(P[:, 0, 1]) > feet_y and P[..., 1].min() > -0.15, entry["id"]
        # sizes: the individual's rest pose stands 1.3-2 m (a dog 0.35-1 m); poses span as much
        J = skel.num_joints
        rest = skel.forward_kinematics(torch.tensor([1.0, 0, 0, 0]).expand(J, 4), torch.zeros(3), offsets)
        height = float(np.ptp(rest[:, 1].numpy()))
        span = np.percentile(np.linalg.norm(np.ptp(P, axis=1), axis=-1), 90)
        if entry["domain"] == "human":
            assert 1.3 < height < 2.0 and 0.8 * height < span < 1.6 * height, (entry["id"], height, span)
        else:
            assert 0.35 < height < 1.0 and 0.8 * height < span < 2.5 * height, (entry["id"], height, span)
    assert maps == {
        "bandai1": {"bandai"}, "bandai2": {"bandai"}, "cmu": {"cmu", "cmu_3dsmax", "cmu_asf"},
        "deepmimic": {"deepmimic_humanoid"}, "mann_dog": {"mann_dog"}, "deepmimic_dog": {"deepmimic_dog"},
    }  # fmt: skip


@pytest.mark.xdist_group("retarget")
def test_left_is_left(retargeted):
    """No mirrored map: on walking clips the left joints lie to the left of the direction the
    toes point (SMPL) or the head points (SMAL), i.e. forward = left x up."""
    for entry, _, clip in retargeted:
        if "walk" not in entry["id"] and entry["domain"] == "human":
            continue
        P, skel = clip.positions, clip.skeleton
        r_hip, l_hip, r_sh, l_sh = skel.face_joints
        left = P[:, l_hip] - P[:, r_hip] + P[:, l_sh] - P[:, r_sh]
        forward = (P[:, 10] - P[:, 7] + P[:, 11] - P[:, 8]) if skel.name == "smpl22" else (P[:, 16] - P[:, 0])
        facing = np.einsum("ti,ti->t", np.cross(left, [0.0, 1.0, 0.0]), forward * [1, 0, 1])
        assert np.mean(facing > 0) > 0.8, entry["id"]


def test_unmappable_rig(tmp_path):
    (tmp_path / "tiny.bvh").write_text(TINY_BVH)
    motion = read_motion(tmp_path / "tiny.bvh")
    assert detect_joint_map(motion) is None
    with pytest.raises(UsageError, match=r"tiny.bvh: cannot map the rig onto smpl22 .*lacks joints .*left_hip"):
        retarget(motion, "smpl22")
    with pytest.raises(UsageError, match="needs joints the file lacks: Hips, Spine, .*UpperLeg_L"):
        retarget(motion, "smpl22", joint_map="bandai")
    with pytest.raises(UsageError, match="maps onto 'smal35', not 'smpl22'"):
        retarget(motion, "smpl22", joint_map="mann_dog")


def _renamed_bvh(src: Path, dst: Path, rename: dict) -> None:
    text = src.read_text()
    for old, new in rename.items():
        text = text.replace(f"JOINT {old}\n", f"JOINT {new}\n").replace(f"ROOT {old}\n", f"ROOT {new}\n")
    dst.write_text(text)


def test_user_yaml_map(shared_motion, tmp_path):
    """A rig with unknown names maps through a YAML file, exactly as the built-in map does."""
    src = sorted((shared_motion / "human/bandai1").glob("*walk_normal*.bvh"))[0]
    rename = {name: f"my_{name}" for name in set(get_joint_map("bandai").joints.values())}
    _renamed_bvh(src, tmp_path / "renamed.bvh", rename)
    renamed = read_motion(tmp_path / "renamed.bvh")
    assert "my_Hips" in renamed.names
    with pytest.raises(UsageError, match="lacks joints"):
        retarget(renamed, "smpl22")
    joints = {t: rename[s] for t, s in get_joint_map("bandai").joints.items()}
    lines = ["target: smpl22", "joints:"] + [f"  {t}: {s}" for t, s in joints.items()]
    (tmp_path / "map.yaml").write_text("\n".join(lines) + "\n")
    mine = retarget(renamed, "smpl22", joint_map=tmp_path / "map.yaml", fps=20)
    builtin = retarget(read_motion(src), "smpl22", fps=20)
    np.testing.assert_allclose(mine.positions, builtin.positions, atol=1e-6)
    assert mine.category == "human"

    # a map that leaves a limb unanchored names the target joints it misses
    short = [line for line in lines if not line.strip().startswith(("left_ankle", "left_foot"))]
    (tmp_path / "short.yaml").write_text("\n".join(short) + "\n")
    with pytest.raises(UsageError, match="leaves left_ankle of smpl22 unmapped"):
        retarget(renamed, "smpl22", joint_map=tmp_path / "short.yaml")
    (tmp_path / "bad.yaml").write_text("joints: [1, 2]\n")
    with pytest.raises(UsageError, match="bad.yaml: expected a mapping"):
        retarget(renamed, "smpl22", joint_map=tmp_path / "bad.yaml")


def test_z_up_source_and_height(shared_motion):
    motion = read_motion(sorted((shared_motion / "human/bandai2").glob("*walk_normal*.bvh"))[0])
    # the whole rig turned so that its up axis is +Z (Rx(90) takes +Y to +Z)
    turn = torch.tensor([np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0], dtype=torch.float64)
    rot = motion.rotations.copy()
    rot[:, 0] = quat_mul(turn.expand(len(motion), 4), torch.from_numpy(rot[:, 0])).numpy()
    trans = motion.translations.copy()
    # (x, y, z) -> (x, -z, y)
    trans[:, 0] = trans[:, 0] @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64)
    z_up = replace(motion, rotations=rot, translations=trans)
    head, toes = motion.names.index("Head"), motion.names.index("Toes_L")
    assert np.median(z_up.positions()[:, head, 2] - z_up.positions()[:, toes, 2]) > 1.0  # Z up indeed
    a, b = retarget(motion, "smpl22", fps=20), retarget(z_up, "smpl22", fps=20)
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-5)
    np.testing.assert_allclose(retarget(z_up, "smpl22", fps=20, up="z").positions, a.positions, atol=1e-5)

    tall = retarget(motion, "smpl22", fps=20, height=1.8)
    skel = tall.skeleton
    identity = torch.tensor([1.0, 0, 0, 0]).expand(1, 22, 4)
    rest = skel.forward_kinematics(identity, torch.zeros(1, 3), torch.from_numpy(tall.offsets))
    assert abs(float(np.ptp(rest[0, :, 1].numpy())) - 1.8) < 1e-4
    ratio = np.linalg.norm(tall.offsets[1:], axis=-1) / np.linalg.norm(a.offsets[1:], axis=-1)
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-5)  # proportions kept
