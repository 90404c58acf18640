"""OmniMotionGPT: primal-joint pooling, the two autoencoders, the end-effector loss, subject
substitution, `omg fit` + `omg generate` from a real BVH, and the OMG -> OmniMotionGPT chain."""

from __future__ import annotations

import json
import re
import sys

import numpy as np
import pytest
import torch

from helpers import REPO, TINY_DIT
from helpers.checkpoints import save_module
from helpers.omgpt import MINI, TINY, fit_config, human_batch, paired, tiny_module
from helpers.omgpt import data as _data
from omg.errors import UsageError
from omg.lit.sampling import SamplingSettings, sampler_of
from omg.models.omgpt import OmniMotionConfig, OmniMotionGPT, end_effector_velocity, primal_joints
from omg.motion import get_representation
from omg.rotations import quat_normalize, quat_to_6d
from omg.skeleton import SMAL35, SMPL22
from omg.text.omgpt import find_animal, to_animal, to_person

# the tests share the mini OmniMotionGPT fit (omgpt_ckpt): under xdist they run on one worker, which fits it once
pytestmark = pytest.mark.xdist_group("omgpt")


def test_primal_joints_come_from_the_graph_with_the_semantic_pairing():
    assert primal_joints(SMPL22) == SMPL22.primal_joints == (0, 10, 11, 15, 20, 21, 9)
    assert primal_joints(SMAL35) == SMAL35.primal_joints == (0, 20, 24, 16, 10, 14, 6)
    names = [(SMPL22.names[h], SMAL35.names[a]) for h, a in zip(primal_joints(SMPL22), primal_joints(SMAL35))]
    assert names == [("pelvis", "pelvis"), ("left_foot", "LFootBack"), ("right_foot", "RFootBack"), ("head", "Head"),
                     ("left_wrist", "LFoot"), ("right_wrist", "RFoot"), ("spine3", "spine3")]


def test_pooling_shapes_and_unpooling_zeros_exactly_the_non_primal_joints():
    torch.manual_seed(0)
    config = OmniMotionConfig.from_name("paper")  # 196 frames -> 49 x 7 x 16
    model = OmniMotionGPT(SMPL22, SMAL35, config, text_dim=8)
    B, T = 2, 196
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[1, 150:] = False
    with torch.no_grad():
        z, z_mask = model.human["ae"].encode(torch.randn(B, T, 23 * 6), torch.randn(B, 22, 3), mask)
    assert z.shape == (B, 49, 7, 16) and z_mask.shape == (B, 49) and z_mask[1].sum() == 38
    for skeleton, ae in ((SMPL22, model.human["ae"]), (SMAL35, model.animal["ae"])):
        h = ae.unpool(z + 1.0, 196)  # (B, 196, J + 1, 16)
        assert h.shape == (B, 196, skeleton.num_joints + 1, 16)
        nonzero = (h != 0).any(-1).any(0).any(0)
        assert nonzero.nonzero().squeeze(1).tolist() == sorted(skeleton.primal_joints)
        torch.testing.assert_close(h[:, 4:8, list(skeleton.primal_joints)], (z + 1.0)[:, 1:2].expand(-1, 4, -1, -1))


def test_latent_decoder_predicts_each_frame_from_the_text_and_the_frames_before_it():
    """With ``latent_shift`` (omg's variant) D_t is a GPT over latent frames: frame t never reads input frame t
    (else it learns to copy Z and ignore C, the collapse of the first mini runs), and the sentence feature changes
    every frame."""
    from omg.models.omgpt import LatentTextDecoder

    torch.manual_seed(0)
    decoder = LatentTextDecoder(OmniMotionConfig.from_name("mini", joint_dim=4, latent_shift=True), text_dim=8).eval()
    z, mask, text = torch.randn(2, 6, 7, 4), torch.ones(2, 6, dtype=torch.bool), torch.randn(2, 8)
    with torch.no_grad():
        out = decoder(text, z, mask)
        changed = z.clone()
        changed[:, 3] += 1.0
        after = decoder(text, changed, mask)
        other_text = decoder(torch.randn(2, 8), z, mask)
    torch.testing.assert_close(after[:, :4], out[:, :4])  # frames 0..3 do not read input frame 3
    assert (after[:, 4:] - out[:, 4:]).abs().amax() > 1e-3
    assert ((other_text - out).abs().flatten(2).amax(-1) > 1e-3).all()  # C reaches every frame


def test_autoencoders_read_standardised_features():
    """Raw maa is mostly near-constant 6D numbers: in raw units an autoencoder that outputs the
    mean pose reaches a small loss (the first mini runs: local joint error no better than the
    mean pose). The autoencoders standardise inside and the reconstruction losses compare
    standardised features; the root's ground position becomes per-frame displacement in metres
    per second (``config.root_velocity``), summed back exactly on the way out."""
    from omg.lit.omgpt import OmniMotionModule

    animal = _data(MINI / "animal_maa/train")
    module = OmniMotionModule(human_data=dict(train=str(MINI / "human_maa/train"), batch_size=4, num_workers=0),
                              flavor="mini", config={**TINY, "root_velocity": True}, text_encoder="hash",
                              spec=animal.spec, ema_decay=0, standardize=True)
    std, mean = torch.tensor(animal.spec.std), torch.tensor(animal.spec.mean)
    ae = module.model.animal["ae"]
    D = len(std)
    ground = torch.zeros(D, dtype=torch.bool)
    ground[[D - 6, D - 4]] = True
    torch.testing.assert_close(ae.feature_scale[~ground], std.clamp_min(0.05)[~ground])
    torch.testing.assert_close(ae.feature_mean[~ground], mean[~ground])
    assert (ae.feature_mean[ground] == 0).all() and torch.allclose(ae.feature_scale[ground], torch.tensor(1 / 20.0))

    batch = next(iter(animal.train_dataloader()))
    motion, mask = module.raw(batch, "animal"), batch["mask"]
    internal = ae.normalize(motion, mask)
    torch.testing.assert_close(ae.denormalize(internal, mask), motion, atol=1e-5, rtol=1e-5)
    assert (internal[~mask] == 0).all()
    walk = torch.zeros(1, 10, D)
    walk[0, :, D - 4] = torch.arange(10) * 0.05  # 1 m/s along z at 20 fps
    step = ae.normalize(walk + mean * ~ground, torch.ones(1, 10, dtype=torch.bool))[0, 1:, D - 4]
    torch.testing.assert_close(step, torch.ones(9))
    flat = OmniMotionModule(human_data=dict(train=str(MINI / "human_maa/train"), batch_size=4, num_workers=0),
                            flavor="mini", config={**TINY, "root_velocity": False}, text_encoder="hash",
                            spec=animal.spec, ema_decay=0, standardize=True)
    torch.testing.assert_close(flat.model.animal["ae"].feature_scale, std.clamp_min(0.05))
    raw = OmniMotionModule(human_data=dict(train=str(MINI / "human_maa/train"), batch_size=4, num_workers=0),
                           flavor="mini", config={**TINY, "root_velocity": False}, text_encoder="hash",
                           spec=animal.spec, ema_decay=0, standardize=False)
    assert (raw.model.human["ae"].feature_scale == 1).all() and (raw.model.human["ae"].feature_mean == 0).all()


def test_module_defaults_are_the_paper_and_the_variant_is_its_config():
    """Built with no arguments but its data, ``OmniMotionModule`` and its networks are the paper's (§3.1): raw maa
    in and out, absolute root translation, D_t unshifted, retrieval as the evaluation protocol draws (32 nearest
    clips by similarity at 0.1). omg's variant is its config: configs/omgpt_variant.yaml and configs/mini/omgpt.yaml
    turn the three switches on, and configs/omgpt.yaml says the paper's values rather than inheriting them."""
    import dataclasses
    import inspect

    import yaml

    from omg.lit.omgpt import OmniMotionModule

    defaults = {k: p.default for k, p in inspect.signature(OmniMotionModule).parameters.items()}
    assert defaults["standardize"] is False
    assert dataclasses.asdict(defaults["source"]) == {
        "human_source": "retrieval", "retrieval_top_k": 32, "retrieval_draw": "similarity",
        "retrieval_temperature": 0.1, "retrieval_bank": None}
    paper = OmniMotionConfig()
    assert (paper.latent_shift, paper.root_velocity) == (False, False)
    assert OmniMotionConfig.from_name("mini").latent_shift is False  # a preset changes sizes, not the model
    animal = _data(MINI / "animal_maa/train")
    module = OmniMotionModule(human_data=dict(train=str(MINI / "human_maa/train"), batch_size=4, num_workers=0),
                              text_encoder="hash", spec=animal.spec)
    assert module.hparams["config"]["latent_shift"] is False and module.hparams["config"]["root_velocity"] is False
    assert module.model.animal["text_decoder"].shift is False
    for domain in ("human", "animal"):  # raw maa: the autoencoders' units are the features' own
        ae = getattr(module.model, domain)["ae"]
        assert (ae.feature_scale == 1).all() and (ae.feature_mean == 0).all()
    assert (module.retrieval_top_k, module.retrieval_draw, module.retrieval_temperature) == (32, "similarity", 0.1)

    switches = ("latent_shift", "root_velocity", "standardize")

    def said(path):  # the three switches as the YAML itself sets them (None: not said)
        args = yaml.safe_load((REPO / path).read_text())["model"]["init_args"]
        return {k: (args.get("config") or {}).get(k, args.get(k)) for k in switches}

    assert said("configs/omgpt.yaml") == dict.fromkeys(switches, False)
    assert said("configs/omgpt_variant.yaml") == said("configs/mini/omgpt.yaml") == dict.fromkeys(switches, True)


def _known_motion(skeleton, T=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    J = skeleton.num_joints
    q = quat_normalize(torch.tensor([1.0, 0, 0, 0]) + 0.3 * torch.randn(1, T, J, 4, generator=g))
    root = torch.cumsum(0.05 * torch.randn(1, T, 3, generator=g), 1)
    features = torch.cat([quat_to_6d(q).flatten(2), root, torch.zeros(1, T, 3)], -1)
    return features, q, root


def test_end_effector_velocity_is_the_finite_difference_of_forward_kinematics():
    for skeleton in (SMPL22, SMAL35):
        features, q, root = _known_motion(skeleton)
        offsets = torch.as_tensor(skeleton.rest_offsets)[None] * 1.3
        velocity = end_effector_velocity(get_representation("maa", skeleton), features, offsets)
        joints = skeleton.forward_kinematics(q, root, offsets[:, None])[..., list(skeleton.end_effectors), :]
        torch.testing.assert_close(velocity, joints[:, 1:] - joints[:, :-1], atol=1e-5, rtol=1e-4)


CAPTIONS = [
    ("a person walks forward.", "dog", "a dog walks forward."),
    ("The man turns around and he waves his right arm.", "horse", "A horse turns around and it waves its right arm."),
    ("someone jumps twice", "cat", "a cat jumps twice"),
    ("she kicks with her left leg", "elephant", "an elephant kicks with its left leg"),
    ("a young woman dances happily.", "dog", "a dog dances happily."),
    ("person runs in a circle", "fox", "a fox runs in a circle"),
    ("jumps up and down", "dog", "a dog jumps up and down"),
    ("the figure crawls on all fours", "cow", "a cow crawls on all fours"),
]


@pytest.mark.parametrize("caption, animal, expected", CAPTIONS)
def test_subject_substitution(caption, animal, expected):
    assert to_animal(caption, animal) == expected


def test_animal_captions_made_about_a_person_and_animals_found():
    animals = ["dog", "horse", "cat", "cow"]
    assert to_person("a dog jumps over a log", animals) == "a person jumps over a log"
    assert to_person("The big horse gallops and shakes its head.", animals) == "A person gallops and shakes their head."
    assert find_animal("two cats walk past a dog", animals) == "cat"
    assert find_animal("a person walks", animals) is None


def test_autoencoders_reconstruct_a_fixed_batch_of_both_domains():
    torch.manual_seed(0)
    animal_data = _data(MINI / "animal_maa/train")
    module = tiny_module(animal_data.spec)
    batches = {"animal": next(iter(animal_data.train_dataloader())), "human": human_batch()}
    optimizer = torch.optim.Adam(module.model.parameters(), lr=3e-3)
    history = []
    for _ in range(50):
        loss = 0.0
        for domain, batch in batches.items():
            text = module.sentence(batch["text"])
            parts, _, _ = module.domain_losses(domain, module.raw(batch, domain), batch["offsets"], batch["mask"],
                                               text, torch.ones(len(text), dtype=torch.bool))
            loss = loss + parts["jrec"] + parts["translation"]
        history.append(loss.item())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert np.isfinite(history).all() and history[-1] < history[0] / 10


# -- the commands ------------------------------------------------------------------------------

def _cli(*argv):
    from omg.cli import main

    main(list(argv))


def _bvh_offsets(path):
    """Joint name -> OFFSET from a BVH hierarchy, read with a few regular expressions."""
    text = path.read_text().split("MOTION")[0]
    found = re.findall(r"(?:ROOT|JOINT)\s+(\S+)\s*\{\s*OFFSET\s+(\S+)\s+(\S+)\s+(\S+)", text)
    return {name: np.array([float(x), float(y), float(z)]) for name, x, y, z in found}


def test_fit_then_generate_an_animal_from_a_real_bvh(omgpt_ckpt, shared_motion, tmp_path, capsys):
    from omg.lit.checkpoint import load_module

    clips = json.loads((shared_motion / "manifest.json").read_text())["clips"]
    bvh = next(shared_motion / c["path"] for c in clips if c.get("domain") == "human" and c["path"].endswith(".bvh"))
    module = load_module(omgpt_ckpt)
    assert set(module.animal_names) == {"cat", "cow", "deer", "dog", "fox", "horse", "sheep"}
    # the checkpoint holds every network field, resolved (a later default cannot change what it means)
    resolved = OmniMotionConfig.from_name("mini", **fit_config())
    assert resolved.latent_shift and resolved.root_velocity  # configs/mini/omgpt.yaml's variant, at TINY's sizes
    assert module.hparams["config"] == {f: getattr(resolved, f) for f in resolved.__dataclass_fields__ if f != "name"}
    out = tmp_path / "dog"
    _cli("generate", "a dog jumps over a log", "--ckpt", str(omgpt_ckpt), "--animal", "dog", "--from_motion", str(bvh),
         "--length", "2", "--out", str(out))
    settings = json.loads((out / "generation.json").read_text())
    assert settings["samples"][0]["animal"] == "dog" and settings["frames"] == 40
    assert np.load(out / "sample_000.features.npy").shape == (40, 36 * 6)
    assert np.load(out / "sample_000.joints.npy").shape == (40, 35, 3)
    assert (out / "preview.gif").stat().st_size > 0
    offsets = _bvh_offsets(out / "sample_000.bvh")
    dog = module.animals["dog"].numpy()
    assert set(offsets) == set(SMAL35.names)
    for j, name in enumerate(SMAL35.names[1:], start=1):
        np.testing.assert_allclose(np.linalg.norm(offsets[name]), np.linalg.norm(dog[j]), atol=1e-4)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        _cli("generate", "a unicorn jumps", "--ckpt", str(omgpt_ckpt), "--animal", "unicorn", "--from_motion",
             str(bvh), "--out", str(tmp_path / "bad"))
    assert exit_.value.code == 2 and not (tmp_path / "bad").exists()
    assert capsys.readouterr().err.strip() == ("omg: error: unknown animal 'unicorn'; this checkpoint knows: cat, cow, "
                                               "deer, dog, fox, horse, sheep")


def test_generated_animals_land_on_the_users_rig(omgpt_ckpt, shared_motion, tmp_path):
    """--to_rig and --format glb reach OmniMotionGPT's writer: the BVH holds the dog rig's joints and
    follows the generated joints (onto_rig of sample_NNN.joints.npy), and the .glb is written."""
    import bvh as bvh_reader

    from helpers import DOG_RIG, rig_bvh
    from omg.retarget import onto_rig, read_rig

    clips = json.loads((shared_motion / "manifest.json").read_text())["clips"]
    human = next(shared_motion / c["path"] for c in clips if c.get("domain") == "human" and c["path"].endswith(".bvh"))
    rig_path = tmp_path / "my_dog.bvh"
    rig_path.write_text(rig_bvh(DOG_RIG))
    for fmt in ("bvh", "glb"):
        out = tmp_path / fmt
        _cli("generate", "a dog walks", "--ckpt", str(omgpt_ckpt), "--from_motion", str(human), "--length", "1",
             "--to_rig", str(rig_path), "--format", fmt, "--no_preview", "--out", str(out))
        assert json.loads((out / "generation.json").read_text())["to_rig"] == str(rig_path)
        assert (out / f"sample_000.{fmt}").stat().st_size > 0
    written = bvh_reader.Bvh((tmp_path / "bvh/sample_000.bvh").read_text())
    rig = read_rig(rig_path, "smal35")
    assert written.get_joints_names() == rig.names and written.nframes == 20
    from omg.io.bvh import read_bvh

    joints = np.load(tmp_path / "bvh/sample_000.joints.npy")
    expected = onto_rig(joints, "smal35", rig, 20).positions()  # the generated motion, on the rig
    assert np.abs(read_bvh(tmp_path / "bvh/sample_000.bvh").positions() - expected).max() < 1e-3


@pytest.fixture(scope="session")
def tiny_controlnet(tmp_path_factory):
    """A ControlNet of 2 steps on a tiny DiT of 2 steps (mini humans, hash text): the human generator of the chain
    and of the evaluation."""
    import lightning as L

    from omg.lit.controlnet import ControlNetModule
    from omg.lit.pretrain import PretrainModule

    root = tmp_path_factory.mktemp("controlnet")
    torch.manual_seed(0)
    human = _data(MINI / "human263/train", max_len=40)
    trainer_args = dict(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, default_root_dir=root)
    pretrain = PretrainModule(flavor="mini", dit=TINY_DIT, spec=human.spec, ema_decay=0, optim={"warmup_steps": 1})
    trainer = L.Trainer(max_steps=2, **trainer_args)
    trainer.fit(pretrain, human)
    trainer.save_checkpoint(root / "pretrain.ckpt")
    controlnet = ControlNetModule(pretrained=str(root / "pretrain.ckpt"), text_encoder="hash",
                                  moc={"d_c": 16, "num_experts": 2}, spec=human.spec, ema_decay=0,
                                  optim={"warmup_steps": 1})
    trainer = L.Trainer(max_steps=2, **trainer_args)
    trainer.fit(controlnet, _data(MINI / "human263/train", max_len=40))
    trainer.save_checkpoint(root / "controlnet.ckpt")
    return root / "controlnet.ckpt"


def test_omg_controlnet_to_omnimotiongpt_chain(omgpt_ckpt, tiny_controlnet, tmp_path):
    from omg.lit.controlnet import ControlNetModule

    out = tmp_path / "chain"
    _cli("generate", "a horse jumps forward", "--ckpt", str(omgpt_ckpt),
         "--human_ckpt", str(tiny_controlnet), "--length", "1.5", "--num_samples", "2", "--steps", "3",
         "--out", str(out))
    settings = json.loads((out / "generation.json").read_text())
    assert [s["animal"] for s in settings["samples"]] == ["horse", "horse"]
    assert settings["samples"][0]["human_prompt"] == "a person jumps forward"
    human_joints = np.load(out / "sample_000.human.joints.npy")
    assert human_joints.shape == (30, 22, 3) and np.isfinite(human_joints).all()
    assert np.load(out / "sample_001.joints.npy").shape == (30, 35, 3)

    # a human generator at another frame rate: the same duration at its rate, resampled to the animal model's
    from dataclasses import replace

    from omg.lit.checkpoint import load_module
    from omg.lit.human_source import generate_human
    from omg.motion.maa import maa_from_positions

    generator = load_module(tiny_controlnet, expect=ControlNetModule)
    generator.spec = replace(generator.spec, fps=40.0)  # as if trained on 40 fps shards
    prompts, lengths = ["a person jumps forward"], torch.tensor([30])
    human, _ = generate_human(generator, prompts, lengths, 20.0, SamplingSettings(seed=7, steps=3))
    own = generator.sample(prompts, [59], SamplingSettings(seed=7, use_ema=False, steps=3))
    own = generator.representation.decode(own.float())
    expected, _ = maa_from_positions(own[0, ::2].numpy(), 20.0)  # 40 -> 20 fps: every other frame, 1.5 s
    assert human.shape == (1, 30, 23 * 6)
    torch.testing.assert_close(human[0], torch.from_numpy(expected), atol=1e-5, rtol=1e-4)


SMALL_EVAL = {"num_prompts": 8, "replications": 2, "mm_prompts": 2, "mm_repeats": 3, "steps": 2,
              "metrics": ["fid", {"r_precision": {"pool_size": 4}}, "mm_dist", {"diversity": {"num_pairs": 4}},
                          {"multimodality": {"num_pairs": 2}}]}


@pytest.fixture(scope="session")
def small_eval(tmp_path_factory):
    """configs/mini/omgpt_eval.yaml scaled down (SMALL_EVAL, 2 generator steps) with an untrained animal evaluator
    (hash text); its path and the evaluator's."""
    import yaml

    from omg.lit.evaluator import EvaluatorModule

    root = tmp_path_factory.mktemp("omgpt_eval")
    torch.manual_seed(0)
    evaluator = EvaluatorModule(text_encoder="hash", flavor="mini", spec=_data(MINI / "animal_maa/val").spec)
    evaluator_path = root / "evaluator.ckpt"
    save_module(evaluator, evaluator_path)
    config = yaml.safe_load((REPO / "configs/mini/omgpt_eval.yaml").read_text())
    for callback in config["trainer"]["callbacks"]:
        if "evaluator" in callback["init_args"]:
            callback["init_args"].update({**SMALL_EVAL, "evaluator": str(evaluator_path)})
    path = root / "eval.yaml"
    path.write_text(yaml.safe_dump(config))
    return path, evaluator_path


def test_evaluation_starts_from_generated_human_motion_by_default():
    """The paper's tables start from human motion sampled from a generative model (Fig. 2c): both evaluation
    configs name an OMG ControlNet checkpoint, the one docs/families/ trains (mini: the quick start's), as
    model.init_args.source.human_source; retrieval is the named overlay, whose bank is never the prompts' split."""
    from helpers.configs import parse

    mini, full = parse(REPO / "configs/mini/omgpt_eval.yaml"), parse(REPO / "configs/omgpt_eval.yaml")
    for evaluation, generator in ((mini, "mini/controlnet.yaml"), (full, "controlnet_base.yaml")):
        root = parse(REPO / "configs" / generator).trainer.default_root_dir
        assert evaluation.model.init_args.source.human_source == f"{root}/checkpoints/last.ckpt"
    assert all(c.init_args.steps == 20 for c in mini.trainer.callbacks if "steps" in c.init_args)
    for overlay, evaluation in (("mini/omgpt_eval_retrieval.yaml", mini), ("omgpt_eval_retrieval.yaml", full)):
        source = parse(REPO / "configs" / overlay).model.init_args.source
        prompts = {c.init_args.prompts for c in evaluation.trainer.callbacks
                   if c.class_path.endswith("OODEvalCallback")}
        assert source.human_source == "retrieval" and source.retrieval_bank.endswith("/train")
        assert prompts and source.retrieval_bank not in prompts


def test_retrieval_never_starts_a_generation_from_the_prompts_own_clip(omgpt_ckpt, small_eval, tmp_path, capsys):
    """`omg test` with the retrieval overlay and a bank that holds the OOD prompts' own clips (the human validation
    split, beside the training split): every clip captioned by a prompt is left out, and no OOD generation starts
    from its prompt's own clip (drawn from, the own clip is the nearest: hash text gives the same caption
    similarity 1). The bank the checkpoint keeps is that split alone: one line. An ID prompt's own clip is an
    animal's, which a human bank cannot hold (an smal35 bank is one line)."""
    path, _ = small_eval
    overlay = REPO / "configs/mini/omgpt_eval_retrieval.yaml"
    both = "[shards/mini/human_maa/train, shards/mini/human_maa/val]"
    _cli("test", "--config", str(path), "--config", str(overlay), "--ckpt_path", str(omgpt_ckpt),
         "--trainer.enable_progress_bar=false", f"--trainer.default_root_dir={tmp_path / 'eval'}",
         f"--model.init_args.source.retrieval_bank={both}")
    capsys.readouterr()
    run = next((tmp_path / "eval").glob("version_*"))
    settings = json.loads((run / "eval_ood.json").read_text())["settings"]
    # 10 validation clips, and 2 training clips that share a caption with one of them
    assert (settings["human_source"], settings["retrieval_excluded"], settings["retrieval_clips"]) == ("retrieval", 12,
                                                                                                       88)
    assert settings["generations"] == 2 * (8 + 2 * 3) and settings["from_prompt_clip"] == 0

    for extra, message in (
        (["--model.init_args.source.retrieval_bank=null"],
         "omg: error: OODEvalCallback: every clip retrieval draws from (the human validation clips kept in the "
         "checkpoint) is captioned by one of the prompts; set model.init_args.source.retrieval_bank"),
        (["--model.init_args.source.retrieval_bank=shards/mini/animal_maa/val"],
         "omg: error: model.init_args.source.retrieval_bank: the checkpoint's human data and its shards differ:"),
        ([f"--model.init_args.source.human_source={tmp_path}/missing.ckpt"],
         f"omg: error: model.init_args.source.human_source: no OMG ControlNet checkpoint at {tmp_path}/missing.ckpt"),
    ):
        with pytest.raises(SystemExit) as exit_:
            _cli("test", "--config", str(path), "--config", str(overlay), "--ckpt_path", str(omgpt_ckpt),
                 "--trainer.enable_progress_bar=false", f"--trainer.default_root_dir={tmp_path / 'bad'}", *extra)
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1 and err.startswith(message), err
    assert not (tmp_path / "bad").exists()


def test_omg_test_prints_the_id_and_ood_tables(omgpt_ckpt, tiny_controlnet, small_eval, tmp_path, capsys):
    """`omg test` with configs/mini/omgpt_eval.yaml (scaled down): ID and OOD reports from an animal evaluator, the
    human motion from the ControlNet the config names (here the tiny one)."""
    import yaml

    path, evaluator_path = small_eval
    _cli("test", "--config", str(path), "--ckpt_path", str(omgpt_ckpt), "--trainer.enable_progress_bar=false",
         f"--trainer.default_root_dir={tmp_path / 'eval'}", f"--model.init_args.source.human_source={tiny_controlnet}")
    printed = capsys.readouterr().out
    assert "OOD prompts" in printed and "| fid_ood |" in printed and "| r_precision/top1 |" in printed
    run = next((tmp_path / "eval").glob("version_*"))
    in_distribution = json.loads((run / "eval.json").read_text())["metrics"]
    ood = json.loads((run / "eval_ood.json").read_text())
    assert {"fid", "r_precision/top1", "mm_dist", "diversity", "multimodality"} <= set(in_distribution)
    assert {"fid_ood", "r_precision/top3", "diversity"} <= set(ood["metrics"]) and "fid" not in ood["metrics"]
    assert len(ood["metrics"]["fid_ood"]["values"]) == 2 and ood["settings"]["protocol"] == "OOD"
    assert ood["settings"]["human_source"] == str(tiny_controlnet) and ood["settings"]["sampling_steps"] == 2
    sides = json.loads((run / "eval_sides.json").read_text())["sides"]  # SideTransferCallback, in the same run
    assert "One-sided human actions made into animals" in printed and sides["dog/leg"]["clips"] > 10
    small = {**SMALL_EVAL, "evaluator": str(evaluator_path)}

    # the paper's self-evaluation: configs/mini/omgpt_self_eval.yaml over the same config
    overlay = yaml.safe_load((REPO / "configs/mini/omgpt_self_eval.yaml").read_text())
    overlay["trainer"]["default_root_dir"] = str(tmp_path / "self_eval")
    for callback in overlay["trainer"]["callbacks"]:
        assert callback["init_args"]["evaluator"]["class_path"] == "omg.lit.evaluator.OmniMotionSelfEvaluator"
        callback["init_args"].update({**small, "evaluator": {**callback["init_args"]["evaluator"],
                                                             "init_args": {"checkpoint": str(omgpt_ckpt)}}})
    (tmp_path / "self_eval.yaml").write_text(yaml.safe_dump(overlay))
    _cli("test", "--config", str(path), "--config", str(tmp_path / "self_eval.yaml"), "--ckpt_path", str(omgpt_ckpt),
         "--trainer.enable_progress_bar=false", f"--model.init_args.source.human_source={tiny_controlnet}")
    run = next((tmp_path / "self_eval").glob("version_*"))
    for report in ("eval.json", "eval_ood.json"):
        assert json.loads((run / report).read_text())["settings"]["evaluator"] == "OmniMotionSelfEvaluator"


def test_sigterm_during_the_evaluation_ends_it_in_one_line(omgpt_ckpt, tiny_controlnet, small_eval, tmp_path, capsys):
    """SIGTERM while `omg test` evaluates: Lightning's handler only sets a flag that no step reads, and the
    protocol's replications ran on to their end (a 5-replication mini evaluation went on for minutes). It ends
    at the next batch with omg's line, exit 143, and writes no report."""
    import yaml

    path, _ = small_eval
    config = yaml.safe_load(path.read_text())
    config["trainer"]["callbacks"].insert(0, {"class_path": "helpers.faults.SigtermAtTestEnd"})
    (tmp_path / "eval.yaml").write_text(yaml.safe_dump(config))
    with pytest.raises(SystemExit) as stop:
        _cli("test", "--config", str(tmp_path / "eval.yaml"), "--ckpt_path", str(omgpt_ckpt),
             "--trainer.enable_progress_bar=false", f"--trainer.default_root_dir={tmp_path / 'eval'}",
             f"--model.init_args.source.human_source={tiny_controlnet}")
    err = capsys.readouterr().err
    assert stop.value.code == 143, err[-2000:]
    assert [ln for ln in err.splitlines() if ln.startswith("omg:") and "interrupted" in ln] == [
        "omg: interrupted by SIGTERM during the evaluation; no report was written"], err[-2000:]
    assert "omg: evaluation replication 1/" not in err
    assert not list((tmp_path / "eval").rglob("eval*.json"))


@pytest.mark.parametrize("extra, message", [
    (["--animal", "dog", "--from_motion", "{tmp}/missing.bvh"], "--from_motion {tmp}/missing.bvh: no such file"),
    (["--animal", "dog", "--from_motion", "x.bvh", "--human_ckpt", "y.ckpt"], "give --from_motion"),
    ([], "the prompt 'a unicorn jumps' names no animal this checkpoint knows; pass --animal (known: cat, cow, deer, "
         "dog, fox, horse, sheep)"),
])
def test_bad_animal_generation_input_is_one_line(omgpt_ckpt, tmp_path, capsys, extra, message):
    extra, message = [e.format(tmp=tmp_path) for e in extra], message.format(tmp=tmp_path)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        _cli("generate", "a unicorn jumps", "--ckpt", str(omgpt_ckpt), *extra, "--out", str(tmp_path / "out"))
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and message in err and not (tmp_path / "out").exists()


def test_animal_and_prompt_follow_one_rule_in_generate_and_sample(omgpt_ckpt, tmp_path):
    """`omg generate --animal cat "a dog ..."` and ``sample(animal="cat")`` both make the cat, from the prompt
    made about the cat, and the human prompt about a person; the prompt's own animal without --animal."""
    from omg.generation.read import read_human_motion
    from omg.lit.checkpoint import load_module

    rng = np.random.default_rng(0)
    joints = SMPL22.rest_positions()[None] + 0.02 * rng.standard_normal((30, 22, 3))
    np.save(tmp_path / "human.joints.npy", joints.astype(np.float32))
    out = tmp_path / "cat"
    _cli("generate", "a dog jumps over a log", "--ckpt", str(omgpt_ckpt), "--animal", "cat", "--from_motion",
         str(tmp_path / "human.joints.npy"), "--no_preview", "--out", str(out))
    record = json.loads((out / "generation.json").read_text())["samples"][0]
    assert (record["animal"], record["animal_prompt"], record["human_prompt"]) == (
        "cat", "a cat jumps over a log", "a person jumps over a log")
    module = load_module(omgpt_ckpt)
    sampler = sampler_of(module, "test")
    human, offsets = (torch.from_numpy(a)[None] for a in read_human_motion(tmp_path / "human.joints.npy", 20.0))
    weights = SamplingSettings(use_ema=False)
    sampled = sampler.sample(["a dog jumps over a log"], [30], weights, animal="cat", human=human,
                             human_offsets=offsets)
    np.testing.assert_allclose(sampled[0].numpy(), np.load(out / "sample_000.features.npy"), atol=1e-5)
    cat = module.translate(["a cat jumps over a log"], human, offsets, [30], ["cat"], use_ema=False)
    dog = module.translate(["a dog jumps over a log"], human, offsets, [30], ["dog"], use_ema=False)
    torch.testing.assert_close(sampled, cat)
    torch.testing.assert_close(sampler.sample(["a dog jumps over a log"], [30], weights, human=human,
                                             human_offsets=offsets), dog)
    with pytest.raises(UsageError, match="names no animal this checkpoint knows"):
        sampler.sample(["a unicorn jumps"], [30], human=human, human_offsets=offsets)


def test_generated_motion_depends_on_the_text_and_on_the_human_motion(omgpt_ckpt):
    """The sampling API keeps both inputs: the same human motion with two prompts, and two human
    motions with one prompt, give different animal motions (a path that drops C or Z^h gives exactly
    the same ones; 4 training steps say nothing about how much they should differ)."""
    from omg.lit.checkpoint import load_module

    sampler = sampler_of(load_module(omgpt_ckpt), "test")
    human = _data(MINI / "human_maa/train", max_len=40, min_len=32)
    batch = next(iter(human.train_dataloader()))
    motion = (batch["motion"] * torch.tensor(human.spec.std) + torch.tensor(human.spec.mean))[:2, :32]
    offsets, lengths = batch["offsets"][:2], torch.tensor([32, 32])
    same_motion = sampler.sample(["a dog walks forward", "a dog lies down"], lengths,
                                 human=motion[:1].expand(2, -1, -1), human_offsets=offsets[:1].expand(2, -1, -1))
    same_text = sampler.sample(["a dog walks forward"] * 2, lengths, human=motion, human_offsets=offsets)
    for pair in (same_motion, same_text):
        assert (pair[0] - pair[1]).square().mean().sqrt() > 1e-5


def test_self_evaluator_embeds_text_and_motion_in_one_space(omgpt_ckpt):
    from omg.evaluation import build_evaluator

    evaluator = build_evaluator({"class_path": "omg.lit.evaluator.OmniMotionSelfEvaluator",
                                 "init_args": {"checkpoint": str(omgpt_ckpt)}})
    from omg.data.datamodule import MotionDataModule

    samples = MotionDataModule(val=str(MINI / "animal_maa/val"), max_len=196).val_clips().samples[:3]
    T = max(len(s["motion"]) for s in samples)
    motion, mask = torch.zeros(3, T, 216), torch.zeros(3, T, dtype=torch.bool)
    for b, s in enumerate(samples):
        motion[b, : len(s["motion"])], mask[b, : len(s["motion"])] = torch.from_numpy(s["motion"]), True
    text = evaluator.encode_text([s["texts"][0] for s in samples])
    features = evaluator.encode_motion(motion, mask)
    assert text.shape == features.shape == (3, 64) and torch.isfinite(features).all()
    # unit vectors: E_t learns directions (a cosine loss), so distances between lengths would mean nothing
    torch.testing.assert_close(features.norm(dim=-1), torch.ones(3))
    torch.testing.assert_close(text.norm(dim=-1), torch.ones(3))
    module = evaluator.module
    z, z_mask = module.model.animal["ae"].encode(motion, evaluator.offsets.expand(3, -1, -1), mask)
    raw = module.model.animal["text_encoder"](z, z_mask)
    torch.testing.assert_close(features, raw / raw.norm(dim=-1, keepdim=True))  # E_t^a(E^a(P)), the paper's
    torch.testing.assert_close(evaluator.encode_motion(motion[:1, : mask[0].sum()], mask[:1, : mask[0].sum()]),
                               features[:1], atol=1e-4, rtol=1e-4)  # padding changes nothing


def test_generated_features_are_canonical_maa():
    from omg.models.omgpt import canonical_maa
    from omg.rotations import sixd_to_matrix

    features, _, _ = _known_motion(SMAL35)
    torch.testing.assert_close(canonical_maa(features), features, atol=1e-5, rtol=0)  # real maa is kept
    noise = torch.randn(features.shape, generator=torch.Generator().manual_seed(0))
    noisy = canonical_maa(features + 0.3 * noise)
    tokens = noisy.unflatten(-1, (-1, 6))
    assert torch.equal(tokens[..., -1, 3:], torch.zeros_like(tokens[..., -1, 3:]))
    m = sixd_to_matrix(tokens[..., :-1, :])
    torch.testing.assert_close(m.mT @ m, torch.eye(3).expand_as(m), atol=1e-5, rtol=0)
    # float32 round-off of a Gram-Schmidt pass: unseeded noise once gave 1.14e-6 on one of 2,520 numbers
    torch.testing.assert_close(tokens[..., :-1, :], torch.cat([m[..., 0], m[..., 1]], -1), atol=1e-5, rtol=0)


def _fit_omgpt(root, seen: dict, kill_at=None, resume=False):
    """A tiny OmniMotionGPT run of 7 steps on the mini sets; ``seen``: step -> the human clip ids it trained on."""
    import lightning as L

    from helpers.resume import run_until_killed
    from omg.lit.omgpt import OmniMotionModule

    class Recorded(OmniMotionModule):
        def training_losses(self, batch):
            seen[self.global_step] = tuple(batch["human"]["id"])
            return super().training_losses(batch)

    L.seed_everything(0, verbose=False)
    # the human stream turns epochs at other steps than the animal one
    data = paired(MINI / "animal_maa/train", human=dict(shuffle_buffer=8, batches_per_epoch=3), batches_per_epoch=4,
                  shuffle_buffer=8)
    model = Recorded(flavor="mini", config=TINY, text_encoder="hash", spec=data.spec, ema_decay=0.9, optim={"lr": 1e-3})
    run_until_killed(model, data, root, max_steps=7, kill_at=kill_at, resume=resume)


def test_a_killed_run_resumes_both_streams_exactly(tmp_path):
    """The human stream's position travels in the checkpoint beside the animal data's (the paired data module's
    combined loader: both streams' positions in Lightning's loop state): a run killed at step 5 and resumed
    trains on the same human clips, step for step, and ends bit-identical."""
    from helpers.resume import assert_identical

    full, killed = {}, {}
    _fit_omgpt(tmp_path / "full", full)
    _fit_omgpt(tmp_path / "killed", killed, kill_at=5)
    assert sorted(killed) == [0, 1, 2, 3, 4]
    _fit_omgpt(tmp_path / "killed", killed, resume=True)
    assert killed == full and sorted(full) == list(range(7))
    assert len(set(full.values())) > 3  # the stream moves on (and rolls over to its next epoch at step 3)
    state = {}
    for run in ("full", "killed"):
        ckpt = torch.load(tmp_path / run / "ckpt" / "last.ckpt", map_location="cpu", weights_only=False)
        state[run] = {"step": ckpt["global_step"], "weights": ckpt["state_dict"], "ema": ckpt["ema"],
                      "optimizer": ckpt["optimizer_states"], "fit_state": ckpt["fit_state"],
                      "streams": ckpt["loops"]["fit_loop"]["state_dict"]["combined_loader"]}
    assert_identical(state["killed"], state["full"])
    animal, human = state["full"]["streams"]
    assert (animal["epoch"], animal["batches_done"]) == (1, 3) and (human["epoch"], human["batches_done"]) == (2, 1)


@pytest.mark.parametrize("caption, expected", [
    ("a person kicks with the left leg.", ("leg", "left")),
    ("someone waves with their right hand", ("arm", "right")),
    ("The man punches twice with his right fist", ("arm", "right")),
    ("a man waves with both hands", None),
    ("a person turns left and walks", None),  # a side, but no limb
    ("the person raises the left arm and kicks with the right leg", None),  # both sides
    ("a person kicks and waves with the left side", None),  # a leg word and an arm word
])
def test_one_sided_limb_in_captions(caption, expected):
    from omg.text.omgpt import one_sided_limb

    assert one_sided_limb(caption) == expected


def _swinging(skeleton, limb_end: int, T: int = 40) -> torch.Tensor:
    """maa features (T, (J+1)·6): the rest pose with the joint two above ``limb_end`` swinging about X."""
    hip = skeleton.parents[skeleton.parents[limb_end]]
    q = torch.zeros(T, skeleton.num_joints, 4)
    q[..., 0] = 1.0
    angle = 0.6 * torch.sin(torch.linspace(0, 6 * np.pi, T))
    q[:, hip] = torch.stack([torch.cos(angle / 2), torch.sin(angle / 2), 0 * angle, 0 * angle], -1)
    return torch.cat([quat_to_6d(q).flatten(1), torch.zeros(T, 6)], -1)


@pytest.mark.parametrize("mirror", [False, True])
def test_side_transfer_counts_the_animal_limb_that_moves(omgpt_ckpt, mirror):
    """A stand-in translation that swings exactly the animal limb the caption names (or, mirrored,
    the other one) is kept on every clip (on none); a left-kick human clip moves its left foot most."""
    from omg.callbacks.omgpt import OTHER_SIDE, SideTransferCallback, limb_travel
    from omg.lit.checkpoint import load_module
    from omg.text.omgpt import one_sided_limb

    module = load_module(omgpt_ckpt)
    callback = SideTransferCallback(str(MINI / "human_maa/train"), animals=["dog", "horse"])
    clips = callback.clips()
    kick = next(s for t, limb, s in clips if limb == ("leg", "left"))
    travel = limb_travel(module.human_rep, torch.from_numpy(kick["motion"]), torch.tensor(kick["meta"]["offsets"]))
    assert travel["leg", "left"] > 1.5 * travel["leg", "right"]

    names = {("leg", "left"): "LFootBack", ("leg", "right"): "RFootBack", ("arm", "left"): "LFoot",
             ("arm", "right"): "RFoot"}  # an animal's hind feet are its legs, its front feet its arms
    ends = {limb: SMAL35.names.index(name) for limb, name in names.items()}

    def translate(texts, human, human_offsets, lengths, animals, use_ema=True):  # each row swings its caption's limb
        swinging = []
        for text in texts:
            kind, side = one_sided_limb(text)
            swinging.append(_swinging(SMAL35, ends[kind, OTHER_SIDE[side] if mirror else side], human.shape[1]))
        return torch.stack(swinging)

    module.translate = translate
    sides = callback.measure(module)  # 32 clips a call (64 rows of 2 animals), each trimmed back to its length
    consistent = 0  # captions whose human limb on the named side travels farther
    for _, (kind, side), s in clips:
        t = limb_travel(module.human_rep, torch.from_numpy(s["motion"]), torch.tensor(s["meta"]["offsets"]))
        consistent += t[kind, side] > t[kind, OTHER_SIDE[side]]
    assert sides["dog/leg"]["clips"] + sides["dog/arm"]["clips"] == consistent > 20
    for key, v in sides.items():
        assert v["kept"] == (0 if mirror else v["clips"]), key
    with pytest.raises(UsageError, match=r"SideTransferCallback.batch_size must be an integer >= 1, got 0$"):
        SideTransferCallback(str(MINI / "human_maa/train"), batch_size=0)


def old_layout(ckpt: dict, **hparams) -> dict:
    """A checkpoint as omg wrote it before the human stream was the data's: the fit-time state in the
    hyper-parameters (``hparams`` over them), the human stream's position as ``human_stream``."""
    loops = ckpt["loops"]["fit_loop"]["state_dict"]
    animal, human = loops["combined_loader"]
    old = {k: v for k, v in ckpt.items() if k != "fit_state"}
    old["hyper_parameters"] = {**ckpt["hyper_parameters"], **ckpt["fit_state"], **hparams}
    old["loops"] = {**ckpt["loops"], "fit_loop": {**ckpt["loops"]["fit_loop"],
                                                  "state_dict": {**loops, "combined_loader": [animal]}}}
    return {**old, "human_stream": human}


def test_a_checkpoint_never_opens_the_data_it_names(omgpt_ckpt, tmp_path, capsys):
    """An OmniMotionGPT checkpoint of the older layout kept its training run's human_data among its
    hyper-parameters (as it did its fit-time state and the human stream's position); one whose
    human_data names `pipe:` commands (here: creating a marker file) runs none of them through `omg generate`,
    `omg convert-ckpt` (nor the .safetensors it writes) or `omg fit --ckpt_path` (the run's config
    says where the human shards are: data.human), and a checkpoint moved where its human shards do not exist
    still generates: the human spec and the retrieval clips are inside it. Resumed, the older layout's human
    stream goes on from its position, in the paired data's loader state."""
    from safetensors import safe_open

    marker = tmp_path / "PWNED"
    ckpt = torch.load(omgpt_ckpt, map_location="cpu", weights_only=True)
    assert ckpt["hyper_parameters"]["human_data"] is None  # the run's human shards are its data's
    assert ckpt["datamodule_hyper_parameters"]["human"]["val"] == "shards/mini/human_maa/val"
    human = dict(ckpt["datamodule_hyper_parameters"]["human"])
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    variants = {
        "pipe": {split: f"pipe:touch {marker}; cat {REPO}/shards/mini/human_maa/{split}/manifest.json"
                 for split in ("train", "val")},
        "gone": {split: str(tmp_path / f"gone/{split}") for split in ("train", "val")},
    }
    for name, locations in variants.items():
        human_source = str(tmp_path / "gone/controlnet.ckpt") if name == "gone" else "retrieval"
        torch.save(old_layout(ckpt, human_data={**human, **locations}, human_source=human_source),
                   moved / f"{name}.ckpt")
        _cli("generate", "a dog jumps forward", "--ckpt", str(moved / f"{name}.ckpt"), "--length", "1",
             "--num_samples", "1", "--no_preview", "--out", str(tmp_path / f"gen_{name}"))
        assert np.load(tmp_path / f"gen_{name}/sample_000.joints.npy").shape == (20, 35, 3)
        assert not marker.exists(), name
    crafted = moved / "pipe.ckpt"

    _cli("convert-ckpt", str(crafted), str(tmp_path / "omgpt.safetensors"))
    with safe_open(tmp_path / "omgpt.safetensors", "pt") as f:
        assert "human_data" not in json.loads(f.metadata()["hyper_parameters"])  # the locations are not copied
    _cli("generate", "a dog jumps forward", "--ckpt", str(tmp_path / "omgpt.safetensors"), "--length", "1",
         "--num_samples", "1", "--no_preview", "--out", str(tmp_path / "gen_safetensors"))
    assert not marker.exists()

    saved = list(sys.argv)
    try:
        _cli("fit", "--config", str(REPO / "configs/mini/omgpt.yaml"), "--trainer.max_steps=5",
             f"--trainer.default_root_dir={tmp_path / 'resumed'}", "--trainer.enable_progress_bar=false",
             "--trainer.val_check_interval=100", "--trainer.enable_model_summary=false",
             "--data.batch_size=4", "--data.human.batch_size=4", f"--ckpt_path={crafted}",
             "--model.init_args.text_encoder=hash", f"--model.init_args.config={json.dumps(fit_config())}")
    finally:
        sys.argv[:] = saved
    resumed = torch.load(tmp_path / "resumed/checkpoints/last.ckpt", map_location="cpu", weights_only=True)
    assert resumed["global_step"] == 5 and resumed["datamodule_hyper_parameters"]["human"]["train"] == \
        "shards/mini/human_maa/train"  # the config's, not the file's
    assert not marker.exists()
    streams = resumed["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    saved = ckpt["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert (streams[1]["epoch"], streams[1]["batches_done"]) == (saved[1]["epoch"], saved[1]["batches_done"] + 1)
    assert resumed["fit_state"] == ckpt["fit_state"] and "human_stream" not in resumed


def test_an_old_layout_checkpoint_loads_and_generates_what_the_new_one_does(omgpt_ckpt, tmp_path):
    """The fit-time state (animals, human_spec, human_bank) is the checkpoint's ``fit_state``; a checkpoint that
    holds it in its hyper-parameters (omg's older layout) loads to the same state and generates the same motion,
    bit for bit (retrieval: the human spec, the kept clips and the animals' offsets all take part), as does the
    .safetensors file converted from it (its metadata carries the state)."""
    from omg.lit.checkpoint import load_module

    ckpt = torch.load(omgpt_ckpt, map_location="cpu", weights_only=True)
    assert set(ckpt["fit_state"]) == {"animals", "human_spec", "human_bank"}
    assert not set(ckpt["fit_state"]) & set(ckpt["hyper_parameters"])
    torch.save(old_layout(ckpt), tmp_path / "old.ckpt")
    new, old = load_module(omgpt_ckpt), load_module(tmp_path / "old.ckpt")
    assert old.fit_state() == new.fit_state() == ckpt["fit_state"]
    assert new.animal_names == sorted(ckpt["fit_state"]["animals"]) and {"dog", "horse"} <= set(new.animal_names)
    assert torch.equal(old.human_bank_motion, new.human_bank_motion) and torch.equal(old.human_mean, new.human_mean)
    _cli("convert-ckpt", str(omgpt_ckpt), str(tmp_path / "new.safetensors"), "--ema")  # the state travels too
    paths = {"new": omgpt_ckpt, "old": tmp_path / "old.ckpt", "safetensors": tmp_path / "new.safetensors"}
    for name, path in paths.items():
        _cli("generate", "a dog jumps forward", "a horse walks", "--ckpt", str(path), "--length", "1",
             "--num_samples", "2", "--seed", "3", "--no_preview", "--out", str(tmp_path / name))
    files = sorted(p.name for p in (tmp_path / "new").glob("*.npy"))
    for other in ("old", "safetensors"):
        assert len(files) >= 8 and files == sorted(p.name for p in (tmp_path / other).glob("*.npy"))
        for f in files:
            assert np.load(tmp_path / "new" / f).tobytes() == np.load(tmp_path / other / f).tobytes(), (other, f)


def test_the_older_human_data_key_is_read_as_data_human(tmp_path, capsys, monkeypatch):
    """configs written before the human shards were the data's name them ``model.init_args.human_data``: `omg fit`
    reads that as ``data.human`` (one warning line), the model built without them; both set is one line."""
    import yaml

    from omg.cli import main
    from omg.tools.lightning import OmgLightningCLI

    monkeypatch.setattr(sys, "argv", list(sys.argv))  # `omg fit` sets it for LightningCLI
    config = yaml.safe_load((REPO / "configs/mini/omgpt.yaml").read_text())
    human = config["data"].pop("human")
    config["model"]["init_args"]["human_data"] = human
    config["model"]["init_args"]["text_encoder"] = "hash"
    config["trainer"]["default_root_dir"] = str(tmp_path / "run")
    (tmp_path / "old.yaml").write_text(yaml.safe_dump(config))
    monkeypatch.chdir(REPO)
    with pytest.warns(UserWarning, match="model.init_args.human_data is read as data.human"):
        cli = OmgLightningCLI("fit", ["--config", str(tmp_path / "old.yaml"),
                                      f"--model.init_args.config={json.dumps(fit_config())}"])
    assert {k: v for k, v in cli.datamodule.hparams["human"].items()} == human
    assert cli.datamodule.human.spec.skeleton == "smpl22" and cli.model.hparams["human_data"] is None
    assert cli.config.data.clip_sampling == "whole"
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", str(tmp_path / "old.yaml"), "--data.human.batch_size=4"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.strip() == (
        "omg: error: model.init_args.human_data and data.human both name the human shards: keep data.human only "
        "(model.init_args.human_data is its older name)")
    assert not (tmp_path / "run").exists()
