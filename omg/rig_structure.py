"""A human rig's SMPL-22 joints, or a quadruped's SMAL-35 joints, found from its hierarchy and standing pose,
whatever its joints are called (``rig_structure``).

Used by ``omg.retarget.scaffold_joint_map`` for the joints no name matches; every proposal comes with the
reason it was made, and where the rest pose does not tell (a rig without mirror symmetry, feet that do not
point forward and names without a side), nothing is proposed rather than a guess. The rig's frame: the
lateral axis is the one the rest pose is mirror-symmetric across, up the longer of the other two (its sign:
the one a biped is found in, below; neither or both: nothing), forward the way the feet point (toes ahead
of ankles). A joint at its parent's place (CMU's ``LHipJoint`` at the hips) is passed over: its parent
turns what hangs from both. Then:

- pelvis: where the lowest joints off the mirror plane on either side (the feet) branch apart;
- legs: the chain from the pelvis to each foot; hip, knee and ankle start, join and end its two longest
  consecutive bones (the first no shorter than ``PROXIMAL`` of the second), the foot is the joint (or the
  end site) after the ankle;
- spine: the chain from the pelvis to the highest joint on the mirror plane (the head's top); spine3 is
  where the arms branch from it, spine1 and spine2 the joints between the pelvis and spine3, neck the joint
  above spine3 and head the next (one named head where there is one);
- arms: the subtrees off the spine reaching farthest to either side, each ending at its joint farthest from
  spine3 (a fingertip); shoulder, elbow and wrist start, join and end its two longest consecutive bones as a
  leg's, the collar the joint before the shoulder.

Left and right: by the joints' names where they say (``L``, ``left``, ``.l``: ``omg.retarget``'s side
tokens), else from up and forward (left = up x forward).

A quadruped (``quadruped_joints``): a dog's longest axis is its length, and its four legs hang from two girdles;
the legs are the two pairs of longest mirror-image limbs, the hind pair's girdle (the pelvis) an ancestor of the
front pair's, up the way they hang, forward from the hind girdle to the front one; it stands where the legs hang
down, their tips end near one ground and the spine runs along it (a biped's arms fail: they do not reach the
ground). A rig whose rest pose (every rotation zero) stands on no legs (the Bandai-Namco and MANN dog BVHs: their
offsets lie along each joint's own axes) is read in a frame of its own clip (``rig_structure``).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from omg.io.rig import RigMotion

MIRROR = 0.03  # of the rig's size: mean distance of a joint's mirror image to the nearest joint on a symmetric rig
ON_PLANE = 0.03  # of the rig's height: a joint this close to the mirror plane is on the body's centre line
CLEAR = 0.02  # of the rig's height: toes no further ahead of their ankles than this point nowhere
LONG_BONE = 0.1  # of the rig's height: the shortest upper arm, forearm, thigh or shin a human rig has
PROXIMAL = 0.8  # the shortest a thigh is of its shin, an upper arm of its forearm (adults: 1.0 and 1.27)
ARM_OUT = 0.05  # of the rig's height: the least a hand reaches out from the centre line (arms hanging down: 0.13)
SAME_PLACE = 1e-3  # of the rig's height: a joint this close to its parent is a second joint at the same place
LIMB_BONE = 0.6  # of a quadruped leg's longest bone: its first bone this long starts the leg (a shoulder blade less)
LEGS_DOWN = 0.5  # cos 60 degrees: the least a standing quadruped's leg points down, girdle to tip
GROUND = 0.4  # of a quadruped's mean leg: its paws' tips this close to the lowest one stand on the ground
PAIRED = 0.1  # of a limb's longest bone: the most two mirror-image limbs' bones differ in length
STAND = 0.6  # the least a quadruped's leg's tip is below its top on average, of the leg's length: it stands
TAIL_CLEAR = 0.1  # of a quadruped's mean leg: a tail this far above the ground touches nothing (a leg would)
SAMPLED = 64  # frames of a clip spread over it that a rig whose rest pose stands on no legs is looked at in
FRAME_MIRROR = 0.15  # MIRROR in a clip's frame: a walking animal swings its legs, turns its head, sways its tail
# the joints a frame's up is read along: from the first (the hind legs' lower joints, the pelvis) to the second
UPRIGHT = {"smal35": (("LLegBack3", "RLegBack3"), "pelvis"), "smpl22": (("pelvis",), "spine3")}
HEMISPHERE = 400  # directions a frame's mirror plane is first looked for among (about 6 degrees apart)


def _path(parents: list[int], child: int, ancestor: int) -> list[int] | None:
    """Joints from ``ancestor`` (excluded) down to ``child`` (included); None if it is not an ancestor."""
    out = []
    while child != ancestor:
        if child < 0:
            return None
        out.append(child)
        child = parents[child]
    return out[::-1]


def _ancestors(parents: list[int], j: int) -> list[int]:
    out = [j]
    while parents[j] >= 0:
        j = parents[j]
        out.append(j)
    return out


def _limb(chain: list[int], rest: np.ndarray, height: float) -> int | None:
    """The index in ``chain`` of a limb's first long bone's start (hip, shoulder): the two longest
    consecutive bones, the first no shorter than ``PROXIMAL`` of the second (a thigh is as long as its shin,
    an upper arm longer than its forearm; a collar bone shorter than its upper arm), start, join and end at
    chain[k], chain[k + 1], chain[k + 2]; None if no two are long."""
    seg = np.linalg.norm(np.diff(rest[chain], axis=0), axis=1)  # (len - 1,)
    pairs = [(seg[k] + seg[k + 1], k) for k in range(len(seg) - 1)
             if min(seg[k], seg[k + 1]) >= LONG_BONE * height and seg[k] >= PROXIMAL * seg[k + 1]]
    return max(pairs)[1] if pairs else None


@dataclass(frozen=True)
class _Frame:
    """A rig's rest pose in the body's terms."""

    lateral: int  # the axis the rest pose is mirror-symmetric across
    up: int  # the longer of the other two
    fwd: int
    sign: float  # +1 where up points along +axis
    side: np.ndarray  # (J,) each joint's distance off the mirror plane, along +lateral
    h: np.ndarray  # (J,) each joint's height along up
    height: float  # the rest pose's extent along up


def _lateral(rest: np.ndarray, mirror: float = MIRROR) -> int | None:
    """The axis ``rest`` (P, 3) is mirror-symmetric across (to within ``MIRROR``: the mean distance of each
    point's mirror image to the nearest point, of the pose's size); None where there is none."""
    extent = rest.max(0) - rest.min(0)  # (3,)
    size = float(extent.max())
    centre = (rest.max(0) + rest.min(0)) / 2

    def mirror_error(axis: int) -> float:
        image = rest.copy()
        image[:, axis] = 2 * centre[axis] - image[:, axis]
        return float(np.linalg.norm(image[:, None] - rest[None], axis=-1).min(1).mean()) / size

    axes = [a for a in range(3) if extent[a] > 0.05 * size]  # a dog rig is as narrow as a tenth of its length
    if size <= 0 or len(axes) < 2:
        return None
    lateral = min(axes, key=mirror_error)
    return lateral if mirror_error(lateral) <= mirror else None


def _frame(rest: np.ndarray, sign: float, mirror: float = MIRROR) -> _Frame | None:
    extent = rest.max(0) - rest.min(0)  # (3,)
    centre = (rest.max(0) + rest.min(0)) / 2
    lateral = _lateral(rest, mirror)
    if lateral is None:
        return None
    up, fwd = sorted((a for a in range(3) if a != lateral), key=lambda a: -extent[a])
    if extent[up] < 1.5 * extent[fwd]:
        return None  # a lying or four-legged rig: no axis is clearly its height
    return _Frame(lateral, up, fwd, sign, rest[:, lateral] - centre[lateral], sign * rest[:, up], float(extent[up]))


def humanoid_joints(motion: RigMotion, side_of: Callable[[str], str | None], pose: np.ndarray | None = None,
                    mirror: float = MIRROR) -> dict[str, tuple[str, str]]:
    """SMPL-22 joint -> (the rig's joint or ``<joint>_end``, why) for what ``pose`` (J + E, 3: joints, then end
    sites; default the rest pose) shows; {} for a rig that is no upright, mirror-symmetric biped. ``side_of``:
    "left"/"right" from a joint's name, or None. Up is the way of the two along the rig's height that a biped's
    structure is found in; neither or both: {}."""
    if motion.num_joints < 10:
        return {}
    pose = motion.rest_positions(end_sites=True) if pose is None else pose
    rest, ends = pose[:motion.num_joints], pose[motion.num_joints:]  # (J, 3), (E, 3)
    found = [_biped(motion, rest, ends, frame, side_of) for sign in (1.0, -1.0)
             if (frame := _frame(rest, sign, mirror))]
    found = [f for f in found if f]
    return found[0] if len(found) == 1 else {}


def _biped(motion: RigMotion, rest: np.ndarray, ends_at: np.ndarray, frame: _Frame,
           side_of: Callable[[str], str | None]) -> dict[str, tuple[str, str]]:
    """``humanoid_joints`` in one frame (up's sign given): {} where its checks fail. ``ends_at``: (E, 3) the
    end sites' places."""
    names, parents = motion.names, motion.parents
    side, h, height = frame.side, frame.h, frame.height
    axis_names = ["X", "Y", "Z"]
    up_name = "+-"[int(frame.sign < 0)] + axis_names[frame.up]
    off_plane = [j for j in range(len(names)) if abs(side[j]) > ON_PLANE * height]

    def solid(chain: list[int]) -> list[int]:
        """``chain`` without the joints at their parent's place (CMU's LHipJoint at the hips, Neck at the
        chest): the joint above such a one is the one that turns what hangs from both."""
        return [j for j in chain if np.linalg.norm(rest[j] - rest[parents[j]]) > SAME_PLACE * height]

    # the feet: the lowest joint off the mirror plane, and the lowest on its other side
    if not off_plane:
        return {}
    foot1 = min(off_plane, key=lambda j: h[j])
    other = [j for j in off_plane if side[j] * side[foot1] < 0]
    if not other:
        return {}
    foot2 = min(other, key=lambda j: h[j])
    if h[foot2] - h[foot1] > 0.1 * height:
        return {}
    a1, a2 = _ancestors(parents, foot1), set(_ancestors(parents, foot2))
    pelvis = next((j for j in a1 if j in a2), None)  # None: two separate trees
    if pelvis is None or h[pelvis] - h[foot1] < 0.3 * height:
        return {}
    out: dict[str, tuple[str, str]] = {"pelvis": (names[pelvis], "where the two legs and the spine branch")}

    legs = {}  # +1/-1 (the side of the mirror plane) -> (hip, knee, ankle, foot or None, the foot's place)
    for foot in (foot1, foot2):
        chain = solid(_path(parents, foot, pelvis))
        k = _limb(chain, rest, height) if chain else None
        if k is None:
            return {}
        hip, knee, ankle = chain[k:k + 3]
        if not h[hip] > h[knee] > h[ankle]:
            return {}
        after = chain[k + 3] if k + 3 < len(chain) else None
        ends = [i for i, (p, _) in enumerate(motion.end_sites) if p == ankle]
        toe = names[after] if after is not None else (motion.end_site_names()[ends[0]] if len(ends) == 1 else None)
        place = rest[after] if after is not None else (ends_at[ends[0]] if toe else None)
        legs[int(np.sign(side[hip]))] = (hip, knee, ankle, toe, place)  # a walk's feet may cross, its hips do not
    if len(legs) < 2:
        return {}

    # the spine up to the head's top, and the arms: the farthest joints to either side, off the legs
    leg_tops = {_path(parents, foot, pelvis)[0] for foot in (foot1, foot2)}
    body = [j for j in range(len(names)) if (up_to := _path(parents, j, pelvis)) and up_to[0] not in leg_tops]
    centre_line = [j for j in body if abs(side[j]) <= ON_PLANE * height]
    if not centre_line:
        return {}
    top = max(centre_line, key=lambda j: h[j])
    spine = solid(_path(parents, top, pelvis))
    arms = {}
    for sign in (1, -1):
        out_most = max(body, key=lambda j: sign * side[j])  # on the arm, which ends at its joint farthest away
        branch = next((j for j in _ancestors(parents, out_most)[1:] if j in spine), None)
        if branch is None or sign * side[out_most] < ARM_OUT * height or not h[branch] > h[pelvis]:
            return {}
        arm_top = _path(parents, out_most, branch)[0]
        hand = max((j for j in body if arm_top in _ancestors(parents, j)),
                   key=lambda j: np.linalg.norm(rest[j] - rest[branch]))
        chain = solid(_path(parents, hand, branch))
        k = _limb(chain, rest, height) if chain else None
        if k is None:
            return {}
        arms[sign] = (branch, chain, k)
    if len({arm[0] for arm in arms.values()}) != 1:
        return {}
    chest = spine.index(arms[1][0])
    out["spine3"] = (names[spine[chest]], "the spine's joint the two arms branch from")
    below = spine[:chest]
    if below:
        out["spine1"] = (names[below[0]], "the first joint of the spine above the pelvis")
    if len(below) >= 2:
        out["spine2"] = (names[below[len(below) // 2]], "the spine's middle joint between the pelvis and spine3")
    above = spine[chest + 1:]
    if len(above) >= 2:
        out["neck"] = (names[above[0]], "the next joint up the spine from where the arms branch")
        headed = [j for j in above[1:] if re.search("head", names[j], re.I)]
        out["head"] = (names[headed[0]], "the joint above the neck named head") if headed else \
            (names[above[1]], "the next joint up from the neck")

    # which side is left: the names', else up x forward with forward the way the feet point
    toes = [(leg[4] - rest[leg[2]])[frame.fwd] for leg in legs.values() if leg[4] is not None]
    facing = None  # +1/-1 (the side of the mirror plane the body's left is on, from the rest pose), and how
    if len(toes) == 2 and abs(float(np.mean(toes))) >= CLEAR * height:
        forward, upward = np.zeros(3), np.zeros(3)
        forward[frame.fwd], upward[frame.up] = np.sign(np.mean(toes)), frame.sign
        facing = (int(np.sign(np.cross(upward, forward)[frame.lateral])),
                  f"facing {'+-'[int(forward[frame.fwd] < 0)]}{axis_names[frame.fwd]}, where the toes point, "
                  f"{up_name} up")
    said = {sign: {side_of(names[j]) for j in leg[:3]} - {None} for sign, leg in legs.items()}
    if said[1] in ({"left"}, {"right"}) and said[-1] in ({"left"}, {"right"}) and said[1] != said[-1]:
        left = 1 if said[1] == {"left"} else -1
        how = "its joints' names say so" + ("" if facing is None else "; the rest pose agrees" if facing[0] == left
                                            else "; the rest pose says the other side")
    elif facing is not None:
        left, how = facing[0], facing[1]
    else:
        return out  # the feet point nowhere and the names say no side: left and right stay TODO

    def limb(s: str, sign: int, what: str) -> str:
        return f"the {s} {what} ({'+-'[int(sign < 0)]}{axis_names[frame.lateral]} side: {how})"

    for sign, (hip, knee, ankle, toe, _) in legs.items():
        s = "left" if sign == left else "right"
        leg = limb(s, sign, "leg")
        out[f"{s}_hip"] = (names[hip], f"{leg}: where its thigh starts (its two longest bones: thigh and shin)")
        out[f"{s}_knee"] = (names[knee], f"{leg}: between its thigh and shin")
        out[f"{s}_ankle"] = (names[ankle], f"{leg}: where its shin ends")
        if toe is not None:
            out[f"{s}_foot"] = (toe, f"{leg}: the next joint after the ankle")
    for sign, (_, chain, k) in arms.items():
        s = "left" if sign == left else "right"
        arm = limb(s, sign, "arm")
        if k >= 1:
            out[f"{s}_collar"] = (names[chain[k - 1]], f"{arm}: the joint between spine3 and the shoulder")
        out[f"{s}_shoulder"] = (names[chain[k]], f"{arm}: where its upper arm starts (its two longest bones)")
        out[f"{s}_elbow"] = (names[chain[k + 1]], f"{arm}: between its upper arm and forearm")
        out[f"{s}_wrist"] = (names[chain[k + 2]], f"{arm}: where its forearm ends")
    return out


def _axis_name(v: np.ndarray) -> str:
    """The signed world axis nearest a direction: ``+Y``."""
    a = int(np.abs(v).argmax())
    return "+-"[int(v[a] < 0)] + "XYZ"[a]


def quadruped_joints(motion: RigMotion, side_of: Callable[[str], str | None], pose: np.ndarray | None = None,
                     mirror: float = MIRROR) -> dict[str, tuple[str, str]]:
    """SMAL-35 joint -> (the rig's joint or ``<joint>_end``, why) for what ``pose`` (J + E, 3: joints, then end
    sites; default the rest pose) shows; {} for a rig that is no mirror-symmetric quadruped standing on its four
    legs. The legs are the two pairs of longest limbs (two chains to a tip with bones of the same lengths, on
    either side of the mirror plane) that branch from one joint each; the hind pair's (the pelvis) is the other's
    ancestor, as a spine runs from the pelvis to the head; up is the way the four legs hang from, forward from the
    pelvis to the front legs."""
    names = list(motion.names) + motion.end_site_names()
    parents = list(motion.parents) + [p for p, _ in motion.end_sites]
    pose = motion.rest_positions(end_sites=True) if pose is None else pose
    lateral = _lateral(pose, mirror) if motion.num_joints >= 8 else None
    if lateral is None:
        return {}
    size = float((pose.max(0) - pose.min(0)).max())
    side = pose[:, lateral] - (pose[:, lateral].max() + pose[:, lateral].min()) / 2  # (P,)
    children = [[c for c, p in enumerate(parents) if p == j] for j in range(len(names))]
    tips = [j for j in range(len(names)) if not children[j]]

    def solid(chain: list[int]) -> list[int]:
        return [j for j in chain if np.linalg.norm(pose[j] - pose[parents[j]]) > SAME_PLACE * size]

    # the limbs: pairs of tips whose chains from the joint where they meet (their girdle) have bones of the same
    # lengths, whatever the pose, their joints on either side of the mirror plane; per girdle the pair reaching
    # farthest
    rest = motion.rest_positions(end_sites=True)
    bones = np.linalg.norm(rest - rest[[max(p, 0) for p in parents]], axis=1)  # (P,) each joint's bone
    limbs: dict[tuple[int, int], tuple[list[int], float]] = {}  # (girdle, +1/-1) -> (chain, its length)
    for i, t in enumerate(tips):
        for u in tips[i + 1:]:
            up_u = set(_ancestors(parents, u))
            girdle = next((a for a in _ancestors(parents, t) if a in up_u), None)
            if girdle is None or girdle in (t, u):
                continue
            ct, cu = _path(parents, t, girdle), _path(parents, u, girdle)
            if len(ct) != len(cu) or np.abs(bones[ct] - bones[cu]).max() > PAIRED * max(bones[ct].max(), 1e-9):
                continue
            if not side[ct].mean() * side[cu].mean() < 0:
                continue  # both on one side: no mirror images
            chains = {1: ct, -1: cu} if side[ct].mean() > 0 else {1: cu, -1: ct}
            length = float(bones[ct].sum())
            if (girdle, 1) not in limbs or length > limbs[(girdle, 1)][1]:
                for s, c in chains.items():
                    limbs[(girdle, s)] = (c, length)
    in_limbs = {j for chain, _ in limbs.values() for j in chain}
    pairs = sorted({g for g, _ in limbs}, key=lambda g: -min(limbs[(g, 1)][1], limbs[(g, -1)][1]))
    if len(pairs) < 2:
        return {}
    a, b = pairs[:2]
    hind, front = (a, b) if a in _ancestors(parents, b) else (b, a) if b in _ancestors(parents, a) else (None, None)
    if hind is None:
        return {}  # the two girdles on separate branches: no spine runs from one to the other
    legs = {(g, s): limbs[(g, s)][0] for g in (hind, front) for s in (1, -1)}
    lengths = [limbs[key][1] for key in legs]
    if min(lengths) < 0.5 * max(lengths):
        return {}  # a pair of arms or ears much shorter than the legs: no four legs

    # up: the way the four legs hang from; they must hang down, end near one ground, the spine run along it
    drop = np.mean([(pose[c[-1]] - pose[g]) / np.linalg.norm(pose[c[-1]] - pose[g]) for (g, _), c in legs.items()], 0)
    up = -drop
    up[lateral] = 0.0
    if np.linalg.norm(up) < 0.5:
        return {}
    up /= np.linalg.norm(up)
    if any((pose[g] - pose[c[-1]]) @ up < LEGS_DOWN * np.linalg.norm(pose[c[-1]] - pose[g])
           for (g, _), c in legs.items()):
        return {}  # a leg that does not hang down: a pose that does not stand on four legs
    h = pose @ up  # (P,)
    ground = min(h[c[-1]] for c in legs.values())
    leg = float(np.mean(lengths))
    if any(h[c[-1]] - ground > GROUND * leg for c in legs.values()):
        return {}  # a limb that does not reach the ground: arms, or a pose on two legs
    along = pose[front] - pose[hind]
    forward = along - (along @ up) * up
    forward[lateral] = 0.0
    if np.linalg.norm(forward) < 0.1 * size or abs(along @ up) > np.linalg.norm(forward):
        return {}  # the girdles one above the other: an upright body
    forward /= np.linalg.norm(forward)
    facing = f"facing {_axis_name(forward)} (from the hind legs to the front), {_axis_name(up)} up (the legs hang down)"

    out: dict[str, tuple[str, str]] = {"pelvis": (names[hind], "where the hind legs branch (the spine runs from it "
                                                               "to where the front legs branch)")}
    legs_at: dict[tuple[int, int], tuple[int, int, int, int | None]] = {}  # (girdle, side) -> top, mid, low, tip
    drops = []  # per leg: how far its tip is below its top, of the leg's length along its bones
    for key, chain in legs.items():
        chain = solid(chain)
        seg = np.linalg.norm(np.diff(pose[chain], axis=0), axis=1)  # (len - 1,)
        k = next((i for i, x in enumerate(seg) if x >= LIMB_BONE * seg.max()), None) if len(seg) else None
        if k is None or k + 2 >= len(chain):
            return {}
        legs_at[key] = (chain[k], chain[k + 1], chain[k + 2], chain[-1] if k + 3 < len(chain) else None)
        below = chain[k:]
        drops.append((h[below[0]] - h[below[-1]]) / np.linalg.norm(np.diff(pose[below], axis=0), axis=1).sum())
    if np.mean(drops) < STAND:
        return {}  # legs folded under the body or stretched along the ground: sitting, lying

    # the centre line from the pelvis through the front girdle to the head's tip (the farthest forward)
    heads = [j for j in tips if j not in in_limbs and front in _ancestors(parents, j)[1:]]
    if not heads:
        return {}
    tip = max(heads, key=lambda j: pose[j] @ forward)
    line = solid(_path(parents, tip, hind))
    withers = np.mean([pose[legs_at[(front, s)][0]] for s in (1, -1)], 0)
    spine3 = min(line[:-1], key=lambda j: np.linalg.norm(pose[j] - withers), default=None)
    if spine3 is None:
        return {}
    i3 = line.index(spine3)
    out["spine3"] = (names[spine3], "the spine's joint nearest the front legs' tops (the withers)")
    if between := line[:i3]:
        out["spine1"] = (names[between[len(between) // 2]], "the spine's middle joint between the pelvis and spine3")
    after = line[i3 + 1:]
    if len(after) >= 2:
        branching = [j for j in after[:-1] if len(children[j]) >= 2]
        named = [j for j in after[:-1] if re.search("head", names[j], re.I)]
        head = named[0] if named else branching[-1] if branching else after[-2]
        why = "named head" if named else "where the head's branches part" if branching else "the joint before its tip"
        out["Head"] = (names[head], f"on the line from spine3 to the head's tip, {why}")
        out["Mouth"] = (names[tip], "the head's tip: the farthest forward point of the centre line")
        if after.index(head) >= 1:
            out["Neck"] = (names[after[0]], "the next joint from spine3 towards the head")
        ears = [g for g in after[:-1] if (g, 1) in limbs]
    else:
        ears = []

    # the tail: the centre line leaving the pelvis backwards, clear of the ground
    tails = [j for j in tips if j not in in_limbs
             and (up_to := _path(parents, j, hind)) and front not in up_to]
    tail = min(tails, key=lambda j: pose[j] @ forward, default=None)
    if tail is not None and pose[tail] @ forward < pose[hind] @ forward - 0.05 * size:
        chain = solid(_path(parents, tail, hind))
        if chain and min(h[chain]) - ground > TAIL_CLEAR * leg:
            out["Tail1"] = (names[chain[0]], "the first joint of the chain leaving the pelvis backwards")
            out["Tail7"] = (names[chain[-1]], "the tail's tip")
            if len(chain) >= 3:
                out["Tail4"] = (names[chain[len(chain) // 2]], "the tail's middle joint")

    # which side is left: the names', else up x forward
    geometric = int(np.sign(np.cross(up, forward)[lateral]))
    said = {s: {side_of(names[j]) for key, joints in legs_at.items() if key[1] == s for j in joints[:3]} - {None}
            for s in (1, -1)}
    if said[1] in ({"left"}, {"right"}) and said[-1] in ({"left"}, {"right"}) and said[1] != said[-1]:
        left = 1 if said[1] == {"left"} else -1
        how = "its joints' names say so" + ("; the pose agrees" if geometric == left
                                            else "; the pose says the other side")
    else:
        left, how = geometric, facing
    lat = "XYZ"[lateral]
    for (g, s), (top, mid, low, paw) in legs_at.items():
        L, end = "L" if s == left else "R", "Back" if g == hind else ""
        where = (f"the {'left' if s == left else 'right'} {'hind' if g == hind else 'front'} leg "
                 f"({'+-'[int(s < 0)]}{lat} side: {how})")
        out[f"{L}Leg{end}1"] = (names[top], f"{where}: where its first long bone starts")
        out[f"{L}Leg{end}2"] = (names[mid], f"{where}: where its first long bone ends")
        out[f"{L}Leg{end}3"] = (names[low], f"{where}: where its second bone from there ends")
        if paw is not None:
            out[f"{L}Foot{end}"] = (names[paw], f"{where}: its tip")
    for g in ears[:1]:
        for s in (1, -1):
            ear = solid(limbs[(g, s)][0])
            if ear:
                which = "left" if s == left else "right"
                out[f"{which[0].upper()}Ear"] = (names[ear[0]], f"the {which} one of a pair of limbs off the head "
                                                                f"({how})")
    return out


def _mirror_turned(pose: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """``pose`` (P, 3) about its centroid, turned so that the plane it is most mirror-symmetric across has the
    nearest world axis as its normal; its mirror error (the mean distance of each point's mirror image to the
    nearest point, of the pose's size); and the turn (3, 3). A frame of a clip faces any way; the finders read
    axes."""
    size = float((pose.max(0) - pose.min(0)).max())
    if size <= 0:
        return pose, float("inf"), np.eye(3)
    x = pose - pose.mean(0)  # (P, 3)

    def error(normals: np.ndarray) -> np.ndarray:  # (D, 3) -> (D,)
        image = x[None] - 2 * (x @ normals.T).T[..., None] * normals[:, None]  # (D, P, 3)
        d2 = (image ** 2).sum(-1)[..., None] + (x ** 2).sum(-1)[None, None] - 2 * image @ x.T  # (D, P, P)
        return np.sqrt(np.maximum(d2.min(-1), 0)).mean(-1) / size

    i = np.arange(HEMISPHERE) + 0.5
    z = 1 - i / HEMISPHERE
    phi = np.pi * (3 - np.sqrt(5)) * i
    normals = np.stack([np.sqrt(1 - z ** 2) * np.cos(phi), np.sqrt(1 - z ** 2) * np.sin(phi), z], -1)
    n = normals[error(normals).argmin()]
    for _ in range(2):  # each point and its mirror partner differ along the normal
        image = x - 2 * (x @ n)[:, None] * n
        partner = ((image[:, None] - x[None]) ** 2).sum(-1).argmin(1)
        d = x - x[partner]  # (P, 3)
        if np.abs(d).max() <= 0:
            break
        refined = np.linalg.svd(d)[2][0]
        n = refined * np.sign(refined @ n)
    a = int(np.abs(n).argmax())
    e = np.zeros(3)
    e[a] = np.sign(n[a])
    v, c = np.cross(n, e), float(n @ e)  # the least turn from n onto e (Rodrigues)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    turn = np.eye(3) + k + k @ k / (1 + c)
    return x @ turn.T, float(error(n[None])[0]), turn


@dataclass(frozen=True)
class Structure:
    """What a rig's hierarchy and standing pose show: the model skeleton it is built as (``smpl22``: an upright
    biped; ``smal35``: a quadruped; None: neither), that skeleton's joints found (joint -> (the rig's joint,
    why)), and the pose they were read in."""

    skeleton: str | None
    joints: dict[str, tuple[str, str]]
    pose: str


def rig_structure(motion: RigMotion, side_of: Callable[[str], str | None]) -> Structure:
    """The skeleton and joints ``motion``'s rig is built as (``quadruped_joints``, ``humanoid_joints``), read in
    its rest pose (every rotation zero) where that stands; else in its own frames: ``SAMPLED`` frames spread over
    the clip, each turned to face along the axes, those mirror-symmetric to within ``FRAME_MIRROR``; the skeleton
    most of them show wins (a quadruped on a tie), read in the most symmetric of those that show most of its
    joints. A quadruped comes first in each pose: a rig standing on four limbs is never taken for a biped, and a
    biped's arms do not reach the ground."""
    rest = motion.rest_positions(end_sites=True)
    for skeleton, finder in (("smal35", quadruped_joints), ("smpl22", humanoid_joints)):
        if found := finder(motion, side_of, rest):
            return Structure(skeleton, found, "its rest pose (every rotation zero)")
    if len(motion) == 0:
        return Structure(None, {}, "its rest pose (every rotation zero; no frames)")
    picked = np.unique(np.linspace(0, len(motion) - 1, min(len(motion), SAMPLED)).round().astype(int))
    sample = replace(motion, rotations=motion.rotations[picked], translations=motion.translations[picked])
    poses = sample.positions_with_end_sites()  # (n, J + E, 3)
    if [c for c, p in enumerate(motion.parents) if p == 0] == [1] and not any(p == 0 for p, _ in motion.end_sites):
        poses[:, 0] = poses[:, 1]  # a root with one child (Bandai's on the floor) is left behind where a clip goes
    turned = [(*_mirror_turned(p), int(t)) for p, t in zip(poses, picked)]
    tried = sorted(((err, t, p, turn) for p, err, turn, t in turned if err <= FRAME_MIRROR), key=lambda x: x[:2])
    found: dict[str, list] = {"smal35": [], "smpl22": []}  # skeleton -> [(frame, joints, the file's axis up)]
    index = {n: i for i, n in enumerate(list(motion.names) + motion.end_site_names())}
    for _, t, p, turn in tried:
        for skeleton, finder in (("smal35", quadruped_joints), ("smpl22", humanoid_joints)):
            if joints := finder(motion, side_of, p, FRAME_MIRROR):
                low, high = UPRIGHT[skeleton]
                low = p[[index[joints[j][0]] for j in low]].mean(0)
                up = turn.T @ (p[index[joints[high][0]]] - low)  # in the file's axes
                found[skeleton].append((t, joints, _axis_name(up)))
                break
    skeleton = max(found, key=lambda s: len(found[s]))
    where = f"{len(tried)} mirror-symmetric frames of {len(picked)} spread over its {len(motion)}"
    if not found[skeleton]:
        return Structure(None, {}, f"its rest pose (every rotation zero) and each of its {where}")
    # the way up most of them stand (a dog sitting or a person lying is the same skeleton turned), then the most
    # joints shown, then the most symmetric
    ups = [f[2] for f in found[skeleton]]
    t, joints, up = max(found[skeleton], key=lambda f: (ups.count(f[2]), len(f[1])))
    return Structure(skeleton, joints, f"its frame {t} ({up} up), turned so that its mirror plane is normal to an "
                                       "axis (its rest pose, every rotation zero, stands on no legs; "
                                       f"{len(found[skeleton])} of its {where} show the same skeleton, "
                                       f"{ups.count(up)} of them {up} up)")
