"""SMPL-family parameter sequences (SMPL, SMPL-H, SMPL-X) -> smpl22 clips by the current retargeting.

Shared by the importers of parameter files (``aistpp``, ``motionx``); the body model itself
(``BodyModel``: ``v_template``, ``shapedirs``, ``J_regressor``, ``kintree_table`` from a
user-given ``.npz``) lives here too and is shared with the ``amass`` importer. The first 22 joints of every SMPL-family
model are SMPL's body joints in smpl22's order (SMPL-X adds jaw, eyes and fingers after them),
so a sequence's body is its first 22 axis-angle rotations (``(T, 66)``): hands and face are
dropped.

A sequence becomes a ``RigMotion`` on the individual's rest joints (``J_regressor @
(v_template + shapedirs @ betas)``) with the parameter file's rotations and the root at its rest
place plus ``trans``, then ``omg.retarget.retarget`` with the identity joint map: resampled to
the target fps (slerp), the given up axis turned to +Y, the floor put under the planted feet,
bone lengths constant, local rotations and offsets kept in the clip.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import read_array
from omg.io.rig import RigMotion
from omg.motion import Clip
from omg.retarget import JointMap, retarget
from omg.rotations import axis_angle_to_quat
from omg.skeleton import SMPL22_PARENTS, Skeleton, get_skeleton

NUM_JOINTS = 22
UP_AXES = ("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z")  # the up axis of a source's world
GENDERS = ("male", "female", "neutral")


@dataclass(frozen=True)
class BodyModel:
    """The parts of an SMPL-family model that joint positions need."""

    v_template: np.ndarray  # (V, 3)
    shapedirs: np.ndarray  # (V, 3, B)
    J_regressor: np.ndarray  # (J, V)
    parents: tuple[int, ...]  # (J,) from kintree_table[0]

    @classmethod
    @lru_cache(maxsize=8)
    def load(cls, path: Path) -> BodyModel:
        if path.suffix == ".pkl":
            raise UsageError(
                f"body model {path} is a .pkl, which needs chumpy to read; convert it to .npz "
                "(np.savez with v_template, shapedirs, J_regressor, kintree_table) and pass "
                "--option.body_model PATH.npz"
            )
        try:
            # float64 models: SMPL-H's ~80 MiB, SMPL-X 2020's (400 shape, 486 pose blend shapes) ~221 MiB,
            # within MOTION_MAX_BYTES (256 MiB)
            with read_array(path, "body model") as f:
                parts = {k: np.asarray(f[k], dtype=np.float64) for k in ("v_template", "shapedirs", "J_regressor")}
                kintree = np.asarray(f["kintree_table"])
        except KeyError as e:
            raise UsageError(
                f"body model {path} lacks {e}; it needs v_template, shapedirs, J_regressor, kintree_table"
            ) from None
        except UsageError:  # no regular file (a FIFO), or larger than the bound: read_file's one line
            raise
        except (OSError, ValueError, EOFError, TypeError, zipfile.BadZipFile) as e:  # TypeError: an .npy, no .npz
            raise UsageError(f"body model {path} is not a readable .npz of plain arrays ({e})") from None
        parents = tuple(int(p) if i else -1 for i, p in enumerate(kintree[0]))
        if parents[:NUM_JOINTS] != tuple(SMPL22_PARENTS):
            raise UsageError(
                f"body model {path}: its first 22 parents {list(parents[:NUM_JOINTS])} are not SMPL's {SMPL22_PARENTS}"
            )
        V = len(parts["v_template"])
        if parts["shapedirs"].shape[:2] != (V, 3) or parts["J_regressor"].shape[1] != V:
            raise UsageError(f"body model {path}: shapedirs {parts['shapedirs'].shape} or J_regressor "
                             f"{parts['J_regressor'].shape} do not fit v_template {parts['v_template'].shape}")
        return cls(parts["v_template"], parts["shapedirs"], parts["J_regressor"], parents)

    def rest_joints(self, betas: np.ndarray) -> np.ndarray:
        """(B',) shape coefficients -> (22, 3) rest joint locations (extra betas are ignored)."""
        n = min(len(betas), self.shapedirs.shape[-1])
        vertices = self.v_template + self.shapedirs[..., :n] @ betas[:n]  # (V, 3)
        return (self.J_regressor @ vertices)[:NUM_JOINTS]


@lru_cache(maxsize=1)
def identity_map() -> JointMap:
    """smpl22 onto itself: every joint is the parameter sequence's own joint of that name."""
    names = get_skeleton("smpl22").names
    return JointMap("smpl_parameters", "smpl22", {n: n for n in names}, "human")


def check_body_model(source: str, body_model: str | None, skeleton: Skeleton) -> Path:
    """The ``--option.body_model`` path of an SMPL-family source, checked before any clip is read."""
    if not body_model:
        raise UsageError(f"{source} needs an SMPL-family body model: --option.body_model PATH (a model.npz, or a "
                         "folder with male/ female/ neutral/model.npz)")
    path = Path(body_model)
    if not path.exists():
        raise UsageError(f"{source}: --option.body_model {body_model}: no such file or folder")
    if not path.is_dir():
        BodyModel.load(path)  # fail now, not on the first clip; a FIFO or device is refused unread
    elif not any((path / g / "model.npz").exists() for g in GENDERS):
        raise UsageError(f"{source}: --option.body_model {body_model}: a folder needs male/, female/ or "
                         "neutral/model.npz")
    if list(skeleton.parents) != SMPL22_PARENTS:
        raise UsageError(f"{source} gives smpl22 clips, not {skeleton.name!r}; use --skeleton smpl22")
    return path


def check_sequence_options(source: str, up: str, source_fps: float) -> None:
    """The ``--option.up`` axis and ``--option.source_fps`` of a parameter-file source."""
    if up not in UP_AXES:
        raise UsageError(f"{source}: --option.up {up!r}: expected one of {', '.join(UP_AXES[:6])}")
    if not source_fps > 0:
        raise UsageError(f"{source}: --option.source_fps must be > 0, got {source_fps!r}")


def body_model_for(path: Path, gender: str) -> BodyModel:
    """The model file itself, or from a folder the gender's model (the neutral one where absent)."""
    if not path.is_dir():
        return BodyModel.load(path)
    for name in (gender if gender in GENDERS else "neutral", "neutral"):
        if (path / name / "model.npz").exists():  # a FIFO there is refused (a UsageError), not passed over
            return BodyModel.load(path / name / "model.npz")
    raise ValueError(f"no body model for gender {gender!r}: {path}/{{{gender},neutral}}/model.npz")


def rig_motion(model: BodyModel, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray, fps: float,
               name: str, source: str = "") -> RigMotion:
    """(T, >=66) axis-angle poses (joint 0: global orientation), (T, 3) trans in metres, betas
    -> the body's 22 joints as a ``RigMotion`` in the parameters' own frame."""
    T = len(poses)
    rest = model.rest_joints(betas)  # (22, 3)
    offsets = rest - rest[SMPL22_PARENTS]  # (22, 3) parent -> joint
    offsets[0] = rest[0]
    aa = torch.from_numpy(np.ascontiguousarray(poses[:, : NUM_JOINTS * 3], dtype=np.float64))
    rotations = axis_angle_to_quat(aa.reshape(T, NUM_JOINTS, 3)).numpy()  # (T, 22, 4)
    translations = np.repeat(offsets[None], T, axis=0)  # (T, 22, 3)
    translations[:, 0] = rest[0] + trans
    return RigMotion(name=name, names=list(get_skeleton("smpl22").names), parents=list(SMPL22_PARENTS),
                     offsets=offsets, fps=float(fps), rotations=rotations, translations=translations, source=source)


def check_sequence(what: str, poses: np.ndarray, trans: np.ndarray) -> None:
    """A ValueError ("<what>: ...") for a sequence that cannot be imported."""
    if poses.ndim != 2 or poses.shape[1] < NUM_JOINTS * 3 or trans.shape != (len(poses), 3):
        raise ValueError(f"{what}: poses {poses.shape} and trans {trans.shape}, expected (T, >=66) and (T, 3)")
    if len(poses) < 2:
        raise ValueError(f"{what}: {len(poses)} frame(s), need 2 or more")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise ValueError(f"{what}: NaN or inf in the motion")


def smpl_clip(motion: RigMotion, skeleton: Skeleton, fps: float, up: str, clip_id: str, labels: dict,
              texts: list[str], source: str) -> Clip:
    """The sequence retargeted onto smpl22 (see the module docstring)."""
    try:
        return retarget(motion, skeleton, identity_map(), fps=fps, up=up, id=clip_id, texts=texts, labels=labels,
                        category="human", source=source)
    except UsageError as e:  # too short after resampling, non-finite joints: a bad clip, not a bad command
        raise ValueError(f"{source}: {e}") from None
