"""Habit transfer: quantizer, EMA codebook and code reset, the flow prior, retrieval, mini fits of both
training orders (the paper's, habit encoders pretrained under their flows, and omg's earlier KL-then-flows)
whose transfers carry the target's habits and keep the source's path, and `omg transfer` on a real dog clip."""

from __future__ import annotations

import gc
import json
import math
import sys

import numpy as np
import pytest
import torch

from helpers import REPO
from helpers.checkpoints import save_module
from helpers.habit import CATEGORIES, QUATVEL
from helpers.habit import fit as _fit
from omg.models.habit import CouplingFlow, Quantizer
from omg.skeleton import SMAL35

# the tests share the mini habit fit (habit_run): under xdist they run on one worker, which fits it once
pytestmark = pytest.mark.xdist_group("habit")

# ----------------------------------------------------------------------------- the mini data's habits


def test_synthetic_species_walk_with_their_own_habits():
    """A horse nods its head in the walk far more than a dog; a cow keeps its paws down longer than a horse."""
    from omg.data.synth import synth_clip

    def walk(index, category):
        clip, contacts = synth_clip("animal", index, fps=20.0)
        assert (clip.category, clip.labels["action"]) == (category, "walk")
        settled = slice(len(contacts) // 3, None)  # past a start from a standstill
        neck_pitch = 2 * np.arcsin(clip.rotations[settled, 15, 1])  # the neck turns about x
        return neck_pitch.std(), contacts[settled].mean()

    (dog_nod, dog_duty), (horse_nod, horse_duty), (cow_nod, cow_duty) = walk(0, "dog"), walk(31, "horse"), walk(
        11, "cow")
    assert horse_nod > 2.5 * dog_nod and cow_nod > 2 * dog_nod
    assert cow_duty > horse_duty + 0.08 and dog_duty > horse_duty


# ----------------------------------------------------------------------------- quantizer


def test_soft_sampling_at_low_temperature_is_the_nearest_code():
    torch.manual_seed(0)
    q = Quantizer(16, 4, mode="soft", temperature=1e-6)
    q.codebook.copy_(torch.randn(16, 4))
    x = torch.randn(200, 4)
    nearest = torch.cdist(x, q.codebook).argmin(-1)
    assert torch.equal(q.assign(x, torch.Generator().manual_seed(1)), nearest)
    assert torch.equal(q.assign(x, mode="nearest"), nearest)
    warm = Quantizer(16, 4, mode="soft", temperature=100.0)
    warm.codebook.copy_(q.codebook)
    assert not torch.equal(warm.assign(x, torch.Generator().manual_seed(1)), nearest)  # it does sample


def _crafted(code_reset: bool) -> tuple[Quantizer, torch.Tensor, torch.Tensor]:
    q = Quantizer(3, 2, mode="nearest", decay=0.5, code_reset=code_reset)
    q.codebook.copy_(torch.tensor([[0.0, 0.0], [10.0, 10.0], [-5.0, 5.0]]))
    q.code_sum.copy_(q.codebook)
    q.code_count.fill_(1.0)
    q.initialized.fill_(True)
    x = torch.tensor([[1.0, 0.0], [0.0, 1.0], [2.0, 2.0], [9.0, 11.0]])  # codes 0, 0, 0, 1; code 2 unused
    return q, x, q.assign(x)


def test_ema_update_equals_the_hand_computation():
    q, x, idx = _crafted(code_reset=False)
    assert idx.tolist() == [0, 0, 0, 1]
    dead = q.ema_update(x, idx)
    # N = 0.5 N + 0.5 n: (0.5 + 1.5, 0.5 + 0.5, 0.5); S = 0.5 S + 0.5 s
    assert torch.allclose(q.code_count, torch.tensor([2.0, 1.0, 0.5]))
    s0 = 0.5 * torch.tensor([0.0, 0.0]) + 0.5 * torch.tensor([3.0, 3.0])
    s1 = 0.5 * torch.tensor([10.0, 10.0]) + 0.5 * torch.tensor([9.0, 11.0])
    assert torch.allclose(q.codebook[0], s0 / 2.0) and torch.allclose(q.codebook[1], s1 / 1.0)
    assert dead.tolist() == [False, False, True]
    assert torch.equal(q.codebook[2], torch.tensor([-5.0, 5.0]))  # EMA only: a dead code keeps its vector


def test_code_reset_restarts_dead_codes_at_encoder_outputs():
    q, x, idx = _crafted(code_reset=True)
    dead = q.ema_update(x, idx, torch.Generator().manual_seed(0))
    assert dead.tolist() == [False, False, True]
    assert any(torch.equal(q.codebook[2], row) for row in x)  # reset to one of the batch's latents
    assert q.code_count[2] == 1.0 and torch.equal(q.code_sum[2], q.codebook[2])
    assert torch.allclose(q.codebook[0], torch.tensor([0.75, 0.75]))  # live codes as without reset


def test_quantizer_forward_gives_straight_through_gradients_and_initialises_the_codebook():
    q = Quantizer(8, 4, mode="soft", temperature=0.5).train()
    x = torch.randn(2, 4, 6, requires_grad=True)
    out, idx, terms = q(x, torch.Generator().manual_seed(0))
    assert bool(q.initialized) and idx.shape == (2, 6) and out.shape == x.shape
    out.sum().backward()
    assert torch.allclose(x.grad, torch.ones_like(x))
    assert terms["commitment"] >= 0 and 1 <= terms["perplexity"] <= 8


# ----------------------------------------------------------------------------- flow prior


def _random_flow(dim: int = 4) -> CouplingFlow:
    torch.manual_seed(0)
    flow = CouplingFlow(dim, layers=4, hidden=16).double()
    for layer in flow.layers:  # away from the identity it starts as
        torch.nn.init.normal_(layer.net[-1].weight, std=0.5)
    return flow


def test_flow_log_likelihood_is_the_change_of_variables_formula():
    flow = _random_flow()
    for z in torch.randn(5, 4, dtype=torch.float64):
        jacobian = torch.autograd.functional.jacobian(lambda v: flow(v[None])[0][0], z)  # (4, 4) du/dz
        u = flow(z[None])[0][0]
        expected = -0.5 * (u.square().sum() + 4 * math.log(2 * math.pi)) + torch.linalg.slogdet(jacobian)[1]
        assert torch.allclose(flow.log_prob(z[None])[0], expected, atol=1e-9)


def test_flow_sample_then_invert_returns_the_input():
    flow = _random_flow()
    u = torch.randn(64, 4, dtype=torch.float64)
    z = flow.inverse(u)
    assert not torch.allclose(z, u)
    assert torch.allclose(flow(z)[0], u, atol=1e-10)


# ----------------------------------------------------------------------------- retrieval


@pytest.fixture(scope="session")
def minilm():
    from omg.text.base import build_text_encoder

    return build_text_encoder("minilm")


# without family words in the descriptions (tests/test_species.py has the whole list)
@pytest.mark.parametrize(("query", "expected"), [("wolf", "fox"), ("camel", "horse"), ("moose", "deer")])
def test_retrieval_finds_the_nearest_known_species(minilm, query, expected):
    from omg.text.habit import SpeciesBook, nearest_category

    book = SpeciesBook.load()
    assert nearest_category(minilm, book.describe(query), book.descriptions(CATEGORIES))[0] == expected


def test_species_descriptions_name_no_family():
    """Retrieval must match build and gait, not a shared family word."""
    import re

    from omg.text.habit import SpeciesBook

    book = SpeciesBook.load()
    cues = re.compile(r"\b(canid|felid|equid|cervid|bovid|bovine|ursid|suid|camelid|big cat|family)\b", re.I)
    assert not [name for name in book.names if cues.search(book.description(name))]


# ----------------------------------------------------------------------------- mini fit


TINY_FIT = dict(flavor="tiny", codebook={"temperature": 0.1}, condition_decoder=True,
                optim={"lr": 3e-3, "lr_after": 3e-4, "lr_switch": 0.8})


@pytest.fixture(scope="session")
def habit_run(tmp_path_factory):
    """A tiny VQ-VAE in omg's earlier order (kl_then_flows), its flow priors fitted after, and an evaluator,
    fitted briefly on the mini quadrupeds."""
    from omg.lit.evaluator import EvaluatorModule
    from omg.lit.habit import HabitPriorModule, HabitVQModule

    out = tmp_path_factory.mktemp("habit")
    earlier = {"habit_order": "kl_then_flows"}
    vq, vq_path = _fit(lambda spec: HabitVQModule(CATEGORIES, order=earlier, **TINY_FIT, spec=spec), out / "vq", 250)
    prior, prior_path = _fit(HabitPriorModule(str(vq_path), optim={"lr": 3e-3}), out / "prior", 60)
    evaluator, _ = _fit(lambda spec: EvaluatorModule(flavor="mini", evaluator={"n_layers": 1, "d_model": 64,
                                                                                "embed_dim": 64},
                                                     r_precision_pool=10, spec=spec,
                                                     optim={"lr": 2e-3, "warmup_steps": 10}),
                        out / "evaluator", 120)
    return {"vq": vq.eval(), "vq_path": vq_path, "prior": prior.eval(), "prior_path": prior_path,
            "evaluator": evaluator.evaluator.eval(), "evaluator_path": out / "evaluator" / "last.ckpt"}


class _Snapshots:
    """The weights at the start, at the end of the habit pretraining and at the end of a fit."""

    def __init__(self):
        import lightning as L

        outer = self
        self.at: dict[str, dict[str, torch.Tensor]] = {}

        class Callback(L.Callback):
            def on_train_batch_start(self, trainer, module, batch, batch_idx):
                if trainer.global_step in (0, module.habit_steps()):
                    outer.take("start" if trainer.global_step == 0 else "pretrained", module)

            def on_train_end(self, trainer, module):
                outer.take("end", module)

        self.callback = Callback()

    def take(self, name, module):
        self.at[name] = {k: v.detach().clone() for k, v in module.state_dict().items()}

    def changed(self, a: str, b: str, prefix: str) -> bool:
        return any(not torch.equal(self.at[a][k], self.at[b][k]) for k in self.at[a] if k.startswith(prefix))


@pytest.fixture(scope="session")
def habit_flow_run(tmp_path_factory):
    """A tiny model of the paper's order (the default, flow_prior): 62 steps pretrain the habit encoders under
    their flows, 248 train the VQ-VAE on them (habit_run's VQ-VAE steps and settings)."""
    from omg.lit.habit import HabitVQModule

    out = tmp_path_factory.mktemp("habit_flow")
    snapshots = _Snapshots()
    vq, vq_path = _fit(lambda spec: HabitVQModule(CATEGORIES, **TINY_FIT, spec=spec), out / "vq", 310,
                       callbacks=[snapshots.callback])
    return {"vq": vq.eval(), "vq_path": vq_path, "snapshots": snapshots}


@torch.no_grad()
@pytest.mark.parametrize("order", ["kl_then_flows", "flow_prior"])
def test_transfer_carries_the_target_habits_and_keeps_the_path(habit_run, order, request):
    from omg.callbacks.habit import crops
    from omg.data.datamodule import MotionDataModule
    from omg.data.loaders import ClipDataset

    vq, prior, evaluator = habit_run["vq"], habit_run["prior"], habit_run["evaluator"]
    if order == "flow_prior":  # the paper's order: the VQ-VAE's own flows, pretrained with its encoders
        vq = prior = request.getfixturevalue("habit_flow_run")["vq"]
    data = MotionDataModule(str(QUATVEL / "train"), max_len=64, min_len=64, clips="windows", verify_shards=False)
    train = crops(ClipDataset.from_shards(data.train_urls, data.feature_dim, data.windows).samples, 64)

    @torch.no_grad()
    def centroid(name):
        motion = torch.stack([torch.from_numpy(np.asarray(c["motion"])) for c in train if c["category"] == name
                              and len(c["motion"]) == 64])
        return evaluator.encode_motion(motion).mean(0)

    def crops_of(name):
        return torch.stack([torch.from_numpy(np.asarray(c["motion"])) for c in train
                            if c["category"] == name and len(c["motion"]) == 64])  # (B, 64, D)

    def tail_carriage(motion):  # mean pitch of the tail's first joint (rad, + up): a habit the species differ in
        quats = motion[..., : vq.num_joints * 4].unflatten(-1, (vq.num_joints, 4))
        return float((2 * torch.asin(torch.nn.functional.normalize(quats[..., 25, :], dim=-1)[..., 1])).mean())

    motion = crops_of("dog")
    for target in ("sheep", "deer", "cow"):
        k = vq.categories.index(target)
        z = prior.habit_latents(k, len(motion), seed=0)
        moved = vq.transfer(motion, k, z, seed=0)
        features = evaluator.encode_motion(moved)
        to_target = (features - centroid(target)).norm(dim=-1).mean()
        to_dog = (features - centroid("dog")).norm(dim=-1).mean()
        assert to_target < to_dog, (target, float(to_target), float(to_dog))
        if target == "cow":  # a dog carries its tail up, a cow lets it hang
            dog, cow, moved_tail = tail_carriage(motion), tail_carriage(crops_of("cow")), tail_carriage(moved)
            assert abs(moved_tail - cow) < abs(moved_tail - dog), (dog, moved_tail, cow)
    # the action is kept: the root travels the way the source does
    J = vq.num_joints
    path_in, path_out = motion[..., J * 4:J * 4 + 3].sum(1), moved[..., J * 4:J * 4 + 3].sum(1)  # (B, 3) displacement
    travelling = path_in[:, [0, 2]].norm(dim=-1) > 0.5
    cos = torch.nn.functional.cosine_similarity(path_in[travelling][:, [0, 2]], path_out[travelling][:, [0, 2]])
    assert travelling.any() and cos.mean() > 0.9, cos


def test_omg_transfer_writes_a_bvh_of_a_real_dog_clip(habit_run, shared_motion, tmp_path, capsys):
    bvh = pytest.importorskip("bvh", reason="the test-only package `bvh` (PyPI) is not installed")
    from omg.cli import main

    clip = shared_motion / "quadruped" / "mann_dog" / "D1_007_KAN01_001.bvh"
    for to, expect in (("horse", "horse"), ("zebra", "horse")):
        out = tmp_path / to
        main(["transfer", str(clip), "--to", to, "--ckpt", str(habit_run["vq_path"]), "--prior_ckpt",
              str(habit_run["prior_path"]), "--out", str(out), "--no_preview" if to == "zebra" else "--preview"])
        settings = json.loads((out / "transfer.json").read_text())
        assert settings["category"] == expect and settings["retrieved"] == (to != expect)
        parsed = bvh.Bvh((out / "transfer.bvh").read_text())  # an independent reader
        joints = np.load(out / "transfer.joints.npy")
        assert len(parsed.get_joints_names()) == 35 and parsed.nframes == len(joints) and np.isfinite(joints).all()
        assert parsed.frame_time == pytest.approx(1 / 20)
        # on the target's proportions: the bones of the horse's mean offsets, not the dog's
        horse = habit_run["vq"].category_offsets(habit_run["vq"].categories.index("horse")).numpy()
        for joint in (8, 12, 19):  # a foreleg, the other foreleg, a hind leg bone
            name = SMAL35.names[joint]
            assert np.linalg.norm(parsed.joint_offset(name)) == pytest.approx(np.linalg.norm(horse[joint]), rel=1e-3)
        assert np.linalg.norm(horse[8]) > 1.5 * np.linalg.norm(SMAL35.rest_offsets[8])  # a horse's legs are longer
    assert (tmp_path / "horse" / "preview.gif").stat().st_size > 0
    assert "via the nearest known category horse" in capsys.readouterr().out


def test_omg_transfer_reads_a_deepmimic_dog(habit_run, shared_motion, tmp_path):
    from omg.tools.habit import transfer

    clip = shared_motion / "quadruped" / "deepmimic_dog" / "dog3d_trot.txt"
    if not clip.is_file():
        pytest.skip(f"no DeepMimic dog clip at {clip}")
    settings = transfer(clip, to="cow", ckpt=habit_run["vq_path"], out=tmp_path / "cow", preview=False)
    assert settings["habit"] == "posterior mean" and (tmp_path / "cow" / "transfer.bvh").is_file()


def test_omg_transfer_refuses_an_unknown_species(habit_run, tmp_path, capsys):
    from omg.cli import main

    source = tmp_path / "m.npy"
    np.save(source, np.zeros((10, 245), np.float32))
    with pytest.raises(SystemExit) as e:
        main(["transfer", str(source), "--to", "griffon", "--ckpt", str(habit_run["vq_path"]), "--out",
              str(tmp_path / "o")])
    assert e.value.code == 2 and "unknown species 'griffon'" in capsys.readouterr().err


# ----------------------------------------------------------------------------- evaluation


def test_cross_category_fid_averages_the_targets_with_enough_real_samples():
    from omg.metrics import CrossCategoryFID, frechet_distance

    gen = torch.Generator().manual_seed(0)
    real_a, moved_a = torch.randn(6, 3, generator=gen), torch.randn(8, 3, generator=gen) + 1.0
    real_b, moved_b = torch.randn(3, 3, generator=gen), torch.randn(8, 3, generator=gen)  # b: 3 real < 5
    metric = CrossCategoryFID(3, ["a", "b"], min_samples=5)
    metric.update(torch.cat([real_a, real_b]), torch.tensor([0] * 6 + [1] * 3), real=True)
    metric.update(torch.cat([moved_a, moved_b]), torch.tensor([0] * 8 + [1] * 8), real=False)
    out = metric.compute()

    def stats(x):
        return x.double().mean(0), torch.cov(x.double().T)

    expected = frechet_distance(*stats(real_a), *stats(moved_a))
    assert torch.allclose(out["cross_category_fid"], expected) and out["cross_category_fid/b"].isnan()


@torch.no_grad()
def test_the_papers_table_scores_own_category_output_and_the_transfers(habit_run):
    """The paper's table (mode "paper", Sec. 4.4.1): FID, Intra-FID, Diversity and 1-NNA of the model's
    own-category output against the real crops, Downstream of the transfers against the target's real crops,
    MPJPE of the transfers against their sources. Stand-in transfers tell which motion each column reads: one
    that keeps a crop moved onto its own category exactly and replaces a crop moved onto another category by
    that category's real crops scores FID 0 and 1-NNA 0 (own output = the real crops), Downstream near 0 and
    MPJPE > 0 (its transfers are not their sources)."""
    from omg.callbacks.habit import evaluate_habits

    prior, evaluator = habit_run["prior"], habit_run["evaluator"]
    items = _train_crops()
    cats = prior.vq.categories
    real_of = {k: torch.stack([torch.from_numpy(np.asarray(c["motion"])) for c in items if c["category"] == name])
               for k, name in enumerate(cats) if any(c["category"] == name for c in items)}
    category_of = {_key(torch.from_numpy(np.asarray(c["motion"]))): cats.index(c["category"]) for c in items}

    def target_real(motion, k, gen):  # the target's real crops, drawn at random (own category included)
        return real_of[k][torch.randint(len(real_of[k]), (len(motion),), generator=gen)]

    def source(motion, k, gen):  # no transfer at all
        return motion

    def habits_moved(motion, k, gen):  # own category: the crop itself; another: that category's real crops
        drawn = target_real(motion, k, gen)
        keep = torch.tensor([category_of[_key(m)] == k for m in motion])
        return torch.where(keep[:, None, None], motion, drawn)

    def run(move, mode="paper"):
        return evaluate_habits(prior, evaluator, items, seed=0, min_samples=5, diversity_pairs=50, mode=mode,
                               move=move)

    moved, kept = run(habits_moved), run(source)
    assert set(moved) == {"fid", "intra_fid", "cross_category_fid", "diversity", "real_diversity", "one_nna", "mpjpe"}
    # the own-category output is the real crops themselves in both: FID, Intra-FID 0, 1-NNA 0 (each crop's
    # nearest other is its twin), Diversity the real crops'
    for values in (moved, kept):
        assert values["fid"] < 1e-6 and values["intra_fid"] < 1e-6 and values["one_nna"] == 0, values
        assert values["diversity"] == pytest.approx(values["real_diversity"])
    # Downstream and MPJPE read the transfers: habits moved onto the target score near 0 Downstream and leave
    # their source; untransferred crops keep their source (MPJPE 0) and are far from the target's crops
    assert moved["cross_category_fid"] < 0.1 * kept["cross_category_fid"], (moved, kept)
    assert kept["mpjpe"] == 0 < moved["mpjpe"]
    # the transfer-distribution diagnostic: every metric on the transfers against the target's real crops
    moved, kept = run(target_real, "transfer_distribution"), run(source, "transfer_distribution")
    assert moved["intra_fid"] < 0.1 * kept["intra_fid"] and moved["fid"] < 0.05, (moved, kept)
    assert kept["mpjpe"] == 0 < moved["mpjpe"] and "cross_category_fid" not in moved
    # the metrics are chosen by name through the registry, like the text evaluation's: any registered one is fed
    from omg.evaluation import parse_metrics

    chosen = parse_metrics(["fid", "foot_skating"], defaults=(), from_prompts=False)
    picked = evaluate_habits(prior, evaluator, items, seed=0, min_samples=5, diversity_pairs=50, move=source,
                             metrics=chosen)
    assert set(picked) == {"fid", "foot_skating", "real_foot_skating"} and picked["fid"] < 1e-6
    assert picked["foot_skating"] == picked["real_foot_skating"]  # untransferred crops skate as the real ones


def test_the_habit_evaluation_has_one_mode_and_a_named_diagnostic(tmp_path):
    """The paper's table is the default; the transfer-distribution figures are asked for by name; the earlier
    modes' names are one error line listing both."""
    from omg.callbacks.habit import HABIT_METRICS, HabitEvalCallback
    from omg.errors import UsageError

    (tmp_path / "evaluator.ckpt").write_bytes(b"")
    callback = HabitEvalCallback(str(tmp_path / "evaluator.ckpt"))
    assert callback.mode == "paper" and tuple(callback.metrics) == HABIT_METRICS
    assert "cross_category_fid" not in HabitEvalCallback(str(tmp_path / "evaluator.ckpt"),
                                                         mode="transfer_distribution").metrics
    for old in ("transfer", "reconstruction"):
        with pytest.raises(UsageError, match="one of paper, transfer_distribution") as error:
            HabitEvalCallback(str(tmp_path / "evaluator.ckpt"), mode=old)
        assert "\n" not in str(error.value)


def _train_crops() -> list[dict]:
    from omg.callbacks.habit import crops
    from omg.data.datamodule import MotionDataModule
    from omg.data.loaders import ClipDataset

    data = MotionDataModule(str(QUATVEL / "train"), max_len=64, min_len=64, clips="windows", verify_shards=False)
    return [c for c in crops(ClipDataset.from_shards(data.train_urls, data.feature_dim, data.windows).samples, 64)
            if len(c["motion"]) == 64]


def _key(motion: torch.Tensor) -> bytes:
    return motion.float().numpy().tobytes()


def _eval_overlay(tmp_path, evaluator, replications: int, **callback) -> str:
    """configs/mini/habit_eval.yaml with this test's evaluator, replications, table and run folder."""
    import yaml

    config = yaml.safe_load((REPO / "configs" / "mini" / "habit_eval.yaml").read_text())
    config["trainer"]["callbacks"][0]["init_args"].update(evaluator=str(evaluator), replications=replications,
                                                          table=str(tmp_path / "table.json"), **callback)
    config["trainer"]["default_root_dir"] = str(tmp_path / "run")
    config["data"]["val"] = str(QUATVEL / "val")
    (tmp_path / "eval.yaml").write_text(yaml.safe_dump(config))
    return str(tmp_path / "eval.yaml")


def test_omg_test_prints_the_papers_table(habit_run, tmp_path, capsys):
    """omg's earlier order: the stage-2 prior's checkpoint, under the config it was fitted with."""
    from omg.cli import main

    overlay = _eval_overlay(tmp_path, habit_run["evaluator_path"], 2)
    main(["test", "--config", str(REPO / "configs/mini/habit_prior.yaml"), "--config", overlay,
          "--ckpt_path", str(habit_run["prior_path"])])
    printed = capsys.readouterr().out
    assert "| quantizer | FID | Intra-FID | Downstream | Diversity | 1-NNA | MPJPE (m) |" in printed
    assert "| EMA-reset, KL then flows |" in printed and "| real motion |" in printed  # omg's earlier order
    rows = json.loads((tmp_path / "table.json").read_text())
    assert set(rows["EMA-reset, KL then flows"]) >= {"fid", "intra_fid", "cross_category_fid", "diversity",
                                                      "one_nna", "mpjpe"}
    assert all(np.isfinite(v["mean"]) for v in rows["EMA-reset, KL then flows"].values())
    report = json.loads(next((tmp_path / "run").rglob("habit_eval.json")).read_text())
    assert report["settings"]["mode"] == "paper" and report["settings"]["min_samples"] == 5


def test_moved_habit_checkpoints_transfer_and_open_nothing_they_name(tmp_path, monkeypatch):
    """A prior checkpoint holds its VQ-VAE: copied elsewhere, with the VQ-VAE file it was fitted on
    gone and its vq_ckpt naming a `pipe:` command (here: creating a marker file), `omg transfer`
    works and runs nothing."""
    from omg.cli import main
    from omg.data.datamodule import MotionDataModule
    from omg.lit.habit import HabitVQModule

    monkeypatch.setattr(sys, "argv", list(sys.argv))  # `omg fit` sets it for LightningCLI
    torch.manual_seed(0)
    spec = MotionDataModule(str(QUATVEL / "train"), verify_shards=False).spec
    vq = HabitVQModule(CATEGORIES, flavor="tiny", text_encoder="hash", spec=spec)
    original = tmp_path / "run" / "vq.ckpt"
    original.parent.mkdir()
    save_module(vq, original)
    main(["fit", "--config", str(REPO / "configs/mini/habit_prior.yaml"), f"--model.init_args.vq_ckpt={original}",
          "--trainer.max_steps=1", f"--trainer.default_root_dir={tmp_path / 'run'}", "--data.num_workers=0",
          "--trainer.enable_progress_bar=false", "--trainer.enable_model_summary=false"])
    prior = torch.load(tmp_path / "run/checkpoints/last.ckpt", map_location="cpu", weights_only=True)
    assert prior["hyper_parameters"]["vq"]["categories"] == CATEGORIES  # the VQ-VAE's own, under LightningCLI
    marker = tmp_path / "PWNED"
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    prior["hyper_parameters"]["vq_ckpt"] = f"pipe:touch {marker}; cat {original}"
    torch.save(prior, moved / "prior.ckpt")
    (moved / "vq.ckpt").write_bytes(original.read_bytes())
    original.unlink()
    source = moved / "source.npy"
    clip = MotionDataModule(val=str(QUATVEL / "val"), max_len=64, verify_shards=False).val_clips().samples[0]
    np.save(source, np.asarray(clip["motion"][:24], np.float32))
    main(["transfer", str(source), "--to", "horse", "--ckpt", str(moved / "vq.ckpt"), "--prior_ckpt",
          str(moved / "prior.ckpt"), "--no_preview", "--out", str(tmp_path / "out")])
    assert np.load(tmp_path / "out" / "transfer.joints.npy").shape == (24, 35, 3)
    assert not marker.exists()


def test_omg_transfer_onto_a_dog_rig(habit_run, shared_motion, tmp_path):
    """``--to_rig``: the transfer is written onto a MANN-named dog rig (its names and offsets), as BVH and glb."""
    from helpers import DOG_RIG, rig_bvh
    from omg.io.bvh import read_bvh
    from omg.tools.habit import transfer

    (tmp_path / "dog.bvh").write_text(rig_bvh(DOG_RIG))
    clip = shared_motion / "quadruped" / "mann_dog" / "D1_007_KAN01_001.bvh"
    transfer(clip, to="horse", ckpt=habit_run["vq_path"], out=tmp_path / "bvh", preview=False,
             to_rig=tmp_path / "dog.bvh")
    rig, out = read_bvh(tmp_path / "dog.bvh"), read_bvh(tmp_path / "bvh" / "transfer.bvh")
    assert out.names == rig.names and np.allclose(out.offsets, rig.offsets) and out.unit == rig.unit
    assert len(out) == len(np.load(tmp_path / "bvh" / "transfer.joints.npy"))
    settings = transfer(clip, to="horse", ckpt=habit_run["vq_path"], out=tmp_path / "glb", preview=False,
                        to_rig=tmp_path / "dog.bvh", format="glb")
    assert (tmp_path / "glb" / "transfer.glb").stat().st_size > 0
    assert settings["glb"].endswith("transfer.glb") and settings["to_rig"] == str(tmp_path / "dog.bvh")


def test_transfer_writes_the_model_rotations_and_omg_generate_makes_the_same_transfer(habit_run, tmp_path):
    """The BVH holds the rotations the model made (an IK round trip would change each bone's twist), and
    the habit prior answers `omg generate` through the one generation interface with the motion
    `omg transfer` makes."""
    from omg.cli import main
    from omg.data.datamodule import MotionDataModule
    from omg.data.loaders import ClipDataset
    from omg.io.bvh import read_bvh
    from omg.tools.habit import transfer

    vq = habit_run["vq"]
    source = tmp_path / "dog.npy"
    data = MotionDataModule(str(QUATVEL / "val"), verify_shards=False)
    dog = next(s for s in ClipDataset.from_shards(data.train_urls, data.feature_dim, data.windows).samples
               if s["meta"]["category"] == "dog")
    np.save(source, np.asarray(dog["motion"][:48], dtype=np.float32))
    transfer(source, to="horse", ckpt=habit_run["vq_path"], prior_ckpt=habit_run["prior_path"], out=tmp_path / "t",
             preview=False)
    features = np.load(tmp_path / "t/transfer.features.npy")
    made = torch.nn.functional.normalize(torch.from_numpy(features[:, : vq.num_joints * 4]).unflatten(-1, (-1, 4)),
                                         dim=-1)
    bvh = read_bvh(tmp_path / "t/transfer.bvh", scale=1.0)
    written = torch.from_numpy(bvh.rotations[:, [bvh.names.index(n) for n in SMAL35.names]]).float()  # model order
    agreement = (made * written).sum(-1).abs()  # |cos| of the half angle between the two rotations
    assert agreement.min() > 0.9999, float(agreement.min())

    main(["generate", "--ckpt", str(habit_run["prior_path"]), "--from_motion", str(source), "--animal", "horse",
          "--num_samples", "1", "--no_preview", "--out", str(tmp_path / "g")])
    np.testing.assert_array_equal(np.load(tmp_path / "g/sample_000.features.npy"), features)
    settings = json.loads((tmp_path / "g/generation.json").read_text())
    assert settings["family"] == "habit" and settings["category"] == "horse" and settings["habit"] == "prior sample"


# ----------------------------------------------------------------------------- the paper's training order


def test_pretraining_trains_encoders_and_flows_on_the_flow_prior_kl_and_the_vqvae_has_no_kl():
    """habit_order flow_prior (the default): the pretraining loss is the habit statistics + flow_weight ·
    (log q(z|m) − log p_flow(z)) per dimension, and its gradient reaches the encoders and the flows, not the
    VQ-VAE; the VQ-VAE's loss then trains the VQ-VAE only, with no KL term."""
    from omg.data.datamodule import MotionDataModule
    from omg.lit.habit import HabitVQModule
    from omg.models.habit import habit_statistics

    data = MotionDataModule(str(QUATVEL / "train"), batch_size=8, max_len=64, min_len=64, clips="windows",
                            batches_per_epoch=1, num_workers=0, shuffle_buffer=32, verify_shards=False)
    batch = next(iter(data.train_dataloader()))
    torch.manual_seed(0)
    module = HabitVQModule(CATEGORIES, flavor="tiny", text_encoder="hash", spec=data.spec).train()
    assert module.habit_order == "flow_prior" and module.habit_steps(10) == 2
    with torch.no_grad():  # an untrained flow is the identity: make it a real density first
        for p in module.flows.parameters():
            p.add_(0.05 * torch.randn_like(p))
    out = module.habit_losses(batch, torch.Generator().manual_seed(3))

    # by hand, with the same posterior sample
    category = module.category_index(batch["category"])
    mu, log_sigma = module.habit_encoders(batch["motion"], batch["mask"], category)
    eps = torch.randn(mu.shape, generator=torch.Generator().manual_seed(3))
    z = mu + log_sigma.exp() * eps
    log_q = torch.distributions.Normal(mu, log_sigma.exp()).log_prob(z).sum(-1)
    log_p = torch.stack([module.flows.flows[int(k)].log_prob(z[i:i + 1])[0] for i, k in enumerate(category)])
    kl = (log_q - log_p).mean() / z.shape[1]
    rotations = batch["motion"][..., 4:35 * 4]  # SMAL-35's local rotations but the root's (no path)
    stats = torch.nn.functional.smooth_l1_loss(module.habit_stats(z), habit_statistics(rotations, batch["mask"]))
    torch.testing.assert_close(out["flow_kl"], kl)
    torch.testing.assert_close(out["loss"], stats + module.loss.flow_weight * kl)

    def grads(loss):
        module.zero_grad()
        loss.backward()
        return {name: p.grad is not None and bool(p.grad.abs().sum() > 0) for name, p in module.named_parameters()}

    reached = grads(out["loss"])
    for part in ("habit_encoders.", "flows.", "habit_stats."):
        assert any(v for k, v in reached.items() if k.startswith(part)), part
    assert not any(v for k, v in reached.items() if k.startswith("vqvae."))
    # the flows learn from the KL term alone (the statistics do not see them): the NLL of the posterior
    only_kl = grads(module.habit_losses(batch, torch.Generator().manual_seed(3))["flow_kl"])
    assert any(v for k, v in only_kl.items() if k.startswith("flows."))

    losses, _, _ = module.losses(batch, torch.Generator().manual_seed(3))
    assert "kl" not in losses
    reached = grads(losses["loss"])
    assert any(v for k, v in reached.items() if k.startswith("vqvae."))
    assert not any(v for k, v in reached.items() if k.startswith(("habit_encoders.", "flows.", "habit_stats.")))


def test_the_default_order_pretrains_then_freezes_the_encoders_and_flows(habit_flow_run):
    snap = habit_flow_run["snapshots"]
    assert set(snap.at) == {"start", "pretrained", "end"}
    for part in ("habit_encoders.", "flows."):
        assert snap.changed("start", "pretrained", part), part  # trained in the pretraining ...
        assert not snap.changed("pretrained", "end", part), part  # ... and frozen after it
    assert not snap.changed("start", "pretrained", "vqvae.")  # the VQ-VAE waits for the pretrained encoders
    assert snap.changed("pretrained", "end", "vqvae.")


def test_omg_transfer_and_generate_work_from_a_checkpoint_of_the_default_order(habit_flow_run, shared_motion,
                                                                                tmp_path):
    """No stage 2: the checkpoint's own flows give the habit latent, through `omg transfer` and `omg generate`;
    `omg transfer` is an alias of `omg generate`: its flags (--temperature, --quantizer, --joint_map) are
    generate's --option and --from_motion_joint_map, and the files they write are the same bytes."""
    from omg.cli import main

    clip = shared_motion / "quadruped" / "mann_dog" / "D1_007_KAN01_001.bvh"
    ckpt = str(habit_flow_run["vq_path"])
    main(["transfer", str(clip), "--to", "horse", "--ckpt", ckpt, "--no_preview", "--out", str(tmp_path / "t"),
          "--temperature", "0.5", "--quantizer", "nearest", "--joint_map", "mann_dog"])
    settings = json.loads((tmp_path / "t/transfer.json").read_text())
    assert settings["habit"] == "prior sample" and settings["habit_order"] == "flow_prior"
    assert (settings["temperature"], settings["quantizer"]) == (0.5, "nearest")
    features = np.load(tmp_path / "t/transfer.features.npy")
    assert np.isfinite(features).all() and np.isfinite(np.load(tmp_path / "t/transfer.joints.npy")).all()
    main(["generate", "--ckpt", ckpt, "--from_motion", str(clip), "--animal", "horse", "--num_samples", "1",
          "--no_preview", "--out", str(tmp_path / "g"), "--option", "temperature=0.5", "--option=quantizer=nearest",
          "--from_motion_joint_map", "mann_dog"])
    for transferred, generated in (("transfer.features.npy", "sample_000.features.npy"),
                                   ("transfer.joints.npy", "sample_000.joints.npy"),
                                   ("transfer.bvh", "sample_000.bvh"), ("source.joints.npy", "source.joints.npy")):
        assert (tmp_path / "t" / transferred).read_bytes() == (tmp_path / "g" / generated).read_bytes(), generated
    main(["generate", "--ckpt", ckpt, "--from_motion", str(clip), "--animal", "horse", "--num_samples", "1",
          "--no_preview", "--out", str(tmp_path / "d")])
    assert not np.array_equal(np.load(tmp_path / "d/sample_000.features.npy"), features)  # the options count
    generated = json.loads((tmp_path / "g/generation.json").read_text())
    assert generated["category"] == "horse" and generated["habit"] == "prior sample"
    # the latent is a sample of horse's pretrained flow, drawn with the seed
    vq = habit_flow_run["vq"]
    z = vq.habit_latents(vq.categories.index("horse"), 1, seed=0)
    assert torch.equal(z, vq.flows.sample(vq.categories.index("horse"), 1, torch.Generator().manual_seed(0)))


def test_omg_test_evaluates_the_default_order_with_its_own_flows(habit_run, habit_flow_run, tmp_path, capsys):
    """`omg test --config configs/mini/habit_vqvae.yaml --config configs/mini/habit_eval.yaml --ckpt_path` on a
    VQ-VAE of the default order, without a stage-2 checkpoint: its own flows give the habit latents. A VQ-VAE of
    omg's earlier order holds none: one error line naming its prior."""
    from omg.cli import main
    from omg.lit.habit import HabitPriorModule

    prior = HabitPriorModule(str(habit_flow_run["vq_path"]))
    assert all(torch.equal(a, b) for a, b in zip(prior.flows.state_dict().values(),
                                                  habit_flow_run["vq"].flows.state_dict().values()))
    overlay = _eval_overlay(tmp_path, habit_run["evaluator_path"], 1, mode="transfer_distribution")
    vqvae = str(REPO / "configs/mini/habit_vqvae.yaml")
    tiny = "--model.init_args.flavor=tiny"  # the checkpoints' size: a config that says otherwise is refused
    main(["test", "--config", vqvae, "--config", overlay, "--ckpt_path", str(habit_flow_run["vq_path"]), tiny])
    assert "| EMA-reset (transfer distribution) |" in capsys.readouterr().out
    main(["test", "--config", vqvae, "--config", overlay, "--ckpt_path", str(habit_flow_run["vq_path"]), tiny,
          "--trainer.callbacks.init_args.mode", "paper"])
    assert "| EMA-reset |" in capsys.readouterr().out
    rows = json.loads((tmp_path / "table.json").read_text())
    assert list(rows) == ["EMA-reset", "EMA-reset (transfer distribution)"]
    assert all(np.isfinite(v["mean"]) for v in rows["EMA-reset"].values()) and "cross_category_fid" in rows["EMA-reset"]
    with pytest.raises(SystemExit) as e:
        main(["test", "--config", vqvae, "--config", overlay, "--ckpt_path", str(habit_run["vq_path"]), tiny,
              "--model.init_args.order.habit_order=kl_then_flows"])  # as trained (the config's flow_prior is refused)
    err = capsys.readouterr().err
    assert e.value.code == 2 and "holds no flow priors" in err and "habit_prior.yaml" in err
    assert len(err.strip().splitlines()) == 1


def test_checkpoints_from_before_the_training_order_option_load_in_the_earlier_order(tmp_path):
    """A VQ-VAE or prior checkpoint written before habit_order existed (no such hyper-parameter, no flows in the
    VQ-VAE) loads as what it is, omg's earlier order, and transfers."""
    from omg.data.datamodule import MotionDataModule
    from omg.lit.checkpoint import load_module
    from omg.lit.habit import HabitPriorModule, HabitVQModule

    spec = MotionDataModule(str(QUATVEL / "train"), verify_shards=False).spec
    old = HabitVQModule(CATEGORIES, order={"habit_order": "kl_then_flows"}, flavor="tiny", text_encoder="hash",
                        spec=spec)
    hparams = {k: v for k, v in old.hparams.items() if k != "order"}
    torch.save({"state_dict": old.state_dict(), "hyper_parameters": hparams,
                "module_class": "omg.lit.habit.HabitVQModule"}, tmp_path / "vq.ckpt")
    vq = load_module(tmp_path / "vq.ckpt", default_class=HabitVQModule)
    assert vq.habit_order == "kl_then_flows" and vq.flows is None and vq.row_label == "EMA-reset, KL then flows"
    prior = HabitPriorModule(str(tmp_path / "vq.ckpt"))
    torch.save({"state_dict": prior.state_dict(), "hyper_parameters": {**prior.hparams, "vq": hparams},
                "module_class": "omg.lit.habit.HabitPriorModule"}, tmp_path / "prior.ckpt")
    moved = load_module(tmp_path / "prior.ckpt", default_class=HabitPriorModule)
    assert moved.vq.habit_order == "kl_then_flows"
    motion = torch.zeros(1, 8, spec.feature_dim)
    assert torch.isfinite(moved.vq.transfer(motion, 1, moved.habit_latents(1, 1))).all()


def test_the_default_order_under_ddp_asks_for_unused_parameters(tmp_path):
    """Each phase of flow_prior leaves a part of the model without gradient: plain DDP would hang or fail at the
    first step, so fit start says which strategy to use (one line). The check reads the DDP wrapper the strategy
    has put around the module by then (one gloo rank here)."""
    import lightning as L
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    from omg.data.datamodule import MotionDataModule
    from omg.errors import UsageError
    from omg.lit.habit import HabitVQModule

    spec = MotionDataModule(str(QUATVEL / "train"), verify_shards=False).spec
    dist.init_process_group("gloo", store=dist.FileStore(str(tmp_path / "store"), 1), rank=0, world_size=1)
    try:
        for find_unused, order, refused in ((False, "flow_prior", True), (False, "kl_then_flows", False),
                                            (True, "flow_prior", False)):
            module = HabitVQModule(CATEGORIES, order={"habit_order": order}, flavor="tiny", text_encoder="hash",
                                   spec=spec)
            module.trainer = L.Trainer(accelerator="cpu", devices=1, logger=False)
            module.trainer.strategy.model = DistributedDataParallel(module, find_unused_parameters=find_unused)
            if refused:
                with pytest.raises(UsageError, match="set trainer.strategy ddp_find_unused_parameters_true"):
                    module.on_fit_start()
            else:
                module.on_fit_start()
    finally:
        # the DDP wrappers (each a reducer holding the gloo group) sit in cycles with their module and trainer:
        # collected here, while the group's threads exist; a process forked from this worker later (a shard
        # build's pool) would otherwise collect them without those threads and hang in the group's destructor
        module = None
        gc.collect()
        dist.destroy_process_group()
