"""glTF 2.0 binary (``.glb``) export of a motion on a rig: a joint node per joint with its rest
transform, a skin over them, and one animation (a rotation channel per joint, translation
channels where a joint's position moves: the root's path) at the motion's frame rate.

glTF's conventions are omg's: metres, Y up (on a model skeleton; a rig's own axes otherwise),
and a node's rotation turns its children's translations. Quaternions are stored (x, y, z, w).
There is no mesh: the skin binds nothing yet, but names the skeleton for tools that rig one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib as gl

from omg.files import atomic_write
from omg.io.rig import RigMotion

MOVING = 1e-7  # m: a joint whose translation varies more than this over the motion gets a translation channel


def write_glb(path: str | Path, motion: RigMotion) -> Path:
    """Write ``motion`` (its rig and animation) as a binary glTF 2.0 file, atomically."""
    T, J = len(motion), motion.num_joints
    times = (np.arange(T) / motion.fps).astype(np.float32)
    blob = bytearray()
    gltf = gl.GLTF2(asset=gl.Asset(version="2.0", generator="omg"), scene=0)

    def add(array: np.ndarray, kind: str, minmax: bool = False) -> int:
        """An accessor over a new bufferView of ``array`` (float32; kind: SCALAR, VEC3, VEC4, MAT4)."""
        data = np.ascontiguousarray(array, dtype=np.float32)
        gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes))
        blob.extend(data.tobytes())
        blob.extend(b"\0" * (-len(blob) % 4))  # accessors align to 4 bytes
        count = {"SCALAR": data.size, "VEC3": data.size // 3, "VEC4": data.size // 4, "MAT4": data.size // 16}[kind]
        flat = data.reshape(count, -1)
        gltf.accessors.append(gl.Accessor(
            bufferView=len(gltf.bufferViews) - 1, componentType=gl.FLOAT, count=count, type=kind,
            min=flat.min(0).tolist() if minmax else None, max=flat.max(0).tolist() if minmax else None))  # fmt: skip
        return len(gltf.accessors) - 1

    children = [[c for c, p in enumerate(motion.parents) if p == j] for j in range(J)]
    for j in range(J):
        gltf.nodes.append(gl.Node(name=motion.names[j], translation=[float(v) for v in motion.offsets[j]],
                                  rotation=[0.0, 0.0, 0.0, 1.0], children=children[j] or None))  # fmt: skip
    rest = motion.rest_positions()  # (J, 3): rest rotations are the identity, so bind = a translation
    bind = np.tile(np.eye(4, dtype=np.float32), (J, 1, 1))
    bind[:, 3, :3] = -rest  # column-major: the translation sits in the last column of the matrix
    gltf.skins.append(gl.Skin(name=motion.name, joints=list(range(J)), skeleton=0,
                              inverseBindMatrices=add(bind, "MAT4")))  # fmt: skip
    gltf.scenes.append(gl.Scene(nodes=[0]))

    time_accessor = add(times, "SCALAR", minmax=True)  # glTF requires min and max on sampler inputs
    samplers, channels = [], []
    quats = np.asarray(motion.rotations)[..., [1, 2, 3, 0]]  # (w, x, y, z) -> glTF's (x, y, z, w)
    translations = np.asarray(motion.translations)
    def animate(j: int, path: str, values: np.ndarray, kind: str) -> None:
        samplers.append(gl.AnimationSampler(input=time_accessor, output=add(values, kind), interpolation="LINEAR"))
        target = gl.AnimationChannelTarget(node=j, path=path)
        channels.append(gl.AnimationChannel(sampler=len(samplers) - 1, target=target))

    for j in range(J):
        animate(j, "rotation", quats[:, j], "VEC4")
        if j == 0 or np.abs(translations[:, j] - translations[0, j]).max() > MOVING:
            animate(j, "translation", translations[:, j], "VEC3")
    gltf.animations.append(gl.Animation(name=motion.name, samplers=samplers, channels=channels))
    gltf.buffers.append(gl.Buffer(byteLength=len(blob)))
    gltf.set_binary_blob(bytes(blob))
    path = Path(path)
    atomic_write(path, b"".join(gltf.save_to_bytes()))
    return path
