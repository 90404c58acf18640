"""The dataset importers (humanml3d, animalml3d, amass) on small fixtures in the official formats."""

from __future__ import annotations

import json
import os
import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from helpers import JointPositions, smpl_reference_joints, walking_clip
from helpers.unreadable import FIFO, TOO_LARGE, huge_npy, no_hang, one_line_error
from omg.cli import main
from omg.data.shards import Manifest, ShardWriter, decode_sample, encode_sample, iter_tar, resolved
from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES
from omg.motion import Clip, get_representation
from omg.registry import DATA_SOURCES
from omg.rotations import quat_between, quat_conjugate, quat_mul, quat_normalize, quat_to_6d
from omg.skeleton import SMAL35, SMPL22, SMPL22_PARENTS


def _split(items):
    items = list(items)
    return {c.id: c for c in items if isinstance(c, Clip)}, [str(e) for e in items if isinstance(e, Exception)]


def _samples(shard_dir: Path) -> dict[str, dict]:
    return {s["meta"]["id"]: s
            for path in Manifest.load(shard_dir).shard_paths for s in map(decode_sample, iter_tar(path))}


# ---------------------------------------------------------------- humanml3d

H263 = get_representation("humanml3d263", SMPL22)
CAPTIONS = {
    "000001": [
        "a person walks forward#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0",
        "someone strolls#someone/PRON stroll/VERB#0.0#0.0",
        "a person takes a few steps#a/DET person/NOUN take/VERB a/DET few/ADJ step/NOUN#0.5#3.0",
        "walking ahead#walk/VERB ahead/ADV#0.5#3.0",
        "a tiny step#a/DET tiny/ADJ step/NOUN#0.1#1.0",  # 18 frames: too short, skipped
    ],
}


def _hml_motion(index: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(frames - 1, 263) features and (frames, 22, 3) canonical joints, as HumanML3D's files."""
    clip = walking_clip(index)
    positions = np.concatenate([clip.positions] * 3)[:frames]
    clip = Clip(id="x", skeleton=SMPL22, fps=20.0, positions=positions)
    return H263.encode(clip)[0], H263.canonicalize(positions).astype(np.float32)


@pytest.fixture(scope="session")
def hml_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("HumanML3D")
    for d in ("new_joint_vecs", "new_joints", "texts"):
        (root / d).mkdir()
    default = ["a person walks#a/DET person/NOUN walk/VERB#0.0#0.0"]
    for i, name in enumerate(["000001", "000002", "000003", "000004", "000006", "007975"]):
        features, joints = _hml_motion(i, 81)
        if name == "007975":
            features[5, 7] = np.nan  # as HumanML3D's own 007975
        if name != "000003":  # 000003: positions only
            np.save(root / "new_joint_vecs" / f"{name}.npy", features)
        if name != "000004":  # 000004: features only
            np.save(root / "new_joints" / f"{name}.npy", joints)
        (root / "texts" / f"{name}.txt").write_text("\n".join(CAPTIONS.get(name, default)) + "\n")
    (root / "new_joint_vecs" / "000005.npy").write_bytes(b"not a numpy file")
    (root / "texts" / "000005.txt").write_text(default[0])
    (root / "train.txt").write_text("000001\n000002\n000003\n000004\n000005\n007975\n")
    (root / "test.txt").write_text("000006\n")
    rng = np.random.default_rng(0)
    np.save(root / "Mean.npy", rng.standard_normal(263).astype(np.float32))
    np.save(root / "Std.npy", rng.uniform(0.5, 2.0, 263).astype(np.float32))
    return root


def _hml(root, **options):
    return DATA_SOURCES.get("humanml3d")(input=str(root), skeleton=SMPL22, fps=20.0, **options)


def test_humanml3d_crops_tokens_and_skips(hml_root):
    clips, errors = _split(_hml(hml_root))
    features = np.load(hml_root / "new_joint_vecs" / "000001.npy")
    joints = np.load(hml_root / "new_joints" / "000001.npy")

    whole, crop = clips["000001"], clips["000001@0.5-3"]
    assert whole.texts == ["a person walks forward", "someone strolls"]
    assert whole.labels["tokens"][1] == ["someone/PRON", "stroll/VERB"]
    np.testing.assert_array_equal(whole.features, features)
    # a span is its own sub-clip: rows [int(0.5 * 20), int(3.0 * 20)) of the features
    assert crop.texts == ["a person takes a few steps", "walking ahead"]
    assert crop.labels["tokens"][1] == ["walk/VERB", "ahead/ADV"] and crop.labels["span"] == [0.5, 3.0]
    np.testing.assert_array_equal(crop.features, features[10:60])
    np.testing.assert_array_equal(crop.positions, joints[10:61])
    assert crop.features_representation == "humanml3d263" and crop.fps == 20.0

    assert clips["000003"].features is None and clips["000003"].positions.shape == (81, 22, 3)
    assert clips["000004"].positions.shape == (80, 22, 3)  # decoded from the features (recover_from_ric)
    np.testing.assert_allclose(clips["000004"].positions,
                               H263.decode(torch.from_numpy(clips["000004"].features)).numpy())
    assert "007975" not in clips and "000001@0.1-1" not in clips
    assert any(e.startswith("humanml3d NaN or inf in motion") and "007975.npy" in e for e in errors)
    assert any(e.startswith("humanml3d unreadable file") and "000005.npy" in e for e in errors)
    assert any(e.startswith("humanml3d length outside") and "000001@0.1-1" in e for e in errors)


def test_humanml3d_split_and_options(hml_root):
    clips, _ = _split(_hml(hml_root, split="test"))
    assert list(clips) == ["000006"]
    assert "000006" not in _split(_hml(hml_root, split="train"))[0]
    with pytest.raises(UsageError, match="option.split 'nope'"):
        _hml(hml_root, split="nope")
    with pytest.raises(UsageError, match="val.txt"):
        _hml(hml_root, split="val")
    with pytest.raises(UsageError, match="--fps 20"):
        DATA_SOURCES.get("humanml3d")(input=str(hml_root), skeleton=SMPL22, fps=30.0)
    # long clips on request: every whole motion has 80 feature rows
    assert "000002" not in _split(_hml(hml_root, max_frames=50))[0]
    assert "000002" in _split(_hml(hml_root, max_frames=0))[0]


def test_humanml3d_keeps_the_papers_lengths(tmp_path):
    """20 to 196 feature frames, both ends included (HumanML3D's loader kept 40 <= T < 200)."""
    for d in ("new_joint_vecs", "texts"):
        (tmp_path / d).mkdir()
    for frames in (19, 20, 196, 197):
        features = np.concatenate([_hml_motion(frames, 81)[0]] * 3)[:frames]
        np.save(tmp_path / "new_joint_vecs" / f"{frames:06d}.npy", features)
        (tmp_path / "texts" / f"{frames:06d}.txt").write_text("a person walks#a/DET person/NOUN walk/VERB#0.0#0.0\n")
    clips, errors = _split(_hml(tmp_path))
    assert sorted(clips) == ["000020", "000196"]
    assert sorted(e.split(":")[0] for e in errors) == ["humanml3d length outside [20, 196] frames"] * 2


def test_humanml3d_shards_through_cli(hml_root, tmp_path, capsys):
    out = tmp_path / "shards"
    main(["shards", "build", "--source", "humanml3d", "--input", str(hml_root), "--out", str(out),
          "--fps", "20", "--option.split", "train"])
    assert "skipped 3" in capsys.readouterr().out
    manifest = Manifest.load(out)
    # the published normalisation, verbatim
    np.testing.assert_array_equal(manifest.mean, np.load(hml_root / "Mean.npy"))
    np.testing.assert_array_equal(manifest.std, np.load(hml_root / "Std.npy"))
    assert manifest["stats_origin"] == "source"
    assert set(manifest["skipped"]) == {"humanml3d NaN or inf in motion", "humanml3d unreadable file",
                                        "humanml3d length outside [20, 196] frames"}
    samples = _samples(out)
    assert set(samples) == {"000001", "000001@0.5-3", "000002", "000003", "000004"}
    np.testing.assert_array_equal(samples["000001@0.5-3"]["motion"],
                                  np.load(hml_root / "new_joint_vecs" / "000001.npy")[10:60])
    assert samples["000001@0.5-3"]["meta"]["labels"]["tokens"][0][0] == "a/DET"
    assert samples["000002"]["texts"] == ["a person walks"]
    # 000003 has positions only: encoded here, as HumanML3D would have
    joints = np.load(hml_root / "new_joints" / "000003.npy")
    expected = H263.encode(Clip(id="c", skeleton=SMPL22, fps=20.0, positions=joints))[0]
    np.testing.assert_allclose(samples["000003"]["motion"], expected, atol=1e-5)


def test_humanml3d_builds_as_maa_by_ik(hml_root, tmp_path):
    """OmniMotionGPT's human data: HumanML3D's joint positions become smpl22 maa through IK, and
    decoding gives the positions back."""
    out = tmp_path / "maa"
    main(["shards", "build", "--source", "humanml3d", "--input", str(hml_root), "--out", str(out),
          "--fps", "20", "--representation", "maa", "--option.split", "train"])
    samples = _samples(out)
    assert {"000001", "000002", "000003"} <= set(samples)
    rep = get_representation("maa", SMPL22)
    for key in ("000002", "000003"):
        sample, joints = samples[key], np.load(hml_root / "new_joints" / f"{key}.npy")
        decoded = rep.decode(torch.from_numpy(sample["motion"]), torch.as_tensor(sample["meta"]["offsets"])).numpy()
        # within the fixture's own non-rigidity (its hips drift 1.4 cm apart, which no rotation reproduces;
        # exactness on rigid motion is tests/test_representations.py's)
        assert decoded.shape == joints.shape and np.abs(decoded - joints).max() < 0.06, key


def test_features_are_verbatim_only_for_their_representation():
    clip = walking_clip(0)
    features = np.random.default_rng(0).standard_normal((len(clip) - 1, 263)).astype(np.float32)
    clip = Clip(id=clip.id, skeleton=SMPL22, fps=20.0, positions=clip.positions, features=features,
                features_representation="humanml3d263")
    np.testing.assert_array_equal(encode_sample(clip, H263)[2], features)
    np.testing.assert_array_equal(encode_sample(clip, JointPositions(SMPL22))[2], clip.positions.reshape(len(clip), -1))
    with pytest.raises(ValueError, match="go together"):
        Clip(id="x", skeleton=SMPL22, fps=20.0, positions=clip.positions, features=features)


def test_fixed_stats_must_fit(tmp_path):
    with pytest.raises(UsageError, match="263 features"):
        ShardWriter(tmp_path, H263, 20.0, stats=(np.zeros(10), np.ones(10)))


# ---------------------------------------------------------------- animalml3d


def _animal_motion(seed: int, frames: int, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A rigid SMAL-35 motion in omg's convention, and the same motion as an OmniMotionGPT
    MAA file (T, 36, 6): HumanML3D-style IK, each bone's swing composed along its chain."""
    rng = np.random.default_rng(seed)
    axis_angle = (0.3 * rng.standard_normal((frames, 35, 3))
                  + 0.05 * np.arange(frames)[:, None, None] * rng.standard_normal(3))
    local = torch.from_numpy(
        Rotation.from_rotvec(axis_angle.reshape(-1, 3)).as_quat()[:, [3, 0, 1, 2]].reshape(frames, 35, 4))
    root = torch.from_numpy(np.cumsum(0.02 * rng.standard_normal((frames, 3)), 0) + [0, 0.5, 0])
    P = SMAL35.forward_kinematics(local, root, torch.from_numpy(offsets))  # (T, 35, 3)
    off = torch.from_numpy(offsets)
    q = [None] * 35
    q[0] = local[:, 0]
    for chain in SMAL35.chains:
        R = q[0]
        for a, b in zip(chain[:-1], chain[1:]):
            swing = quat_between(off[b].expand(frames, 3), P[:, b] - P[:, a])  # global rotation of bone b
            q[b] = quat_mul(quat_conjugate(R), swing)
            R = swing
    sixd = quat_to_6d(quat_normalize(torch.stack(q, 1))).numpy()  # (T, 35, 6)
    root6 = np.concatenate([root.numpy(), np.zeros((frames, 3))], 1)[:, None]
    return P.numpy(), np.concatenate([sixd, root6], 1).astype(np.float32)


def _write_animal(root: Path, animal: str, action: str, frames: int, offsets: np.ndarray, seed: int = 0,
                  caption: str | None = None) -> np.ndarray:
    """One clip in the release's layout (motion, and captions unless ``caption`` is ""); its joint positions."""
    positions, maa = _animal_motion(seed, frames, offsets)
    name = f"{animal}_{action}"
    (root / "animals_maa_motions").mkdir(parents=True, exist_ok=True)
    np.save(root / "animals_maa_motions" / f"{name}.npy", maa)
    if caption != "":
        (root / "motion_captions" / name).mkdir(parents=True)
        (root / "motion_captions" / name / "screenshots.txt").write_text(
            caption or f"the {animal} moves\n\nan animal {action.lower()}s#x\n")
    return positions


def _write_offsets(root: Path, animal: str, offsets: np.ndarray) -> None:
    (root / "animals_maa_offsets" / animal).mkdir(parents=True)
    with open(root / "animals_maa_offsets" / animal / "offset.pkl", "wb") as f:
        pickle.dump(offsets, f)
    np.save(root / "animals_maa_offsets" / animal / "mean.npy", np.zeros((36, 6)))
    np.save(root / "animals_maa_offsets" / animal / "std.npy", np.ones((36, 6)))


# real identities of the release: bearPDD's captions call it a pig, deerA4K a deer, foxXAT a fox, canieLTT a wolf
@pytest.fixture(scope="session")
def animal_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("AnimalML3D")
    rng = np.random.default_rng(1)
    for animal in ("bearPDD", "deerA4K", "foxXAT", "canieLTT"):
        offsets = SMAL35.rest_offsets.astype(np.float64) * rng.uniform(0.5, 2.0)
        if animal != "canieLTT":  # canieLTT has no offsets: skipped
            _write_offsets(root, animal, offsets)
        for k, action in enumerate(("Walk", "RunFast")):
            name = f"{animal}_{action}"
            positions = _write_animal(root, animal, action, 30 + k, offsets, seed=k,
                                      caption="" if name == "foxXAT_RunFast" else None)  # no captions: skipped
            np.save(root / f"expected_{name}.npy", positions)
    np.save(root / "animals_maa_motions" / "deerA4K_Broken.npy", np.zeros((30, 12)))
    return root


def _animals(root, **options):
    return DATA_SOURCES.get("animalml3d")(input=str(root), skeleton=SMAL35, fps=20.0, **options)


def test_animalml3d_layout_and_offsets(animal_root):
    clips, errors = _split(_animals(animal_root))
    assert set(clips) == {"bearPDD_Walk", "bearPDD_RunFast", "deerA4K_Walk", "deerA4K_RunFast", "foxXAT_Walk"}
    clip = clips["deerA4K_RunFast"]
    assert clip.category == "deer" and clip.labels == {"identity": "deerA4K", "species": "deer", "action": "RunFast"}
    assert clips["bearPDD_Walk"].category == "pig"  # the word of its captions, not of its name
    assert clip.texts == ["the deerA4K moves", "an animal runfasts"] and clip.fps == 20.0
    with open(animal_root / "animals_maa_offsets" / "deerA4K" / "offset.pkl", "rb") as f:
        np.testing.assert_allclose(clip.offsets, pickle.load(f), rtol=1e-6)
    expected = np.load(animal_root / "expected_deerA4K_RunFast.npy")
    np.testing.assert_allclose(clip.positions, expected, atol=1e-5)  # OmniMotionGPT's chain FK
    # the re-solved local rotations give the same positions through omg's FK, and through maa
    fk = SMAL35.forward_kinematics(torch.from_numpy(clip.rotations).double(),
                                   torch.from_numpy(clip.positions[:, 0]).double(),
                                   torch.from_numpy(clip.offsets).double())
    np.testing.assert_allclose(fk.numpy(), expected, atol=1e-4)
    maa = get_representation("maa", SMAL35)
    features, extra = maa.encode(clip)
    decoded = maa.decode(torch.from_numpy(features).double(), torch.tensor(extra["offsets"], dtype=torch.float64))
    np.testing.assert_allclose(decoded.numpy(), expected, atol=1e-4)
    for reason, file in [("animalml3d missing captions", "foxXAT_RunFast"), ("animalml3d missing offsets", "canieLTT"),
                         ("animalml3d wrong array shape", "deerA4K_Broken")]:
        assert any(e.startswith(reason) and file in e for e in errors), (reason, errors)


def test_animalml3d_split_by_identity(animal_root):
    ids = lambda **o: {c.labels["identity"] for c in _split(_animals(animal_root, **o))[0].values()}  # noqa: E731
    assert ids(split="test", test_animals="deerA4K,foxXAT") == {"deerA4K", "foxXAT"}
    assert ids(split="train", test_animals=["deerA4K", "foxXAT"]) == {"bearPDD"}
    train, test = ids(split="train"), ids(split="test")
    assert not train & test and train | test == {"bearPDD", "deerA4K", "foxXAT"}
    assert test == ids(split="test")  # deterministic
    with pytest.raises(UsageError, match="cat"):
        _animals(animal_root, split="test", test_animals="cat")
    with pytest.raises(UsageError, match="smal35"):
        DATA_SOURCES.get("animalml3d")(input=str(animal_root), skeleton=SMPL22, fps=20.0)


def test_animalml3d_shards_count_skips(animal_root, tmp_path):
    maa = get_representation("maa", SMAL35)
    summary = ShardWriter(tmp_path, maa, 20.0, log=lambda m: None).write(_animals(animal_root))
    assert summary.clips == 5
    assert summary.skipped == {"animalml3d missing captions": 1, "animalml3d missing offsets": 2,
                               "animalml3d wrong array shape": 1}
    sample = _samples(tmp_path)["bearPDD_Walk"]
    assert len(sample["meta"]["offsets"]) == 35 and sample["meta"]["category"] == "pig"
    assert sample["meta"]["labels"] == {"identity": "bearPDD", "species": "pig", "action": "Walk"}


def test_animalml3d_keeps_the_papers_lengths_and_names_unknown_identities(tmp_path):
    """The paper's AnimalML3D filter keeps 10 to 196 frames, both ends included; an identity outside the
    release's table is a counted skip until --option.species names its animal."""
    offsets = SMAL35.rest_offsets.astype(np.float64)
    for animal in ("foxXAT", "unicorn7"):
        _write_offsets(tmp_path, animal, offsets)
    for frames in (9, 10, 196, 197):
        _write_animal(tmp_path, "foxXAT", f"Len{frames}", frames, offsets)
    _write_animal(tmp_path, "unicorn7", "Walk", 30, offsets)
    clips, errors = _split(_animals(tmp_path))
    assert set(clips) == {"foxXAT_Len10", "foxXAT_Len196"}
    assert sorted(e.split(":")[0] for e in errors) == ["animalml3d length outside [10, 196] frames"] * 2 + [
        "animalml3d unknown identity"]
    clips, errors = _split(_animals(tmp_path, species={"unicorn7": "unicorn"}, min_frames=20))
    assert set(clips) == {"foxXAT_Len196", "unicorn7_Walk"} and clips["unicorn7_Walk"].category == "unicorn"
    with pytest.raises(UsageError, match="species must map identities to species words"):
        _animals(tmp_path, species={"unicorn7": ""})


# ---------------------------------------------------------------- amass


def _body_model(path: Path, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    V, J = 40, 52  # SMPL-H: 22 body joints + 30 hand joints below the wrists
    parents = SMPL22_PARENTS + [20 if j < 37 else 21 for j in range(22, J)]
    regressor = rng.uniform(0, 1, (J, V))
    model = {
        "v_template": rng.uniform(-0.5, 0.5, (V, 3)) + [0, 0.9, 0],
        "shapedirs": 0.01 * rng.standard_normal((V, 3, 16)),
        "J_regressor": regressor / regressor.sum(1, keepdims=True),
        "kintree_table": np.stack([np.array(parents) % 2**32, np.arange(J)]).astype(np.int64),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **model)
    return model


def _reference_joints(model: dict, poses, trans, betas) -> np.ndarray:
    """Independent SMPL joints (``smpl_reference_joints``), then AMASS's (x, y, z) -> (-x, z, y)."""
    out = smpl_reference_joints(model, poses, trans, betas)
    return np.stack([-out[..., 0], out[..., 2], out[..., 1]], -1)


@pytest.fixture(scope="session")
def amass_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("AMASS")
    _body_model(root / "models" / "smplh" / "male" / "model.npz", seed=0)
    _body_model(root / "models" / "smplh" / "neutral" / "model.npz", seed=1)
    rng = np.random.default_rng(2)
    data = root / "data" / "CMU" / "01"
    data.mkdir(parents=True)
    np.savez(data / "01_01_poses.npz", poses=0.4 * rng.standard_normal((121, 156)), trans=rng.standard_normal((121, 3)),
             betas=rng.standard_normal(16), mocap_framerate=np.array(120.0), gender=np.array("male"))
    np.savez(data / "01_02_poses.npz", poses=0.4 * rng.standard_normal((50, 72)), trans=rng.standard_normal((50, 3)),
             betas=rng.standard_normal(10), mocap_frame_rate=np.array(100.0), gender=np.array(b"female"))
    np.savez(data / "shape.npz", betas=rng.standard_normal(16), gender=np.array("male"))
    np.savez(data / "01_03_poses.npz", poses=np.zeros((10, 156)), mocap_framerate=np.array(120.0))  # no trans, betas
    (data / "01_04_poses.npz").write_bytes(b"truncated")
    return root


def _amass(root, fps=20.0, **options):
    return resolved(DATA_SOURCES.get("amass")(input=str(root / "data"), skeleton=SMPL22, fps=fps, **options))


def test_amass_joints_match_independent_fk(amass_root):
    model_file = amass_root / "models" / "smplh" / "male" / "model.npz"
    clips, errors = _split(_amass(amass_root, body_model=str(model_file)))
    assert set(clips) == {"CMU/01/01_01_poses", "CMU/01/01_02_poses"}  # shape.npz is not a motion
    with np.load(amass_root / "data" / "CMU" / "01" / "01_01_poses.npz") as f:
        expected = _reference_joints(dict(np.load(model_file)), f["poses"], f["trans"], f["betas"])
    clip = clips["CMU/01/01_01_poses"]
    assert clip.fps == 20.0 and clip.texts == [] and clip.labels == {"dataset": "CMU", "gender": "male"}
    np.testing.assert_allclose(clip.positions, expected[::6], atol=1e-5)  # 120 -> 20 fps: every 6th frame
    assert any(e.startswith("amass missing keys") and "01_03_poses.npz" in e and "trans" in e for e in errors)
    assert any(e.startswith("amass unreadable file") and "01_04_poses.npz" in e for e in errors)


def test_amass_resampling_and_gendered_models(amass_root):
    folder = str(amass_root / "models" / "smplh")
    clips, _ = _split(_amass(amass_root, fps=30.0, body_model=folder))
    with np.load(amass_root / "data" / "CMU" / "01" / "01_02_poses.npz") as f:
        # female has no model in the folder: the neutral one is used
        expected = _reference_joints(dict(np.load(amass_root / "models/smplh/neutral/model.npz")), f["poses"],
                                     f["trans"], f["betas"])
    clip = clips["CMU/01/01_02_poses"]  # 50 frames at 100 fps -> 0.49 s -> 15 frames at 30 fps
    assert clip.positions.shape == (15, 22, 3) and clip.labels["gender"] == "female"
    t = np.arange(15) / 30 * 100  # source frame of each output frame
    i, w = np.floor(t).astype(int), (t - np.floor(t))[:, None, None]
    np.testing.assert_allclose(clip.positions, (1 - w) * expected[i] + w * expected[np.minimum(i + 1, 49)], atol=1e-5)
    assert len(clips["CMU/01/01_01_poses"]) == 31  # 120 -> 30 fps: every 4th of 121 frames


def test_amass_body_model_errors(amass_root, tmp_path):
    with pytest.raises(UsageError, match=r"--option.body_model PATH"):
        _amass(amass_root)
    (tmp_path / "model.pkl").write_bytes(b"\x80\x02}q\x00.")
    with pytest.raises(UsageError, match="chumpy.*npz"):
        _amass(amass_root, body_model=str(tmp_path / "model.pkl"))
    np.savez(tmp_path / "partial.npz", v_template=np.zeros((4, 3)))
    with pytest.raises(UsageError, match="lacks"):
        _amass(amass_root, body_model=str(tmp_path / "partial.npz"))


def test_amass_shards_count_skips(amass_root, tmp_path):
    out = tmp_path / "amass"
    main(["shards", "build", "--source", "amass", "--input", str(amass_root / "data"), "--out", str(out), "--fps", "20",
          "--option.body_model", str(amass_root / "models" / "smplh")])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["num_clips"] == 2 and manifest["stats_origin"] == "measured"
    assert manifest["skipped"] == {"amass missing keys": 1, "amass unreadable file": 1}


def test_humanml3d_object_array_stats_are_one_line(hml_root, tmp_path, capsys):
    """A Mean.npy that holds a pickled object array (np.save of a list of objects) is refused with
    one line naming the file, never unpickled."""
    import shutil

    root = tmp_path / "HumanML3D"
    shutil.copytree(hml_root, root)
    np.save(root / "Mean.npy", np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    out = tmp_path / "shards"
    with pytest.raises(SystemExit) as exit:
        main(["shards", "build", "--source", "humanml3d", "--input", str(root), "--out", str(out), "--fps", "20"])
    err = capsys.readouterr().err.strip()
    assert exit.value.code == 2 and "\n" not in err and "Traceback" not in err, err
    assert err.startswith(f"omg: error: humanml3d: {root / 'Mean.npy'} is not a plain numeric .npy array"), err
    assert not out.exists()


# ---------------------------------------------------------------- files that are no regular file, or too large

def test_humanml3d_fifo_and_huge_clip_files_are_counted_skips(hml_root, tmp_path, capsys):
    """A FIFO named like a motion or a caption file, and a motion over the bound, are each one counted
    skip ("humanml3d unreadable file", as a garbled .npy), and the build finishes."""
    root = tmp_path / "HumanML3D"
    shutil.copytree(hml_root, root)
    os.mkfifo(root / "new_joint_vecs" / "000007.npy")  # np.load(path) would wait for a writer forever
    huge_npy(root / "new_joint_vecs" / "000008.npy", (263,))
    shutil.copy(root / "new_joint_vecs" / "000002.npy", root / "new_joint_vecs" / "000009.npy")
    for name in ("000007", "000008"):
        (root / "texts" / f"{name}.txt").write_text("a person walks#a/DET person/NOUN walk/VERB#0.0#0.0\n")
    os.mkfifo(root / "texts" / "000009.txt")
    out = tmp_path / "shards"
    with no_hang():
        main(["shards", "build", "--source", "humanml3d", "--input", str(root), "--out", str(out), "--fps", "20"])
    log = capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["skipped"]["humanml3d unreadable file"] == 4  # 000005 (garbled), 000007, 000008, 000009
    assert {"000001", "000002", "000006"} <= set(_samples(out))
    skips = [line for line in log.splitlines() if "humanml3d unreadable file" in line]
    for name, why in [("new_joint_vecs/000007.npy", FIFO), ("new_joint_vecs/000008.npy", TOO_LARGE),
                      ("texts/000009.txt", FIFO)]:
        assert any(name in line and why in line for line in skips), (name, skips)


@pytest.mark.parametrize("name", ["train.txt", "Mean.npy"])
def test_humanml3d_fifo_split_or_stats_file_is_one_line(hml_root, tmp_path, capsys, name):
    root = tmp_path / "HumanML3D"
    shutil.copytree(hml_root, root)
    (root / name).unlink()
    os.mkfifo(root / name)
    err = one_line_error(capsys, ["shards", "build", "--source", "humanml3d", "--input", str(root),
                                   "--out", str(tmp_path / "out"), "--fps", "20", "--option.split", "train"])
    assert f"{root / name}: {FIFO}" in err, err


def test_amass_fifo_and_huge_clip_files_are_counted_skips(amass_root, tmp_path, capsys):
    data = tmp_path / "data" / "CMU"
    data.mkdir(parents=True)
    shutil.copy(amass_root / "data" / "CMU" / "01" / "01_01_poses.npz", data)
    os.mkfifo(data / "02_01_poses.npz")
    with open(data / "02_02_poses.npz", "wb") as f:  # sparse: one byte over the bound, no disk used
        f.truncate(MOTION_MAX_BYTES + 1)
    out = tmp_path / "amass"
    with no_hang():
        main(["shards", "build", "--source", "amass", "--input", str(tmp_path / "data"), "--out", str(out),
              "--fps", "20", "--option.body_model", str(amass_root / "models" / "smplh")])
    log = capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["num_clips"] == 1 and manifest["skipped"] == {"amass unreadable file": 2}
    assert any("02_01_poses.npz" in line and FIFO in line for line in log.splitlines()), log
    assert any("02_02_poses.npz" in line and TOO_LARGE in line for line in log.splitlines()), log


def test_amass_fifo_body_model_is_one_line(amass_root, tmp_path, capsys):
    """A FIFO given as the body model, or found in the body-model folder, is refused unread in one line."""
    os.mkfifo(tmp_path / "model.npz")
    (tmp_path / "models" / "neutral").mkdir(parents=True)
    os.mkfifo(tmp_path / "models" / "neutral" / "model.npz")
    for body_model, fifo in [(tmp_path / "model.npz", tmp_path / "model.npz"),
                             (tmp_path / "models", tmp_path / "models" / "neutral" / "model.npz")]:
        err = one_line_error(capsys, ["shards", "build", "--source", "amass", "--input", str(amass_root / "data"),
                                       "--out", str(tmp_path / "out"), "--fps", "20",
                                       "--option.body_model", str(body_model)])
        assert f"body model {fifo}: {FIFO}" in err, err


def test_animalml3d_fifo_and_huge_files_are_counted_skips(tmp_path):
    offsets = SMAL35.rest_offsets.astype(np.float64)
    for animal in ("foxXAT", "bearPDD"):
        _write_offsets(tmp_path, animal, offsets)
    _write_animal(tmp_path, "foxXAT", "Walk", 30, offsets)
    motions = tmp_path / "animals_maa_motions"
    os.mkfifo(motions / "foxXAT_Trot.npy")
    huge_npy(motions / "foxXAT_Run.npy", (36, 6))
    for name in ("foxXAT_Trot", "foxXAT_Run"):
        (tmp_path / "motion_captions" / name).mkdir(parents=True)
        (tmp_path / "motion_captions" / name / "screenshots.txt").write_text("a fox moves\n")
    _write_animal(tmp_path, "bearPDD", "Walk", 30, offsets, caption="")
    (tmp_path / "motion_captions" / "bearPDD_Walk").mkdir(parents=True)
    os.mkfifo(tmp_path / "motion_captions" / "bearPDD_Walk" / "screenshots.txt")
    _write_animal(tmp_path, "deerA4K", "Walk", 30, offsets)
    (tmp_path / "animals_maa_offsets" / "deerA4K").mkdir(parents=True)
    os.mkfifo(tmp_path / "animals_maa_offsets" / "deerA4K" / "offset.pkl")
    logs: list[str] = []
    with no_hang():
        summary = ShardWriter(tmp_path / "out", get_representation("maa", SMAL35), 20.0,
                              log=logs.append).write(_animals(tmp_path))
    assert summary.clips == 1
    assert summary.skipped == {"animalml3d unreadable motion": 2, "animalml3d unreadable captions": 1,
                               "animalml3d unreadable offsets": 1}
    for name, why in [("foxXAT_Trot.npy", FIFO), ("foxXAT_Run.npy", TOO_LARGE), ("bearPDD_Walk/screenshots.txt", FIFO),
                      ("deerA4K/offset.pkl", FIFO)]:
        assert any(name in line and why in line for line in logs), (name, logs)


def test_importers_read_only_through_omg_files():
    """No importer opens a dataset file itself (np.load(path), Path.read_text/read_bytes, open): each read
    goes through omg.files (read_file, read_array, read_text), which refuses a FIFO or a huge file unread."""
    import omg.data.sources

    direct = re.compile(r"np\.load\(|\.read_text\(|\.read_bytes\(|\.open\(|(?<![\w.])open\(")
    found = [f"{path.name}:{i}: {line.strip()}" for path in sorted(Path(omg.data.sources.__file__).parent.glob("*.py"))
             for i, line in enumerate(path.read_text().splitlines(), 1) if direct.search(line.split("#")[0])]
    assert not found, found
