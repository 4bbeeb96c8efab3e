"""Bone naming: the one place where rig and file bone names are normalised and
matched to the tracked points (head, hands) and to the body's sides.

Used by the BVH reader (which joints are the tracked points), the Blender import
of rigs and FBX files (which bones), and the retarget mapping (conventions).
"""
from __future__ import annotations

import re

# Normalised names (see bone_key) that identify the points, in order of preference.
# The head point and orientation: the skull bone (Mixamo/Rokoko/Unreal/VRM/CMU ``Head``,
# VRoid ``J_Bip_C_Head``, Rigify's ``DEF-spine.006`` / ``ORG-spine.006``).
HEAD_ALIASES = ("head", "jbipchead", "defspine006", "orgspine006")
# The hand point is the head of the hand bone (the wrist). The first ones are the CMU-converted
# BVH's LeftFingerBase (its ``LeftHand`` is ASF ``lwrist``, the forearm's end) and ASF ``lhand``
# (its parent ``lwrist`` ends at the wrist); then Mixamo/Rokoko/generic ``LeftHand``, Unreal
# ``hand_l``, Rigify ``DEF-hand.L`` / ``ORG-hand.L``, VRoid ``J_Bip_L_Hand``, and joint-named rigs
# (SMPL ``L_Wrist``: the bone that starts at the wrist).
HAND_ALIASES = {
    "lhand": ("leftfingerbase", "lhand", "lefthand", "handl", "handleft", "defhandl", "orghandl",
              "jbiplhand", "leftwrist", "lwrist", "wristl"),
    "rhand": ("rightfingerbase", "rhand", "righthand", "handr", "handright", "defhandr", "orghandr",
              "jbiprhand", "rightwrist", "rwrist", "wristr"),
}
TRACKED_ALIASES = {"head": HEAD_ALIASES, **HAND_ALIASES}
MIXAMO_CORE = ("hips", "spine", "head", "leftarm", "rightarm", "leftforearm", "rightforearm",
               "lefthand", "righthand")
# Left and right bones whose heads give the body's left-right direction: hips, else shoulders.
SIDE_ALIASES = (
    (("leftupleg", "lefthip", "lthigh", "thighl", "leftthigh", "upperlegl", "lupleg", "lhip", "hipl",
      "lfemur", "defthighl", "orgthighl", "jbiplupperleg", "leftupperleg"),
     ("rightupleg", "righthip", "rthigh", "thighr", "rightthigh", "upperlegr", "rupleg", "rhip", "hipr",
      "rfemur", "defthighr", "orgthighr", "jbiprupperleg", "rightupperleg")),
    (("leftarm", "leftupperarm", "upperarml", "lupperarm", "larm", "lhumerus", "defupperarml",
      "orgupperarml", "jbiplupperarm", "leftshoulder", "lshoulder"),
     ("rightarm", "rightupperarm", "upperarmr", "rupperarm", "rarm", "rhumerus", "defupperarmr",
      "orgupperarmr", "jbiprupperarm", "rightshoulder", "rshoulder")),
)
# Namings told apart (``rig_naming``), by keys only their rigs have.
NAMING_KEYS = (
    ("asf", ("lhumerus", "lradius", "lwrist", "lhand")),
    ("unreal", ("upperarml", "lowerarml", "handl")),
    ("rigify", ("defforearml", "defhandl")),
    ("rigify", ("orgforearml", "orghandl")),
    ("vrm", ("jbipllowerarm", "jbiplhand")),
    ("vrm", ("leftlowerarm", "lefthand")),
    ("mixamo", MIXAMO_CORE),
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


def rig_naming(bone_names) -> str:
    """The naming a rig's bones follow: ``'cmu'`` (the CMU-converted BVH), ``'asf'``,
    ``'unreal'``, ``'rigify'``, ``'vrm'``, ``'mixamo'`` (also Rokoko's, which is the
    same) or ``'generic'``; said in the take's ``source_naming``."""
    names = list(bone_names)
    idx = index_by_key(names)
    if "leftfingerbase" in idx and "rightfingerbase" in idx and "lefthand" in idx:
        return "cmu"
    for naming, keys in NAMING_KEYS:
        if all(k in idx for k in keys):
            return naming
    return "generic"


def rig_tracked_bones(bone_names):
    """``(point bones, naming)``: the bones whose heads are the head, left hand
    and right hand points (:data:`TRACKED_ALIASES`), or None when the rig has
    no head bone or no hand bone. Which bones give the orientations is
    :func:`.rig_rest.tracked_rig`'s (it needs the hierarchy)."""
    names = list(bone_names)
    idx = {k: names[i] for k, i in index_by_key(names).items()}
    found = [first_alias(idx, TRACKED_ALIASES[k]) for k in ("head", "lhand", "rhand")]
    if any(f is None for f in found):
        return None
    return tuple(found), rig_naming(names)
