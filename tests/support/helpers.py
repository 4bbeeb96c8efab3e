"""Helpers shared by several test modules (tests never import one another)."""
import json
import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np

from conftest import MODELS, ROOT, SALSA
from dancing_points_addon.formats.take import COLUMNS, Take
from dancing_points_addon.rotations import matrix_to_quat, quat_to_matrix
from dancing_points_addon.skeleton import PARENTS, Motion

IDENT = [1.0, 0.0, 0.0, 0.0]


def bone_twist_deg(R, P, bone):
    """The bone's twist (degrees) about itself relative to its parent, per frame
    (world rotations ``R (T, 31, 3, 3)``, positions ``P (T, 31, 3)``)."""
    M = np.einsum("tji,tjk->tik", R[:, PARENTS[bone]], R[:, bone])
    d = np.einsum("tji,tj->ti", R[:, bone], P[:, bone] - P[:, PARENTS[bone]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    w = 0.5 * np.sqrt(1 + np.trace(M, axis1=1, axis2=2))
    v = np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], 1) / (4 * w[:, None])
    return np.degrees(2 * np.arctan2((v * d).sum(1), w))


def quat_angle_deg(a, b):
    """Rotation angle (degrees) between unit quaternions ``(…, 4)``, accurate near 0."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    b = b * np.where(np.sum(a * b, -1, keepdims=True) < 0, -1.0, 1.0)
    return np.degrees(4 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=-1) / 2, 0, 1)))


# --------------------------------------------------------------------------- take files

def row(t, head=(0.1, 1.6, 0.2), lhand=(-0.3, 1.1, 0.1), rhand=(0.3, 1.1, 0.1),
        hq=(0, 0, 1, 0), lq=IDENT, rq=IDENT):
    vals = [t, *head, *hq, *lhand, *lq, *rhand, *rq]
    return ",".join(str(v) for v in vals)


def good_lines(n=5):
    return [row(i / 90.0) for i in range(n)]


def write_lines(path, lines, header=",".join(COLUMNS), comments=("# height_m=1.78", "# a comment")):
    path.write_text("\n".join(list(comments) + ([header] if header is not None else []) + list(lines)) + "\n")
    return path


HEADER_LINE = 3  # two comment lines, then the header
ROW1 = 4         # first data row


def _replace_field(line, col, value):
    f = line.split(",")
    f[COLUMNS.index(col)] = value
    return ",".join(f)


def _case(kind):
    """(header, data lines, expected line, message fragment) for a rejection."""
    h = ",".join(COLUMNS)
    L = good_lines(6)
    if kind == "missing column":
        return (h.replace(",rhand_qz", ""), [ln.rsplit(",", 1)[0] for ln in L], HEADER_LINE,
                "missing header column rhand_qz")
    if kind == "unknown column":
        return h + ",extra", [ln + ",0" for ln in L], HEADER_LINE, "unknown header column 'extra'"
    if kind == "duplicate column":
        return h.replace("head_qw", "head_qx"), L, HEADER_LINE, "twice"
    if kind == "no header":
        return None, L, 3, "missing header line"
    if kind == "too few fields":
        L[2] = L[2].rsplit(",", 1)[0]
        return h, L, ROW1 + 2, "21 fields"
    if kind == "too many fields":
        L[3] = L[3] + ",1"
        return h, L, ROW1 + 3, "23 fields"
    if kind == "non-numeric":
        L[4] = _replace_field(L[4], "lhand_pz", "abc")
        return h, L, ROW1 + 4, "non-numeric value 'abc' in column lhand_pz"
    if kind == "non-numeric hex":
        L[1] = _replace_field(L[1], "head_px", "0x10")
        return h, L, ROW1 + 1, "non-numeric"
    if kind == "non-numeric space":
        L[1] = _replace_field(L[1], "rhand_py", "1 2")
        return h, L, ROW1 + 1, "non-numeric"
    if kind == "infinity":
        L[2] = _replace_field(L[2], "rhand_qx", "inf")
        return h, L, ROW1 + 2, "infinite value in column rhand_qx"
    if kind == "overflow":
        L[5] = _replace_field(L[5], "time", "1e400")
        return h, L, ROW1 + 5, "infinite value in column time"
    if kind == "far position":
        L[3] = _replace_field(L[3], "lhand_py", "1000.5")
        return h, L, ROW1 + 3, "lhand position is 1000.5"
    if kind == "small quaternion":
        L[1] = row(1 / 90, rq=(0.3, 0, 0, 0.3))
        return h, L, ROW1 + 1, "rhand quaternion norm 0.424264"
    if kind == "large quaternion":
        L[2] = row(2 / 90, hq=(0, 0, 2.1, 0))
        return h, L, ROW1 + 2, "head quaternion norm 2.1"
    if kind == "equal time":
        L[3] = row(2 / 90)
        return h, L, ROW1 + 3, "not after"
    if kind == "decreasing time":
        L[4] = row(0.0)
        return h, L, ROW1 + 4, "not after"
    if kind == "missing time":
        L[2] = _replace_field(L[2], "time", "")
        return h, L, ROW1 + 2, "missing time value"
    if kind == "one row":
        return h, L[:1], ROW1, "at least 2"
    if kind == "no rows":
        return h, [], HEADER_LINE, "at least 2"
    if kind == "earliest wins":
        L[5] = row(5 / 90, hq=(0, 0, 9, 0))
        L[2] = _replace_field(L[2], "head_pz", "-inf")
        return h, L, ROW1 + 2, "infinite"
    raise AssertionError(kind)


REJECTIONS = ["missing column", "unknown column", "duplicate column", "no header", "too few fields",
              "too many fields", "non-numeric", "non-numeric hex", "non-numeric space", "infinity",
              "overflow", "far position", "small quaternion", "large quaternion", "equal time",
              "decreasing time", "missing time", "one row", "no rows", "earliest wins"]


def write_case(path, kind):
    header, lines, line, frag = _case(kind)
    write_lines(path, lines, header=header)
    return line, frag


def axis_quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = np.asarray(angle)[..., None] / 2.0
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


def irregular_take(n=400, seed=1):
    """A 90 Hz take with jittered times, linear positions and constant-rate turns."""
    rng = np.random.default_rng(seed)
    t = 0.25 + np.arange(n) / 90.0 + rng.uniform(-0.003, 0.003, n)
    A = rng.uniform(-1, 1, (3, 3))
    B = rng.uniform(-2, 2, (3, 3))
    pos = A[None] + B[None] * t[:, None, None]
    axes = [(0, 1, 0), (1, 2, 0.5), (-0.3, 0.2, 1)]
    rates = [2.0, -5.0, 9.0]  # rad/s; several full turns over the take
    q = np.stack([axis_quat(ax, w * t) for ax, w in zip(axes, rates)], axis=1)
    q = matrix_to_quat(quat_to_matrix(q))  # canonical w >= 0: sign flips between rows
    return Take(t, pos, q, {"height_m": 1.8}, "irregular"), (A, B, axes, rates)


# --------------------------------------------------------------------------- the command line

def run_cli(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "dancing_points_addon", *map(str, args)],
                          cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def assert_bad_input(res, out_path, *fragments, old=None):
    """Exit 2, exactly one stderr line, no traceback, output absent or untouched."""
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error: "), res.stderr
    assert "Traceback" not in res.stderr + res.stdout
    for frag in fragments:
        assert frag in lines[0], (frag, lines[0])
    if old is None:
        assert not out_path.exists()
    else:
        assert out_path.read_bytes() == old
    # No temporary files left beside the output either.
    if out_path.parent.is_dir():
        leftovers = [p.name for p in out_path.parent.iterdir() if p.name.startswith("." + out_path.name)]
        assert not leftovers, leftovers
    return lines[0]


def broken_amc(tmp_path, edit):
    d = tmp_path / "amc"
    d.mkdir()
    shutil.copy(SALSA / "60.asf", d / "60.asf")
    lines = (SALSA / "60_01.amc").read_text().splitlines()
    lineno = edit(lines)
    (d / "60_01.amc").write_text("\n".join(lines) + "\n")
    return d / "60_01.amc", lineno


def bad_number(lines):
    i = next(k for k, ln in enumerate(lines) if ln.startswith("lfemur ") and k > 500)
    lines[i] = "lfemur 1.0 x2.5 3.0"
    return i + 1


def short_bone(lines):
    i = next(k for k, ln in enumerate(lines) if ln.startswith("rtibia ") and k > 300)
    lines[i] = "rtibia"
    return i + 1


def unknown_bone(lines):
    i = next(k for k, ln in enumerate(lines) if ln.startswith("head ") and k > 100)
    lines[i] = "nose 1 2 3"
    return i + 1


def _frame_line(lines, number):
    return next(k for k, ln in enumerate(lines) if ln.strip() == str(number))


def frames_missing(lines):
    """Frames 100-150 cut out: the motion after them would be shifted in time."""
    a, b = _frame_line(lines, 100), _frame_line(lines, 151)
    del lines[a:b]
    return a + 1


def frames_swapped(lines):
    """Frame 10 numbered 200."""
    i = _frame_line(lines, 10)
    lines[i] = "200"
    return i + 1


def frame_truncated(lines):
    """The file cut off inside its last frame."""
    last = max(k for k, ln in enumerate(lines) if ln.strip().isdigit())
    del lines[last + 3:]
    return last + 1


def bone_missing(lines):
    """Frame 50 without its lfemur line."""
    i = _frame_line(lines, 50)
    j = next(k for k in range(i, len(lines)) if lines[k].startswith("lfemur "))
    del lines[j]
    return i + 1


def root_far(lines):
    """Frame 60's root moved 1e30 units away: its line is the frame's number."""
    i = _frame_line(lines, 60)
    j = next(k for k in range(i, len(lines)) if lines[k].startswith("root "))
    lines[j] = "root 1e30 " + " ".join(lines[j].split()[2:])
    return i + 1


def non_finite(lines):
    i = next(k for k, ln in enumerate(lines) if ln.startswith("rtibia ") and k > 400)
    lines[i] = "rtibia nan"
    return i + 1


# --------------------------------------------------------------------------- motion clips

def cut(motion: Motion, start: int, n: int) -> Motion:
    """Frames ``start .. start + n`` of a motion."""
    return Motion(motion.positions[start:start + n], motion.rotations[start:start + n], motion.fps,
                  motion.bone_vectors, motion.source)


def trim_amc(src, dst, n_frames):
    """The header and the first ``n_frames`` frame blocks of an AMC file."""
    out, frames = [], 0
    with open(src, newline="") as f:
        for line in f:
            if line.strip().isdigit():
                frames += 1
                if frames > n_frames:
                    break
            out.append(line)
    with open(dst, "w", newline="") as f:
        f.writelines(out)


N60 = 300  # frames at 60 Hz per good take of :func:`make_takes` (5 s): 150 duet frames


def make_takes(d, salsa_dir):
    """A folder ``d`` of real takes (CSV, BVH, AMC; sub-folders) plus broken and
    ignored files, for the batch tests (local and on a cluster)."""
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.formats.bvh import write_bvh
    from dancing_points_addon.formats.take import take_from_motion, write_take

    for sub in ("sub", "amc", "noasf"):
        (d / sub).mkdir()
    write_take(d / "a.csv", take_from_motion(cut(load_amc(salsa_dir / "60_01.amc"), 600, N60)))
    write_take(d / "c.csv", take_from_motion(cut(load_amc(salsa_dir / "60_04.amc"), 0, N60)))
    write_bvh(d / "sub" / "b.bvh", cut(load_amc(salsa_dir / "60_02.amc"), 300, N60))
    trim_amc(salsa_dir / "60_03.amc", d / "amc" / "60_03.amc", N60)
    shutil.copy(salsa_dir / "60.asf", d / "amc" / "60.asf")
    # broken: bad header, truncated BVH, AMC without its ASF, empty file
    (d / "broken.csv").write_text("time,head_px,foo\n0,1,2\n")
    text = (d / "sub" / "b.bvh").read_text()
    (d / "sub" / "trunc.bvh").write_text(text[:len(text) // 50])
    trim_amc(salsa_dir / "61_09.amc", d / "noasf" / "61_09.amc", 50)
    (d / "empty.csv").write_text("")
    # ignored: other extensions, hidden files
    (d / "notes.txt").write_text("not a take")
    (d / "amc" / ".hidden.csv").write_text("time\n")
    return d


def model_dir(explicit, tool):
    """The models folder of a benchmark script (``--models`` > $DP_MODEL_DIR > bundled), or exit."""
    from dancing_points_addon.errors import InputError
    from dancing_points_addon.nets import resolve_model_dir

    try:
        return resolve_model_dir(explicit)
    except InputError:
        sys.exit(f"{tool}: no synthesis models (give --models DIR)")


def busy_seconds():
    """CPU seconds spent by the whole machine (all processes), from /proc/stat; None elsewhere."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
    except OSError:
        return None
    return (sum(v[:8]) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


def target_rig_from_bones(bones, world=None):
    """A retarget :class:`TargetRig` of ``bones`` = ``(name, parent, head, tail,
    roll)`` (armature space, metres): rest matrices as Blender makes them from a
    head, a tail and a roll; the object at ``world`` (4×4, default identity)."""
    from dancing_points_addon.retarget import TargetRig

    names = [b[0] for b in bones]
    parents = [names.index(b[1]) if b[1] else -1 for b in bones]
    rest = []
    for _, _, h, t, roll in bones:
        y = np.subtract(t, h) / np.linalg.norm(np.subtract(t, h))
        ref = np.array([0.0, 0.0, 1.0]) if abs(y[2]) < 0.9 else np.array([0.0, -1.0, 0.0])
        x = np.cross(y, ref)
        x /= np.linalg.norm(x)
        z = np.cross(x, y)
        c, s_ = np.cos(roll), np.sin(roll)
        x, z = c * x + s_ * z, -s_ * x + c * z
        m = np.eye(4)
        m[:3, :3] = np.stack([x, y, z], axis=1)
        m[:3, 3] = h
        rest.append(m)
    lengths = [np.linalg.norm(np.subtract(t, h)) for _, _, h, t, _ in bones]
    return TargetRig(names, parents, np.array(rest), lengths, matrix_world=world)


def apose_rig():
    """A rig in another convention and rest pose (Unreal names, A-pose, facing
    +Y in armature space, arbitrary rolls): ``(joints, bones)`` where bones are
    ``(name, parent, head, tail, roll)`` in metres."""
    s = np.sqrt(0.5)
    bones = [("root", None, (0, 0, 0), (0, 0.2, 0), 0.0),
             ("pelvis", "root", (0, 0, 0.88), (0, 0, 0.98), 1.1),
             ("spine_01", "pelvis", (0, 0, 0.98), (0, 0.01, 1.09), 0.3),
             ("spine_02", "spine_01", (0, 0.01, 1.09), (0, 0.01, 1.20), -0.7),
             ("spine_03", "spine_02", (0, 0.01, 1.20), (0, 0, 1.32), 2.0),
             ("neck_01", "spine_03", (0, 0, 1.32), (0, 0.02, 1.47), 0.0),
             ("head", "neck_01", (0, 0.02, 1.47), (0, 0.02, 1.64), 0.5)]
    for sg, side in ((-1, "l"), (1, "r")):
        x = sg  # facing +Y: the left side is -X
        sh = np.array([0.17 * x, 0.0, 1.30])
        d = np.array([s * x, 0.0, -s])
        el, wr, hd = sh + 0.30 * d, sh + 0.57 * d, sh + 0.65 * d
        bones += [("clavicle_" + side, "spine_03", (0.03 * x, 0, 1.29), tuple(sh), 0.4 * x),
                  ("upperarm_" + side, "clavicle_" + side, tuple(sh), tuple(el), 1.3 * x),
                  ("upperarm_twist_01_" + side, "upperarm_" + side, tuple((sh + el) / 2), tuple(el), 0.0),
                  ("lowerarm_" + side, "upperarm_" + side, tuple(el), tuple(wr), -0.9),
                  ("hand_" + side, "lowerarm_" + side, tuple(wr), tuple(hd), 2.5),
                  ("index_01_" + side, "hand_" + side, tuple(hd), tuple(hd + 0.04 * d), 0.0),
                  ("thigh_" + side, "pelvis", (0.09 * x, 0, 0.86), (0.09 * x, 0, 0.465), 0.8 * x),
                  ("calf_" + side, "thigh_" + side, (0.09 * x, 0, 0.465), (0.09 * x, 0, 0.08), -0.4),
                  ("foot_" + side, "calf_" + side, (0.09 * x, 0, 0.08), (0.09 * x, 0.12, 0.03), 3.0),
                  ("ball_" + side, "foot_" + side, (0.09 * x, 0.12, 0.03), (0.09 * x, 0.18, 0.03), 0.0)]
    return bones


# --------------------------------------------------------------------------- batch runs

def run_cli_long(*args, timeout=600, **kw):
    """``python -m dancing_points_addon ARGS`` with a batch's time limit (and ``subprocess.run`` options)."""
    return subprocess.run([sys.executable, "-m", "dancing_points_addon", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout, **kw)


def run_batch(inputs, out, fmt="npz", *extra, jobs=2, timeout=600):
    inputs = inputs if isinstance(inputs, (list, tuple)) else [inputs]
    """``batch`` of ``inputs`` into ``out`` with the shipped models, no progress bar."""
    return run_cli_long("batch", *inputs, "-o", out, "--format", fmt, "--jobs", jobs, "--models", MODELS,
                   "--no-progress", *extra, timeout=timeout)


def proc_table():
    """``{pid: (parent pid, state, CPU seconds)}`` of every process (Linux /proc)."""
    tck = os.sysconf("SC_CLK_TCK")
    out = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            out[int(entry)] = (int(fields[1]), fields[0], (int(fields[11]) + int(fields[12])) / tck)
    return out


def leftovers(folder):
    """Temporary or hidden files under ``folder``."""
    from dancing_points_addon.batch import PART

    bad = []
    for dirpath, dirnames, filenames in os.walk(folder):
        for n in filenames + dirnames:
            if n.startswith(".") or PART in n or n.endswith("@"):
                bad.append(os.path.join(dirpath, n))
    return bad


def read_report(out):
    """The batch report in ``out``."""
    from dancing_points_addon.batch import REPORT_NAME

    with open(os.path.join(out, REPORT_NAME)) as f:
        return json.load(f)


_PRELUDE = """
def action_fcurves(act):
    # an action's F-Curves: legacy action.fcurves, or the channelbags of a slotted action
    if act is None:
        return []
    fcs = list(getattr(act, "fcurves", []) or [])
    if not fcs:
        for layer in act.layers:
            for strip in layer.strips:
                for bag in strip.channelbags:
                    fcs.extend(bag.fcurves)
    return fcs
"""


def run_bpy_script(code, timeout=600):
    """Run ``code`` in a fresh Python with bpy (``action_fcurves(action)`` defined);
    it prints ``RESULT <json>``."""
    res = subprocess.run([sys.executable, "-c", _PRELUDE + textwrap.dedent(code)], cwd=ROOT, capture_output=True,
                         text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    found = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")]
    assert found, res.stdout[-3000:] + res.stderr[-3000:]
    return json.loads(found[-1][len("RESULT "):])


# --------------------------------------------------------------------------- retarget tests

# The take: seconds 10-15 of CMU salsa 60_10 (the dancers hold hands in it).
START, SECONDS = 10.0, 5.0
CM = 1e-2

# Landmarks: source DP bone whose tail it is / target bone whose head it is, per convention.
SRC_POINTS = {"lhip": "lhipjoint", "rhip": "rhipjoint", "head": "upperneck", "lwrist": "lwrist",
              "rwrist": "rwrist", "lankle": "ltibia", "rankle": "rtibia", "lball": "lfoot", "rball": "rfoot"}
TGT_POINTS = {
    "mixamo": {"lhip": "LeftUpLeg", "rhip": "RightUpLeg", "head": "Head", "lwrist": "LeftHand",
               "rwrist": "RightHand", "lankle": "LeftFoot", "rankle": "RightFoot", "lball": "LeftToeBase",
               "rball": "RightToeBase"},
    "unreal": {"lhip": "thigh_l", "rhip": "thigh_r", "head": "head", "lwrist": "hand_l", "rwrist": "hand_r",
               "lankle": "foot_l", "rankle": "foot_r", "lball": "ball_l", "rball": "ball_r"},
}


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing listens on (just now)."""
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port
