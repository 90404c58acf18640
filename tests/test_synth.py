"""The procedural mini dataset: deterministic, kinematically clean, labelled the way it moves."""

import json

import numpy as np
import pytest
import torch

from omg.data.synth import ANIMAL_ACTIONS, ANIMALS, HUMAN_ACTIONS, synth_clip, synth_clips

pytestmark = pytest.mark.xdist_group("synth")  # the tests share the `clips` fixture's generated clips

FPS = 30.0
NUM = {"human": 2 * len(HUMAN_ACTIONS), "animal": len(ANIMAL_ACTIONS) * len(ANIMALS)}  # every (category, action)


@pytest.fixture(scope="session")
def clips():
    """{kind: [(clip, contacts)]}, generated once for the module."""
    return {kind: [synth_clip(kind, i, seed=0, fps=FPS) for i in range(n)] for kind, n in NUM.items()}


def _all(clips):
    return [item for kind in clips for item in clips[kind]]


def _first_human(action: str, **labels):
    """The first human clip of an action with these labels (actions cycle with the index)."""
    for i in range(HUMAN_ACTIONS.index(action), 100 * len(HUMAN_ACTIONS), len(HUMAN_ACTIONS)):
        clip = synth_clip("human", i, seed=0)[0]
        if all(clip.labels.get(k) == v for k, v in labels.items()):
            return clip
    raise AssertionError(f"no {action} clip with {labels}")


def _root_travel(clip) -> float:
    return float(np.linalg.norm(clip.positions[-1, 0, [0, 2]] - clip.positions[0, 0, [0, 2]]))


def test_deterministic_by_seed():
    a, ca = synth_clip("animal", 5, seed=3)
    b, cb = synth_clip("animal", 5, seed=3)
    assert a.id == b.id and a.texts == b.texts and a.labels == b.labels
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.rotations, b.rotations)
    np.testing.assert_array_equal(ca, cb)
    other = synth_clip("animal", 5, seed=4)[0]
    assert other.positions.shape != a.positions.shape or not np.array_equal(other.positions, a.positions)
    # a clip depends on its own index only, not on how many clips come before it
    np.testing.assert_array_equal(list(synth_clips(0, 6, seed=3))[5].positions, a.positions)


def test_synth_clips_order_and_ids():
    out = list(synth_clips(3, 2, seed=0))
    assert [c.category == "human" for c in out] == [True, True, True, False, False]
    assert len({c.id for c in out}) == 5
    assert out[0].id == f"synth_human_00000_{HUMAN_ACTIONS[0]}"
    assert out[3].id == f"synth_dog_00000_{ANIMAL_ACTIONS[0]}"


def test_shapes_and_metadata(clips):
    for kind, joints in (("human", 22), ("animal", 35)):
        for clip, contacts in clips[kind]:
            T = len(clip)
            assert clip.skeleton.name == ("smpl22" if kind == "human" else "smal35")
            assert clip.positions.shape == (T, joints, 3) and clip.positions.dtype == np.float32
            assert clip.rotations.shape == (T, joints, 4)
            np.testing.assert_allclose(np.linalg.norm(clip.rotations, axis=-1), 1.0, atol=1e-5)
            assert clip.offsets.shape == (joints, 3)
            assert contacts.shape == (T, len(clip.skeleton.feet)) and contacts.dtype == bool
            assert 2.0 <= clip.seconds <= 10.5 and clip.fps == FPS
            assert clip.source == "synth" and (clip.category == "human") == (kind == "human")
            assert clip.id.startswith(f"synth_{clip.category}_") and clip.id.endswith(clip.labels["action"])
            json.dumps(clip.labels)  # goes into the shards' meta.json


def test_every_action_and_category_appears(clips):
    assert {c.labels["action"] for c, _ in clips["human"]} == set(HUMAN_ACTIONS)
    assert {c.labels["action"] for c, _ in clips["animal"]} == set(ANIMAL_ACTIONS)
    assert {c.category for c, _ in clips["animal"]} == set(ANIMALS)


def test_bone_lengths_constant_and_positions_are_fk(clips):
    for clip, _ in _all(clips):
        fk = clip.skeleton.forward_kinematics(
            torch.from_numpy(clip.rotations), torch.from_numpy(clip.positions[:, 0]), torch.from_numpy(clip.offsets)
        )
        np.testing.assert_allclose(fk.numpy(), clip.positions, atol=1e-4)
        parents = np.asarray(clip.skeleton.parents[1:])
        bones = np.linalg.norm(clip.positions[:, 1:] - clip.positions[:, parents], axis=-1)  # (T, J-1)
        expected = np.linalg.norm(clip.offsets[1:], axis=-1)
        assert np.abs(bones - expected).max() < 1e-4, clip.id


def test_planted_feet_on_the_floor_and_still(clips):
    for clip, contacts in _all(clips):
        feet = clip.positions[:, list(clip.skeleton.feet)]  # (T, F, 3)
        assert contacts.any(0).all(), f"{clip.id}: a foot never touches the floor"
        # a planted joint does not slide between consecutive contact frames
        step = np.linalg.norm(np.diff(feet[..., [0, 2]], axis=0), axis=-1)
        held = contacts[1:] & contacts[:-1]
        assert step[held].max(initial=0.0) < 0.01, f"{clip.id}: planted foot slides {step[held].max():.3f} m/frame"
        # the lowest point of a foot in contact is on the floor (humans: ankle + toe; animals: one paw)
        groups = [(0, 1), (2, 3)] if clip.category == "human" else [(0,), (1,), (2,), (3,)]
        for group in groups:
            down = contacts[:, list(group)].any(1)
            lowest = feet[down][:, list(group), 1].min(-1)
            assert np.abs(lowest).max() < 0.01, f"{clip.id}: planted foot {lowest.max():.3f} m off the floor"
        assert clip.positions[..., 1].min() > -0.01, f"{clip.id}: a joint goes below the floor"


def test_captions(clips):
    for clip, _ in _all(clips):
        assert 2 <= len(clip.texts) <= 3 and len(set(clip.texts)) == len(clip.texts), clip.texts
        assert all(isinstance(t, str) and t.endswith(".") and "  " not in t for t in clip.texts)
        if clip.category != "human":
            assert all(clip.category in t for t in clip.texts), clip.texts


def test_walking_travels_further_than_jumping_in_place_or_waving(clips):
    walk = _first_human("walk", direction="forward")
    assert _root_travel(walk) > 1.5
    for clip in (_first_human("jump", direction="in_place"), _first_human("wave")):
        assert _root_travel(clip) < 0.3, clip.id


def test_gallop_faster_than_walk(clips):
    for category in ("dog", "horse"):
        walk = next(c for c, _ in clips["animal"] if c.category == category and c.labels["action"] == "walk")
        gallop = next(c for c, _ in clips["animal"] if c.category == category and c.labels["action"] == "gallop")
        assert _root_travel(gallop) / gallop.seconds > 2 * _root_travel(walk) / walk.seconds


def test_footfall_patterns(clips):
    """Trot: diagonal pairs land together; walk: four separate beats; gallop: hinds, then fronts."""
    for clip, contacts in clips["animal"]:
        lf, lh, rf, rh = contacts.T.astype(float)
        touchdown = np.diff(contacts.astype(int), axis=0) == 1  # (T-1, 4)
        first = [np.flatnonzero(touchdown[:, i])[:1] for i in range(4)]
        if clip.labels["action"] == "trot":
            assert (lf == rh).mean() > 0.95 and (rf == lh).mean() > 0.95 and (lf == rf).mean() < 0.3
        elif clip.labels["action"] == "walk" and all(len(f) for f in first):
            assert len({int(f[0]) for f in first}) == 4  # no two feet land on the same frame
        elif clip.labels["action"] == "gallop":
            assert (lh == rh).mean() > 0.6 and (lf == rf).mean() > 0.6 and (lf == lh).mean() < 0.7


def test_other_frame_rates():
    clip, contacts = synth_clip("human", 0, fps=20.0)
    assert clip.fps == 20.0 and abs(len(clip) - 20.0 * clip.seconds) < 1 and contacts.shape[0] == len(clip)
