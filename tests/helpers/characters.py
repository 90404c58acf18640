"""Skinned glTF characters the tests make themselves (nothing binary is committed): a figure with
Mixamo's joint names, a box of mesh around each bone, skin weights, a textured material (a PNG
made here) and an extension; in a T-pose in metres, or in an A-pose in centimetres under a Z-up
root node, every joint node with its own rest rotation. ``evaluate`` plays a written file's animation by the
tests' own forward kinematics and linear-blend skinning (numpy and scipy), independently of omg's.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pygltflib as gl
from scipy.spatial.transform import Rotation

M = "mixamorig:"
# (name, parent, world rest position in metres, Y up, facing +Z; the body's left along +X): a T-pose
FIGURE = [
    ("Hips", None, (0.0, 0.98, 0.0)), ("Spine", "Hips", (0.0, 1.08, 0.0)), ("Spine1", "Spine", (0.0, 1.2, 0.0)),
    ("Spine2", "Spine1", (0.0, 1.32, 0.0)), ("Neck", "Spine2", (0.0, 1.47, 0.0)), ("Head", "Neck", (0.0, 1.57, 0.0)),
    ("HeadTop_End", "Head", (0.0, 1.75, 0.0)),
    *[(f"{s}{n}", f"{s}{p}" if p != "Spine2" else "Spine2", (x * d, y, z)) for s, d in (("Left", 1.0), ("Right", -1.0))
      for n, p, (x, y, z) in (("Shoulder", "Spine2", (0.05, 1.42, 0.0)), ("Arm", "Shoulder", (0.17, 1.42, 0.0)),
                              ("ForeArm", "Arm", (0.45, 1.42, 0.0)), ("Hand", "ForeArm", (0.7, 1.42, 0.0)),
                              ("Hand_End", "Hand", (0.8, 1.42, 0.0)))],
    *[(f"{s}{n}", f"{s}{p}" if p != "Hips" else "Hips", (x * d, y, z)) for s, d in (("Left", 1.0), ("Right", -1.0))
      for n, p, (x, y, z) in (("UpLeg", "Hips", (0.09, 0.92, 0.0)), ("Leg", "UpLeg", (0.09, 0.5, 0.0)),
                              ("Foot", "Leg", (0.09, 0.09, 0.0)), ("ToeBase", "Foot", (0.09, 0.03, 0.12)),
                              ("Toe_End", "ToeBase", (0.09, 0.03, 0.19)))],
]  # fmt: skip
HALF_WIDTH = 0.03  # m: the boxes' half width around each bone


def png(width: int = 4, height: int = 4) -> bytes:
    """A small RGB PNG: a checkerboard (the texture's image)."""
    rows = b"".join(b"\0" + b"".join(bytes((200, 40, 40) if (x + y) % 2 else (40, 40, 200)) for x in range(width))
                    for y in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")


def figure_rest(pose: str = "T") -> tuple[list[str], list[int], np.ndarray]:
    """Names, parents and (J, 3) world rest positions in metres; "A": the arms 45 degrees down."""
    names = [M + n for n, _, _ in FIGURE]
    parents = [-1 if p is None else names.index(M + p) for _, p, _ in FIGURE]
    rest = np.array([p for _, _, p in FIGURE], dtype=np.float64)
    if pose == "A":
        for side, angle in (("Left", -45), ("Right", 45)):
            turn = Rotation.from_euler("z", angle, degrees=True)
            shoulder = rest[names.index(f"{M}{side}Arm")]
            for part in ("ForeArm", "Hand", "Hand_End"):
                j = names.index(f"{M}{side}{part}")
                rest[j] = shoulder + turn.apply(rest[j] - shoulder)
    return names, parents, rest


CORNERS = ((-1, -1), (-1, 1), (1, -1), (1, 1))  # a box's four corners around each end of its bone: (side, up)
QUADS = ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))  # a box's faces


def boxes(pose: str = "T") -> tuple[np.ndarray, list[list[tuple[int, float]]], list[list[int]]]:
    """The figure's mesh, the one both the glTF characters and Blender's FBX ones are made with: a box around
    each bone (parent joint -> joint), 8 vertices a bone in joint order, the 4 at the parent end bound to the
    parent, the 4 at the far end half and half; the soles of the foot's boxes on the ground. Each box a little
    wider than the one before, so that no two vertices share a place at rest (a reader that splits or reorders
    vertices, as glTF's does, is matched back by place).
    Returns (V, 3) rest positions (metres, Y up), each vertex's (joint, weight) list, and the quads."""
    names, parents, rest = figure_rest(pose)
    vertices, groups, faces = [], [], []
    for j in range(1, len(names)):
        p = parents[j]
        a, b = rest[p], rest[j]
        axis = (b - a) / np.linalg.norm(b - a)
        side = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        up = np.cross(axis, side)
        half = HALF_WIDTH * (1.0 + 0.02 * j)
        foot = names[j].endswith(("ToeBase", "Toe_End"))  # the bones of the foot: their soles on the ground
        base = len(vertices)
        for end, point in enumerate((a, b)):
            for u, v in CORNERS:
                q = point + half * (u * side + v * up)
                if foot and q[1] < point[1]:
                    q[1] = 0.0
                vertices.append(q)
                groups.append([(p, 1.0)] if end == 0 else [(p, 0.5), (j, 0.5)])
        faces += [[base + k for k in quad] for quad in QUADS]
    return np.array(vertices), groups, faces


def write_character(path: Path, pose: str = "T", unit: float = 1.0, z_up: bool = False,
                    turned: bool = False, posed: bool = False) -> Path:
    """A skinned character at ``path`` (.glb, or .gltf with its buffer as a data URI).

    ``unit``: metres per unit of the joints' translations (0.01: centimetres, under a root node scaled
    0.01); ``z_up``: that root node also turns the Z-up authored skeleton to glTF's Y up; ``turned``:
    every joint node has its own rest rotation (their translations turned to match); ``posed``: saved with
    the spine and left forearm nodes turned off the pose the inverse bind matrices bind. Returns ``path``."""
    names, parents, rest = figure_rest(pose)
    J = len(names)
    rng = np.random.default_rng(7)
    world_rot = [Rotation.from_rotvec(rng.normal(size=3) * 0.6) if turned else Rotation.identity() for _ in range(J)]
    root_rot = Rotation.from_euler("x", -90, degrees=True) if z_up else Rotation.identity()
    root_matrix = np.eye(4)
    root_matrix[:3, :3] = root_rot.as_matrix() * unit
    world = []  # (J) 4x4 world matrices of the joint nodes (their own scale 1: the root node's unit below them)
    for j in range(J):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = world_rot[j].as_matrix() * unit, rest[j]
        world.append(m)
    gltf = gl.GLTF2(asset=gl.Asset(version="2.0", generator="omg tests"), scene=0)
    blob = bytearray()

    def view(data: bytes, target: int | None = None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        return len(gltf.bufferViews) - 1

    def accessor(array: np.ndarray, kind: str, component: int, target: int | None, minmax: bool = False) -> int:
        data = np.ascontiguousarray(array)
        count = len(data)
        gltf.accessors.append(gl.Accessor(bufferView=view(data.tobytes(), target), componentType=component,
                                          count=count, type=kind,
                                          min=data.reshape(count, -1).min(0).tolist() if minmax else None,
                                          max=data.reshape(count, -1).max(0).tolist() if minmax else None))
        return len(gltf.accessors) - 1

    # nodes: 0 the root node ("Armature"), 1..J the joints, J + 1 the skinned mesh
    gltf.nodes.append(gl.Node(name="Armature", children=[1]))
    if unit != 1.0 or z_up:
        x, y, z, w = root_rot.as_quat()
        gltf.nodes[0].rotation, gltf.nodes[0].scale = [x, y, z, w], [unit] * 3
    for j in range(J):
        parent = root_matrix if parents[j] < 0 else world[parents[j]]
        local = np.linalg.inv(parent) @ world[j]
        x, y, z, w = Rotation.from_matrix(local[:3, :3]).as_quat()
        gltf.nodes.append(gl.Node(name=names[j], translation=local[:3, 3].tolist(),
                                  rotation=None if not (turned or z_up) else [x, y, z, w],
                                  children=[c + 1 for c in range(J) if parents[c] == j] or None))
    if posed:  # the nodes stand in another pose than the bind pose (a file saved mid-animation)
        for name, turn in (("Spine", Rotation.from_euler("x", 20, degrees=True)),
                           ("LeftForeArm", Rotation.from_euler("z", 40, degrees=True))):
            node = gltf.nodes[names.index(M + name) + 1]
            node.rotation = (turn * Rotation.from_quat(node.rotation or [0, 0, 0, 1])).as_quat().tolist()
    # the mesh: ``boxes``, each corner's texture coordinates across the box (u) and along the bone (v)
    positions, groups, quads = boxes(pose)
    joints = [[j for j, _ in g] + [0] * (4 - len(g)) for g in groups]
    weights = [[w for _, w in g] + [0.0] * (4 - len(g)) for g in groups]
    uvs = [(0.5 + 0.5 * u, float(end)) for _ in range(J - 1) for end in (0, 1) for u, _ in CORNERS]
    indices = [q for q0, q1, q2, q3 in quads for q in (q0, q1, q2, q0, q2, q3)]
    attributes = gl.Attributes(
        POSITION=accessor(np.array(positions, np.float32), "VEC3", gl.FLOAT, gl.ARRAY_BUFFER, minmax=True),
        TEXCOORD_0=accessor(np.array(uvs, np.float32), "VEC2", gl.FLOAT, gl.ARRAY_BUFFER),
        JOINTS_0=accessor(np.array(joints, np.uint16), "VEC4", gl.UNSIGNED_SHORT, gl.ARRAY_BUFFER),
        WEIGHTS_0=accessor(np.array(weights, np.float32), "VEC4", gl.FLOAT, gl.ARRAY_BUFFER))
    index = accessor(np.array(indices, np.uint16), "SCALAR", gl.UNSIGNED_SHORT, gl.ELEMENT_ARRAY_BUFFER)
    gltf.images.append(gl.Image(bufferView=view(png()), mimeType="image/png", name="checker"))
    gltf.samplers.append(gl.Sampler(magFilter=gl.NEAREST, minFilter=gl.NEAREST, wrapS=gl.REPEAT, wrapT=gl.REPEAT))
    gltf.textures.append(gl.Texture(sampler=0, source=0, name="checker"))
    gltf.materials.append(gl.Material(
        name="skin", pbrMetallicRoughness=gl.PbrMetallicRoughness(baseColorTexture=gl.TextureInfo(index=0),
                                                                  metallicFactor=0.0, roughnessFactor=0.8),
        emissiveFactor=[1.0, 0.5, 0.2], extensions={"KHR_materials_emissive_strength": {"emissiveStrength": 2.0}}))
    gltf.extensionsUsed = ["KHR_materials_emissive_strength"]
    gltf.meshes.append(gl.Mesh(name="body", primitives=[gl.Primitive(attributes=attributes, indices=index,
                                                                     material=0)]))
    inverse_bind = np.stack([np.linalg.inv(m).T for m in world]).astype(np.float32)  # column-major
    gltf.skins.append(gl.Skin(name="figure", joints=list(range(1, J + 1)),
                              inverseBindMatrices=accessor(inverse_bind, "MAT4", gl.FLOAT, None)))
    gltf.nodes.append(gl.Node(name="body", mesh=0, skin=0))
    gltf.scenes.append(gl.Scene(nodes=[0, J + 1]))
    gltf.buffers.append(gl.Buffer(byteLength=len(blob)))
    gltf.set_binary_blob(bytes(blob))
    path = Path(path)
    if path.suffix == ".gltf":
        gltf.convert_buffers(gl.BufferFormat.DATAURI)
        path.write_text(gltf.to_json())
    else:
        path.write_bytes(b"".join(gltf.save_to_bytes()))
    return path


def read_accessor(gltf: gl.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """(count, width) float64 values of accessor ``index`` (float or unsigned short, packed or strided)."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    dtype = np.dtype({gl.FLOAT: np.float32, gl.UNSIGNED_SHORT: np.uint16}[acc.componentType])
    stride = view.byteStride or width * dtype.itemsize
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    rows = np.frombuffer(blob, np.uint8, (acc.count - 1) * stride + width * dtype.itemsize, start)
    rows = np.lib.stride_tricks.as_strided(rows, (acc.count, width * dtype.itemsize), (stride, 1))
    return rows.copy().view(dtype).reshape(acc.count, width).astype(np.float64)


def _node_matrix(translation, rotation, scale) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(rotation).as_matrix() * np.asarray(scale)  # glTF and scipy: (x, y, z, w)
    m[:3, 3] = translation
    return m


def evaluate(path: Path) -> tuple[gl.GLTF2, np.ndarray, np.ndarray]:
    """The file's last animation at every key: (T, N, 4, 4) world matrices of every node and (T, V, 3) the
    skinned mesh's vertices (linear-blend skinning: sum of weight * joint world @ inverse bind)."""
    gltf = gl.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    anim = gltf.animations[-1]
    keys = {(c.target.node, c.target.path): read_accessor(gltf, blob, anim.samplers[c.sampler].output)
            for c in anim.channels}
    T = len(next(iter(keys.values())))
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    world = np.zeros((T, len(gltf.nodes), 4, 4))
    done: set[int] = set()

    def place(n: int) -> None:
        if n in done:
            return
        node = gltf.nodes[n]
        if node.matrix is not None:  # a node the animation leaves alone (a Z-up root's turn)
            assert not any(node_ == n for node_, _ in keys)
            local = [np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T] * T  # column-major
        else:
            moves = keys.get((n, "translation"), [node.translation or [0, 0, 0]] * T)
            turns = keys.get((n, "rotation"), [node.rotation or [0, 0, 0, 1]] * T)
            local = [_node_matrix(moves[t], turns[t], node.scale or [1, 1, 1]) for t in range(T)]
        if n in parent:
            place(parent[n])
            world[:, n] = world[:, parent[n]] @ np.stack(local)
        else:
            world[:, n] = np.stack(local)
        done.add(n)

    for n in range(len(gltf.nodes)):
        place(n)
    mesh_node = next(n for n in gltf.nodes if n.skin is not None)
    skin, primitive = gltf.skins[mesh_node.skin], gltf.meshes[mesh_node.mesh].primitives[0]
    inverse_bind = read_accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    joint_matrices = world[:, skin.joints] @ inverse_bind  # (T, J, 4, 4)
    vertices = read_accessor(gltf, blob, primitive.attributes.POSITION)
    joints = read_accessor(gltf, blob, primitive.attributes.JOINTS_0).astype(int)
    weights = read_accessor(gltf, blob, primitive.attributes.WEIGHTS_0)
    homogeneous = np.concatenate([vertices, np.ones((len(vertices), 1))], axis=1)  # (V, 4)
    skinned = np.einsum("vk,tvkab,vb->tva", weights, joint_matrices[:, joints], homogeneous)[..., :3]
    return gltf, world, skinned


def joint_places(gltf: gl.GLTF2, world: np.ndarray, names: list[str]) -> np.ndarray:
    """(T, J, 3) the places of the nodes named ``names`` in ``evaluate``'s world matrices."""
    by_name = {n.name: i for i, n in enumerate(gltf.nodes)}
    return world[:, [by_name[n] for n in names]][..., :3, 3]
