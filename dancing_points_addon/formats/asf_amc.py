"""Acclaim ASF (skeleton) and AMC (motion) files, as used by the CMU database.

Parsing is kept apart from any scene building (as io_anim_bvh does). An ASF
bone ``n`` with rest axis matrix ``C`` (from ``axis a b c ORDER``) and DOF angles
``E`` (composed in ``dof`` order) has local rotation ``L = C · E · C⁻¹`` in
motion space; its global rotation is ``G = G_parent · L``; it starts at its
parent's end and ends at ``start + G · direction · length``.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .files import read_text
from ..rotations import euler_to_matrix
from ..skeleton import JOINT_NAMES, Motion, forward_kinematics

INCH = 0.0254


@dataclass
class AsfBone:
    name: str
    direction: np.ndarray  # unit vector, rest pose, motion space
    length: float  # metres
    axis: np.ndarray  # 3x3 C
    dofs: tuple  # e.g. ("rx", "ry", "rz") or root ("tx", ..., "rz")
    line: int = 0


@dataclass
class AsfSkeleton:
    path: str
    bones: list  # [AsfBone], root first, topological order
    parents: np.ndarray
    scale: float  # file length unit -> metres
    angle_deg: bool
    root_position: np.ndarray  # metres

    @property
    def names(self):
        return [b.name for b in self.bones]

    def index(self, name):
        return self.names.index(name)

    @property
    def bone_vectors(self) -> np.ndarray:
        return np.array([b.direction * b.length for b in self.bones])

    def to_spec_order(self) -> np.ndarray:
        """Indices of this skeleton's bones in SPEC §2 order (error if missing)."""
        names = self.names
        missing = [n for n in JOINT_NAMES if n not in names]
        if missing:
            raise InputError(self.path, f"not the CMU 31-bone skeleton: missing bones {', '.join(missing)}")
        return np.array([names.index(n) for n in JOINT_NAMES])


def _floats(path, lineno, tokens, what):
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        raise InputError(path, f"non-numeric value in {what}: {' '.join(tokens)!r}", lineno) from None
    if not np.all(np.isfinite(vals)):
        raise InputError(path, f"non-finite value in {what}", lineno)
    return vals


def parse_asf(path) -> AsfSkeleton:
    """Parse an ASF file. Units become metres; angles are handled per ``:units``."""
    text = read_text(path)
    lines = text.splitlines()
    length_unit, angle_deg = 1.0, True
    section = None
    root = {"order": ("tx", "ty", "tz", "rx", "ry", "rz"), "axis": "XYZ",
            "position": [0.0, 0.0, 0.0], "orientation": [0.0, 0.0, 0.0]}
    raw_bones: list[dict] = []
    hierarchy: list[tuple[int, list[str]]] = []
    cur = None
    for lineno, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            parts = line.split()
            section = parts[0][1:].lower()
            continue
        tok = line.split()
        key = tok[0].lower()
        if section == "units":
            if key == "length" and len(tok) > 1:
                length_unit = _floats(path, lineno, tok[1:2], "units length")[0]
                if length_unit <= 0:
                    raise InputError(path, "units length must be positive", lineno)
            elif key == "angle" and len(tok) > 1:
                angle_deg = tok[1].lower().startswith("deg")
        elif section == "root":
            if key == "order":
                root["order"] = tuple(t.lower() for t in tok[1:])
            elif key == "axis":
                root["axis"] = tok[1].upper() if len(tok) > 1 else "XYZ"
            elif key in ("position", "orientation"):
                vals = _floats(path, lineno, tok[1:4], f"root {key}")
                if len(vals) != 3:
                    raise InputError(path, f"root {key} needs 3 values", lineno)
                root[key] = vals
        elif section == "bonedata":
            if key == "begin":
                cur = {"line": lineno, "dofs": ()}
            elif key == "end":
                if cur is None:
                    raise InputError(path, "'end' without 'begin' in bonedata", lineno)
                for need in ("name", "direction", "length", "axis"):
                    if need not in cur:
                        raise InputError(path, f"bone at line {cur['line']} has no '{need}'", lineno)
                raw_bones.append(cur)
                cur = None
            elif cur is not None:
                if key == "name":
                    cur["name"] = tok[1]
                elif key == "direction":
                    cur["direction"] = _floats(path, lineno, tok[1:4], "direction")
                elif key == "length":
                    cur["length"] = _floats(path, lineno, tok[1:2], "length")[0]
                elif key == "axis":
                    if len(tok) < 5:
                        raise InputError(path, "axis needs 3 angles and an order", lineno)
                    cur["axis"] = (_floats(path, lineno, tok[1:4], "axis"), tok[4].upper())
                elif key == "dof":
                    dofs = tuple(t.lower() for t in tok[1:])
                    bad = [d for d in dofs if d not in ("rx", "ry", "rz", "tx", "ty", "tz", "l")]
                    if bad:
                        raise InputError(path, f"unknown dof {bad[0]!r}", lineno)
                    cur["dofs"] = dofs
        elif section == "hierarchy":
            if key in ("begin", "end"):
                continue
            hierarchy.append((lineno, tok))
    if not raw_bones:
        raise InputError(path, "no bones in :bonedata (not an ASF file?)")

    scale = (1.0 / length_unit) * INCH
    to_rad = np.pi / 180.0 if angle_deg else 1.0
    by_name = {}
    for b in raw_bones:
        d = np.asarray(b["direction"], dtype=np.float64)
        n = np.linalg.norm(d)
        d = d / n if n > 0 else d
        ang, order = b["axis"]
        by_name[b["name"]] = AsfBone(
            b["name"], d, float(b["length"]) * scale,
            euler_to_matrix(np.asarray(ang) * to_rad, order), b["dofs"], b["line"])
    root_bone = AsfBone("root", np.zeros(3), 0.0,
                        euler_to_matrix(np.asarray(root["orientation"]) * to_rad, root["axis"]),
                        root["order"], 0)
    parent_of = {}
    for lineno, tok in hierarchy:
        for child in tok[1:]:
            if tok[0] != "root" and tok[0] not in by_name:
                raise InputError(path, f"hierarchy names unknown bone {tok[0]!r}", lineno)
            if child not in by_name:
                raise InputError(path, f"hierarchy names unknown bone {child!r}", lineno)
            parent_of[child] = tok[0]
    # Topological order: breadth-first from root, children in file order.
    order = ["root"]
    i = 0
    while i < len(order):
        order += [b["name"] for b in raw_bones if parent_of.get(b["name"]) == order[i]]
        i += 1
    bones = [root_bone] + [by_name[n] for n in order[1:]]
    index = {n: k for k, n in enumerate(order)}
    parents = np.array([-1] + [index[parent_of[n]] for n in order[1:]], dtype=np.int64)
    return AsfSkeleton(str(path), bones, parents, scale, angle_deg,
                       np.asarray(root["position"], dtype=np.float64) * scale)


_FRAME_RE = re.compile(r"^\s*(\d+)\s*$")


def parse_amc(path, skeleton: AsfSkeleton):
    """Parse an AMC file into per-bone DOF arrays ``{name: (T, ndof)}`` (file units).
    Frame numbers must follow each other (a gap or a frame out of order would
    shift the motion after it in time) and every frame must list each bone once."""
    text = read_text(path)
    lines = text.splitlines()
    rows: dict[str, list[str]] = {}
    row_lines: dict[str, list[int]] = {}
    frame_lines: list[int] = []  # the line of each frame's number
    frame_no = first_no = None
    in_frame = 0  # bone lines in the current frame (each bone once: fewer means one is missing)
    header_done = False
    dof_count = {b.name: len(b.dofs) for b in skeleton.bones}
    for lineno, raw in enumerate(lines, 1):
        line = raw.strip()
        if not line or line[0] == "#":
            continue
        if line[0] == ":":
            if header_done:
                raise InputError(path, f"header keyword {line.split()[0]!r} after the first frame", lineno)
            continue
        if line[0].isdigit() and _FRAME_RE.match(line):
            k = int(line)
            if frame_no is not None and k != frame_no + 1:
                raise InputError(path, f"frame {k} follows frame {frame_no} (frames missing or out of order)",
                                 lineno)
            if frame_lines and in_frame < len(rows):
                _check_frame_complete(path, rows, frame_no, frame_lines[-1], len(frame_lines))
            frame_no, in_frame = k, 0
            first_no = k if first_no is None else first_no
            frame_lines.append(lineno)
            header_done = True
            continue
        if not header_done:
            raise InputError(path, f"data before the first frame number: {line[:40]!r}", lineno)
        name, _, rest = line.partition(" ")
        if name not in dof_count:
            raise InputError(path, f"unknown bone {name!r} (not in the ASF)", lineno)
        lst = rows.get(name)
        if lst is None:
            if len(frame_lines) > 1:  # first seen after frame one: missing there
                raise InputError(path, f"frame {first_no} has no line for bone {name!r}", frame_lines[0])
            lst = rows[name] = []
            row_lines[name] = []
        if len(lst) == len(frame_lines):
            raise InputError(path, f"bone {name!r} listed twice in frame {frame_no}", lineno)
        lst.append(rest)
        row_lines[name].append(lineno)
        in_frame += 1
    n_frames = len(frame_lines)
    if n_frames == 0:
        raise InputError(path, "no frames (not an AMC file?)")
    _check_frame_complete(path, rows, frame_no, frame_lines[-1], n_frames, last=True)
    out = {}
    for name, lst in rows.items():
        k = dof_count[name]
        try:
            vals = np.array(" ".join(lst).split(), dtype=np.float64)
        except ValueError:
            _locate_bad_value(path, lines, name)
            raise
        if vals.size != n_frames * k:
            _locate_bad_count(path, lines, name, k)
        vals = vals.reshape(n_frames, k)
        if not np.all(np.isfinite(vals)):
            bad = int(np.argwhere(~np.isfinite(vals))[0, 0])
            raise InputError(path, f"non-finite value for bone {name!r} in frame {first_no + bad}",
                             row_lines[name][bad])
        out[name] = vals
    return out, n_frames


def frame_line(path, index: int) -> int | None:
    """The line of the frame number of the ``index``-th frame (from 0) of an
    AMC file, for a message about that frame found after parsing; None if
    there is no such frame."""
    k = -1
    for lineno, raw in enumerate(read_text(path).splitlines(), 1):
        if _FRAME_RE.match(raw):
            k += 1
            if k == index:
                return lineno
    return None


def _check_frame_complete(path, rows, frame_no, frame_line, n_frames, last=False):
    """Every bone seen so far has a line in frame ``frame_no`` (the ``n_frames``-th)."""
    for name, lst in rows.items():
        if len(lst) < n_frames:
            hint = " (truncated file?)" if last else ""
            raise InputError(path, f"frame {frame_no} has no line for bone {name!r}{hint}", frame_line)


def _locate_bad_value(path, lines, name):
    for lineno, raw in enumerate(lines, 1):
        tok = raw.split()
        if tok and tok[0] == name:
            for t in tok[1:]:
                try:
                    float(t)
                except ValueError:
                    raise InputError(path, f"non-numeric value {t!r} for bone {name!r}", lineno) from None


def _locate_bad_count(path, lines, name, k):
    for lineno, raw in enumerate(lines, 1):
        tok = raw.split()
        if tok and tok[0] == name and len(tok) - 1 != k:
            raise InputError(path, f"bone {name!r} needs {k} values, got {len(tok) - 1}", lineno)
    raise InputError(path, f"wrong number of values for bone {name!r}")


def local_rotations(skeleton: AsfSkeleton, dof_values: dict, n_frames: int):
    """Root translation (T, 3) in metres and local rotations (T, J, 3, 3)."""
    J = len(skeleton.bones)
    to_rad = np.pi / 180.0 if skeleton.angle_deg else 1.0
    local = np.broadcast_to(np.eye(3), (n_frames, J, 3, 3)).copy()
    root_t = np.zeros((n_frames, 3))
    for j, bone in enumerate(skeleton.bones):
        vals = dof_values.get(bone.name)
        if vals is None or not bone.dofs:
            continue  # no DOFs: rest pose (L = C I C^-1 = I)
        rot_axes, rot_vals = [], []
        for k, d in enumerate(bone.dofs):
            if d[0] == "r":
                rot_axes.append(d[1].upper())
                rot_vals.append(vals[:, k] * to_rad)
            elif d[0] == "t":
                root_t[:, "xyz".index(d[1])] = vals[:, k] * skeleton.scale
        if rot_axes:
            e = euler_to_matrix(np.stack(rot_vals, axis=-1), "".join(rot_axes))
            c = bone.axis
            local[:, j] = c @ e @ c.T
    return root_t, local


def load_amc(amc_path, asf_path=None, fps: float | None = None) -> Motion:
    """Load a CMU AMC take as a SPEC §2 :class:`Motion` (31 bones, metres, Y up).

    The ASF is ``asf_path`` or found beside the AMC (``60_01.amc`` -> ``60.asf``,
    else the only ``.asf`` in the folder). ``fps`` defaults to 120, the CMU
    database's rate, except for the salsa subjects 60/61 (60 Hz).
    """
    amc_path = str(amc_path)
    if asf_path is None:
        asf_path = find_asf(amc_path)
    skel = parse_asf(asf_path)
    order = skel.to_spec_order()
    values, n = parse_amc(amc_path, skel)
    root_t, local = local_rotations(skel, values, n)
    offsets = np.zeros((len(skel.bones), 3))
    vecs = skel.bone_vectors
    for j in range(1, len(skel.bones)):
        offsets[j] = vecs[skel.parents[j]]
    offsets[0] = skel.root_position
    glob, starts = forward_kinematics(skel.parents, offsets, root_t, local)
    ends = starts + np.einsum("tjab,jb->tja", glob, vecs)
    if fps is None:
        fps = default_fps(amc_path, asf_path)
    return Motion(ends[:, order], glob[:, order], float(fps), vecs[order], amc_path,
                  {"asf": str(asf_path)})


def default_fps(amc_path, asf_path=None) -> float:
    """The CMU database's rate of a take: 60 Hz for the salsa subjects 60 and 61,
    else 120 Hz. The subject is the AMC name's (``60_08.amc``), else, for an AMC
    renamed, the ASF's (``60.asf``), so a copy under another name plays at its speed."""
    m = re.match(r"(\d+)_", os.path.basename(str(amc_path)))
    subject = m.group(1) if m else os.path.splitext(os.path.basename(str(asf_path or "")))[0]
    return 60.0 if subject in ("60", "61") else 120.0


def find_asf(amc_path) -> str:
    folder = os.path.dirname(os.path.abspath(amc_path))
    subject = os.path.basename(amc_path).split("_")[0]
    cand = os.path.join(folder, subject + ".asf")
    if os.path.exists(cand):
        return cand
    asfs = [f for f in os.listdir(folder) if f.lower().endswith(".asf")]
    if len(asfs) == 1:
        return os.path.join(folder, asfs[0])
    raise InputError(amc_path, "no ASF skeleton found beside the AMC file (give it with --asf)")
