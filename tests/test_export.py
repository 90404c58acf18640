"""BVH writing, inverse kinematics from joint positions, GIF previews and ``omg export``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from omg.cli import main as cli_main
from omg.data.synth import synth_clips
from omg.export import EULER_ORDERS, export_motion, positions_to_rotations
from omg.io.bvh import read_bvh, write_bvh
from omg.io.render import render_gif
from omg.rotations import axis_angle_to_quat, quat_normalize
from omg.skeleton import SMAL35, SMPL22, Skeleton

SKELETONS = {"smpl22": SMPL22, "smal35": SMAL35}


def _fk(skel: Skeleton, rotations, root, offsets=None) -> np.ndarray:
    offsets = None if offsets is None else torch.as_tensor(offsets, dtype=torch.float64)
    rot, root = torch.as_tensor(rotations, dtype=torch.float64), torch.as_tensor(root, dtype=torch.float64)
    return skel.forward_kinematics(rot, root, offsets).numpy()


def _read_positions(path, skel: Skeleton) -> np.ndarray:
    """(T, J, 3) positions of a BVH file in the skeleton's joint order (files list joints depth first)."""
    motion = read_bvh(path)
    return motion.positions()[:, [motion.names.index(name) for name in skel.names]]


def _plausible_motion(skel: Skeleton, frames: int = 40, seed: int = 0) -> np.ndarray:
    """(T, J, 3) FK positions of random local rotations of up to about 30 degrees per axis."""
    g = torch.Generator().manual_seed(seed)
    rotations = axis_angle_to_quat(0.3 * torch.randn(frames, skel.num_joints, 3, generator=g, dtype=torch.float64))
    root = torch.tensor([0.0, 0.9, 0.0]).double() + 0.1 * torch.randn(frames, 3, generator=g, dtype=torch.float64)
    return _fk(skel, rotations, root)


@pytest.mark.parametrize("name", SKELETONS)
@pytest.mark.parametrize("order", EULER_ORDERS)
def test_bvh_round_trip(tmp_path, name, order):
    skel = SKELETONS[name]
    g = torch.Generator().manual_seed(0)
    rotations = quat_normalize(torch.randn(12, skel.num_joints, 4, generator=g, dtype=torch.float64))  # any rotation
    root = torch.randn(12, 3, generator=g, dtype=torch.float64)
    expected = _fk(skel, rotations, root)
    for scale in (1.0, 100.0):  # metres, centimetres (the reader detects the unit)
        path = write_bvh(tmp_path / f"{name}.bvh", skel, rotations, root, fps=30, order=order, scale=scale)
        motion = read_bvh(path)
        assert sorted(motion.names) == sorted(skel.names) and motion.names[0] == skel.names[0]
        assert motion.fps == 30.0 and len(motion) == 12
        assert motion.channels[0] == ("Xposition", "Yposition", "Zposition", *(f"{a}rotation" for a in order))
        assert all(c == tuple(f"{a}rotation" for a in order) for c in motion.channels[1:])
        np.testing.assert_allclose(_read_positions(path, skel), expected, atol=1e-5)
    assert not list(tmp_path.glob(".*tmp"))  # written atomically, no temporary file left


@pytest.mark.parametrize("name", SKELETONS)
def test_ik_recovers_fk_positions(name):
    skel = SKELETONS[name]
    positions = _plausible_motion(skel)
    rotations, root, offsets = positions_to_rotations(skel, positions)
    assert rotations.shape == (len(positions), skel.num_joints, 4) and root.shape == (len(positions), 3)
    np.testing.assert_allclose(offsets[1:], skel.rest_offsets[1:], atol=1e-5)  # the clip's own bones are the rest ones
    np.testing.assert_allclose(_fk(skel, rotations, root, offsets), positions, atol=1e-4)


def test_ik_on_synthetic_clips_and_exported_bvh(tmp_path):
    for clip in synth_clips(2, 1, seed=0, fps=20):  # bone directions of their own, unlike the rest offsets
        rotations, root, offsets = positions_to_rotations(clip.skeleton, clip.positions)
        np.testing.assert_allclose(_fk(clip.skeleton, rotations, root, offsets), clip.positions, atol=1e-3)
        report = export_motion(tmp_path / clip.id, clip.positions, clip.skeleton, clip.fps, preview=False)
        assert report["ik_error_m"] < 1e-3 and "gif" not in report
        np.testing.assert_allclose(_read_positions(report["bvh"], clip.skeleton), clip.positions, atol=1e-3)
        assert read_bvh(report["bvh"]).fps == 20.0


def test_bvh_parsed_by_an_independent_reader(tmp_path):
    bvh = pytest.importorskip("bvh", reason="the test-only package `bvh` (PyPI) is not installed")
    positions = _plausible_motion(SMAL35, frames=25)
    path = export_motion(tmp_path / "dog", positions, SMAL35, fps=30, preview=False)["bvh"]
    with open(path) as f:
        parsed = bvh.Bvh(f.read())
    assert len(parsed.get_joints_names()) == SMAL35.num_joints and parsed.nframes == 25
    assert parsed.frame_time == pytest.approx(1 / 30)
    assert parsed.joint_channels("pelvis")[:3] == ["Xposition", "Yposition", "Zposition"]


def test_render_gif(tmp_path):
    motions = [_plausible_motion(SMPL22, frames=80, seed=s) for s in range(2)]
    one = render_gif(tmp_path / "one.gif", motions[:1], SMPL22, fps=20, max_frames=20)
    two = render_gif(tmp_path / "two.gif", motions, SMPL22, fps=20, titles=["a person waves", "b"], max_frames=20)
    with Image.open(one) as a, Image.open(two) as b:
        assert a.n_frames == b.n_frames == 20 and b.info["duration"] == 200  # every 4th frame of 20 fps
        assert b.width == 2 * a.width and b.height == a.height  # one panel per motion
        b.seek(10)
        ink = np.asarray(b.convert("L")) < 200  # (H, W) drawn pixels
    half = ink.shape[1] // 2
    assert ink[:, :half].sum() > 100 and ink[:, half:].sum() > 100  # a figure in each panel


def _generated_dir(tmp_path, frames: int = 30):
    clips = list(synth_clips(2, 0, seed=0, fps=20))
    for i, clip in enumerate(clips):
        np.save(tmp_path / f"sample_{i:03d}.joints.npy", clip.positions[:frames])
    settings = {"fps": 20, "skeleton": "smpl22", "representation": "humanml3d263", "num_samples": 1,
                "prompts": ["a person walks", "a person runs"]}  # fmt: skip
    (tmp_path / "generation.json").write_text(json.dumps(settings))
    return clips


def test_cli_export(tmp_path, capsys):
    clips = _generated_dir(tmp_path)
    cli_main(["export", str(tmp_path)])
    for i, clip in enumerate(clips):
        assert Image.open(tmp_path / f"sample_{i:03d}.gif").n_frames == 30
        positions = _read_positions(tmp_path / f"sample_{i:03d}.bvh", SMPL22)
        np.testing.assert_allclose(positions, clip.positions[:30], atol=1e-3)
    assert "sample_001.bvh, sample_001.gif" in capsys.readouterr().out


def test_cli_export_into_another_folder(tmp_path):
    np.save(tmp_path / "walk.joints.npy", SMPL22.rest_positions()[None].repeat(3, 0))
    cli_main(["export", str(tmp_path / "walk.joints.npy"), "--out", str(tmp_path / "exported"), "--no_preview"])
    assert (tmp_path / "exported" / "walk.bvh").is_file() and not (tmp_path / "walk.bvh").exists()


def test_cli_export_features(tmp_path):
    from omg.motion import get_representation

    representation = get_representation("humanml3d263", SMPL22)
    features, _ = representation.encode(next(synth_clips(1, 0, seed=0, fps=20)))
    path = tmp_path / "walk.features.npy"
    np.save(path, features)
    cli_main(["export", str(path), "--representation", "humanml3d263", "--no_preview", "--scale", "100"])
    expected = representation.decode(torch.from_numpy(features)).numpy()
    np.testing.assert_allclose(_read_positions(tmp_path / "walk.bvh", SMPL22), expected, atol=1e-3)
    assert not (tmp_path / "walk.gif").exists()


@pytest.mark.parametrize(
    "array, reason",
    [(np.zeros((10, 21, 3)), "expected joint positions (T, 22, 3)"),
     (np.full((10, 22, 3), np.nan), "holds NaN or inf values")],  # the one reader's words (generation.read)
)
def test_cli_export_rejects_bad_files(tmp_path, capsys, array, reason):
    _generated_dir(tmp_path)
    np.save(tmp_path / "sample_002.joints.npy", array)
    with pytest.raises(SystemExit) as e:
        cli_main(["export", str(tmp_path), "--no_preview"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "sample_002.joints.npy" in err and reason in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.glob("*.bvh"))  # every file is checked before any is written
