"""Motion onto a character made outside the project: Khronos' "Rigged Figure" sample (tests/data/characters/,
CC BY 4.0, © Cesium; its README says where from), a skinned, meshed figure whose joint names are no registered
map's (``torso_joint_1``, ``leg_joint_L_5``). ``omg joint-map`` proposes its map from the figure's structure;
RiggedFigure.joints.yaml is that map as a user finished it by hand. Motion goes onto it from ``omg generate``
and ``omg export``, as the glTF it is and as the FBX Blender makes of it (its importer, then its exporter, in
the test).

The glTF outputs are played by the tests' own forward kinematics and skinning (``helpers.characters.evaluate``),
the FBX ones by Blender (``helpers.blender_scenes``' probe), and compared here with numpy.
"""

from __future__ import annotations

import json

import numpy as np
import pygltflib
import pytest
import torch
import yaml

from helpers import REPO, SHARED_MOTION, TINY_DIT
from helpers.characters import evaluate, joint_places, read_accessor
from helpers.checkpoints import save_module
from helpers.gltf_validator import validation_errors
from omg.cli import main
from omg.errors import UsageError
from omg.io.bvh import read_bvh
from omg.kinematics import ground_contacts
from omg.retarget import onto_rig, read_rig, retarget
from omg.skeleton import get_skeleton

pytestmark = pytest.mark.xdist_group("outside")  # the tests share the `written` and `as_fbx` fixtures' runs
DATA = REPO / "tests/data/characters"
FIGURE = DATA / "RiggedFigure.gltf"
MAP = DATA / "RiggedFigure.joints.yaml"
WALK = "dataset-2_walk-turn-left_normal_*.bvh"


def _sample() -> pygltflib.GLTF2:
    """The sample as pygltflib reads it, its data URI buffer decoded into the binary blob."""
    gltf = pygltflib.GLTF2().load(str(FIGURE))
    gltf.convert_buffers(pygltflib.BufferFormat.BINARYBLOB)
    return gltf


def _walk() -> np.ndarray:
    """(T, 22, 3) a real Bandai-Namco walk on SMPL-22 at 20 fps."""
    found = sorted((SHARED_MOTION / "human/bandai2").glob(WALK))
    if not found:
        pytest.skip(f"real motion data not found at {SHARED_MOTION} (the shared/ folder beside the checkout)")
    return retarget(read_bvh(found[0]), "smpl22", fps=20).positions


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict:
    """``omg generate`` (a tiny untrained checkpoint, 2 s) and ``omg export`` (a real walk) onto the figure."""
    from omg.data.datamodule import MotionDataModule
    from omg.lit.pretrain import PretrainModule

    walk = _walk()
    root = tmp_path_factory.mktemp("outside")
    torch.manual_seed(0)
    spec = MotionDataModule(str(REPO / "shards/mini/human263/train"), batch_size=2, num_workers=0).spec
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec=spec, ema_decay=0)
    save_module(module, root / "pre.ckpt")
    main(["generate", "--unconditional", "--ckpt", str(root / "pre.ckpt"), "--steps", "2", "--length", "2",
          "--num_samples", "1", "--no_preview", "--device", "cpu", "--to_rig", str(FIGURE), "--joint_map", str(MAP),
          "--out", str(root / "generated")])
    np.save(root / "walk.joints.npy", walk)
    main(["export", str(root / "walk.joints.npy"), "--fps", "20", "--no_preview", "--to_rig", str(FIGURE),
          "--joint_map", str(MAP), "--out", str(root / "walk")])
    return {"root": root, "walk": walk, "rig": read_rig(FIGURE, "smpl22", MAP),
            "generated": root / "generated/sample_000.glb",
            "generated_joints": root / "generated/sample_000.joints.npy",
            "walked": root / "walk/walk.glb"}


def test_the_figure_is_the_sample_unchanged():
    """The committed file is Khronos' sample as its README describes it: its buffer whole, its joints not
    Mixamo's or any registered map's."""
    import hashlib

    digest = hashlib.sha256(FIGURE.read_bytes()).hexdigest()
    assert digest == "354572cfef17b136b437ac9749da0fa316fd6e42ee7d62fe50a696b25f5047e9"
    assert digest in (DATA / "README.md").read_text()
    gltf = _sample()
    assert len(gltf.binary_blob()) == gltf.buffers[0].byteLength == 22184
    assert len(gltf.skins[0].joints) == 19 and gltf.nodes[gltf.skins[0].joints[0]].name == "torso_joint_1"


def test_the_scaffold_proposes_the_hand_finished_map_and_the_rig_needs_one(capsys):
    """Without a map the rig is one line naming ``omg joint-map``; no name is like a built-in map's, and the
    scaffold finds every joint the hand-finished map names from the figure's hierarchy and rest pose, the same
    joint, each marked a guess with its reason."""
    with pytest.raises(UsageError, match="omg joint-map .*RiggedFigure.gltf"):
        read_rig(FIGURE, "smpl22")
    main(["joint-map", str(FIGURE)])
    text = capsys.readouterr().out
    assert yaml.safe_load(text)["joints"] == yaml.safe_load(MAP.read_text())["joints"]
    assert "0 joints matched by name, 19 guessed (check them), 0 TODO" in text
    assert '  left_knee:      "leg_joint_L_2"  # guessed: the left leg (+X side: its joints\' names say so; the rest ' \
        "pose agrees): between its thigh and shin; check" in text


def test_the_output_is_the_figure_with_one_animation_added(written):
    """Every node, mesh, skin, material and accessor's data of the sample is kept (its own animation too); one
    animation is added, its channels on the skin's joint nodes; the Z-up node above them keeps its matrix."""
    before = _sample()
    for key in ("generated", "walked"):
        after = pygltflib.GLTF2().load(str(written[key]))
        kept, now = json.loads(before.to_json()), json.loads(after.to_json())
        for field in set(kept) | set(now):
            if field not in ("accessors", "bufferViews", "buffers", "animations", "asset"):
                assert now.get(field) == kept.get(field), (key, field)
        # a .gltf's buffer is repacked into the .glb's one binary chunk (each view where it lands): the views keep
        # their length, stride and target, the accessors their fields and data
        assert [(v.byteLength, v.byteStride, v.target) for v in after.bufferViews[: len(before.bufferViews)]] == \
            [(v.byteLength, v.byteStride, v.target) for v in before.bufferViews]
        assert after.accessors[: len(before.accessors)] == before.accessors
        for i, accessor in enumerate(before.accessors):
            view = before.bufferViews[accessor.bufferView]
            assert np.array_equal(read_accessor(after, after.binary_blob(), i),
                                  read_accessor(before, before.binary_blob(), i)), (key, i, view)
        assert len(after.animations) == len(before.animations) + 1 == 2
        assert after.animations[0] == before.animations[0]
        assert {c.target.node for c in after.animations[-1].channels} == set(before.skins[0].joints)


def test_the_mesh_follows_the_joints_and_bones_keep_their_length(written):
    """The file's joints (its nodes played by the tests' own FK, under the Z-up node) are where onto_rig puts
    the figure's; bone lengths are kept; and the mesh is skinned onto them: each vertex bound to one joint
    alone keeps its place in that joint's frame at every frame (its distance to the joint and to the joint's
    child)."""
    rig = written["rig"]
    frames = np.load(written["generated_joints"]).shape[0]
    for key, motion in (("generated", np.load(written["generated_joints"])), ("walked", written["walk"])):
        gltf, world, skinned = evaluate(written[key])
        assert skinned.shape[0] == len(motion) == (frames if key == "generated" else len(written["walk"]))
        places = joint_places(gltf, world, rig.names)  # (T, J, 3)
        expected = onto_rig(motion, "smpl22", rig, 20, MAP).positions()
        assert np.abs(places - expected).max() < 1e-4, key
        lengths = np.linalg.norm(places[:, 1:] - places[:, rig.parents[1:]], axis=-1)
        assert np.abs(lengths - np.linalg.norm(rig.offsets[1:], axis=-1)).max() < 1e-4, key
        assert np.linalg.norm(places[-1] - places[0], axis=-1).max() > 0.05, key  # the motion moves the figure
        blob = gltf.binary_blob()
        primitive = gltf.meshes[0].primitives[0]
        bones = read_accessor(gltf, blob, primitive.attributes.JOINTS_0).astype(int)
        weights = read_accessor(gltf, blob, primitive.attributes.WEIGHTS_0)
        by_node = {n: rig.names.index(gltf.nodes[n].name) for n in gltf.skins[0].joints}
        checked = 0
        for v in np.flatnonzero(weights.max(1) > 0.999):
            j = by_node[gltf.skins[0].joints[bones[v, weights[v].argmax()]]]
            children = [c for c, p in enumerate(rig.parents) if p == j]
            for other in [j] + children[:1]:
                d = np.linalg.norm(skinned[:, v] - places[:, other], axis=-1)  # (T,)
                assert np.ptp(d) < 1e-4, (key, v, rig.names[j])
            checked += 1
        assert checked >= 30, checked  # of the 370 vertices, those bound to one joint alone


def test_the_khronos_validator_finds_no_error(written):
    """Khronos' glTF validator on the figure with the generated motion and with the walk: 0 errors."""
    assert validation_errors([written["generated"], written["walked"]]) == {}


@pytest.fixture(scope="module")
def as_fbx(written) -> dict:
    """The figure as FBX (Blender's glTF importer, then its FBX exporter), the walk written onto it by
    ``omg export --to_rig figure.fbx`` as .fbx, and what Blender reads back from that."""
    from helpers.blender_scenes import blender
    from omg.io.fbx import available

    if not available():
        pytest.skip("Blender's Python module (bpy) is not installed: pip install 'omg[fbx]', or point "
                    "OMG_BLENDER_PYTHON at a Python that has it (.ci/run installs one)")
    root = written["root"] / "fbx"
    root.mkdir()
    blender("convert", [{"path": str(FIGURE), "out": str(root / "figure.fbx")}], root)
    main(["export", str(written["root"] / "walk.joints.npy"), "--fps", "20", "--no_preview", "--to_rig",
          str(root / "figure.fbx"), "--joint_map", str(MAP), "--out", str(root / "walk")])
    blender("probe", [{"path": str(root / "walk/walk.fbx"), "out": str(root / "walk.npz"), "fps": 20}], root)
    with np.load(root / "walk.npz") as arrays:
        probe = {**json.loads((root / "walk.json").read_text()), **arrays}
    return {"root": root, "probe": probe, "rig": read_rig(root / "figure.fbx", "smpl22", MAP)}


def test_the_figure_as_fbx_moves_its_mesh_as_the_gltf_does(written, as_fbx):
    """The FBX of the sample reads as the same rig (its joints' rest places within 1e-5 m); the walk written onto
    it is one take over the walk's frames, its bones where onto_rig puts the glTF figure's, lengths kept,
    and Blender's skinned mesh at every frame where the tests' own skinning of the glTF output puts it (each
    vertex matched by its rest place: Blender's importer splits and reorders them)."""
    rig, probe, walk = written["rig"], as_fbx["probe"], written["walk"]
    fbx_rig = as_fbx["rig"]
    order = [fbx_rig.names.index(n) for n in rig.names]
    assert np.abs(fbx_rig.rest_positions()[order] - rig.rest_positions()).max() < 1e-5
    # one take, "walk" (Blender's importer names each object's curves of it "<object>|walk"): the armature's over
    # the walk's frames
    assert {a["name"].split("|")[-1] for a in probe["actions"]} == {"walk"}
    assert probe["action"] == "Armature|walk" and probe["heads"].shape[0] == len(walk)
    heads = probe["heads"][:, [probe["names"].index(n) for n in rig.names]]  # (T, J, 3)
    assert np.abs(heads - onto_rig(walk, "smpl22", rig, 20, MAP).positions()).max() < 1e-4
    lengths = np.linalg.norm(heads[:, 1:] - heads[:, rig.parents[1:]], axis=-1)
    assert np.abs(lengths - np.linalg.norm(rig.offsets[1:], axis=-1)).max() < 1e-4
    _, _, skinned = evaluate(written["walked"])  # (T, V, 3) the glTF output's mesh
    gltf = _sample()

    rest = read_accessor(gltf, gltf.binary_blob(), gltf.meshes[0].primitives[0].attributes.POSITION)
    rest = rest[:, [0, 2, 1]] * [1, 1, -1]  # the sample's Z-up mesh in the Y-up world (its root node's turn)
    gap = np.linalg.norm(probe["rest"][:, None] - rest[None], axis=-1)  # (V', V)
    assert gap.min(1).max() < 1e-4
    assert np.abs(probe["skinned"] - skinned[:, gap.argmin(1)]).max() < 1e-3


def test_feet_stand_on_the_ground(written):
    """Where the model's feet are planted, the figure's mesh stands on the ground: its lowest vertex, heel or toes,
    within 1 cm of the floor on every planted frame of the walk (measured 0.03 cm median, 0.36 cm at most), and no
    foot through the floor on the others. The figure's toe joint sits 6 cm under its ankle and its mesh runs 15 cm
    past it: the model's foot bone's direction and one ground for the clip (the commit before) sank its soles
    4.3 cm at the median, 5.2 cm at most."""
    walk = written["walk"]
    planted = ground_contacts(torch.from_numpy(walk).double(), get_skeleton("smpl22").feet, 20).numpy().any(1)
    assert planted.sum() > 20
    _, _, skinned = evaluate(written["walked"])
    low = skinned[..., 1].min(1) * 100  # (T,) cm
    sole = np.abs(low[planted])
    assert np.median(sole) < 0.1 and sole.max() < 1.0, np.round(np.sort(sole)[-5:], 2)
    assert low.min() > -1.0, low.min()


def test_feet_stand_on_the_ground_as_fbx(as_fbx, written):
    """The same on the FBX of the figure, read back by Blender: its soles within 1 cm on every planted frame."""
    walk = written["walk"]
    planted = ground_contacts(torch.from_numpy(walk).double(), get_skeleton("smpl22").feet, 20).numpy().any(1)
    low = as_fbx["probe"]["skinned"][..., 1].min(1) * 100  # (T,) cm
    sole = np.abs(low[planted])
    assert np.median(sole) < 0.1 and sole.max() < 1.0, np.round(np.sort(sole)[-5:], 2)
    assert low.min() > -1.0, low.min()
