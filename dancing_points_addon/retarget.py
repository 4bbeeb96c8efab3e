"""Retarget a dancer of the duet (SPEC §2 skeleton) onto any humanoid rig
(numpy only, no ``bpy``; the Blender side is ``operators/retarget.py``).

Everything happens in Blender *world* space (Z up, metres), per frame and
vectorised over the frames.

Bone mapping
    A mapping is a plain dict ``{target bone name: source chain}``; a source
    chain is one SPEC bone (``"lfemur"``) or consecutive SPEC bones joined by
    ``+`` (``"lradius+lwrist"``: the elbow -> wrist segment), and ``"root"``
    for the pelvis (it carries the root motion). Several target bones mapped to
    the same chain share it in proportion to their rest lengths (Rigify's
    ``DEF-upper_arm.L`` + ``DEF-upper_arm.L.001``, a 5-bone UE5 spine on the
    3-bone CMU spine). Target bones that are not mapped keep their reference
    pose relative to their parent. :func:`auto_mapping` guesses a mapping from
    the bone names for the conventions in ``retarget_presets/*.json`` (CMU/BVH,
    Mixamo with or without the ``mixamorig:`` prefix, Rigify ``DEF-``,
    Unreal); :func:`save_preset` / :func:`load_preset` write and read a
    mapping as JSON.

Rest-pose alignment (once per pair of rigs, :class:`Retargeter`)
    For each mapped target bone, the segment it covers (its head to the head of
    the bone that continues the chain) is matched with the source segment of
    its chain: both get a frame from the segment direction and a secondary axis
    (the body's forward direction, or up for bones that point forward such as
    feet), and ``A = F_source · F_targetᵀ`` turns the target's reference pose
    into the source's rest pose. T-pose vs A-pose, bone rolls, bone axes and the
    rig's facing all end up in ``A``. A posed frame is then
    ``Q(t) = G(t) · A · Q_ref`` where ``G(t)`` is the source bone's world
    rotation relative to its rest (SPEC §2 global rotation), corrected by the
    smallest turn that puts the segment exactly on the source segment's
    direction (a target bone spanning several source bones).

Proportions
    Target positions come from forward kinematics of the target's own bone
    lengths. The pelvis (the midpoint of the hip joints) follows the source's,
    scaled by ``k`` = target leg length / source leg length (thigh + shin)
    horizontally about the duet's centre (:func:`duet_origin`) and vertically
    above the floor (each rig's ankle height above its floor kept). The head
    point and the wrists are then pulled to where the source's are relative to
    the pelvis, scaled by the ratio of the head-point heights: the spine and
    neck lean rigidly about the spine's base, the arms by two-bone IK (as far as
    they reach).

Contacts and hands
    Foot points planted on the source (SPEC §6 contact: < 6 cm above their
    floor level and slower than 0.30 m/s; and within 2 cm of where the contact
    began, :func:`planted`) are locked on the target with two-bone leg IK
    (:func:`..ik.two_bone_ik`) where they were on the contact's first frame
    (never below the target's own floor level); the lock fades out over a
    few frames after the contact (as a safety net, a lock is also released when
    the unlocked point drifts more than 30 cm away from it). Where a locked leg
    is too short for its lock, the pelvis is lowered (by at most 6 % of the leg
    length).
    :func:`close_hands` keeps the hands of leader and follower that hold each
    other together (source wrists < 15 cm apart): both target wrists move to
    meet at the source's gap (scaled), by two-bone arm IK.
"""
from __future__ import annotations

import glob
import json
import os
import re

import numpy as np

from . import blender_math as bm
from .blender_math import C  # motion space (Y up) -> Blender (Z up)
from .ik import rotation_between, smoothstep, two_bone_ik
from .representation import CONTACT_HEIGHT, CONTACT_SPEED, floor_levels, foot_speeds
from .rotations import matrix_to_euler, matrix_to_quat
from .skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS
from .take import atomic_output

PRESET_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "retarget_presets")
ROOT_CHAIN = "root"
SIDES = ("l", "r")
# Source rest body frame in the source armature (Blender axes): left +X, up +Z, forward -Y.
_SRC_LEFT = np.array([1.0, 0.0, 0.0])
_UP = np.array([0.0, 0.0, 1.0])
_SRC_FWD = np.array([0.0, -1.0, 0.0])
# Landmarks compared between source and target (name: source SPEC joint whose end it is).
LANDMARKS = {
    "hips": None,  # midpoint of the hip joints (ends of lhipjoint, rhipjoint)
    "head": "upperneck", "lwrist": "lwrist", "rwrist": "rwrist",
    "lankle": "ltibia", "rankle": "rtibia", "lball": "lfoot", "rball": "rfoot",
}
FOOT_POINTS = ("lankle", "lball", "rankle", "rball")


class RetargetError(ValueError):
    """A mapping or rig that cannot be retargeted (one user-facing line)."""


# --------------------------------------------------------------------------- mapping

def parse_chain(chain: str):
    """SPEC bone indices of a chain string (``"a+b"``); raises on unknown or
    non-consecutive bones."""
    parts = [p.strip() for p in str(chain).split("+") if p.strip()]
    if not parts:
        raise RetargetError("empty source chain")
    idx = []
    for p in parts:
        if p not in JOINT_INDEX:
            raise RetargetError("unknown source bone {!r} (SPEC §2 names: {:s})".format(p, ", ".join(JOINT_NAMES)))
        idx.append(JOINT_INDEX[p])
    for a, b in zip(idx, idx[1:]):
        if PARENTS[b] != a:
            raise RetargetError("source chain {!r}: {:s} is not the child of {:s}".format(
                chain, JOINT_NAMES[b], JOINT_NAMES[a]))
    if idx[0] == 0 and len(idx) > 1:
        raise RetargetError("'root' cannot start a chain")
    return idx


def normalise_name(name: str) -> str:
    """Lower-case bone name without a namespace (``mixamorig:``, ``rig|``) prefix."""
    n = re.split(r"[:|]", str(name))[-1]
    n = re.sub(r"^mixamorig\d*_?", "", n, flags=re.IGNORECASE)
    return n.lower()


def builtin_conventions():
    """``{name: preset dict}`` of the JSON presets shipped in ``retarget_presets/``."""
    out = {}
    for path in sorted(glob.glob(os.path.join(PRESET_DIR, "*.json"))):
        try:
            preset = load_preset(path)
        except (OSError, ValueError):
            continue
        out[preset.get("name") or os.path.splitext(os.path.basename(path))[0]] = preset
    return out


def load_preset(path) -> dict:
    """A preset: ``{"name", "convention", "signature", "bones": {target: chain}}``.
    Chains are validated; an unreadable file raises :class:`RetargetError`."""
    try:
        with open(path, "r", encoding="utf-8") as fh:
            data = json.load(fh)
    except OSError as exc:
        raise RetargetError("cannot read {:s}: {:s}".format(os.fspath(path), exc.strerror or str(exc))) from None
    except json.JSONDecodeError as exc:
        raise RetargetError("{:s}: not JSON ({:s})".format(os.fspath(path), str(exc))) from None
    if not isinstance(data, dict) or not isinstance(data.get("bones"), dict):
        raise RetargetError("{:s}: a preset needs a 'bones' object {{target bone: source chain}}".format(
            os.fspath(path)))
    for tgt, chain in data["bones"].items():
        if chain:
            parse_chain(chain)
    data.setdefault("name", os.path.splitext(os.path.basename(os.fspath(path)))[0])
    data.setdefault("signature", [])
    return data


def save_preset(path, mapping: dict, name: str = "", convention: str = "") -> None:
    """Write ``mapping`` ({target bone: source chain}) as a JSON preset."""
    for chain in mapping.values():
        parse_chain(chain)
    data = {"name": name or os.path.splitext(os.path.basename(os.fspath(path)))[0],
            "convention": convention, "bones": {k: mapping[k] for k in mapping}}
    with atomic_output(path, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")


def detect_convention(names, conventions=None):
    """``(convention name, matched bones)`` that fits ``names`` best: most
    signature bones found, then most bones found; ``(None, 0)`` when nothing matches."""
    conventions = builtin_conventions() if conventions is None else conventions
    norm = {normalise_name(n) for n in names}
    best, best_key = None, (0, 0)
    for cname, preset in conventions.items():
        table = {normalise_name(k) for k in preset["bones"]}
        sig = sum(1 for s in preset.get("signature", []) if normalise_name(s) in norm)
        hits = len(table & norm)
        key = (sig, hits)
        if hits and key > best_key:
            best, best_key = cname, key
    return best, best_key[1]


def _depths(parents):
    d = np.zeros(len(parents), dtype=np.int64)
    for i in topological_order(parents):
        if parents[i] >= 0:
            d[i] = d[parents[i]] + 1
    return d


def topological_order(parents):
    """Bone indices with every parent before its children."""
    parents = [int(p) for p in parents]
    children = [[] for _ in parents]
    roots = []
    for i, p in enumerate(parents):
        (children[p] if p >= 0 else roots).append(i)
    out, stack = [], list(reversed(roots))
    while stack:
        i = stack.pop()
        out.append(i)
        stack.extend(reversed(children[i]))
    if len(out) != len(parents):
        raise RetargetError("the rig's bone hierarchy has a cycle")
    return out


# Spine and neck chains that are split evenly when the rig's bone count differs.
_SPINE = "lowerback+upperback+thorax"
_NECK = "lowerneck+upperneck"


def auto_mapping(names, parents=None, convention=None, conventions=None):
    """``(mapping, convention)``: target bone -> source chain guessed from the names.

    ``convention``: a preset name to use (default: :func:`detect_convention`).
    A spine (neck) whose number of bones differs from the preset's is mapped as
    one chain on the whole source spine (neck)."""
    conventions = builtin_conventions() if conventions is None else conventions
    if convention is None:
        convention, _ = detect_convention(names, conventions)
    if convention is None:
        return {}, None
    if convention not in conventions:
        raise RetargetError("unknown convention {!r} (known: {:s})".format(convention, ", ".join(conventions)))
    table = {normalise_name(k): v for k, v in conventions[convention]["bones"].items()}
    mapping = {}
    for n in names:
        chain = table.get(normalise_name(n))
        if chain:
            mapping[n] = chain
    # Spine / neck counts: 1:1 only when the rig has exactly as many bones.
    for whole, parts in ((_SPINE, ("lowerback", "upperback", "thorax")), (_NECK, ("lowerneck", "upperneck"))):
        members = [n for n, c in mapping.items() if c == whole or c in parts or set(c.split("+")) <= set(parts)]
        singles = [n for n in members if mapping[n] in parts]
        if members and not (len(singles) == len(members) == len(parts)
                            and sorted(mapping[n] for n in singles) == sorted(parts)):
            for n in members:
                mapping[n] = whole
    return mapping, convention


def validate_mapping(mapping: dict, names) -> dict:
    """The usable part of ``mapping``: known target bones, valid chains, at most
    one ``root``. Raises when nothing usable (no root or no leg) remains."""
    names = set(names)
    out = {}
    for tgt, chain in mapping.items():
        if tgt not in names or not chain:
            continue
        parse_chain(chain)
        out[tgt] = chain
    roots = [t for t, c in out.items() if c == ROOT_CHAIN]
    if len(roots) != 1:
        raise RetargetError("the mapping needs exactly one bone mapped to 'root' (the pelvis), found {:d}".format(
            len(roots)))
    for side in SIDES:
        for part in ("femur", "tibia"):
            if not any(side + part in c.split("+") for c in out.values()):
                raise RetargetError("the mapping has no bone for {:s}".format(side + part))
    return out


# --------------------------------------------------------------------------- the source

def spec_pose_from_channels(quats, root_location, rest_rot, rest_heads, bone_vectors):
    """Inverse of ``blender_math.pose_channels``: SPEC ``positions (T, 31, 3)`` and
    global ``rotations (T, 31, 3, 3)`` (motion space) of a Dancing Points armature
    from its keyed pose channels ``quats (T, 31, 4)`` (``matrix_basis``) and the
    root bone's ``location (T, 3)``; ``rest_rot``/``rest_heads`` are the bones'
    ``matrix_local`` rotations and heads (Blender space)."""
    from .rotations import quat_to_matrix

    q = np.asarray(quats, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    basis = quat_to_matrix(q)
    B = np.asarray(rest_rot, dtype=np.float64)
    rel = B[None] @ basis @ np.swapaxes(B, -1, -2)[None]
    T = q.shape[0]
    rb = np.empty_like(rel)
    for n in range(len(JOINT_NAMES)):
        p = PARENTS[n]
        rb[:, n] = rel[:, n] if p < 0 else rb[:, p] @ rel[:, n]
    R = C.T[None, None] @ rb @ C[None, None]
    root_b = np.asarray(rest_heads, dtype=np.float64)[0] + np.asarray(root_location, dtype=np.float64) @ B[0].T
    pos = np.empty((T, len(JOINT_NAMES), 3))
    pos[:, 0] = root_b @ C
    bv = np.asarray(bone_vectors, dtype=np.float64)
    for n in range(1, len(JOINT_NAMES)):
        pos[:, n] = pos[:, PARENTS[n]] + np.einsum("tab,b->ta", R[:, n], bv[n])
    return pos, R


def source_world(positions, rotations, source_matrix=None):
    """SPEC positions / global rotations (motion space) in Blender world space:
    ``(points (T, 31, 3), rotations (T, 31, 3, 3))`` — the rotations are the
    world rotations *relative to the rest pose* (``source_matrix``: the source
    armature object's world matrix)."""
    M = np.eye(4) if source_matrix is None else np.asarray(source_matrix, dtype=np.float64)
    S = M[:3, :3]
    scale = np.cbrt(abs(np.linalg.det(S))) or 1.0
    Rw = S / scale
    pts = np.asarray(positions, dtype=np.float64) @ C.T @ S.T + M[:3, 3]
    rot = Rw @ C @ np.asarray(rotations, dtype=np.float64) @ C.T @ Rw.T
    return pts, rot


def duet_origin(*points):
    """Horizontal centre ``(2,)`` of dancers given as SPEC world points ``(T, 31, 3)``:
    the mean over frames and dancers of their hip joints' midpoint."""
    c = [0.5 * (p[:, JOINT_INDEX["lhipjoint"], :2] + p[:, JOINT_INDEX["rhipjoint"], :2]).mean(0) for p in points]
    return np.mean(c, axis=0)


def source_landmarks(points):
    """``{landmark: (T, 3)}`` of SPEC joint positions (any space)."""
    out = {}
    for name, bone in LANDMARKS.items():
        if bone is None:
            out[name] = 0.5 * (points[:, JOINT_INDEX["lhipjoint"]] + points[:, JOINT_INDEX["rhipjoint"]])
        else:
            out[name] = points[:, JOINT_INDEX[bone]]
    return out


def detect_contacts(points, fps=30.0, up=2, height=CONTACT_HEIGHT, speed=CONTACT_SPEED, floor=None):
    """Contacts ``(T, K)`` of foot points ``(T, K, 3)`` by the SPEC §6 rule
    (:func:`~.representation.contact_labels`: < ``height`` above the point's
    floor level, 5th percentile of its height or ``floor``; slower than
    ``speed`` m/s), with the speed relaxed to the slower of the two steps
    around a frame, so a planted foot's first and last frames count.
    ``up``: the up axis (2 for Blender space)."""
    p = np.asarray(points, dtype=np.float64)
    h = p[..., up]
    lvl = floor_levels(h) if floor is None else np.asarray(floor, dtype=np.float64)
    v = foot_speeds(p, fps)
    if len(p) > 2:
        v[1:-1] = np.minimum(v[1:-1], v[2:])  # either neighbouring step slow
    return (h - lvl < height) & (v < speed)


def planted(contacts, points, tol=0.02):
    """Contacts ``(T, K)`` reduced to where each point is planted: a contact run
    ends (for the rest of it) once the point ``(T, K, 3)`` has moved more than
    ``tol`` (m, horizontally) from where the run began — a foot pivoting on the
    other point or gliding along the floor is low and slow, but not planted."""
    c = np.array(contacts, dtype=bool)
    p = np.asarray(points, dtype=np.float64)
    for k in range(c.shape[1]):
        t = 0
        while t < len(c):
            if not c[t, k]:
                t += 1
                continue
            s = t
            while t < len(c) and c[t, k]:
                t += 1
            moved = np.linalg.norm(p[s:t, k, :2] - p[s, k, :2], axis=-1) > tol
            if moved.any():
                c[s + int(np.argmax(moved)):t, k] = False
    return c


# --------------------------------------------------------------------------- the target

class TargetRig:
    """A target armature as arrays.

    ``names``, ``parents`` (index, -1 for roots), ``rest (B, 4, 4)``
    (``Bone.matrix_local``), ``lengths (B,)``, ``ref_basis (B, 4, 4)`` (the
    reference pose as ``matrix_basis``; default identity: the rest pose),
    ``matrix_world (4, 4)`` (the armature object's).
    """

    def __init__(self, names, parents, rest, lengths=None, ref_basis=None, matrix_world=None):
        self.names = list(names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.parents = np.asarray(parents, dtype=np.int64)
        self.rest = np.asarray(rest, dtype=np.float64)
        B = len(self.names)
        self.lengths = np.ones(B) if lengths is None else np.asarray(lengths, dtype=np.float64)
        self.ref_basis = np.broadcast_to(np.eye(4), (B, 4, 4)).copy() if ref_basis is None \
            else np.asarray(ref_basis, dtype=np.float64)
        self.matrix_world = np.eye(4) if matrix_world is None else np.asarray(matrix_world, dtype=np.float64)
        self.order = topological_order(self.parents)
        self.depth = _depths(self.parents)
        self.ref_pose = pose_from_basis(self.rest, self.parents, self.ref_basis[None], self.order)[0]
        self.ref_world = self.matrix_world[None] @ self.ref_pose  # (B, 4, 4)

    def heads(self):
        return self.ref_world[:, :3, 3]

    def tails(self):
        y = np.zeros((len(self.names), 4))
        y[:, 1] = self.lengths
        y[:, 3] = 1.0
        return np.einsum("bij,bj->bi", self.ref_world, y)[:, :3]

    def ground(self) -> float:
        """World height of the rig's floor: the armature object's origin."""
        return float(self.matrix_world[2, 3])


def pose_from_basis(rest, parents, basis, order=None):
    """Armature-space pose matrices ``(T, B, 4, 4)`` from ``matrix_basis (T, B, 4, 4)``
    (Blender: ``pose = pose_parent · rest_parent⁻¹ · rest · basis``)."""
    rest = np.asarray(rest, dtype=np.float64)
    basis = np.asarray(basis, dtype=np.float64)
    order = topological_order(parents) if order is None else order
    out = np.empty(basis.shape)
    inv_rest = np.linalg.inv(rest)
    for b in order:
        p = parents[b]
        if p < 0:
            out[:, b] = rest[b] @ basis[:, b]
        else:
            out[:, b] = out[:, p] @ (inv_rest[p] @ rest[b]) @ basis[:, b]
    return out


def basis_from_pose(rest, parents, pose):
    """Inverse of :func:`pose_from_basis`."""
    rest = np.asarray(rest, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    inv_rest = np.linalg.inv(rest)
    inv_pose = np.linalg.inv(pose)
    out = np.empty(pose.shape)
    for b in range(pose.shape[1]):
        p = parents[b]
        if p < 0:
            out[:, b] = inv_rest[b] @ pose[:, b]
        else:
            out[:, b] = (inv_rest[b] @ rest[p]) @ inv_pose[:, p] @ pose[:, b]
    return out


def channels(basis, rotation_modes=None):
    """``(location (T, B, 3), rotation (T, B, 4) quaternions or Euler angles in
    the first 3, scale (T, B, 3))`` of ``matrix_basis (T, B, 4, 4)``.
    ``rotation_modes``: per bone 'QUATERNION' (default) or an Euler order."""
    basis = np.asarray(basis, dtype=np.float64)
    lin = basis[..., :3, :3]
    scale = np.linalg.norm(lin, axis=-2)
    rot = lin / np.where(scale > 1e-12, scale, 1.0)[..., None, :]
    rot = _nearest_rotation(rot)
    q = bm.continuous_quats(matrix_to_quat(rot))
    out_rot = q.copy()
    if rotation_modes is not None:
        for b, mode in enumerate(rotation_modes):
            if mode in ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"):
                e = np.unwrap(matrix_to_euler(rot[:, b], mode), axis=0)  # angles in the order's axis order
                for i, axis in enumerate(mode):  # Blender stores (x, y, z) whatever the order
                    out_rot[:, b, "XYZ".index(axis)] = e[:, i]
                out_rot[:, b, 3] = 0.0
    return basis[..., :3, 3].copy(), out_rot, scale


def _nearest_rotation(m):
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= d[..., None]
    return u @ vt


def _unit(v, fallback=None):
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if fallback is None:
        return v / np.where(n > 1e-12, n, 1.0)
    return np.where(n > 1e-12, v / np.where(n > 1e-12, n, 1.0), fallback)


def _frame(d, s):
    """Rotation ``(3, 3)`` with columns (d, s⊥, d × s⊥)."""
    x = _unit(d)
    y = s - np.dot(s, x) * x
    y = _unit(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def _body_frame(left, up):
    """Columns (left, up, forward = left × up)."""
    x = _unit(left - np.dot(left, up) * up)
    return np.stack([x, up, np.cross(x, up)], axis=1)


class _Pose:
    """A retargeted clip: world linear parts of the mapped bones, the root head,
    the source-driven rotations G (for poles), and the world matrices."""

    def __init__(self, lin, root_head, G, W):
        self.lin, self.root_head, self.G, self.W = lin, root_head, G, W


class Retargeter:
    """Source (SPEC skeleton with ``bone_vectors``) -> ``target`` (:class:`TargetRig`)
    with ``mapping`` {target bone: source chain}. Alignment, proportions and the
    segment bookkeeping are computed here, once."""

    def __init__(self, bone_vectors, target: TargetRig, mapping: dict, foot_lock: bool = True,
                 blend_frames: int = 6, match_hands: bool = True, match_head: bool = True,
                 max_drift: float = 0.30, max_step_deg: float = 60.0, max_drop: float = 0.06):
        self.target = target
        self.max_drift = float(max_drift)
        self.max_drop = float(max_drop)
        self.max_step_deg = float(max_step_deg)
        self.mapping = validate_mapping(mapping, target.names)
        self.foot_lock = bool(foot_lock)
        self.match_hands = bool(match_hands)
        self.match_head = bool(match_head)
        self.blend_frames = max(int(blend_frames), 1)
        self.bv = np.asarray(bone_vectors, dtype=np.float64)
        self.src_rest = bm.to_blender(bm.rest_joints(self.bv))  # (31, 3) source armature, Blender axes
        tgt = target
        heads = tgt.heads()
        # Groups of target bones sharing a chain, ordered root-most first.
        groups = {}
        for name, chain in self.mapping.items():
            groups.setdefault(chain, []).append(tgt.index[name])
        for chain in groups:
            groups[chain].sort(key=lambda b: (tgt.depth[b], b))
        self.groups = groups
        self.root_bone = groups[ROOT_CHAIN][0]
        # Which bone covers which source bone (for the IK chains and landmarks).
        self.by_source = {}
        for chain, bones in groups.items():
            for s in (parse_chain(chain) if chain != ROOT_CHAIN else [0]):
                self.by_source.setdefault(JOINT_NAMES[s], bones)
        # Target body frame from its reference pose.
        hip_l, hip_r = self._hip_joint(heads, "l"), self._hip_joint(heads, "r")
        self.tgt_body = _body_frame(hip_l - hip_r, _UP)
        self.src_body = _body_frame(_SRC_LEFT, _UP)
        # Per mapped bone: source polyline, fractions, twist bone, alignment.
        self.seg = {}
        for chain, bones in groups.items():
            if chain == ROOT_CHAIN:
                b = bones[0]
                self.seg[b] = dict(chain=[0], f0=0.0, f1=0.0, twist=0,
                                   A=self.src_body @ self.tgt_body.T)
                for extra in bones[1:]:
                    self.seg[extra] = dict(self.seg[b])
                continue
            src = parse_chain(chain)
            pts_idx = [int(PARENTS[src[0]])] + src  # polyline vertices (joint ends)
            poly = self.src_rest[pts_idx]
            seglen = np.linalg.norm(np.diff(poly, axis=0), axis=-1)
            s_cum = np.concatenate([[0.0], np.cumsum(seglen)])
            s_cum = s_cum / max(s_cum[-1], 1e-12)
            ends = [self._end_point(b, bones, chain) for b in bones]
            lens = np.array([np.linalg.norm(e - heads[b]) for b, e in zip(bones, ends)])
            f = np.concatenate([[0.0], np.cumsum(lens)]) / max(lens.sum(), 1e-12)
            for i, b in enumerate(bones):
                f0, f1 = float(f[i]), float(f[i + 1])
                mid = 0.5 * (f0 + f1)
                k = int(np.clip(np.searchsorted(s_cum, mid, side="right") - 1, 0, len(src) - 1))
                d_src = _interp_poly(poly[None], s_cum, f1)[0] - _interp_poly(poly[None], s_cum, f0)[0]
                d_tgt = ends[i] - heads[b]
                if np.linalg.norm(d_src) < 1e-9 or np.linalg.norm(d_tgt) < 1e-9:
                    A = self.src_body @ self.tgt_body.T
                else:
                    ds, dt = _unit(d_src), _unit(d_tgt)
                    use_up = abs(np.dot(ds, _SRC_FWD)) > 0.7 or abs(np.dot(dt, self.tgt_body[:, 2])) > 0.7
                    A = _frame(ds, _UP if use_up else _SRC_FWD) @ _frame(dt, _UP if use_up else self.tgt_body[:, 2]).T
                self.seg[b] = dict(chain=pts_idx, s=s_cum, f0=f0, f1=f1, twist=src[k], A=A,
                                   d_rest=_unit(d_src))
        # Proportions: leg lengths (thigh + shin), ankle heights.
        lt = [self._leg_length_target(heads, s) for s in SIDES]
        ls = [self._src_leg(s) for s in SIDES]
        self.scale = float(np.mean(lt) / np.mean(ls))
        self.tgt_anchor0 = 0.5 * (hip_l + hip_r)
        ground = tgt.ground()
        self.ground = ground
        self.tgt_foot_height = {}
        for side in SIDES:
            a, b = self._foot_points_ref(heads, side)
            self.tgt_foot_height[side + "ankle"] = float(a[2] - ground) if a is not None else None
            self.tgt_foot_height[side + "ball"] = float(b[2] - ground) if b is not None else None
        self.height = self._rig_height(heads)

    # -- reference-pose helpers ------------------------------------------------
    def _src_leg(self, side):
        """Source thigh + shin length of ``side``."""
        return float(sum(np.linalg.norm(self.bv[JOINT_INDEX[side + n]]) for n in ("femur", "tibia")))

    def _bones_of(self, spec_name):
        return self.by_source.get(spec_name)

    def _hip_joint(self, heads, side):
        bones = self._bones_of(side + "femur")
        return heads[bones[0]]

    def _knee_bone(self, side):
        return self._bones_of(side + "tibia")[0]

    def _leg_length_target(self, heads, side):
        hip = heads[self._bones_of(side + "femur")[0]]
        knee = heads[self._knee_bone(side)]
        foot = self._bones_of(side + "foot")
        if foot is not None:
            ankle = heads[foot[0]]
        else:
            bones = self.groups[self.mapping[self.target.names[self._knee_bone(side)]]]
            ankle = self._end_point(bones[-1], bones, self.mapping[self.target.names[bones[-1]]])
        return float(np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee))

    def _foot_points_ref(self, heads, side):
        foot = self._bones_of(side + "foot")
        toe = self._bones_of(side + "toes")
        a = heads[foot[0]] if foot is not None else None
        if toe is not None:
            b = heads[toe[0]]
        elif foot is not None:
            b = self._end_point(foot[-1], foot, self.mapping[self.target.names[foot[-1]]])
        else:
            b = None
        return a, b

    def _rig_height(self, heads):
        """Height of the head point (the skull base, SPEC §2's tracked head: the
        head bone's start) above the floor, in the reference pose."""
        head = self._bones_of("head")
        if head is not None:
            return float(heads[head[0], 2] - self.ground)
        neck = self._bones_of("upperneck")
        b = neck[-1]
        return float(self._end_point(b, neck, self.mapping[self.target.names[b]])[2] - self.ground)

    def source_height(self, ankle_height):
        """The source's head-point height standing straight: ``ankle_height`` (its
        ankles' floor level) + leg length + rest height of the skull base above the hip joints."""
        r = self.src_rest
        hip = 0.5 * (r[JOINT_INDEX["lhipjoint"]] + r[JOINT_INDEX["rhipjoint"]])
        legs = np.mean([self._src_leg(s) for s in SIDES])
        return float(ankle_height + legs + r[JOINT_INDEX["upperneck"], 2] - hip[2])

    def _end_point(self, b, bones, chain):
        """World reference point where target bone ``b``'s segment ends."""
        tgt = self.target
        heads = tgt.heads()
        i = bones.index(b)
        if i + 1 < len(bones):
            return heads[bones[i + 1]]
        last = parse_chain(chain)[-1] if chain != ROOT_CHAIN else 0
        kids = [c for c in range(len(tgt.names)) if tgt.parents[c] == b]
        # a child (or deeper descendant) continuing the chain: prefer the lowest SPEC index
        best = None
        stack = list(kids)
        while stack:
            c = stack.pop()
            cname = tgt.names[c]
            if cname in self.mapping and self.mapping[cname] != ROOT_CHAIN:
                first = parse_chain(self.mapping[cname])[0]
                if PARENTS[first] == last and (best is None or first < best[0]):
                    best = (first, c)
            else:
                stack.extend(x for x in range(len(tgt.names)) if tgt.parents[x] == c)
        if best is not None:
            return heads[best[1]]
        if kids:
            axis = _unit(tgt.tails()[b] - heads[b])
            proj = [float(np.dot(heads[c] - heads[b], axis)) for c in kids]
            c = kids[int(np.argmax(proj))]
            if proj[int(np.argmax(proj))] > 1e-6:
                return heads[c]
        return tgt.tails()[b]

    # -- solving -----------------------------------------------------------------
    def solve(self, positions, rotations, source_matrix=None, contacts=None, fps=30.0, origin=None):
        """Retarget a clip: SPEC ``positions (T, 31, 3)`` and ``rotations (T, 31, 3, 3)``
        (motion space) of the source armature placed at ``source_matrix``.
        ``contacts (T, 4)`` (bool, SPEC §2 foot points) default to :func:`detect_contacts`.
        ``origin``: the world point (x, y) about which the root motion is scaled
        (default the world origin; for a duet, :func:`duet_origin`, so that
        partners of different sizes keep their distance).
        Returns a pose object (world matrices in ``.W``)."""
        pts, G_src = source_world(positions, rotations, source_matrix)
        T = pts.shape[0]
        tgt = self.target
        W0 = tgt.ref_world
        lin0 = W0[:, :3, :3]
        Bn = len(tgt.names)
        lin = np.zeros((T, Bn, 3, 3))
        G = np.zeros((T, Bn, 3, 3))
        M = np.eye(4) if source_matrix is None else np.asarray(source_matrix, dtype=np.float64)
        Rw = M[:3, :3] / (np.cbrt(abs(np.linalg.det(M[:3, :3]))) or 1.0)
        for b, sg in self.seg.items():
            Gt = G_src[:, sg["twist"]]
            if b not in self.groups[ROOT_CHAIN]:
                a = _interp_poly(pts[:, sg["chain"]], sg["s"], sg["f0"])
                e = _interp_poly(pts[:, sg["chain"]], sg["s"], sg["f1"])
                cur = np.einsum("tij,j->ti", Gt, Rw @ sg["d_rest"])
                Gt = _no_flips(rotation_between(cur, e - a) @ Gt, Rw @ sg["d_rest"], e - a, self.max_step_deg)
            else:
                Gt = _no_flips(Gt, None, None, self.max_step_deg)
            G[:, b] = Gt
            lin[:, b] = Gt @ (Rw @ sg["A"]) @ lin0[b]
        # Pelvis anchor: midpoint of the hip joints, scaled.
        src_anchor = 0.5 * (pts[:, JOINT_INDEX["lhipjoint"]] + pts[:, JOINT_INDEX["rhipjoint"]])
        src_ground = float(M[2, 3])
        ankles = pts[:, [JOINT_INDEX["ltibia"], JOINT_INDEX["rtibia"]], 2] - src_ground
        src_ankle_h = float(np.mean(np.percentile(ankles, 5, axis=0)))
        tgt_ankle_h = np.mean([h for k, h in self.tgt_foot_height.items() if k.endswith("ankle") and h is not None]
                              or [src_ankle_h * self.scale])
        k = self.scale
        anchor = np.empty_like(src_anchor)
        o = np.zeros(2) if origin is None else np.asarray(origin, dtype=np.float64)[:2]
        anchor[:, :2] = o + k * (src_anchor[:, :2] - o)
        anchor[:, 2] = self.ground + tgt_ankle_h + k * (src_anchor[:, 2] - src_ground - src_ankle_h)
        rb = self.root_bone
        R_root = lin[:, rb] @ np.linalg.inv(lin0[rb])  # rotation applied to the pelvis
        root_head = anchor + np.einsum("tij,j->ti", R_root, W0[rb, :3, 3] - self.tgt_anchor0)
        pose = _Pose(lin, root_head, G, None)
        pose.W = self.fk(pose)
        self._Rw = Rw
        self.src_height = self.source_height(src_ankle_h)
        self.height_ratio = self.height / self.src_height
        pose.anchor, pose.src_anchor = anchor, src_anchor
        pose.src_ground = src_ground
        if self.foot_lock:  # first: it may lower the pelvis
            if contacts is None:
                src_feet = pts[:, [JOINT_INDEX[n] for n in ("ltibia", "lfoot", "rtibia", "rfoot")]]
                contacts = planted(detect_contacts(src_feet, fps), src_feet)
            self.lock_feet(pose, np.asarray(contacts, dtype=bool))
        if self.match_head:
            self.lean_to(pose, self.goal(pose, pts[:, JOINT_INDEX["upperneck"]]))
            pose.W = self.fk(pose)
        if self.match_hands:
            for side in SIDES:
                self.reach(pose, side, self.goal(pose, pts[:, JOINT_INDEX[side + "wrist"]]), np.ones(T))
            pose.W = self.fk(pose)
        return pose

    def fk(self, pose):
        """World matrices ``(T, B, 4, 4)`` of all target bones: mapped bones take
        their linear part from ``pose.lin``, every bone its head from its parent
        (reference offsets), unmapped bones their reference pose relative to the parent."""
        tgt = self.target
        W0 = tgt.ref_world
        T = pose.lin.shape[0]
        W = np.empty((T, len(tgt.names), 4, 4))
        mapped = self.seg
        inv0 = getattr(self, "_inv0", None)
        if inv0 is None:
            inv0 = self._inv0 = np.linalg.inv(W0)
        roots = set(self.groups[ROOT_CHAIN])
        for b in tgt.order:
            p = tgt.parents[b]
            if b in roots and b == self.root_bone:
                W[:, b] = np.eye(4)
                W[:, b, :3, :3] = pose.lin[:, b]
                W[:, b, :3, 3] = pose.root_head
                continue
            if p < 0:
                W[:, b] = W0[b]
            else:
                W[:, b] = W[:, p] @ (inv0[p] @ W0[b])
            if b in mapped:
                W[:, b, :3, :3] = pose.lin[:, b]
        return W

    def landmarks(self, W):
        """``{landmark: (T, 3)}`` of the target (world), the same names as
        :func:`source_landmarks`: hip joints' midpoint, skull base, wrists, ankles, balls."""
        heads = W[..., :3, 3]
        out = {"hips": 0.5 * (heads[:, self._bones_of("lfemur")[0]] + heads[:, self._bones_of("rfemur")[0]])}
        for side in SIDES:
            wr = self._bones_of(side + "hand")
            if wr is not None:
                out[side + "wrist"] = heads[:, wr[0]]
            else:
                fa = self._bones_of(side + "radius")
                if fa is not None:
                    out[side + "wrist"] = self._end_world(W, fa[-1])
            foot = self._bones_of(side + "foot")
            if foot is not None:
                out[side + "ankle"] = heads[:, foot[0]]
            toe = self._bones_of(side + "toes")
            if toe is not None:
                out[side + "ball"] = heads[:, toe[0]]
            elif foot is not None:
                out[side + "ball"] = self._end_world(W, foot[-1])
        head = self._bones_of("head")
        if head is not None:
            out["head"] = heads[:, head[0]]
        return out

    def _end_world(self, W, b):
        """World position (T, 3) of bone ``b``'s segment end point."""
        chain = self.mapping[self.target.names[b]]
        end0 = self._end_point(b, self.groups[chain], chain)
        local = np.linalg.inv(self.target.ref_world[b]) @ np.append(end0, 1.0)
        return np.einsum("tij,j->ti", W[:, b], local)[:, :3]

    def _apply_delta(self, pose, bones, D, mask):
        for b in bones:
            pose.lin[mask, b] = D[mask] @ pose.lin[mask, b]
            pose.G[mask, b] = D[mask] @ pose.G[mask, b]

    # -- feet ---------------------------------------------------------------------
    def lock_feet(self, pose, contacts):
        """Lock the target's foot points where ``contacts (T, 4)`` (left ankle,
        left ball, right ankle, right ball) are on (:func:`_foot_targets`): two-bone
        leg IK to the ankle target, the foot turned about the ankle to the foot
        target. Where a locked leg cannot reach its target, the pelvis is first
        lowered as much as needed (smoothly over a few frames)."""
        legs = self._leg_targets(pose, contacts)  # world targets: they stay where they are
        total = np.zeros(len(pose.root_head))
        for _ in range(3):  # the smoothed drop changes the hips' path a little: a few rounds
            heads = pose.W[..., :3, 3]
            drop = np.zeros(len(pose.root_head))
            for side, (_, ankle_t, act, L) in legs.items():
                hip = heads[:, self._bones_of(side + "femur")[0]]
                need = np.minimum(_reach_drop(hip, ankle_t, 0.998 * L, self.max_drop * L),
                                  np.maximum(self.max_drop * L - total, 0.0))
                drop = np.maximum(drop, np.where(act, need, 0.0))
            if drop.max() < 1e-4:
                break
            drop = _smooth_max(drop, self.blend_frames)
            total += drop
            pose.root_head = pose.root_head - drop[:, None] * _UP
            pose.W = self.fk(pose)
        heads = pose.W[..., :3, 3]
        for side, (_, ankle_t, act, _) in legs.items():
            thigh, shin, foot = (self._bones_of(side + n) for n in ("femur", "tibia", "foot"))
            hip = heads[:, thigh[0]]
            toe = self._bones_of(side + "toes") or []
            A = heads[:, foot[0]]
            Fv = (heads[:, toe[0]] if toe else self._end_world(pose.W, foot[-1])) - A
            knee = heads[:, shin[0]]
            fwd = np.einsum("tij,j->ti", pose.G[:, thigh[0]], self._Rw @ _SRC_FWD)
            _, _, R1, R2 = two_bone_ik(hip, knee, A, ankle_t, knee + 0.1 * fwd)
            R3 = rotation_between(Fv, pose.foot_vec[side])
            self._apply_delta(pose, thigh, R1, act)
            self._apply_delta(pose, shin, R2, act)
            self._apply_delta(pose, foot + list(toe), R3, act)
        pose.W = self.fk(pose)
        return pose

    def _leg_targets(self, pose, contacts):
        """``{side: (hip (T, 3), ankle target (T, 3), frames to solve (T,), leg length)}``;
        the foot vectors go to ``pose.foot_vec``."""
        W = pose.W
        heads = W[..., :3, 3]
        out = {}
        pose.foot_vec = {}
        ref = self.target.heads()
        for si, side in enumerate(SIDES):
            thigh, shin, foot = (self._bones_of(side + n) for n in ("femur", "tibia", "foot"))
            if thigh is None or shin is None or foot is None:
                continue
            toe = self._bones_of(side + "toes") or []
            A = heads[:, foot[0]]
            Bp = heads[:, toe[0]] if toe else self._end_world(W, foot[-1])
            floor_a = self.ground + (self.tgt_foot_height[side + "ankle"] or 0.0)
            floor_b = self.ground + (self.tgt_foot_height[side + "ball"] or 0.0)
            ankle_t, newF, act = _foot_targets(A, Bp, contacts[:, 2 * si], contacts[:, 2 * si + 1], floor_a,
                                               floor_b, self.blend_frames, self.max_drift)
            if not act.any():
                continue
            L = float(np.linalg.norm(ref[shin[0]] - ref[thigh[0]]) + np.linalg.norm(ref[foot[0]] - ref[shin[0]]))
            out[side] = (heads[:, thigh[0]], ankle_t, act, L)
            pose.foot_vec[side] = newF
        return out

    def goal(self, pose, src_point):
        """Where a source point ``(T, 3)`` (world) goes on the target: horizontally
        relative to the pelvis, vertically above the floor, scaled by the ratio
        of the head-point heights."""
        s = self.height_ratio
        out = np.empty_like(src_point)
        out[:, :2] = pose.anchor[:, :2] + s * (src_point[:, :2] - pose.src_anchor[:, :2])
        out[:, 2] = self.ground + s * (src_point[:, 2] - pose.src_ground)
        return out

    # -- head ---------------------------------------------------------------------
    def lean_to(self, pose, goal):
        """Turn the spine and neck rigidly about the spine's base by the smallest
        rotation that aims the head point (skull base) at ``goal (T, 3)``."""
        spine = []
        for part in ("lowerback", "upperback", "thorax", "lowerneck", "upperneck"):
            for b in self._bones_of(part) or ():
                if b not in spine:
                    spine.append(b)
        head = self._bones_of("head")
        if not spine or head is None:
            return
        heads = pose.W[..., :3, 3]
        base = heads[:, spine[0]]
        D = rotation_between(heads[:, head[0]] - base, goal - base)
        self._apply_delta(pose, spine, D, np.ones(len(D), dtype=bool))

    # -- arms ---------------------------------------------------------------------
    def arm(self, side):
        """``(upper arm bones, forearm bones, hand bones or None)`` of ``side``."""
        fore = []
        for part in ("radius", "wrist"):
            for b in self._bones_of(side + part) or ():
                if b not in fore:
                    fore.append(b)
        return self._bones_of(side + "humerus"), fore or None, self._bones_of(side + "hand")

    def wrists(self, W):
        lm = self.landmarks(W)
        return np.stack([lm["lwrist"], lm["rwrist"]], axis=1)

    def reach(self, pose, side, target, weight):
        """Move the wrist of ``side`` towards ``target (T, 3)`` by ``weight (T,)``
        with two-bone arm IK (elbow as the pole). Where the arm is too short, the
        clavicle first turns to bring the shoulder closer (as ``ik.EndEffectorIK``)."""
        up, fa, _ = self.arm(side)
        if up is None or fa is None:
            return
        act = weight > 0
        if not act.any():
            return
        W = pose.W
        heads = W[..., :3, 3]
        sh, el = heads[:, up[0]], heads[:, fa[0]]
        wr = self.wrists(W)[:, SIDES.index(side)]
        goal = wr + weight[:, None] * (target - wr)
        clav = self._bones_of(side + "clavicle")
        reach = 0.999 * (np.linalg.norm(el - sh, axis=-1) + np.linalg.norm(wr - el, axis=-1))
        dist = np.linalg.norm(goal - sh, axis=-1)
        far = act & (dist > reach)
        if clav is not None and far.any():
            tip = sh + (goal - sh) * (reach / np.maximum(dist, 1e-12))[:, None]
            _, _, Rc, _ = two_bone_ik(heads[:, clav[0]], sh, tip, goal, sh)
            self._apply_delta(pose, list(clav) + list(up) + list(fa), Rc, far)
            pose.W = W = self.fk(pose)
            heads = W[..., :3, 3]
            sh, el = heads[:, up[0]], heads[:, fa[0]]
            wr = self.wrists(W)[:, SIDES.index(side)]
        _, _, R1, R2 = two_bone_ik(sh, el, wr, goal, el)
        self._apply_delta(pose, up, R1, act)
        self._apply_delta(pose, fa, R2, act)

    # -- output -------------------------------------------------------------------
    def basis(self, W):
        """``matrix_basis (T, B, 4, 4)`` of every target bone for world matrices ``W``."""
        tgt = self.target
        pose = np.linalg.inv(tgt.matrix_world)[None, None] @ W
        return basis_from_pose(tgt.rest, tgt.parents, pose)


def _reach_drop(hip, target, reach, most):
    """How far ``(T,)`` the hip must go down (at most ``most``) for ``target`` to
    lie within ``reach`` of it: 0 where it already does, and where lowering the
    hip cannot help (the target horizontally out of reach)."""
    d = target - hip
    h2 = np.sum(d[:, :2] ** 2, axis=-1)
    v = -d[:, 2]  # how far the target lies below the hip
    fit = np.sqrt(np.maximum(reach * reach - h2, 0.0))
    return np.where(h2 < reach * reach, np.clip(v - fit, 0.0, most), 0.0)


def _smooth_max(x, w):
    """A smooth envelope of ``x (T,)`` that is at least ``x`` everywhere: the
    running maximum over ±w frames, then its running mean over ±w frames."""
    T = len(x)
    pad = np.pad(x, w, mode="edge")
    mx = np.max(np.stack([pad[j:j + T] for j in range(2 * w + 1)]), axis=0)
    pad = np.pad(mx, w, mode="edge")
    return np.mean(np.stack([pad[j:j + T] for j in range(2 * w + 1)]), axis=0)


def _no_flips(G, d_rest, d, max_deg, hold=6):
    """World rotations ``G (T, 3, 3)`` without source glitches. A frame that turns
    more than ``max_deg`` from the previous output (a flip of the source's bone:
    1800 deg/s at 30 Hz) keeps the previous rotation, swung onto the bone's
    direction ``d (T, 3)`` (``d_rest`` at rest) when that is no jump itself (a
    twist flip). A jump that lasts more than ``hold`` frames is caught up with
    at half ``max_deg`` per frame."""
    from .rotations import matrix_to_quat, quat_slerp, quat_to_matrix

    if len(G) < 2:
        return G
    c = np.cos(np.deg2rad(max_deg))
    tr = np.trace(np.swapaxes(G[:-1], -1, -2) @ G[1:], axis1=-2, axis2=-1)
    if not np.any((tr - 1.0) / 2.0 < c):
        return G
    out = np.array(G)
    held = 0
    for t in range(1, len(G)):
        cos_a = np.clip((np.trace(out[t - 1].T @ G[t]) - 1.0) / 2.0, -1.0, 1.0)
        if cos_a >= c:
            held = 0
            continue
        held += 1
        if held <= hold:
            nxt = out[t - 1]
            if d is not None:  # a twist flip: keep the twist, follow the direction if that is no jump
                swing = rotation_between(nxt @ d_rest, d[t]) @ nxt
                if (np.trace(nxt.T @ swing) - 1.0) / 2.0 >= c:
                    nxt = swing
        else:  # a lasting jump: turn towards the source, max_deg / 2 per frame
            q0, q1 = matrix_to_quat(out[t - 1]), matrix_to_quat(G[t])
            if np.dot(q0, q1) < 0:
                q1 = -q1
            frac = 0.5 * np.deg2rad(max_deg) / np.arccos(cos_a)
            nxt = quat_to_matrix(quat_slerp(q0, q1, np.array(frac)))
        out[t] = nxt
    return out


def _interp_poly(pts, s_cum, f):
    """Point at arc-length fraction ``f`` of polylines ``pts (T, K, 3)`` whose rest
    vertices sit at fractions ``s_cum (K,)``."""
    f = float(np.clip(f, 0.0, 1.0))
    K = pts.shape[1]
    k = int(np.clip(np.searchsorted(s_cum, f, side="right") - 1, 0, K - 2))
    span = s_cum[k + 1] - s_cum[k]
    u = 0.0 if span <= 1e-12 else (f - s_cum[k]) / span
    return pts[:, k] + u * (pts[:, k + 1] - pts[:, k])


def _foot_targets(A, B, on_a, on_b, floor_a, floor_b, blend, max_drift=0.30):
    """Ankle targets ``(T, 3)``, foot vectors ``(T, 3)`` (ankle -> ball) and the
    frames to solve ``(T,)`` of one foot, from its unlocked ankle and ball
    ``A``, ``B (T, 3)`` and their contacts ``on_a``, ``on_b (T,)``.

    A point locks where it actually is when its contact starts (derived from the
    other point's lock when that one is already locked, so nothing jumps;
    otherwise lifted to its floor level if it is below it) and holds to the end
    of the contact. Then the offset between the lock and the unlocked point (on the
    last locked frame) fades out over ``blend`` frames: the foot moves on with
    the motion. A lock is
    released early when the unlocked point drifts farther than ``max_drift`` (m,
    horizontally) from it; that point then stays free until its contact ends.
    A locked ball has priority: the ankle turns about it (heel lifts);
    otherwise the ankle leads and the ball follows the foot's own orientation,
    pulled to its lock."""
    T = len(A)
    Fv = B - A
    flen = np.linalg.norm(Fv, axis=-1)
    ankle_t = A.copy()
    foot = Fv.copy()
    act = np.zeros(T, dtype=bool)
    pts = {"a": A, "b": B}
    # per point: lock point, frames since release (0: locked), armed, offset at release
    st = {"a": [None, 0, True, None], "b": [None, 0, True, None]}
    fade = [float(smoothstep(1.0 - j / (blend + 1))) for j in range(1, blend + 1)]

    def weight(k):
        p, j = st[k][0], st[k][1]
        if p is None:
            return 0.0
        return 1.0 if j == 0 else (fade[j - 1] if j <= blend else 0.0)

    def lock(k, t):
        p, j, _, off = st[k]
        return p if j == 0 else pts[k][t] + off

    for t in range(T):
        for k, on in (("a", on_a[t]), ("b", on_b[t])):
            p, j, armed, off = st[k]
            pt = pts[k][t]
            if p is not None and j == 0:  # locked: end of contact, or drifted away
                if not on or np.hypot(*(pt[:2] - p[:2])) > max_drift:
                    # fade out the lock's offset from the unlocked point as it was while
                    # locked (the last locked frame), not the lift-off's motion
                    st[k] = [p, 1, not on, p - pts[k][max(t - 1, 0)]]
            elif p is not None:  # fading out
                st[k] = [p, j + 1, armed or not on, off] if j < blend else [None, 0, armed or not on, None]
            else:
                st[k][2] = armed or not on
        starts = [k for k, on in (("a", on_a[t]), ("b", on_b[t])) if on and st[k][2] and not (
            st[k][0] is not None and st[k][1] == 0)]
        wa, wb = weight("a"), weight("b")
        for k in sorted(starts):  # the ankle first
            # Where the point actually is: derived from the other point's lock when
            # that one leads the foot (as it is: no jump), else its own position,
            # lifted to its floor level if it is below.
            if k == "a":
                if "b" not in starts and wb == 1.0:  # the ball leads
                    p = st["b"][0] - Fv[t]
                elif "b" in starts:  # both at once: the foot as it is, lifted out of the floor
                    p = A[t] + max(0.0, floor_a - A[t, 2], floor_b - B[t, 2]) * _UP
                else:
                    p = A[t].copy()
                    p[2] = max(p[2], floor_a)
            else:
                if "a" in starts:  # both at once: the ball at the foot's length from the ankle's lock
                    p = st["a"][0] + Fv[t]
                elif wa > 0.0:  # the ankle leads
                    p = A[t] + wa * (lock("a", t) - A[t]) + Fv[t]
                else:
                    p = B[t].copy()
                    p[2] = max(p[2], floor_b)
            st[k] = [p, 0, True, None]
        wa, wb = weight("a"), weight("b")
        if wa == 0.0 and wb == 0.0:
            continue
        act[t] = True
        la = lock("a", t) if wa > 0 else A[t]
        if wb == 1.0:
            lb = st["b"][0]
            d = (1.0 - wa) * Fv[t] + wa * (lb - la)
            d = d / max(np.linalg.norm(d), 1e-12) * flen[t]
            ankle_t[t], foot[t] = lb - d, d
        else:
            at = A[t] + wa * (la - A[t])
            bt = at + Fv[t]
            if wb > 0.0:
                bt = bt + wb * (lock("b", t) - bt)
            d = bt - at
            ankle_t[t], foot[t] = at, d / max(np.linalg.norm(d), 1e-12) * flen[t]
    return ankle_t, foot, act


def close_hands(ret_a: Retargeter, pose_a, src_a, src_b, ret_b: Retargeter = None, pose_b=None, wrists_b=None,
                near: float = 0.15, far: float = 0.20):
    """Keep hands that hold each other together.

    ``src_a``/``src_b``: source wrist positions ``(T, 2, 3)`` (world; left,
    right) of the two dancers. Where the closest leader/follower wrist pair of
    the source (and the complementary pair) is nearer than ``near`` (fading out
    at ``far``), the two target wrists are moved to meet at the source's gap
    vector (scaled by the mean of both rigs' scales): half each when ``pose_b``
    is given, else only ``a`` moves to the fixed partner wrists ``wrists_b (T, 2, 3)``.
    Returns the per-frame gap of the handled pairs ``(T, 2)`` before and after
    (NaN where no pair is held)."""
    T = src_a.shape[0]
    tw_a = ret_a.wrists(pose_a.W)
    tw_b = ret_b.wrists(pose_b.W) if pose_b is not None else np.asarray(wrists_b, dtype=np.float64)
    scale = 0.5 * (ret_a.scale + (ret_b.scale if ret_b is not None else ret_a.scale))
    d = np.linalg.norm(src_a[:, :, None] - src_b[:, None, :], axis=-1)  # (T, 2, 2)
    flat = d.reshape(T, 4)
    first = np.argmin(flat, axis=1)
    pairs = [(first // 2, first % 2), (1 - first // 2, 1 - first % 2)]
    rows = np.arange(T)
    goal_a = np.zeros((T, 2, 3))
    goal_b = np.zeros((T, 2, 3))
    wt_a = np.zeros((T, 2))
    wt_b = np.zeros((T, 2))
    before = np.full((T, 2), np.nan)
    for k, (ia, ib) in enumerate(pairs):
        ds = d[rows, ia, ib]
        w = 1.0 - smoothstep((ds - near) / max(far - near, 1e-9))
        gap = (src_b[rows, ib] - src_a[rows, ia]) * scale
        pa, pb = tw_a[rows, ia], tw_b[rows, ib]
        before[:, k] = np.where(w > 0, np.linalg.norm(pb - pa, axis=-1), np.nan)
        if pose_b is not None:
            mid = 0.5 * (pa + pb)
            ga, gb = mid - 0.5 * gap, mid + 0.5 * gap
        else:
            ga, gb = pb - gap, pb
        goal_a[rows, ia] = ga
        wt_a[rows, ia] = w
        goal_b[rows, ib] = gb
        wt_b[rows, ib] = w
    for s, side in enumerate(SIDES):
        ret_a.reach(pose_a, side, goal_a[:, s], wt_a[:, s])
    pose_a.W = ret_a.fk(pose_a)
    if pose_b is not None:
        for s, side in enumerate(SIDES):
            ret_b.reach(pose_b, side, goal_b[:, s], wt_b[:, s])
        pose_b.W = ret_b.fk(pose_b)
    tw_a = ret_a.wrists(pose_a.W)
    tw_b = ret_b.wrists(pose_b.W) if pose_b is not None else tw_b
    after = np.full((T, 2), np.nan)
    for k, (ia, ib) in enumerate(pairs):
        held = ~np.isnan(before[:, k])
        after[held, k] = np.linalg.norm(tw_b[rows, ib] - tw_a[rows, ia], axis=-1)[held]
    return before, after


def rotation_steps_deg(W):
    """Frame-to-frame rotation angle (degrees) ``(T-1, B)`` of world matrices ``(T, B, 4, 4)``."""
    lin = np.asarray(W, dtype=np.float64)[..., :3, :3]
    lin = lin / np.linalg.norm(lin, axis=-2, keepdims=True)
    rel = np.swapaxes(lin[:-1], -1, -2) @ lin[1:]
    tr = np.trace(rel, axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
