"""FBX characters through Blender's own Python module (``bpy``, the optional extra ``omg[fbx]``): a user's
skinned ``.fbx`` read as a rig (``read_character``: its armature's bones, the same ``RigMotion`` a glTF
character gives, so that ``omg.retarget.onto_rig`` moves both), and that character written with a motion
added (``write_character``: keyframes on the armature's pose bones, the mesh skinned and untouched) as
``.fbx`` by Blender's FBX exporter or ``.glb`` by its glTF exporter (Blender converts the whole character,
mesh, skin and materials, as it reads them; the glTF writer of ``omg.io.gltf`` only adds an animation to
a glTF document, which an FBX file is not).

Blender runs in a child Python (``python -m omg.io.fbx``), one per read and one per write, or per character
for all the writes made inside ``one_blender_run`` (a generation's motions): the calling process never loads
it (its hundreds of megabytes, its threads, its global scene, its printing on stdout), a file that crashes
it is one line, and a server's threads never share its scene. The child's side is the end of this module,
under ``_child``; it imports only bpy and numpy.

Conventions are ``omg.io.gltf``'s: the rig in the world, metres, Y up (Blender's Z-up world turned as its
glTF exporter turns it: x, z, -y), whatever the file's axes and unit scale, which Blender's importer applies.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from omg.errors import UsageError
from omg.files import atomic_path, file_problem, read_head

if TYPE_CHECKING:  # the child imports this module too: it loads neither torch nor the rest of omg
    from omg.io.rig import RigMotion

FBX_MAX_BYTES = 512 * 2**20  # a character's file: its meshes and embedded textures
BINARY_MAGIC = b"Kaydara FBX Binary  \x00"  # Blender reads binary FBX only (7.1 and later)
# a Python that has bpy, when omg's own has none: bpy pins numpy<2 and one CPython (3.11), so it may live in a
# venv of its own; the child needs only bpy, numpy and this module
BLENDER_PYTHON = "OMG_BLENDER_PYTHON"
INSTALL = ("pip install 'omg[fbx]' (Blender's Python module, bpy, for Python 3.11), or point OMG_BLENDER_PYTHON "
           "at a Python 3.11 that has it")
CHILD_TIMEOUT = 900.0  # s: a read or a write of a large character by Blender
MOVING = 1e-7  # a bone whose location varies more than this (its own units) gets location keys
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # Blender's world (Z up) -> Y up


@dataclass
class FbxCharacter:
    """An FBX character as read, for the writer to animate: the file Blender reimports and its armature."""

    path: str  # the file, absolute
    armature: str  # the armature object's name in Blender's scene
    sole: float | None  # m: the height of the skinned meshes' lowest point in the rest pose (None: no mesh)
    # the skinned meshes' vertices in the rest pose's lower quarter, world, metres, Y up (V, 3), and the bone each
    # follows most (V,): ``omg.io.gltf.Character.ground``'s
    ground: tuple[np.ndarray, np.ndarray] | None = None


def blender_python() -> str:
    """The interpreter Blender's child runs in: ``OMG_BLENDER_PYTHON``, else this one."""
    return os.environ.get(BLENDER_PYTHON) or sys.executable


def available() -> bool:
    """Whether Blender's Python module is installed (without importing it): in this interpreter, or the one
    ``OMG_BLENDER_PYTHON`` names (whose bpy the child's own import then checks)."""
    if os.environ.get(BLENDER_PYTHON):
        return Path(os.environ[BLENDER_PYTHON]).is_file()
    try:
        return importlib.util.find_spec("bpy") is not None
    except ValueError:  # a module entry set to None: an import of it would fail
        return False


def check_file(path: str | Path, what: str = "--to_rig") -> str:
    """``where`` of the messages; one line for a path that is no binary FBX omg can give Blender, or no bpy
    (before a command loads anything, Blender included)."""
    path = Path(path)
    where = f"{what} {path}" if what else str(path)
    if (problem := file_problem(path)) is not None:
        raise UsageError(f"{where}: {problem}")
    if path.stat().st_size > FBX_MAX_BYTES:
        raise UsageError(f"{where}: larger than the {FBX_MAX_BYTES // 2**20} MiB omg reads from a character")
    head = read_head(path, len(BINARY_MAGIC), what)
    if head != BINARY_MAGIC:
        why = "an ASCII FBX, which Blender does not read: save it as binary FBX" if head.startswith(b";") or \
            b"FBXHeaderExtension" in read_head(path, 4096, what) else "no binary FBX header"
        raise UsageError(f"{where}: not a readable FBX file ({why})")
    if not available():
        raise UsageError(f"{where}: FBX characters are read by Blender's Python module, which is not installed: "
                         f"{INSTALL}")
    return where


def _run(request: dict, arrays: dict[str, np.ndarray], where: str, each: list[str] | None = None) -> dict:
    """The child's answer to ``request`` (``arrays`` beside it as .npz); its error as one UsageError, named
    ``where`` (or, for an error of one of a request's ``writes``, that write's in ``each``)."""
    with tempfile.TemporaryDirectory(prefix="omg-fbx-") as folder:
        folder = Path(folder)
        (folder / "request.json").write_text(json.dumps(request))
        np.savez(folder / "arrays.npz", **arrays)
        root = str(Path(__file__).resolve().parents[2])  # the omg this module is, first on the child's path
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])}
        timeout = CHILD_TIMEOUT * max(1, len(request.get("writes", ())))
        try:
            run = subprocess.run([blender_python(), "-m", "omg.io.fbx", str(folder)], capture_output=True, text=True,
                                 errors="replace", env=env, timeout=timeout)
        except subprocess.TimeoutExpired:
            raise UsageError(f"{where}: Blender took more than {timeout:g} s") from None
        answer = folder / "answer.json"
        if not answer.is_file():
            said = [line for line in (run.stderr + run.stdout).splitlines() if line.strip()]
            raise UsageError(f"{where}: Blender stopped (exit status {run.returncode})"
                             + (f": {said[-1].strip()[:300]}" if said else ""))
        out = json.loads(answer.read_text())
    if "error" in out:
        raise UsageError(f"{each[out['index']] if each and 'index' in out else where}: {out['error']}")
    return out


def read_character(path: str | Path, what: str = "--to_rig") -> RigMotion:
    """A skinned FBX character as a rig: its armature's bones (one tree; named as in the file, Mixamo's
    ``mixamorig:`` kept), their heads in the rest pose in the world (metres, Y up); the ``FbxCharacter``
    rides along for the writer. Conventions are ``RigMotion``'s: rest rotations the identity, offsets in
    world axes, one frame."""
    from omg.io.rig import RigMotion

    path = Path(path)
    where = check_file(path, what)
    out = _run({"op": "read", "path": str(path.resolve())}, {}, where)
    rest = np.asarray(out["rest"], dtype=np.float64).reshape(-1, 3)  # (J, 3) world, metres, Y up
    parents = [int(p) for p in out["parents"]]
    offsets = rest - np.concatenate([np.zeros((1, 3)), rest[parents[1:]]])
    J = len(parents)
    ground = None
    if out.get("ground"):
        rows = np.asarray(out["ground"], dtype=np.float64).reshape(-1, 4)  # x, y, z, bone
        ground = (rows[:, :3], rows[:, 3].astype(int))
    character = FbxCharacter(path=str(path.resolve()), armature=out["armature"], sole=out["sole"], ground=ground)
    return RigMotion(name=path.stem, names=list(out["names"]), parents=parents, offsets=offsets, fps=30.0,
                     rotations=np.tile([1.0, 0.0, 0.0, 0.0], (1, J, 1)), translations=offsets[None].copy(),
                     source=str(path), character=character)  # fmt: skip


@dataclass
class _Write:
    """A motion to write onto an FBX character: its files and what the child keys."""

    files: list[Path]  # the file, and the one beside it from the same keys
    character: FbxCharacter
    keys: dict  # the child's request for it: the bones' names, the rate, the take's name
    turns: np.ndarray  # (T, J, 4) world rotations from rest, Y up
    places: np.ndarray  # (T, J, 3) joints in the world, metres, Y up


_PENDING: ContextVar[list[_Write] | None] = ContextVar("omg_fbx_pending", default=None)


@contextmanager
def one_blender_run() -> Iterator[None]:
    """The writes onto FBX characters made inside it (``write_character``) are made when it ends, in one
    Blender run per character rather than one per motion: Blender's start-up is most of a short motion's
    write. Their files exist once it has ended; an error inside it writes none of them.
    Nested, the outermost one writes."""
    if _PENDING.get() is not None:
        yield
        return
    pending: list[_Write] = []
    token = _PENDING.set(pending)
    try:
        yield
    finally:
        _PENDING.reset(token)
    _write(pending)


def write_character(path: str | Path, motion: RigMotion, also: str | Path | None = None) -> Path:
    """The FBX character of ``motion`` (``read_character``'s) with the motion added, written atomically as
    ``path``'s suffix says: ``.fbx`` (Blender's FBX exporter: one take, a key on every frame) or ``.glb``
    (Blender's glTF exporter: one animation, sampled on every frame); ``also``, a second file the same way from
    the same keys (the ``.glb`` beside an ``.fbx`` that a page plays), in the same Blender run. Inside
    ``one_blender_run`` the files are written when it ends.

    Each bone is posed so that its head is where the motion puts its joint and its orientation is its rest
    orientation turned by the joint's world rotation: the bones keep their lengths and the mesh, skinned to
    them, follows."""
    import torch

    rotations = torch.from_numpy(np.asarray(motion.rotations, dtype=np.float64))
    write = _Write(files=[Path(p) for p in (path, also) if p is not None], character=motion.character,
                   keys={"names": list(motion.names), "fps": float(motion.fps), "name": motion.name},
                   turns=motion.skeleton().global_rotations(rotations).numpy(), places=motion.positions())
    pending = _PENDING.get()
    if pending is None:
        _write([write])
    else:
        pending.append(write)
    return Path(path)


def _write(writes: list[_Write]) -> None:
    """``writes`` made, one Blender run per character; each file atomically."""
    by_character: dict[tuple[str, str], list[_Write]] = {}
    for write in writes:
        by_character.setdefault((write.character.path, write.character.armature), []).append(write)
    for (character, armature), group in by_character.items():
        each = [f"{write.files[0]} (onto {character})" for write in group]
        where = each[0] if len(group) == 1 else f"{group[0].files[0]} and {len(group) - 1} more (onto {character})"
        with ExitStack() as stack:
            outs = [[str(stack.enter_context(atomic_path(f)).resolve()) for f in write.files] for write in group]
            arrays = {f"{name}_{k}": getattr(write, name) for k, write in enumerate(group)
                      for name in ("turns", "places")}
            _run({"op": "write", "path": character, "armature": armature,
                  "writes": [{**write.keys, "out": out} for write, out in zip(group, outs)]}, arrays, where, each)


# -- the child: Blender's side (bpy and numpy only) ---------------------------------------------------------


def _child(folder: Path) -> None:
    request = json.loads((folder / "request.json").read_text())
    try:
        if request["op"] == "read":
            answer = _child_read(request["path"])
        else:
            answer = {"writes": []}
            with np.load(folder / "arrays.npz") as arrays:
                for k, write in enumerate(request["writes"]):
                    try:
                        answer["writes"].append(_child_write({**request, **write}, arrays[f"turns_{k}"],
                                                             arrays[f"places_{k}"]))
                    except _Refused as e:
                        answer = {"error": str(e), "index": k}
                        break
    except _Refused as e:
        answer = {"error": str(e)}
    (folder / "answer.json").write_text(json.dumps(answer))


class _Refused(Exception):
    """What the child answers as the one line of the parent's UsageError."""


def _child_import(path: str):
    """An empty scene with the file imported (no animation: the writer adds its own); its one armature."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    try:
        done = bpy.ops.import_scene.fbx(filepath=path, use_anim=False, ignore_leaf_bones=False,
                                        automatic_bone_orientation=False)
    except RuntimeError as e:  # the importer's own report, "Error: ..." lines
        lines = [line.strip() for line in str(e).splitlines() if line.strip()]
        raise _Refused(f"Blender could not import it ({lines[-1] if lines else 'no reason given'})") from None
    if "FINISHED" not in done:
        raise _Refused("Blender could not import it")
    armatures = [o for o in bpy.context.scene.objects if o.type == "ARMATURE"]
    if not armatures:
        raise _Refused("the file has no armature (a character's skeleton); give a rigged character")
    if len(armatures) > 1:  # the one the skinned meshes deform with
        used = {m.object.name for o in bpy.context.scene.objects if o.type == "MESH"
                for m in o.modifiers if m.type == "ARMATURE" and m.object is not None}
        armatures = [a for a in armatures if a.name in used] or armatures
        if len(armatures) > 1:
            names = ", ".join(repr(a.name) for a in armatures[:4])
            raise _Refused(f"the file has {len(armatures)} armatures ({names}), not one skeleton")
    return bpy, armatures[0]


def _bone_order(arm) -> list:
    """The armature's bones depth first from its one root bone, children in the file's order."""
    roots = [b for b in arm.data.bones if b.parent is None]
    if len(roots) != 1:
        names = ", ".join(repr(b.name) for b in roots[:4])
        raise _Refused(f"its armature's bones form {len(roots)} trees ({names}), not one skeleton")
    order, stack = [], [roots[0]]
    while stack:
        bone = stack.pop()
        order.append(bone)
        stack.extend(reversed(list(bone.children)))
    return order


def _to_world(arm) -> np.ndarray:
    """(4, 4) the armature's space -> the world, metres, Y up."""
    turn = np.eye(4)
    turn[:3, :3] = Y_UP
    return turn @ np.array(arm.matrix_world)


def _child_read(path: str) -> dict:
    bpy, arm = _child_import(path)
    bones = _bone_order(arm)
    index = {b.name: j for j, b in enumerate(bones)}
    world = _to_world(arm)
    rest = [(world @ np.append(np.array(b.head_local), 1.0))[:3].tolist() for b in bones]
    # the skinned meshes as they deform in the rest pose: their lowest point is the character's ground
    arm.data.pose_position = "REST"
    graph = bpy.context.evaluated_depsgraph_get()
    lows, ground = [], []
    for o in bpy.context.scene.objects:
        if o.type != "MESH" or not any(m.type == "ARMATURE" and m.object == arm for m in o.modifiers):
            continue
        evaluated = o.evaluated_get(graph)
        mesh = evaluated.to_mesh()
        co = np.zeros(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        evaluated.to_mesh_clear()
        if not len(co):
            continue
        m = np.array(evaluated.matrix_world)
        points = (co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]) @ Y_UP.T  # (V, 3)
        lows.append(float(points[:, 1].min()))
        if len(points) != len(o.data.vertices):  # a modifier made other vertices: their groups are not these
            continue
        groups = [index.get(g.name, -1) for g in o.vertex_groups]
        for v, p in zip(o.data.vertices, points):  # each vertex with the bone whose group weighs most on it
            best = max(((g.weight, -groups[g.group]) for g in v.groups if groups[g.group] >= 0), default=None)
            if best is not None:  # of bones weighing alike, the first (a parent before its child), as glTF's
                ground.append([*p.tolist(), -best[1]])
    if ground:  # the lower quarter: feet stand on it
        rows = np.array(ground)
        low, high = rows[:, 1].min(), rows[:, 1].max()
        ground = rows[rows[:, 1] <= low + 0.25 * (high - low)].tolist()
    return {"armature": arm.name, "names": [b.name for b in bones], "rest": rest, "sole": min(lows) if lows else None,
            "parents": [-1] + [index[b.parent.name] for b in bones[1:]], "ground": ground}


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) (w, x, y, z) unit quaternions."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def _child_write(request: dict, turns: np.ndarray, places: np.ndarray) -> dict:
    """Pose bone keys for the motion ((T, J, 4) world turns from rest, (T, J, 3) joint places; world, Y up),
    then the character exported.

    A bone's pose matrix in the armature's space is P = [R^-1 G R B | W^-1 x] (G: the joint's world turn,
    R: the armature-to-world rotation, B: the bone's rest matrix, W: armature-to-world, x: the joint's
    place); Blender's own relation P = P_parent (B_parent^-1 B) basis gives each bone's keyed basis."""
    bpy, arm = _child_import(request["path"])
    from mathutils import Matrix  # Blender's, once bpy is imported
    if arm.name != request["armature"]:
        raise _Refused(f"its armature is {arm.name!r} now, not {request['armature']!r} as read")
    bones = {b.name: b for b in _bone_order(arm)}
    names = request["names"]
    if sorted(bones) != sorted(names):
        raise _Refused("its armature's bones changed since it was read")
    T, J = turns.shape[:2]
    world = _to_world(arm)
    scale = np.linalg.norm(world[:3, :3], axis=0).mean()
    R = world[:3, :3] / scale
    rest = np.stack([np.array(bones[n].matrix_local) for n in names])  # (J, 4, 4) armature space, unscaled
    pose = np.tile(np.eye(4), (T, J, 1, 1))
    pose[..., :3, :3] = R.T @ _quat_matrix(turns) @ R @ rest[:, :3, :3]
    pose[..., :3, 3] = (np.concatenate([places, np.ones((T, J, 1))], -1) @ np.linalg.inv(world).T)[..., :3]
    index = {n: j for j, n in enumerate(names)}
    parent = [index[bones[n].parent.name] if bones[n].parent is not None else -1 for n in names]
    relative = np.stack([rest[j] if p < 0 else np.linalg.inv(rest[p]) @ rest[j] for j, p in enumerate(parent)])
    above = np.stack([np.eye(4)[None].repeat(T, 0) if p < 0 else pose[:, p] for p in parent], 1)  # (T, J, 4, 4)
    basis = np.linalg.inv(relative) @ np.linalg.inv(above) @ pose  # (T, J, 4, 4)
    quats = np.array([[Matrix(basis[t, j, :3, :3].tolist()).to_quaternion() for j in range(J)] for t in range(T)])
    # q and -q are one rotation; keys are interpolated, so each keeps the side of the one before
    flips = np.cumsum((quats[1:] * quats[:-1]).sum(-1) < 0, axis=0) % 2
    quats[1:] *= np.where(flips, -1.0, 1.0)[..., None]
    action = bpy.data.actions.new(request["name"])
    arm.animation_data_create().action = action
    frames = np.arange(T, dtype=np.float64)

    def keys(data_path: str, index: int, group: str, values: np.ndarray) -> None:
        curve = action.fcurve_ensure_for_datablock(arm, data_path, index=index, group_name=group)
        curve.keyframe_points.add(T)
        curve.keyframe_points.foreach_set("co", np.stack([frames, values], -1).ravel())
        curve.keyframe_points.foreach_set("interpolation", [1] * T)  # LINEAR: a key on every frame
        curve.update()

    for j, n in enumerate(names):
        bone = arm.pose.bones[n]
        bone.rotation_mode = "QUATERNION"
        for i in range(4):
            keys(f'pose.bones["{bpy.utils.escape_identifier(n)}"].rotation_quaternion', i, n, quats[:, j, i])
        location = basis[:, j, :3, 3]
        if parent[j] < 0 or np.abs(location).max() > MOVING:
            for i in range(3):
                keys(f'pose.bones["{bpy.utils.escape_identifier(n)}"].location', i, n, location[:, i])
    scene = bpy.context.scene
    scene.name = request["name"]  # the FBX take's name (Blender names it after the scene)
    fps = request["fps"]
    scene.render.fps = max(1, round(fps))
    scene.render.fps_base = scene.render.fps / fps
    scene.frame_start, scene.frame_end = 0, T - 1
    for out in request["out"]:  # the file, and the one written beside it from the same keys
        if out.lower().endswith(".fbx"):
            done = bpy.ops.export_scene.fbx(
                filepath=out, add_leaf_bones=False, bake_anim=True, bake_anim_use_all_bones=True,
                bake_anim_use_nla_strips=False, bake_anim_use_all_actions=False, bake_anim_force_startend_keying=True,
                bake_anim_step=1.0, bake_anim_simplify_factor=0.0, path_mode="COPY", embed_textures=True)
        else:
            done = bpy.ops.export_scene.gltf(
                filepath=out, export_format="GLB", export_animations=True, export_animation_mode="ACTIVE_ACTIONS",
                export_force_sampling=True, export_optimize_animation_size=False, export_def_bones=False,
                export_anim_single_armature=True, export_skins=True, export_yup=True)
        if "FINISHED" not in done:
            raise _Refused(f"Blender could not export {out}")
    return {"frames": T}


if __name__ == "__main__":
    _child(Path(sys.argv[1]))
