"""``omg joint-map RIG``: for a rig no registered map fits, the closest map with each joint matched by
name, guessed from what the registered maps call it (to check) or TODO; finished, it maps the rig;
unfinished, it is refused in one line; the error for an unfitted rig names the command."""

from __future__ import annotations

import re

import pytest
import yaml

from helpers import BANDAI_RIG, DOG_RIG, rig_bvh
from omg.cli import main
from omg.errors import UsageError
from omg.retarget import load_joint_map, read_rig

# the Bandai rig with names of another studio: thighs and shins no map calls so, hands and chest close to a map's
RENAMED = {"UpperLeg_L": "Thigh_L", "UpperLeg_R": "Thigh_R", "LowerLeg_L": "Shin_L", "LowerLeg_R": "Shin_R",
           "Hand_L": "hand.l", "Hand_R": "hand.r", "Chest": "Chest1"}


@pytest.fixture
def odd_rig(tmp_path):
    rows = [(RENAMED.get(n, n), RENAMED.get(p, p) if p else None, offset) for n, p, offset in BANDAI_RIG]
    path = tmp_path / "odd.bvh"
    path.write_text(rig_bvh(rows))
    return path


def test_the_scaffold_matches_guesses_and_marks_and_once_finished_maps_the_rig(odd_rig, tmp_path, capsys):
    with pytest.raises(UsageError, match=rf"closest 'bandai' lacks joints .*`omg joint-map {odd_rig}` starts one"):
        read_rig(odd_rig, "smpl22")
    main(["joint-map", str(odd_rig)])
    text = capsys.readouterr().out
    joints = yaml.safe_load(text)["joints"]
    assert joints["pelvis"] == "Hips" and joints["left_ankle"] == "Foot_L"  # the closest map's names, as they are
    assert {k: v for k, v in joints.items() if v == "TODO"} == dict.fromkeys(
        ["left_hip", "right_hip", "left_knee", "right_knee"], "TODO")
    guessed = {m.group(1): m.group(2) for m in re.finditer(r"^  (\w+): +\"([^\"]+)\"  # guessed", text, re.M)}
    assert guessed == {"spine3": "Chest1", "left_wrist": "hand.l", "right_wrist": "hand.r"}  # sides kept apart
    assert "14 joints matched by name, 3 guessed (check them), 4 TODO" in text

    out = tmp_path / "maps/odd.yaml"
    main(["joint-map", str(odd_rig), "--out", str(out)])
    assert capsys.readouterr().out.startswith(f"wrote {out}: 14 joints matched, 3 guessed")
    with pytest.raises(UsageError, match=r"left_hip is TODO \(no joint of the rig was matched to it\)"):
        read_rig(odd_rig, "smpl22", out)  # unfinished: one line, the first joint left
    rig_joint = {"hip": "Thigh", "knee": "Shin"}  # what the user writes where the scaffold says TODO
    finished = re.sub(r"^  (left|right)_(hip|knee):( +)TODO.*$",
                      lambda m: f"  {m[1]}_{m[2]}:{m[3]}{rig_joint[m[2]]}_{m[1][0].upper()}", out.read_text(),
                      flags=re.M)
    out.write_text(finished)
    assert load_joint_map(out).joints["left_knee"] == "Shin_L"
    rig = read_rig(odd_rig, "smpl22", out)  # the finished map takes the rig onto SMPL-22
    assert rig.names[0] == "joint_Root"


def test_a_rig_a_map_fits_is_all_matched_and_the_target_can_be_chosen(tmp_path, capsys):
    dog = tmp_path / "dog.bvh"
    dog.write_text(rig_bvh(DOG_RIG))
    main(["joint-map", str(dog)])
    text = capsys.readouterr().out
    assert "target: smal35" in text and "0 guessed (check them), 0 TODO" in text and "'mann_dog'" in text
    main(["joint-map", str(dog), "--target", "smpl22"])  # a dog's names onto the human skeleton: mostly TODO
    assert "target: smpl22" in capsys.readouterr().out
