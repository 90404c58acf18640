"""``omg joint-map RIG``: for a rig no registered map fits, the closest map with each joint matched by
name, guessed (to check, with the reason) from the rig's hierarchy and rest pose or from what the registered
maps call it, or TODO; finished, it maps the rig; unfinished, it is refused in one line; the error for an
unfitted rig names the command. The rigs: the tests' own, their joints renamed (opaque ``j0``.., and other
studios' conventions), so that only their structure tells the joints."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import yaml

from helpers import BANDAI_RIG, DOG_RIG, REPO, SHARED_MOTION, rig_bvh
from helpers.characters import figure_rest
from omg.cli import main
from omg.errors import UsageError
from omg.retarget import detect_joint_map, load_joint_map, read_rig, read_rig_file, scaffold_joint_map

# the Bandai rig with names of another studio: thighs and shins no map calls so, hands and chest close to a map's
RENAMED = {"UpperLeg_L": "Thigh_L", "UpperLeg_R": "Thigh_R", "LowerLeg_L": "Shin_L", "LowerLeg_R": "Shin_R",
           "Hand_L": "hand.l", "Hand_R": "hand.r", "Chest": "Chest1"}


@pytest.fixture
def odd_rig(tmp_path):
    rows = [(RENAMED.get(n, n), RENAMED.get(p, p) if p else None, offset) for n, p, offset in BANDAI_RIG]
    path = tmp_path / "odd.bvh"
    path.write_text(rig_bvh(rows))
    return path


def _guessed(text: str) -> dict[str, tuple[str, str]]:
    """target joint -> (the rig's joint, why) of a scaffold's lines marked as guesses."""
    return {m[1]: (m[2], m[3]) for m in re.finditer(r'^  (\w+): +"([^"]+)"  # guessed: (.*); check$', text, re.M)}


def test_the_scaffold_matches_by_name_guesses_by_structure_and_the_map_maps_the_rig(odd_rig, tmp_path, capsys):
    with pytest.raises(UsageError, match=rf"closest 'bandai' lacks joints .*`omg joint-map {odd_rig}` starts one"):
        read_rig(odd_rig, "smpl22")
    main(["joint-map", str(odd_rig)])
    text = capsys.readouterr().out
    joints = yaml.safe_load(text)["joints"]
    assert joints["pelvis"] == "Hips" and joints["left_ankle"] == "Foot_L"  # the closest map's names, as they are
    guessed = _guessed(text)
    assert {k: v for k, (v, _) in guessed.items()} == {
        "spine3": "Chest1", "left_wrist": "hand.l", "right_wrist": "hand.r", "left_hip": "Thigh_L",
        "right_hip": "Thigh_R", "left_knee": "Shin_L", "right_knee": "Shin_R"}
    assert guessed["left_knee"][1] == ("the left leg (+X side: its joints' names say so; the rest pose agrees): "
                                       "between its thigh and shin")
    assert guessed["spine3"][1] == "the spine's joint the two arms branch from"
    assert "14 joints matched by name, 7 guessed (check them), 0 TODO" in text

    out = tmp_path / "maps/odd.yaml"
    main(["joint-map", str(odd_rig), "--out", str(out)])
    assert capsys.readouterr().out.startswith(f"wrote {out}: 14 joints matched, 7 guessed")
    assert load_joint_map(out).joints["left_knee"] == "Shin_L"
    rig = read_rig(odd_rig, "smpl22", out)  # the map as proposed takes the rig onto SMPL-22
    assert rig.names[0] == "joint_Root"


def _figure_rows(pose: str) -> list[tuple[str, str | None, tuple]]:
    """The tests' Mixamo-style figure (``helpers.characters``) as ``rig_bvh`` rows, in centimetres."""
    names, parents, rest = figure_rest(pose)
    short = [n.removeprefix("mixamorig:") for n in names]
    return [(short[j], short[p] if p >= 0 else None, tuple(100 * (rest[j] - (rest[p] if p >= 0 else 0))))
            for j, p in enumerate(parents)]


def _side_word(name: str) -> tuple[str | None, str]:
    for word in ("Left", "Right"):
        if name.startswith(word):
            return word, name.removeprefix(word)
    return None, name


# other conventions for the figure's joints: the side as a token, the rest of the name kept
RENAMINGS = {
    "opaque": lambda i, n: f"j{i}",
    "3dsmax": lambda i, n: "Bip01_" + (f"{s[0]}_" if (s := _side_word(n)[0]) else "") + _side_word(n)[1],
    "blender": lambda i, n: "DEF-" + _side_word(n)[1].lower() + (f".{s[0]}" if (s := _side_word(n)[0]) else ""),
    "vrm": lambda i, n: f"J_Bip_{(_side_word(n)[0] or 'C')[0]}_{_side_word(n)[1]}",
    "lowercase": lambda i, n: (f"{s[0].lower()}_" if (s := _side_word(n)[0]) else "") + _side_word(n)[1].lower(),
}
JOINT_MAPS = REPO / "omg/joint_maps"
MIXAMO = {k: v.removeprefix("mixamorig:") for k, v in load_joint_map(JOINT_MAPS / "mixamo.yaml").joints.items()}
BANDAI = load_joint_map(JOINT_MAPS / "bandai.yaml").joints


def _renamed(tmp_path, rows, rename) -> tuple[str, dict[str, str], dict[str, int]]:
    """The scaffold of the rig of ``rows`` with each joint renamed: its text, its joints, its counts; and the
    renaming."""
    new = {n: rename(i, n) for i, (n, _, _) in enumerate(rows)}
    path = tmp_path / "renamed.bvh"
    path.write_text(rig_bvh([(new[n], new.get(p), offset) for n, p, offset in rows]))
    text, counts = scaffold_joint_map(read_rig_file(path))
    return text, new, counts


@pytest.mark.parametrize("pose", ["T", "A"])
@pytest.mark.parametrize("convention", sorted(RENAMINGS))
def test_a_figure_with_names_no_map_knows_is_scaffolded_by_its_structure(tmp_path, pose, convention):
    text, new, counts = _renamed(tmp_path, _figure_rows(pose), RENAMINGS[convention])
    assert yaml.safe_load(text)["joints"] == {k: new[v] for k, v in MIXAMO.items()}
    assert counts == {"matched": 0, "guessed": 22, "todo": 0}


def test_a_figure_z_up_facing_minus_x_is_scaffolded_by_its_structure(tmp_path):
    """Up, forward and left are read from the rest pose, not assumed: the figure turned Z up, facing -X (its
    left on -Y), opaque names."""
    turn = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # Y up, facing +Z -> Z up, facing -X
    rows = [(n, p, tuple(turn @ np.array(offset))) for n, p, offset in _figure_rows("A")]
    text, new, counts = _renamed(tmp_path, rows, RENAMINGS["opaque"])
    assert yaml.safe_load(text)["joints"] == {k: new[v] for k, v in MIXAMO.items()}
    assert "the left leg (-Y side: facing -X, where the toes point, +Z up)" in text


def test_a_rig_standing_on_a_root_at_its_feet_is_scaffolded_by_its_structure(tmp_path):
    """The Bandai rig's root is on the floor, between the feet: the pelvis is where the legs branch."""
    text, new, counts = _renamed(tmp_path, BANDAI_RIG, RENAMINGS["opaque"])
    assert yaml.safe_load(text)["joints"] == {k: new[v] for k, v in BANDAI.items()}
    assert counts == {"matched": 0, "guessed": 21, "todo": 0}


@pytest.mark.parametrize("clip", ["01_01", "131_01"])
def test_real_mocap_rigs_with_opaque_names_are_scaffolded_by_their_structure(clip):
    """CMU's BVH rigs (cgspeed's names, and 3ds Max's: arms hanging down, joints at their parent's place),
    every joint renamed ``j0``..: the scaffold proposes the joints their registered map names."""
    path = SHARED_MOTION / f"human/cmu/{clip}.bvh"
    if not path.exists():
        pytest.skip(f"real motion data not found at {SHARED_MOTION}")
    rig = read_rig_file(path)
    truth = detect_joint_map(rig).joints
    new = {n: f"j{i}" for i, n in enumerate(rig.names)}
    text, counts = scaffold_joint_map(dataclasses.replace(rig, names=[new[n] for n in rig.names]), "smpl22")
    assert yaml.safe_load(text)["joints"] == {k: new[v] for k, v in truth.items()}
    assert counts == {"matched": 0, "guessed": 19, "todo": 0}


@pytest.mark.parametrize("clip", ["human/bandai1/dataset-1_walk_normal_001.bvh",
                                  "quadruped/mann_dog/D1_004_KAN01_001.bvh"])
def test_a_rig_whose_rest_pose_is_no_standing_biped_gets_no_guess(clip):
    """The Bandai-Namco BVHs' rest pose (every rotation zero) lies along each joint's own axes, the MANN dog is
    a quadruped: with opaque names, nothing is proposed, on either skeleton."""
    path = SHARED_MOTION / clip
    if not path.exists():
        pytest.skip(f"real motion data not found at {SHARED_MOTION}")
    rig = read_rig_file(path)
    opaque = dataclasses.replace(rig, names=[f"j{i}" for i in range(rig.num_joints)])
    for target in ("smpl22", "smal35"):
        assert scaffold_joint_map(opaque, target)[1]["guessed"] == 0


def test_what_the_structure_does_not_tell_stays_todo(tmp_path, capsys):
    """Feet that point nowhere (no toes, end sites straight down), opaque names: the centre line is found, left
    and right are not, and stay TODO; the unfinished map is refused in one line. A dog is no biped: nothing."""
    flat = [row for row in BANDAI_RIG if not row[0].startswith("Toes")]
    text, new, counts = _renamed(tmp_path, flat, RENAMINGS["opaque"])
    joints = yaml.safe_load(text)["joints"]
    assert {k: v for k, v in joints.items() if v != "TODO"} == {
        "pelvis": new["Hips"], "spine1": new["Spine"], "spine3": new["Chest"], "neck": new["Neck"],
        "head": new["Head"]}
    assert counts == {"matched": 0, "guessed": 5, "todo": 14}
    assert re.search(r"^  left_hip: +TODO  # .*; the rig has no such joint, and its rest pose does not tell left "
                     "from right$", text, re.M)
    out = tmp_path / "flat.yaml"
    out.write_text(text)
    with pytest.raises(UsageError, match=r"left_hip is TODO \(no joint of the rig was matched to it\)"):
        read_rig(tmp_path / "renamed.bvh", "smpl22", out)  # unfinished: one line, the first joint left

    dog = [(f"j{i}", None if p is None else f"j{[n for n, _, _ in DOG_RIG].index(p)}", offset)
           for i, (_, p, offset) in enumerate(DOG_RIG)]
    (tmp_path / "dog.bvh").write_text(rig_bvh(dog))
    main(["joint-map", str(tmp_path / "dog.bvh"), "--target", "smpl22"])
    text = capsys.readouterr().out
    assert "0 joints matched by name, 0 guessed" in text and "its rest pose shows no standing biped" in text


def test_a_rig_a_map_fits_is_all_matched_and_the_target_can_be_chosen(tmp_path, capsys):
    dog = tmp_path / "dog.bvh"
    dog.write_text(rig_bvh(DOG_RIG))
    main(["joint-map", str(dog)])
    text = capsys.readouterr().out
    assert "target: smal35" in text and "0 guessed (check them), 0 TODO" in text and "'mann_dog'" in text
    main(["joint-map", str(dog), "--target", "smpl22"])  # a dog's names onto the human skeleton: mostly TODO
    assert "target: smpl22" in capsys.readouterr().out
