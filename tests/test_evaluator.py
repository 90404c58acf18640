"""Text–motion evaluators: the contrastive one trained with a real Trainer on the mini humans,
its checkpoints, and the port of the HumanML3D T2M evaluator on official key names and shapes."""

from __future__ import annotations

import pickle
import sys
import time

import lightning as L
import numpy as np
import pytest
import torch

from helpers import REPO
from omg.data.datamodule import MotionDataModule
from omg.data.loaders import ClipDataset
from omg.data.shards import Manifest
from omg.data.windows import Collate, WindowSampler
from omg.errors import UsageError
from omg.lit.evaluator import EvaluatorModule, load_evaluator
from omg.losses import info_nce
from omg.metrics import RPrecision
from omg.models.evaluator import TextMotionEvaluator, same_pairs
from omg.tools.shards import build

MINI = REPO / "shards/mini/human263"
ANIMAL = REPO / "shards/mini/animal_maa"
STEPS = 120
POOL = 32
# the tests share the trained evaluator: under xdist they run on one worker, which trains it once
pytestmark = pytest.mark.xdist_group("evaluator")


def _data(root=MINI, **kw):
    args = dict(batch_size=32, max_len=196, min_len=60, batches_per_epoch=1000, num_workers=0, shuffle_buffer=90,
                clip_sampling="whole")  # EvaluatorModule's, which `omg fit` links
    return MotionDataModule(str(root / "train"), str(root / "val"), **{**args, **kw})


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    """The mini evaluator trained for STEPS steps on the mini humans' train split (validated once, at the end)."""
    root = tmp_path_factory.mktemp("evaluator")
    torch.manual_seed(0)
    data = _data()
    module = EvaluatorModule(text_encoder="minilm", flavor="mini", r_precision_pool=10,
                             spec=data.spec, optim={"lr": 1e-3, "warmup_steps": 20})
    backbone = {k: v.clone() for k, v in module.evaluator.text_encoder.state_dict().items()}
    trainer = L.Trainer(max_steps=STEPS, val_check_interval=STEPS, check_val_every_n_epoch=None, accelerator="cpu",
                        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=root, gradient_clip_val=1.0)
    start = time.perf_counter()
    trainer.fit(module, data)
    seconds = time.perf_counter() - start
    trainer.save_checkpoint(root / "evaluator.ckpt")
    print(f"\ntrained the mini evaluator: {STEPS} steps of 32 in {seconds:.1f}s; {trainer.callback_metrics}")
    return {"module": module, "ckpt": root / "evaluator.ckpt", "metrics": dict(trainer.callback_metrics),
            "backbone": backbone}


@pytest.fixture(scope="session")
def held_out(tmp_path_factory):
    """96 unseen clips of the same procedural distribution (another seed): un-normalised whole
    motions, their first captions and action labels. The mini val split has only 10 clips, fewer
    than one pool of 32."""
    out = tmp_path_factory.mktemp("held_out")
    build("synth", out, "humanml3d263", "smpl22", 20.0, options={"num_clips": 96, "seed": 1}, max_clips=1000)
    urls = [str(p) for p in Manifest.load(out).shard_paths]
    ds = ClipDataset.from_shards(urls, 263, WindowSampler(200, 200))
    batch = Collate()([ds[i] for i in range(len(ds))])  # no stats: raw features, as generators hand them over
    actions = [s["meta"]["labels"]["action"] for s in ds.samples]
    return batch, actions


def _pools(n: int, seed: int) -> torch.Tensor:
    """RPrecision's pools: the same seeded permutation, cut into rows of POOL."""
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    return order[: n // POOL * POOL].view(-1, POOL)


def _action_oracle(actions: list[str], seed: int, k: int) -> float:
    """Expected top-k of a ranker that knows each motion's action and nothing else (ties broken
    at random): with m other same-action motions in the pool, P(top-k) = min(1, k / (m + 1))."""
    hits = []
    for pool in _pools(len(actions), seed):
        labels = [actions[i] for i in pool]
        hits += [min(1.0, k / labels.count(a)) for a in labels]
    return float(np.mean(hits))


def test_ranks_true_pairs_far_above_shuffled(trained, held_out):
    evaluator = trained["module"].evaluator.eval()
    batch, actions = held_out
    with torch.no_grad():
        motion = evaluator.encode_motion(batch["motion"], batch["mask"])
        text = evaluator.encode_text(batch["text"])
    true, shuffled, oracle = {1: [], 3: []}, {1: [], 3: []}, {1: [], 3: []}
    for seed in range(4):
        r = RPrecision(pool_size=POOL, seed=seed)
        r.update(text, motion)
        got = r.compute()
        perm = torch.randperm(len(motion), generator=torch.Generator().manual_seed(100 + seed))
        s = RPrecision(pool_size=POOL, seed=seed)
        s.update(text, motion[perm])  # every caption paired with a random motion
        got_shuffled = s.compute()
        for k in (1, 3):
            true[k].append(float(got[f"r_precision/top{k}"]))
            shuffled[k].append(float(got_shuffled[f"r_precision/top{k}"]))
            oracle[k].append(_action_oracle(actions, seed, k))
    mean = lambda xs: float(np.mean(xs))  # noqa: E731
    print(f"\nheld-out R-precision (pools of {POOL}, 4 shuffles of 96 clips): true top1 {mean(true[1]):.3f} "
          f"top3 {mean(true[3]):.3f}; shuffled top1 {mean(shuffled[1]):.3f} top3 {mean(shuffled[3]):.3f}; "
          f"action-only oracle top1 {mean(oracle[1]):.3f} top3 {mean(oracle[3]):.3f}")
    assert mean(true[3]) > 0.8
    # a shuffled pair's motion is a random one: its rank is uniform over the pool, so top-k = k/32
    assert abs(mean(shuffled[3]) - 3 / POOL) < 0.06 and abs(mean(shuffled[1]) - 1 / POOL) < 0.04
    # The captions are templates of 10 actions: a pool holds ~3 clips of each action, and an
    # evaluator that only recognised the action would score the oracle's top-1. Beating it means
    # it also reads direction, hand, count, speed or style from the text and the motion.
    assert mean(true[1]) > mean(oracle[1]) + 0.1


def test_validation_logs_loss_r_precision_and_mm_dist(trained):
    metrics = trained["metrics"]
    for key in ("train/loss", "val/loss", "val/r_precision_top1", "val/r_precision_top3", "val/mm_dist"):
        assert key in metrics and torch.isfinite(metrics[key]), key
    # the 10 validation clips are one per action, a pool of 10: top-3 is 0.3 by chance
    assert metrics["val/r_precision_top3"] >= 0.8
    assert 0 < metrics["val/mm_dist"] < 2  # unit vectors


def test_backbone_stays_frozen_and_out_of_checkpoints(trained):
    module = trained["module"]
    backbone = module.evaluator.text_encoder
    assert not any(p.requires_grad for p in backbone.parameters()) and not backbone.training
    assert all(torch.equal(v, trained["backbone"][k]) for k, v in backbone.state_dict().items())
    state = torch.load(trained["ckpt"], weights_only=False)["state_dict"]
    assert not any(k.startswith("evaluator.text_encoder.") for k in state)
    assert {"evaluator.mean", "evaluator.std", "evaluator.logit_scale"} <= state.keys()
    trainable = {n for n, p in module.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith("evaluator.") and ".text_encoder." not in n for n in trainable)


def test_load_evaluator_round_trip(trained, held_out, tmp_path):
    from omg.lit.checkpoint import convert

    evaluator = trained["module"].evaluator.eval()
    batch, _ = held_out
    motion, mask, texts = batch["motion"][:8], batch["mask"][:8], batch["text"][:8]
    with torch.no_grad():
        want_m, want_t = evaluator.encode_motion(motion, mask), evaluator.encode_text(texts)
    converted = convert(trained["ckpt"], tmp_path / "evaluator.safetensors", default_class=EvaluatorModule)["path"]
    for path in (trained["ckpt"], converted):
        loaded = load_evaluator(path)
        assert isinstance(loaded, TextMotionEvaluator) and not loaded.training
        assert not any(p.requires_grad for p in loaded.parameters())
        assert loaded.spec == trained["module"].evaluator.spec and loaded.spec.fps == 20.0
        with torch.no_grad():
            torch.testing.assert_close(loaded.encode_motion(motion, mask), want_m)
            torch.testing.assert_close(loaded.encode_text(texts), want_t)
    with pytest.raises(UsageError, match="no such file"):
        load_evaluator(tmp_path / "missing.ckpt")


def test_motion_is_normalised_inside_and_padding_ignored(trained, held_out):
    evaluator = trained["module"].evaluator.eval()
    batch, _ = held_out
    motion, mask = batch["motion"][:6].clone(), batch["mask"][:6]
    with torch.no_grad():
        raw = evaluator.encode_motion(motion, mask)
        normalised = evaluator.encode_normalized_motion((motion - evaluator.mean) / evaluator.std, mask)
        motion[~mask] = 1e3  # whatever lies past the end
        garbage = evaluator.encode_motion(motion, mask)
        alone = torch.cat([evaluator.encode_motion(motion[i : i + 1, : int(mask[i].sum())]) for i in range(6)])
    torch.testing.assert_close(raw, normalised)
    torch.testing.assert_close(garbage, raw)
    torch.testing.assert_close(alone, raw, atol=1e-5, rtol=1e-4)  # batch-independent
    assert raw.shape == (6, evaluator.config.embed_dim)
    torch.testing.assert_close(raw.norm(dim=-1), torch.ones(6))


def test_duplicate_captions_are_not_negatives():
    texts = ["A person walks.", "a person walks", "a person jumps.", "a person waves"]
    same = same_pairs(texts, ids=["c0", "c1", "c2", "c2"])
    assert same.tolist() == [[True, True, False, False], [True, True, False, False],
                             [False, False, True, True], [False, False, True, True]]
    logits = torch.randn(4, 4, requires_grad=True)
    info_nce(logits, same).backward()
    grad = logits.grad
    assert grad[0, 1] == 0 and grad[1, 0] == 0 and grad[2, 3] == 0 and grad[3, 2] == 0  # twins: no push
    assert (grad[0, 2:] > 0).all() and (grad.diagonal() < 0).all()  # real negatives pushed, positives pulled
    # without masking, two identical captions over two motions can never go below log 2 per side
    twins = torch.tensor([[10.0, 10.0], [10.0, 10.0]])
    assert info_nce(twins) == pytest.approx(np.log(2), abs=1e-4)
    assert info_nce(twins, same_pairs(["a", "a"])) == pytest.approx(0.0, abs=1e-6)


def test_paraphrases_with_the_same_labels_are_not_negatives():
    texts = ["a person walks backward like an old person.", "an old man backs away slowly.",
             "a person bows like an old person.", "a person stands."]
    labels = [{"content": "walk-back", "style": "old"}, {"style": "old", "content": "walk-back"},
              {"content": "bow", "style": "old"}, {}]
    same = same_pairs(texts, ids=["a", "b", "c", "d"], labels=labels)
    assert same.tolist() == [[True, True, False, False], [True, True, False, False],
                             [False, False, True, False], [False, False, False, True]]
    # rows without labels are not all one class
    assert not same_pairs(["x", "y"], labels=[{}, {}])[0, 1]


def test_batches_carry_each_clips_labels(toy_shards):
    from omg.data.datamodule import MotionDataModule

    batch = next(iter(MotionDataModule(str(toy_shards), batch_size=4, num_workers=0,
                                       batches_per_epoch=1).train_dataloader()))
    assert batch["labels"] == [{}] * 4  # toy clips carry no labels; bandai1 takes carry {content, style}


def test_any_skeleton_animals_train_and_registry(tmp_path):
    data = _data(ANIMAL, batch_size=8, max_len=60, min_len=40)
    assert data.spec.skeleton == "smal35" and data.spec.representation == "maa"
    module = EvaluatorModule(text_encoder="hash", flavor="mini", evaluator={"n_layers": 1},
                             spec=data.spec, optim={"lr": 1e-3, "warmup_steps": 1})
    before = {k: v.clone() for k, v in module.evaluator.motion_encoder.state_dict().items()}
    trainer = L.Trainer(max_steps=3, limit_val_batches=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    trainer.fit(module, data)
    assert torch.isfinite(trainer.callback_metrics["train/loss"])
    assert any(not torch.equal(before[k], v) for k, v in module.evaluator.motion_encoder.state_dict().items())
    x = torch.randn(2, 30, data.feature_dim)
    assert module.evaluator.encode_motion(x, torch.ones(2, 30, dtype=torch.bool)).shape == (2, 128)
    with pytest.raises(UsageError, match="unknown evaluator flavor"):
        EvaluatorModule(text_encoder="hash", flavor="huge", spec=data.spec)
    with pytest.raises(UsageError, match="spec"):
        EvaluatorModule(text_encoder="hash", flavor="mini")


def test_mini_config_runs_through_the_cli(tmp_path, monkeypatch):
    from omg.cli import main

    monkeypatch.chdir(REPO)
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # omg.cli sets it for LightningCLI
    main(["fit", "--config", "configs/mini/evaluator.yaml", "--trainer.max_steps=2", "--trainer.val_check_interval=2",
          f"--trainer.default_root_dir={tmp_path}", f"--trainer.callbacks.dirpath={tmp_path}/ckpt",
          "--trainer.enable_progress_bar=false", "--data.num_workers=0", "--data.batch_size=8",
          "--model.init_args.text_encoder=hash"])
    evaluator = load_evaluator(tmp_path / "ckpt/last.ckpt")
    assert evaluator.encode_text(["a person walks"]).shape == (1, 128)


# -- the T2M port ---------------------------------------------------------------------------

# The official checkpoint's keys and shapes (networks/modules.py with the t2m sizes), written out
# by hand so that the port is checked against the original, not against itself.
def _gru(prefix: str, inp: int, hidden: int) -> dict:
    out = {}
    for suffix in ("l0", "l0_reverse"):
        out |= {f"{prefix}.weight_ih_{suffix}": (3 * hidden, inp), f"{prefix}.weight_hh_{suffix}": (3 * hidden, hidden),
                f"{prefix}.bias_ih_{suffix}": (3 * hidden,), f"{prefix}.bias_hh_{suffix}": (3 * hidden,)}
    return out


def _head(hidden: int, out: int) -> dict:
    return {"output_net.0.weight": (hidden, 2 * hidden), "output_net.0.bias": (hidden,),
            "output_net.1.weight": (hidden,), "output_net.1.bias": (hidden,), "output_net.3.weight": (out, hidden),
            "output_net.3.bias": (out,), "hidden": (2, 1, hidden)}


OFFICIAL_SHAPES = {
    "movement_encoder": {"main.0.weight": (512, 259, 4), "main.0.bias": (512,), "main.3.weight": (512, 512, 4),
                         "main.3.bias": (512,), "out_net.weight": (512, 512), "out_net.bias": (512,)},
    "text_encoder": {"pos_emb.weight": (300, 15), "pos_emb.bias": (300,), "input_emb.weight": (512, 300),
                     "input_emb.bias": (512,), **_gru("gru", 512, 512), **_head(512, 512)},
    "motion_encoder": {"input_emb.weight": (1024, 512), "input_emb.bias": (1024,), **_gru("gru", 1024, 1024),
                       **_head(1024, 512)},
}
WORDS = ["unk", "sos", "eos", "a", "person", "walk", "forward", "turn", "left", "jump", "man", "kick", "with", "his",
         "leg", "wave", "both", "hand", "box"]


@pytest.fixture(scope="session")
def t2m_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("t2m")
    g = torch.Generator().manual_seed(0)
    ckpt = {name: {k: 0.05 * torch.randn(shape, generator=g) for k, shape in keys.items()}
            for name, keys in OFFICIAL_SHAPES.items()}
    torch.save({**ckpt, "epoch": 7, "iter": 1000}, root / "finest.tar")
    glove = root / "glove"
    glove.mkdir()
    np.save(glove / "our_vab_data.npy", np.random.default_rng(0).standard_normal((len(WORDS), 300)).astype(np.float32))
    (glove / "our_vab_words.pkl").write_bytes(pickle.dumps(WORDS))
    (glove / "our_vab_idx.pkl").write_bytes(pickle.dumps({w: i for i, w in enumerate(WORDS)}))
    meta = root / "meta"
    meta.mkdir()
    rng = np.random.default_rng(1)
    np.save(meta / "mean.npy", rng.standard_normal(263).astype(np.float32))
    np.save(meta / "std.npy", (0.5 + rng.random(263)).astype(np.float32))
    return {"ckpt": root / "finest.tar", "glove": glove, "meta": meta, "state": ckpt}


def test_t2m_loads_official_keys_strictly_and_encodes(t2m_files):
    from omg.models.t2m import load_t2m_evaluator

    ev = load_t2m_evaluator(t2m_files["ckpt"], t2m_files["glove"], t2m_files["meta"])
    for name, keys in OFFICIAL_SHAPES.items():
        state = getattr(ev, name).state_dict()
        assert {k: tuple(v.shape) for k, v in state.items()} == keys  # exactly the official names and shapes
        assert all(torch.equal(state[k], v) for k, v in t2m_files["state"][name].items())
    assert not ev.training and not any(p.requires_grad for p in ev.parameters())
    assert ev.spec["feature_dim"] == 263 and ev.spec["fps"] == 20.0

    motion = torch.randn(5, 60, 263)
    mask = torch.arange(60) < torch.tensor([60, 23, 41, 8, 60])[:, None]
    emb = ev.encode_motion(motion, mask)
    assert emb.shape == (5, 512)
    # sorted internally, returned in input order: each row equals the motion encoded alone
    for i, n in enumerate([60, 20, 40, 8, 60]):  # lengths cropped to whole 4-frame units
        torch.testing.assert_close(ev.encode_motion(motion[i : i + 1, :n]), emb[i : i + 1], atol=1e-5, rtol=1e-4)
    texts = ["a/DET person/NOUN walk/VERB forward/ADV", "a man kicks with his left leg", "someone boxes."]
    text = ev.encode_text(texts)
    assert text.shape == (3, 512)
    torch.testing.assert_close(ev.encode_text(texts[::-1]), text.flip(0))
    # a HumanML3D text-file line is read through its tokens
    torch.testing.assert_close(
        ev.encode_text(["a person walks forward.#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0"]), text[:1])


def test_t2m_matches_a_direct_recomputation(t2m_files):
    import torch.nn.functional as F

    from omg.models.t2m import load_t2m_evaluator

    ev = load_t2m_evaluator(t2m_files["ckpt"], t2m_files["glove"], t2m_files["meta"])
    s = t2m_files["state"]

    # movement encoder: conv (k4 s2 p1) -> leaky relu -> conv -> leaky relu -> linear,
    # on normalised features w/o contacts
    x = torch.randn(2, 16, 263)
    m = s["movement_encoder"]
    z = (x - ev.mean) / ev.std
    h = F.leaky_relu(F.conv1d(z[..., :-4].transpose(1, 2), m["main.0.weight"], m["main.0.bias"], 2, 1), 0.2)
    h = F.leaky_relu(F.conv1d(h, m["main.3.weight"], m["main.3.bias"], 2, 1), 0.2).transpose(1, 2)
    torch.testing.assert_close(ev.movement_encoder(z[..., :-4]), F.linear(h, m["out_net.weight"], m["out_net.bias"]))

    # text encoder on "sos a person walk forward eos": a plain bidirectional GRU run from the learned h0
    t = s["text_encoder"]
    words, pos, sent_len = ev.tokenize("a/DET person/NOUN walk/VERB forward/ADV")
    assert sent_len == 6 and words.shape == (22, 300) and pos.shape == (22, 15)
    assert pos[3].argmax() == 12 and pos[4].argmax() == 9  # walk -> Act_VIP, forward -> Loc_VIP
    assert pos[0].argmax() == pos[5].argmax() == pos[6].argmax() == 14  # sos, eos, unk padding: OTHER
    w = torch.as_tensor(words[:sent_len], dtype=torch.float32)[None]
    p = torch.as_tensor(pos[:sent_len], dtype=torch.float32)[None]
    inp = F.linear(w + F.linear(p, t["pos_emb.weight"], t["pos_emb.bias"]), t["input_emb.weight"], t["input_emb.bias"])
    gru = torch.nn.GRU(512, 512, batch_first=True, bidirectional=True)
    gru.load_state_dict({k.removeprefix("gru."): v for k, v in t.items() if k.startswith("gru.")})
    with torch.no_grad():
        _, last = gru(inp, t["hidden"])
    h = F.linear(torch.cat([last[0], last[1]], -1), t["output_net.0.weight"], t["output_net.0.bias"])
    h = F.leaky_relu(F.layer_norm(h, (512,), t["output_net.1.weight"], t["output_net.1.bias"]), 0.2)
    want = F.linear(h, t["output_net.3.weight"], t["output_net.3.bias"])
    torch.testing.assert_close(ev.encode_text(["a/DET person/NOUN walk/VERB forward/ADV"]), want, atol=1e-5, rtol=1e-4)


def test_t2m_word_vectorizer_and_caption_fallback(t2m_files):
    from omg.models.t2m import POS_enumerator, WordVectorizer, process_tokens, tag_caption

    wv = WordVectorizer(t2m_files["glove"])
    vec, pos = wv["hand/NOUN"]
    assert vec.shape == (300,) and pos.argmax() == POS_enumerator["Body_VIP"]
    vec, pos = wv["zebra/NOUN"]  # unknown: unk vector, OTHER
    assert np.array_equal(vec, wv.word2vec["unk"]) and pos.argmax() == POS_enumerator["OTHER"]
    assert (wv["his/PRON"][1].argmax() == POS_enumerator["PRON"]
            and wv["zebra/PRON"][1].argmax() == POS_enumerator["OTHER"])
    assert wv["a/DET"][1].argmax() == POS_enumerator["DET"]

    tokens, n = process_tokens([f"w{i}/NOUN" for i in range(25)])
    assert n == 22 and len(tokens) == 22 and tokens[0] == "sos/OTHER" and tokens[-1] == "eos/OTHER"
    tokens, n = process_tokens(["a/DET", "man/NOUN"])
    assert n == 4 and len(tokens) == 22 and tokens[4:] == ["unk/OTHER"] * 18

    assert tag_caption("A man kicks with his left leg twice.", wv) == [
        "a/DET", "man/NOUN", "kick/VERB", "with/ADP", "his/PRON", "left/ADV", "leg/NOUN", "twice/ADV"]
    assert tag_caption("Someone is waving both hands", wv) == [
        "someone/PRON", "is/AUX", "wave/VERB", "both/DET", "hand/NOUN"]


class _Payload:
    """Unpickling this calls ``open(path, "w")``: a crafted GloVe file would call os.system."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return open, (self.path, "w")


def test_t2m_glove_files_cannot_run_code(t2m_files, tmp_path):
    import shutil

    from omg.models.t2m import WordVectorizer

    crafted = {"our_vab_words.pkl": lambda marker: [*WORDS, _Payload(marker)],
               "our_vab_idx.pkl": lambda marker: {"unk": 0, "sos": _Payload(marker)}}
    for name, content in crafted.items():
        glove, marker = tmp_path / name, tmp_path / f"ran-{name}"
        shutil.copytree(t2m_files["glove"], glove)
        (glove / name).write_bytes(pickle.dumps(content(marker)))
        with pytest.raises(UsageError, match=rf"{name} holds pickled Python objects .*refused"):
            WordVectorizer(glove)
        assert not marker.exists()
    glove = tmp_path / "wrong_types"
    shutil.copytree(t2m_files["glove"], glove)
    (glove / "our_vab_idx.pkl").write_bytes(pickle.dumps(WORDS))  # a list where the dict belongs
    with pytest.raises(UsageError, match="holds a list, not the dict"):
        WordVectorizer(glove)
    np.save(glove / "our_vab_data.npy", np.array([object()] * 3), allow_pickle=True)
    with pytest.raises(UsageError, match="our_vab_data.npy is not a plain array file"):
        WordVectorizer(glove)


def test_t2m_missing_files_name_the_argument(t2m_files, tmp_path):
    from omg.models.t2m import load_t2m_evaluator

    f = t2m_files
    with pytest.raises(UsageError, match="checkpoint=.*finest.tar"):
        load_t2m_evaluator(tmp_path / "finest.tar", f["glove"], f["meta"])
    with pytest.raises(UsageError, match="glove_dir=.*our_vab_data.npy"):
        load_t2m_evaluator(f["ckpt"], tmp_path, f["meta"])
    with pytest.raises(UsageError, match="mean_std_dir="):
        load_t2m_evaluator(f["ckpt"], f["glove"], tmp_path)
    torch.save({"movement_encoder": {}}, tmp_path / "other.tar")
    with pytest.raises(UsageError, match="lacks 'text_encoder'"):
        load_t2m_evaluator(tmp_path / "other.tar", f["glove"], f["meta"])
