"""The mannequin's proportions (step 1 of the package): the primitives of its
distance field placed on the bones of a skeleton's rest pose and sized from its
height, and the weight capsules of its skinned bones (:func:`weight_capsules`).
"""
from __future__ import annotations

import numpy as np

from ..errors import UserError
from ..skeleton import JOINT_INDEX, JOINT_NAMES, rest_starts
from .sdf import Prim, frame_rows, unit

_J = JOINT_INDEX
N_BONES = len(JOINT_NAMES)
# The reference skeleton (CMU subject 60): ankle-to-head-bone-end height in rest pose, metres.
_REF_EXTENT = 1.51


class BodyError(UserError, ValueError):
    """Bone vectors a body cannot be built on (wrong shape, not finite, a limb of length 0)."""


def check_bones(bone_vectors):
    try:
        bv = np.asarray(bone_vectors, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise BodyError(f"bone vectors are not numbers: {exc}") from None
    if bv.shape != (N_BONES, 3):
        raise BodyError(f"bone vectors must have shape ({N_BONES}, 3), got {bv.shape}")
    if not np.all(np.isfinite(bv)):
        raise BodyError("bone vectors are not all finite")
    lengths = np.linalg.norm(bv, axis=1)
    need = ("lfemur", "ltibia", "rfemur", "rtibia", "lhumerus", "lradius", "rhumerus", "rradius",
            "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head", "lclavicle", "rclavicle",
            "lwrist", "rwrist", "lfoot", "rfoot")
    short = [n for n in need if lengths[_J[n]] < 1e-3]
    if short:
        raise BodyError(f"cannot build a body on a skeleton with bones of length 0: {', '.join(short)}")
    return bv


def stature_scale(start, end):
    """The skeleton's size relative to the reference (CMU subject 60)."""
    ankle = 0.5 * (end[_J["ltibia"], 1] + end[_J["rtibia"], 1])
    extent = end[_J["head"], 1] - ankle
    if not 0.3 < extent < 3.5:
        raise BodyError(f"the skeleton's rest pose is {extent:.2f} m from ankle to head; "
                        f"expected an upright T-pose (Y up), 0.3-3.5 m")
    return extent / _REF_EXTENT


def proportions(start, end, s):
    """The mannequin's primitives (in smooth-union order) and weight capsules
    ``{bone: (a, b, r1, r2)}``. Lengths in metres at the reference size, × ``s``."""
    j = _J
    up = np.array([0.0, 1.0, 0.0])
    front = np.array([0.0, 0.0, 1.0])
    P = []
    caps = {}

    def cone(blend, a, b, r1, r2, **kw):
        P.append(Prim("cone", blend, a=np.asarray(a, float), b=np.asarray(b, float), r1=r1 * s, r2=r2 * s, **kw))

    def ellipsoid(blend, centre, size, axes=np.eye(3)):
        P.append(Prim("ellipsoid", blend, centre=np.asarray(centre, float), size=np.asarray(size) * s, axes=axes))

    root = start[j["root"]]
    hips = 0.5 * (end[j["lhipjoint"]] + end[j["rhipjoint"]])
    hip_half = 0.5 * abs(end[j["lhipjoint"], 0] - end[j["rhipjoint"], 0])
    neck0 = end[j["thorax"]]
    lb, ub = end[j["lowerback"]], end[j["upperback"]]
    # torso: pelvis, belly, rib cage: ellipsoids blended wide
    ellipsoid(0.0, [root[0], hips[1] + 0.03 * s, 0.5 * (root[2] + hips[2]) - 0.012 * s],
              [hip_half / s + 0.06, 0.13, 0.1])
    ellipsoid(0.09 * s, lb + np.array([0.0, -0.02, 0.01]) * s, [0.13, 0.15, 0.095])
    ellipsoid(0.08 * s, ub + np.array([0.0, 0.035, 0.018]) * s, [0.145, 0.145, 0.102])
    # neck and head
    cone(0.045 * s, neck0 - 0.02 * s * up, end[j["upperneck"]], 0.058, 0.05)
    hb = end[j["head"]] - start[j["head"]]
    hax = frame_rows(np.cross(unit(hb), front), unit(hb))  # rows: side (+X), up, front
    ellipsoid(0.03 * s, start[j["head"]] + 0.55 * hb + hax[2] * 0.012 * s, [0.078, 0.108, 0.094], axes=hax)
    caps["lowerneck"] = (start[j["lowerneck"]], end[j["lowerneck"]], 0.058, 0.055)
    caps["upperneck"] = (start[j["upperneck"]], end[j["upperneck"]], 0.055, 0.05)
    caps["head"] = (start[j["head"]] + 0.4 * hb, end[j["head"]], 0.08, 0.08)
    caps["root"] = (root + 0.02 * s * up, np.array([root[0], hips[1] - 0.04 * s, 0.5 * (root[2] + hips[2])]),
                    0.12, 0.12)
    caps["lowerback"] = (start[j["lowerback"]], lb, 0.115, 0.12)
    caps["upperback"] = (start[j["upperback"]], ub, 0.12, 0.125)
    caps["thorax"] = (start[j["thorax"]], end[j["thorax"]], 0.125, 0.1)
    for side in "lr":
        n = lambda name: side + name  # noqa: E731
        clav0, sh = start[j[n("clavicle")]], end[j[n("clavicle")]]
        el, wr = end[j[n("humerus")]], end[j[n("radius")]]
        knuck, tips = end[j[n("wrist")]], end[j[n("fingers")]]
        thumb = end[j[n("thumb")]]
        hip, knee, ankle = end[j[n("hipjoint")]], end[j[n("femur")]], end[j[n("tibia")]]
        ball, toe = end[j[n("foot")]], end[j[n("toes")]]
        # shoulder (trapezius to deltoid), arm, forearm
        sh_in = clav0 + 0.3 * (sh - clav0)
        cone(0.045 * s, sh_in, sh, 0.058, 0.05)
        cone(0.0, sh, el, 0.05, 0.038)
        cone(0.0, el, wr, 0.038, 0.027)
        # hand: a mitten (a flat round cone) from the wrist to past the finger tips, and a thumb
        hdir = unit(tips - wr)
        tip = tips + hdir * 0.02 * s
        hax = frame_rows(hdir, thumb - wr)  # rows: along, towards the thumb, thickness
        cone(0.035 * s, wr + hdir * 0.025 * s, tip - hdir * 0.016 * s, 0.0195, 0.016, squash=(1.0, 2.1, 1.0),
             axes=hax)
        t0 = wr + 0.3 * (knuck - wr) + hax[1] * 0.02 * s
        cone(0.015 * s, t0, t0 + unit(hdir + 0.6 * hax[1]) * 0.06 * s, 0.0145, 0.012)
        # leg: thigh, shin (one chain), foot (heel, ball, toes, instep)
        cone(0.05 * s, hip, knee, 0.085, 0.053)
        cone(0.0, knee, ankle, 0.053, 0.036)
        fwd = toe - ankle
        fwd[1] = 0.0
        fwd = unit(fwd, front)
        side_ax = unit(np.cross(up, fwd))
        fax = np.stack([side_ax, up, fwd])
        sole = min(ball[1], toe[1]) - 0.026 * s
        heel = np.array([ankle[0], sole + 0.03 * s, ankle[2]]) - fwd * 0.05 * s
        ballp = np.array([ball[0], sole + 0.024 * s, ball[2]])
        toep = np.array([toe[0], sole + 0.017 * s, toe[2]]) + fwd * 0.015 * s
        cone(0.035 * s, heel, ballp, 0.03, 0.024, squash=(1.3, 1.0, 1.0), axes=fax)
        cone(0.02 * s, ballp, toep, 0.024, 0.017, squash=(1.85, 1.0, 1.0), axes=fax)
        cone(0.025 * s, ankle - 0.005 * s * up, ballp + 0.008 * s * up, 0.033, 0.018, squash=(1.4, 1.0, 1.0),
             axes=fax)
        # weight capsules
        caps[n("clavicle")] = (clav0 + 0.35 * (sh - clav0), sh, 0.05, 0.05)
        caps[n("humerus")] = (sh, el, 0.05, 0.038)
        caps[n("radius")] = (el, wr, 0.038, 0.027)
        caps[n("wrist")] = (wr, knuck, 0.03, 0.028)
        caps[n("hand")] = (knuck, tip, 0.024, 0.02)
        caps[n("femur")] = (hip, knee, 0.085, 0.053)
        caps[n("tibia")] = (knee, ankle, 0.053, 0.036)
        caps[n("foot")] = (heel + fwd * 0.02 * s, ballp, 0.032, 0.026)
        caps[n("toes")] = (ballp, toep, 0.026, 0.018)
    caps = {b: (np.asarray(a, float), np.asarray(c, float), r1 * s, r2 * s) for b, (a, c, r1, r2) in caps.items()}
    return P, caps


def weight_capsules(bone_vectors):
    """The weight capsules of the mannequin of ``bone_vectors``: ``(bones (B,),
    a (B, 3), b (B, 3), r1 (B,), r2 (B,))`` — a round cone per skinned bone
    (bone indices ``bones``), in rest pose."""
    bv = check_bones(bone_vectors)
    start = rest_starts(bv)
    end = start + bv
    _, caps = proportions(start, end, stature_scale(start, end))
    names = [n for n in JOINT_NAMES if n in caps]
    return (np.array([_J[n] for n in names]), np.array([caps[n][0] for n in names]),
            np.array([caps[n][1] for n in names]), np.array([caps[n][2] for n in names]),
            np.array([caps[n][3] for n in names]))
