"""Prompt following from the joints: each target test on real takes (Bandai-Namco dataset 2, never
trained on), on their mirror images (the mirror flips every sided verdict), the prompt file, and
the registered metric end to end."""

from __future__ import annotations

import json

import lightning as L
import pytest
import torch
import yaml

from omg.errors import UsageError
from omg.metrics.following import (
    CATEGORIES,
    Joints,
    PromptFollowing,
    label_targets,
    load_prompts,
    passes,
    turn_angle,
)
from omg.registry import METRICS
from omg.skeleton import SMPL22

FPS = 20.0
TAKES = ("raise-up-left-hand_normal_013", "raise-up-right-hand_exhausted_001", "raise-up-both-hands_normal_028",
         "wave-left-hand_normal_024", "wave-right-hand_exhausted_009", "wave-both-hands_normal_008",
         "walk-turn-left_normal_001", "walk-turn-right_exhausted_027", "walk_normal_013", "run_normal_001",
         "1/walk-left_normal_001", "1/walk-right_normal_001")  # "1/": Bandai-Namco dataset 1


@pytest.fixture(scope="session")
def takes(request) -> dict[str, torch.Tensor]:
    """content label -> SMPL-22 joints (T, 22, 3) at 20 fps, read through omg's BVH retarget path."""
    from helpers import SHARED_MOTION
    from omg.io.read import read_motion
    from omg.retarget import retarget

    folder = SHARED_MOTION / "human"
    if not (folder / "bandai2").is_dir():
        pytest.skip(f"real motion data not found at {folder} (the shared/ folder beside the checkout)")
    out = {}
    for take in TAKES:
        dataset, _, name = take.rpartition("/")
        path = folder / f"bandai{dataset or 2}" / f"dataset-{dataset or 2}_{name}.bvh"
        out[name.split("_")[0]] = torch.from_numpy(retarget(read_motion(path), "smpl22", fps=FPS).positions)
    return out


def verdict(joints, **target) -> bool:
    return passes(joints, target, FPS)


@pytest.mark.parametrize("content", ["raise-up-left-hand", "raise-up-right-hand", "raise-up-both-hands",
                                     "wave-left-hand", "wave-right-hand", "wave-both-hands"])
def test_hand_targets_tell_the_side_on_real_takes(takes, content):
    joints = takes[content]
    action = "raise" if content.startswith("raise") else "wave"
    side = content.split("-")[-2]  # left | right | both
    for hand in ("left", "right", "both"):
        assert verdict(joints, hand=hand, action=action) == (hand == side), (content, hand)
    assert verdict(joints, hand="either", action=action)
    if action == "raise":  # raising is not waving: the wave test needs the back-and-forth
        assert not verdict(joints, hand="either", action="wave")


def test_turns_and_paces_on_real_takes(takes):
    left, right = takes["walk-turn-left"], takes["walk-turn-right"]
    assert verdict(left, turn="left") and not verdict(left, turn="right")
    assert verdict(right, turn="right") and not verdict(right, turn="left")
    assert verdict(left, turn="left", angle=90) and not verdict(left, turn="left", angle=180)
    assert not verdict(left, turn="around")
    walk, run, wave = takes["walk"], takes["run"], takes["wave-left-hand"]
    for joints in (walk, run):
        assert verdict(joints, travel="forward") and not verdict(joints, travel="backward")
        assert not verdict(joints, travel="left") and not verdict(joints, travel="right")
        assert not verdict(joints, turn="left") and not verdict(joints, turn="right")
        assert verdict(joints, pace="moving") and not verdict(joints, pace="still")
    assert verdict(walk, pace="walk") and not verdict(walk, pace="run")
    assert verdict(run, pace="run") and not verdict(run, pace="walk")
    assert verdict(wave, pace="still") and not verdict(wave, pace="moving")
    assert not verdict(wave, travel="forward")  # standing has no direction of travel


def test_the_mirror_image_flips_every_sided_verdict(takes):
    for content, target in (("wave-left-hand", {"hand": "left", "action": "wave"}),
                            ("raise-up-right-hand", {"hand": "right", "action": "raise"}),
                            ("walk-turn-left", {"turn": "left"})):
        joints = takes[content]
        mirrored = SMPL22.mirror(joints)
        other = {k: {"left": "right", "right": "left"}.get(v, v) for k, v in target.items()}
        assert passes(joints, target, FPS) and not passes(joints, other, FPS)
        assert passes(mirrored, other, FPS) and not passes(mirrored, target, FPS)
    angle = turn_angle(takes["walk-turn-left"].double(), FPS, Joints())
    assert turn_angle(SMPL22.mirror(takes["walk-turn-left"].double()), FPS, Joints()) == pytest.approx(-angle)


def test_travel_to_a_side_backward_and_the_frame_rate(takes):
    for side, other in (("left", "right"), ("right", "left")):
        joints = takes[f"walk-{side}"]
        assert verdict(joints, travel=side) and not verdict(joints, travel=other)
        assert verdict(SMPL22.mirror(joints), travel=other) and not verdict(SMPL22.mirror(joints), travel=side)
        assert verdict(joints, pace="walk") and not verdict(joints, travel="backward")
    walk = takes["walk"].double()
    # the same walk seen from the side and reversed: a body walking along its left is walk-left
    turned = walk.clone()
    turned[..., 0], turned[..., 2] = walk[..., 2], -walk[..., 0]  # rotate the world, not the body
    assert verdict(turned, travel="forward")  # the body's own frame, not the world's
    reversed_time = walk.flip(0)
    assert verdict(reversed_time, travel="backward") and not verdict(reversed_time, travel="forward")
    # half the frames at half the rate is the same motion: the verdicts hold
    half = takes["run"][::2]
    assert passes(half, {"pace": "run"}, FPS / 2) and passes(half, {"travel": "forward"}, FPS / 2)


def test_every_labelled_take_of_dataset_2_passes_its_label_targets(shared_motion):
    from omg.io.read import read_motion
    from omg.retarget import retarget

    table = label_targets()
    clips = [c for c in json.loads((shared_motion / "manifest.json").read_text())["clips"] if "bandai2" in c["path"]]
    assert len(clips) == 20
    failed = []
    for c in clips:
        joints = torch.from_numpy(retarget(read_motion(shared_motion / c["path"]), "smpl22", fps=FPS).positions)
        if not all(passes(joints, t, FPS) for t in table[c["labels"]["content"]]):
            failed.append(c["id"])
    assert not failed


def test_the_prompt_set_covers_each_category_and_bad_files_fail(tmp_path):
    prompts = load_prompts()
    assert {p["category"] for p in prompts} == set(CATEGORIES)
    assert all(len(p["targets"]) == 2 for p in prompts if p["category"] == "combinations")
    for text, problem in (("prompts: [{text: a, targets: [{hand: up, action: wave}]}]", "hand must be one of"),
                          ("prompts: [{text: a, targets: [{turn: left, travel: left}]}]", "exactly one of"),
                          ("prompts: [{text: a, category: weird, targets: [{pace: run}]}]", "category must be"),
                          ("prompts: [{text: a}]", "targets is a non-empty list"),
                          ("nothing: 1", "expected `prompts:`")):
        path = tmp_path / "p.yaml"
        path.write_text(text)
        with pytest.raises(UsageError, match=problem):
            load_prompts(path)


def test_the_registered_metric_scores_parts_and_categories(takes):
    metric = METRICS.get("following")(skeleton="smpl22", fps=FPS)
    assert isinstance(metric, PromptFollowing)
    wave, walk = takes["wave-left-hand"], takes["walk"]
    T = max(len(wave), len(walk))
    joints = torch.zeros(3, T, 22, 3)
    joints[0, : len(wave)], joints[1, : len(wave)], joints[2, : len(walk)] = wave, wave, walk
    mask = torch.arange(T)[None] < torch.tensor([len(wave), len(wave), len(walk)])[:, None]
    labels = [{"following": "sidedness", "targets": [{"hand": "left", "action": "wave"}]},
              {"following": "sidedness", "targets": [{"hand": "right", "action": "wave"}]},  # the wrong side
              {"following": "combinations", "targets": [{"pace": "walk"}, {"hand": "left", "action": "wave"}]}]
    metric.update(joints, mask, labels)
    out = {k: float(v) for k, v in metric.compute().items()}
    assert out["following"] == pytest.approx(1 / 3)
    assert out["following/sidedness"] == pytest.approx(0.5) and out["following/combinations"] == 0.0
    assert out["following/parts"] == pytest.approx(2 / 4) and out["following/pace"] == 1.0
    assert out["following/hand"] == pytest.approx(1 / 3)
    assert out["following/combinations/parts"] == 0.5 and out["following/sidedness/parts"] == 0.5


def test_validation_clips_are_scored_by_their_action_label(takes):
    """Rows of a validation set carry clip labels, not targets: the prompt file's labels: table
    gives them (a side named: sidedness), and a label without targets is left out."""
    names = ["wave-left-hand", "walk-turn-right", "walk", "run"]
    T = max(len(takes[n]) for n in names)
    joints, mask = torch.zeros(len(names), T, 22, 3), torch.zeros(len(names), T, dtype=torch.bool)
    for b, n in enumerate(names):
        joints[b, : len(takes[n])], mask[b, : len(takes[n])] = takes[n], True
    metric = PromptFollowing(fps=FPS)
    # the run take labelled as a left wave fails; "bow-deep" has no targets and is left out
    metric.update(joints, mask, [{"content": "wave-left-hand"}, {"content": "walk-turn-right"},
                                 {"content": "walk"}, {"content": "wave-left-hand"}])
    metric.update(joints[:1], mask[:1], [{"content": "bow-deep"}])
    out = {k: float(v) for k, v in metric.compute().items()}
    assert out["following/sidedness"] == pytest.approx(2 / 3) and out["following/plain"] == 1.0
    assert out["following"] == pytest.approx(3 / 4)
    assert out["following/turn"] == 1.0 and out["following/hand"] == pytest.approx(1 / 2)
    with pytest.raises(UsageError, match="the prompt file .*: no such file"):
        PromptFollowing(targets_file="/nonexistent/prompts.yaml")


class Replay(L.LightningModule):
    """A 'generator' that answers every prompt with one real take's features (humanml3d263), so
    what the evaluation should find is known: the take's own verdicts."""

    text_conditional = True

    def __init__(self, features: torch.Tensor, spec):
        super().__init__()
        self.features, self.spec, self.seen = features, spec, []
        self.anchor = torch.nn.Parameter(torch.zeros(()))

    def sample(self, texts, lengths, settings=None):  # omg.lit.sampling.Sampler
        self.seen.append(list(texts))
        out = torch.zeros(len(texts), int(lengths.max()), self.features.shape[-1])
        for b, n in enumerate(lengths.tolist()):
            out[b, :n] = self.features[:n]
        return out

    def check_sampling(self, settings, key):
        pass

    def test_step(self, batch, index):
        return None


def test_the_metric_end_to_end_through_the_eval_callback_with_a_prompt_file(shared_motion, tmp_path):
    from omg.callbacks import EvalCallback
    from omg.data.datamodule import MotionDataModule
    from omg.data.shards import ShardWriter
    from omg.io.read import read_motion
    from omg.motion import get_representation
    from omg.retarget import retarget

    clip = retarget(read_motion(shared_motion / "human/bandai2/dataset-2_wave-left-hand_normal_024.bvh"),
                    "smpl22", fps=FPS, texts=["a person waves the left hand."])
    rep = get_representation("humanml3d263", SMPL22)
    ShardWriter(tmp_path / "shards", rep, fps=FPS, log=lambda m: None).write([clip])
    data = MotionDataModule(val=str(tmp_path / "shards"), batch_size=2, max_len=200, clips="whole", num_workers=0)
    seconds = (len(clip) - 1) / FPS
    (tmp_path / "prompts.yaml").write_text(yaml.safe_dump({"prompts": [
        {"text": "a person waves the left hand.", "category": "sidedness", "seconds": seconds,
         "targets": [{"hand": "left", "action": "wave"}]},
        {"text": "a person waves the right hand.", "category": "sidedness", "seconds": seconds,
         "targets": [{"hand": "right", "action": "wave"}]},
        {"text": "a man walks while waving the left hand.", "category": "combinations", "seconds": seconds,
         "targets": [{"pace": "walk"}, {"hand": "left", "action": "wave"}]}]}))
    module = Replay(torch.from_numpy(rep.encode(clip)[0]), data.spec)
    callback = EvalCallback(metrics=["following", "foot_skating"], prompts=str(tmp_path / "prompts.yaml"),
                            samples_per_prompt=2, replications=2, steps=2, batch_size=4)  # no evaluator needed
    trainer = L.Trainer(accelerator="cpu", logger=False, callbacks=[callback], limit_test_batches=1,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path / "run")
    results = trainer.test(module, data, verbose=False)[0]
    assert [t for batch in module.seen for t in batch][:6] == [
        "a person waves the left hand."] * 2 + ["a person waves the right hand."] * 2 + [
        "a man walks while waving the left hand."] * 2  # each prompt samples_per_prompt times
    assert results["eval/following"] == pytest.approx(1 / 3)
    assert results["eval/following/sidedness"] == pytest.approx(0.5)
    assert results["eval/following/combinations"] == 0.0
    assert results["eval/following/parts"] == pytest.approx(2 / 4)
    assert "eval/real/following" not in results  # a prompt file has no real motions
    report = json.loads(next((tmp_path / "run").rglob("eval.json")).read_text())
    assert report["settings"]["prompts"] == 3 and report["settings"]["samples_per_prompt"] == 2


def test_a_prompt_file_takes_only_metrics_that_need_no_real_motion():
    from omg.callbacks import EvalCallback

    with pytest.raises(UsageError, match="fid compare with real motions"):
        EvalCallback(metrics=["following", "fid"], prompts="following")
    with pytest.raises(UsageError, match="r_precision read the evaluator's embeddings"):
        EvalCallback(metrics=["r_precision"])
    assert EvalCallback(metrics=["following"], prompts="following", samples_per_prompt=3).num_prompts == 3 * len(
        load_prompts())


def test_bench_following_scores_real_clips_and_their_mirror_images(shared_motion, tmp_path, capsys):
    from omg.cli import main

    folder = shared_motion / "human" / "bandai2"
    (tmp_path / "manifest.json").write_text(json.dumps({"clips": [
        {"id": name, "path": str(folder / f"dataset-2_{name}.bvh"), "format": "bvh", "domain": "human",
         "labels": {"content": name.split("_")[0]}}
        for name in ("wave-left-hand_normal_024", "walk-turn-right_exhausted_027", "raise-up-left-hand_normal_013")]}))
    for flag, rows in (([], ("| wave-left-hand |", "| walk-turn-right |", "| raise-up-left-hand |")),
                       (["--mirror"], ("| wave-right-hand |", "| walk-turn-left |", "| raise-up-right-hand |"))):
        main(["bench", "following", "--input", str(tmp_path), *flag])
        out = capsys.readouterr().out
        for row in rows:
            assert any(line.startswith(row) and line.endswith("| 1/1 |") for line in out.splitlines()), (row, out)
        assert "| all | | 3/3 (1.00) |" in out
    with pytest.raises(SystemExit) as exit_info:
        main(["bench", "following", "--input", str(tmp_path), "--label", "style"])
    assert exit_info.value.code == 2 and "no clip has a 'style' label" in capsys.readouterr().err


def test_a_validation_pass_scores_generated_and_real_motions_by_label(shared_motion, tmp_path):
    """evaluate() on a prompt set drawn from labelled clips, with no evaluator: a generator that
    returns each prompt's real motion scores as the real motions do (real/following)."""
    from omg.data.datamodule import MotionDataModule
    from omg.data.shards import ShardWriter
    from omg.evaluation import evaluate, prompt_set
    from omg.io.read import read_motion
    from omg.motion import get_representation
    from omg.retarget import retarget

    clips = []
    for name in ("wave-right-hand_normal_015", "walk-turn-left_exhausted_038", "run_exhausted_030"):
        path = shared_motion / "human/bandai2" / f"dataset-2_{name}.bvh"
        clips.append(retarget(read_motion(path), "smpl22", fps=FPS, id=name, texts=[name],
                              labels={"content": name.split("_")[0]}))
    ShardWriter(tmp_path / "val", get_representation("humanml3d263", SMPL22), fps=FPS, log=lambda m: None).write(clips)
    data = MotionDataModule(val=str(tmp_path / "val"), max_len=300, clips="whole", num_workers=0)
    prompts = prompt_set(data.val_clips().samples, 6, seed=0, windows=data.windows)
    replay = iter(prompts.slice(0, 6).motions.split(6))
    values = evaluate(lambda texts, lengths, seed: next(replay), None, prompts, {"following": {}}, seed=0,
                      spec=data.spec)
    assert values["following"] == values["real/following"] == 1.0
    assert values["following/sidedness"] == 1.0 and values["following/plain"] == 1.0
    with pytest.raises(UsageError, match="fid reads the evaluator's embeddings"):
        evaluate(lambda *a: None, None, prompts, {"fid": {}}, seed=0, spec=data.spec)
