"""Habit transfer on AnimalML3D's categories: every species word the importer gives a clip has a description,
and configs/habit_animalml3d.yaml trains the habit model on shards built from an AnimalML3D-layout folder (here
written with synthetic motion: the release's motions are not public) through the commands a user runs."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from helpers import REPO, SHARED
from omg.rotations import axis_angle_to_quat, quat_to_6d
from omg.skeleton import SMAL35
from omg.text.habit import SpeciesBook
from omg.text.omgpt import animal_table, species_of

ANIMALML3D = SHARED / "data" / "animalml3d"
CONFIG = REPO / "configs" / "habit_animalml3d.yaml"


def _real(folder: str) -> Path:
    root = ANIMALML3D / folder
    if not root.is_dir():
        pytest.skip(f"the real AnimalML3D files are not at {root} (the shared/ folder beside the checkout)")
    return root


def test_every_species_the_importer_derives_from_the_real_captions_has_a_description():
    """AnimalML3D's 59 identities (its caption folders) name 34 species words; each is described (19 were not),
    and "milkcow10L" is the "milk cow" its captions say."""
    identities = {p.name.split("_")[0] for p in _real("motion_captions").iterdir()}
    words = {species_of(identity) for identity in identities}
    assert len(identities) == 59 and len(words) == 34 and None not in words
    assert species_of("milkcow10L") == "milk cow" and "milkcow" not in words
    book = SpeciesBook.load()
    assert sorted(w for w in words if w not in book) == []
    for word in words:  # a description of its own kind: sentences with a size
        assert book.description(word).count(". ") >= 1 and " kg" in book.description(word), word


def test_the_animalml3d_config_lists_the_species_of_the_identities_with_motion():
    """Its categories are the species of the 36 identities with offsets (the clips the importer can read)."""
    with_offsets = {p.name for p in _real("animals_maa_offsets").iterdir()}
    categories = yaml.safe_load(CONFIG.read_text())["model"]["init_args"]["categories"]
    assert len(with_offsets) == 36 and sorted(categories) == sorted({species_of(i) for i in with_offsets})
    assert len(categories) == 21 and "milk cow" in categories


def _maa(frames: int, seed: int) -> np.ndarray:
    """A smooth synthetic motion in the release's MAA layout (T, 36, 6): 35 6D rotations, then the root."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None, None]
    axis_angle = 0.25 * np.sin(2 * np.pi * t / rng.uniform(12, 24) + rng.uniform(0, 6.3, (1, 35, 3)))
    sixd = quat_to_6d(axis_angle_to_quat(torch.from_numpy(axis_angle))).numpy()  # (T, 35, 6)
    root = np.zeros((frames, 1, 6))
    root[:, 0, 0], root[:, 0, 1] = 0.03 * np.arange(frames), 0.5  # walking forward at hip height
    return np.concatenate([sixd, root], 1).astype(np.float32)


def _write_release(root: Path, identities: dict[str, str]) -> None:
    """Two clips of each identity in AnimalML3D's layout: motion, captions ("a <species> walks"), offsets."""
    for n, (identity, phrase) in enumerate(identities.items()):
        (root / "animals_maa_offsets" / identity).mkdir(parents=True)
        with open(root / "animals_maa_offsets" / identity / "offset.pkl", "wb") as f:
            pickle.dump(SMAL35.rest_offsets.astype(np.float64) * (0.6 + 0.2 * n), f)
        for k, action in enumerate(("Walk", "Trot")):
            name = f"{identity}_{action}"
            (root / "animals_maa_motions").mkdir(exist_ok=True)
            np.save(root / "animals_maa_motions" / f"{name}.npy", _maa(80, 10 * n + k))
            (root / "motion_captions" / name).mkdir(parents=True)
            (root / "motion_captions" / name / "screenshots.txt").write_text(f"{phrase} {action.lower()}s\n")


def test_the_animalml3d_config_trains_the_habit_model_on_animalml3d_layout_shards(tmp_path):
    """`omg shards build --source animalml3d` on an AnimalML3D-layout folder, `omg fit --config
    configs/habit_vqvae.yaml --config configs/habit_animalml3d.yaml` (tiny, a few steps of both phases), then
    `omg transfer --to "milk cow"`: the model knows AnimalML3D's categories by their captions' words."""
    from omg.cli import main
    from omg.data.datamodule import MotionDataModule
    from omg.data.loaders import ClipDataset

    release, shards = tmp_path / "AnimalML3D", tmp_path / "shards"
    identities = {"milkcow10L": "a milk cow", "foxXAT": "a fox", "bearPDD": "a pig", "deerA4K": "a deer"}
    _write_release(release, identities)
    main(["shards", "build", "--source", "animalml3d", "--input", str(release), "--out", str(shards),
          "--skeleton", "smal35", "--representation", "quatvel", "--fps", "20", "--val_where.identity", "deerA4K"])
    data = MotionDataModule(str(shards / "train"), verify_shards=False)
    clips = ClipDataset.from_shards(data.train_urls, data.feature_dim, data.windows).samples
    assert {c["meta"]["category"] for c in clips} == {"milk cow", "fox", "pig"}  # bearPDD's captions say "a pig"
    run = tmp_path / "run"
    main(["fit", "--config", str(REPO / "configs/habit_vqvae.yaml"), "--config", str(CONFIG),
          f"--data.train={shards / 'train'}", f"--data.val={shards / 'val'}", "--data.batch_size=4",
          "--data.num_workers=0", "--data.shuffle_buffer=8", "--data.batches_per_epoch=5",
          "--model.init_args.flavor=tiny", "--model.init_args.text_encoder=hash",
          "--model.init_args.text_encoder_args=null",
          "--trainer.max_steps=5", "--trainer.accelerator=cpu", "--trainer.limit_val_batches=0",
          f"--trainer.default_root_dir={run}", "--trainer.enable_progress_bar=false",
          "--trainer.enable_model_summary=false"])
    ckpt = run / "checkpoints" / "last.ckpt"
    hparams = torch.load(ckpt, map_location="cpu", weights_only=True)["hyper_parameters"]
    assert hparams["categories"] == yaml.safe_load(CONFIG.read_text())["model"]["init_args"]["categories"]
    assert hparams["species"]["descriptions"]["milk cow"] == SpeciesBook.load().description("cow")  # a dairy cow
    assert hparams["order"]["habit_order"] == "flow_prior"
    source = tmp_path / "fox.npy"
    np.save(source, np.asarray(next(c for c in clips if c["meta"]["category"] == "fox")["motion"], np.float32))
    main(["transfer", str(source), "--to", "milk cow", "--ckpt", str(ckpt), "--no_preview", "--out",
          str(tmp_path / "out")])
    settings = json.loads((tmp_path / "out" / "transfer.json").read_text())
    assert settings["category"] == "milk cow" and not settings["retrieved"]
    assert np.isfinite(np.load(tmp_path / "out" / "transfer.joints.npy")).all()
    assert "milk cow" in animal_table()[0].values()
