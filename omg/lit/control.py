"""Spatial control of diffusion sampling: every denoised estimate steered towards joint targets in the space they
are stated in, global joint positions (OmniControl's spatial guidance, Xie et al. ICLR 2024, applied to x̂0).

``Control`` is the resolved, tensor-level form of a constraints file (``omg.generation.control`` reads and checks
the file): per frame and joint a target position in the model's world (metres, Y up; a motion's first frame has
its root above the XZ origin and faces +Z, as the representation decodes it), the axes that count, a weight and a
tolerance; feet that must stay planted (given, or the model's own contact channels); a facing. It travels in
``SamplingSettings.control``, so ``omg generate``, ``omg serve``, ``omg bench control`` and the callbacks sample
along one path (``MotionDiffusionModule.sample``).

``steered`` wraps the sampler's denoiser: each x̂0 the network estimates is moved to meet the constraints on the
representation's differentiable ``decode`` (``steer``: Gauss-Newton, each pass solved by conjugate gradients
for the least change in the features' own spread; a few iterations per estimate, more on the last estimates,
whose last is the sample). On all but the last estimates the change is smoothed over time by a Gaussian of
``smooth`` frames, the realism term: a target at one frame bends its neighbourhood instead of one frame's pose,
and the network, which denoises the steered estimate at the next step, carries the unconstrained joints and
frames along as its prior would; the last estimates are met exactly, frame by frame. Planted feet (given spans,
the model's own contact channels, the feet each estimate puts on the ground: ``planted_feet``) are residuals of
the same solve: each planted frame's foot against one place per stretch of planted frames (``held_feet``).
Features a target states outright (humanml3d263's root height) are written in (``Representation.inpaint``).
Why x̂0 and not x_t: every registered sampler steps on x̂0 (``omg.samplers``), so one wrapper serves them all,
and the estimate is in the space the targets are stated in after one decode, without a backward pass through
the network.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from omg.diffusion import Denoiser
from omg.errors import UsageError
from omg.io.contacts import CLEANUP_SPEED, EASE_FRAMES
from omg.motion.base import Representation
from omg.skeleton import Skeleton

# weight of a planted foot's distance from its place (m²) against a target's miss (m²): measured on the small
# prior's held-out takes with their paths, 0.1 skated least (0.159, 1.0: 0.190, 0.01: 0.372) and missed the
# targets less than 1.0 (path 4.8 cm against 8.8; 0.01: 2.7)
FEET_STILL = 0.1
PASS = 16  # conjugate-gradient iterations of one Gauss-Newton pass
STRIDE = 0.8  # the root's travel on the ground, in leg lengths, over which a planted foot is held at one place
FACING_WEIGHT = 0.05  # weight of the facing's miss (unit vectors) against a target's (m²): 0.05 ≈ (22 cm)² per rad²


@dataclass(frozen=True, eq=False)
class Control:
    """Resolved constraints of N motions (N = 1: the same for every motion sampled) over T frames and the skeleton's J
    joints.

    ``targets`` (N, T, J, 3) metres; ``axes`` (N, T, J, 3) bool: the axes a target states (a hand's height: Y only);
    ``weights`` (N, T, J) >= 0, 0 where no target is; ``tolerance`` (N, T, J) metres within which a target counts as
    met and pulls no further; ``groups`` (N, T, J) long: the index in ``names`` of the constraint that set the
    target (-1: none), for the errors reported per constraint. ``contacts`` (N, T, F) bool: the skeleton's feet
    (``skeleton.feet`` order) planted at frame t; ``own_contacts``: keep still the feet the model's own contact
    channels plant (``Representation.foot_contacts``); ``ground_contacts``: keep still the feet each estimate puts
    on the ground, low and slow (``ground_feet``; needs ``fps``, the motion's frames per second). ``facing`` (N, T,
    2): the unit XZ direction the body faces (zero where free). Steering: ``iterations`` conjugate-gradient
    iterations per estimate, ``final_iterations`` on the estimates of the last ``final_share`` of the noise levels,
    met without smoothing; ``smooth``: the Gaussian's sigma in frames on the others (0: each frame moves alone);
    ``curvature``: the weight, in every solve, of the change's second difference over time (in the features' own
    spread, against a target's miss in m²), so that a keyframe bends the frames around it instead of moving its own
    frame alone (0: off); ``inpaint``: write in the features a target states outright."""

    targets: Tensor
    axes: Tensor
    weights: Tensor
    tolerance: Tensor
    groups: Tensor
    names: tuple[str, ...] = ()
    contacts: Tensor | None = None
    own_contacts: bool = False
    ground_contacts: bool = False
    fps: float | None = None
    facing: Tensor | None = None
    iterations: int = 4
    # feet held still while a path moves the body are met with the targets in about 64 (four Gauss-Newton passes):
    # fewer leave both part of the way (docs/results/control.md, "Planted feet held and met")
    final_iterations: int = 64
    final_share: float = 0.1
    smooth: float = 2.0
    curvature: float = 0.0
    inpaint: bool = True

    def __post_init__(self) -> None:
        if self.ground_contacts and not (self.fps or 0) > 0:
            raise ValueError("Control.ground_contacts needs the motion's fps")

    @property
    def frames(self) -> int:
        return self.targets.shape[1]

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> Control:
        """The tensors on ``device``, positions in ``dtype``."""
        moved = {k: getattr(self, k) for k in ("targets", "axes", "weights", "tolerance", "groups", "contacts",
                                               "facing")}
        moved = {k: None if v is None else v.to(device, dtype if v.is_floating_point() else v.dtype)
                 for k, v in moved.items()}
        return replace(self, **moved)

    def tiled(self, k: int) -> Control:
        """The control of K copies of the motions (separate timeline chains: K·B rows), itself when N = 1 or
        k = 1."""
        if k == 1 or self.targets.shape[0] == 1:
            return self
        moved = {key: getattr(self, key) for key in ("targets", "axes", "weights", "tolerance", "groups",
                                                      "contacts", "facing")}
        return replace(self, **{key: None if v is None else v.repeat(k, *[1] * (v.ndim - 1))
                                for key, v in moved.items()})


@dataclass(frozen=True)
class HintTraining:
    """A ControlNet trained to read spatial hints (OmniControl's realism branch, Xie et al. ICLR 2024, Sec. 3.3;
    ``omg.models.controlnet``): ``enabled`` gives the network its hint input (``hint_features``, 9 channels a
    joint) and training draws each motion's hints from its own joints (``draw_hints``). OmniControl draws one
    random joint at a random density of frames; here the kinds a constraints file states are drawn, so the
    network sees what users give: a motion without hints with probability ``free_share`` (text alone, as when
    sampled without constraints), else its root path with probability ``root_share`` (on the ground alone, x and
    z, in ``ground_share`` of them), 1 to ``max_joints`` other joints with ``joint_share`` (a joint's height alone in
    a fifth of them), full-body keyframes with ``keyframe_share``, at least one of the three. Each is stated on
    every frame, on one random span or on a random sparse set of frames, a third of the time each; keyframes
    every 10 to 60 frames from a random first one."""

    enabled: bool = False
    free_share: float = 0.1
    root_share: float = 0.5
    ground_share: float = 0.5
    joint_share: float = 0.5
    max_joints: int = 3
    keyframe_share: float = 0.25

    def __post_init__(self) -> None:
        for name in ("free_share", "root_share", "ground_share", "joint_share", "keyframe_share"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
                raise UsageError(f"model.init_args.hints.{name} must be a probability in [0, 1], got {value!r}")
        if isinstance(self.max_joints, bool) or not isinstance(self.max_joints, int) or self.max_joints < 1:
            raise UsageError(f"model.init_args.hints.max_joints must be an integer >= 1, got {self.max_joints!r}")


def hint_channels(skeleton: Skeleton) -> int:
    """Channels of a hint per frame: each joint's stated position, whether each axis is stated, and its stated
    step to the next frame."""
    return 9 * len(skeleton.names)


def hint_features(targets: Tensor, stated: Tensor, fps: float) -> Tensor:
    """targets (N, T, J, 3) metres in the model's world, stated (N, T, J, 3) bool -> hint (N, T, 9·J): per joint its
    stated coordinates (0 where not stated), 1 on each stated axis, and its velocity to the next frame's target in
    m/s where both frames state that axis (0 elsewhere, and at the last frame). The velocity is what the
    representation's root features are made of: a path given at every frame says the root's speed outright."""
    stated = stated.to(targets.dtype)
    both = stated[:, 1:] * stated[:, :-1]  # (N, T-1, J, 3)
    velocity = F.pad((targets[:, 1:] - targets[:, :-1]) * both * fps, (0, 0, 0, 0, 0, 1))  # (N, T, J, 3)
    return torch.cat([targets * stated, stated, velocity], dim=-1).flatten(2)


def control_hint(control: Control, fps: float) -> Tensor:
    """The hint (N, T, 9·J) of a control's targets: the axes each target states where its weight is above 0."""
    return hint_features(control.targets, control.axes & (control.weights > 0)[..., None], fps)


def draw_hints(joints: Tensor, mask: Tensor, hints: HintTraining, generator: torch.Generator, fps: float) -> Tensor:
    """Random hints (B, T, 9·J) of a training batch from its own joints (B, T, J, 3) on its real frames (B, T), as
    ``HintTraining`` describes; every draw from ``generator`` (a run's noise RNG, so a resumed run draws the same)."""
    B, T, J, _ = joints.shape
    device = joints.device
    # per motion: 4 values for each of 4 constraint slots (the root, up to 3 joint slots: frames' kind, span start,
    # span length or density, height alone), then which kinds, free, ground, joint count, keyframe spacing and start
    u = torch.rand(B, 24, generator=generator, device=device).tolist()
    order = (torch.rand(B, J - 1, generator=generator, device=device).argsort(dim=1) + 1).tolist()  # joints, not root
    sparse = torch.rand(B, 4, T, generator=generator, device=device)  # a sparse frame set per slot
    stated = torch.zeros(B, T, J, 3, dtype=torch.bool, device=device)
    frame = torch.arange(T, device=device)

    def frames(b: int, slot: int, n: int) -> Tensor:  # (T,) bool: all n real frames, a span or a sparse set
        kind, start, size = u[b][4 * slot:4 * slot + 3]
        if kind < 1 / 3:
            return frame < n
        if kind < 2 / 3:
            first = int(start * n)
            return (frame >= first) & (frame < first + max(1, int(size * (n - first))))
        chosen = (sparse[b, slot] < 0.02 + 0.18 * size) & (frame < n)
        return chosen if bool(chosen.any()) else frame == int(start * n)  # one frame at least

    for b, n in enumerate(int(n) for n in mask.sum(dim=1).tolist()):
        r = u[b]
        if n == 0 or r[19] < hints.free_share:
            continue
        root, joint, key = r[16] < hints.root_share, r[17] < hints.joint_share, r[18] < hints.keyframe_share
        if not (root or joint or key):
            root = True
        if root:  # the root's path, on the ground alone or with its height
            stated[b, frames(b, 0, n), 0] = torch.tensor([True, r[20] >= hints.ground_share, True], device=device)
        if joint:  # 1 to max_joints other joints, each on its own frames; a fifth of them by their height alone
            for slot, j in enumerate(order[b][:1 + min(int(r[21] * hints.max_joints), J - 2)]):
                slot = 1 + slot % 3
                height_only = r[4 * slot + 3] < 0.2
                stated[b, frames(b, slot, n), j] = torch.tensor([not height_only, True, not height_only], device=device)
        if key:  # full-body poses every 10 to 60 frames from a random first one
            every = 10 + int(r[22] * 51)
            first = int(r[23] * every)
            stated[b, (frame >= first) & ((frame - first) % every == 0) & (frame < n)] = True
    return hint_features(joints, stated & mask[:, :, None, None], fps)


def distances(joints: Tensor, control: Control) -> Tensor:
    """(B, T, J, 3) positions -> (B, T, J) metres from each target on its stated axes (0 where none is)."""
    return ((joints - control.targets) * control.axes).square().sum(-1).add(1e-12).sqrt() * (control.weights > 0)


def facing_of(joints: Tensor, face_joints: tuple[int, ...]) -> Tensor:
    """(..., J, 3) -> (..., 2) unit XZ direction the body faces, from its hips and shoulders (right hip, left hip,
    right shoulder, left shoulder): perpendicular to the line from its right side to its left, Y up."""
    r_hip, l_hip, r_shoulder, l_shoulder = face_joints
    across = (joints[..., l_hip, :] - joints[..., r_hip, :]) + (joints[..., l_shoulder, :] - joints[..., r_shoulder, :])
    forward = torch.stack((-across[..., 2], across[..., 0]), dim=-1)  # (across × up) in XZ
    return F.normalize(forward, dim=-1, eps=1e-8)


def residuals(joints: Tensor, control: Control, representation: Representation,
              hold: tuple[Tensor, Tensor] | None, pull: Tensor) -> Tensor:
    """(B, T, J, 3) positions -> (B, R) residuals whose squares sum to the constraint loss: each target's miss on
    its stated axes times ``pull`` (B, T, J: √weight and the share of the miss beyond the tolerance, fixed where
    the joints were linearised); each planted foot's distance from where its stretch of planted frames holds it
    (``hold``: ``eased`` places (B, T, F, 3), NaN where the foot is free, and their weights (B, T, F, 1); or
    None); the facing's miss."""
    parts = [((joints - control.targets) * control.axes * pull[..., None]).flatten(1)]
    feet = list(representation.skeleton.feet)
    if hold is not None and feet:
        places, weight = hold
        miss = torch.where(places.isfinite(), joints[:, :, feet] - places, 0.0) * weight.sqrt()
        parts.append((math.sqrt(FEET_STILL) * miss).flatten(1))
    if control.facing is not None and representation.skeleton.face_joints:
        given = (control.facing.norm(dim=-1, keepdim=True) > 0)  # (N, T, 1)
        miss = (facing_of(joints, representation.skeleton.face_joints) - control.facing) * given
        parts.append((math.sqrt(FACING_WEIGHT) * miss).flatten(1))
    return torch.cat([p.expand(joints.shape[0], -1) for p in parts], dim=1)


def eased(hold: Tensor, frames: int) -> tuple[Tensor, Tensor]:
    """``held_feet``'s places (B, T, K, 3) -> the same with the ``frames`` frames before each stretch and after it
    held on the ground (x, z) at the stretch's place by a weight falling from the stretch's 1 (frame k outside:
    1 - k / (frames + 1)), and (B, T, K, 1) the weights (1 in a stretch). As the foot clean-up eases its pin
    (``omg.io.contacts``): a foot held still up to its last planted frame and free at the next one jumps there,
    low and fast, which is foot skating (half the skating left on held-out takes with the feet held was on
    such edges); eased, it is set down and lifted off over a few frames. The height stays free: the foot
    rises as it lifts."""
    held = hold[..., :1].isfinite()  # (B, T, K, 1)
    weight = held.to(hold.dtype)
    on_ground = hold.clone()
    on_ground[..., 1] = math.nan  # the height free: the foot rises as it lifts
    out = hold.clone()
    T = hold.shape[1]
    for k in range(1, min(frames, T - 1) + 1):
        w = 1 - k / (frames + 1)
        for near, source in ((slice(0, T - k), slice(k, T)), (slice(k, T), slice(0, T - k))):  # before, after
            take = held[:, source] & (weight[:, near] < w)  # a stretch k frames away, nothing nearer
            out[:, near] = torch.where(take, on_ground[:, source], out[:, near])
            weight[:, near] = torch.where(take, w, weight[:, near])
    return out, weight


def held_feet(joints: Tensor, planted: Tensor, control: Control, feet: list[int], stride: float) -> Tensor:
    """(B, T, J, 3) positions and (B, T, K) planted feet -> (B, T, K, 3): where each stretch of a foot's planted
    frames (two or more in a row) holds it, NaN elsewhere: on each axis the mean of the targets the stretch
    states for that foot (a keyframe's foot), else the mean of the foot's positions over the stretch. A stretch
    is cut where the root (joint 0) has travelled ``stride`` metres on the ground since it began: the foot is
    set down again there.

    Why a place and not each step's length: a step residual couples every frame to the next, and conjugate
    gradients need about as many iterations as the stretch has frames to carry a keyframe's foot along it (16
    left the held-out takes' planted feet moving 2.3 cm a frame, 7x real takes'); a place per stretch leaves
    each frame's residual its own, met in a few iterations, and the next Gauss-Newton pass (or estimate) moves
    the place with the foot. Why the cut: contacts that a path does not fit (the model plants its feet for a
    stretch the path walks on through) would otherwise hold a foot metres behind the body, and meeting both
    leaves the targets missed by tens of centimetres; no foot stays planted while the body travels farther
    than a step."""
    B, T, K = planted.shape
    root = joints[:, :, 0, [0, 2]].detach()  # (B, T, 2) on the ground
    travel = F.pad((root[:, 1:] - root[:, :-1]).norm(dim=-1).cumsum(1), (1, 0))[..., None]  # (B, T, 1) so far
    start = planted & ~F.pad(planted[:, :-1], (0, 0, 1, 0))  # (B, T, K) a stretch begins
    began = torch.where(start, travel, -math.inf).cummax(1).values  # (B, T, K) the travel where it began
    piece = ((travel - began) / stride).floor().clamp(min=0, max=T).long()  # (B, T, K) the step since then
    start = start | (planted & (piece != F.pad(piece[:, :-1], (0, 0, 1, 0), value=-1)))
    stretch = start.long().cumsum(1) * planted  # (B, T, K) 1, 2, ... per stretch; 0 where free
    slots = (torch.arange(B * K, device=planted.device).view(B, 1, K) * (T + 1) + stretch).flatten()  # (B*T*K,)

    def total(values: Tensor) -> Tensor:  # (B, T, K, k) summed over each stretch, back on its frames
        flat = values.flatten(0, 2)
        sums = flat.new_zeros(B * K * (T + 1), flat.shape[-1]).index_add_(0, slots, flat)
        return sums[slots].view(B, T, K, -1)

    on = planted[..., None].to(joints.dtype)  # (B, T, K, 1)
    position = joints[:, :, feet].detach()  # (B, T, K, 3)
    stated = (control.axes[:, :, feet] & (control.weights[:, :, feet] > 0)[..., None]).to(joints.dtype)
    stated = stated.expand(B, -1, -1, -1) * on  # (B, T, K, 3)
    count, given = total(on), total(stated)
    aimed = total(control.targets[:, :, feet].expand(B, -1, -1, -1) * stated) / given.clamp(min=1)
    place = torch.where(given > 0, aimed, total(position * on) / count.clamp(min=1))
    return torch.where((count >= 2) & planted[..., None], place, math.nan)


def leg_length(skeleton: Skeleton) -> float:
    """The longest distance from the root to a foot joint in the rest pose (metres; 1 for a skeleton without
    feet, which holds none)."""
    rest = skeleton.rest_positions()
    return float(max((np.linalg.norm(rest[f] - rest[0]) for f in skeleton.feet), default=1.0))


def planted_feet(features: Tensor, joints: Tensor, control: Control, representation: Representation,
                 mask: Tensor) -> Tensor | None:
    """(B, T, F) bool: the feet ``control`` plants, with those the features' own contact channels plant and
    those their joints (B, T, J, 3) put on the ground, on each motion's real frames (``mask``, (B, T))."""
    found = [control.contacts] if control.contacts is not None else []
    if control.own_contacts and (own := representation.foot_contacts(features)) is not None:
        found.append(own > 0.5)
    if control.ground_contacts:
        found.append(ground_feet(joints.detach(), mask, representation.skeleton, control.fps))
    if not found:
        return None
    planted = found[0]
    for more in found[1:]:
        planted = planted | more
    return planted.expand(mask.shape[0], -1, -1) & mask[..., None]


def ground_feet(joints: Tensor, mask: Tensor, skeleton: Skeleton, fps: float) -> Tensor:
    """(B, T, J, 3) positions -> (B, T, F) bool: each foot joint low and slow on each motion's real frames (the
    house's ground contact, ``omg.kinematics.ground_contacts``, at the foot clean-up's speed: a generated foot
    that lingers on the ground slides, and the clean-up pins what this holds)."""
    from omg.kinematics import ground_contacts

    planted = torch.zeros(*joints.shape[:2], len(skeleton.feet), dtype=torch.bool, device=joints.device)
    for b, n in enumerate(mask.sum(1).tolist()):
        if n > 1:
            planted[b, :n] = ground_contacts(joints[b, :n], skeleton.feet, fps, max_speed=CLEANUP_SPEED)
    return planted


def target_pull(joints: Tensor, control: Control) -> Tensor:
    """(B, T, J): √weight times the share of each target's miss beyond its tolerance (0 within it)."""
    dist = distances(joints, control)
    beyond = (1 - control.tolerance / dist.clamp(min=1e-9)).clamp(min=0)
    return control.weights.sqrt() * beyond


def gaussian_kernel(sigma: float, frames: int, device: torch.device, dtype: torch.dtype) -> Tensor | None:
    """(1, 1, 2r + 1) a Gaussian of ``sigma`` frames cut at 3 sigma (and within ``frames``), summing to 1; None
    where it would change nothing (sigma 0, or a radius under one frame)."""
    if sigma <= 0:
        return None
    radius = min(int(3 * sigma + 0.5), frames - 1)
    if radius < 1:
        return None
    offsets = torch.arange(-radius, radius + 1, device=device, dtype=dtype)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    return (kernel / kernel.sum()).view(1, 1, -1)


def gaussian_smoother(sigma: float, frames: int, device: torch.device,
                      dtype: torch.dtype) -> Callable[[Tensor], Tensor]:
    """(B, T, D) -> the same smoothed along T by a Gaussian of ``sigma`` frames (edges repeated); identity at 0."""
    kernel = gaussian_kernel(sigma, frames, device, dtype)
    if kernel is None:
        return lambda z: z
    radius = kernel.shape[-1] // 2

    def smooth(z: Tensor) -> Tensor:
        B, T, D = z.shape
        flat = z.transpose(1, 2).reshape(B * D, 1, T)
        flat = F.conv1d(F.pad(flat, (radius, radius), mode="replicate"), kernel)
        return flat.reshape(B, D, T).transpose(1, 2)

    return smooth


def smoothed(denoise: Denoiser, sigma: float, mask: Tensor, fixed: tuple[int, ...]) -> Denoiser:
    """``denoise`` whose every x̂0 (B, T, D) is smoothed over time by a Gaussian of ``sigma`` frames (sampling's
    ``smoothing``), each motion over its own frames (``mask``) and the ``fixed`` channels (flags, such as foot
    contacts: ``Representation.contact_features``) left as they are; the identity at sigma 0.

    Why: a guided sample's joints shake from frame to frame (the small recipe's ControlNet: 4.8x the real takes'
    jerk, a seventh of its joints' velocity power above 5 Hz against a hundredth in real takes; guidance 1 halves
    it), noise no sampler or step count removes. Smoothing every estimate, not the sample alone, lets the network
    denoise the smoothed estimate at the next step, so it keeps what its motion says; the last estimate is the
    sample, smoothed. The features are smoothed where they are normalised, which is the same as in the
    representation's own units (normalising is affine per channel). A motion's first and last frames average over
    the frames it has (the Gaussian renormalised, not its edge repeated), so a motion smooths alike whatever
    length the motions sampled with it have."""
    kernel = gaussian_kernel(sigma, mask.shape[1], mask.device, torch.float32)
    if kernel is None:
        return denoise
    radius = kernel.shape[-1] // 2
    on = mask[..., None]  # (B, T, 1)

    def smoothed_denoise(x: Tensor, t: Tensor) -> Tensor:
        x0 = denoise(x, t)  # (B, T, D)
        B, T, D = x0.shape
        k, weight = kernel.to(x0.dtype), on.to(x0.dtype)
        flat = (x0 * weight).transpose(1, 2).reshape(B * D, 1, T)
        total = F.conv1d(F.pad(flat, (radius, radius)), k).reshape(B, D, T).transpose(1, 2)
        share = F.conv1d(F.pad(weight.transpose(1, 2), (radius, radius)), k).transpose(1, 2)  # (B, T, 1)
        channels = torch.ones(D, dtype=torch.bool, device=x0.device)
        channels[list(fixed)] = False
        return torch.where(on & channels, total / share.clamp(min=1e-12), x0)

    return smoothed_denoise


def feature_change(change: Tensor, integrated: tuple[int, ...], smooth: Callable[[Tensor], Tensor]) -> Tensor:
    """(B, T, D) change per frame, in the features' own units -> the change of the features: smoothed over time,
    and on the ``integrated`` channels (a velocity whose running sum ``decode`` takes) the difference of the
    change from frame t to t + 1, so that each frame's target asks a change of its own frame (a root displaced
    at frame t), not a sum over every frame before it: the problem stays about as well conditioned as the targets
    are."""
    change = smooth(change)
    if not integrated:
        return change
    index = list(integrated)
    moved = change[..., index]
    stepped = F.pad(moved[:, 1:] - moved[:, :-1], (0, 0, 0, 1))  # the last row moves no frame after it
    return change.index_copy(-1, torch.tensor(index, device=change.device), stepped)


def steer(x0: Tensor, control: Control, representation: Representation, std: Tensor, mean: Tensor, mask: Tensor,
          iterations: int) -> Tensor:
    """x̂0 (B, T, D) normalised -> moved to meet ``control`` (``solve``): with a facing, first the heading alone
    towards it (the one channel decode is not linear in), then every other channel, the heading kept, towards the
    targets and planted feet (turning the whole body is no way to reach a hand's target)."""
    base = x0 * std + mean
    if control.inpaint:
        stated = control.axes & (control.weights > 0)[..., None]
        base = torch.where(mask[..., None], representation.inpaint(base, control.targets, stated), base)
    if iterations <= 0:
        return (base - mean) / std
    integrated, heading = representation.integrated_features(), list(representation.heading_features())
    # the change's unit per channel: the feature's spread in the data, so that the least change moves each feature
    # in proportion to it; an integrated channel's change is an offset of its running sum (a root displacement, a
    # heading), whose spread over T frames of a random walk is √T velocities': in a velocity's own spread, the
    # displacements the targets ask would be T-fold and CG would crawl through them
    scale = std.clone()
    scale[list(integrated)] *= math.sqrt(x0.shape[1])
    turning = torch.zeros_like(scale)
    turning[heading] = scale[heading]
    scale[heading] = 0.0
    if control.facing is not None and heading:
        facing_only = replace(control, weights=torch.zeros_like(control.weights), contacts=None, own_contacts=False,
                              ground_contacts=False)
        base = solve(base, facing_only, representation, turning, mask, iterations)
    return (solve(base, control, representation, scale, mask, iterations) - mean) / std


def solve(base: Tensor, control: Control, representation: Representation, scale: Tensor, mask: Tensor,
          iterations: int) -> Tensor:
    """Features (B, T, D) -> changed to meet ``control``: Gauss-Newton passes on the residuals of their decoded
    joints (``residuals``), each solved by up to ``PASS`` conjugate-gradient (CGLS) iterations, ``iterations`` in
    all. The change is sought in units of ``scale`` (D,) per channel (0: the channel stays) through
    ``feature_change`` (smoothed over time, integrated channels changed by differences), and CGLS started from no
    change finds the least change that meets the targets, the rest of the motion kept."""
    keep = mask[..., None].to(base.dtype)  # (B, T, 1)
    smooth = gaussian_smoother(control.smooth, base.shape[1], base.device, base.dtype)
    integrated = representation.integrated_features()
    feet, stride = list(representation.skeleton.feet), STRIDE * leg_length(representation.skeleton)
    change = torch.zeros_like(base)

    def features_of(z: Tensor) -> Tensor:
        return base + feature_change(z, integrated, smooth) * scale * keep

    with torch.enable_grad():
        for start in range(0, iterations, PASS):
            now = features_of(change)
            joints = representation.decode(now)
            planted = planted_feet(now, joints, control, representation, mask)
            hold = None if planted is None else eased(held_feet(joints, planted, control, feet, stride), EASE_FRAMES)
            pull = target_pull(joints, control)

            def residual(z: Tensor) -> Tensor:
                r = residuals(representation.decode(features_of(z)), control, representation, hold, pull)
                if control.curvature > 0:  # the change's bend from frame to frame, each motion on its own frames
                    moved = z * keep
                    bend = moved[:, 2:] - 2 * moved[:, 1:-1] + moved[:, :-2]  # (B, T-2, D)
                    r = torch.cat([r, math.sqrt(control.curvature) * bend.flatten(1)], dim=1)
                return r

            point = change.clone().requires_grad_(True)
            r0 = residual(point)  # (B, R), its graph kept for the transposed products

            def vjp(u: Tensor) -> Tensor:
                return torch.autograd.grad(r0, point, u, retain_graph=True)[0]

            def jvp(v: Tensor) -> Tensor:
                # a forward difference: exact where decode is linear in the change (positions given the heading),
                # and a fifth of the cost of forward-mode autograd here
                h = 1e-2 / v.abs().flatten(1).amax(1).clamp(min=1e-12)  # (B,) a step of 0.01 in the largest unit
                with torch.no_grad():
                    return (residual(change + h[:, None, None] * v) - r0.detach()) / h[:, None]

            # CGLS for each motion on its own (its own step sizes): min ‖r0 + J·delta‖ from delta = 0
            delta, r = torch.zeros_like(change), -r0.detach()
            s = vjp(r)
            p, gamma = s, s.square().flatten(1).sum(1)  # (B,)
            for _ in range(min(PASS, iterations - start)):
                q = jvp(p)
                alpha = gamma / q.square().flatten(1).sum(1).clamp(min=1e-30)
                delta, r = delta + alpha[:, None, None] * p, r - alpha[:, None] * q
                s = vjp(r)
                gamma_next = s.square().flatten(1).sum(1)
                p, gamma = s + (gamma_next / gamma.clamp(min=1e-30))[:, None, None] * p, gamma_next
            change = (change + delta).detach()
    return features_of(change)


def steered(denoise: Denoiser, control: Control, representation: Representation, std: Tensor, mean: Tensor,
            mask: Tensor, num_timesteps: int, steps: int) -> Denoiser:
    """``denoise`` whose every x̂0 is steered towards ``control`` (``steer``): ``control.iterations`` per
    estimate, ``control.final_iterations`` once the noise level t is in the last ``final_share`` of the
    schedule (the estimates that become the sample)."""
    # the last share of the schedule, and at least the last of ``steps`` evenly spaced steps (a few-step solver's
    # last noise level is T / steps, above a tenth of T)
    final = max(control.final_share * num_timesteps, num_timesteps / steps + 1)

    def steered_denoise(x: Tensor, t: Tensor) -> Tensor:
        x0 = denoise(x, t)
        if float(t.max()) < final:  # the estimates that become the sample: met exactly, each frame on its own
            return steer(x0, replace(control, smooth=0.0), representation, std, mean, mask, control.final_iterations)
        return steer(x0, control, representation, std, mean, mask, control.iterations)

    return steered_denoise


def constraint_errors(joints: Tensor, control: Control) -> list[dict[str, float]]:
    """(B, T, J, 3) -> per motion, each named constraint's worst distance to its targets (metres)."""
    dist = distances(joints, control)  # (B, T, J)
    groups = control.groups.expand(dist.shape)
    out = []
    for b in range(dist.shape[0]):
        row: dict[str, float] = {}
        for index, name in enumerate(control.names):
            chosen = groups[b] == index
            if chosen.any():
                row[name] = float(dist[b][chosen].max())
        out.append(row)
    return out
