"""Full-body rigs as SPEC §3 ``joints`` devices, whatever the rig (bpy-free).

Used by the BVH reader (:func:`.bvh.tracked_points`) and by the Blender import
of BVH and FBX files (``operators/take_rig.py``, also behind the command line's
FBX reader), so that every full-body reader gives the same meaning:

Which bones (:func:`tracked_rig`)
  - Points: the head of the skull bone and of each hand bone
    (:data:`.naming.TRACKED_ALIASES`: Mixamo/Rokoko ``LeftHand``, Unreal
    ``hand_l``, Rigify ``DEF-hand.L``, VRoid ``J_Bip_L_Hand``, ASF ``lhand``,
    the CMU-converted BVH's ``LeftFingerBase``, ...): the wrist, SPEC §2's end
    of ``lwrist``.
  - Hand orientation: the bone that ends at the wrist, i.e. the hand bone's
    parent: the forearm's end (ASF ``lwrist``, the CMU BVH's ``LeftHand``,
    Rigify's ``DEF-forearm.L.001``) or, where the rig has none, the forearm
    itself with its twist (Mixamo ``LeftForeArm``, Unreal ``lowerarm_l``,
    VRoid ``J_Bip_L_LowerArm``). Never the hand bone, which bends at the
    wrist. Unreal's ``lowerarm_twist_01_l`` is a skinning helper beside the
    hand, not its parent, and is not read: the animation's forearm twist is on
    ``lowerarm_l``.
  - Head orientation: the skull bone itself.

Rest pose (:func:`rest_corrections`)
  A rig's rotation relative to its own rest pose, ``R_rig = W · W_restᵀ``
  (independent of bone rolls), is the SPEC rotation only when the rest pose is
  the SPEC's (§2: standing, facing +Z, left +X, arms straight out along ±X).
  Otherwise ``R_spec = R_rig · Q`` with ``Q`` taking the SPEC rest frame of
  the bone to the rig's: for a forearm, the frames ``[d, f⊥, d × f⊥]`` of its
  rest direction ``d`` (its head to the wrist) and the body's forward ``f``,
  ``Q = F_rig · F_specᵀ`` (SPEC: ``d = ±X``, ``f = +Z``); for the skull, and
  for a forearm within 5° of straight out (a T-pose, as the SPEC's own rest
  pose of any dancer), the body's rest frame (left, up, forward). The body's rest frame is measured
  from the hips (else the shoulders, else the wrists) and the head, and
  snapped onto the axes when within 10° of them, as rest poses are.

  The rest pose must be one the SPEC's can be related to: upright (the head
  within 30° of straight above the hips), each forearm pointing outwards
  (within 70° of horizontal: T-pose, A-pose), not forwards or backwards
  (within 25°), straight at the elbow (within 25°), both sides alike (within
  15°); and each hand bone needs a parent. Otherwise the orientations are not
  read (``problem`` says why) and the take carries ``orientations=none``
  (:data:`.take.ORIENTATIONS_KEY`): its points are used, the device follow is
  off for it.

The CMU-converted BVH's rest pose is the ASF rest pose (the SPEC's): its
corrections are exactly the identity (a T-pose facing +Z), so it is read as
it always was; the same rig exported without its rest pose is not.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .naming import SIDE_ALIASES, first_alias, index_by_key, rig_tracked_bones

UPRIGHT_TOL_DEG = 30.0
SNAP_TOL_DEG = 10.0
ARM_DOWN_MAX_DEG = 70.0
ARM_FORWARD_MAX_DEG = 25.0
ELBOW_BEND_MAX_DEG = 25.0
ARM_ASYMMETRY_MAX_DEG = 15.0
T_POSE_TOL_DEG = 5.0


class TrackedRig(NamedTuple):
    """Bone indices of a rig (head, left hand, right hand order)."""

    naming: str
    points: tuple  # bones whose heads are the points
    rotations: tuple  # skull, left and right forearm's end (None: no such bone)
    sides: tuple | None  # a left and a right bone (hips, else shoulders) for the body's direction


def tracked_rig(names, parents) -> TrackedRig | None:
    """The bones of a rig (``names``, ``parents``: parent index per bone, −1 for
    none) that give the SPEC §3 ``joints`` points and orientations; None when it
    has no head bone or no hand bone."""
    names = list(names)
    found = rig_tracked_bones(names)
    if found is None:
        return None
    point_names, naming = found
    where = {n: i for i, n in reversed(list(enumerate(names)))}
    points = tuple(where[n] for n in point_names)
    rots = [points[0]]
    for p in points[1:]:
        par = int(parents[p])
        rots.append(par if par >= 0 else None)
    idx = index_by_key(names)
    sides = None
    for left, right in SIDE_ALIASES:
        lb, rb = first_alias(idx, left), first_alias(idx, right)
        if lb is not None and rb is not None:
            sides = (lb, rb)
            break
    return TrackedRig(naming, points, tuple(rots), sides)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else None


def _deg(cos):
    return float(np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0))))


def _snap(v, tol_deg=SNAP_TOL_DEG):
    """``v`` (unit) onto the nearest signed axis when within ``tol_deg``."""
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) >= np.cos(np.deg2rad(tol_deg)):
        out = np.zeros(3)
        out[k] = np.sign(v[k])
        return out
    return v


def bone_frame(d, f):
    """Orthonormal frame ``(3, 3)``, columns ``d``, ``f`` made perpendicular to ``d``, ``d × f``."""
    d = _unit(d)
    f = np.asarray(f, dtype=np.float64)
    f = _unit(f - (f @ d) * d)
    return np.stack([d, f, np.cross(d, f)], axis=1)


def rest_body_frame(left, right, head):
    """``(frame (3, 3), problem)``: the body's rest frame in motion space (columns
    left, up, forward) from a left and a right point and the head point, or
    ``(None, why)`` when the rest pose is not upright."""
    left, right, head = (np.asarray(v, dtype=np.float64) for v in (left, right, head))
    up = _unit(head - (left + right) / 2)
    if up is None or up[1] < np.cos(np.deg2rad(UPRIGHT_TOL_DEG)):
        return None, "its rest pose is not upright (the head is not above the hips along the file's up axis)"
    lr = left - right
    lr[1] = 0.0
    lr = _unit(lr)
    if lr is None:
        return None, "its rest pose has no left-right direction (the left and right bones coincide)"
    x = _snap(lr)
    y = np.array([0.0, 1.0, 0.0])
    return np.stack([x, y, np.cross(x, y)], axis=1), ""


def rest_corrections(rest_heads, parents, rig: TrackedRig, wrists=None):
    """``(Q (3, 3, 3), problem)``: the rest corrections of the skull and the two
    forearm's ends (``R_spec = R_rig · Q[k]``), from the rest pose's bone heads
    ``rest_heads (N, 3)`` (motion space, Y up, any unit); ``wrists`` (2, 3):
    the rest hand points when they are not the heads of ``rig.points``
    (default: they are). ``(None, why)`` when the rest pose cannot be related
    to the SPEC's (module docstring)."""
    heads = np.asarray(rest_heads, dtype=np.float64)
    for k, side in ((1, "left"), (2, "right")):
        if rig.rotations[k] is None:
            return None, f"its {side} hand bone has no parent (forearm) bone"
    w = heads[list(rig.points[1:])] if wrists is None else np.asarray(wrists, dtype=np.float64)
    lr = heads[list(rig.sides)] if rig.sides is not None else w
    body, problem = rest_body_frame(lr[0], lr[1], heads[rig.points[0]])
    if body is None:
        return None, problem
    fwd = body[:, 2]
    Q = [body]
    down = []
    for k, (side, s) in enumerate((("left", 1.0), ("right", -1.0))):
        rot = rig.rotations[k + 1]
        d = _unit(w[k] - heads[rot])
        if d is None:
            return None, f"its {side} forearm bone has no length in the rest pose"
        db = body.T @ d  # (left, up, forward) components
        out = s * db[0]
        below = float(np.rad2deg(np.arctan2(-db[1], out)))  # degrees below horizontal, in the frontal plane
        ahead = float(np.rad2deg(np.arcsin(np.clip(abs(db[2]), 0.0, 1.0))))
        if out <= 0 or abs(below) > ARM_DOWN_MAX_DEG or ahead > ARM_FORWARD_MAX_DEG:
            return None, f"its rest pose's {side} forearm does not point sideways (not a T- or A-pose)"
        par = int(parents[rot])
        u = _unit(heads[rot] - heads[par]) if par >= 0 else None
        if u is None or _deg(u @ d) > ELBOW_BEND_MAX_DEG:
            return None, f"its rest pose's {side} arm is not straight (not a T- or A-pose)"
        down.append(below)
        if _deg(db[0] * s) <= T_POSE_TOL_DEG:  # a T-pose: straight out, as the SPEC's
            Q.append(body)
        else:
            Q.append(bone_frame(d, fwd) @ bone_frame(np.array([s, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])).T)
    if abs(down[0] - down[1]) > ARM_ASYMMETRY_MAX_DEG:
        return None, (f"its rest pose's arms are not alike (left {down[0]:.0f}°, right {down[1]:.0f}° "
                      "below horizontal)")
    return np.stack(Q), ""


def spec_rotations(rig_rot, Q):
    """SPEC global rotations ``(T, 3, 3, 3)`` of the skull and forearm's ends from
    their rotations relative to the rig's rest pose ``rig_rot (T, 3, 3, 3)``
    (motion space) and the rest corrections ``Q (3, 3, 3)``."""
    return np.asarray(rig_rot, dtype=np.float64) @ np.asarray(Q)[None]


def rig_problem_line(path, problem) -> str:
    """The one-line warning for a rig whose orientations cannot be read."""
    return (f"{path}: the rig's head and hand orientations cannot be read ({problem}); its points are used, "
            "without the device follow")



def asf_rest_corrections(bone_vectors):
    """:func:`rest_corrections` of an ASF skeleton's rest pose (SPEC §2 bones,
    ``bone_vectors (31, 3)``): the identity for the CMU skeletons (their rest
    pose is a T-pose facing +Z); an ASF resting otherwise is corrected the same
    way as any rig."""
    from ..skeleton import JOINT_NAMES, PARENTS, rest_starts

    return rest_corrections(rest_starts(np.asarray(bone_vectors, dtype=np.float64)), PARENTS,
                            tracked_rig(JOINT_NAMES, PARENTS))
