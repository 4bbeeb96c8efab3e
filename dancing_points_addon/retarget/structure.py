"""Mapping a humanoid rig by its structure, for bone names no preset knows
(numpy only).

From the rig's reference pose (:class:`.rig.TargetRig`, world space, Z up):

- the pelvis is the bone from which two chains go down (the legs: the two
  child subtrees that end lowest) and one goes up (the spine: the subtree that
  ends highest);
- a leg: the chain towards the lowest point; the thigh is its first long bone
  pointing down, then the shin, the foot and the toe;
- the spine: the chain towards the highest point; the chest is the spine bone
  the arms branch off, the neck the bones above it, the head the last long one;
- an arm: the chain off the upper spine that reaches farthest sideways; its
  two longest consecutive bones are the upper arm and forearm, the bone before
  them the clavicle, the one after them the hand;
- left / right by side in the rest pose: the left is ``up × forward``, the
  forward direction being where the feet point (else -Y, Blender's front view).

:func:`structural_mapping` returns ``(mapping, roles)``: the bone mapping and
``{role: bone}`` (pelvis, lthigh, ..., head) for telling the user what was mapped.
"""
from __future__ import annotations

import numpy as np

from .mapping import RetargetError

_SPINE = ("lowerback", "upperback", "thorax")
_NECK = ("lowerneck", "upperneck")


def _children(parents):
    kids = [[] for _ in parents]
    for i, p in enumerate(parents):
        if p >= 0:
            kids[int(p)].append(i)
    return kids


def _subtree(kids, b):
    out, stack = [], [b]
    while stack:
        i = stack.pop()
        out.append(i)
        stack.extend(kids[i])
    return out


def _chain(kids, start, score):
    """From ``start``, follow the child whose subtree has the best ``score`` (max)."""
    out = [start]
    while kids[out[-1]]:
        out.append(max(kids[out[-1]], key=lambda c: max(score(i) for i in _subtree(kids, c))))
    return out


def structural_mapping(rig):
    """``(mapping {bone: source chain}, roles {role: bone name})`` of a humanoid
    rig found from its bone hierarchy and reference pose; raises
    :class:`RetargetError` when no pelvis with two legs and a spine is found."""
    names = rig.names
    kids = _children(rig.parents)
    heads = rig.heads()
    tails = rig.tails()
    pts = np.concatenate([heads, tails])
    lo, hi = float(pts[:, 2].min()), float(pts[:, 2].max())
    H = max(hi - lo, 1e-6)
    lens = np.linalg.norm(tails - heads, axis=-1)
    # End points of every bone's subtree.
    zmin = np.array([min(min(heads[i, 2], tails[i, 2]) for i in _subtree(kids, b)) for b in range(len(names))])
    zmax = np.array([max(max(heads[i, 2], tails[i, 2]) for i in _subtree(kids, b)) for b in range(len(names))])
    # Pelvis: two child subtrees reaching the floor (< 25% of the height) and one
    # the top (> 80%); the deepest such bone in the hierarchy wins.
    pelvis, best = None, None
    for b in range(len(names)):
        c = kids[b]
        down = [x for x in c if zmin[x] < lo + 0.25 * H]
        up = [x for x in c if zmax[x] > lo + 0.8 * H and x not in down]
        if len(down) >= 2 and up and heads[b, 2] > lo + 0.3 * H:
            key = (int(rig.depth[b]), -b)
            if best is None or key > best:
                pelvis, best = b, key
    if pelvis is None:
        raise RetargetError("no bone naming convention recognised, and no pelvis found by structure (a bone "
                            "with two legs and a spine below it): fill in the bone map")
    legs = sorted((x for x in kids[pelvis] if zmin[x] < lo + 0.25 * H), key=lambda x: zmin[x])[:2]
    spine_start = max((x for x in kids[pelvis] if x not in legs), key=lambda x: zmax[x])
    roles = {"pelvis": pelvis}
    # Forward: where the feet point (toes ahead of the ankles), else -Y.
    leg_chains = [_chain(kids, x, lambda i: -min(heads[i, 2], tails[i, 2])) for x in legs]
    fwd = np.zeros(3)
    leg_parts = []
    for ch in leg_chains:
        down = [b for b in ch if lens[b] > 0.08 * H and (tails[b, 2] - heads[b, 2]) < -0.6 * lens[b]]
        if len(down) < 2:
            raise RetargetError("no bone naming convention recognised, and the legs under '{:s}' have no thigh "
                                "and shin pointing down: fill in the bone map".format(names[pelvis]))
        thigh, shin = down[0], down[1]
        rest = ch[ch.index(shin) + 1:]
        foot = rest[0] if rest else None
        toe = rest[1] if len(rest) > 1 else None
        leg_parts.append((thigh, shin, foot, toe))
        if foot is not None:
            tip = tails[toe] if toe is not None else tails[foot]
            d = tip - heads[foot]
            fwd[:2] += d[:2]
    if np.linalg.norm(fwd[:2]) < 1e-3 * H:
        fwd = np.array([0.0, -1.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    left = np.cross([0.0, 0.0, 1.0], fwd)
    mapping = {names[pelvis]: "root"}
    leg_parts.sort(key=lambda p: -float(np.dot(heads[p[0]], left)))  # left leg first
    for side, (thigh, shin, foot, toe) in zip("lr", leg_parts):
        for role, b, chain in (("thigh", thigh, "femur"), ("shin", shin, "tibia"), ("foot", foot, "foot"),
                               ("toe", toe, "toes")):
            if b is not None:
                mapping[names[b]] = side + chain
                roles[side + role] = b
    # Spine: towards the top; the chest is where the arms branch off.
    up_chain = _chain(kids, spine_start, lambda i: max(heads[i, 2], tails[i, 2]))
    axis_pt = heads[pelvis]

    def side_reach(i):
        v = np.concatenate([heads[i], tails[i]]).reshape(2, 3) - axis_pt
        return float(np.max(np.abs(v @ left)))

    chest, arms = None, []
    for i, b in enumerate(up_chain):
        branches = [c for c in kids[b] if c not in up_chain and max(side_reach(x) for x in _subtree(kids, c))
                    > 0.2 * H]
        if len(branches) >= 2:
            chest, arms = i, branches
            break
    if chest is None:
        raise RetargetError("no bone naming convention recognised, and no arms found off the spine of '{:s}': "
                            "fill in the bone map".format(names[pelvis]))
    spine = up_chain[:chest + 1]
    above = [b for b in up_chain[chest + 1:] if lens[b] > 0.02 * H]
    if not above:
        raise RetargetError("no bone naming convention recognised, and no head found above the arms: "
                            "fill in the bone map")
    head = above[-1] if len(above) == 1 or lens[above[-1]] > 0.06 * H else above[-2]
    neck = above[:above.index(head)]
    for bones, parts, role in ((spine, _SPINE, "spine"), (neck, _NECK, "neck")):
        if len(bones) == len(parts):
            for b, p in zip(bones, parts):
                mapping[names[b]] = p
        else:
            for b in bones:
                mapping[names[b]] = "+".join(parts)
        for i, b in enumerate(bones):
            roles["{:s}{:d}".format(role, i + 1)] = b
    mapping[names[head]] = "head"
    roles["head"] = head
    # Arms: the two branches reaching farthest to either side.
    arm_parts = []
    for c in arms:
        ch = _chain(kids, c, side_reach)
        if len(ch) < 2:
            continue
        pair = max(range(len(ch) - 1), key=lambda i: lens[ch[i]] + lens[ch[i + 1]])
        up, fore = ch[pair], ch[pair + 1]
        clav = ch[pair - 1] if pair >= 1 else None
        hand = ch[pair + 2] if pair + 2 < len(ch) else None
        arm_parts.append((float(np.dot(heads[fore] - axis_pt, left)), clav, up, fore, hand))
    arm_parts.sort(key=lambda p: -p[0])
    if len(arm_parts) < 2 or arm_parts[0][0] <= 0 or arm_parts[-1][0] >= 0:
        raise RetargetError("no bone naming convention recognised, and no left and right arm found: "
                            "fill in the bone map")
    for side, (_, clav, up, fore, hand) in zip("lr", (arm_parts[0], arm_parts[-1])):
        for role, b, chain in (("clavicle", clav, side + "clavicle"), ("upperarm", up, side + "humerus"),
                               ("forearm", fore, side + "radius+" + side + "wrist"), ("hand", hand, side + "hand")):
            if b is not None:
                mapping[names[b]] = chain
                roles[side + role] = b
    return mapping, {k: names[v] for k, v in roles.items()}


def describe(mapping):
    """One line listing a mapping (``bone→chain, ...``) for the user."""
    return ", ".join("{:s}→{:s}".format(k, v) for k, v in mapping.items())
