"""The committed shards/mini is what `omg shards synth` makes, and every sample is valid."""

from __future__ import annotations

import numpy as np

from helpers import REPO
from omg.data.shards import Manifest, decode_sample, iter_tar, validate
from omg.tools.shards import MINI_SETS

MINI = REPO / "shards" / "mini"


def _samples(shard_dir):
    return {s["key"]: s for p in Manifest.load(shard_dir).shard_paths for s in map(decode_sample, iter_tar(p))}


def test_committed_mini_data_is_valid_and_split():
    for subdir, skeleton, representation, _ in MINI_SETS:
        ids = {}
        for split in ("train", "val"):
            manifest, good, problems = validate(MINI / subdir / split)
            assert not problems and good == manifest["num_clips"] > 0
            assert ((manifest["skeleton"], manifest["representation"], manifest["fps"])
                    == (skeleton, representation, 20.0))
            ids[split] = set(_samples(MINI / subdir / split))
        assert not ids["train"] & ids["val"]


def test_committed_mini_data_matches_the_generator(tmp_path):
    from omg.tools.shards import main as shards_main

    shards_main(["synth", "--out", str(tmp_path)])
    for subdir, *_ in MINI_SETS:
        for split in ("train", "val"):
            committed, fresh = _samples(MINI / subdir / split), _samples(tmp_path / subdir / split)
            assert committed.keys() == fresh.keys()
            for key, sample in committed.items():
                assert (sample["texts"] == fresh[key]["texts"]
                        and sample["meta"]["labels"] == fresh[key]["meta"]["labels"])
                np.testing.assert_allclose(sample["motion"], fresh[key]["motion"], atol=1e-4)
