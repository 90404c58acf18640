"""FBX characters the tests make with Blender itself, and what Blender reads back from the files omg writes.

Run as a script under the Python that has ``bpy`` (``python tests/helpers/blender_scenes.py build|probe
REQUESTS.json``: a list of calls), in a child process as omg runs Blender, so that the test process never
loads Blender (``blender``: the same from a test):

- ``build``: the figure of ``helpers.characters`` (Mixamo's names; its ``boxes``: a box of mesh around each
  bone, the glTF figure's mesh) as an armature with a skinned mesh, written as FBX; ``unit`` in
  metres per file unit (0.01: centimetres, the scene's unit scale, as Mixamo's files), ``z_up``: the
  file's axes Blender's own (Z up, -Y forward) instead of FBX's Y up, ``pose`` "A": the arms 45 degrees down;
- ``probe``: a written file (.fbx or .glb) opened in an empty scene at ``fps``: its actions (name, frame
  range), the skinned meshes' vertices at rest, and at every frame of the armature's action its bones'
  heads and the evaluated (skinned) meshes' vertices, in the world, metres, Y up (Blender's Z-up world
  turned as its glTF exporter turns it): an .npz, and a .json beside it.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # Blender's world (Z up) -> Y up


def _empty_scene():
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy


def _characters():
    """The glTF figure's module alone (the helpers package would load torch into Blender's child)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("characters", HERE / "characters.py")
    characters = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(characters)
    return characters


def figure_of(pose: str = "T") -> dict:
    """The glTF figure in ``pose`` as plain data (names, parents, rest heads in metres Y up, and its mesh:
    ``characters.boxes``' vertices, their (joint, weight) lists and the quads), made by the caller's Python:
    Blender's child gets it in its request, needing no package of the tests' (Blender's Python may be a venv of
    its own with bpy and numpy alone), and both formats' figures are one geometry."""
    characters = _characters()
    names, parents, rest = characters.figure_rest(pose)
    vertices, groups, faces = characters.boxes(pose)
    return {"names": list(names), "parents": [int(p) for p in parents], "rest": np.asarray(rest).tolist(),
            "vertices": np.asarray(vertices).tolist(), "groups": [[[int(j), float(w)] for j, w in g] for g in groups],
            "faces": [[int(k) for k in f] for f in faces]}


def build(path: str, figure: dict, unit: float = 1.0, z_up: bool = False) -> None:
    bpy = _empty_scene()
    scene = bpy.context.scene
    scene.unit_settings.scale_length = unit  # one Blender unit is ``unit`` metres: the file's numbers in that unit
    names, parents, rest_yup = figure["names"], figure["parents"], np.asarray(figure["rest"])
    rest = (rest_yup @ Y_UP) / unit  # (J, 3) Blender's world (Y_UP's inverse is its transpose), file units
    J = len(names)
    arm_data = bpy.data.armatures.new("Armature")
    arm = bpy.data.objects.new("Armature", arm_data)
    scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    bones = []
    for j in range(J):
        bone = arm_data.edit_bones.new(names[j])
        children = [c for c in range(J) if parents[c] == j]
        towards = rest[children[0]] - rest[j] if children else rest[j] - rest[parents[j]]
        bone.head = rest[j].tolist()
        bone.tail = (rest[j] + towards / np.linalg.norm(towards) * 0.05 / unit).tolist()
        if parents[j] >= 0:
            bone.parent = bones[parents[j]]
        bones.append(bone)
    bpy.ops.object.mode_set(mode="OBJECT")
    vertices, groups, faces = np.asarray(figure["vertices"]), figure["groups"], figure["faces"]
    mesh = bpy.data.meshes.new("body")
    mesh.from_pydata(((vertices @ Y_UP) / unit).tolist(), [], faces)
    body = bpy.data.objects.new("body", mesh)
    scene.collection.objects.link(body)
    material = bpy.data.materials.new("skin")
    material.diffuse_color = (0.8, 0.2, 0.2, 1.0)
    mesh.materials.append(material)
    vertex_groups = [body.vertex_groups.new(name=n) for n in names]
    for i, weights in enumerate(groups):
        for j, w in weights:
            vertex_groups[j].add([i], w, "ADD")
    body.parent = arm
    body.modifiers.new("Armature", "ARMATURE").object = arm
    axes = {"axis_up": "Z", "axis_forward": "-Y"} if z_up else {"axis_up": "Y", "axis_forward": "-Z"}
    bpy.ops.export_scene.fbx(filepath=str(path), add_leaf_bones=False, bake_anim=False, apply_unit_scale=True,
                             **axes)


def probe(path: str, out: str, fps: float) -> None:
    bpy = _empty_scene()
    scene = bpy.context.scene
    scene.render.fps = round(fps)  # glTF keys times in seconds: its importer keys frames at the scene's rate
    if path.lower().endswith(".fbx"):
        bpy.ops.import_scene.fbx(filepath=path)
    else:
        bpy.ops.import_scene.gltf(filepath=path)
    arm = next(o for o in scene.objects if o.type == "ARMATURE")
    meshes = [o for o in scene.objects if o.type == "MESH" and any(m.type == "ARMATURE" for m in o.modifiers)]
    action = arm.animation_data.action if arm.animation_data else None
    actions = [{"name": a.name, "range": list(a.frame_range)} for a in bpy.data.actions]
    first, last = (int(round(x)) for x in action.frame_range)
    names = [b.name for b in arm.data.bones]

    def vertices() -> np.ndarray:
        graph = bpy.context.evaluated_depsgraph_get()
        points = []
        for o in meshes:
            evaluated = o.evaluated_get(graph)
            m = evaluated.to_mesh()
            co = np.zeros(len(m.vertices) * 3)
            m.vertices.foreach_get("co", co)
            mw = np.array(evaluated.matrix_world)
            points.append((co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]) @ Y_UP.T)
            evaluated.to_mesh_clear()
        return np.concatenate(points)

    arm.data.pose_position = "REST"
    rest = vertices()
    arm.data.pose_position = "POSE"
    heads, skinned = [], []
    for f in range(first, last + 1):
        scene.frame_set(f)
        world = np.array(arm.matrix_world)
        heads.append([(world @ np.append(np.array(b.head), 1.0))[:3] @ Y_UP.T for b in arm.pose.bones])
        skinned.append(vertices())
    np.savez(out, heads=np.array(heads), skinned=np.array(skinned), rest=rest)
    Path(out).with_suffix(".json").write_text(json.dumps({
        "actions": actions, "action": action.name, "frames": [first, last], "names": names,
        "fps": scene.render.fps / scene.render.fps_base, "meshes": [o.name for o in meshes],
        "vertices": [len(o.data.vertices) for o in meshes]}))


def convert(path: str, out: str) -> None:
    """A glTF character made elsewhere, as FBX: Blender's glTF importer, then its FBX exporter (the armature,
    the skinned mesh and its materials; no animation)."""
    bpy = _empty_scene()
    bpy.ops.import_scene.gltf(filepath=path)
    for o in bpy.context.scene.objects:
        if o.animation_data:  # the file's own animation stays in the glTF: the FBX is the character at rest
            o.animation_data_clear()
    bpy.ops.export_scene.fbx(filepath=out, add_leaf_bones=False, bake_anim=False)


if __name__ == "__main__":  # REQUEST.json: a list of keyword arguments, one call each
    for request in json.loads(Path(sys.argv[2]).read_text()):
        {"build": build, "probe": probe, "convert": convert}[sys.argv[1]](**request)


def blender(what: str, requests: list[dict], folder: Path) -> None:
    """``build``, ``probe`` or ``convert`` each of ``requests`` in one child Python (one Blender start for them
    all)."""
    import os
    import subprocess

    if what == "build":  # the figure made here: the child needs no test package
        requests = [{**{k: v for k, v in r.items() if k != "pose"}, "figure": figure_of(r.get("pose", "T"))}
                    for r in requests]
    (folder / f"{what}.json").write_text(json.dumps(requests))
    from omg.io.fbx import blender_python

    run = subprocess.run([blender_python(), __file__, what, str(folder / f"{what}.json")], capture_output=True,
                         text=True, timeout=600, env={**os.environ, "PYTHONPATH": str(HERE.parent.parent)})
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
