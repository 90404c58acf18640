"""The bvh-dir source: the real manifest into shards (smpl22 and smal35), folders without a
manifest, and bad files skipped with counted reasons."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from helpers import BANDAI_RIG, TINY_BVH, rig_bvh
from helpers.unreadable import FIFO, TOO_LARGE, no_hang
from omg.cli import main
from omg.data.shards import resolved
from omg.data.sources.bvh_dir import SkippedClip, bvh_dir_source
from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES
from omg.motion import Clip
from omg.skeleton import SMAL35, SMPL22
from omg.tools.shards import build

GOOD = TINY_BVH
BAD = {
    "truncated.bvh": GOOD[: GOOD.index("0 90 0 0 0 0 0 0 0\n0")],
    "garbled.bvh": GOOD.replace("0 90 0 0 0 0 0 0 0\n0", "0 9x 0 0 0 0 0 0 0\n0"),
    "channels.bvh": GOOD.replace("Zrotation Xrotation Yrotation\n    End", "Zrotation Xrotation Wrotation\n    End"),
    "empty.bvh": GOOD[: GOOD.index("Frames: 2")] + "Frames: 0\nFrame Time: 0.05\n",
    "nan.bvh": GOOD.replace("0 90 0 0 0 0 0 0 0\n0", "0 nan 0 0 0 0 0 0 0\n0"),
    "bad_deepmimic.json": '{"Loop": "wrap", "Frames": [[0.1, 0, 0.9',
    "tiny.bvh": GOOD,  # reads, but no joint map fits
}


def _build_cli(shared: Path, out: Path, skeleton: str, representation: str) -> dict:
    main(["shards", "build", "--source", "bvh-dir", "--input", str(shared), "--skeleton", skeleton,
          "--representation", representation, "--fps", "20", "--out", str(out)])  # fmt: skip
    return json.loads((out / "manifest.json").read_text())


def test_real_manifest_builds(shared_motion, tmp_path, capsys):
    humans = _build_cli(shared_motion, tmp_path / "human", "smpl22", "humanml3d263")
    assert humans["num_clips"] == 75 and humans["skipped"] == {} and humans["fps"] == 20.0
    dogs = _build_cli(shared_motion, tmp_path / "dog", "smal35", "maa")
    assert dogs["num_clips"] == 13 and dogs["skipped"] == {} and dogs["skeleton"] == "smal35"
    out = capsys.readouterr().out
    assert "75 clips" in out and "13 clips" in out and "skipped 0" in out


@pytest.fixture
def folder(shared_motion, tmp_path) -> Path:
    """A folder without a manifest: real files (linked, not copied) plus bad ones."""
    d = tmp_path / "motions"
    (d / "sub").mkdir(parents=True)
    links = {
        "walk.bvh": "human/bandai1/dataset-1_walk_normal_001.bvh",
        "walk.txt": "human/deepmimic/humanoid3d_walk.txt",  # same id as walk.bvh
        "sub/humanoid3d_jog.txt": "human/deepmimic/humanoid3d_jog.txt",
        "sub/char_humanoid3d.txt": "human/deepmimic/char_humanoid3d.txt",
        "11.asf": "human/cmu/11.asf",
        "11_01.amc": "human/cmu/11_01.amc",
        "dog.bvh": "quadruped/mann_dog/D1_007_KAN01_001.bvh",
        "LICENSE.txt": "human/deepmimic/LICENSE_DeepMimic_MIT.txt",
        "char_humanoid3d.txt": "human/deepmimic/char_humanoid3d.txt",
    }
    for name, target in links.items():
        (d / name).symlink_to(shared_motion / target)
    (d / "walk.captions.txt").write_text("a person walks forward.\n\na person strolls.\n")
    for name, text in BAD.items():
        (d / "sub" / name).write_text(text)
    return d


def _run(folder: Path, skeleton=SMPL22, **options) -> tuple[dict[str, Clip], list[str]]:
    clips, errors = {}, []
    for item in resolved(bvh_dir_source(str(folder), skeleton, 20.0, **options)):  # read the lazy items
        if isinstance(item, Clip):
            clips[item.id] = item
        elif item is not None:
            assert isinstance(item, SkippedClip)
            errors.append(str(item))
    return clips, errors


def test_folder_without_manifest(folder):
    clips, errors = _run(folder)
    assert sorted(clips) == ["11_01", "sub/humanoid3d_jog", "walk"]  # the dog is not a human: passed over
    assert clips["walk"].texts == ["a person walks forward.", "a person strolls."] and clips["walk"].fps == 20.0
    assert clips["11_01"].texts == [] and clips["11_01"].category == "human"
    assert all(c.skeleton is SMPL22 for c in clips.values())
    reasons = sorted(e.split(": ")[0] for e in errors)
    assert reasons == ["bad motion file"] * 6 + ["duplicate clip id", "unmappable rig"]
    text = "\n".join(errors)
    for name in BAD:
        assert f"sub/{name}" in text  # every message names its file
    assert "unknown channel 'Wrotation'" in text and "zero frames" in text and "non-finite" in text
    assert "id 'walk' is already taken" in text and "tiny.bvh: cannot map the rig" in text

    dogs, errors = _run(folder, SMAL35)
    assert sorted(dogs) == ["dog"] and dogs["dog"].category == "dog"
    everything, errors = _run(folder, domain="all")  # the dog is tried on smpl22, and fails
    assert sorted(everything) == sorted(clips) and sum("dog.bvh: cannot map" in e for e in errors) == 1


def test_build_counts_skips(folder, tmp_path):
    [summary] = build("bvh-dir", tmp_path / "out", "humanml3d263", "smpl22", 20.0, input=str(folder))
    assert summary.clips == 3
    assert summary.skipped == {"bad motion file": 6, "duplicate clip id": 1, "unmappable rig": 1}


def test_manifest_duplicates_missing_and_options(shared_motion, tmp_path):
    d = tmp_path / "m"
    d.mkdir()
    (d / "a.bvh").symlink_to(shared_motion / "human/bandai1/dataset-1_bow_normal_001.bvh")
    clips = [
        {"id": "bow", "path": "a.bvh", "format": "bvh", "domain": "human", "texts": ["a person bows."],
         "labels": {"x": 1}},
        {"id": "bow", "path": "a.bvh", "format": "bvh", "domain": "human"},
        {"id": "gone", "path": "missing.bvh", "format": "bvh", "domain": "human"},
        {"id": "a_dog", "path": "a.bvh", "format": "bvh", "domain": "dog"},  # not for smpl22
    ]
    (d / "manifest.json").write_text(json.dumps({"clips": clips}))
    got, errors = _run(d)
    assert list(got) == ["bow"] and got["bow"].labels == {"x": 1} and got["bow"].texts == ["a person bows."]
    assert [e.split(": ")[0] for e in errors] == ["duplicate clip id", "missing file"]
    with pytest.raises(UsageError, match="maps onto 'smal35', but the build targets 'smpl22'"):
        bvh_dir_source(str(d), SMPL22, 20.0, joint_map="mann_dog")
    with pytest.raises(UsageError, match="needs --input FOLDER"):
        bvh_dir_source(str(d / "a.bvh"), SMPL22, 20.0)
    tall, _ = _run(d, height=1.9)
    assert tall["bow"].positions[..., 1].max() > got["bow"].positions[..., 1].max()


def test_fifo_and_huge_files_are_counted_skips(tmp_path):
    """A FIFO as a captions sidecar (read while the folder is scanned) or named like a motion, and a
    motion over the bound: each one counted skip, the other clips still imported."""
    d = tmp_path / "motions"
    d.mkdir()
    for name in ("bow", "walk"):
        (d / f"{name}.bvh").write_text(rig_bvh(BANDAI_RIG, frames=30))  # a human rig every map finds
    (d / "bow.captions.txt").write_text("a person bows.\n")
    os.mkfifo(d / "walk.captions.txt")  # reading it would wait for a writer forever
    os.mkfifo(d / "fifo.bvh")
    with open(d / "huge.bvh", "wb") as f:  # sparse: one byte over the bound, no disk used
        f.truncate(MOTION_MAX_BYTES + 1)
    with no_hang():
        clips, errors = _run(d)
        [summary] = build("bvh-dir", tmp_path / "out", "humanml3d263", "smpl22", 20.0, input=str(d))
    assert list(clips) == ["bow"] and clips["bow"].texts == ["a person bows."]
    assert summary.clips == 1 and summary.skipped == {"bad captions file": 1, "bad motion file": 2}
    for name, why in [("walk.captions.txt", FIFO), ("fifo.bvh", FIFO), ("huge.bvh", TOO_LARGE)]:
        assert any(name in e and why in e for e in errors), (name, errors)


def test_fifo_manifest_is_one_line(tmp_path):
    (tmp_path / "a.bvh").write_text(rig_bvh(BANDAI_RIG, frames=30))
    os.mkfifo(tmp_path / "manifest.json")
    with no_hang(), pytest.raises(UsageError) as error:
        bvh_dir_source(str(tmp_path), SMPL22, 20.0)
    assert str(error.value) == f"{tmp_path / 'manifest.json'}: {FIFO}; a file is expected"
