"""``omg joint-map RIG``: for a rig no registered map fits, the closest map with each joint matched by
name, guessed (to check, with the reason) from the rig's hierarchy and rest pose or from what the registered
maps call it, or TODO; finished, it maps the rig; unfinished, it is refused in one line; the error for an
unfitted rig names the command. The rigs: the tests' own and real ones (CMU and Bandai-Namco mocap, the MANN and
DeepMimic dogs), their joints renamed (opaque ``j0``.., and other studios' conventions), so that only their
structure tells the joints; a quadruped gets SMAL-35 joints, a biped SMPL-22 ones, never the other's; a rig whose
rest pose stands on no legs is read in a frame of its clip."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch
import yaml

from helpers import BANDAI_RIG, DOG_RIG, REPO, SHARED_MOTION, rig_bvh
from helpers.characters import figure_rest
from omg.cli import main
from omg.errors import UsageError
from omg.io.bvh import write_bvh
from omg.io.read import read_motion
from omg.retarget import (
    _side,
    detect_joint_map,
    get_joint_map,
    load_joint_map,
    read_rig,
    read_rig_file,
    retarget,
    scaffold_joint_map,
)
from omg.rig_structure import humanoid_joints
from omg.rotations import quat_apply, quat_between, quat_conjugate, quat_mul

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


def test_what_the_structure_does_not_tell_stays_todo(tmp_path, capsys):
    """Feet that point nowhere (no toes, end sites straight down), opaque names: the centre line is found, left
    and right are not, and stay TODO; the unfinished map is refused in one line. A dog is no biped: nothing
    on SMPL-22, and the TODO says what it is."""
    flat = [row for row in BANDAI_RIG if not row[0].startswith("Toes")]
    text, new, counts = _renamed(tmp_path, flat, RENAMINGS["opaque"])
    joints = yaml.safe_load(text)["joints"]
    assert {k: v for k, v in joints.items() if v != "TODO"} == {
        "pelvis": new["Hips"], "spine1": new["Spine"], "spine3": new["Chest"], "neck": new["Neck"],
        "head": new["Head"]}
    assert counts == {"matched": 0, "guessed": 5, "todo": 14}
    assert re.search(r"^  left_hip: +TODO  # .*; the rig has no such joint, and its pose does not tell left "
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
    assert "0 joints matched by name, 0 guessed" in text
    assert "its structure shows a smal35 rig, no standing biped" in text


def test_a_rig_a_map_fits_is_all_matched_and_the_target_can_be_chosen(tmp_path, capsys):
    dog = tmp_path / "dog.bvh"
    dog.write_text(rig_bvh(DOG_RIG))
    main(["joint-map", str(dog)])
    text = capsys.readouterr().out
    assert "target: smal35" in text and "0 guessed (check them), 0 TODO" in text and "'mann_dog'" in text
    main(["joint-map", str(dog), "--target", "smpl22"])  # a dog's names onto the human skeleton: mostly TODO
    assert "target: smpl22" in capsys.readouterr().out


# the real dogs and their registered (hand-written) maps
DOGS = {"mann_dog": "quadruped/mann_dog/D1_010_KAN01_001.bvh",
        "deepmimic_dog": "quadruped/deepmimic_dog/dog3d_trot.txt"}
# other conventions for a dog's joints: nothing but a number; Blender's side suffix; Maya-like prefixes omg reads no
# side in (``Lf_``), so that the pose alone tells left from right
DOG_NAMINGS = {
    "opaque": lambda i, n: f"joint_{i}",
    "blender": lambda i, n: f"bone{i:02d}" + {"left": ".L", "right": ".R", None: ""}[_side(n)],
    "maya": lambda i, n: {"left": "Lf_", "right": "Rt_", None: "Ct_"}[_side(n)] + f"jnt{i}",
}


def _real(rel: str):
    path = SHARED_MOTION / rel
    if not path.exists():
        pytest.skip(f"real motion data not found at {SHARED_MOTION}")
    return read_motion(path)


def _renamed_rig(rig, rename) -> tuple:
    """``rig`` with each joint renamed, and old -> new of every name a map can use (end sites follow)."""
    new = {n: rename(i, n) for i, n in enumerate(rig.names)}
    out = dataclasses.replace(rig, names=[new[n] for n in rig.names])
    return out, {**new, **dict(zip(rig.end_site_names(), out.end_site_names()))}


@pytest.mark.parametrize("naming", sorted(DOG_NAMINGS))
@pytest.mark.parametrize("dog", sorted(DOGS))
def test_real_quadruped_rigs_with_names_no_map_knows_are_scaffolded_by_their_structure(dog, naming):
    """The MANN dog (its rest pose lays every bone along +X: read in its own frames) and the DeepMimic dog (standing
    at rest), renamed: the scaffold proposes SMAL-35 and the joints of their hand-written maps, every one."""
    rig, new = _renamed_rig(_real(DOGS[dog]), DOG_NAMINGS[naming])
    text, counts = scaffold_joint_map(rig)
    assert "target: smal35" in text and "shows a quadruped standing on four legs (smal35)" in text
    assert yaml.safe_load(text)["joints"] == {k: new[v] for k, v in get_joint_map(dog).joints.items()}
    assert counts == {"matched": 0, "guessed": 24, "todo": 0}
    assert ("in its frame" if dog == "mann_dog" else "in its rest pose (every rotation zero)") in text
    how = "its joints' names say so; the pose agrees" if naming == "blender" else "facing"
    assert re.search(rf"^  LLegBack2: +\S+  # guessed: the left hind leg \([+-][XYZ] side: {how}", text, re.M)


def test_a_dog_never_gets_a_human_map_nor_a_human_a_dog_map():
    """Both directions, opaque names: the dogs onto SMPL-22 and real human rigs (standing at rest, and the
    Bandai-Namco rig read in its frames) onto SMAL-35 get no guess, and the TODOs say what the rig is."""
    for rel in DOGS.values():
        dog, _ = _renamed_rig(_real(rel), DOG_NAMINGS["opaque"])
        text, counts = scaffold_joint_map(dog, "smpl22")
        assert counts["guessed"] == 0 and "its structure shows a smal35 rig, no standing biped" in text
    for rel in ("human/cmu/01_01.bvh", "human/bandai1/dataset-1_walk_normal_001.bvh"):
        human, new = _renamed_rig(_real(rel), DOG_NAMINGS["opaque"])
        text, counts = scaffold_joint_map(human, "smal35")
        assert counts["guessed"] == 0 and "its structure shows a smpl22 rig, no quadruped standing" in text
        text, counts = scaffold_joint_map(human)
        assert "target: smpl22" in text and counts["todo"] == 0
        assert yaml.safe_load(text)["joints"] == {k: new[v] for k, v in detect_joint_map(_real(rel)).joints.items()}


def _along_own_axes(rig):
    """``rig`` with each joint's rest frame turned so that its first bone (or end site) lies along its own +X, as
    the Bandai-Namco and MANN rigs are built: every rotation zero, it stands on no legs; the frames turn back by as
    much, so that the motion is the same."""
    turn = torch.zeros(rig.num_joints, 4, dtype=torch.float64)
    turn[:, 0] = 1.0
    for j in range(rig.num_joints):
        bone = next((rig.offsets[c] for c, p in enumerate(rig.parents) if p == j),
                    next((o for p, o in rig.end_sites if p == j), None))
        if bone is not None and np.linalg.norm(bone) > 0:
            turn[j] = quat_between(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.from_numpy(bone))
    back = quat_conjugate(turn)  # (J, 4)
    of_parent = torch.stack([back[p] if p >= 0 else torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
                             for p in rig.parents])
    offsets = quat_apply(of_parent, torch.from_numpy(rig.offsets)).numpy()
    offsets[0] = rig.offsets[0]
    q = torch.from_numpy(rig.rotations)  # (T, J, 4)
    rotations = quat_mul(quat_mul(of_parent.expand_as(q), q), turn.expand_as(q)).numpy()
    return rotations, offsets


def test_a_rig_whose_rest_pose_stands_on_no_legs_is_read_in_its_frames(tmp_path, capsys):
    """A real clip's rig (CMU 02_01) written with every bone along its joint's own axis, the frames compensating
    (the same motion), names opaque: the rest pose shows nothing; the scaffold reads a frame and proposes the
    registered map's joints, saying which pose it read."""
    rig = _real("human/cmu/02_01.bvh")
    rotations, offsets = _along_own_axes(rig)
    names = [f"j{i}" for i in range(rig.num_joints)]
    path = write_bvh(tmp_path / "flat.bvh", rig.skeleton().from_parents("flat", rig.parents, offsets, names),
                     rotations, rig.translations[:, 0], rig.fps, offsets, scale=100)
    flat = read_rig_file(path)
    by_name = [flat.names.index(n) for n in names]  # the file lists joints depth first
    assert np.abs(flat.positions()[:, by_name] - rig.positions()).max() < 1e-4  # the same motion
    assert humanoid_joints(flat, _side) == {}  # its rest pose: no standing biped
    main(["joint-map", str(path)])
    text = capsys.readouterr().out
    new = dict(zip(rig.names, names))
    assert yaml.safe_load(text)["joints"] == {k: new[v] for k, v in get_joint_map("cmu").joints.items()}
    assert "Its structure shows a standing biped (smpl22) in its frame" in text


def test_the_proposed_map_of_a_real_dog_retargets_it_as_its_hand_map(tmp_path, capsys):
    """The MANN dog's BVH file with opaque joint names: unfitted, the error names the command; `omg joint-map`
    proposes a map onto smal35 that loads and takes the clip onto SMAL-35 where the hand-written map does."""
    source = SHARED_MOTION / DOGS["mann_dog"]
    hand = retarget(_real(DOGS["mann_dog"]), "smal35", "mann_dog")
    names = iter(range(1000))
    dog = tmp_path / "dog.bvh"
    dog.write_text(re.sub(r"^(\s*(?:ROOT|JOINT)\s+)\S+", lambda m: f"{m[1]}joint_{next(names)}",
                          source.read_text(), flags=re.M))
    with pytest.raises(UsageError, match=rf"`omg joint-map {dog}` starts one"):
        read_rig(dog, "smal35")
    out = tmp_path / "dog.yaml"
    main(["joint-map", str(dog), "--out", str(out)])
    assert capsys.readouterr().out.startswith(f"wrote {out}: 0 joints matched, 24 guessed")
    assert load_joint_map(out).target == "smal35"
    proposed = retarget(read_rig_file(dog), "smal35", out)
    assert np.abs(proposed.positions - hand.positions).max() < 1e-6
    assert read_rig(dog, "smal35", out).names[0] == "joint_0"  # and onto the rig, the other way


def test_a_dog_with_ears_a_neck_and_no_tail_gets_them_proposed_and_the_tail_todo(tmp_path):
    """The tests' dog rig (its left turned to -Z, where up x forward puts it) with a second neck joint, ears and a
    nose, and no tail, opaque names: the neck and the ears are proposed on lines of their own (the maps leave them
    to be filled in), the tail stays TODO saying why."""
    rows = [(n, p, (x, y, -z)) for n, p, (x, y, z) in DOG_RIG if not n.startswith("Tail") and n != "Head"] + [
        ("Neck1", "Neck", (8, 3, 0)), ("Head", "Neck1", (8, 3, 0)), ("Nose", "Head", (10, -3, 0)),
        ("LeftEar", "Head", (-2, 6, -4)), ("RightEar", "Head", (-2, 6, 4))]
    text, new, counts = _renamed(tmp_path, rows, RENAMINGS["opaque"])
    joints = yaml.safe_load(text)["joints"]
    assert {k: joints[k] for k in ("Neck", "Head", "Mouth", "LEar", "REar")} == {
        "Neck": new["Neck"], "Head": new["Head"], "Mouth": new["Nose"] + "_end", "LEar": new["LeftEar"],
        "REar": new["RightEar"]}
    assert joints["pelvis"] == new["Hips"] and joints["LLegBack1"] == new["LeftUpLeg"]
    assert re.search(r"^  Tail1: +TODO  # .*; the rig has no such joint, nor a joint there by its structure$", text,
                     re.M)
    assert counts == {"matched": 0, "guessed": 24, "todo": 3}



def test_the_proposed_map_of_the_deepmimic_dog_imports_its_clip_as_its_hand_map(tmp_path, capsys):
    """A DeepMimic motion (the dog's trot, its character file's joints renamed ``joint_N``) is a file `omg
    joint-map` reads too: the map it proposes imports the clip onto SMAL-35 where the hand-written map does."""
    source = SHARED_MOTION / DOGS["deepmimic_dog"]
    hand = retarget(_real(DOGS["deepmimic_dog"]), "smal35", "deepmimic_dog")
    character = source.with_name("char_dog3d.txt").read_text()
    names = {n: f"joint_{i}" for i, n in enumerate(dict.fromkeys(re.findall(r'"Name": "([^"]*)"', character)))}
    (tmp_path / "char_dog3d.txt").write_text(re.sub(r'"Name": "([^"]*)"', lambda m: f'"Name": "{names[m[1]]}"',
                                                    character))  # joints, bodies and shapes renamed alike
    dog = tmp_path / source.name
    dog.write_text(source.read_text())
    out = tmp_path / "dog.yaml"
    main(["joint-map", str(dog), "--out", str(out)])
    assert capsys.readouterr().out.startswith(f"wrote {out}: 0 joints matched, 24 guessed (check them), 0 TODO")
    proposed = retarget(read_motion(dog), "smal35", out)
    assert np.abs(proposed.positions - hand.positions).max() < 1e-6
