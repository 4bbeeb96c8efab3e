"""Take files (SPEC §3), extraction from motion and resampling to 30 Hz (SPEC §1)."""
import time as _time

import numpy as np
import pytest

from conftest import SALSA, SOLO
from support.helpers import (IDENT, REJECTIONS, axis_quat, good_lines, irregular_take, quat_angle_deg,
                             row, write_case, write_lines)
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.errors import InputError
from dancing_points_addon.resample import output_times, resample_motion, resample_take
from dancing_points_addon.rotations import (axis_rotation, matrix_to_quat, quat_to_matrix,
                                            rotation_angle)
from dancing_points_addon.skeleton import HEAD_BONE, TRACKED, Motion
from dancing_points_addon.inputs import load_input
from dancing_points_addon.formats.take import COLUMNS, HEAD_DEVICE_OFFSET, Take, take_from_motion, write_take
from dancing_points_addon.formats.take_read import read_take

def random_take(n=50, seed=0, gaps=True):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.008, 0.014, n))
    pos = rng.uniform(-3, 3, (n, 3, 3))
    q = rng.normal(size=(n, 3, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    if gaps:
        pos[7, 1] = np.nan
        q[7, 1] = np.nan
        pos[20:23, 2] = np.nan
        q[20:23, 2] = np.nan
    return Take(t, pos, q, {"height_m": 1.78, "device": "quest3"}, "synthetic")


# --------------------------------------------------------------------------- round trip

def test_write_read_round_trip(tmp_path):
    take = random_take()
    p = tmp_path / "take.csv"
    write_take(p, take)
    back = read_take(p)
    assert back.n_frames == take.n_frames
    assert np.abs(back.time - take.time).max() < 1e-9
    assert np.array_equal(back.valid, take.valid)
    ok = take.valid
    assert np.abs(back.positions[ok] - take.positions[ok]).max() < 1e-6
    assert quat_angle_deg(back.quats[ok], take.quats[ok]).max() < 1e-4
    assert np.isnan(back.positions[~ok]).all() and np.isnan(back.quats[~ok]).all()
    assert back.meta == {"height_m": 1.78, "device": "quest3"}
    assert back.height == 1.78
    # No temporary files are left beside the output.
    assert sorted(x.name for x in tmp_path.iterdir()) == ["take.csv"]


def test_write_is_atomic_and_keeps_old_file_on_error(tmp_path):
    p = tmp_path / "take.csv"
    p.write_text("old content\n")

    class Boom(Take):
        @property
        def n_frames(self):
            raise RuntimeError("boom")

    bad = Boom(np.zeros(2), np.zeros((2, 3, 3)), np.zeros((2, 3, 4)))
    with pytest.raises(RuntimeError):
        write_take(p, bad)
    assert p.read_text() == "old content\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["take.csv"]
    with pytest.raises(InputError, match="output folder does not exist"):
        write_take(tmp_path / "nope" / "take.csv", random_take())


def test_columns_in_any_order_and_crlf(tmp_path):
    take = random_take(gaps=False)
    p = tmp_path / "a.csv"
    write_take(p, take)
    lines = p.read_text().splitlines()
    rng = np.random.default_rng(3)
    perm = rng.permutation(len(COLUMNS))
    out = []
    for ln in lines:
        if ln.startswith("#"):
            out.append(ln)
        else:
            f = ln.split(",")
            out.append(",".join(f[i] for i in perm))
    q = tmp_path / "b.csv"
    q.write_bytes(("\r\n".join(out) + "\r\n").encode())
    back = read_take(q)
    assert np.abs(back.positions - take.positions).max() < 1e-6
    assert np.abs(back.time - take.time).max() < 1e-9


def test_comments_blank_lines_and_spaces(tmp_path):
    lines = ["# height_m = 1.65", "", "  # indented comment, not metadata: a=b c",
             ", ".join(COLUMNS), row(0.0), "", "# mid-file comment", " " + row(0.01).replace(",", " , "),
             row(0.02), "   "]
    p = tmp_path / "c.csv"
    p.write_text("\n".join(lines) + "\n")
    take = read_take(p)
    assert take.n_frames == 3
    assert take.meta["height_m"] == 1.65
    assert np.allclose(take.time, [0, 0.01, 0.02])
    assert take.valid.all()
    # The row after the mid-file comment and blank lines keeps its real line number.
    lines[8] = row(0.02).replace("1.6", "abc", 1)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as ei:
        read_take(p)
    assert ei.value.line == 9


def test_gaps_empty_field_and_nan(tmp_path):
    lines = good_lines(6)
    f = lines[1].split(",")
    f[2] = ""          # head_py empty -> head lost on row 1
    lines[1] = ",".join(f)
    f = lines[2].split(",")
    f[11] = "nan"      # lhand_qw nan -> lhand lost on row 2
    lines[2] = ",".join(f)
    f = lines[3].split(",")
    f[15:22] = [""] * 7  # rhand fully empty (last columns: trailing empties)
    lines[3] = ",".join(f)
    f = lines[4].split(",")
    f[1:8] = ["NaN", "", "nan", "0", "", "", "7"]  # head mixed, bogus quaternion ignored
    lines[4] = ",".join(f)
    f = lines[5].split(",")
    f[9] = " \t "     # lhand_py whitespace only = empty -> lhand lost on row 5
    lines[5] = ",".join(f)
    p = write_lines(tmp_path / "g.csv", lines)
    take = read_take(p)
    expect = np.ones((6, 3), bool)
    expect[1, 0] = expect[2, 1] = expect[3, 2] = expect[4, 0] = expect[5, 1] = False
    assert np.array_equal(take.valid, expect)
    assert np.isnan(take.positions[~expect]).all() and np.isnan(take.quats[~expect]).all()
    assert np.isfinite(take.positions[expect]).all()
    # Quaternions are normalised (a valid, non-unit one).
    lines = good_lines(3)
    lines[1] = row(1 / 90, hq=(0, 0, 1.5, 0))
    take = read_take(write_lines(tmp_path / "n.csv", lines))
    assert np.allclose(take.quats[1, 0], [0, 0, 1, 0])


# --------------------------------------------------------------------------- rejections

@pytest.mark.parametrize("kind", REJECTIONS)
def test_rejections_name_file_and_line(tmp_path, kind):
    p = tmp_path / "bad.csv"
    line, frag = write_case(p, kind)
    with pytest.raises(InputError) as ei:
        read_take(p)
    msg = str(ei.value)
    assert ei.value.line == line, msg
    assert msg.startswith(f"{p}:{line}: "), msg
    assert frag in msg, msg


def test_accepts_limits(tmp_path):
    """Just inside the limits is fine: 999 m, norms 0.5 and 2."""
    L = good_lines(4)
    L[1] = row(1 / 90, head=(999.0, 0.0, 0.0), hq=(0.5, 0, 0, 0), rq=(0, 2.0, 0, 0))
    take = read_take(write_lines(tmp_path / "ok.csv", L))
    assert take.positions[1, 0, 0] == 999.0
    assert np.allclose(take.quats[1, 0], IDENT) and np.allclose(take.quats[1, 2], [0, 1, 0, 0])


def test_other_read_errors(tmp_path):
    with pytest.raises(InputError, match="cannot read file"):
        read_take(tmp_path / "missing.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(InputError, match="empty take file"):
        read_take(tmp_path / "empty.csv")
    (tmp_path / "h.csv").write_text("# height_m=tall\n" + ",".join(COLUMNS) + "\n" + "\n".join(good_lines(3)))
    with pytest.raises(InputError) as ei:
        read_take(tmp_path / "h.csv")
    assert ei.value.line == 1 and "height_m" in str(ei.value)
    # a body offset is checked where it is written, with its line (not later, without one)
    (tmp_path / "o.csv").write_text("# devices=openxr\n# head_offset_m=0,-0.09\n" + ",".join(COLUMNS) + "\n"
                                    + "\n".join(good_lines(3)))
    with pytest.raises(InputError, match="head_offset_m must be three numbers") as ei:
        read_take(tmp_path / "o.csv")
    assert ei.value.line == 2 and "o.csv:2:" in str(ei.value)
    (tmp_path / "b.csv").write_bytes(b"\x00\x01\x02binary")
    with pytest.raises(InputError):
        read_take(tmp_path / "b.csv")


def test_large_file_vectorised(tmp_path):
    """100k rows parse in one go (time printed, not asserted)."""
    n = 100_000
    rng = np.random.default_rng(5)
    t = np.arange(n) / 90.0
    pos = rng.uniform(-2, 2, (n, 3, 3))
    q = rng.normal(size=(n, 3, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    pos[1000, 0] = np.nan
    take = Take(t, pos, q, {"height_m": 1.7})
    p = tmp_path / "big.csv"
    t0 = _time.perf_counter()
    write_take(p, take)
    t1 = _time.perf_counter()
    back = read_take(p)
    t2 = _time.perf_counter()
    size = p.stat().st_size / 1e6
    print(f"\n100k-row take ({size:.1f} MB): write {t1 - t0:.2f} s, read {t2 - t1:.2f} s")
    assert back.n_frames == n and (~back.valid).sum() == 1
    assert np.nanmax(np.abs(back.positions - pos)) < 1e-6


# --------------------------------------------------------------------------- resampling

def test_output_times():
    t = np.array([0.5, 0.6, 0.7, 0.8])
    assert np.allclose(output_times(t, 30.0), 0.5 + np.arange(10) / 30.0)
    t = np.arange(61) / 60.0  # exactly 1 s: the last frame (k = 30) is included
    out = output_times(t, 30.0)
    assert len(out) == 31 and out[-1] == pytest.approx(1.0)
    t = np.arange(60) / 60.0
    assert len(output_times(t, 30.0)) == 30


def test_resample_irregular_take_closed_form():
    take, (A, B, axes, rates) = irregular_take()
    out = resample_take(take, 30.0)
    t0, t1 = take.time[0], take.time[-1]
    k = np.arange(int(np.floor((t1 - t0) * 30)) + 1)
    assert np.allclose(out.time, t0 + k / 30.0, atol=1e-12, rtol=0)
    assert out.time[-1] <= t1
    exp_pos = A[None] + B[None] * out.time[:, None, None]
    pos_err = np.abs(out.positions - exp_pos).max()
    exp_q = np.stack([axis_quat(ax, w * out.time) for ax, w in zip(axes, rates)], axis=1)
    ang_err = quat_angle_deg(out.quats, exp_q).max()
    print(f"\nirregular 90 Hz -> 30 Hz: position {pos_err:.2e} m, angle {ang_err:.2e} deg")
    assert pos_err < 1e-12
    assert ang_err < 1e-5
    assert np.allclose(np.linalg.norm(out.quats, axis=-1), 1.0)
    assert out.meta == take.meta


def test_resample_slerp_midpoint():
    """Half-way between two generic rotations: half the relative angle, shortest arc."""
    q0 = matrix_to_quat(axis_rotation("X", 0.3) @ axis_rotation("Z", -1.1))
    rel = axis_quat((0.2, 0.9, -0.4), 2.6)
    q1 = matrix_to_quat(quat_to_matrix(rel) @ quat_to_matrix(q0))
    q1 = -q1  # the other sign: slerp must still take the short way
    t = np.array([0.0, 1 / 15])
    take = Take(t, np.zeros((2, 3, 3)), np.stack([np.stack([q0] * 3), np.stack([q1] * 3)]))
    out = resample_take(take, 30.0)
    assert out.n_frames == 3
    mid = quat_to_matrix(out.quats[1, 0])
    assert rotation_angle(mid @ quat_to_matrix(q0).T) == pytest.approx(1.3, abs=1e-9)
    assert rotation_angle(quat_to_matrix(q1) @ mid.T) == pytest.approx(1.3, abs=1e-9)


def test_resample_gaps_stay_gaps():
    take, _ = irregular_take(n=120)
    take.positions[10, 1] = np.nan  # lhand lost on one input row
    take.quats[10, 1] = np.nan
    take.positions[40:50, 0] = np.nan  # head lost on ten rows
    take.quats[40:50, 0] = np.nan
    out = resample_take(take, 30.0)
    i = np.searchsorted(take.time, out.time, side="right") - 1
    i = np.clip(i, 0, take.n_frames - 2)
    on_row = np.isclose(out.time, take.time[i], atol=1e-12, rtol=0)
    for d, lost_rows in ((1, {10}), (0, set(range(40, 50)))):
        expect_lost = np.array([(i[k] in lost_rows) or (not on_row[k] and i[k] + 1 in lost_rows)
                                for k in range(out.n_frames)])
        assert expect_lost.any()
        assert np.array_equal(~out.valid[:, d], expect_lost)
    assert out.valid[:, 2].all()
    assert np.isnan(out.positions[~out.valid]).all() and np.isnan(out.quats[~out.valid]).all()
    # An output frame exactly on a tracked row next to a lost row stays tracked.
    t = np.array([0.0, 1 / 30, 1.5 / 30, 2 / 30])
    pos = np.zeros((4, 3, 3))
    q = np.tile(IDENT, (4, 3, 1)).astype(float)
    pos[2, 0] = np.nan
    out = resample_take(Take(t, pos, q), 30.0)
    assert out.n_frames == 3
    assert out.valid[:, 0].tolist() == [True, True, True]
    pos[1, 0] = np.nan
    out = resample_take(Take(t, pos, q), 30.0)
    assert out.valid[:, 0].tolist() == [True, False, True]


# --------------------------------------------------------------------------- extraction

def test_head_device_convention_at_rest():
    """Rest pose (R_head = I, the character facing +Z) -> quaternion (0, 0, 1, 0)."""
    T = 3
    rot = np.broadcast_to(np.eye(3), (T, 31, 3, 3)).copy()
    m = Motion(np.zeros((T, 31, 3)), rot, 60.0, np.zeros((31, 3)))
    take = take_from_motion(m)
    assert np.allclose(take.quats[:, 0], [0, 0, 1, 0])
    assert np.allclose(take.quats[:, 1:], IDENT)
    assert np.allclose(take.time, [0, 1 / 60, 2 / 60])
    # The device looks along local -Z: world forward = +Z at rest.
    assert np.allclose(quat_to_matrix(take.quats[0, 0]) @ [0, 0, -1], [0, 0, 1])
    # A wearer turned 90 deg left (about +Y) looks along +X.
    rot[:, HEAD_BONE] = axis_rotation("Y", np.pi / 2)
    take = take_from_motion(Motion(np.zeros((T, 31, 3)), rot, 60.0, np.zeros((31, 3))))
    assert np.allclose(quat_to_matrix(take.quats[0, 0]) @ [0, 0, -1], [1, 0, 0])


def _check_extraction(amc, step, tmp_path):
    m = load_amc(amc)
    take = take_from_motion(m)
    assert take.n_frames == m.n_frames and np.allclose(np.diff(take.time), 1 / m.fps)
    # Through the file format too.
    p = tmp_path / "take.csv"
    write_take(p, take)
    take = read_take(p)
    out = resample_take(take, 30.0)
    ref = m.subsample(step)
    n = min(out.n_frames, ref.n_frames)
    assert out.n_frames == ref.n_frames
    assert np.allclose(out.time, np.arange(out.n_frames) / 30.0, atol=1e-9)
    pos_err = np.linalg.norm(out.positions[:n] - ref.positions[:n][:, TRACKED], axis=-1).max()
    q_ref = matrix_to_quat(ref.rotations[:n, HEAD_BONE] @ HEAD_DEVICE_OFFSET)
    ang_err = quat_angle_deg(out.quats[:n, 0], q_ref).max()
    hand_err = max(quat_angle_deg(out.quats[:n, 1], matrix_to_quat(ref.rotations[:n, TRACKED[1]])).max(),
                   quat_angle_deg(out.quats[:n, 2], matrix_to_quat(ref.rotations[:n, TRACKED[2]])).max())
    print(f"\n{amc.name} ({m.fps:g} Hz -> 30 Hz, {n} frames): tracked points max {pos_err * 1000:.2e} mm, "
          f"head orientation max {ang_err:.2e} deg, hands {hand_err:.2e} deg")
    assert pos_err < 1e-3
    assert ang_err < 0.5
    assert hand_err < 0.5
    # Head device: the skull's forward (+Z) is the device's -Z.
    fwd = quat_to_matrix(out.quats[:n, 0]) @ np.array([0, 0, -1.0])
    assert np.allclose(fwd, ref.rotations[:n, HEAD_BONE] @ np.array([0, 0, 1.0]), atol=1e-5)


def test_extract_salsa_60hz_to_30hz(tmp_path):
    _check_extraction(SALSA / "60_01.amc", 2, tmp_path)


def test_extract_solo_120hz_to_30hz(tmp_path):
    _check_extraction(SOLO / "05_01.amc", 4, tmp_path)


def test_resample_motion_real_data():
    m = load_amc(SALSA / "60_01.amc")
    r = resample_motion(m, 30.0)
    ref = m.subsample(2)
    assert r.fps == 30.0 and r.n_frames == ref.n_frames
    assert np.abs(r.positions - ref.positions).max() < 1e-9
    assert np.abs(r.rotations - ref.rotations).max() < 1e-9
    # Upsampling to 120 Hz: odd frames are the midpoints of their neighbours.
    up = resample_motion(m, 120.0)
    assert up.n_frames == 2 * m.n_frames - 1
    assert np.abs(up.positions[1::2] - 0.5 * (m.positions[:-1] + m.positions[1:])).max() < 1e-9
    half0 = rotation_angle(np.swapaxes(m.rotations[:-1], -1, -2) @ up.rotations[1::2])
    half1 = rotation_angle(np.swapaxes(up.rotations[1::2], -1, -2) @ m.rotations[1:])
    assert np.abs(half0 - half1).max() < 1e-6
    assert np.allclose(up.rotations @ np.swapaxes(up.rotations, -1, -2), np.eye(3), atol=1e-9)


# --------------------------------------------------------------------------- load_input

def test_load_input_dispatch(tmp_path):
    take = load_input(SALSA / "60_01.amc", height=1.7)
    assert take.meta["height_m"] == 1.7 and np.allclose(np.diff(take.time), 1 / 60)
    take = load_input(SALSA / "60_01.amc", input_fps=30)
    assert np.allclose(np.diff(take.time), 1 / 30)
    take = load_input(SALSA / "60_01.amc", asf=SALSA / "60.asf")
    assert take.n_frames > 1000
    t2, _ = irregular_take()
    p = tmp_path / "t.csv"
    write_take(p, t2)
    take = load_input(p)
    assert np.allclose(take.time, t2.time)
    take = load_input(p, input_fps=72)
    assert np.allclose(take.time, t2.time[0] + np.arange(t2.n_frames) / 72)
    with pytest.raises(InputError, match="no such file"):
        load_input(tmp_path / "missing.amc")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(InputError, match="unsupported input type"):
        load_input(tmp_path / "x.txt")
    with pytest.raises(InputError, match="positive"):
        load_input(p, input_fps=-1)
    with pytest.raises(InputError, match="no such ASF"):
        load_input(SALSA / "60_01.amc", asf=tmp_path / "none.asf")
