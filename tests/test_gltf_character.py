"""Motion onto a user's skinned glTF character (``--to_rig character.glb``): the output is the same
character with one animation added, its mesh follows the joints, bones keep their length, feet stand
on the ground, and the prompt-following check passes on the character's joints.

The characters are written by the tests (``helpers.characters``): a T-pose figure in metres with
Mixamo's names, and the same figure in an A-pose, in centimetres under a Z-up root node, every joint
node with its own rest rotation. The output files are read back with pygltflib and evaluated by the tests'
own numpy / scipy forward kinematics and linear-blend skinning (``helpers.characters.evaluate``),
independently of omg's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import torch

from helpers import SHARED_MOTION
from helpers.characters import M, evaluate, joint_places, write_character
from helpers.gltf_validator import validation_errors
from omg.export import export_motion
from omg.io.bvh import read_bvh
from omg.kinematics import ground_contacts
from omg.metrics.following import label_targets, passes
from omg.retarget import get_joint_map, onto_rig, read_rig, retarget
from omg.skeleton import get_skeleton

pytestmark = pytest.mark.xdist_group("gltf_character")  # the tests share the `written` fixture's characters and outputs

CLIPS = {  # Bandai-Namco takes, each passing its own label's targets on the model skeleton
    "wave-left-hand": "human/bandai2/dataset-2_wave-left-hand_normal_{}.bvh",
    "raise-up-right-hand": "human/bandai2/dataset-2_raise-up-right-hand_normal_{}.bvh",
    "walk-turn-left": "human/bandai2/dataset-2_walk-turn-left_normal_{}.bvh",
}
CHARACTERS = {"t_pose_m": {}, "a_pose_cm_z_up": {"pose": "A", "unit": 0.01, "z_up": True, "turned": True}}


def _clip_file(shared_motion: Path, label: str) -> Path:
    pattern = CLIPS[label]
    found = sorted((shared_motion / Path(pattern).parent).glob(Path(pattern.format("*")).name))
    assert found, pattern
    return found[0]


@pytest.fixture(scope="session")
def written(tmp_path_factory) -> dict:
    """Per character: its file, its rig, and per clip the model's clip, onto_rig's motion and the output .glb."""
    if not (SHARED_MOTION / "manifest.json").exists():
        pytest.skip(f"real motion data not found at {SHARED_MOTION} (the shared/ folder beside the checkout)")
    shared_motion = SHARED_MOTION
    root = tmp_path_factory.mktemp("characters")
    out = {}
    for name, options in CHARACTERS.items():
        path = write_character(root / f"{name}.glb", **options)
        rig = read_rig(path, "smpl22")
        motions = {}
        for label in CLIPS:
            clip = retarget(read_bvh(_clip_file(shared_motion, label)), "smpl22", fps=20)
            moved = onto_rig(clip.positions, "smpl22", rig, 20)
            report = export_motion(root / f"{name}_{label}", clip.positions, "smpl22", 20, rig=rig, format="glb",
                                   preview=False)
            motions[label] = (clip, moved, Path(report["glb"]))
        out[name] = (path, rig, motions)
    return out


def test_the_output_is_the_character_with_one_animation_added(written):
    """Every node, mesh, skin, material, texture, image, sampler, extension and byte of the input is kept;
    one animation is added, its channels on the skin's joint nodes only."""
    for name, (path, _, motions) in written.items():
        before = pygltflib.GLTF2().load(str(path))
        for _, _, glb in motions.values():
            after = pygltflib.GLTF2().load(str(glb))
            kept, now = json.loads(before.to_json()), json.loads(after.to_json())
            for key in set(kept) | set(now):
                if key not in ("accessors", "bufferViews", "buffers", "animations"):
                    assert now.get(key) == kept.get(key), (name, key)
            assert after.accessors[: len(before.accessors)] == before.accessors
            assert after.bufferViews[: len(before.bufferViews)] == before.bufferViews
            assert after.binary_blob()[: len(before.binary_blob())] == before.binary_blob()
            assert len(after.animations) == len(before.animations) + 1
            targets = {c.target.node for c in after.animations[-1].channels}
            assert targets == set(before.skins[0].joints), name


def test_the_mesh_follows_the_joints_and_bones_keep_their_length(written):
    """Linear-blend skinning of the output at every frame: each bone's box ends stay centred on its two
    joints, which are where onto_rig put them (the character's joints, read back through its nodes)."""
    for name, (path, rig, motions) in written.items():
        for label, (_, moved, glb) in motions.items():
            gltf, world, skinned = evaluate(glb)
            places = joint_places(gltf, world, rig.names)  # (T, J, 3)
            assert np.abs(places - moved.positions()).max() < 1e-4, (name, label)
            lengths = np.linalg.norm(places[:, 1:] - places[:, rig.parents[1:]], axis=-1)
            rest_lengths = np.linalg.norm(rig.offsets[1:], axis=-1)
            assert np.abs(lengths - rest_lengths).max() < 1e-4, (name, label)
            # the boxes: 8 vertices per bone (joints 1..J-1 in order), 4 around the parent joint, 4 around it
            for j in range(1, rig.num_joints):
                if rig.names[j].endswith(("ToeBase", "Toe_End")):  # their soles are flattened onto the ground
                    continue
                box = skinned[:, 8 * (j - 1): 8 * j]  # (T, 8, 3)
                assert np.abs(box[:, :4].mean(1) - places[:, rig.parents[j]]).max() < 1e-4, (name, label, j)
                assert np.abs(box[:, 4:].mean(1) - places[:, j]).max() < 1e-4, (name, label, j)


def test_feet_stand_on_the_ground(written):
    """Where the model's feet are planted, the mesh's lowest point (the soles, modelled on y = 0) is on the
    ground within 1 cm on every planted frame, heel or toes (measured: 0.01-0.02 cm median, 0.46 cm at most,
    in the walk's heel-to-toe roll); no foot goes through the floor on the others. With one ground for the clip
    and the model's foot bone's direction (the commit before), the walk's roll put them 1.96 cm off."""
    skel = get_skeleton("smpl22")
    for name, (_, _, motions) in written.items():
        for label, (clip, _, glb) in motions.items():
            _, _, skinned = evaluate(glb)
            contact = ground_contacts(torch.from_numpy(clip.positions).double(), skel.feet, 20).numpy().any(1)
            low = skinned[..., 1].min(1) * 100  # (T,) cm
            sole = np.abs(low[contact])
            assert np.median(sole) < 0.1 and sole.max() < 1.0, (name, label, np.round(np.sort(sole)[-5:], 2))
            assert low.min() > -1.0, (name, label, low.min())


def test_prompt_following_passes_on_the_characters_joints(written):
    """Each real take passes its label's targets on the model skeleton, and on the character's joints read
    from the output file (the Mixamo map's joints in SMPL-22's order): the retarget keeps sides, turns and
    hands (a left-hand wave stays left, on the A-pose, centimetre, Z-up figure too)."""
    targets = label_targets()
    jmap = get_joint_map("mixamo")
    order = [jmap.joints[n] for n in get_skeleton("smpl22").names]
    for name, (_, _, motions) in written.items():
        for label, (clip, _, glb) in motions.items():
            gltf, world, _ = evaluate(glb)
            on_character = torch.from_numpy(joint_places(gltf, world, order))
            for target in targets[label]:
                assert passes(torch.from_numpy(clip.positions), target, 20), (label, target)
                assert passes(on_character, target, 20), (name, label, target)


def test_a_gltf_with_its_buffer_beside_and_the_commands(written, tmp_path, capsys):
    """``omg export --to_rig character.gltf`` writes the character as .glb by default, the same as from the
    .glb; a file that is no glTF, or a glTF without a skin, is one line."""
    from omg.cli import main
    from omg.errors import UsageError

    gltf_path = write_character(tmp_path / "figure.gltf")
    clip, moved, _ = written["t_pose_m"][2]["wave-left-hand"]
    np.save(tmp_path / "wave.joints.npy", clip.positions[:40])
    main(["export", str(tmp_path / "wave.joints.npy"), "--to_rig", str(gltf_path), "--fps", "20", "--no_preview"])
    assert "on the rig of" in capsys.readouterr().out
    gltf, world, _ = evaluate(tmp_path / "wave.glb")
    rig = read_rig(gltf_path, "smpl22")
    expected = onto_rig(clip.positions[:40], "smpl22", rig, 20).positions()
    assert np.abs(joint_places(gltf, world, rig.names) - expected).max() < 1e-4
    assert gltf.images[0].bufferView is not None and gltf.materials[0].name == "skin"
    (tmp_path / "bad.glb").write_bytes(b"not a glb at all")
    with pytest.raises(UsageError, match="not a readable glTF 2.0 file"):
        read_rig(tmp_path / "bad.glb", "smpl22")
    bare = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0"), nodes=[pygltflib.Node(name="x")])
    bare.save(str(tmp_path / "bare.gltf"))
    with pytest.raises(UsageError, match="has no skin"):
        read_rig(tmp_path / "bare.gltf", "smpl22")
    with pytest.raises(UsageError, match="the rig is a human rig|quadruped|cannot map"):
        read_rig(gltf_path, "smal35")


def test_the_khronos_validator_finds_no_error(written, tmp_path):
    """Khronos' glTF validator (npm gltf-validator, installed by .ci/run into .ci/node) on what omg writes:
    the characters with their animation and a skeleton-only .glb, 0 errors."""
    clip, _, _ = written["t_pose_m"][2]["walk-turn-left"]
    skeleton = export_motion(tmp_path / "skeleton", clip.positions, "smpl22", 20, format="glb", preview=False)["glb"]
    assert validation_errors([glb for _, _, motions in written.values() for _, _, glb in motions.values()]
                             + [skeleton]) == {}


def test_mixamo_names_are_detected(written):
    _, rig, _ = written["a_pose_cm_z_up"]
    assert rig.names[0] == f"{M}Hips"
    from omg.retarget import detect_joint_map

    assert detect_joint_map(rig, "smpl22").name == "mixamo"


def test_a_character_saved_off_its_bind_pose_is_read_in_its_bind_pose(written, tmp_path):
    """The rest pose is the one the inverse bind matrices bind the mesh in, not the pose the nodes were saved
    in: the rig reads as the unposed figure, and the mesh follows the joints on the written file."""
    clean = read_rig(written["t_pose_m"][0], "smpl22")
    posed = read_rig(write_character(tmp_path / "posed.glb", posed=True), "smpl22")
    np.testing.assert_allclose(posed.rest_positions(), clean.rest_positions(), atol=1e-6)
    clip = written["t_pose_m"][2]["raise-up-right-hand"][0]
    report = export_motion(tmp_path / "raise", clip.positions[:30], "smpl22", 20, rig=posed, format="glb",
                           preview=False)
    gltf, world, skinned = evaluate(Path(report["glb"]))
    places = joint_places(gltf, world, posed.names)
    assert np.abs(places - onto_rig(clip.positions[:30], "smpl22", posed, 20).positions()).max() < 1e-4
    for j in range(1, posed.num_joints):
        if not posed.names[j].endswith(("ToeBase", "Toe_End")):
            assert np.abs(skinned[:, 8 * j - 4: 8 * j].mean(1) - places[:, j]).max() < 1e-4, posed.names[j]
