"""Motion onto a user's FBX character (``--to_rig character.fbx``, ``omg.io.fbx``: Blender's Python module in a
child process): what omg writes opens in Blender with one action playing on the mesh, the bones keep their
lengths, the feet stand on the ground, and the .glb from it passes Khronos' validator.

The characters are made by Blender itself (``helpers.blender_scenes``: the glTF tests' figure with
Mixamo's names and a box of mesh around each bone, skinned): a T-pose in metres with FBX's Y up, and an
A-pose in centimetres with Blender's Z up. The written files are re-opened in a fresh Blender scene, in a
child process, and the armature's pose and the evaluated (skinned) mesh compared here with numpy.
Without bpy (``pip install 'omg[fbx]'``; .ci/run installs it) the tests that need Blender skip; the
one line a user without it gets is tested everywhere.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch
import yaml

import omg.io.fbx as fbx_io
from helpers import REPO, SHARED_MOTION, TINY_DIT
from helpers.blender_scenes import blender
from helpers.characters import boxes, figure_rest, write_character
from helpers.checkpoints import save_module
from helpers.gltf_validator import validation_errors
from omg.cli import main
from omg.io.bvh import read_bvh
from omg.io.fbx import BINARY_MAGIC, available
from omg.kinematics import ground_contacts
from omg.retarget import onto_rig, read_rig, retarget
from omg.skeleton import get_skeleton

pytestmark = pytest.mark.xdist_group("fbx")  # the tests share the `written` fixture's Blender runs
WALK = "human/bandai2/dataset-2_walk-turn-left_normal_{}.bvh"
CHARACTERS = {"t_pose_m": {}, "a_pose_cm_z_up": {"pose": "A", "unit": 0.01, "z_up": True}}


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict:
    """Blender's characters, what omg wrote onto them and what Blender reads back from that: ``omg generate``
    (a tiny untrained checkpoint, 1 s) onto the T-pose figure as .fbx, and a real walk (``omg export``) onto
    the A-pose centimetre Z-up figure as .fbx and onto the T-pose figure as .glb."""
    if not available():
        pytest.skip("Blender's Python module (bpy) is not installed: pip install 'omg[fbx]', or point "
                    "OMG_BLENDER_PYTHON at a Python that has it (.ci/run installs one)")
    found = sorted((SHARED_MOTION / "human/bandai2").glob(WALK.format("*").split("/")[-1]))
    if not found:
        pytest.skip(f"real motion data not found at {SHARED_MOTION} (the shared/ folder beside the checkout)")
    from omg.data.datamodule import MotionDataModule
    from omg.lit.pretrain import PretrainModule

    root = tmp_path_factory.mktemp("fbx")
    blender("build", [{"path": str(root / f"{name}.fbx"), **options} for name, options in CHARACTERS.items()], root)
    torch.manual_seed(0)
    spec = MotionDataModule(str(REPO / "shards/mini/human263/train"), batch_size=2, num_workers=0).spec
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec=spec, ema_decay=0)
    with torch.no_grad():  # DiT's zero-initialised output would give every sample the mean motion
        torch.nn.init.normal_(module.model.final_layer.linear.weight, std=0.05)
    save_module(module, root / "pre.ckpt")
    runs, run = [], fbx_io._run
    with pytest.MonkeyPatch.context() as patch:  # the Blender runs of the generation
        patch.setattr(fbx_io, "_run", lambda request, *a: runs.append(request) or run(request, *a))
        main(["generate", "--unconditional", "--ckpt", str(root / "pre.ckpt"), "--steps", "2", "--length", "1",
              "--num_samples", "2", "--no_preview", "--device", "cpu", "--to_rig", str(root / "t_pose_m.fbx"),
              "--out", str(root / "generated")])
    clip = retarget(read_bvh(found[0]), "smpl22", fps=20)
    walk = clip.positions[:60]
    np.save(root / "walk.joints.npy", walk)
    main(["export", str(root / "walk.joints.npy"), "--fps", "20", "--no_preview", "--to_rig",
          str(root / "a_pose_cm_z_up.fbx"), "--out", str(root / "a")])
    main(["export", str(root / "walk.joints.npy"), "--fps", "20", "--no_preview", "--to_rig",
          str(root / "t_pose_m.fbx"), "--format", "glb", "--out", str(root / "t")])
    files = {"generated": root / "generated/sample_000.fbx", "generated_1": root / "generated/sample_001.fbx",
             "walk_a": root / "a/walk.fbx", "walk_t": root / "t/walk.glb"}
    blender("probe", [{"path": str(path), "out": str(root / f"{key}.npz"), "fps": 20} for key, path in files.items()],
            root)
    probes = {}
    for key in files:
        with np.load(root / f"{key}.npz") as arrays:
            probes[key] = {**json.loads((root / f"{key}.json").read_text()), **arrays}
    frames = np.load(root / "generated/sample_000.joints.npy").shape[0]
    return {"root": root, "files": files, "probes": probes, "walk": walk, "generated_frames": frames,
            "generate_runs": [(r["op"], len(r.get("writes", ()))) for r in runs]}


def _figure(probe: dict, pose: str) -> tuple[list[int], np.ndarray]:
    """The probed bones in the figure's order: their indices in the probe, and the figure's rest (J, 3)."""
    names, _, rest = figure_rest(pose)
    return [probe["names"].index(n) for n in names], rest


def _follows(probe: dict, pose: str) -> None:
    """The evaluated mesh's boxes at every frame are centred on their two bones' heads (the far end's four
    vertices shared half and half, the near end's bound to the parent), and the bones keep their lengths."""
    names, parents, rest = figure_rest(pose)
    order, _ = _figure(probe, pose)
    heads = probe["heads"][:, order]  # (T, J, 3)
    lengths = np.linalg.norm(heads[:, 1:] - heads[:, parents[1:]], axis=-1)
    assert np.abs(lengths - np.linalg.norm(rest[1:] - rest[parents[1:]], axis=-1)).max() < 1e-4
    made = boxes(pose)[0]  # (8 (J - 1), 3) the boxes as made, 8 vertices a bone
    # each vertex read back is one made (a reader may split them by face and reorder them): matched by place
    gap = np.linalg.norm(probe["rest"][:, None] - made[None], axis=-1)  # (V, 8 (J - 1))
    assert gap.min(1).max() < 1e-4 and len(set(gap.argmin(1))) == len(made)
    skinned = probe["skinned"][:, [int(np.flatnonzero(gap.argmin(1) == k)[0]) for k in range(len(made))]]
    for j in range(1, len(names)):
        if names[j].endswith(("ToeBase", "Toe_End")):  # their soles are flattened onto the ground
            continue
        box = skinned[:, 8 * (j - 1): 8 * j]
        assert np.abs(box[:, :4].mean(1) - heads[:, parents[j]]).max() < 1e-4, names[j]
        assert np.abs(box[:, 4:].mean(1) - heads[:, j]).max() < 1e-4, names[j]


def test_generate_onto_an_fbx_character_writes_it_with_one_action_on_the_mesh(written):
    """``omg generate --to_rig character.fbx`` writes the character (every bone, the mesh's vertices) with one
    action over the motion's frames at its rate; in Blender the mesh moves with the bones."""
    probe, frames = written["probes"]["generated"], written["generated_frames"]
    assert len(probe["actions"]) == 1 and probe["frames"][1] - probe["frames"][0] + 1 == frames
    assert probe["fps"] == 20 and probe["heads"].shape[:2] == (frames, len(figure_rest()[0]))
    assert sorted(probe["names"]) == sorted(figure_rest()[0]) and probe["vertices"] == [len(boxes()[0])]
    heads = probe["heads"]
    assert np.linalg.norm(heads[-1] - heads[0], axis=-1).max() > 0.05  # the motion moves the bones
    _follows(probe, "T")
    # the generation's two motions: one Blender run reads the character, one writes both, each its own motion
    assert written["generate_runs"] == [("read", 0), ("write", 2)]
    other = written["probes"]["generated_1"]
    assert [probe["action"], other["action"]] == ["Armature|sample_000", "Armature|sample_001"]
    assert len(other["actions"]) == 1 and other["heads"].shape == heads.shape
    joints = [np.load(written["root"] / f"generated/sample_00{k}.joints.npy") for k in (0, 1)]
    assert np.abs(joints[1] - joints[0]).max() > 0.05 and np.abs(other["heads"] - heads).max() > 0.05
    _follows(other, "T")


def test_a_walk_on_the_centimetre_z_up_character_keeps_bones_and_feet_on_the_ground(written, tmp_path):
    """A real walk on the A-pose figure in centimetres, Z up (.fbx) and on the T-pose figure in metres, Y up
    (.glb): the bones are where ``onto_rig`` puts the same figure's joints read from a glTF character (one
    retargeting for both formats; units, axes and exporter change nothing), the mesh follows them, bone
    lengths kept, and where the model's feet are planted the mesh's soles are on the ground within 1 cm on every
    frame, heel or toes (the retarget's, the same on a glTF character); no foot goes through the floor."""
    walk = written["walk"]
    for key, options in (("walk_a", CHARACTERS["a_pose_cm_z_up"]), ("walk_t", CHARACTERS["t_pose_m"])):
        probe = written["probes"][key]
        assert len(probe["actions"]) == 1 and probe["heads"].shape[0] == len(walk)
        pose = options.get("pose", "T")
        _follows(probe, pose)
        gltf = read_rig(write_character(tmp_path / f"{key}.glb", turned=True, **options), "smpl22")
        order, _ = _figure(probe, pose)
        expected = onto_rig(walk, "smpl22", gltf, 20).positions()  # (T, J, 3) in the figure's order
        assert np.abs(probe["heads"][:, order] - expected).max() < 1e-4, key
        planted = ground_contacts(torch.from_numpy(walk).double(), get_skeleton("smpl22").feet, 20).numpy().any(1)
        assert planted.sum() > 20
        low = probe["skinned"][..., 1].min(1) * 100  # (T,) cm
        sole = np.abs(low[planted])
        assert np.median(sole) < 0.1 and sole.max() < 1.0, (key, np.round(np.sort(sole)[-5:], 2))
        assert low.min() > -1.0, (key, low.min())


def test_the_glb_of_an_fbx_character_opens_in_blender_and_passes_the_validator(written):
    """``--format glb`` onto an FBX character: Blender's glTF exporter writes the character with the walk as
    one animation (read back by Blender's glTF importer above: the mesh follows the bones), and Khronos'
    validator finds 0 errors where .ci/run installed it."""
    assert validation_errors([written["files"]["walk_t"]]) == {}


def test_the_joint_map_scaffold_of_an_fbx_character(written, capsys):
    """``omg joint-map character.fbx`` prints the YAML map of its bones: Mixamo's names all matched."""
    main(["joint-map", str(written["root"] / "a_pose_cm_z_up.fbx")])
    text = capsys.readouterr().out
    joints = yaml.safe_load(text)["joints"]
    assert joints["pelvis"] == "mixamorig:Hips" and joints["left_wrist"] == "mixamorig:LeftHand", text


def _refused(argv: list[str], capsys) -> str:
    """The one stderr line of a refused ``omg`` command (exit status 2)."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exited:
        main(argv)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exited.value.code == 2 and len(lines) == 1 and lines[0].startswith("omg: error: "), lines
    return lines[0]


def test_a_broken_fbx_is_one_line(written, tmp_path, capsys):
    """A file with FBX's header and nothing Blender can read: Blender's refusal in one line."""
    (tmp_path / "broken.fbx").write_bytes(BINARY_MAGIC + b"\x1a\x00" + bytes(range(256)) * 4)
    line = _refused(["joint-map", str(tmp_path / "broken.fbx")], capsys)
    assert line.startswith(f"omg: error: RIG {tmp_path}/broken.fbx: ") and "Blender" in line, line


def test_without_blender_an_fbx_is_one_line_saying_how_to_install_it(tmp_path, capsys, monkeypatch):
    """Without bpy every place an .fbx is given says, in one line, to pip install 'omg[fbx]'; a file that is
    no binary FBX (an ASCII FBX, which Blender does not read) says so before Blender is asked; --format fbx
    is an FBX character's only."""
    monkeypatch.setitem(sys.modules, "bpy", None)  # what an import of a module that is not installed finds
    monkeypatch.delenv("OMG_BLENDER_PYTHON", raising=False)  # nor a Python of Blender's own
    character = tmp_path / "character.fbx"
    character.write_bytes(BINARY_MAGIC + b"\x1a\x00" + b"\0" * 64)
    (tmp_path / "ascii.fbx").write_text("; FBX 7.4.0 project file\nFBXHeaderExtension:  {\n}\n")
    np.save(tmp_path / "still.joints.npy", np.repeat(get_skeleton("smpl22").rest_positions()[None], 5, 0))
    export = ["export", str(tmp_path / "still.joints.npy"), "--no_preview"]
    for argv in (["joint-map", str(character)], [*export, "--to_rig", str(character)],
                 ["generate", "--unconditional", "--ckpt", str(tmp_path / "none.ckpt"), "--to_rig", str(character),
                  "--out", str(tmp_path / "out")]):
        assert "FBX characters are read by Blender's Python module, which is not installed: pip install 'omg[fbx]'" \
            in _refused(argv, capsys), argv
    assert "an ASCII FBX, which Blender does not read" in _refused(["joint-map", str(tmp_path / "ascii.fbx")], capsys)
    assert "--format fbx writes an FBX character" in _refused([*export, "--format", "fbx"], capsys)
    assert not (tmp_path / "out").exists() and not (tmp_path / "still.fbx").exists()


def test_omg_bench_character_writes_a_generation_in_one_blender_run(written, capsys):
    """``omg bench character``: the motions written onto an FBX character a Blender run each and all in one run,
    one Markdown row with both times."""
    main(["bench", "character", "--fbx", str(written["root"] / "t_pose_m.fbx"), "--motions", "2", "--frames", "10"])
    printed = capsys.readouterr().out
    line = next(line for line in printed.splitlines() if line.startswith("| t_pose_m.fbx |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1:3] == ["2", "10"] and float(cells[3]) > 0 and float(cells[4]) > 0 and cells[5].endswith("x")
    assert "`omg bench character --fbx" in printed
