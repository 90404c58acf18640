"""Foot-contact clean-up: skating removed, bones kept, the rest of the body untouched."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from omg.data.synth import synth_clip
from omg.io.contacts import clean_foot_contacts
from omg.metrics import FootSkating
from omg.skeleton import get_skeleton


def _bone_lengths(positions: np.ndarray, skeleton) -> np.ndarray:
    parents = np.array(skeleton.parents[1:])
    return np.linalg.norm(positions[:, 1:] - positions[:, parents], axis=-1)  # (T, J-1)


def _skating(positions: np.ndarray, skeleton, fps: float) -> float:
    metric = FootSkating(skeleton, fps=fps)
    metric.update(torch.from_numpy(positions)[None])
    return float(metric.compute())


def _contact_speed(positions: np.ndarray, skeleton, contacts: np.ndarray, fps: float) -> float:
    """Median horizontal speed of the feet over the frames the generator planted them."""
    feet = positions[:, list(skeleton.feet)][..., [0, 2]]  # (T, F, 2)
    speed = np.linalg.norm(feet[1:] - feet[:-1], axis=-1) * fps  # (T-1, F)
    return float(np.median(speed[contacts[:-1] & contacts[1:]]))


@pytest.mark.parametrize("kind, index", [("human", 0), ("animal", 1)])
def test_sliding_feet_are_pinned_with_bones_kept(kind, index):
    fps = 20.0
    clip, contacts = synth_clip(kind, index, fps=fps)  # contacts: (T, F) where the generator planted each foot
    skel = clip.skeleton
    t = np.arange(len(clip)) / fps
    drift = np.stack([0.04 * np.sin(2 * np.pi * 3 * t), 0 * t, 0.04 * np.cos(2 * np.pi * 3 * t)], -1)
    sliding = (clip.positions + drift[:, None]).astype(np.float32)  # the whole body wobbles: planted feet skate
    assert (_contact_speed(clip.positions, skel, contacts, fps) < 0.01
            < 0.5 < _contact_speed(sliding, skel, contacts, fps))

    fixed = clean_foot_contacts(sliding, skel, fps)
    assert _contact_speed(fixed, skel, contacts, fps) < 0.05
    if kind == "human":  # the GMD skating ratio: its 5 cm contact height suits human feet, not a cat's swing
        assert _skating(fixed, skel, fps) < 0.25 * _skating(sliding, skel, fps)
    np.testing.assert_allclose(_bone_lengths(fixed, skel), _bone_lengths(sliding, skel), rtol=1e-4, atol=1e-5)
    legs = set()
    for foot in skel.feet:  # the feet, their parents and grandparents may move; nothing else
        legs |= {foot, skel.parents[foot], skel.parents[skel.parents[foot]]}
    others = [j for j in range(skel.num_joints) if j not in legs]
    np.testing.assert_array_equal(fixed[:, others], sliding[:, others])


def test_still_clip_and_single_frame_are_unchanged():
    skel = get_skeleton("smpl22")
    still = np.repeat(skel.rest_positions()[None], 10, axis=0).astype(np.float32)
    np.testing.assert_allclose(clean_foot_contacts(still, skel, 20.0), still, atol=1e-6)
    np.testing.assert_allclose(clean_foot_contacts(still[:1], skel, 20.0), still[:1], atol=1e-6)


def test_omg_export_clean_contacts(tmp_path):
    from omg.cli import main
    from omg.io.bvh import read_bvh

    fps = 20.0
    clip, contacts = synth_clip("human", 3, fps=fps)
    t = np.arange(len(clip)) / fps
    drift = np.stack([0.04 * np.sin(2 * np.pi * 3 * t), 0 * t, 0.04 * np.cos(2 * np.pi * 3 * t)], -1)
    np.save(tmp_path / "walk.joints.npy", (clip.positions + drift[:, None]).astype(np.float32))
    main(["export", str(tmp_path / "walk.joints.npy"), "--fps", "20", "--no_preview", "--clean_contacts"])
    bvh = read_bvh(tmp_path / "walk.bvh")
    exported = bvh.positions()[:, [bvh.names.index(n) for n in clip.skeleton.names]]  # BVH lists joints depth-first
    assert _contact_speed(exported, clip.skeleton, contacts, fps) < 0.05
