"""BVH (Biovision hierarchy) motion files: forward kinematics, tracked points,
motion, writer (the text parser is :mod:`.bvh_parse`; ``parse_bvh`` and
``BvhData`` are importable from here too).

Conventions of this module
--------------------------
- A BVH *joint* is the start of a bone. Its rest pose is all rotations zero:
  joint ``j`` starts at ``start(parent) + offset[j]``. Rotation channels listed
  as ``Zrotation Xrotation Yrotation`` mean ``L = Rz · Rx · Ry`` (column
  vectors: the last listed axis is applied first), angles in degrees. The
  global rotation is ``G[j] = G[parent] · L[j]``; joint positions are
  ``p[j] = p[parent] + G[parent] · t[j]``; an End Site of joint ``j`` lies at
  ``p[j] + G[j] · offset``. So ``G`` is the rotation *relative to the BVH rest
  pose*: a posed bone vector is ``G · rest bone vector``.
- Position channels, on any joint and anywhere in the channel list, *replace*
  the corresponding component of that joint's OFFSET (Blender's importer and
  exporter do the same; most files only have them on the root, whose offset is
  usually zero).
- The numbers are in the file's units. :func:`unit_scale` picks a factor to
  metres (``units='auto'``: from the rest-pose size of the skeleton, see there).
- Up axis: BVH is normally Y up (the SPEC's motion space). Files written by
  Blender's own exporter are in Blender's armature space, Z up. The functions
  that produce motion-space data (:func:`tracked_points`, :func:`bvh_to_motion`)
  take ``up='auto'``: if, in the rest pose, the head lies above the hips along
  +Z rather than +Y, the file is taken as Z up and converted with
  ``(x, y, z) -> (x, z, -y)`` (the inverse of the SPEC's Y-up -> Z-up map).
- Rest pose: :func:`fk`'s global rotations are relative to the file's rest
  pose. :func:`tracked_points` gives SPEC §2 rotations whatever the rest pose
  (T- or A-pose, any facing): measured from the rest pose's bone directions
  (:mod:`.rig_rest`); the CMU conversion's rest pose is exactly the ASF rest
  pose and is read as is.

Namings recognised (joint names may carry a ``namespace:`` prefix, matching is
case-insensitive and ignores ``_ - . space``; :mod:`.naming`):

- ``'cmu'``: the widely used CMU-converted naming (``skeleton.CMU_BVH_NAMES``:
  Hips, LHipJoint, LeftUpLeg, ..., Neck1, Head, LeftShoulder, LeftArm,
  LeftForeArm, LeftHand, LeftFingerBase, LeftHandIndex1, LThumb, ...). All 31
  must be present. Only this naming can become a full :class:`Motion`.
- ``'mixamo'`` (also Rokoko), ``'unreal'``, ``'rigify'``, ``'vrm'``, ``'asf'``
  and ``'generic'``: any rig with a skull joint and hand joints
  (:data:`.naming.TRACKED_ALIASES`).

Tracked points (SPEC §2): head = the skull joint (``Head``: for the CMU naming
the start of ``head`` = end of ``upperneck``); hands = the start of the hand
joint (the wrist: ``LeftFingerBase`` for the CMU naming, ASF ``lhand``, else
``LeftHand``, ``hand_l``, ...). Orientations: the skull joint and the hand
joint's parent, the forearm's end (:mod:`.rig_rest`).
"""
from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from ..rotations import euler_to_matrix, matrix_to_euler
from .bvh_parse import BvhData, parse_bvh
from .files import atomic_output
from .units import UNIT_SCALES, unit_scale_for_height
from .naming import bone_key, index_by_key
from .rig_rest import rest_corrections, tracked_rig
from ..skeleton import CMU_BVH_NAMES, JOINT_NAMES, PARENTS, Motion

# Y up -> motion space for a Z-up file: (x, y, z) -> (x, z, -y).
_Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class BvhPose(NamedTuple):
    """Forward kinematics result, scaled to metres by ``scale``."""

    positions: np.ndarray  # (T, J, 3) joint starts
    rotations: np.ndarray  # (T, J, 3, 3) global, relative to the rest pose
    end_positions: np.ndarray  # (T, E, 3)
    scale: float


class TrackedPoints(NamedTuple):
    """Head, left hand, right hand (this order) over the file's frames."""

    positions: np.ndarray  # (T, 3, 3) motion space, metres
    rotations: np.ndarray  # (T, 3, 3, 3) SPEC §2 global rotations (identity when not read)
    fps: float
    naming: str  # 'cmu' | 'asf' | 'mixamo' | 'unreal' | 'rigify' | 'vrm' | 'generic'
    joints: tuple  # BVH joint names whose positions were used
    scale: float  # file units -> metres used
    up: str  # 'Y' | 'Z': the file's up axis as used
    rotation_joints: tuple = ()  # BVH joint names whose rotations were used (skull, forearm ends)
    problem: str = ""  # why the orientations could not be read ('' when they were)


# --------------------------------------------------------------------------- parsing


def joint_local(data: BvhData, j: int, scale: float = 1.0):
    """Local translation ``(T, 3)`` (× ``scale``) and rotation ``(T, 3, 3)`` of joint ``j``."""
    T = data.n_frames
    trans = np.broadcast_to(data.offsets[j] * scale, (T, 3)).copy()
    c0 = int(data.channel_start[j])
    axes, cols = [], []
    for k, ch in enumerate(data.channels[j]):
        col = data.values[:, c0 + k]
        if ch.endswith("position"):
            trans[:, "XYZ".index(ch[0])] = col * scale
        else:
            axes.append(ch[0])
            cols.append(col)
    if axes:
        # Listed order c1 c2 c3 means R = R_c1 · R_c2 · R_c3: c3 is applied first.
        rot = euler_to_matrix(np.deg2rad(np.stack(cols[::-1], axis=-1)), "".join(axes[::-1]))
    else:
        rot = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    return trans, rot


def _fk_joints(data: BvhData, scale: float, needed):
    """``{j: (position (T, 3), global rotation (T, 3, 3))}`` for ``needed`` and their ancestors."""
    keep = set()
    for j in needed:
        while j >= 0 and j not in keep:
            keep.add(j)
            j = int(data.parents[j])
    out = {}
    for j in sorted(keep):  # parents come before children
        t, r = joint_local(data, j, scale)
        p = int(data.parents[j])
        if p < 0:
            out[j] = (t, r)
        else:
            pp, pg = out[p]
            out[j] = (pp + np.einsum("tab,tb->ta", pg, t), pg @ r)
    return out


def fk(data: BvhData, scale: float = 1.0) -> BvhPose:
    """Forward kinematics in file axes, lengths × ``scale``: every joint and End Site."""
    T, J = data.n_frames, data.n_joints
    res = _fk_joints(data, scale, range(J))
    pos = np.empty((T, J, 3))
    glob = np.empty((T, J, 3, 3))
    for j, (p, g) in res.items():
        pos[:, j], glob[:, j] = p, g
    ends = pos[:, data.end_parents] + np.einsum("teab,eb->tea", glob[:, data.end_parents],
                                                 data.end_offsets * scale)
    return BvhPose(pos, glob, ends, float(scale))


def rest_positions(data: BvhData, scale: float = 1.0):
    """Rest-pose (all channels zero, offsets only) joint starts ``(J, 3)`` and
    End Site positions ``(E, 3)``, lengths × ``scale``."""
    pos = np.zeros((data.n_joints, 3))
    for j in range(data.n_joints):
        p = data.parents[j]
        pos[j] = data.offsets[j] * scale + (pos[p] if p >= 0 else 0.0)
    ends = pos[data.end_parents] + data.end_offsets * scale
    return pos, ends


def rest_height(data: BvhData) -> float:
    """Largest extent (file units) of the rest-pose skeleton along any axis."""
    pos, ends = rest_positions(data)
    pts = np.concatenate([pos, ends])
    return float(np.max(pts.max(0) - pts.min(0))) if len(pts) else 0.0


def unit_scale(data: BvhData, units="auto") -> float:
    """Factor from the file's length unit to metres.

    ``units``: a number (used as is), one of :data:`UNIT_SCALES` (``'m'``,
    ``'cm'``, ``'mm'``, ``'inch'``, ``'cmu'``), or ``'auto'``: the unit that
    makes the rest-pose skeleton's largest extent (:func:`rest_height`; head
    to toe, or the arm span of a T-pose) closest to 1.7 m on a log scale. That
    is metres below 7.2 units, CMU units (×0.0254/0.45) to 45, inches to 107,
    centimetres to 540, millimetres above.
    """
    if isinstance(units, (int, float, np.floating)) and not isinstance(units, bool):
        if not (np.isfinite(units) and units > 0):
            raise ValueError(f"scale must be positive, got {units}")
        return float(units)
    if units != "auto":
        try:
            return UNIT_SCALES[str(units).lower()]
        except KeyError:
            raise ValueError(f"unknown units {units!r}; use 'auto', a number or one of "
                             f"{', '.join(UNIT_SCALES)}") from None
    return unit_scale_for_height(rest_height(data))


# --------------------------------------------------------------------------- naming


def detect_naming(data: BvhData):
    """``'cmu'`` (all 31 CMU-converted names), another naming of
    :func:`.naming.rig_naming` (head and hands found) or ``None``."""
    idx = index_by_key(data.names)
    if all(bone_key(v) in idx for v in CMU_BVH_NAMES.values()):
        return "cmu"
    rig = tracked_rig(data.names, data.parents)
    return None if rig is None else rig.naming


def _up_matrix(data: BvhData, up, head_joint: int | None):
    """(3x3 matrix file -> motion space, 'Y' | 'Z')."""
    if up == "auto":
        up = "Y"
        if head_joint is not None:
            pos, _ = rest_positions(data)
            d = pos[head_joint] - pos[0]
            if abs(d[2]) > abs(d[1]) and d[2] > 0:
                up = "Z"
    up = str(up).upper()
    if up == "Y":
        return np.eye(3), "Y"
    if up == "Z":
        return _Z_UP_TO_Y_UP, "Z"
    raise ValueError(f"up must be 'auto', 'Y' or 'Z', got {up!r}")


def _naming_error(data: BvhData):
    return InputError(
        data.path,
        "cannot find the head and hand joints: expected a skull joint and hand joints (Head with LeftHand/"
        "RightHand as in Mixamo, Rokoko or the CMU-converted BVH; hand_l (Unreal), DEF-hand.L (Rigify), "
        "J_Bip_L_Hand (VRoid) or lhand (ASF))",
        data.joint_lines[0] if data.joint_lines else None)


def tracked_points(data: BvhData, scale: float | None = None, units="auto", up="auto") -> TrackedPoints:
    """The SPEC §2 tracked points (head, left hand, right hand) for any
    recognised naming, in motion space (metres, Y up).

    Rotations are SPEC §2 global rotations of the skull and the forearm's ends
    (the hand joints' parents; :mod:`.rig_rest`), corrected for the file's rest
    pose; when the rest pose cannot be related to the SPEC's, identities and
    ``problem`` says why. The SPEC head device orientation is
    ``rotations[:, 0] @ Ry(180°)`` (composed by the take builder, not here).
    """
    rig = tracked_rig(data.names, data.parents)
    if rig is None:
        raise _naming_error(data)
    pj = list(rig.points)
    s = unit_scale(data, units if scale is None else scale)
    m, up_used = _up_matrix(data, up, pj[0])
    Q, problem = rest_corrections(rest_positions(data)[0] @ m.T, data.parents, rig)
    rj = [pj[0] if r is None else r for r in rig.rotations]
    res = _fk_joints(data, s, pj + rj)
    pos = np.stack([res[j][0] for j in pj], axis=1) @ m.T
    T = pos.shape[0]
    if Q is None:
        rot = np.broadcast_to(np.eye(3), (T, 3, 3, 3)).copy()
    else:
        rot = m @ np.stack([res[j][1] for j in rj], axis=1) @ m.T @ Q[None]
    return TrackedPoints(pos, rot, data.fps, "cmu" if detect_naming(data) == "cmu" else rig.naming,
                         tuple(data.names[i] for i in pj), s, up_used,
                         tuple(data.names[i] for i in rj), problem)


def head_bone_rotation(data: BvhData, up="auto") -> np.ndarray:
    """``(T, 3, 3)`` SPEC §2 global rotation of the skull joint, motion space (see
    :func:`tracked_points`). The SPEC head device is this ``@ Ry(180°)``."""
    return tracked_points(data, scale=1.0, up=up).rotations[:, 0]


def bvh_to_motion(data: BvhData, scale: float | None = None, units="auto", up="auto") -> Motion:
    """A CMU-named BVH as a SPEC §2 :class:`Motion` (metres, motion space).

    Joint position of bone ``n`` = the BVH joint that is the child of
    ``CMU_BVH_NAMES[n]`` (or its End Site for a leaf); root = ``Hips``. Global
    rotation of bone ``n`` = that of joint ``CMU_BVH_NAMES[n]`` (relative to the
    BVH rest pose, which for the CMU conversion is the ASF rest pose). Bone
    vectors are the rest offsets of those children (root: zero).
    """
    if detect_naming(data) != "cmu":
        idx = index_by_key(data.names)
        missing = [v for v in CMU_BVH_NAMES.values() if bone_key(v) not in idx]
        raise InputError(data.path, "not a CMU-skeleton BVH (missing joints " + ", ".join(missing[:6])
                         + (", ..." if len(missing) > 6 else "") + "); only its tracked points can be used",
                         data.joint_lines[0] if data.joint_lines else None)
    idx = index_by_key(data.names)
    bj = np.array([idx[bone_key(CMU_BVH_NAMES[n])] for n in JOINT_NAMES])
    for n in range(1, len(JOINT_NAMES)):
        if data.parents[bj[n]] != bj[PARENTS[n]]:
            raise InputError(data.path, f"joint {data.names[bj[n]]!r} should be a child of "
                             f"{data.names[bj[PARENTS[n]]]!r} (CMU skeleton)", data.joint_lines[bj[n]])
    s = unit_scale(data, units if scale is None else scale)
    m, up_used = _up_matrix(data, up, int(bj[JOINT_NAMES.index("head")]))
    pose = fk(data, s)
    T = data.n_frames
    positions = np.empty((T, len(JOINT_NAMES), 3))
    vectors = np.zeros((len(JOINT_NAMES), 3))
    positions[:, 0] = pose.positions[:, bj[0]]
    for n in range(1, len(JOINT_NAMES)):
        kids = np.nonzero(PARENTS == n)[0]
        if len(kids):
            c = bj[kids[0]]
            positions[:, n] = pose.positions[:, c]
            vectors[n] = data.offsets[c] * s
        else:
            ends = np.nonzero(data.end_parents == bj[n])[0]
            if not len(ends):
                raise InputError(data.path, f"leaf joint {data.names[bj[n]]!r} has no End Site",
                                 data.joint_lines[bj[n]])
            positions[:, n] = pose.end_positions[:, ends[0]]
            vectors[n] = data.end_offsets[ends[0]] * s
    rotations = m @ pose.rotations[:, bj] @ m.T
    return Motion(positions @ m.T, rotations, data.fps, vectors @ m.T, data.path,
                  {"bvh_scale": s, "bvh_up": up_used, "naming": "cmu"})


def load_bvh(path, input_fps: float | None = None, scale: float | None = None, units="auto",
             up="auto") -> Motion:
    """``bvh_to_motion(parse_bvh(path, input_fps), ...)``."""
    return bvh_to_motion(parse_bvh(path, input_fps), scale=scale, units=units, up=up)


# --------------------------------------------------------------------------- writing

_WRITE_ORDER = "ZXY"  # channel order written: Zrotation Xrotation Yrotation (R = Rz·Rx·Ry)


def _names_list(names):
    if isinstance(names, dict):
        return [names[n] for n in JOINT_NAMES]
    names = list(names)
    if len(names) != len(JOINT_NAMES):
        raise ValueError(f"need {len(JOINT_NAMES)} joint names, got {len(names)}")
    return names


def bvh_text(motion: Motion, names=CMU_BVH_NAMES) -> str:
    """The BVH text :func:`write_bvh` writes (metres, Y up, rest = ASF rest pose)."""
    names = _names_list(names)
    pos = np.asarray(motion.positions, dtype=np.float64)
    rot = np.asarray(motion.rotations, dtype=np.float64)
    vec = np.asarray(motion.bone_vectors, dtype=np.float64)
    J = len(JOINT_NAMES)
    if pos.ndim != 3 or pos.shape[1:] != (J, 3) or rot.shape != pos.shape[:2] + (3, 3) or vec.shape != (J, 3):
        raise ValueError("motion must have positions (T, 31, 3), rotations (T, 31, 3, 3), bone_vectors (31, 3)")
    if not (np.all(np.isfinite(pos[:, 0])) and np.all(np.isfinite(rot)) and np.all(np.isfinite(vec))):
        raise ValueError("motion has non-finite values")
    if not (np.isfinite(motion.fps) and motion.fps > 0):
        raise ValueError(f"fps must be positive, got {motion.fps}")
    T = pos.shape[0]
    local = rot.copy()
    local[:, 1:] = np.swapaxes(rot[:, PARENTS[1:]], -1, -2) @ rot[:, 1:]
    # R = Rz·Rx·Ry = euler_to_matrix((y, x, z), "YXZ"); write in listed order Z X Y.
    ang = np.rad2deg(matrix_to_euler(local, _WRITE_ORDER[::-1])[..., ::-1])
    ang = np.unwrap(ang, period=360.0, axis=0)

    children = [[c for c in range(J) if PARENTS[c] == n] for n in range(J)]
    out = ["HIERARCHY"]
    order = []
    rot_ch = " ".join(f"{a}rotation" for a in _WRITE_ORDER)

    def f3(v):
        return " ".join(f"{x:.8f}" for x in (v + 0.0))

    def emit(n, depth):
        ind = "\t" * depth
        out.append(f"{ind}{'ROOT' if n == 0 else 'JOINT'} {names[n]}")
        out.append(f"{ind}{{")
        off = np.zeros(3) if n == 0 else vec[PARENTS[n]]
        out.append(f"{ind}\tOFFSET {f3(off)}")
        if n == 0:
            out.append(f"{ind}\tCHANNELS 6 Xposition Yposition Zposition {rot_ch}")
        else:
            out.append(f"{ind}\tCHANNELS 3 {rot_ch}")
        order.append(n)
        for c in children[n]:
            emit(c, depth + 1)
        if not children[n]:
            out.append(f"{ind}\tEnd Site")
            out.append(f"{ind}\t{{")
            out.append(f"{ind}\t\tOFFSET {f3(vec[n])}")
            out.append(f"{ind}\t}}")
        out.append(f"{ind}}}")

    emit(0, 0)
    out.append("MOTION")
    out.append(f"Frames: {T}")
    out.append(f"Frame Time: {1.0 / float(motion.fps):.10f}")
    cols = [pos[:, 0]] + [ang[:, n] for n in order]
    table = np.concatenate(cols, axis=1) + 0.0  # + 0.0: no "-0.000000"
    fmt = " ".join(["%.8f"] * 3 + ["%.6f"] * (table.shape[1] - 3))
    body = "\n".join(fmt % tuple(row) for row in table)
    return "\n".join(out) + "\n" + body + "\n"


def write_bvh(path, motion: Motion, names=CMU_BVH_NAMES):
    """Write ``motion`` as a BVH on the CMU skeleton; returns ``path``.

    One BVH joint per ASF bone, named by ``names`` (a SPEC-bone -> name dict or
    31 names in SPEC order); rest pose = the ASF rest pose (OFFSET of a joint =
    its parent's rest bone vector, root offset 0); End Sites at the ends of the
    leaf bones. ``Hips`` has ``Xposition Yposition Zposition Zrotation Xrotation
    Yrotation`` (the root translation), the others ``Zrotation Xrotation
    Yrotation``. Metres, Y up (Blender's importer at scale 1.0 gives metres),
    ``Frame Time = 1/fps``. Only the root position, the global rotations and
    the bone vectors are written: the other joint positions follow by FK.
    Written atomically (a temporary file beside ``path``, then renamed).
    """
    text = bvh_text(motion, names)
    with atomic_output(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(text)
    return os.fspath(path)
