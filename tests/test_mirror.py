"""Mirror augmentation: features of humanml3d263 and maa mirrored exactly (an involution whose
decoded joints are the original's reflected joints, on real clips), captions mirrored word by word,
and the data-module option that streams mirrored training pairs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omg.data.datamodule import MotionDataModule
from omg.data.shards import ShardWriter
from omg.errors import UsageError
from omg.metrics.following import passes
from omg.motion import get_representation
from omg.skeleton import SMAL35, SMPL22
from omg.text.sides import mirror_caption

WAVE_LEFT = "human/bandai2/dataset-2_wave-left-hand_normal_024.bvh"
TURN_LEFT = "human/bandai2/dataset-2_walk-turn-left_normal_001.bvh"


def real_clip(shared_motion, path, skeleton="smpl22", texts=(), labels=None):
    from omg.io.read import read_motion
    from omg.retarget import retarget

    return retarget(read_motion(shared_motion / path), skeleton, fps=20, id=path, texts=list(texts),
                    labels=labels or {})


@pytest.mark.parametrize("skeleton", [SMPL22, SMAL35], ids=lambda s: s.name)
def test_skeleton_mirror_swaps_sides_and_reflects(skeleton):
    rest = torch.from_numpy(skeleton.rest_positions()).double()  # (J, 3), left side at +X
    mirrored = skeleton.mirror(rest)
    assert torch.equal(skeleton.mirror(mirrored), rest)
    left = [j for j, name in enumerate(skeleton.names) if name.startswith(("left_", "L"))]
    assert len(left) >= 7
    for j in left:  # a left joint's mirror joint sits where the left one would be seen in a mirror
        k = skeleton.symmetry[j]
        assert k != j and rest[j, 0] > 0 and mirrored[k, 0] == -rest[j, 0] and mirrored[k, 1] == rest[j, 1]
    if skeleton is SMAL35:  # built symmetric: its rest pose is its own mirror image
        torch.testing.assert_close(mirrored, rest, atol=1e-6, rtol=0)


def test_humanml3d263_mirror_is_exact_on_a_real_clip(shared_motion):
    rep = get_representation("humanml3d263", SMPL22)
    features = torch.from_numpy(rep.encode(real_clip(shared_motion, WAVE_LEFT))[0]).double()  # (T', 263)
    mirrored, _ = rep.mirror(features)
    assert torch.equal(rep.mirror(mirrored)[0], features)  # an involution
    assert not torch.allclose(mirrored, features)
    joints = rep.decode(features)  # (T', 22, 3)
    torch.testing.assert_close(rep.decode(mirrored), SMPL22.mirror(joints), atol=1e-9, rtol=0)
    # the rotations mirror too: FK of the mirrored rotations on the mirrored bones is the mirror image
    offsets = torch.from_numpy(rep.target_offsets)
    torch.testing.assert_close(rep.positions_from_rotations(mirrored, SMPL22.mirror(offsets)),
                               SMPL22.mirror(rep.positions_from_rotations(features)), atol=1e-9, rtol=0)
    # a swap of the joints without reflecting the rotations would not be the mirror image
    index, sign = rep.mirror_map()
    unreflected = features[..., index] * torch.from_numpy(np.where(np.arange(263) // 67 == 1, 1.0, sign))
    assert not torch.allclose(rep.positions_from_rotations(unreflected, SMPL22.mirror(offsets)),
                              SMPL22.mirror(rep.positions_from_rotations(features)), atol=1e-3)
    # foot contacts swap sides; and what the motion does is mirrored: the left hand's wave is the right's
    assert torch.equal(rep.foot_contacts(mirrored), rep.foot_contacts(features)[..., [2, 3, 0, 1]])
    assert passes(joints, {"hand": "left", "action": "wave"}, 20.0)
    assert passes(rep.decode(mirrored), {"hand": "right", "action": "wave"}, 20.0)
    assert not passes(rep.decode(mirrored), {"hand": "left", "action": "wave"}, 20.0)


def test_humanml3d263_mirror_of_a_turn_turns_the_other_way(shared_motion):
    rep = get_representation("humanml3d263", SMPL22)
    features = torch.from_numpy(rep.encode(real_clip(shared_motion, TURN_LEFT))[0])
    mirrored, _ = rep.mirror(features)
    torch.testing.assert_close(rep.decode(mirrored), SMPL22.mirror(rep.decode(features)), atol=1e-5, rtol=0)
    assert passes(rep.decode(features), {"turn": "left"}, 20.0)
    assert passes(rep.decode(mirrored), {"turn": "right"}, 20.0)


@pytest.mark.parametrize("skeleton", [SMPL22, SMAL35], ids=lambda s: s.name)
def test_maa_mirror_is_exact_on_a_real_clip(shared_motion, skeleton):
    if skeleton is SMPL22:
        path = WAVE_LEFT
    else:
        manifest = json.loads((shared_motion / "manifest.json").read_text())["clips"]
        path = next(c["path"] for c in manifest if "mann_dog" in c["path"])
    rep = get_representation("maa", skeleton)
    features, meta = rep.encode(real_clip(shared_motion, path, skeleton.name))
    features, offsets = torch.from_numpy(features).double(), torch.tensor(meta["offsets"], dtype=torch.float64)
    mirrored, mirrored_offsets = rep.mirror(features, offsets)
    again, again_offsets = rep.mirror(mirrored, mirrored_offsets)
    assert torch.equal(again, features) and torch.equal(again_offsets, offsets)
    torch.testing.assert_close(rep.decode(mirrored, mirrored_offsets), skeleton.mirror(rep.decode(features, offsets)),
                               atol=1e-9, rtol=0)
    # numpy features (the data stream's) mirror the same way
    numpy_mirror, _ = rep.mirror(features.float().numpy())
    np.testing.assert_array_equal(numpy_mirror, mirrored.float().numpy())


@pytest.mark.parametrize("text, mirrored", [
    ("a person waves the left hand.", "a person waves the right hand."),
    ("A person waves the Left hand, then turns RIGHT.", "A person waves the Right hand, then turns LEFT."),
    ("Left foot forward", "Right foot forward"),
    ("someone spins clockwise", "someone spins counterclockwise"),
    ("walks counter-clockwise, then counterclockwise", "walks clockwise, then clockwise"),
    ("he circles anticlockwise", "he circles clockwise"),
    ("moves leftward then rightwards", "moves rightward then leftwards"),
    ("a left-handed throw", "a right-handed throw"),
    ("walk-left", "walk-right"),
    ("left-right-left", "right-left-right"),
    ("bright light, leftovers, righteous", "bright light, leftovers, righteous"),  # whole words only
    ("he is all right and leaves right away", "he is all right and leaves right away"),  # not a side
    ("turns right after raising his left arm", "turns left after raising his right arm"),
])  # fmt: skip
def test_caption_mirror(text, mirrored):
    assert mirror_caption(text) == mirrored


def write_real_shards(out, clips, representation="humanml3d263"):
    ShardWriter(out, get_representation(representation, SMPL22), fps=20.0, max_clips=10, log=lambda m: None).write(
        clips)
    return out


def test_the_stream_mirrors_training_pairs_when_asked(shared_motion, tmp_path):
    clips = [real_clip(shared_motion, WAVE_LEFT, texts=["a person waves the left hand."],
                       labels={"content": "wave-left-hand", "style": "normal"}),
             real_clip(shared_motion, TURN_LEFT, texts=["a person walks and turns left."],
                       labels={"content": "walk-turn-left", "style": "normal"})]
    labels = {c.id: c.labels for c in clips}
    shards = write_real_shards(tmp_path / "train", clips)
    rep = get_representation("humanml3d263", SMPL22)
    originals = {c.id: (rep.encode(c)[0], c.texts[0]) for c in clips}
    for prob, expect_mirrored in ((1.0, 1.0), (0.0, 0.0), (0.5, None)):
        data = MotionDataModule(train=str(shards), batch_size=2, clips="whole", max_len=400, normalize=False,
                                num_workers=0, batches_per_epoch=8, shuffle_buffer=2, mirror_prob=prob)
        items = list(data.stream_loader(0, 1, data.windows).dataset)
        assert len(items) == 16
        mirrored = []
        for item in items:
            features, text = originals[item["id"]]
            window = features[item["start"]: item["start"] + len(item["motion"])]
            flipped = bool(np.array_equal(item["motion"], rep.mirror(window)[0]))
            assert flipped or np.array_equal(item["motion"], window)
            assert item["text"] == (mirror_caption(text) if flipped else text)
            content = labels[item["id"]]["content"]
            assert item["labels"] == {"content": mirror_caption(content) if flipped else content, "style": "normal"}
            mirrored.append(flipped)
        if expect_mirrored is not None:
            assert np.mean(mirrored) == expect_mirrored
        else:
            assert 0 < np.mean(mirrored) < 1


def test_mirror_prob_is_checked(shared_motion, tmp_path):
    shards = write_real_shards(tmp_path / "quatvel", [real_clip(shared_motion, WAVE_LEFT)], "quatvel")
    with pytest.raises(UsageError, match="mirror_prob is a probability"):
        MotionDataModule(train=str(shards), mirror_prob=1.5)
    with pytest.raises(UsageError, match="quatvel.* does not define its mirror image"):  # not for every one
        MotionDataModule(train=str(shards), mirror_prob=0.5)
    MotionDataModule(train=str(shards), mirror_prob=0.0)  # off: any representation


def test_side_spans_sign_the_words_mirroring_swaps():
    from omg.text.sides import side_spans

    text = "turns right after raising his Left hand, all right, then spins counter-clockwise"
    spans = side_spans(text)
    assert [(text[a:b], sign) for a, b, sign in spans] == [("right", -1), ("Left", 1), ("counter-clockwise", 1)]
    assert side_spans("a bright, leftover light.") == []


def cosine_distance(a, b) -> float:
    return float(1 - torch.nn.functional.cosine_similarity(a.double(), b.double(), dim=-1))


def test_side_separation_of_text_features():
    from omg.text import build_text_encoder
    from omg.text.sides import FEATURES, side_separation, side_tokens

    captions = [("a person waves the left hand.", "wave-left"), ("a person waves the right hand.", "wave-right"),
                ("a person waves the left hand sadly.", "wave-left"), ("a person runs forward.", "run"),
                ("a person bows.", "bow")]
    encoder = build_text_encoder("hash")
    out = side_separation(encoder, captions)
    assert set(out) == set(FEATURES) and out["sentence"]["captions"] == 3
    for name, r in out.items():
        assert 0 < r["side"] and r["ratio"] == pytest.approx(r["side"] / r["action"]) and 0 <= r["rank"] <= 1
        # the whole captions: a side swap is a small change (the hash encoder's side word alone is random)
        assert name == "side word" or r["side"] < r["action"]
    # the mirror of "waves the left hand" is the caption "waves the right hand": their distances
    left, right = "a person waves the left hand.", "a person waves the right hand."
    features = encoder([left, right])
    only_side = side_separation(encoder, [(left, "wave-left"), (right, "wave-right")] + captions[3:])
    assert only_side["sentence"]["side"] == pytest.approx(cosine_distance(*features.eot_embedding()))
    assert only_side["token mean"]["side"] == pytest.approx(
        cosine_distance(features.tokens[0, :-1].mean(0), features.tokens[1, :-1].mean(0)))
    # ... and the side word's: the token of "left" (position 5 of [start] a person waves the left ...)
    # to its nearest token of the mirrored caption, and that of "right" to the left caption's, averaged
    assert side_tokens(encoder, left) == side_tokens(encoder, right) == [5]
    nearest = [min(cosine_distance(features.tokens[a, 5], t) for t in features.tokens[b, :8])
               for a, b in ((0, 1), (1, 0))]
    assert only_side["side word"]["side"] == pytest.approx(sum(nearest) / 2) and min(nearest) > 0.1
    # the other style of the same action differs elsewhere: its side word is there, unchanged
    assert out["side word"]["same_action"] == pytest.approx(0, abs=1e-9)
    # a caption that is its own "mirror" (a side word in an idiom) is not compared; a pair of identical
    # captions is 0 apart on every feature
    same = side_separation(encoder, [(left, "wave-left"), (left, "wave-left"), ("a person bows.", "bow")])
    assert same["sentence"]["captions"] == 1
    twin = side_separation(encoder, [("he turns left.", "turn-left"), ("he turns left.", "turn-left"),
                                     ("he bows.", "bow")])
    assert twin["tokens"]["same_action"] != twin["tokens"]["same_action"]  # nan: no other text of that action
    with pytest.raises(ValueError, match="no caption names a side"):
        side_separation(encoder, captions[3:])
    with pytest.raises(ValueError, match="nothing to compare a side swap with"):  # the mirror action is no other
        side_separation(encoder, captions[:3])


def test_side_separation_is_zero_for_an_encoder_blind_to_sides():
    """An encoder that reads "right" as "left" cannot tell a caption from its mirror: 0 on every feature."""
    from omg.text.hashed import HashTextEncoder
    from omg.text.sides import side_separation

    class SideBlind(HashTextEncoder):
        def _encode(self, texts):
            return super()._encode([t.replace("right", "left") for t in texts])

    out = side_separation(SideBlind(), [("a person walks to the left.", "walk-left"),
                                        ("a person runs forward.", "run"), ("a person bows.", "bow")])
    for r in out.values():
        assert r["side"] == pytest.approx(0, abs=1e-9) and r["action"] > 0.1 and r["rank"] == 0


def test_minilm_side_gain_separates_left_from_right():
    from omg.text import build_text_encoder
    from omg.text.sides import side_separation

    captions = [("a person walks to the left.", "walk-left"), ("a person walks forward.", "walk"),
                ("a person bows.", "bow"), ("a person runs forward.", "run")]
    plain, gained = build_text_encoder("minilm"), build_text_encoder("minilm", side_gain=2.0)
    before, after = side_separation(plain, captions), side_separation(gained, captions)
    assert before["sentence"]["ratio"] < 0.15 < 0.3 < after["sentence"]["ratio"]  # measured: 0.07 -> 0.5
    assert after["side word"]["side"] > 2 * before["side word"]["side"]
    # captions with no side word are encoded exactly as without the gain
    texts = ["a person bows.", "a person walks forward, all right."]
    assert torch.equal(plain(texts).tokens, gained(texts).tokens)
    # a left and a right word move by the same amount along opposite directions
    u = gained.side_direction()
    left, right = gained(["he turns left."]).tokens[0], gained(["he turns right."]).tokens[0]
    left0, right0 = plain(["he turns left."]).tokens[0], plain(["he turns right."]).tokens[0]
    assert float((left[3] - left0[3]) @ u) == pytest.approx(2.0 * float(left0[3].norm()), rel=1e-4)
    assert float((right[3] - right0[3]) @ u) == pytest.approx(-2.0 * float(right0[3].norm()), rel=1e-4)
    with pytest.raises(UsageError, match="side_gain"):
        build_text_encoder("minilm", side_gain=-1)


def test_bench_sides_reads_manifests_and_fails_in_one_line(tmp_path, capsys):
    from omg.cli import main

    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"clips": [
        {"texts": ["a person walks to the left."], "labels": {"content": "walk-left"}},
        {"texts": ["a person walks forward."], "labels": {"content": "walk"}}]}))
    main(["bench", "sides", "--manifests", f"[{manifest}]", "--encoders", "[hash]", "--prompts", "none"])
    out = capsys.readouterr().out
    for feature in ("sentence", "token mean", "tokens", "side word"):
        assert f"| manifests | hash | {feature} | 1 |" in out
    assert "prompt set" not in out
    # the built-in prompt set: its 28 prompts that name a side; encoder options after a colon
    main(["bench", "sides", "--encoders", "[hash, 'hash:dim=32']"])
    out = capsys.readouterr().out
    assert "| prompt set | hash | side word | 28 |" in out and "| prompt set | hash:dim=32 | sentence | 28 |" in out
    assert "manifests" not in out
    (tmp_path / "bad.json").write_text("[]")
    with pytest.raises(SystemExit) as exit_info:
        main(["bench", "sides", "--manifests", f"[{tmp_path / 'bad.json'}]", "--encoders", "[hash]"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip().startswith("omg: error: --manifests:")
