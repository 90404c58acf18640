"""A human rig's SMPL-22 joints found from its hierarchy and rest pose, whatever its joints are called.

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
tokens), else from up and forward (left = up x forward). Quadrupeds (smal35) are not attempted: a dog's
longest axis is its length, not its height, and its four legs hang from two girdles; a rig that is no
upright biped fails the checks below and gets nothing, as does a rig whose rest pose (every rotation zero)
is no standing pose (the Bandai-Namco BVHs': their offsets lie along each joint's own axes).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from omg.io.rig import RigMotion

MIRROR = 0.03  # of the rig's size: mean distance of a joint's mirror image to the nearest joint on a symmetric rig
ON_PLANE = 0.03  # of the rig's height: a joint this close to the mirror plane is on the body's centre line
CLEAR = 0.02  # of the rig's height: toes no further ahead of their ankles than this point nowhere
LONG_BONE = 0.1  # of the rig's height: the shortest upper arm, forearm, thigh or shin a human rig has
PROXIMAL = 0.8  # the shortest a thigh is of its shin, an upper arm of its forearm (adults: 1.0 and 1.27)
ARM_OUT = 0.05  # of the rig's height: the least a hand reaches out from the centre line (arms hanging down: 0.13)
SAME_PLACE = 1e-3  # of the rig's height: a joint this close to its parent is a second joint at the same place


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


def _frame(rest: np.ndarray, sign: float) -> _Frame | None:
    extent = rest.max(0) - rest.min(0)  # (3,)
    size = float(extent.max())
    centre = (rest.max(0) + rest.min(0)) / 2

    def mirror_error(axis: int) -> float:
        image = rest.copy()
        image[:, axis] = 2 * centre[axis] - image[:, axis]
        return float(np.linalg.norm(image[:, None] - rest[None], axis=-1).min(1).mean()) / size

    axes = [a for a in range(3) if extent[a] > 0.1 * size]
    if size <= 0 or len(axes) < 2:
        return None
    lateral = min(axes, key=mirror_error)
    if mirror_error(lateral) > MIRROR:
        return None
    up, fwd = sorted((a for a in range(3) if a != lateral), key=lambda a: -extent[a])
    if extent[up] < 1.5 * extent[fwd]:
        return None  # a lying or four-legged rig: no axis is clearly its height
    return _Frame(lateral, up, fwd, sign, rest[:, lateral] - centre[lateral], sign * rest[:, up], float(extent[up]))


def humanoid_joints(motion: RigMotion, side_of: Callable[[str], str | None]) -> dict[str, tuple[str, str]]:
    """SMPL-22 joint -> (the rig's joint or ``<joint>_end``, why) for what the rest pose shows; {} for a rig
    that is no upright, mirror-symmetric biped. ``side_of``: "left"/"right" from a joint's name, or None.
    Up is the way of the two along the rig's height that a biped's structure is found in; neither or both: {}."""
    if motion.num_joints < 10:
        return {}
    rest = motion.rest_positions()  # (J, 3)
    found = [_biped(motion, rest, frame, side_of) for sign in (1.0, -1.0) if (frame := _frame(rest, sign))]
    found = [f for f in found if f]
    return found[0] if len(found) == 1 else {}


def _biped(motion: RigMotion, rest: np.ndarray, frame: _Frame, side_of: Callable[[str], str | None]
           ) -> dict[str, tuple[str, str]]:
    """``humanoid_joints`` in one frame (up's sign given): {} where its checks fail."""
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
        place = rest[after] if after is not None else (rest[ankle] + motion.end_sites[ends[0]][1] if toe else None)
        legs[int(np.sign(side[foot]))] = (hip, knee, ankle, toe, place)

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
