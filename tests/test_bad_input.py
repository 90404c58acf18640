"""Bad input ends as one line on stderr (``omg: error: ...``), exit code 2, no traceback, and
leaves nothing behind: no output files, no empty folders, pre-existing folders untouched.

One table of bad invocations of ``omg generate``, ``export``, ``shards build|synth``, ``fit``
(the config file) and ``bench``, run in-process. The checkpoints are tiny and untrained: only
the argument handling is under test, so nothing needs training.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from helpers import BANDAI_RIG, DOG_RIG, REPO, TINY_BVH, TINY_DIT, rig_bvh
from helpers.checkpoints import save_module
from omg.cli import main
from omg.files import MOTION_MAX_BYTES
from omg.skeleton import SMPL22


@pytest.fixture(scope="session")
def ckpts(tmp_path_factory) -> dict[str, str]:
    """Untrained tiny checkpoints: unconditional, text-conditioned, one with NaN weights, a habit VQ-VAE,
    and an animal evaluator in a copy of the human evaluation config."""
    from omg.data.datamodule import MotionDataModule
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.evaluator import EvaluatorModule
    from omg.lit.habit import HabitVQModule
    from omg.lit.pretrain import PretrainModule

    root = tmp_path_factory.mktemp("bad_input_ckpts")

    def save(module, name):
        save_module(module, root / name)
        return str(root / name)

    torch.manual_seed(0)
    spec = MotionDataModule(str(REPO / "shards/mini/human263/train"), batch_size=2, num_workers=0).spec
    pre = PretrainModule(flavor="mini", dit=TINY_DIT, spec=spec, ema_decay=0)
    paths = {"pre": save(pre, "pre.ckpt")}
    cn = ControlNetModule(pretrained=paths["pre"], text_encoder="hash", moc={"d_c": 16, "num_experts": 2}, ema_decay=0)
    paths["cn"] = save(cn, "cn.ckpt")
    with torch.no_grad():
        for p in pre.parameters():
            p.fill_(float("nan"))
    paths["nanck"] = save(pre, "nan.ckpt")
    animal_spec = MotionDataModule(str(REPO / "shards/mini/animal_quatvel/train"), batch_size=2, num_workers=0).spec
    habit = HabitVQModule(["dog", "horse"], flavor="tiny", text_encoder="hash", spec=animal_spec)
    paths["habit"] = save(habit, "habit.ckpt")
    maa_spec = MotionDataModule(str(REPO / "shards/mini/animal_maa/train"), batch_size=2, num_workers=0).spec
    evaluator = EvaluatorModule(flavor="mini", evaluator={"n_layers": 1, "d_model": 64, "embed_dim": 64},
                                text_encoder="hash", spec=maa_spec)
    config = (REPO / "configs/mini/eval.yaml").read_text().replace("runs/mini_evaluator/checkpoints/last.ckpt",
                                                                   save(evaluator, "animal_evaluator.ckpt"))
    (root / "eval_animal_evaluator.yaml").write_text(config.replace("shards/mini", str(REPO / "shards/mini")))
    paths["eval_animal"] = str(root / "eval_animal_evaluator.yaml")
    return paths


def _write_inputs(d: Path, out: Path) -> None:
    """Small bad (and good) input files, fresh for every row."""
    rng = np.random.default_rng(0)
    d.mkdir()
    (d / "latin1.txt").write_bytes("a person walks to the caf\u00e9\n".encode("latin-1"))
    (d / "elf.bin").write_bytes(b"\x7fELF\x02\x01\x01\x00\xff\xfe" + rng.bytes(2000))  # like /bin/ls
    (d / "random.bin").write_bytes(b"\x81\xff" + rng.bytes(2000))
    (d / "nul.txt").write_bytes(b"\x00" * 64 + b"\n")  # valid UTF-8, still binary
    (d / "afile").write_text("a file, not a folder\n")
    (d / "timeline.json").write_text('[{"start": 0, "end": 1, "text": "a person walks"}]')
    torch.save({"state_dict": {"w": torch.zeros(2)}}, d / "bare.ckpt")  # weights without hyper-parameters
    (d / "latin1.yaml").write_bytes("trainer:\n  default_root_dir: caf\u00e9\n".encode("latin-1"))
    (d / "nan.yaml").write_text(f"source: synth\nout: {out}\nfps: .nan\noption: {{num_clips: 2}}\n")
    (d / "list_out.yaml").write_text("source: synth\nout: [1, 2]\n")
    (d / "syntax.yaml").write_text("trainer:\n  max_steps: 3\n  devices: [1, 2\nmodel: x\n")  # ] missing
    (d / "old_and_new_lr.yaml").write_text("model:\n  init_args:\n    lr: 1.0e-3\n    optim:\n      lr: 2.0e-3\n")
    (d / "empty.yaml").write_text("")
    animals = REPO / "shards/mini/animal_maa/train"
    (d / "mix_negative.yaml").write_text(f"data:\n  train:\n    - {{path: {MINI_SHARDS}, weight: -1}}\n")
    (d / "mix_unknown_key.yaml").write_text(f"data:\n  train:\n    - {{pat: {MINI_SHARDS}, weight: 1}}\n")
    (d / "mix_mismatched.yaml").write_text(f"data:\n  train:\n    - {{path: {MINI_SHARDS}, weight: 1}}\n"
                                           f"    - {{path: {animals}, weight: 1}}\n")
    np.save(d / "nan.npy", np.full((10, 245), np.nan, np.float32))  # quatvel features' shape on smal35
    np.save(d / "still.npy", np.zeros((10, 245), np.float32))  # a sound source
    os.mkfifo(d / "fifo.npy")
    shutil.copytree(MINI_VAL, d / "val_copy")  # the same clips as MINI_VAL
    (d / "bvh").mkdir()
    (d / "bvh/tiny.bvh").write_text(TINY_BVH)
    (d / "rigs").mkdir()  # --to_rig: a human rig, a dog rig, one without a rest pose, one without a hierarchy
    (d / "rigs/human.bvh").write_text(rig_bvh(BANDAI_RIG))
    (d / "rigs/dog.bvh").write_text(rig_bvh(DOG_RIG))
    (d / "rigs/flat.bvh").write_text(rig_bvh(BANDAI_RIG, zero=True))
    (d / "rigs/motion_only.bvh").write_text("MOTION\nFrames: 1\nFrame Time: 0.05\n0 0 0\n")
    (d / "rigs/garbage.glb").write_bytes(b"glTF\x02\0\0\0" + bytes(range(40)))
    (d / "rigs/truncated.gltf").write_text('{"asset": {"version": "2.0"}, "nodes": [')
    (d / "rigs/folder.bvh").mkdir()  # --to_rig: no regular file (a FIFO or /dev/zero: tests/test_user_files.py)
    (d / "rigs/null.bvh").symlink_to(os.devnull)
    with open(d / "rigs/huge.bvh", "wb") as f:  # sparse: one byte over the bound, no disk used
        f.truncate(MOTION_MAX_BYTES + 1)
    (d / "python_tag.yaml").write_text("model: !!python/object/apply:os.system ['echo pwned']\n")
    (d / "empty").mkdir()
    (d / "user").mkdir()
    (d / "user/keep.txt").write_text("the user's own file\n")

    positions = np.repeat(SMPL22.rest_positions()[None], 10, axis=0).astype(np.float32)
    settings = {"binary": None, "list": "[1, 2]", "types": '{"skeleton": 5}',
                "nan": '{"fps": NaN, "prompts": 5, "num_samples": -1}', "dir": None, "bvhdir": "{}"}
    (d / "joints").mkdir()  # a sound motion without settings, for the --to_rig rows
    np.save(d / "joints/still.joints.npy", positions)
    for name, text in settings.items():
        gen = d / f"gen_{name}"
        gen.mkdir()
        np.save(gen / "sample_000.joints.npy", positions)
        if text is not None:
            (gen / "generation.json").write_text(text)
    (d / "gen_binary/generation.json").write_bytes(b"\xff\xfe{\x00")
    (d / "gen_dir/generation.json").mkdir()
    (d / "gen_bvhdir/sample_000.bvh").mkdir()  # where the BVH file would go
    (d / "gen_glbdir/sample_000.glb").mkdir(parents=True)
    (d / "transfer_bvhdir/transfer.bvh").mkdir(parents=True)
    # SLURM requeue checkpoints (hpc_ckpt_N.ckpt in default_root_dir): one holding a pickled object
    # that a weights-only load refuses, and a torn one
    (d / "hpc_pickled").mkdir()
    torch.save({"state_dict": {}, "args": argparse.Namespace(lr=1.0)}, d / "hpc_pickled/hpc_ckpt_1.ckpt")
    (d / "hpc_torn").mkdir()
    torch.save({"state_dict": {"w": torch.zeros(4096)}}, d / "hpc_torn/hpc_ckpt_2.ckpt")
    (d / "hpc_torn/hpc_ckpt_2.ckpt").write_bytes((d / "hpc_torn/hpc_ckpt_2.ckpt").read_bytes()[:-2000])


# (id, argv); {in}: the input folder, {out}: a path that does not exist yet, {pre}/{cn}/{nanck}: checkpoints
GEN = ["generate", "--steps", "2", "--length", "1", "--num_samples", "1", "--no_preview"]
TEXT = [*GEN, "a person walks", "--ckpt", "{cn}", "--out", "{out}"]
UNCOND = [*GEN, "--unconditional", "--ckpt", "{pre}", "--out", "{out}"]
EXPORT = ["export", "{in}/gen_list/sample_000.joints.npy", "--no_preview"]  # no generation.json read: a plain file
RIG_EXPORT = ["export", "{in}/joints/still.joints.npy", "--no_preview"]  # a sound motion: only the rig is at fault
SYNTH_BUILD = ["shards", "build", "--source", "synth", "--out", "{out}", "--option.num_clips", "2"]
FIT = ["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), "--trainer.default_root_dir", "{out}"]
# small sizes: were a check missing, the benchmark would run (and fail or hang) quickly
BENCH_DATA = ["bench", "data", "--clips", "20", "--batch_size", "4", "--batches", "2", "--workers", "0"]
BENCH_TRAIN = ["bench", "train", "--steps", "1", "--warmup", "0", "--frames", "8", "--batch_size", "1"]
BENCH_SAMPLE = ["bench", "sample", "--steps", "1", "--frames", "8", "--batch_sizes", "[1]"]
MINI_SHARDS = str(REPO / "shards/mini/human263/train")
MINI_VAL = str(REPO / "shards/mini/human263/val")
TRANSFER = ["transfer", "--to", "horse", "--ckpt", "{habit}", "--no_preview"]
FIT_HABIT = ["fit", "--config", str(REPO / "configs/mini/habit_vqvae.yaml"), "--trainer.default_root_dir", "{out}",
             "--data.train", str(REPO / "shards/mini/animal_quatvel/train"),
             "--data.val", str(REPO / "shards/mini/animal_quatvel/val"), "--trainer.max_steps", "1"]
FIT_DATA = [*FIT, "--data.train", MINI_SHARDS, "--data.val", MINI_VAL,  # the config names them from the repo
            "--trainer.max_steps", "1"]  # were a check missing, the run would end soon
FIT_OMGPT = ["fit", "--config", str(REPO / "configs/mini/omgpt.yaml"), "--trainer.default_root_dir", "{out}",
             "--model.init_args.text_encoder", "hash", "--trainer.max_steps", "1",  # the config's sets, from the repo:
             "--data.train", str(REPO / "shards/mini/animal_maa/train"),
             "--data.val", str(REPO / "shards/mini/animal_maa/val"),
             "--data.human.train", str(REPO / "shards/mini/human_maa/train"),
             "--data.human.val", str(REPO / "shards/mini/human_maa/val")]
ROWS = [
    # omg generate
    ("gen-prompts-latin1", [*GEN, "--ckpt", "{cn}", "--out", "{out}", "--prompts_file", "{in}/latin1.txt"]),
    ("gen-prompts-binary", [*GEN, "--ckpt", "{cn}", "--out", "{out}", "--prompts_file", "{in}/elf.bin"]),
    ("gen-prompts-nul", [*GEN, "--ckpt", "{cn}", "--out", "{out}", "--prompts_file", "{in}/nul.txt"]),
    ("gen-prompt-lone-surrogate", [*GEN, "a person \ud800 walks", "--ckpt", "{cn}", "--out", "{out}"]),
    ("gen-prompt-c1-control", [*GEN, "a person\x85walks", "--ckpt", "{cn}", "--out", "{out}"]),
    ("gen-animal-control-character", [*TEXT, "--animal", "do\x07g"]),
    ("gen-prompts-dir", [*GEN, "--ckpt", "{cn}", "--out", "{out}", "--prompts_file", "{in}"]),
    ("gen-prompts-missing", [*GEN, "--ckpt", "{cn}", "--out", "{out}", "--prompts_file", "{in}/nope.txt"]),
    ("gen-length-nan", [*UNCOND, "--length", "nan"]),
    ("gen-length-inf", [*UNCOND, "--length", "inf"]),
    ("gen-length-neg", [*UNCOND, "--length", "-1"]),
    ("gen-guidance-nan", [*TEXT, "--guidance", "nan"]),
    ("gen-guidance-inf", [*TEXT, "--guidance", "inf"]),
    ("gen-guidance-overflow", [*TEXT, "--guidance", "1e308"]),
    ("gen-stance-root-2", [*TEXT, "--stance_root", "2"]),
    ("gen-stance-root-habit", ["generate", "--from_motion", "{in}/still.npy", "--animal", "horse", "--ckpt", "{habit}",
                               "--no_preview", "--out", "{out}", "--stance_root", "1"]),
    ("gen-option-unknown", [*UNCOND, "--option", "temperature=0.5"]),
    ("gen-option-no-value", [*TEXT, "--option", "stance_root"]),
    ("gen-option-habit-value", ["generate", "--from_motion", "{in}/still.npy", "--animal", "horse", "--ckpt",
                                "{habit}", "--no_preview", "--out", "{out}", "--option", "quantizer=best"]),
    ("gen-prior-on-omg", [*UNCOND, "--prior_ckpt", "{habit}"]),
    ("gen-device-banana", [*UNCOND, "--device", "banana"]),
    ("gen-device-cuda99", [*UNCOND, "--device", "cuda:99"]),
    ("gen-out-is-file", [*UNCOND, "--out", "{in}/afile"]),
    ("gen-out-under-file", [*UNCOND, "--out", "{in}/afile/sub"]),
    ("gen-out-in-proc", [*UNCOND, "--out", "/proc/omg-out"]),  # os.access says root may write there
    ("gen-steps-too-many", [*UNCOND, "--steps", "100000"]),
    ("gen-steps-zero", [*UNCOND, "--steps", "0"]),
    ("gen-seed-neg", [*UNCOND, "--seed", "-1"]),
    ("gen-seed-overflow", [*UNCOND, "--seed", "99999999999999999999999"]),
    ("gen-num-samples-neg", [*UNCOND, "--num_samples", "-2"]),
    ("gen-batch-size-zero", [*UNCOND, "--batch_size", "0"]),
    ("gen-nan-weights", [*GEN, "--unconditional", "--ckpt", "{nanck}", "--out", "{out}"]),
    ("gen-ckpt-bare-state-dict", [*GEN, "--unconditional", "--ckpt", "{in}/bare.ckpt", "--out", "{out}"]),
    ("gen-fails-in-user-folder", [*GEN, "--unconditional", "--ckpt", "{nanck}", "--out", "{in}/user"]),
    ("gen-out-holds-bvh-folder", [*UNCOND, "--out", "{in}/gen_bvhdir"]),
    ("gen-out-holds-glb-folder", [*UNCOND, "--out", "{in}/gen_glbdir", "--format", "glb"]),
    # omg export (writes beside its inputs: nothing may appear there either)
    ("export-fps-nan", [*EXPORT, "--fps", "nan"]),
    ("export-fps-inf", [*EXPORT, "--fps", "inf"]),
    ("export-fps-neg", [*EXPORT, "--fps", "-3"]),
    ("export-scale-nan", [*EXPORT, "--scale", "nan"]),
    ("export-scale-inf", [*EXPORT, "--scale", "inf"]),
    ("export-scale-zero", [*EXPORT, "--scale", "0"]),
    ("export-scale-neg", [*EXPORT, "--scale", "-100"]),
    ("export-representation-unknown", [*EXPORT, "--representation", "banana"]),
    ("export-settings-binary", ["export", "{in}/gen_binary", "--no_preview"]),
    ("export-settings-list", ["export", "{in}/gen_list", "--no_preview"]),
    ("export-settings-types", ["export", "{in}/gen_types", "--no_preview"]),
    ("export-settings-nan", ["export", "{in}/gen_nan", "--no_preview"]),
    ("export-settings-dir", ["export", "{in}/gen_dir", "--no_preview"]),
    ("export-bvh-is-dir", ["export", "{in}/gen_bvhdir", "--no_preview"]),
    ("export-input-binary", ["export", "{in}/random.bin"]),
    ("export-rig-no-map", [*RIG_EXPORT, "--to_rig", "{in}/bvh/tiny.bvh"]),
    ("export-rig-quadruped", [*RIG_EXPORT, "--to_rig", "{in}/rigs/dog.bvh"]),
    ("export-rig-no-rest-pose", [*RIG_EXPORT, "--to_rig", "{in}/rigs/flat.bvh"]),
    ("export-rig-no-hierarchy", [*RIG_EXPORT, "--to_rig", "{in}/rigs/motion_only.bvh"]),
    ("export-rig-not-bvh", [*RIG_EXPORT, "--to_rig", "{in}/afile"]),
    ("export-rig-glb-garbage", [*RIG_EXPORT, "--to_rig", "{in}/rigs/garbage.glb"]),
    ("export-rig-gltf-truncated", [*RIG_EXPORT, "--to_rig", "{in}/rigs/truncated.gltf"]),
    ("export-joint-map-without-rig", [*RIG_EXPORT, "--joint_map", "bandai"]),
    ("export-rig-wrong-map", [*RIG_EXPORT, "--to_rig", "{in}/rigs/human.bvh", "--joint_map", "cmu"]),
    ("export-rig-dir", [*RIG_EXPORT, "--to_rig", "{in}/rigs/folder.bvh"]),
    ("export-rig-device", [*RIG_EXPORT, "--to_rig", "{in}/rigs/null.bvh"]),
    ("export-rig-oversize", [*RIG_EXPORT, "--to_rig", "{in}/rigs/huge.bvh"]),
    ("export-joint-map-dir", [*RIG_EXPORT, "--to_rig", "{in}/rigs/human.bvh", "--joint_map", "{in}/empty"]),
    # omg shards build
    ("build-fps-nan", [*SYNTH_BUILD, "--fps", "nan"]),
    ("build-fps-inf", [*SYNTH_BUILD, "--fps", "inf"]),
    ("build-fps-neg", [*SYNTH_BUILD, "--fps", "-20"]),
    ("build-max-mb-nan", [*SYNTH_BUILD, "--max_mb", "nan"]),
    ("build-max-mb-inf", [*SYNTH_BUILD, "--max_mb", "inf"]),
    ("build-max-clips-neg", [*SYNTH_BUILD, "--max_clips", "-1"]),
    ("build-val-fraction-nan", [*SYNTH_BUILD, "--val_fraction", "nan"]),
    ("build-val-where-no-value", [*SYNTH_BUILD, "--val_where", "style"]),
    ("build-val-where-empty", [*SYNTH_BUILD, "--val_where.style", "[]"]),
    ("build-val-where-and-fraction", [*SYNTH_BUILD, "--val_where.style", "old", "--val_fraction", "0.1"]),
    ("build-shuffle-buffer-neg", [*SYNTH_BUILD, "--shuffle_buffer", "-1"]),
    ("build-out-is-file", ["shards", "build", "--source", "synth", "--out", "{in}/afile", "--option.num_clips", "2"]),
    ("build-out-under-file", ["shards", "build", "--source", "synth", "--out", "{in}/afile/x",
                              "--option.num_clips", "2"]),
    ("build-out-in-proc", [*SYNTH_BUILD, "--out", "/proc/omg-out"]),
    ("build-config-binary", ["shards", "build", "--config", "{in}/random.bin"]),
    ("build-config-latin1", ["shards", "build", "--config", "{in}/latin1.yaml"]),
    ("build-config-dir", ["shards", "build", "--config", "{in}", "--source", "synth", "--out", "{out}"]),
    ("build-config-nan", ["shards", "build", "--config", "{in}/nan.yaml"]),
    ("build-config-wrong-type", ["shards", "build", "--config", "{in}/list_out.yaml"]),
    ("build-config-syntax", ["shards", "build", "--config", "{in}/syntax.yaml"]),
    ("build-config-empty", ["shards", "build", "--config", "{in}/empty.yaml"]),
    ("build-option-nan", [*SYNTH_BUILD, "--option.num_clips", "nan"]),
    ("build-option-neg-seed", [*SYNTH_BUILD, "--option.seed", "-1"]),
    ("build-option-unknown", [*SYNTH_BUILD, "--option.banana", "1"]),
    ("build-option-no-key", [*SYNTH_BUILD, "--option.=3"]),
    ("build-option-not-mapping", [*SYNTH_BUILD, "--option", "num_clips=2"]),
    ("build-option-bad-yaml", [*SYNTH_BUILD, "--option", "{{seed: [1, 2"]),  # {{: a brace after format()
    ("build-option-neg-count", ["shards", "build", "--source", "synth", "--out", "{out}", "--option.num_clips", "-1"]),
    ("build-joint-map-binary", ["shards", "build", "--source", "bvh-dir", "--input", "{in}/bvh", "--out", "{out}",
                                "--option.joint_map", "{in}/random.bin"]),
    ("build-empty-source", ["shards", "build", "--source", "bvh-dir", "--input", "{in}/empty", "--out", "{out}/a/b"]),
    ("build-fails-in-user-folder", ["shards", "build", "--source", "synth", "--out", "{in}/user",
                                    "--val_fraction", "0.5", "--option.num_clips", "1"]),
    ("build-workers-zero", [*SYNTH_BUILD, "--workers", "0"]),
    ("build-part-out-of-range", [*SYNTH_BUILD, "--part", "2", "--parts", "2"]),
    ("build-part-without-parts", [*SYNTH_BUILD, "--part", "1"]),
    # omg shards merge
    ("merge-no-parts", ["shards", "merge", "--out", "{out}"]),
    ("merge-part-missing", ["shards", "merge", "{in}/nope", "--out", "{out}"]),
    ("merge-part-not-a-set", ["shards", "merge", "{in}/empty", "{in}/user", "--out", "{out}"]),
    ("merge-mismatched-parts", ["shards", "merge", MINI_SHARDS, str(REPO / "shards/mini/animal_maa/train"),
                                "--out", "{out}"]),
    ("merge-part-twice", ["shards", "merge", MINI_VAL, MINI_VAL, "--out", "{out}"]),
    ("merge-part-twice-other-spelling", ["shards", "merge", MINI_VAL, f"{MINI_VAL}/../val", "--out", "{out}"]),
    ("merge-parts-overlap", ["shards", "merge", MINI_VAL, "{in}/val_copy", "--out", "{out}"]),
    # omg transfer (the habit checkpoints are checked before anything is read or written)
    ("transfer-ckpt-other-class", ["transfer", "{in}/bvh/tiny.bvh", "--to", "horse", "--ckpt", "{cn}",
                                   "--out", "{out}"]),
    ("transfer-ckpt-missing", ["transfer", "{in}/bvh/tiny.bvh", "--to", "horse", "--ckpt", "{in}/nope.ckpt",
                               "--out", "{out}"]),
    ("transfer-ckpt-binary", ["transfer", "{in}/bvh/tiny.bvh", "--to", "horse", "--ckpt", "{in}/random.bin",
                              "--out", "{out}"]),
    ("transfer-out-is-file", [*TRANSFER, "{in}/still.npy", "--out", "{in}/afile"]),
    ("transfer-no-to", ["transfer", "{in}/still.npy", "--ckpt", "{habit}", "--out", "{out}"]),
    ("transfer-out-in-proc", [*TRANSFER, "{in}/still.npy", "--out", "/proc/omg-out"]),
    ("transfer-source-nan", [*TRANSFER, "{in}/nan.npy", "--out", "{out}"]),
    ("transfer-source-dir", [*TRANSFER, "{in}/empty", "--out", "{out}"]),
    ("transfer-source-fifo", [*TRANSFER, "{in}/fifo.npy", "--out", "{out}"]),
    ("transfer-rig-human", [*TRANSFER, "{in}/still.npy", "--out", "{out}", "--to_rig", "{in}/rigs/human.bvh"]),
    ("transfer-out-holds-bvh-folder", [*TRANSFER, "{in}/still.npy", "--out", "{in}/transfer_bvhdir"]),
    ("transfer-species-file-dir", ["transfer", "{in}/still.npy", "--to", "fox", "--ckpt", "{habit}", "--no_preview",
                                   "--out", "{out}", "--species_file", "{in}/empty"]),  # fox: a species of the book
    # omg generate's animal options on a checkpoint that is not OmniMotionGPT's
    ("gen-animal-on-controlnet", [*TEXT, "--animal", "dog"]),
    ("gen-from-motion-on-controlnet", [*TEXT, "--from_motion", "{in}/bvh/tiny.bvh"]),
    # omg generate --timeline (the file is read before a checkpoint; what fits the model, after it loads)
    ("gen-timeline-missing", [*GEN, "--ckpt", "{cn}", "--timeline", "{in}/nope.json", "--out", "{out}"]),
    ("gen-timeline-binary", [*GEN, "--ckpt", "{cn}", "--timeline", "{in}/elf.bin", "--out", "{out}"]),
    ("gen-timeline-not-json", [*GEN, "--ckpt", "{cn}", "--timeline", "{in}/afile", "--out", "{out}"]),
    ("gen-timeline-on-prior", ["generate", "--steps", "2", "--ckpt", "{pre}", "--timeline", "{in}/timeline.json",
                               "--out", "{out}"]),
    # omg shards inspect on a mixture
    ("inspect-mixture-negative-weight", ["shards", "inspect", "{in}/mix_negative.yaml"]),
    ("inspect-mixture-unknown-key", ["shards", "inspect", "{in}/mix_unknown_key.yaml"]),
    ("inspect-mixture-mismatched-sets", ["shards", "inspect", "{in}/mix_mismatched.yaml"]),
    # omg shards synth
    ("synth-scale-nan", ["shards", "synth", "--out", "{out}", "--scale", "nan"]),
    ("synth-scale-neg", ["shards", "synth", "--out", "{out}", "--scale", "-1"]),
    ("synth-fps-nan", ["shards", "synth", "--out", "{out}", "--fps", "nan"]),
    ("synth-seed-neg", ["shards", "synth", "--out", "{out}", "--seed", "-1", "--scale", "0.02"]),
    ("synth-out-is-file", ["shards", "synth", "--out", "{in}/afile", "--scale", "0.02"]),
    # omg fit: the config files
    ("fit-config-elf", ["fit", "--config", "{in}/elf.bin"]),
    ("fit-config-random", ["fit", "--config", "{in}/random.bin"]),
    ("fit-config-random-eq", ["fit", "--config={in}/random.bin"]),
    ("fit-config-latin1", ["fit", "--config", "{in}/latin1.yaml"]),
    ("fit-config-syntax", ["fit", "--config", "{in}/syntax.yaml"]),
    ("fit-config-empty", ["fit", "--config={in}/empty.yaml"]),
    ("fit-data-config-binary", [*FIT, "--data", "{in}/random.bin"]),
    ("fit-ckpt-hpc-pickled", [*FIT_DATA, "--trainer.default_root_dir", "{in}/hpc_pickled", "--ckpt_path", "hpc"]),
    ("fit-ckpt-hpc-torn", [*FIT_DATA, "--trainer.default_root_dir", "{in}/hpc_torn", "--ckpt_path", "hpc"]),
    ("fit-ckpt-hpc-none", [*FIT_DATA, "--trainer.default_root_dir", "{in}/empty", "--ckpt_path", "hpc"]),
    # omg fit: values refused before the run folder is made (they failed at fit start, or at the first batch)
    ("fit-ema-decay-over-1", [*FIT_DATA, "--model.init_args.ema_decay", "1.5"]),
    ("fit-vel-weight-neg", [*FIT_DATA, "--model.init_args.loss.vel_weight", "-1"]),
    ("fit-optim-lr-zero", [*FIT_DATA, "--model.init_args.optim.lr", "0"]),
    ("fit-optim-unknown-key", [*FIT_DATA, "--model.init_args.optim.learning_rate", "1e-3"]),
    ("fit-loss-unknown-key", [*FIT_DATA, "--model.init_args.loss.velocity_weight", "3"]),
    ("fit-optim-old-and-new-key", [*FIT_DATA, "--config", "{in}/old_and_new_lr.yaml"]),
    ("fit-dit-unknown-key", [*FIT_DATA, "--model.init_args.dit.dpeth", "3"]),
    ("fit-dit-key-not-a-number", [*FIT_DATA, "--model.init-args.dit.n-layers", "three"]),
    ("fit-root-dir-is-file", [*FIT_DATA, "--trainer.default_root_dir", "{in}/afile"]),
    ("fit-root-dir-in-proc", [*FIT_DATA, "--trainer.default_root_dir", "/proc/omg-runs"]),
    ("fit-max-bad-fraction-over-1", [*FIT_DATA, "--data.max_bad_fraction", "2"]),
    ("fit-max-bad-fraction-neg", [*FIT_DATA, "--data.max_bad_fraction", "-1"]),
    ("fit-cache-mb-negative", [*FIT_DATA, "--data.cache_mb", "-1"]),
    ("fit-min-len-over-max-len", [*FIT_DATA, "--data.min_len", "200", "--data.max_len", "120"]),
    ("fit-val-other-representation", [*FIT_DATA, "--data.val", str(REPO / "shards/mini/animal_maa/val")]),
    # omg test: an evaluator of another representation than the data's
    ("test-evaluator-other-kind", ["test", "--config", "{eval_animal}", "--trainer.default_root_dir", "{out}",
                                   "--model.init_args.pretrained", "{pre}", "--model.init_args.text_encoder", "hash",
                                   "--model.init_args.moc", "{{d_c: 16, num_experts: 2}}"]),
    ("fit-habit-order-banana", [*FIT_HABIT, "--model.init_args.order.habit_order", "banana"]),
    ("fit-habit-fraction-one", [*FIT_HABIT, "--model.init_args.order.habit_fraction", "1"]),
    ("fit-mirror-prob-above-one", [*FIT_DATA, "--data.mirror_prob", "1.5"]),
    ("fit-mirror-prob-nan", [*FIT_DATA, "--data.mirror_prob", "nan"]),
    ("fit-progress-every-neg", [*FIT_DATA, "--progress_every=-1"]),
    # OmniMotionGPT's second set (data.human), its older key, and a run without it
    ("fit-human-batch-zero", [*FIT_OMGPT, "--data.human.batch_size", "0"]),
    ("fit-human-other-skeleton", [*FIT_OMGPT, "--data.human.train", str(REPO / "shards/mini/animal_maa/train"),
                                  "--data.human.val", str(REPO / "shards/mini/animal_maa/val")]),
    ("fit-human-none", [*FIT_OMGPT, "--data.human", "null"]),
    ("fit-human-data-and-human", [*FIT_OMGPT, "--model.init_args.human_data.batch_size", "4"]),
    # omg bench
    ("bench-train-batch-neg", ["bench", "train", "--batch_size", "-1", "--steps", "1", "--warmup", "0",
                               "--frames", "8"]),
    ("bench-train-peak-nan", ["bench", "train", "--peak_tflops", "nan", "--steps", "1", "--warmup", "0",
                              "--frames", "8", "--batch_size", "1"]),
    ("bench-plan-mfu-zero", ["bench", "plan", "--mfu", "0"]),
    ("bench-plan-offload-ddp", ["bench", "plan", "--strategy", "ddp", "--offload"]),
    ("bench-plan-not-planned", ["bench", "plan", "--configs", f"[{REPO}/configs/habit_vqvae.yaml]"]),
    ("bench-plan-python-tag", ["bench", "plan", "--configs", "[{in}/python_tag.yaml]"]),
    ("bench-plan-global-batch-gpus", ["bench", "plan", "--configs", f"[{REPO}/configs/pretrain_base.yaml]",
                                      "--gpus", "3"]),
    ("bench-gpu-few-steps", ["bench", "gpu", "--dry_run", "--train_steps", "5"]),
    ("bench-gpu-shards-missing", ["bench", "gpu", "--dry_run", "--shards", "{in}/nope"]),
    ("bench-sample-frames-neg", ["bench", "sample", "--frames", "-1", "--steps", "1", "--batch_sizes", "[1]"]),
    ("bench-data-batches-zero", [*BENCH_DATA, "--batches", "0"]),
    ("bench-data-batches-nan", [*BENCH_DATA, "--batches", "nan"]),
    ("bench-data-batch-size-zero", [*BENCH_DATA, "--batch_size", "0"]),
    ("bench-data-clips-zero", [*BENCH_DATA, "--clips", "0"]),
    ("bench-data-clips-below-batch", [*BENCH_DATA, "--clips", "3"]),
    ("bench-data-feature-dim-zero", [*BENCH_DATA, "--feature_dim", "0"]),
    ("bench-data-workers-neg", [*BENCH_DATA, "--workers", "-1"]),
    ("bench-data-sample-interval-zero", [*BENCH_DATA, "--sample_interval", "0"]),
    ("bench-data-max-len-zero", [*BENCH_DATA, "--max_len", "0"]),
    ("bench-data-cache-mb-negative", [*BENCH_DATA, "--cache_mb", "-1"]),
    ("bench-data-max-len-below-window", [*BENCH_DATA, "--max_len", "40"]),
    ("bench-data-shards-missing", [*BENCH_DATA, "--shards", "{in}/nope"]),
    ("bench-data-shards-not-shards", [*BENCH_DATA, "--shards", "{in}/empty"]),
    ("bench-data-shards-file", [*BENCH_DATA, "--shards", "{in}/afile"]),
    ("bench-data-shards-below-batch", [*BENCH_DATA, "--shards", MINI_SHARDS, "--batch_size", "100000"]),
    ("bench-train-steps-zero", [*BENCH_TRAIN, "--steps", "0"]),
    ("bench-train-steps-nan", [*BENCH_TRAIN, "--steps", "nan"]),
    ("bench-train-batch-zero", [*BENCH_TRAIN, "--batch_size", "0"]),
    ("bench-train-frames-zero", [*BENCH_TRAIN, "--frames", "0"]),
    ("bench-train-warmup-neg", [*BENCH_TRAIN, "--warmup", "-1"]),
    ("bench-train-peak-zero", [*BENCH_TRAIN, "--peak_tflops", "0"]),
    ("bench-train-peak-inf", [*BENCH_TRAIN, "--peak_tflops", "inf"]),
    ("bench-train-peak-neg", [*BENCH_TRAIN, "--peak_tflops", "-5"]),
    ("bench-train-precision-banana", [*BENCH_TRAIN, "--precision", "banana"]),
    ("bench-train-strategy-banana", [*BENCH_TRAIN, "--strategy", "banana"]),
    ("bench-train-flavor-banana", [*BENCH_TRAIN, "--flavor", "banana"]),
    ("bench-sample-batch-sizes-letters", [*BENCH_SAMPLE, "--batch_sizes", "[a, b]"]),
    ("bench-sample-batch-sizes-zero", [*BENCH_SAMPLE, "--batch_sizes", "[0]"]),
    ("bench-sample-batch-sizes-neg", [*BENCH_SAMPLE, "--batch_sizes", "[1, -8]"]),
    ("bench-sample-batch-sizes-gap", [*BENCH_SAMPLE, "--batch_sizes", "[1,,8]"]),
    ("bench-sample-batch-sizes-not-list", [*BENCH_SAMPLE, "--batch_sizes", "1,8"]),
    ("bench-sample-batch-sizes-empty", [*BENCH_SAMPLE, "--batch_sizes", ""]),
    ("bench-sample-batch-sizes-nan", [*BENCH_SAMPLE, "--batch_sizes", "[nan]"]),
    ("bench-sample-steps-zero", [*BENCH_SAMPLE, "--steps", "0"]),  # legitimate only with --token-steps
    ("bench-sample-steps-too-many", [*BENCH_SAMPLE, "--steps", "100000"]),
    ("bench-sample-steps-nan", [*BENCH_SAMPLE, "--steps", "nan"]),
    ("bench-sample-frames-zero", [*BENCH_SAMPLE, "--frames", "0"]),
    ("bench-sample-token-steps-neg", [*BENCH_SAMPLE, "--token_steps", "-1"]),
    ("bench-sample-flavor-banana", [*BENCH_SAMPLE, "--flavor", "banana"]),
    ("bench-sample-text-encoder-banana", [*BENCH_SAMPLE, "--text_encoder", "banana"]),
    ("bench-sample-precision-banana", [*BENCH_SAMPLE, "--precision", "banana"]),
    ("bench-following-input-missing", ["bench", "following", "--input", "{in}/nope"]),
    ("bench-following-input-no-labels", ["bench", "following", "--input", "{in}"]),
    ("bench-following-prompts-missing", ["bench", "following", "--input", "{in}", "--prompts", "{in}/nope.yaml"]),
    ("bench-following-prompts-binary", ["bench", "following", "--input", "{in}", "--prompts", "{in}/elf.bin"]),
    ("bench-following-fps-nan", ["bench", "following", "--input", "{in}", "--fps", "nan"]),
    ("bench-sides-manifest-missing", ["bench", "sides", "--manifests", "[{in}/nope.json]", "--encoders", "[hash]"]),
    ("bench-sides-manifest-binary", ["bench", "sides", "--manifests", "[{in}/elf.bin]", "--encoders", "[hash]"]),
    ("bench-sides-prompts-missing", ["bench", "sides", "--prompts", "{in}/nope.yaml", "--encoders", "[hash]"]),
    ("bench-sides-no-captions", ["bench", "sides", "--prompts", "none", "--encoders", "[hash]"]),
    ("bench-sides-encoder-option", ["bench", "sides", "--encoders", "[hash:dim]"]),
    ("bench-timeline-prior", ["bench", "timeline", "--ckpt", "{pre}", "--val", MINI_VAL]),
    ("bench-timeline-val-without-actions", ["bench", "timeline", "--ckpt", "{cn}", "--val", MINI_VAL]),
    ("bench-rig-data-is-file", ["bench", "rig", "--data", "{in}/afile"]),
    ("bench-rig-data-without-clips", ["bench", "rig", "--data", "{in}/empty"]),
    ("bench-character-not-fbx", ["bench", "character", "--fbx", "{in}/afile"]),
    ("bench-character-fbx-missing", ["bench", "character", "--fbx", "{in}/nope.fbx"]),
    # omg serve (checked before a checkpoint loads or a port is bound)
    ("serve-out-is-file", ["serve", "--ckpt", "{cn}", "--out", "{in}/afile"]),
    ("serve-out-in-proc", ["serve", "--ckpt", "{cn}", "--out", "/proc/omg-out"]),
    ("serve-allowed-hosts-port", ["serve", "--ckpt", "{cn}", "--allowed_hosts", "[localhost:8000]"]),
    ("joint-map-rig-missing", ["joint-map", "{in}/nope.bvh"]),
    ("joint-map-rig-not-bvh", ["joint-map", "{in}/afile"]),
    ("joint-map-target-banana", ["joint-map", "{in}/nope.bvh", "--target", "banana"]),
    ("joint-map-motion-missing", ["joint-map", "{in}/nope.txt"]),
    ("joint-map-motion-not-deepmimic", ["joint-map", "{in}/latin1.txt"]),
    ("plot-run-missing", ["plot", "{in}/nope"]),
    ("plot-run-without-metrics", ["plot", "{in}"]),
]


# what the line of each row must hold: the key or file it names and the reason, so that a row that
# fails for another reason (a path of the config relative to the repository, a missing fixture, a
# check that runs first) does not pass. Formatted as the argv ({in}, {out}, the checkpoints).
ANIMAL_TRAIN = str(REPO / "shards/mini/animal_maa/train")
ANIMAL_VAL = str(REPO / "shards/mini/animal_maa/val")
SPECS_DIFFER = "differ: representation humanml3d263 vs maa"
PROGRESS = re.compile(r"motions? \d+(-\d+)? of \d+ made in ")  # omg generate's progress line when redirected
SAYS = {
    "gen-prompts-latin1": "--prompts_file {in}/latin1.txt: not a UTF-8 text file (byte 0xe9",
    "gen-prompts-binary": "--prompts_file {in}/elf.bin: not a UTF-8 text file (byte 0xff",
    "gen-prompts-nul": "--prompts_file {in}/nul.txt: line 1 holds the control character",
    "gen-prompt-lone-surrogate": "prompt 1 holds a lone surrogate or undecodable byte '\\ud800'",
    "gen-prompt-c1-control": "prompt 1 holds the control character '\\x85'",
    "gen-animal-control-character": "--animal holds the control character '\\x07'",
    "gen-prompts-dir": "--prompts_file {in}: is a directory; a file is expected",
    "gen-prompts-missing": "--prompts_file {in}/nope.txt: no such file",
    "gen-length-nan": "length: expected a number of seconds in (0, 60], got 'nan'",
    "gen-length-inf": "length: expected a number of seconds in (0, 60], got 'inf'",
    "gen-length-neg": "length: expected a number of seconds in (0, 60], got '-1'",
    "gen-guidance-nan": "guidance: expected a finite number, got 'nan'",
    "gen-guidance-inf": "guidance: expected a finite number, got 'inf'",
    "gen-guidance-overflow": "NaN or inf motions: a diverged checkpoint ({cn}) or --guidance 1e+308 too large",
    "gen-stance-root-2": "stance_root: expected a number in [0, 1], got '2'",
    "gen-stance-root-habit": "(HabitVQModule) takes no option stance_root; its options: temperature",
    "gen-option-unknown": "{pre} (PretrainModule) takes no option temperature; its options: stance_root",
    "gen-option-no-value": "--option 'stance_root': give KEY=VALUE, e.g. --option stance_root=VALUE",
    "gen-option-habit-value": "--option quantizer=best: give one of soft, nearest",
    "gen-prior-on-omg": "--prior_ckpt: {pre} (PretrainModule) takes no prior checkpoint",
    "gen-device-banana": "--device 'banana': not a device",
    "gen-device-cuda99": "--device cuda:99: ",  # the reason depends on the GPUs this machine has
    "gen-out-is-file": "--out {in}/afile: not a folder",
    "gen-out-under-file": "--out {in}/afile/sub: not a folder (its parent {in}/afile is a file)",
    "gen-out-in-proc": "--out /proc/omg-out: cannot write in /proc",
    "gen-steps-too-many": "--steps must be in 1..1000 (the checkpoint's diffusion steps), got 100000",
    "gen-steps-zero": "steps: expected an integer >= 1, got '0'",
    "gen-seed-neg": "seed: expected an integer in [0, 2^63), got '-1'",
    "gen-seed-overflow": "seed: expected an integer in [0, 2^63), got '99999999999999999999999'",
    "gen-num-samples-neg": "num_samples: expected an integer >= 1, got '-2'",
    "gen-batch-size-zero": "batch_size: expected an integer >= 1, got '0'",
    "gen-nan-weights": "the model produced NaN or inf motions: a diverged checkpoint ({nanck})",
    "gen-ckpt-bare-state-dict": "{in}/bare.ckpt is a bare state dict: it holds weights without the module's hyper",
    "gen-fails-in-user-folder": "the model produced NaN or inf motions: a diverged checkpoint ({nanck})",
    "gen-out-holds-bvh-folder": "--out {in}/gen_bvhdir: sample_000.bvh is a folder, where an output file goes",
    "gen-out-holds-glb-folder": "--out {in}/gen_glbdir: sample_000.glb is a folder, where an output file goes",
    "export-fps-nan": "fps: expected a finite number > 0, got 'nan'",
    "export-fps-inf": "fps: expected a finite number > 0, got 'inf'",
    "export-fps-neg": "fps: expected a finite number > 0, got '-3'",
    "export-scale-nan": "scale: expected a finite number > 0, got 'nan'",
    "export-scale-inf": "scale: expected a finite number > 0, got 'inf'",
    "export-scale-zero": "scale: expected a finite number > 0, got '0'",
    "export-scale-neg": "scale: expected a finite number > 0, got '-100'",
    "export-representation-unknown": "unknown representation 'banana'; known representations:",
    "export-settings-binary": "settings file {in}/gen_binary/generation.json: not a UTF-8 text file",
    "export-settings-list": "{in}/gen_list/generation.json: expected a JSON object (omg generate's settings), got a "
                            "JSON list",
    "export-settings-types": "{in}/gen_types/generation.json: 'skeleton' must be a name, got 5",
    "export-settings-nan": "{in}/gen_nan/generation.json: 'fps' must be a positive number, got nan",
    "export-settings-dir": "settings file {in}/gen_dir/generation.json: is a directory; a file is expected",
    "export-bvh-is-dir": "{in}/gen_bvhdir/sample_000.bvh: a folder is in the way of the output file",
    "export-input-binary": "{in}/random.bin: not a directory or an existing .npy file",
    "export-rig-no-map": "{in}/bvh/tiny.bvh: cannot map the rig onto smpl22 (no registered map fits); closest",
    "export-rig-quadruped": "{in}/rigs/dog.bvh: the rig is a dog rig (its names fit joint map 'mann_dog', onto "
    "smal35), the motion is on smpl22",
    "export-rig-no-rest-pose": "{in}/rigs/flat.bvh: the rig has no rest pose (its leg joints' OFFSETs are zero)",
    "export-rig-no-hierarchy": "{in}/rigs/motion_only.bvh:1: no HIERARCHY before MOTION",
    "export-rig-not-bvh": "--to_rig {in}/afile: the rig must be a .bvh file",
    "export-rig-glb-garbage": "--to_rig {in}/rigs/garbage.glb: not a readable glTF 2.0 file",
    "export-rig-gltf-truncated": "--to_rig {in}/rigs/truncated.gltf: not a readable glTF 2.0 file",
    "export-joint-map-without-rig": "--joint_map names the map of the --to_rig rig; give --to_rig",
    "export-rig-wrong-map": "{in}/rigs/human.bvh: joint map 'cmu' needs joints the file lacks: Spine1, Neck1",
    "export-rig-dir": "--to_rig {in}/rigs/folder.bvh: is a directory; a file is expected",
    "export-rig-device": "--to_rig {in}/rigs/null.bvh: not a regular file (a FIFO, socket or device)",
    "export-rig-oversize": "--to_rig {in}/rigs/huge.bvh: larger than the 256 MiB omg reads from such a file "
                           f"({MOTION_MAX_BYTES + 1} bytes)",
    "export-joint-map-dir": "joint map {in}/empty: is a directory; a file is expected",
    "build-fps-nan": "fps: expected a number of frames per second in (0, 1000], got 'nan'",
    "build-fps-inf": "fps: expected a number of frames per second in (0, 1000], got 'inf'",
    "build-fps-neg": "fps: expected a number of frames per second in (0, 1000], got '-20'",
    "build-max-mb-nan": "max_mb: expected a finite number > 0, got 'nan'",
    "build-max-mb-inf": "max_mb: expected a finite number > 0, got 'inf'",
    "build-max-clips-neg": "max_clips: expected an integer >= 1, got '-1'",
    "build-val-fraction-nan": "val_fraction: expected a number in [0, 1), got 'nan'",
    "build-val-where-no-value": "val_where: expected a mapping such as {{key: value}}, got 'style'",
    "build-val-where-empty": "--val_where.style: give the label values that go to out/val",
    "build-val-where-and-fraction": "give --val_fraction (a random split) or --val_where (a split by label), not both",
    "build-shuffle-buffer-neg": "shuffle_buffer: expected an integer >= 0, got '-1'",
    "build-out-is-file": "--out {in}/afile: not a folder",
    "build-out-under-file": "--out {in}/afile/x: not a folder (its parent {in}/afile is a file)",
    "build-out-in-proc": "--out /proc/omg-out: cannot write in /proc",
    "build-config-binary": "--config {in}/random.bin: not a UTF-8 text file (byte 0x81",
    "build-config-latin1": "--config {in}/latin1.yaml: not a UTF-8 text file (byte 0xe9",
    "build-config-dir": "--config {in}: is a directory; a file is expected",
    "build-config-nan": "fps: expected a number of frames per second in (0, 1000], got nan",
    "build-config-wrong-type": "out: expected a path, got [1, 2]",
    "build-config-syntax": "--config {in}/syntax.yaml: not valid YAML at line 4",
    "build-config-empty": "--config {in}/empty.yaml: the file is empty",
    "build-option-nan": "--option.num_clips 'nan': the synth source expects an integer",
    "build-option-neg-seed": "--option.seed -1: expected a finite number >= 0",
    "build-option-unknown": "--option.banana: the synth source has no such option; its options: num_clips, seed",
    "build-option-no-key": "--option. 3: the key must be a name",
    "build-option-not-mapping": "option: expected a mapping such as {{key: value}}, got 'num_clips=2'",
    "build-option-bad-yaml": "option: expected a mapping such as {{key: value}}, got '{{seed: [1, 2'",
    "build-option-neg-count": "--option.num_clips -1: expected a finite number >= 0",
    "build-joint-map-binary": "joint map {in}/random.bin: not a UTF-8 text file",
    "build-empty-source": "no clip could be written to {out}/a/b (the source was empty)",
    "build-fails-in-user-folder": "no clip could be written to {in}/user/val (none of the 1 source items went to it)",
    "build-workers-zero": "workers: expected an integer >= 1, got '0'",
    "build-part-out-of-range": "--part must be in [0, --parts), i.e. 0 to 1, got 2",
    "build-part-without-parts": "--part must be in [0, --parts), i.e. 0 to 0, got 1",
    "merge-no-parts": "the following arguments are required: merge.parts",
    "merge-part-missing": "{in}/nope: no such folder (a part built with omg shards build",
    "merge-part-not-a-set": "{in}/empty: neither a shard set (manifest.json) nor a folder of them",
    "merge-mismatched-parts": f"cannot merge {ANIMAL_TRAIN}: representation 'maa', but {MINI_SHARDS} has "
                              "'humanml3d263'",
    "merge-part-twice": f"cannot merge {MINI_VAL}: the same part as {MINI_VAL}, given twice",
    "merge-part-twice-other-spelling": f"cannot merge {MINI_VAL}/../val: the same part as {MINI_VAL}, given twice",
    "merge-parts-overlap": f"cannot merge {{in}}/val_copy and {MINI_VAL}: they overlap (both hold clip",
    "transfer-ckpt-other-class": "{cn} holds a omg.lit.controlnet.ControlNetModule checkpoint, not a "
                                 "omg.lit.habit.HabitVQModule",
    "transfer-ckpt-missing": "{in}/nope.ckpt: no such file or directory; expected a Lightning .ckpt file",
    "transfer-ckpt-binary": "{in}/random.bin is not a checkpoint; expected a Lightning .ckpt file",
    "transfer-out-is-file": "--out {in}/afile: not a folder",
    "transfer-no-to": "the following arguments are required: to; see `omg transfer --help`",
    "transfer-out-in-proc": "--out /proc/omg-out: cannot write in /proc",
    "transfer-source-nan": "SOURCE {in}/nan.npy: holds NaN or inf values",
    "transfer-source-dir": "SOURCE {in}/empty: is a directory; a file is expected",
    "transfer-source-fifo": "SOURCE {in}/fifo.npy: not a regular file (a FIFO",
    "transfer-rig-human": "{in}/rigs/human.bvh: the rig is a human rig (its names fit joint map 'bandai', onto "
    "smpl22), the motion is on smal35",
    "transfer-out-holds-bvh-folder": "--out {in}/transfer_bvhdir: transfer.bvh is a folder, where an output file "
                                     "goes",
    "transfer-species-file-dir": "species file {in}/empty: is a directory; a file is expected",
    "gen-animal-on-controlnet": "{cn} (ControlNetModule) does not generate from a species (--animal); it takes "
                                "prompts",
    "gen-from-motion-on-controlnet": "{cn} (ControlNetModule) does not generate from a source motion (--from_motion); "
                                     "it takes prompts",
    "gen-timeline-missing": "--timeline {in}/nope.json: no such file",
    "gen-timeline-binary": "--timeline {in}/elf.bin: not a UTF-8 text file",
    "gen-timeline-not-json": "--timeline {in}/afile: not valid JSON",
    "gen-timeline-on-prior": "--timeline: {pre} (PretrainModule) takes no prompt timeline; its card lists none",
    "inspect-mixture-negative-weight": f"{{in}}/mix_negative.yaml: data.train[0] ({MINI_SHARDS}): 'weight' must be a "
                                       "positive number, got -1",
    "inspect-mixture-unknown-key": "{in}/mix_unknown_key.yaml: data.train[0]: unknown key 'pat'",
    "inspect-mixture-mismatched-sets": f"{{in}}/mix_mismatched.yaml: data.train[0] ({MINI_SHARDS}) and data.train[1] "
                                       f"({ANIMAL_TRAIN}) {SPECS_DIFFER}",
    "synth-scale-nan": "scale: expected a finite number > 0, got 'nan'",
    "synth-scale-neg": "scale: expected a finite number > 0, got '-1'",
    "synth-fps-nan": "fps: expected a number of frames per second in (0, 1000], got 'nan'",
    "synth-seed-neg": "seed: expected an integer in [0, 2^63), got '-1'",
    "synth-out-is-file": "--out {in}/afile: not a folder",
    "fit-config-elf": "--config {in}/elf.bin: not a UTF-8 text file (byte 0xff",
    "fit-config-random": "--config {in}/random.bin: not a UTF-8 text file (byte 0x81",
    "fit-config-random-eq": "--config {in}/random.bin: not a UTF-8 text file (byte 0x81",
    "fit-config-latin1": "--config {in}/latin1.yaml: not a UTF-8 text file (byte 0xe9",
    "fit-config-syntax": "--config {in}/syntax.yaml: not valid YAML at line 4",
    "fit-config-empty": "--config {in}/empty.yaml: the file is empty",
    "fit-data-config-binary": "--data {in}/random.bin: not a UTF-8 text (YAML) file",
    "fit-ckpt-hpc-pickled": "--ckpt_path hpc: {in}/hpc_pickled/hpc_ckpt_1.ckpt holds pickled Python objects "
                            "(argparse.Namespace)",
    "fit-ckpt-hpc-torn": "--ckpt_path hpc: {in}/hpc_torn/hpc_ckpt_2.ckpt is corrupt",
    "fit-ckpt-hpc-none": "--ckpt_path hpc: {in}/empty holds no hpc_ckpt_N.ckpt",
    "fit-ema-decay-over-1": "model.ema_decay must be in [0, 1) (0: no EMA), got 1.5",
    "fit-vel-weight-neg": "model.loss.vel_weight must be a finite number >= 0, got -1.0",
    "fit-optim-lr-zero": "model.optim.lr must be a finite number > 0, got 0.0",
    "fit-optim-unknown-key": "model.init_args.optim.learning_rate: unknown key 'learning_rate'; accepted keys: lr, "
                             "weight_decay, betas, warmup_steps",
    "fit-loss-unknown-key": "model.init_args.loss.velocity_weight: unknown key 'velocity_weight'; did you mean "
                            "model.init_args.loss.vel_weight? (accepted keys: vel_weight, foot_weight",
    "fit-optim-old-and-new-key": "model.init_args.lr and model.init_args.optim.lr are both set: keep "
                                 "model.init_args.optim.lr only (model.init_args.lr is its older name)",
    "fit-dit-unknown-key": "model.init_args.dit.dpeth: unknown key 'dpeth'; accepted keys: n_layers, d_model, ",
    "fit-dit-key-not-a-number": "model.init_args.dit.n_layers: expected an integer, got 'three'",
    "fit-root-dir-is-file": "trainer.default_root_dir {in}/afile: not a folder",
    "fit-root-dir-in-proc": "trainer.default_root_dir /proc/omg-runs: cannot write in /proc",
    "fit-max-bad-fraction-over-1": "data.max_bad_fraction must be in [0, 1], got 2.0",
    "fit-max-bad-fraction-neg": "data.max_bad_fraction must be in [0, 1], got -1.0",
    "fit-cache-mb-negative": "data.cache_mb must be >= 0 MiB (0: decode every shard at each read), got -1.0",
    "fit-min-len-over-max-len": "data.min_len and data.max_len must satisfy 1 <= min_len <= max_len, got min_len=200, "
                                "max_len=120",
    "fit-val-other-representation": f"data.train ({MINI_SHARDS}) and data.val ({ANIMAL_VAL}) {SPECS_DIFFER}",
    "test-evaluator-other-kind": f"the data and EvalCallback.evaluator {SPECS_DIFFER}",
    "fit-habit-order-banana": "model.order.habit_order must be one of flow_prior, kl_then_flows (flow_prior: the "
                              "paper's",
    "fit-habit-fraction-one": "model.order.habit_fraction must be in (0, 1) (the share of the run that pretrains the "
                              "habit encoders), got 1.0",
    "fit-mirror-prob-above-one": "data.mirror_prob is a probability in [0, 1], got 1.5",
    "fit-mirror-prob-nan": "data.mirror_prob: expected a number, got 'nan'",
    "fit-progress-every-neg": "progress_every: expected an integer >= 0, got '-1'",
    "fit-human-batch-zero": "data.human: data.batch_size, data.batches_per_epoch and data.shuffle_buffer must be "
                            "positive",
    "fit-human-other-skeleton": "data.human: OmniMotionGPT reads smpl22 shards in the maa representation, got "
                                "smal35 maa",
    "fit-human-none": "OmniMotionGPT trains on two shard sets: set data.human to the human shards",
    "fit-human-data-and-human": "model.init_args.human_data and data.human both name the human shards: keep data.human "
                                "only",
    "bench-train-batch-neg": "batch_size: expected an integer >= 1, got '-1'",
    "bench-train-peak-nan": "peak_tflops: expected a finite number > 0, got 'nan'",
    "bench-plan-mfu-zero": "mfu: expected a number in (0, 1], got '0'",
    "bench-plan-offload-ddp": "--offload needs a ZeRO --strategy (zero1, zero2, zero3)",
    "bench-plan-not-planned": "HabitVQModule is not PretrainModule or ControlNetModule; the planner covers",
    "bench-plan-python-tag": "--configs {in}/python_tag.yaml: the YAML tag !!python/object/apply:os.system at line 1 "
                             "is not allowed",
    "bench-plan-global-batch-gpus": "pretrain_base: global batch 256 is not a multiple of micro-batch 32 x --gpus 3",
    "bench-gpu-few-steps": "--train_steps must be above the 5 untimed warm-up steps, got 5",
    "bench-gpu-shards-missing": "--shards {in}/nope: no train/manifest.json",
    "bench-sample-frames-neg": "frames: expected an integer >= 1, got '-1'",
    "bench-data-batches-zero": "batches: expected an integer >= 1, got '0'",
    "bench-data-batches-nan": "batches: expected an integer >= 1, got 'nan'",
    "bench-data-batch-size-zero": "batch_size: expected an integer >= 1, got '0'",
    "bench-data-clips-zero": "clips: expected an integer >= 1, got '0'",
    "bench-data-clips-below-batch": "--clips gives 3 clips, fewer than --batch_size 4",
    "bench-data-feature-dim-zero": "feature_dim: expected an integer >= 1, got '0'",
    "bench-data-workers-neg": "workers: expected an integer >= 0, got '-1'",
    "bench-data-sample-interval-zero": "sample_interval: expected a finite number > 0, got '0'",
    "bench-data-max-len-zero": "max_len: expected an integer >= 60 (frames: the shortest window the benchmark cuts), "
                               "got '0'",
    "bench-data-cache-mb-negative": "--cache_mb must be >= 0 MiB (0: decode every shard at each read), got -1.0",
    "bench-data-max-len-below-window": "max_len: expected an integer >= 60 (frames: the shortest window the benchmark "
                                       "cuts), got '40'",
    "bench-data-shards-missing": "--shards: shards '{in}/nope': no such directory or file",
    "bench-data-shards-not-shards": "--shards: no manifest.json in {in}/empty;",
    "bench-data-shards-file": "--shards {in}/afile: no manifest.json in {in};",  # a file is read as a shard pattern
    "bench-data-shards-below-batch": f"--shards {MINI_SHARDS} (its manifest) gives 90 clips, fewer than --batch_size "
                                     "100000",
    "bench-train-steps-zero": "steps: expected an integer >= 1, got '0'",
    "bench-train-steps-nan": "steps: expected an integer >= 1, got 'nan'",
    "bench-train-batch-zero": "batch_size: expected an integer >= 1, got '0'",
    "bench-train-frames-zero": "frames: expected an integer >= 1, got '0'",
    "bench-train-warmup-neg": "warmup: expected an integer >= 0, got '-1'",
    "bench-train-peak-zero": "peak_tflops: expected a finite number > 0, got '0'",
    "bench-train-peak-inf": "peak_tflops: expected a finite number > 0, got 'inf'",
    "bench-train-peak-neg": "peak_tflops: expected a finite number > 0, got '-5'",
    "bench-train-precision-banana": "precision: expected one of 32-true, ",  # then the rest of Lightning's list
    "bench-train-strategy-banana": "--strategy 'banana': not one of Lightning's strategies",
    "bench-train-flavor-banana": "flavor: expected one of mini, base, large, huge, giant, got 'banana'",
    "bench-sample-batch-sizes-letters": "batch_sizes: expected a list such as [a, b] with each item an integer >= 1, "
                                        "got '[a, b]'",
    "bench-sample-batch-sizes-zero": "batch_sizes: expected a list such as [a, b] with each item an integer >= 1, "
                                     "got '[0]'",
    "bench-sample-batch-sizes-neg": "batch_sizes: expected a list such as [a, b] with each item an integer >= 1, "
                                    "got '[1, -8]'",
    "bench-sample-batch-sizes-gap": "batch_sizes: expected a list such as [a, b] with each item an integer >= 1, "
                                    "got '[1,,8]'",
    "bench-sample-batch-sizes-not-list": "batch_sizes: expected a list such as [a, b] with each item an integer >= 1, "
                                         "got '1,8'",
    "bench-sample-batch-sizes-empty": "batch_sizes: expected a list such as [a, b] with each item an integer >= 1, "
                                      "got ''",
    "bench-sample-batch-sizes-nan": "batch_sizes: expected a list such as [a, b] with each item an integer >= 1, "
                                    "got '[nan]'",
    "bench-sample-steps-zero": "--steps 0 times nothing: give --steps 1 or more, or --token_steps N",
    "bench-sample-steps-too-many": "--steps must be in 1..1000 (the model's diffusion steps), got 100000",
    "bench-sample-steps-nan": "steps: expected an integer >= 0, got 'nan'",
    "bench-sample-frames-zero": "frames: expected an integer >= 1, got '0'",
    "bench-sample-token-steps-neg": "token_steps: expected an integer >= 0, got '-1'",
    "bench-sample-flavor-banana": "flavor: expected one of mini, base, large, huge, giant, got 'banana'",
    "bench-sample-text-encoder-banana": "unknown text encoder 'banana'; known text encoders:",
    "bench-sample-precision-banana": "precision: expected one of fp32, bf16-mixed, bf16, got 'banana'",
    "bench-following-input-missing": "the bvh-dir source needs --input FOLDER with motion files, got '{in}/nope'",
    "bench-following-input-no-labels": "--input {in}: no clip has a 'content' label with targets in the prompt file",
    "bench-following-prompts-missing": "the prompt file {in}/nope.yaml: no such file",
    "bench-following-prompts-binary": "the prompt file {in}/elf.bin: not a UTF-8 text file (byte 0xff",
    "bench-following-fps-nan": "fps: expected a finite number > 0, got 'nan'",
    "bench-sides-manifest-missing": "--manifests: {in}/nope.json is not a clip manifest",
    "bench-sides-manifest-binary": "--manifests: {in}/elf.bin is not a clip manifest",
    "bench-sides-prompts-missing": "the prompt file {in}/nope.yaml: no such file",
    "bench-sides-no-captions": "--manifests or --prompts: no captions to measure",
    "bench-sides-encoder-option": "--encoders: 'hash:dim': options are key=value pairs",
    "bench-timeline-prior": "--ckpt {pre}: a timeline needs a text-conditioned (ControlNet) checkpoint",
    "bench-timeline-val-without-actions": f"--val {MINI_VAL}: fewer than two actions with targets among its "
                                          "captions ('content' labels)",
    "bench-rig-data-is-file": "--data {in}/afile: not a folder (the motion data folder",
    "bench-rig-data-without-clips": "--data {in}/empty: none of the benchmark's clips is there",
    "bench-character-not-fbx": "--fbx {in}/afile: give an .fbx character",
    "bench-character-fbx-missing": "--fbx {in}/nope.fbx: no such file",
    "serve-out-is-file": "--out {in}/afile: not a folder",
    "serve-out-in-proc": "--out /proc/omg-out: cannot write in /proc",
    "serve-allowed-hosts-port": "--allowed_hosts 'localhost:8000': give host names or addresses without a port",
    "joint-map-rig-missing": "RIG {in}/nope.bvh: no such file",
    "joint-map-rig-not-bvh": "RIG {in}/afile: the rig must be a .bvh file (its HIERARCHY is the rig), a skinned glTF",
    "joint-map-target-banana": "target: expected one of smpl22, smal35",
    "joint-map-motion-missing": "RIG {in}/nope.txt: no such file",
    "joint-map-motion-not-deepmimic": 'RIG {in}/latin1.txt: not a DeepMimic motion (a JSON object with "Frames")',
    "plot-run-missing": "RUN {in}/nope: no such folder; give a run folder",
    "plot-run-without-metrics": "RUN {in}: no metrics.csv in it or in a version_N folder of it",
}


def _tree(root: Path) -> dict[str, tuple]:
    """Every file and folder under root, with size and modification time of the files."""
    tree = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames:
            tree[os.path.relpath(os.path.join(dirpath, name), root)] = ("dir",)
        for name in filenames:
            stat = os.stat(os.path.join(dirpath, name))
            tree[os.path.relpath(os.path.join(dirpath, name), root)] = (stat.st_size, stat.st_mtime_ns)
    return tree


@pytest.mark.parametrize("name, argv", ROWS, ids=[name for name, _ in ROWS])
def test_bad_input_is_one_line_exit_2_and_leaves_nothing(name, argv, ckpts, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # default output folders would land here
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # `omg fit` sets it for LightningCLI
    _write_inputs(tmp_path / "in", tmp_path / "out")
    before = _tree(tmp_path)
    fields = {"in": tmp_path / "in", "out": tmp_path / "out", **ckpts}
    argv = [a.format(**fields) for a in argv]

    with pytest.raises(SystemExit) as e:
        main(argv)
    captured = capsys.readouterr()
    # the error is one line; a generation's progress lines (``motion 1 of 1 made in 2 steps``) may come before it
    lines = [line for line in captured.err.splitlines() if line.strip() and not PROGRESS.match(line)]
    assert e.value.code == 2, captured.err[-3000:]
    assert "Traceback" not in captured.out + captured.err
    assert len(lines) == 1 and lines[0].startswith("omg: error: "), captured.err[-3000:]
    assert SAYS[name].format(**fields) in lines[0], "not the check the row is for"
    assert _tree(tmp_path) == before, "the failed run left files behind or changed them"


def test_the_table_covers_every_command():
    commands = {argv[0] if argv[0] not in ("shards", "bench") else " ".join(argv[:2]) for _, argv in ROWS}
    assert commands == {"generate", "export", "shards build", "shards synth", "shards merge", "shards inspect",
                        "transfer", "fit", "test", "bench data", "bench train", "bench sample", "bench following",
                        "bench sides", "bench plan", "bench gpu", "bench rig", "bench character", "bench timeline",
                        "serve", "plot", "joint-map"}
    assert len({name for name, _ in ROWS}) == len(ROWS)
    assert list(SAYS) == [name for name, _ in ROWS], "every row, in the table's order, has the words its line holds"


def _group(argv: list[str]) -> str:
    return {"test": "fit"}.get(argv[0], argv[0])  # shards build|synth|merge|inspect: one group


def _names_key(fragment: str, argv: list[str]) -> bool:
    """The fragment starts with an option the row gives (``--out …``, ``steps: …``)."""
    key = re.match(r"(?:--)?([A-Za-z_][\w.]*)", fragment)
    return key is not None and f"--{key.group(1)}" in {a.partition("=")[0] for a in argv}


def test_the_expected_words_tell_the_checks_apart():
    """Rows of different commands may not expect the same words (or words one of the other holds)
    unless both name the option the row gives: generic words ("not a folder", "is a directory")
    would pass for another command's check."""
    rows = dict(ROWS)
    for (a, argv_a), (b, argv_b) in itertools.combinations(ROWS, 2):
        says_a, says_b = SAYS[a], SAYS[b]
        if _group(argv_a) == _group(argv_b) or (says_a not in says_b and says_b not in says_a):
            continue
        assert _names_key(says_a, rows[a]) and _names_key(says_b, rows[b]), (a, b, says_a)
    assert all(len(says.strip()) >= 15 for says in SAYS.values())


def test_good_input_still_works(ckpts, tmp_path, capsys, monkeypatch):
    """The checks refuse only bad input: the same commands with sound values run (and write)."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "gen"
    main([*GEN, "--unconditional", "--ckpt", ckpts["pre"], "--out", str(out), "--seed", "0", "--device", "cpu"])
    assert (out / "sample_000.bvh").is_file() and json.loads((out / "generation.json").read_text())["seed"] == 0
    main([*GEN, "a person walks", "--ckpt", ckpts["cn"], "--out", str(out), "--guidance", "-0.5"])
    main(["export", str(out), "--no_preview", "--scale", "100", "--fps", "20"])
    config = tmp_path / "build.yaml"
    config.write_text(f"source: synth\nout: {tmp_path / 'shards'}\nfps: 20\nmax_mb: 1\nmax_clips: 2\n"
                      "option: {num_clips: 3, seed: 1}\n")
    main(["shards", "build", "--config", str(config)])
    assert (tmp_path / "shards/manifest.json").is_file()
    assert "Traceback" not in capsys.readouterr().err
    main(["bench", "sample", "--steps", "0", "--token_steps", "1", "--batch_sizes", "[1]", "--frames", "8"])
    captured = capsys.readouterr()  # --steps 0 with --token-steps: only the token padding is timed
    assert "trimming:" in captured.out and "Traceback" not in captured.err


def test_dashed_option_names_are_the_underscore_options(ckpts, tmp_path, capsys, monkeypatch):
    """Scripts of the CLI before jsonargparse spell options with dashes (--num-samples, --no-preview,
    --trainer.max-steps): the same options, for the tools and for omg fit; values are never rewritten."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    out = tmp_path / "gen"
    main(["generate", "--unconditional", "--ckpt", ckpts["pre"], "--out", str(out), "--num-samples", "2",
          "--batch-size", "1", "--steps", "2", "--length", "1", "--no-preview"])
    assert sorted(p.name for p in out.glob("sample_*.bvh")) == ["sample_000.bvh", "sample_001.bvh"]
    assert not (out / "preview.gif").exists()
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), "--trainer.max-steps", "7",
              "--data.batch-size", "5", "--model.init-args.ema-decay", "0.5", "--trainer.default-root-dir=--my-runs",
              "--data.train", "shards/--dashed-set", "--print-config"])
    assert e.value.code == 0
    config = yaml.safe_load(capsys.readouterr().out)
    assert config["trainer"]["max_steps"] == 7 and config["data"]["batch_size"] == 5
    assert config["model"]["init_args"]["ema_decay"] == 0.5
    assert config["trainer"]["default_root_dir"] == "--my-runs" and config["data"]["train"] == "shards/--dashed-set"
    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    help_text = capsys.readouterr().out
    assert "--num_samples" in help_text and "--num-samples" not in help_text  # help shows one spelling
