"""Bone naming: the one place where rig and file bone names are normalised and
matched to the tracked points (head, hands) and to the body's sides.

Used by the BVH reader (which joints are the tracked points), the Blender import
of rigs and FBX files (which bones), and the retarget mapping (conventions).
"""
from __future__ import annotations

import re

# Normalised names (see bone_key) that identify the points, in order of preference.
HEAD_ALIASES = ("head",)
HAND_ALIASES = {
    "lhand": ("lefthand", "lhand", "handl", "handleft", "leftwrist", "lwrist", "wristl"),
    "rhand": ("righthand", "rhand", "handr", "handright", "rightwrist", "rwrist", "wristr"),
}
TRACKED_ALIASES = {"head": HEAD_ALIASES, **HAND_ALIASES}
MIXAMO_CORE = ("hips", "spine", "head", "leftarm", "rightarm", "leftforearm", "rightforearm",
               "lefthand", "righthand")
# Left and right bones whose heads give the body's left-right direction: hips, else shoulders.
SIDE_ALIASES = (
    (("leftupleg", "lefthip", "lthigh", "thighl", "leftthigh", "upperlegl", "lupleg", "lhip", "hipl"),
     ("rightupleg", "righthip", "rthigh", "thighr", "rightthigh", "upperlegr", "rupleg", "rhip", "hipr")),
    (("leftarm", "leftupperarm", "upperarml", "lupperarm", "larm", "leftshoulder", "lshoulder"),
     ("rightarm", "rightupperarm", "upperarmr", "rupperarm", "rarm", "rightshoulder", "rshoulder")),
)


def strip_namespace(name) -> str:
    """The bone name without a namespace prefix (``mixamorig:``, ``rig|``)."""
    return re.split(r"[:|]", str(name))[-1]


def bone_key(name) -> str:
    """Matching key: no namespace, no spaces/underscores/dashes/dots, lower case
    (``mixamorig:Left_Hand`` -> ``lefthand``)."""
    return re.sub(r"[\s_\-.]", "", strip_namespace(name)).lower()


def normalise_name(name) -> str:
    """Lower-case bone name without a namespace and without Mixamo's
    ``mixamorig``/``mixamorig1_`` prefix; separators kept (retarget conventions)."""
    n = strip_namespace(name)
    n = re.sub(r"^mixamorig\d*_?", "", n, flags=re.IGNORECASE)
    return n.lower()


def index_by_key(names) -> dict:
    """``{bone_key: index of the first name with that key}``."""
    out = {}
    for i, n in enumerate(names):
        out.setdefault(bone_key(n), i)
    return out


def first_alias(idx: dict, aliases):
    """The value of the first of ``aliases`` present in ``idx``, else None."""
    return next((idx[a] for a in aliases if a in idx), None)


def rig_tracked_bones(bone_names):
    """``(point bones, rotation bones, naming)`` for head, lhand, rhand of a
    rig's bone names; the point is the head of the point bone. None when the rig
    is not recognised."""
    names = list(bone_names)
    idx = {k: names[i] for k, i in index_by_key(names).items()}
    if "head" not in idx:
        return None
    if all(k in idx for k in ("leftfingerbase", "rightfingerbase", "lefthand", "righthand")):
        return ((idx["head"], idx["leftfingerbase"], idx["rightfingerbase"]),
                (idx["head"], idx["lefthand"], idx["righthand"]), "cmu")
    hands = []
    for dev in ("lhand", "rhand"):
        found = first_alias(idx, HAND_ALIASES[dev])
        if found is None:
            return None
        hands.append(found)
    bones = (idx["head"], hands[0], hands[1])
    naming = "mixamo" if any(n.lower().startswith("mixamorig") for n in names) else "generic"
    return bones, bones, naming


def rig_side_bones(bone_names):
    """A left and a right bone (hips, else shoulders) whose heads give the
    body's left-right direction, or None."""
    names = list(bone_names)
    idx = {k: names[i] for k, i in index_by_key(names).items()}
    for left, right in SIDE_ALIASES:
        lb, rb = first_alias(idx, left), first_alias(idx, right)
        if lb is not None and rb is not None:
            return lb, rb
    return None
