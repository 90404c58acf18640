"""glTF 2.0: a user's skinned character read as a rig (``read_character``), and the one writer of
``.glb`` files (``write_glb``): a motion on a model skeleton or a BVH rig as joint nodes, a skin and
one animation; a motion on a character as that character, every node, mesh, skin, material,
texture, image, sampler and extension kept, with one animation added on its skin's joint nodes.

glTF's conventions are omg's: metres, Y up (on a model skeleton or a character; a BVH rig's own
axes otherwise), and a node's rotation turns its children's translations. Quaternions are stored
(x, y, z, w). A character authored Z up carries a rotation on a node above its joints: the rig is
read in the scene's (Y-up) world, and the animation written in each joint node's own frame, so
that node keeps its meaning.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib as gl
import torch

from omg.errors import UsageError
from omg.files import atomic_write, read_file
from omg.io.rig import RigMotion
from omg.rotations import matrix_to_quat, quat_conjugate, quat_mul

MOVING = 1e-7  # m: a joint whose translation varies more than this over the motion gets a translation channel
CHARACTER_MAX_BYTES = 512 * 2**20  # a character's file: its meshes and embedded textures
CHARACTER_SUFFIXES = (".glb", ".gltf")
BIND_TOLERANCE = 1e-4  # relative: a joint node farther than this from its inverse bind matrix's pose is posed


@dataclass
class Character:
    """A glTF character as read, for the writer to add an animation to: the document (its buffers in one
    binary blob) and how the rig's joints sit on its nodes."""

    gltf: gl.GLTF2
    nodes: list[int]  # rig joint j -> its node
    rest_local: np.ndarray  # (J, 4) (w, x, y, z): each joint node's rotation in the rest (bind) pose
    rest_translation: np.ndarray  # (J, 3) each joint node's translation in the rest pose, in its parent's units
    parent_rest: np.ndarray  # (J, 4) (w, x, y, z): the world rotation of each joint node's parent node at rest
    root_parent: np.ndarray  # (4, 4) world matrix of the root joint's parent node (the identity without one)
    sole: float | None  # m: the height of the skinned meshes' lowest point in the rest pose (None: no mesh)
    # the skinned meshes' vertices in the rest pose's lower quarter (feet stand on them), in the world, metres,
    # Y up (V, 3), and the rig joint each follows most (V,): what ``onto_rig`` puts on the ground
    ground: tuple[np.ndarray, np.ndarray] | None = None


def _local_matrix(node: gl.Node) -> np.ndarray:
    """(4, 4) a node's local transform: its matrix, else translation @ rotation @ scale."""
    if node.matrix is not None:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF stores it column-major
    x, y, z, w = node.rotation if node.rotation is not None else (0.0, 0.0, 0.0, 1.0)
    m = np.eye(4)
    m[:3, :3] = _rotation_matrix(np.array([w, x, y, z], dtype=np.float64)) * np.asarray(
        node.scale if node.scale is not None else (1.0, 1.0, 1.0), dtype=np.float64)
    m[:3, 3] = node.translation if node.translation is not None else (0.0, 0.0, 0.0)
    return m


def _rotation_matrix(q: np.ndarray) -> np.ndarray:
    from omg.rotations import quat_to_matrix

    return quat_to_matrix(torch.from_numpy(np.asarray(q, dtype=np.float64))).numpy()


def _rotation_of(m: np.ndarray) -> np.ndarray:
    """(..., 4) (w, x, y, z) the rotation of (..., 4, 4) transforms whose scale is uniform per axis."""
    r = m[..., :3, :3] / np.linalg.norm(m[..., :3, :3], axis=-2, keepdims=True)
    return matrix_to_quat(torch.from_numpy(r)).numpy()


def _read_floats(gltf: gl.GLTF2, blob: bytes, index: int, width: int) -> np.ndarray:
    """(count, width) float32 values of accessor ``index`` (tightly packed or strided)."""
    acc = gltf.accessors[index]
    if acc.componentType != gl.FLOAT or acc.bufferView is None:
        raise ValueError(f"accessor {index} is not float data in a buffer view")
    view = gltf.bufferViews[acc.bufferView]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    stride = view.byteStride or 4 * width
    raw = np.frombuffer(blob, np.uint8, acc.count * stride, start).reshape(acc.count, stride)[:, : 4 * width]
    return raw.copy().view(np.float32).astype(np.float64)  # (count, width)


def _load(path: Path, what: str) -> gl.GLTF2:
    """The document at ``path`` with its buffers (and a ``.gltf``'s external images) in one binary blob."""
    data = read_file(path, what, CHARACTER_MAX_BYTES)
    where = f"{what} {path}" if what else str(path)
    try:
        if path.suffix.lower() == ".glb":
            if data[:4] != b"glTF":
                raise ValueError("not a binary glTF (no 'glTF' magic)")
            gltf = gl.GLTF2.load_from_bytes(data)
        else:
            gltf = gl.GLTF2.from_json(data.decode("utf-8"))
            gltf._path = path.parent  # relative buffer and image URIs resolve beside the file
            gltf.convert_images(gl.ImageFormat.BUFFERVIEW)
            gltf.convert_buffers(gl.BufferFormat.BINARYBLOB)
        if gltf is None or not isinstance(gltf.nodes, list):  # pygltflib answers a broken chunk with None
            raise ValueError("its chunks cannot be read")
    except UsageError:
        raise
    except Exception as e:  # pygltflib raises whatever its parser meets
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise UsageError(f"{where}: not a readable glTF 2.0 file ({why})") from None
    if any(b.uri is not None for b in gltf.buffers[1:] or []) or (gltf.buffers and gltf.buffers[0].uri is not None):
        raise UsageError(f"{where}: its buffers must be embedded (a .glb, or a .gltf whose buffers omg can read)")
    return gltf


def read_character(path: str | Path, what: str = "--to_rig") -> RigMotion:
    """A skinned glTF character as a rig: its skins' joints (one tree), named as their nodes, in the
    scene's world (metres, Y up), rest pose the bind pose of the inverse bind matrices (the nodes' own
    transforms where they agree or there are none); the ``Character`` rides along for the writer.

    Conventions are ``RigMotion``'s: rest rotations the identity, offsets in world axes, one frame."""
    path = Path(path)
    where = f"{what} {path}" if what else str(path)
    gltf = _load(path, what)
    nodes = gltf.nodes or []
    if not gltf.skins:
        raise UsageError(f"{where}: the file has no skin (a character's skeleton); give a skinned character")
    joints = sorted({j for skin in gltf.skins for j in skin.joints})
    parent = {c: i for i, n in enumerate(nodes) for c in (n.children or [])}
    world: dict[int, np.ndarray] = {}

    def world_of(n: int) -> np.ndarray:
        if n not in world:
            world[n] = (world_of(parent[n]) if n in parent else np.eye(4)) @ _local_matrix(nodes[n])
        return world[n]

    def joint_parent(n: int) -> int | None:
        p = parent.get(n)
        while p is not None and p not in joints:
            p = parent.get(p)
        return p

    roots = [n for n in joints if joint_parent(n) is None]
    if len(roots) != 1:
        names = ", ".join(repr(nodes[n].name or f"node {n}") for n in roots[:4])
        raise UsageError(f"{where}: its skins' joints form {len(roots)} trees ({names}), not one skeleton")
    order, stack = [], [roots[0]]
    while stack:  # depth first from the root, children in the file's order: parents come first
        n = stack.pop()
        if n in joints:
            order.append(n)
        stack.extend(reversed(nodes[n].children or []))
    index = {n: j for j, n in enumerate(order)}
    rest_world = np.stack([world_of(n) for n in order])  # (J, 4, 4) the nodes' own pose
    bind_world, mesh_to_world = _bind_pose(gltf, order, rest_world)
    if bind_world is not None:
        rest_world = bind_world
    node_parent_rest = {}  # node -> its rest world matrix, for the joints' parent nodes below the root

    def rest_of(n: int) -> np.ndarray:  # a node's world matrix in the rest pose (joints: their bind pose)
        if n in index:
            return rest_world[index[n]]
        if n not in node_parent_rest:
            node_parent_rest[n] = (rest_of(parent[n]) if n in parent else np.eye(4)) @ _local_matrix(nodes[n])
        return node_parent_rest[n]

    root_parent = world_of(parent[order[0]]) if order[0] in parent else np.eye(4)
    parent_world = np.stack([rest_of(parent[n]) if n in parent and n != order[0] else root_parent for n in order])
    local = np.linalg.inv(parent_world) @ rest_world  # (J, 4, 4) each joint node's rest transform
    names, seen = [], set()
    for n in order:
        name = nodes[n].name or f"node{n}"
        while name in seen:  # joint maps address joints by name: each must be one joint's
            name += "_"
        seen.add(name)
        names.append(name)
    rest = rest_world[:, :3, 3]  # (J, 3) world positions, metres
    parents = [-1] + [index[joint_parent(n)] for n in order[1:]]
    offsets = rest - np.concatenate([np.zeros((1, 3)), rest[parents[1:]]])
    character = Character(gltf=gltf, nodes=order, rest_local=_rotation_of(local), rest_translation=local[:, :3, 3],
                          parent_rest=_rotation_of(parent_world), root_parent=root_parent,
                          sole=_sole(gltf, mesh_to_world), ground=_ground(gltf, mesh_to_world, index))
    J = len(order)
    return RigMotion(name=path.stem, names=names, parents=parents, offsets=offsets, fps=30.0,
                     rotations=np.tile([1.0, 0.0, 0.0, 0.0], (1, J, 1)), translations=offsets[None].copy(),
                     source=str(path), character=character)  # fmt: skip


def _bind_pose(gltf: gl.GLTF2, order: list[int], rest_world: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """(J, 4, 4) the joints' world matrices in the pose their inverse bind matrices bind the mesh in, placed
    at the root joint's node (None where the nodes already stand in it, or no skin has the matrices), and
    the (4, 4) transform from the skinned meshes' space to the world in that pose."""
    blob = gltf.binary_blob() or b""
    bind: dict[int, np.ndarray] = {}
    for skin in gltf.skins:
        if skin.inverseBindMatrices is None:
            continue
        mats = _read_floats(gltf, blob, skin.inverseBindMatrices, 16).reshape(-1, 4, 4).transpose(0, 2, 1)
        for n, m in zip(skin.joints, mats):
            bind.setdefault(n, np.linalg.inv(m))
    if any(n not in bind for n in order):
        return None, np.eye(4)
    b = np.stack([bind[n] for n in order])
    mesh_to_world = rest_world[0] @ np.linalg.inv(b[0])
    placed = mesh_to_world @ b  # (J, 4, 4) the bind pose with the root where it stands
    size = max(float(np.ptp(rest_world[:, :3, 3], axis=0).max()), 1e-9)
    moved = np.abs(placed[:, :3, 3] - rest_world[:, :3, 3]).max() / size
    unit = max(float(np.abs(rest_world[0, :3, :3]).max()), 1e-12)  # the scale the joints' matrices carry
    turned = np.abs(placed[:, :3, :3] - rest_world[:, :3, :3]).max() / unit
    return (placed if max(moved, turned) > BIND_TOLERANCE else None), mesh_to_world


def _sole(gltf: gl.GLTF2, mesh_to_world: np.ndarray) -> float | None:
    """The lowest height of the skinned meshes' bounding boxes (their POSITION min and max, which glTF
    requires) in the rest pose, in the world; None without a skinned mesh."""
    lows = []
    for node in gltf.nodes or []:
        if node.mesh is None or node.skin is None:
            continue
        for primitive in gltf.meshes[node.mesh].primitives:
            acc = gltf.accessors[primitive.attributes.POSITION]
            if acc.min is None or acc.max is None:
                continue
            corners = np.array([[x, y, z, 1.0] for x in (acc.min[0], acc.max[0]) for y in (acc.min[1], acc.max[1])
                                for z in (acc.min[2], acc.max[2])])  # fmt: skip
            lows.append(float((corners @ mesh_to_world.T)[:, 1].min()))
    return min(lows) if lows else None


def _read_any(gltf: gl.GLTF2, blob: bytes, index: int) -> np.ndarray | None:
    """(count, width) values of accessor ``index`` as stored (float, or unsigned integers, normalized or not);
    None for one omg does not read (sparse, or in no buffer view)."""
    acc = gltf.accessors[index]
    kinds = {gl.FLOAT: np.float32, gl.UNSIGNED_BYTE: np.uint8, gl.UNSIGNED_SHORT: np.uint16, gl.UNSIGNED_INT: np.uint32}
    if acc.bufferView is None or acc.sparse is not None or acc.componentType not in kinds:
        return None
    dtype = np.dtype(kinds[acc.componentType])
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}.get(acc.type)
    if width is None:
        return None
    view = gltf.bufferViews[acc.bufferView]
    stride = view.byteStride or width * dtype.itemsize
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    raw = np.frombuffer(blob, np.uint8, (acc.count - 1) * stride + width * dtype.itemsize, start)
    rows = np.lib.stride_tricks.as_strided(raw, (acc.count, width * dtype.itemsize), (stride, 1))
    return rows.copy().view(dtype).reshape(acc.count, width)


def _ground(gltf: gl.GLTF2, mesh_to_world: np.ndarray, index: dict[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """The skinned meshes' vertices in the lower quarter of their height in the rest pose (the bind pose's mesh
    is the mesh as modelled, turned by ``mesh_to_world``), in the world, and the rig joint (``index``: node ->
    joint) whose weight on each is the largest; None without a skinned mesh omg can read."""
    blob = gltf.binary_blob() or b""
    points, joints = [], []
    for node in gltf.nodes or []:
        if node.mesh is None or node.skin is None:
            continue
        skin = gltf.skins[node.skin]
        for primitive in gltf.meshes[node.mesh].primitives:
            at = primitive.attributes
            if at.POSITION is None or at.JOINTS_0 is None or at.WEIGHTS_0 is None:
                continue
            xyz, bones, weights = (_read_any(gltf, blob, i) for i in (at.POSITION, at.JOINTS_0, at.WEIGHTS_0))
            if xyz is None or bones is None or weights is None or xyz.dtype != np.float32:
                continue
            world = np.concatenate([xyz, np.ones((len(xyz), 1))], axis=1) @ mesh_to_world.T  # (V, 4)
            # (V, 4) rig joints; of those weighing alike on a vertex, the first of the rig (a parent before its child)
            rig_of = np.array([index.get(n, -1) for n in skin.joints] + [-1])
            joint = rig_of[np.minimum(bones.astype(int), len(skin.joints))]
            heaviest = weights == weights.max(1, keepdims=True)
            rig = np.where(heaviest & (joint >= 0), joint, np.iinfo(np.int64).max).min(1)
            rig[rig == np.iinfo(np.int64).max] = -1
            points.append(world[rig >= 0, :3])
            joints.append(rig[rig >= 0])
    if not points or not sum(len(p) for p in points):
        return None
    points, joints = np.concatenate(points), np.concatenate(joints)
    low, high = points[:, 1].min(), points[:, 1].max()
    keep = points[:, 1] <= low + 0.25 * (high - low)
    return points[keep], joints[keep]


class _Builder:
    """Appends data to a document's binary blob: one accessor over its own 4-byte aligned buffer view each."""

    def __init__(self, gltf: gl.GLTF2, blob: bytes = b""):
        self.gltf, self.blob = gltf, bytearray(blob)

    def add(self, array: np.ndarray, kind: str, minmax: bool = False) -> int:
        """An accessor over a new bufferView of ``array`` (float32; kind: SCALAR, VEC3, VEC4, MAT4)."""
        gltf, blob = self.gltf, self.blob
        blob.extend(b"\0" * (-len(blob) % 4))  # accessors align to 4 bytes
        data = np.ascontiguousarray(array, dtype=np.float32)
        gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes))
        blob.extend(data.tobytes())
        blob.extend(b"\0" * (-len(blob) % 4))
        count = {"SCALAR": data.size, "VEC3": data.size // 3, "VEC4": data.size // 4, "MAT4": data.size // 16}[kind]
        flat = data.reshape(count, -1)
        gltf.accessors.append(gl.Accessor(
            bufferView=len(gltf.bufferViews) - 1, componentType=gl.FLOAT, count=count, type=kind,
            min=flat.min(0).tolist() if minmax else None, max=flat.max(0).tolist() if minmax else None))  # fmt: skip
        return len(gltf.accessors) - 1

    def animation(self, name: str, fps: float, tracks: list[tuple[int, str, np.ndarray]]) -> None:
        """One animation of (node, "rotation" (T, 4) x, y, z, w | "translation" (T, 3), values) tracks at ``fps``."""
        T = len(tracks[0][2])
        time_accessor = self.add((np.arange(T) / fps).astype(np.float32), "SCALAR", minmax=True)  # glTF requires
        samplers, channels = [], []  # min and max on sampler inputs
        for node, path, values in tracks:
            kind = "VEC4" if path == "rotation" else "VEC3"
            samplers.append(gl.AnimationSampler(input=time_accessor, output=self.add(values, kind),
                                                interpolation="LINEAR"))  # fmt: skip
            channels.append(gl.AnimationChannel(sampler=len(samplers) - 1,
                                                target=gl.AnimationChannelTarget(node=node, path=path)))
        self.gltf.animations.append(gl.Animation(name=name, samplers=samplers, channels=channels))

    def save(self, path: str | Path) -> Path:
        if self.gltf.buffers:
            self.gltf.buffers[0].byteLength = len(self.blob)
        else:
            self.gltf.buffers.append(gl.Buffer(byteLength=len(self.blob)))
        self.gltf.set_binary_blob(bytes(self.blob))
        path = Path(path)
        atomic_write(path, b"".join(self.gltf.save_to_bytes()))
        return path


def write_glb(path: str | Path, motion: RigMotion) -> Path:
    """Write ``motion`` as a binary glTF 2.0 file, atomically: on its character where it has one
    (``read_character``), else its rig as joint nodes with a skin that binds no mesh."""
    if motion.character is not None:
        return _write_character(path, motion)
    J = motion.num_joints
    gltf = gl.GLTF2(asset=gl.Asset(version="2.0", generator="omg"), scene=0)
    out = _Builder(gltf)
    children = [[c for c, p in enumerate(motion.parents) if p == j] for j in range(J)]
    for j in range(J):
        gltf.nodes.append(gl.Node(name=motion.names[j], translation=[float(v) for v in motion.offsets[j]],
                                  rotation=[0.0, 0.0, 0.0, 1.0], children=children[j] or None))  # fmt: skip
    rest = motion.rest_positions()  # (J, 3): rest rotations are the identity, so bind = a translation
    bind = np.tile(np.eye(4, dtype=np.float32), (J, 1, 1))
    bind[:, 3, :3] = -rest  # column-major: the translation sits in the last column of the matrix
    gltf.skins.append(gl.Skin(name=motion.name, joints=list(range(J)), skeleton=0,
                              inverseBindMatrices=out.add(bind, "MAT4")))  # fmt: skip
    gltf.scenes.append(gl.Scene(nodes=[0]))
    quats = np.asarray(motion.rotations)[..., [1, 2, 3, 0]]  # (w, x, y, z) -> glTF's (x, y, z, w)
    translations = np.asarray(motion.translations)
    tracks = []
    for j in range(J):
        tracks.append((j, "rotation", quats[:, j]))
        if j == 0 or np.abs(translations[:, j] - translations[0, j]).max() > MOVING:
            tracks.append((j, "translation", translations[:, j]))
    out.animation(motion.name, motion.fps, tracks)
    return out.save(path)


def _write_character(path: str | Path, motion: RigMotion) -> Path:
    """The character of ``motion`` with the motion added as an animation on its joint nodes.

    A joint's node rotation is r = P^-1 q P r0 (q: the motion's local rotation about world axes at rest,
    P: the world rotation of the node's parent at rest, r0: the node's rest rotation), so that its world
    rotation is the motion's turn applied to its rest orientation; the root's path is written in its
    parent node's frame (units and up axis of the file). Joints whose node stands off the bind pose get
    their rest translation as a constant track, so that the mesh is bound where it was modelled."""
    ch: Character = motion.character
    gltf = copy.deepcopy(ch.gltf)
    gltf.asset.generator = gltf.asset.generator or "omg"
    out = _Builder(gltf, gltf.binary_blob() or b"")
    T = len(motion)
    q = torch.from_numpy(np.asarray(motion.rotations, dtype=np.float64))  # (T, J, 4)
    P = torch.from_numpy(ch.parent_rest).expand_as(q)
    r0 = torch.from_numpy(ch.rest_local).expand_as(q)
    node_rot = quat_mul(quat_mul(quat_mul(quat_conjugate(P), q), P), r0).numpy()[..., [1, 2, 3, 0]]  # (T, J, 4)
    # q and -q are one rotation; a sampler interpolates between neighbours, so each keeps the side of the one before
    flips = np.cumsum((node_rot[1:] * node_rot[:-1]).sum(-1) < 0, axis=0) % 2  # (T - 1, J)
    node_rot[1:] *= np.where(flips, -1.0, 1.0)[..., None]
    world_root = np.concatenate([motion.translations[:, 0], np.ones((T, 1))], axis=1)  # (T, 4)
    root_path = (np.linalg.inv(ch.root_parent) @ world_root.T).T[:, :3]  # (T, 3) in the parent node's frame
    tracks = []
    for j, n in enumerate(ch.nodes):
        node = gltf.nodes[n]
        if node.matrix is not None:  # an animated node must be TRS: the same transform, decomposed
            m = _local_matrix(node)
            scale = np.linalg.norm(m[:3, :3], axis=0)
            x = _rotation_of(m)
            node.matrix, node.translation = None, m[:3, 3].tolist()
            node.rotation, node.scale = [*map(float, x[1:]), float(x[0])], scale.tolist()
        tracks.append((n, "rotation", node_rot[:, j]))
        if j == 0:
            tracks.append((n, "translation", root_path))
        elif np.abs(np.asarray(node.translation or (0.0, 0.0, 0.0)) - ch.rest_translation[j]).max() > MOVING:
            tracks.append((n, "translation", np.broadcast_to(ch.rest_translation[j], (T, 3))))
    out.animation(motion.name, motion.fps, tracks)
    return out.save(path)
