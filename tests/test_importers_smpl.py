"""The SMPL-family parameter importers (aistpp, motionx) on files the tests write in the real formats:
an AIST++ pickle (60 fps, centimetres times smpl_scaling), Motion-X (T, 322) SMPL-X frames in the
release layout with a caption, and an AMASS-style SMPL-X .npz. Each walks: the imported smpl22 clip
must be the walk an independent forward kinematics gives, with constant bones and planted feet."""

from __future__ import annotations

import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import smpl_reference_joints
from helpers.unreadable import FIFO, TOO_LARGE, huge_npy, no_hang, one_line_error
from omg.cli import main
from omg.data.shards import resolved
from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES
from omg.kinematics import ground_contacts
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.skeleton import SMAL35, SMPL22, SMPL22_PARENTS

AIST_NAME = "gBR_sBM_cAll_d04_mBR0_ch01"
SCALING = 93.5  # AIST++'s smpl_scaling is about this


def _body_model(path: Path, joints: int, betas: int) -> dict:
    """A body whose rest joints are smpl22's template (vertex j is joint j), plus the extra joints
    of SMPL (24) or SMPL-X (55); beta 0 scales the whole body by 5 % per unit."""
    rng = np.random.default_rng(joints)
    extra = joints - 22
    v_template = np.concatenate([SMPL22.rest_positions(), rng.uniform(-0.2, 0.2, (extra, 3)) + [0, 1.5, 0]])
    shapedirs = np.zeros((len(v_template), 3, betas))
    shapedirs[..., 0] = 0.05 * v_template
    parents = SMPL22_PARENTS + [15 if j < 25 else 20 + (j - 25) % 2 for j in range(22, joints)]
    model = {"v_template": v_template, "shapedirs": shapedirs, "J_regressor": np.eye(joints, len(v_template)),
             "kintree_table": np.stack([np.array(parents) % 2**32, np.arange(joints)]).astype(np.int64)}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **model)
    return model


def _walk(model: dict, fps: float, seconds: float, betas: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SMPL parameters of a walk along +Z (Y up), one stride per second: hips swinging in
    antiphase, the swinging knee bent; the root bobs to keep the lower foot on y = 0 and travels
    as far as the stance foot swings back. Returns (T, 72) poses, (T, 3) trans, (T, 22, 3) joints."""
    T = int(seconds * fps) + 1
    phase = 2 * np.pi * np.arange(T) / fps
    poses = np.zeros((T, 72))
    for hip, knee, sign in ((1, 4, 1.0), (2, 5, -1.0)):
        poses[:, 3 * hip] = sign * 0.35 * np.sin(phase)  # about X: > 0 takes the foot back (-Z)
        poses[:, 3 * knee] = 0.6 * np.maximum(0.0, -sign * np.cos(phase))
    poses[:, 3 * 16 + 2], poses[:, 3 * 17 + 2] = -1.2, 1.2  # arms lowered
    P = smpl_reference_joints(model, poses, np.zeros((T, 3)), betas)
    feet = np.array([[7, 10], [8, 11]])  # (left, right) x (ankle, foot)
    lowest = P[:, feet, 1].min(2)  # (T, 2)
    stance = lowest.argmin(1)
    toe_z = P[:, feet[:, 1], 2]
    step = -(toe_z[1:, stance[:-1]].diagonal() - toe_z[:-1, stance[:-1]].diagonal())
    trans = np.stack([np.zeros(T), -lowest.min(1), np.concatenate([[0.0], np.cumsum(step)])], 1)
    return poses, trans, smpl_reference_joints(model, poses, trans, betas)


def _check_walk(clip: Clip, expected: np.ndarray) -> None:
    """A clean smpl22 walk: constant bones, feet on the floor and planting, left at +X, the
    expected joints (up to the floor's height)."""
    P = clip.positions
    assert clip.skeleton.name == "smpl22" and clip.category == "human" and np.isfinite(P).all()
    assert P.shape == expected.shape
    bones = np.stack([np.linalg.norm(P[:, j] - P[:, p], axis=-1) for j, p in enumerate(SMPL22_PARENTS) if p >= 0], 1)
    assert np.ptp(bones, 0).max() < 1e-4  # constant bone lengths (metres)
    assert abs(P[:, list(SMPL22.feet), 1].min()) < 0.01  # the lowest foot joint touches the floor
    contact = ground_contacts(torch.from_numpy(P).double(), SMPL22.feet, clip.fps).numpy()
    assert contact[:, [1, 3]].any(0).all()  # both feet plant
    assert (P[:, 1, 0] > P[:, 2, 0]).all()  # left hip at +X while walking along +Z
    assert P[-1, 0, 2] - P[0, 0, 2] > 0.5
    floor = np.median(P[..., 1] - expected[..., 1])
    assert abs(floor) < 0.01
    np.testing.assert_allclose(P, expected + [0.0, floor, 0.0], atol=1e-4)
    assert clip.rotations is not None and clip.offsets is not None  # a rig that BVH export can use


# ---------------------------------------------------------------- AIST++


@pytest.fixture(scope="session")
def aist_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("aistpp")
    model = _body_model(root / "smpl" / "neutral" / "model.npz", joints=24, betas=10)
    poses, trans, joints = _walk(model, 60.0, 2.0, np.zeros(10))
    motions = root / "motions"
    motions.mkdir()
    with open(motions / f"{AIST_NAME}.pkl", "wb") as f:  # as AIST++ ships them: a dict of numpy arrays
        pickle.dump({"smpl_poses": poses, "smpl_trans": trans * SCALING, "smpl_scaling": np.array([SCALING]),
                     "smpl_loss": np.float64(0.5)}, f)
    with open(motions / "gPO_sFM_cAll_d10_mPO1_ch02.pkl", "wb") as f:
        pickle.dump({"smpl_poses": poses, "smpl_trans": trans * SCALING}, f)  # no smpl_scaling
    (motions / "gHO_sBM_cAll_d19_mHO0_ch01.pkl").write_bytes(pickle.dumps(print))  # code, not arrays
    with open(motions / "gKR_sBM_cAll_d28_mKR0_ch01.pkl", "wb") as f:  # listed in ignore_list.txt
        pickle.dump({}, f)
    (root / "ignore_list.txt").write_text("gKR_sBM_cAll_d28_mKR0_ch01\n")
    np.save(root / "expected.npy", joints)
    return root


def _aist(root: Path, fps: float = 30.0, **options):
    options.setdefault("body_model", str(root / "smpl"))
    return list(resolved(DATA_SOURCES.get("aistpp")(input=str(root / "motions"), skeleton=SMPL22, fps=fps,
                                                     **options)))


def test_aistpp_pickle_imports_a_clean_walk(aist_root):
    items = _aist(aist_root)
    clips = [c for c in items if isinstance(c, Clip)]
    errors = sorted(str(e) for e in items if isinstance(e, Exception))
    assert len(items) == 3  # the ignored sequence is not listed
    assert [c.id for c in clips] == [AIST_NAME]
    clip = clips[0]
    assert clip.fps == 30.0 and clip.texts == [] and clip.source.endswith(f"{AIST_NAME}.pkl")
    assert clip.labels == {"genre": "break", "situation": "basic", "dancer": "d04", "music": "mBR0"}
    _check_walk(clip, np.load(aist_root / "expected.npy")[::2])  # 60 -> 30 fps: every other frame
    assert errors[0].startswith("aistpp missing keys") and "smpl_scaling" in errors[0]
    assert errors[1].startswith("aistpp unreadable file") and "only numpy arrays" in errors[1]


def test_aistpp_options_and_body_model_errors(aist_root, tmp_path):
    with pytest.raises(UsageError, match=r"--option.body_model PATH"):
        DATA_SOURCES.get("aistpp")(input=str(aist_root / "motions"), skeleton=SMPL22, fps=30.0)
    with pytest.raises(UsageError, match="no such file"):
        _aist(aist_root, body_model=str(tmp_path / "nothing.npz"))
    with pytest.raises(UsageError, match="smpl22"):
        DATA_SOURCES.get("aistpp")(input=str(aist_root / "motions"), skeleton=SMAL35, fps=30.0,
                                   body_model=str(aist_root / "smpl"))
    with pytest.raises(UsageError, match="--option.up"):
        _aist(aist_root, up="w")
    clip = next(c for c in _aist(aist_root, fps=20.0) if isinstance(c, Clip))
    assert clip.fps == 20.0 and len(clip) == 41  # 2 s at 20 fps


def test_aistpp_shards_count_skips(aist_root, tmp_path):
    out = tmp_path / "aist"
    main(["shards", "build", "--source", "aistpp", "--input", str(aist_root / "motions"), "--out", str(out),
          "--fps", "30", "--option.body_model", str(aist_root / "smpl")])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["num_clips"] == 1 and manifest["num_frames"] == 60  # humanml3d263: one feature row per frame pair
    assert manifest["skipped"] == {"aistpp missing keys": 1, "aistpp unreadable file": 1}


# ---------------------------------------------------------------- Motion-X


@pytest.fixture(scope="session")
def motionx_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("motionx")
    model = _body_model(root / "smplx" / "neutral" / "model.npz", joints=55, betas=400)
    betas = np.zeros(10)
    betas[0] = 1.0  # a 5 % taller body
    poses, trans, joints = _walk(model, 30.0, 2.0, betas)
    T = len(poses)
    frames = np.zeros((T, 322), dtype=np.float32)
    frames[:, 0:66] = poses[:, :66]  # root orientation, body pose
    frames[:, 66:156] = 0.3  # hands: dropped
    frames[:, 159:209] = 0.5  # face expression: dropped
    frames[:, 309:312], frames[:, 312:322] = trans, betas
    subset = root / "data" / "motion_data" / "smplx_322" / "idea400"
    subset.mkdir(parents=True)
    np.save(subset / "walk_clip1.npy", frames)
    np.save(subset / "short.npy", frames[:1])
    np.save(subset / "wrong.npy", np.zeros((10, 100), dtype=np.float32))
    (subset / "broken.npy").write_bytes(b"\x93NUMPY garbage")
    captions = root / "data" / "texts" / "semantic_labels" / "idea400"
    captions.mkdir(parents=True)
    (captions / "walk_clip1.txt").write_text("a person walks forward.\n")
    np.save(root / "expected30.npy", joints.astype(np.float64))

    # an AMASS-style SMPL-X parameter file at 60 fps (hands and jaw given, dropped)
    poses60, trans60, joints60 = _walk(model, 60.0, 2.0, betas)
    amass = root / "amass" / "ACCAD"
    amass.mkdir(parents=True)
    np.savez(amass / "walk_stageii.npz", root_orient=poses60[:, :3], pose_body=poses60[:, 3:66],
             pose_hand=np.full((len(poses60), 90), 0.2), pose_jaw=np.zeros((len(poses60), 3)), trans=trans60,
             betas=np.concatenate([betas, np.zeros(6)]), gender=np.array("female"),
             mocap_frame_rate=np.array(60.0), surface_model_type=np.array("smplx"))
    np.savez(amass / "no_trans.npz", poses=poses60)
    np.save(root / "expected60.npy", joints60)
    return root


def _motionx(root: Path, folder: str, fps: float = 30.0, **options):
    options.setdefault("body_model", str(root / "smplx"))
    return list(resolved(DATA_SOURCES.get("motionx")(input=str(root / folder), skeleton=SMPL22, fps=fps,
                                                      **options)))


def test_motionx_npy_release_layout(motionx_root):
    items = _motionx(motionx_root, "data")
    clips = {c.id: c for c in items if isinstance(c, Clip)}
    errors = sorted(str(e) for e in items if isinstance(e, Exception))
    assert list(clips) == ["idea400/walk_clip1"]
    clip = clips["idea400/walk_clip1"]
    assert clip.texts == ["a person walks forward."] and clip.labels == {"subset": "idea400", "gender": "neutral"}
    _check_walk(clip, np.load(motionx_root / "expected30.npy"))  # 30 fps in, 30 fps out
    assert [e.split(":")[0] for e in errors] == ["motionx bad motion", "motionx unreadable file",
                                                 "motionx wrong array shape"]


def test_motionx_smplx_npz_drops_hands_and_resamples(motionx_root):
    items = _motionx(motionx_root, "amass")
    clips = {c.id: c for c in items if isinstance(c, Clip)}
    errors = [str(e) for e in items if isinstance(e, Exception)]
    clip = clips["ACCAD/walk_stageii"]
    assert clip.labels == {"subset": "ACCAD", "gender": "female"}  # no female model: the neutral one
    _check_walk(clip, np.load(motionx_root / "expected60.npy")[::2])  # 60 -> 30 fps
    assert len(errors) == 1 and errors[0].startswith("motionx missing keys") and "trans" in errors[0]


def test_motionx_shards_build(motionx_root, tmp_path):
    out = tmp_path / "mx"
    main(["shards", "build", "--source", "motionx", "--input", str(motionx_root / "data"), "--out", str(out),
          "--fps", "20", "--option.body_model", str(motionx_root / "smplx" / "neutral" / "model.npz")])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["num_clips"] == 1 and manifest["num_frames"] == 40  # 41 frames at 20 fps, one feature row per pair
    assert sum(manifest["skipped"].values()) == 3


# ---------------------------------------------------------------- files that are no regular file, or too large


def test_aistpp_fifo_and_huge_pickles_are_counted_skips(aist_root, tmp_path, capsys):
    motions = tmp_path / "motions"
    motions.mkdir()
    shutil.copy(aist_root / "motions" / f"{AIST_NAME}.pkl", motions)
    os.mkfifo(motions / "gJB_sBM_cAll_d07_mJB0_ch01.pkl")  # reading it whole would wait for a writer forever
    with open(motions / "gJS_sBM_cAll_d01_mJS0_ch01.pkl", "wb") as f:  # sparse: one byte over the bound
        f.truncate(MOTION_MAX_BYTES + 1)
    out = tmp_path / "aist"
    with no_hang():
        main(["shards", "build", "--source", "aistpp", "--input", str(motions), "--out", str(out), "--fps", "30",
              "--option.body_model", str(aist_root / "smpl")])
    log = capsys.readouterr().out.splitlines()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["num_clips"] == 1 and manifest["skipped"] == {"aistpp unreadable file": 2}
    assert any("gJB_sBM_cAll_d07_mJB0_ch01.pkl" in line and FIFO in line for line in log), log
    assert any("gJS_sBM_cAll_d01_mJS0_ch01.pkl" in line and TOO_LARGE in line for line in log), log


def test_aistpp_fifo_ignore_list_is_one_line(aist_root, tmp_path, capsys):
    shutil.copytree(aist_root / "motions", tmp_path / "motions")
    os.mkfifo(tmp_path / "ignore_list.txt")
    err = one_line_error(capsys, ["shards", "build", "--source", "aistpp", "--input", str(tmp_path / "motions"),
                                  "--out", str(tmp_path / "out"), "--fps", "30",
                                  "--option.body_model", str(aist_root / "smpl")])
    assert f"aistpp: {tmp_path / 'ignore_list.txt'}: {FIFO}" in err, err


def test_motionx_fifo_and_huge_files_are_counted_skips(motionx_root, tmp_path, capsys):
    """A FIFO named like a motion (listed, not passed over) or like a caption file, and a motion over
    the bound: each one counted skip, and the build finishes."""
    subset = tmp_path / "motion_data" / "smplx_322" / "idea400"
    captions = tmp_path / "texts" / "semantic_labels" / "idea400"
    subset.mkdir(parents=True)
    captions.mkdir(parents=True)
    for name in ("walk_clip1", "walk_clip2"):
        shutil.copy(motionx_root / "data" / "motion_data" / "smplx_322" / "idea400" / "walk_clip1.npy",
                    subset / f"{name}.npy")
    (captions / "walk_clip1.txt").write_text("a person walks forward.\n")
    os.mkfifo(captions / "walk_clip2.txt")
    os.mkfifo(subset / "fifo.npy")
    huge_npy(subset / "huge.npy", (10,))
    out = tmp_path / "mx"
    with no_hang():
        main(["shards", "build", "--source", "motionx", "--input", str(tmp_path), "--out", str(out), "--fps", "20",
              "--option.body_model", str(motionx_root / "smplx" / "neutral" / "model.npz")])
    log = capsys.readouterr().out.splitlines()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["num_clips"] == 1 and manifest["skipped"] == {"motionx unreadable file": 3}
    for name, why in [("walk_clip2.txt", FIFO), ("fifo.npy", FIFO), ("huge.npy", TOO_LARGE)]:
        assert any(name in line and why in line for line in log), (name, log)
