"""BVH parser, kinematics, namings and writer (dancing_points_addon.formats.bvh)."""
import os

import numpy as np
import pytest

from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.formats.bvh import (UNIT_SCALES, bvh_to_motion, detect_naming, fk, head_bone_rotation,
                                      load_bvh, parse_bvh, rest_height, tracked_points, unit_scale,
                                      write_bvh)
from dancing_points_addon.errors import InputError
from dancing_points_addon.skeleton import CMU_BVH_NAMES, HEAD_BONE, JOINT_NAMES, TRACKED, Motion


# --------------------------------------------------------------------------- helpers

def rot(axis, deg):
    """Rotation about a principal axis, written out by hand (column vectors)."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "X":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "Y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def make_bvh(joints, ends, frames, frame_time="0.0333333", nl="\n", ind="\t", brace_same_line=False,
             n_frames=None):
    """BVH text. ``joints``: [(name, parent, offset, channels)] in depth-first
    order; ``ends``: {joint index: offset}; ``frames``: (T, C) in file column order."""
    out = ["HIERARCHY"]

    def f(v):
        return " ".join(repr(float(x)) for x in v)

    def emit(j, depth):
        name, parent, off, chans = joints[j]
        pre = ind * depth
        kw = "ROOT" if parent < 0 else "JOINT"
        if brace_same_line:
            out.append(f"{pre}{kw} {name} {{")
        else:
            out.extend([f"{pre}{kw} {name}", f"{pre}{{"])
        out.append(f"{pre}{ind}OFFSET {f(off)}")
        out.append(f"{pre}{ind}CHANNELS {len(chans)} {' '.join(chans)}")
        for c, jj in enumerate(joints):
            if jj[1] == j:
                emit(c, depth + 1)
        if j in ends:
            out.extend([f"{pre}{ind}End Site", f"{pre}{ind}{{", f"{pre}{ind}{ind}OFFSET {f(ends[j])}",
                        f"{pre}{ind}}}"])
        out.append(f"{pre}}}")

    emit(0, 0)
    frames = np.atleast_2d(frames)
    out += ["MOTION", f"Frames: {len(frames) if n_frames is None else n_frames}", f"Frame Time: {frame_time}"]
    out += [" ".join(repr(float(x)) for x in row) for row in frames]
    return nl.join(out) + nl


def ref_fk(joints, ends, row, scale=1.0):
    """Independent FK for one frame: positions, global rotations, end sites."""
    P, G, col = [], [], 0
    for name, parent, off, chans in joints:
        t = np.array(off, dtype=float) * scale
        R = np.eye(3)
        for ch in chans:
            v = row[col]
            col += 1
            if ch.lower().endswith("position"):
                t["XYZ".index(ch[0].upper())] = v * scale
            else:
                R = R @ rot(ch[0].upper(), v)
        if parent < 0:
            P.append(t)
            G.append(R)
        else:
            P.append(P[parent] + G[parent] @ t)
            G.append(G[parent] @ R)
    E = [P[j] + G[j] @ (np.asarray(o, dtype=float) * scale) for j, o in sorted(ends.items())]
    return np.array(P), np.array(G), np.array(E)


def write(tmp_path, text, name="t.bvh", newline=""):
    p = tmp_path / name
    with open(p, "w", newline=newline) as f:
        f.write(text)
    return p


# --------------------------------------------------------------------------- writer <-> parser


@pytest.fixture(scope="module")
def salsa_motion(salsa_dir):
    return load_amc(salsa_dir / "60_01.amc")


def test_round_trip_real_take(salsa_motion, tmp_path):
    m = salsa_motion
    path = write_bvh(tmp_path / "take.bvh", m)
    assert os.listdir(tmp_path) == ["take.bvh"]  # no temporary file left behind
    data = parse_bvh(path)
    assert data.n_frames == m.n_frames and data.fps == 60.0 and not data.warnings
    assert data.names[0] == "Hips" and set(data.names) == set(CMU_BVH_NAMES.values())
    assert data.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")
    assert all(c == ("Zrotation", "Xrotation", "Yrotation") for c in data.channels[1:])
    assert len(data.end_parents) == 7  # ltoes rtoes head lfingers lthumb rfingers rthumb
    assert unit_scale(data) == 1.0 and 1.5 < rest_height(data) < 2.0
    back = bvh_to_motion(data)
    err = np.linalg.norm(back.positions - m.positions, axis=-1).max()
    print(f"\nwrite_bvh -> parse_bvh round trip, {m.n_frames} frames: max {err * 1e3:.2e} mm")
    assert err < 1e-6
    assert np.abs(back.rotations - m.rotations).max() < 1e-6
    assert np.abs(back.bone_vectors - m.bone_vectors).max() < 1e-7
    assert back.fps == m.fps and back.meta["naming"] == "cmu" and back.meta["bvh_up"] == "Y"
    # Tracked points (SPEC §2): Head joint = end of upperneck; FingerBase = end of lwrist.
    tp = tracked_points(data)
    assert tp.naming == "cmu" and tp.joints == ("Head", "LeftFingerBase", "RightFingerBase")
    assert np.abs(tp.positions - m.positions[:, TRACKED]).max() < 1e-6
    assert np.abs(tp.rotations[:, 0] - m.rotations[:, HEAD_BONE]).max() < 1e-6
    assert np.abs(tp.rotations[:, 1:] - m.rotations[:, TRACKED[1:]]).max() < 1e-6
    assert np.abs(head_bone_rotation(data) - m.rotations[:, HEAD_BONE]).max() < 1e-6
    assert np.abs(load_bvh(path).positions - back.positions).max() == 0.0


def test_writer_custom_names_and_rate(salsa_motion, tmp_path):
    m = salsa_motion.subsample(2)  # 30 Hz
    m = Motion(m.positions[:50], m.rotations[:50], m.fps, m.bone_vectors)
    names = [f"dp:{CMU_BVH_NAMES[n]}" for n in JOINT_NAMES]  # a namespace prefix is still the CMU naming
    data = parse_bvh(write_bvh(tmp_path / "a.bvh", m, names=names))
    assert data.names[0] == "dp:Hips" and data.fps == 30.0 and detect_naming(data) == "cmu"
    assert np.abs(bvh_to_motion(data).positions - m.positions).max() < 1e-6


def test_writer_is_atomic(salsa_motion, tmp_path):
    target = tmp_path / "keep.bvh"
    target.write_text("old")
    bad = Motion(salsa_motion.positions[:3], np.full_like(salsa_motion.rotations[:3], np.nan), 60.0,
                 salsa_motion.bone_vectors)
    with pytest.raises(ValueError):
        write_bvh(target, bad)
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["keep.bvh"]
    with pytest.raises(InputError) as e:
        write_bvh(tmp_path / "missing" / "x.bvh", salsa_motion)
    assert "missing" in str(e.value)


# --------------------------------------------------------------------------- channel orders

ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]


@pytest.mark.parametrize("order", ORDERS)
def test_channel_orders_match_independent_fk(order, tmp_path):
    rng = np.random.default_rng(ORDERS.index(order))
    rch = [f"{a}rotation" for a in order]
    # positions at the front, at the end, and interleaved; a child with positions too
    joints = [
        ("Root", -1, (0.1, 0.9, -0.2), ["Xposition", "Yposition", "Zposition"] + rch),
        ("A", 0, (0.0, 0.3, 0.05), rch),
        ("B", 1, (0.2, 0.0, 0.1), [rch[0], "Zposition", rch[1], "Xposition", rch[2]]),
        ("C", 2, (0.0, -0.25, 0.0), rch + ["Yposition"]),
        ("D", 0, (-0.1, -0.1, 0.0), rch[::-1]),
        ("E", 4, (0.0, -0.4, 0.0), [rch[1]]),  # a single rotation channel
    ]
    ends = {3: (0.05, 0.0, 0.12), 5: (0.0, -0.4, 0.0)}
    C = sum(len(j[3]) for j in joints)
    frames = rng.uniform(-180, 180, size=(5, C))
    pos_cols = [k for k, ch in enumerate(c for j in joints for c in j[3]) if ch.endswith("position")]
    frames[:, pos_cols] = rng.uniform(-1, 1, size=(5, len(pos_cols)))
    data = parse_bvh(write(tmp_path, make_bvh(joints, ends, frames)))
    assert data.names == [j[0] for j in joints] and list(data.parents) == [j[1] for j in joints]
    assert [len(c) for c in data.channels] == [len(j[3]) for j in joints]
    pose = fk(data)
    for t, row in enumerate(frames):
        P, G, E = ref_fk(joints, ends, row)
        assert np.abs(pose.positions[t] - P).max() < 1e-12
        assert np.abs(pose.rotations[t] - G).max() < 1e-12
        assert np.abs(pose.end_positions[t] - E).max() < 1e-12
    # scale applies to offsets and position channels
    pose2 = fk(data, scale=0.01)
    P, G, E = ref_fk(joints, ends, frames[2], scale=0.01)
    assert np.abs(pose2.positions[2] - P).max() < 1e-12


def test_rotation_order_known_answers(tmp_path):
    def child_pos(chans):
        joints = [("R", -1, (0, 0, 0), chans), ("C", 0, (0, 1, 0), [])]
        data = parse_bvh(write(tmp_path, make_bvh(joints, {1: (0, 0, 1)}, [[90.0, 90.0]])))
        return fk(data).positions[0, 1]

    # Zrotation Xrotation: R = Rz·Rx, X applied first: (0,1,0) -> (0,0,1) -> (0,0,1)
    assert np.allclose(child_pos(["Zrotation", "Xrotation"]), [0, 0, 1])
    # Xrotation Zrotation: R = Rx·Rz: (0,1,0) -> (-1,0,0) -> (-1,0,0)
    assert np.allclose(child_pos(["Xrotation", "Zrotation"]), [-1, 0, 0])


def test_crlf_tabs_spaces_and_braces_on_keyword_lines(tmp_path):
    joints = [("Hips", -1, (0, 1, 0), ["Xposition", "Yposition", "Zposition", "Yrotation", "Xrotation",
                                       "Zrotation"]),
              ("Chest", 0, (0, 0.5, 0), ["Yrotation", "Zrotation", "Xrotation"])]
    frames = np.array([[0.1, 1.0, 0.2, 10, 20, 30, 5, 6, 7], [0.2, 1.1, 0.3, -10, 40, 3, 1, 2, 3]])
    ref = parse_bvh(write(tmp_path, make_bvh(joints, {1: (0, 0.2, 0)}, frames), "ref.bvh"))
    for k, kw in enumerate([dict(nl="\r\n"), dict(ind="    "), dict(nl="\r\n", ind=" \t", brace_same_line=True),
                            dict(nl="\r")]):
        data = parse_bvh(write(tmp_path, make_bvh(joints, {1: (0, 0.2, 0)}, frames, **kw), f"v{k}.bvh"))
        assert data.names == ref.names and np.array_equal(data.values, ref.values)
        assert np.array_equal(data.end_offsets, ref.end_offsets)
    assert ref.fps == 30.0  # 0.0333333 is 1/30 rounded


def test_frame_rate_and_overrides(tmp_path):
    joints = [("Hips", -1, (0, 0, 0), ["Xposition", "Yposition", "Zposition"])]
    p = write(tmp_path, make_bvh(joints, {0: (0, 1, 0)}, [[0, 1, 0], [0, 1, 1]], frame_time="0.016667"))
    assert parse_bvh(p).fps == 60.0
    p = write(tmp_path, make_bvh(joints, {0: (0, 1, 0)}, [[0, 1, 0]], frame_time="0.0333667"))
    assert abs(parse_bvh(p).fps - 29.97) < 0.001  # not snapped
    p = write(tmp_path, make_bvh(joints, {0: (0, 1, 0)}, [[0, 1, 0]], frame_time="0"))
    with pytest.raises(InputError):
        parse_bvh(p)
    assert parse_bvh(p, input_fps=72).fps == 72.0  # the override wins over a bad header
    with pytest.raises(InputError):
        parse_bvh(p, input_fps=0)


def test_more_rows_than_declared_is_accepted_with_warning(tmp_path):
    joints = [("Hips", -1, (0, 0, 0), ["Xposition", "Yposition", "Zposition"])]
    p = write(tmp_path, make_bvh(joints, {0: (0, 1, 0)}, [[0, 1, 0], [0, 1, 1], [0, 1, 2]], n_frames=2))
    data = parse_bvh(p)
    assert data.n_frames == 3 and data.warnings and "3 rows" in data.warnings[0]


# --------------------------------------------------------------------------- units and namings


def test_unit_heuristic(tmp_path):
    joints = [("Hips", -1, (0, 0, 0), ["Yrotation"]), ("Head", 0, (0, 1.0, 0), [])]
    for height, unit in [(1.0, "m"), (1.9, "m"), (30.0, "cmu"), (68.0, "inch"), (175.0, "cm"),
                         (1800.0, "mm")]:
        data = parse_bvh(write(tmp_path, make_bvh([joints[0], ("Head", 0, (0, height * 0.8, 0), [])],
                                                  {1: (0, height * 0.2, 0)}, [[0.0]])))
        assert unit_scale(data) == UNIT_SCALES[unit], (height, unit)
        assert unit_scale(data, "cm") == 0.01 and unit_scale(data, 0.5) == 0.5
    with pytest.raises(ValueError):
        unit_scale(data, "furlong")


def mixamo_rig(prefix="mixamorig:"):
    """A small Mixamo-named T-pose in centimetres, facing +Z, Y up."""
    J = []

    def add(name, parent, off, chans=("Zrotation", "Xrotation", "Yrotation")):
        J.append((prefix + name, parent, off, list(chans)))
        return len(J) - 1

    hips = add("Hips", -1, (0, 0, 0), ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation",
                                       "Yrotation"))
    sp = add("Spine", hips, (0, 10, 0))
    sp1 = add("Spine1", sp, (0, 12, 0))
    sp2 = add("Spine2", sp1, (0, 12, 0))
    neck = add("Neck", sp2, (0, 15, 0))
    head = add("Head", neck, (0, 10, 0))
    ends = {head: (0, 18, 0)}
    for side, sx in (("Left", 1), ("Right", -1)):
        sh = add(f"{side}Shoulder", sp2, (sx * 5, 12, 0))
        arm = add(f"{side}Arm", sh, (sx * 12, 0, 0))
        fore = add(f"{side}ForeArm", arm, (sx * 27, 0, 0))
        hand = add(f"{side}Hand", fore, (sx * 25, 0, 0))
        ends[hand] = (sx * 18, 0, 0)
    for side, sx in (("Left", 1), ("Right", -1)):
        up = add(f"{side}UpLeg", hips, (sx * 9, -6, 0))
        leg = add(f"{side}Leg", up, (0, -44, 0))
        foot = add(f"{side}Foot", leg, (0, -42, 0))
        toe = add(f"{side}ToeBase", foot, (0, -7, 12))
        ends[toe] = (0, 0, 8)
    # depth-first order for the file columns
    order = []

    def dfs(j):
        order.append(j)
        for c, jj in enumerate(J):
            if jj[1] == j:
                dfs(c)

    dfs(0)
    remap = {o: k for k, o in enumerate(order)}
    joints = [(J[o][0], remap.get(J[o][1], -1), J[o][2], J[o][3]) for o in order]
    return joints, {remap[j]: off for j, off in ends.items()}


@pytest.mark.parametrize("prefix", ["mixamorig:", "", "Armature:", "mixamorig1:"])
def test_mixamo_naming_tracked_points(prefix, tmp_path):
    joints, ends = mixamo_rig(prefix)
    rng = np.random.default_rng(3)
    C = sum(len(j[3]) for j in joints)
    frames = rng.uniform(-40, 40, size=(4, C))
    frames[:, :3] = [[3, 95, -2], [4, 96, 0], [5, 97, 2], [6, 96, 4]]
    data = parse_bvh(write(tmp_path, make_bvh(joints, ends, frames)))
    assert detect_naming(data) == "mixamo"
    tp = tracked_points(data)
    assert tp.naming == "mixamo" and tp.scale == 0.01 and tp.up == "Y" and tp.fps == 30.0
    assert tp.joints == tuple(prefix + n for n in ("Head", "LeftHand", "RightHand"))
    # the hand orientation is the forearm's (the hand bone bends at the wrist); a T-pose facing +Z
    # is the SPEC's rest pose, so the rotations are the file's as they are
    assert tp.rotation_joints == tuple(prefix + n for n in ("Head", "LeftForeArm", "RightForeArm"))
    assert tp.problem == ""
    idx = [data.names.index(n) for n in tp.joints]
    ridx = [data.names.index(n) for n in tp.rotation_joints]
    for t, row in enumerate(frames):
        P, G, _ = ref_fk(joints, ends, row, scale=0.01)
        assert np.abs(tp.positions[t] - P[idx]).max() < 1e-12
        assert np.abs(tp.rotations[t] - G[ridx]).max() < 1e-12
    assert np.abs(head_bone_rotation(data) - tp.rotations[:, 0]).max() < 1e-12
    with pytest.raises(InputError) as e:
        bvh_to_motion(data)  # not the CMU skeleton
    assert e.value.line == 2 and "LHipJoint" in str(e.value)


def test_z_up_file_is_detected(tmp_path):
    """The same take written Z up (as Blender's exporter does) gives the same points."""
    joints, ends = mixamo_rig()
    rng = np.random.default_rng(5)
    C = sum(len(j[3]) for j in joints)
    frames = rng.uniform(-30, 30, size=(3, C))
    frames[:, :3] = [[3, 95, -2], [4, 96, 0], [5, 97, 2]]
    # Y up -> Z up: (x, y, z) -> (x, -z, y); so axis Y -> Z, axis Z -> -Y (angle negated)
    zj, zf = [], frames.copy()
    col = 0
    for name, parent, off, chans in joints:
        new = []
        for ch in chans:
            a, kind = ch[0], ch[1:]
            if a == "Y":
                new.append("Z" + kind)
            elif a == "Z":
                new.append("Y" + kind)
                zf[:, col] = -zf[:, col]
            else:
                new.append(ch)
            col += 1
        zj.append((name, parent, (off[0], -off[2], off[1]), new))
    zends = {j: (o[0], -o[2], o[1]) for j, o in ends.items()}
    y = tracked_points(parse_bvh(write(tmp_path, make_bvh(joints, ends, frames), "y.bvh")))
    z = tracked_points(parse_bvh(write(tmp_path, make_bvh(zj, zends, zf), "z.bvh")))
    assert z.up == "Z" and y.up == "Y"
    assert np.abs(z.positions - y.positions).max() < 1e-12
    assert np.abs(z.rotations - y.rotations).max() < 1e-12


def test_generic_and_unknown_naming(tmp_path):
    chans = ["Zrotation", "Xrotation", "Yrotation"]
    joints = [("hip", -1, (0, 0, 0), ["Xposition", "Yposition", "Zposition"] + chans),
              ("head", 0, (0, 60, 0), chans), ("lHand", 0, (70, 40, 0), chans),
              ("rHand", 0, (-70, 40, 0), chans), ("lFoot", 0, (10, -90, 0), chans)]
    ends = {1: (0, 20, 0), 2: (10, 0, 0), 3: (-10, 0, 0), 4: (0, -5, 10)}
    frames = np.zeros((2, 3 + 3 * 5))
    data = parse_bvh(write(tmp_path, make_bvh(joints, ends, frames)))
    tp = tracked_points(data)
    assert tp.naming == "generic" and tp.joints == ("head", "lHand", "rHand") and tp.scale == 0.01
    assert np.allclose(tp.positions[0], [[0, 0.6, 0], [0.7, 0.4, 0], [-0.7, 0.4, 0]])
    # hands hung on the hips: no forearm whose orientation could be read, so none is guessed
    assert "arm is not straight" in tp.problem and np.all(tp.rotations == np.eye(3))
    joints[2] = ("Bone.002", 0, (70, 40, 0), chans)
    data = parse_bvh(write(tmp_path, make_bvh(joints, ends, frames), "u.bvh"))
    assert detect_naming(data) is None
    with pytest.raises(InputError) as e:
        tracked_points(data)
    assert e.value.line == 2 and "head and hand joints" in str(e.value)


# --------------------------------------------------------------------------- rejections

BASE = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
\tJOINT Spine
\t{
\t\tOFFSET 0 10 0
\t\tCHANNELS 3 Zrotation Xrotation Yrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 10 0
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: 0.033333
0 1 0 0 0 0 10 0 0
0 1 0 0 0 0 20 0 0
""".split("\n")


def edit(**changes):
    """BASE with lines replaced ({lineno: text}, None deletes) or inserted ({'ins_N': text} before N)."""
    lines = list(BASE)
    for key in sorted(changes, key=lambda k: -int(str(k).split("_")[-1])):
        n = int(str(key).split("_")[-1])
        if str(key).startswith("ins"):
            lines[n - 1:n - 1] = changes[key].split("\n")
        elif changes[key] is None:
            del lines[n - 1]
        else:
            lines[n - 1] = changes[key]
    return "\n".join(lines)


REJECT = [
    ("not_bvh", edit(l_1="HEIRARCHY"), 1, "HIERARCHY"),
    ("empty", "", 1, "HIERARCHY"),
    ("two_roots", edit(ins_16="ROOT Other\n{\n\tOFFSET 0 0 0\n}"), 16, "several roots"),
    ("no_motion", "\n".join(BASE[:15]) + "\n", 15, "MOTION"),
    ("no_root", "HIERARCHY\nMOTION\nFrames: 1\nFrame Time: 0.1\n\n", 2, "ROOT"),
    ("row_too_long", edit(l_20="0 1 0 0 0 0 20 0 0 7"), 20, "10 values, expected 9"),
    ("row_too_short", edit(l_19="0 1 0 0 0 0 10 0"), 19, "8 values, expected 9"),
    ("non_numeric", edit(l_19="0 1 0 0 abc 0 10 0 0"), 19, "non-numeric"),
    ("nan_value", edit(l_20="0 1 0 0 0 nan 20 0 0"), 20, "non-finite"),
    ("fewer_rows", edit(l_17="Frames: 3"), 17, "declares 3 frames but only 2"),
    ("zero_frames", edit(l_17="Frames: 0", l_19=None, l_20=None), 17, "no frames"),
    ("bad_frames_line", edit(l_17="Frame: 2"), 17, "Frames"),
    ("frames_not_int", edit(l_17="Frames: two"), 17, "whole number"),
    ("zero_frame_time", edit(l_18="Frame Time: 0"), 18, "positive"),
    ("negative_frame_time", edit(l_18="Frame Time: -0.01"), 18, "positive"),
    ("bad_frame_time", edit(l_18="Frame Time: fast"), 18, "non-numeric"),
    ("missing_frame_time", edit(l_18=None, l_19=None, l_20=None), 17, "Frame Time"),
    ("unclosed_brace", edit(l_14=None), 3, "never closed"),
    ("extra_brace", edit(ins_16="}"), 16, "without a matching"),
    ("end_site_unclosed", edit(l_13="\t\tJOINT Neck"), 13, "End Site"),
    ("short_offset", edit(l_8="\t\tOFFSET 0 10"), 8, "3 numbers"),
    ("offset_not_number", edit(l_8="\t\tOFFSET 0 x 0"), 8, "non-numeric"),
    ("missing_offset", edit(l_8=None), 6, "no OFFSET"),
    ("offset_twice", edit(ins_9="\t\tOFFSET 0 1 0"), 9, "twice"),
    ("unknown_channel", edit(l_9="\t\tCHANNELS 3 Zrotation Xrotation Wrotation"), 9, "Wrotation"),
    ("channel_twice", edit(l_9="\t\tCHANNELS 3 Zrotation Xrotation Zrotation"), 9, "twice"),
    ("channels_count", edit(l_9="\t\tCHANNELS x Zrotation"), 9, "count"),
    ("stray_word", edit(ins_10="\t\tBogus"), 10, "Bogus"),
    ("junk_after_motion", edit(l_16="MOTION now"), 16, "after MOTION"),
]


@pytest.mark.parametrize("name,text,line,fragment", REJECT, ids=[r[0] for r in REJECT])
def test_rejections_name_file_and_line(name, text, line, fragment, tmp_path):
    p = write(tmp_path, text, "bad.bvh")
    assert name == "empty" or parse_bvh(write(tmp_path, "\n".join(BASE), "ok.bvh")).n_frames == 2
    with pytest.raises(InputError) as e:
        parse_bvh(p)
    err = e.value
    assert err.line == line, str(err)
    assert str(p) in str(err) and f":{line}:" in str(err)
    assert fragment in str(err)


def test_missing_file_is_input_error(tmp_path):
    with pytest.raises(InputError):
        parse_bvh(tmp_path / "nope.bvh")


def test_channels_before_offset_is_accepted(tmp_path):
    text = edit(l_8="\t\tCHANNELS 3 Zrotation Xrotation Yrotation", l_9="\t\tOFFSET 0 10 0")
    data = parse_bvh(write(tmp_path, text))
    assert data.channels[1] == ("Zrotation", "Xrotation", "Yrotation")
    a = np.radians(20.0)  # frame 2: Spine Zrotation 20 about (0, 11, 0)
    assert np.allclose(fk(data).end_positions[1, 0], [-10 * np.sin(a), 11 + 10 * np.cos(a), 0])


def test_mutated_files_parse_or_raise_input_error(tmp_path):
    """Random line and token damage never escapes as anything but InputError."""
    rng = np.random.default_rng(0)
    base = [ln for ln in BASE]
    junk = ["}", "{", "ROOT X", "JOINT", "End Site", "OFFSET", "CHANNELS 9", "MOTION", "Frames: -1",
            "Frame Time:", "1e999", "nan", "", "\t", "x y z"]
    p = tmp_path / "m.bvh"
    outcomes = {"ok": 0, "InputError": 0}
    for _ in range(400):
        lines = list(base)
        for _ in range(rng.integers(1, 4)):
            k = int(rng.integers(0, len(lines)))
            op = rng.integers(0, 4)
            if op == 0 and len(lines) > 1:
                del lines[k]
            elif op == 1:
                lines.insert(k, lines[int(rng.integers(0, len(lines)))])
            elif op == 2:
                lines[k] = str(junk[int(rng.integers(0, len(junk)))])
            else:
                toks = lines[k].split()
                if toks:
                    toks[int(rng.integers(0, len(toks)))] = str(junk[int(rng.integers(0, len(junk)))])
                lines[k] = " ".join(toks)
        p.write_text("\n".join(lines))
        try:
            data = parse_bvh(p)
            fk(data)
            outcomes["ok"] += 1
        except InputError as e:
            assert e.line is not None, str(e)
            outcomes["InputError"] += 1
    assert outcomes["InputError"] > 100


def test_absurd_nesting_is_input_error(tmp_path):
    n = 300
    text = "HIERARCHY\n" + "".join(f"{'ROOT' if k == 0 else 'JOINT'} J{k}\n{{\nOFFSET 0 1 0\nCHANNELS 1 Xrotation\n"
                                   for k in range(n)) + "}\n" * n + "MOTION\nFrames: 1\nFrame Time: 0.1\n" + \
        " ".join(["0"] * n) + "\n"
    with pytest.raises(InputError) as e:
        parse_bvh(write(tmp_path, text))
    assert "deep" in str(e.value) and e.value.line is not None
