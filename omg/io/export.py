"""``omg export``: joint positions -> local rotations (IK) -> BVH files and GIF previews.

Generated motions are joint positions; animation tools want a rig with local rotations.
``positions_to_rotations`` solves them for a fixed skeleton: each joint turns the rest
directions of its child bones onto the observed ones, aiming from where forward kinematics
has put the joint so far, so that errors do not accumulate along a chain.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from omg.cli import ToolParser, check_output_dir, positive_float, read_text
from omg.errors import UsageError
from omg.io.bvh import write_bvh
from omg.io.contacts import clean_foot_contacts
from omg.rotations import matrix_to_quat, quat_apply, quat_between, quat_conjugate, quat_identity, quat_mul
from omg.skeleton import Skeleton, get_skeleton

DEFAULT_FPS = 20.0
DEFAULT_SKELETON = "smpl22"
EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def _best_rotation(rest: torch.Tensor, observed: torch.Tensor) -> torch.Tensor:
    """(C, 3) rest directions, (T, C, 3) observed ones -> (T, 3, 3) least-squares rotation (Kabsch)."""
    U, _, Vh = torch.linalg.svd(rest.T @ observed)  # of the (T, 3, 3) cross-covariance
    V, Ut = Vh.transpose(-1, -2), U.transpose(-1, -2)
    # flip the weakest axis where the best orthogonal fit is a reflection (e.g. coplanar bones)
    d = torch.sign(torch.linalg.det(V @ Ut))
    return V @ torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1)) @ Ut


def clip_offsets(skeleton: Skeleton, positions: torch.Tensor) -> torch.Tensor:
    """(T, J, 3) -> (J, 3) rest offsets for IK: the skeleton's bone directions, the clip's mean lengths.

    The child bones of a joint with several (hips and spine from the pelvis) keep the angles
    between them that the clip has, turned to fit the skeleton's directions best: no rotation
    can match them otherwise (HumanML3D's uniform skeleton has its hips level, SMPL's drop).
    """
    rest = torch.as_tensor(skeleton.rest_offsets, dtype=positions.dtype)
    dirs = F.normalize(rest, dim=-1)
    for j in range(skeleton.num_joints):
        children = skeleton.children(j)
        if len(children) > 1:
            observed = F.normalize(positions[:, children] - positions[:, j, None], dim=-1)  # (T, C, 3)
            R = _best_rotation(dirs[children], observed)  # (T, 3, 3)
            dirs[children] = F.normalize((observed @ R).mean(0), dim=-1)  # R^T o per frame, averaged
    parents = torch.tensor(skeleton.parents[1:])
    lengths = (positions[:, 1:] - positions[:, parents]).norm(dim=-1).mean(0)  # (J - 1,)
    return torch.cat([rest[:1], dirs[1:] * lengths[:, None]])


def positions_to_rotations(
    skeleton: Skeleton | str,
    positions: np.ndarray,  # (T, J, 3) metres
    offsets: np.ndarray | None = None,  # (J, 3) rest offsets to keep as they are
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # rotations (T, J, 4), root (T, 3), offsets (J, 3)
    """Local joint rotations that reproduce ``positions`` by forward kinematics.

    Without ``offsets`` the bones come from ``clip_offsets``, so that FK is exact up to the
    clip's own bone-length jitter. A joint with one child bone gets the shortest arc in its
    parent's frame (no twist of its own: smooth in time, as a tracked limb would be); one
    with several (pelvis, chest) gets the best-fit rotation of all of them. Leaf joints,
    whose twist no position shows, keep the identity.
    """
    skel = get_skeleton(skeleton)
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float64)  # (T, J, 3)
    if pos.ndim != 3 or pos.shape[1:] != (skel.num_joints, 3):
        raise ValueError(f"positions must be (T, {skel.num_joints}, 3) for {skel.name!r}, got {tuple(pos.shape)}")
    off = clip_offsets(skel, pos) if offsets is None else torch.as_tensor(np.asarray(offsets), dtype=torch.float64)
    T, J = pos.shape[:2]
    local = quat_identity((T, J), dtype=torch.float64)
    identity = quat_identity((T,), dtype=torch.float64)
    world = [identity] * J  # (T, 4) global rotations
    fk = [pos[:, 0]] * J  # (T, 3) joint positions as FK places them
    for j, p in enumerate(skel.parents):
        parent_rot = world[p] if p >= 0 else identity
        if p >= 0:
            fk[j] = fk[p] + quat_apply(parent_rot, off[j])
        children = skel.children(j)
        if len(children) == 1:
            aim = quat_apply(quat_conjugate(parent_rot), pos[:, children[0]] - fk[j])  # (T, 3) in the parent frame
            local[:, j] = quat_between(off[children[0]].expand_as(aim), aim)
        elif children:
            aim = F.normalize(pos[:, children] - fk[j][:, None], dim=-1)  # (T, C, 3)
            best = matrix_to_quat(_best_rotation(F.normalize(off[children], dim=-1), aim))
            local[:, j] = quat_mul(quat_conjugate(parent_rot), best)
        world[j] = quat_mul(parent_rot, local[:, j])
    return local.float().numpy(), pos[:, 0].float().numpy(), off.float().numpy()


def export_motion(
    out_stem: str | Path,
    positions: np.ndarray,  # (T, J, 3) metres, Y up
    skeleton: Skeleton | str,
    fps: float,
    texts: list[str] | None = None,
    preview: bool = True,
    order: str = "ZXY",
    scale: float = 1.0,
    clean_contacts: bool = False,
) -> dict:
    """Write ``<stem>.bvh`` and, with ``preview``, ``<stem>.gif``; returns what was written.
    ``clean_contacts`` pins planted feet first (``omg.io.contacts``)."""
    from omg.io.render import render_gif

    skel = get_skeleton(skeleton)
    if clean_contacts:
        positions = clean_foot_contacts(positions, skel, fps)
    rotations, root, offsets = positions_to_rotations(skel, positions)
    fk = skel.forward_kinematics(torch.from_numpy(rotations), torch.from_numpy(root), torch.from_numpy(offsets))
    stem = Path(out_stem)
    report = {
        "bvh": str(write_bvh(stem.with_name(f"{stem.name}.bvh"), skel, rotations, root, fps, offsets, order, scale)),
        "frames": len(positions),
        "ik_error_m": float(np.abs(fk.numpy() - positions).max()),
    }
    if preview:
        title = " / ".join(texts) if texts else stem.name
        report["gif"] = str(render_gif(stem.with_name(f"{stem.name}.gif"), [fk.numpy()], skel, fps, titles=[title]))
    return report


def parse_args(argv: list[str]):
    p = ToolParser(prog="omg export", description="Write BVH files (and GIF previews) of generated motions.")
    p.add_argument("inputs", nargs="+", help="directories (of *.joints.npy, else *.features.npy) or .npy files")
    p.add_argument("--skeleton", help=f"skeleton name (default: generation.json's, else {DEFAULT_SKELETON})")
    p.add_argument("--fps", type=positive_float, help=f"frames per second (default: generation.json's, else {DEFAULT_FPS:g})")
    p.add_argument("--representation", help="decode *.features.npy with this representation (e.g. humanml3d263)")
    p.add_argument("--order", default="ZXY", choices=EULER_ORDERS, help="Euler order of the BVH rotation channels")
    p.add_argument("--scale", type=positive_float, default=1.0, help="BVH units per metre (100 for centimetres)")
    p.add_argument("--no-preview", action="store_true", help="skip the GIF previews")
    p.add_argument("--out", help="write the files into this folder (default: beside each input)")
    p.add_argument("--clean-contacts", action="store_true", help="pin planted feet (removes foot skating) before IK")
    return p.parse_args(argv)


def _inputs(spec: str) -> list[Path]:
    path = Path(spec)
    if path.is_dir():
        files = sorted(path.glob("*.joints.npy")) or sorted(path.glob("*.features.npy"))
        if not files:
            raise UsageError(f"{path}: no *.joints.npy or *.features.npy files to export")
        return files
    if not path.is_file() or path.suffix != ".npy":
        raise UsageError(f"{path}: not a directory or an existing .npy file")
    return [path]


def _settings(directory: Path) -> dict:
    """``omg generate``'s generation.json beside the motions, checked; {} when there is none."""
    path = directory / "generation.json"
    if not path.exists() and not path.is_symlink():
        return {}
    try:
        settings = json.loads(read_text(path, "settings file"))
    except json.JSONDecodeError as e:
        raise UsageError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(settings, dict):
        raise UsageError(f"{path}: expected a JSON object (omg generate's settings), got a JSON {type(settings).__name__}")
    for key in ("skeleton", "representation"):
        if settings.get(key) is not None and not isinstance(settings[key], str):
            raise UsageError(f"{path}: {key!r} must be a name, got {settings[key]!r}")
    fps = settings.get("fps")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float))
                            or not math.isfinite(fps) or fps <= 0):
        raise UsageError(f"{path}: 'fps' must be a positive number, got {fps!r}; or pass --fps")
    prompts = settings.get("prompts")
    if prompts is not None and not (isinstance(prompts, list) and all(isinstance(p, str) for p in prompts)):
        raise UsageError(f"{path}: 'prompts' must be a list of strings, got {prompts!r}")
    num = settings.get("num_samples")
    if num is not None and (isinstance(num, bool) or not isinstance(num, int) or num < 1):
        raise UsageError(f"{path}: 'num_samples' must be a positive integer, got {num!r}")
    return settings


def _prompt(settings: dict, stem: str) -> list[str]:
    """``omg generate`` writes ``num_samples`` motions per prompt, named sample_NNN in order."""
    prompts, match = settings.get("prompts") or [], re.fullmatch(r"sample_(\d+)", stem)
    if not prompts or not match:
        return []
    index = int(match.group(1)) // max(int(settings.get("num_samples", 1)), 1)
    return [prompts[index]] if index < len(prompts) else []


def _load_positions(path: Path, skeleton: Skeleton, representation: str | None) -> np.ndarray:
    """(T, J, 3) joint positions from a joints file, or decoded from a features file."""
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise UsageError(f"{path}: cannot read as a .npy array ({e})") from None
    if not np.issubdtype(array.dtype, np.number):
        raise UsageError(f"{path}: expected a numeric array, got dtype {array.dtype}")
    if not np.isfinite(array).all():
        raise UsageError(f"{path}: contains NaN or inf values")
    J = skeleton.num_joints
    if path.name.endswith(".features.npy"):
        from omg.motion import get_representation

        if representation is None:
            raise UsageError(f"{path}: a features file needs --representation (e.g. humanml3d263)")
        try:
            rep = get_representation(representation, skeleton)
        except UsageError as e:
            raise UsageError(f"{path}: {e}") from None
        if array.ndim != 2 or array.shape[1] != rep.dim or len(array) < 1:
            raise UsageError(f"{path}: expected features (T, {rep.dim}) for {rep.name}, got shape {array.shape}")
        return rep.decode(torch.from_numpy(array.astype(np.float32))).numpy()
    if array.ndim != 3 or array.shape[1:] != (J, 3) or len(array) < 1:
        raise UsageError(
            f"{path}: expected joint positions (T, {J}, 3) for skeleton {skeleton.name!r}, got shape {array.shape}"
        )
    return array.astype(np.float32)


def main(argv: list[str]) -> None:
    args = parse_args(argv)
    if args.representation is not None:
        from omg.registry import REPRESENTATIONS

        REPRESENTATIONS.get(args.representation)  # an unknown name is a UsageError naming the known ones
    if args.skeleton is not None:
        get_skeleton(args.skeleton)
    out = check_output_dir(args.out) if args.out else None
    jobs = []  # every file is read and checked before anything is written
    for path in [f for spec in args.inputs for f in _inputs(spec)]:
        settings = _settings(path.parent)
        skel = get_skeleton(args.skeleton or settings.get("skeleton") or DEFAULT_SKELETON)
        positions = _load_positions(path, skel, args.representation or settings.get("representation"))
        stem = path.with_name(re.sub(r"(\.joints|\.features)?\.npy$", "", path.name))
        if args.out:
            stem = out / stem.name
        fps = args.fps or settings.get("fps") or DEFAULT_FPS
        jobs.append((path, stem, positions, skel, fps, _prompt(settings, stem.name)))
    extensions = ("bvh",) if args.no_preview else ("bvh", "gif")
    targets = [stem.with_name(f"{stem.name}.{ext}") for _, stem, *_ in jobs for ext in extensions]
    for target in targets:
        if target.is_dir():
            raise UsageError(f"{target}: a folder is in the way of the output file; move it or export elsewhere")
        if target.parent.exists() and not os.access(target.parent, os.W_OK | os.X_OK):
            raise UsageError(f"{target.parent}: not writable; copy the motions to a folder you can write to")
    if len({t for t in targets}) < len(targets):
        raise UsageError("two inputs have the same name and would be written to the same --out file; export them apart")
    new = [t for t in targets if not t.exists()]
    created = out is not None and not out.exists()
    try:
        if created:
            out.mkdir(parents=True)
        for path, stem, positions, skel, fps, texts in jobs:
            start = time.perf_counter()
            report = export_motion(stem, positions, skel, fps, texts, not args.no_preview, args.order, args.scale,
                                   args.clean_contacts)
            written = ", ".join(Path(report[k]).name for k in ("bvh", "gif") if k in report)
            print(f"{path}: {written} ({report['frames']} frames at {fps:g} fps, IK error "
                  f"{report['ik_error_m'] * 1000:.3f} mm, {time.perf_counter() - start:.1f} s)")  # fmt: skip
    except Exception:  # a failed export leaves none of the files it created
        for target in new:
            target.unlink(missing_ok=True)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
