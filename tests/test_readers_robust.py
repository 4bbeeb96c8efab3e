"""Issue 15 (a fuzzing pass): the readers' bounds and rules, shared by the command
line and the Blender import.

* epoch timestamps resample like the same take starting at 0; times round-trip exactly;
* a take's ``height_m`` is checked like ``--height`` (0.5-3.0 m);
* bounded duration, gaps, time values and input frame rates, rejected before
  anything the size of the take is allocated; the CSV reader streams;
* one rule for what can be synthesised (``check_take``): something tracked, two 30 Hz frames;
* out-of-range numbers without numpy warnings; symbolic link loops; FIFOs and devices.
"""
import os
import threading
import tracemalloc
import warnings

import numpy as np
import pytest

from conftest import MODELS, SALSA
from support.helpers import assert_bad_input, good_lines, irregular_take, row, run_cli, write_lines
from dancing_points_addon.errors import InputError
from dancing_points_addon.formats.files import read_text
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.formats.bvh import parse_bvh, write_bvh
from dancing_points_addon.formats.limits import MAX_DURATION_S
from dancing_points_addon.inputs import check_take, load_input
from dancing_points_addon.formats.take import COLUMNS, Take, take_from_motion, write_take
from dancing_points_addon.formats.take_read import parse_take_bytes, read_take
from dancing_points_addon.resample import output_times, resample_take
from dancing_points_addon.skeleton import Motion

SAMPLE = os.path.join(os.path.dirname(__file__), "..", "dancing_points_addon", "samples", "sample_take.csv")
EPOCH = 1.7e9  # seconds since 1970: a headset's clock in late 2023


def _shifted(take, dt=EPOCH):
    return Take(take.time + dt, take.positions.copy(), take.quats.copy(), dict(take.meta), "shifted")


@pytest.fixture(scope="module")
def sample():
    return read_take(SAMPLE)


@pytest.fixture(scope="module")
def sample_duet(sample):
    from dancing_points_addon.runtime import Synthesizer
    from dancing_points_addon.synthesis_options import SynthesisOptions
    return Synthesizer(SynthesisOptions(models=MODELS)).synthesize(sample)


# --------------------------------------------------------------------------- 2. epoch timestamps

def test_epoch_times_resample_like_zero_based(sample):
    ref = resample_take(sample)
    out = resample_take(_shifted(sample))
    assert out.n_frames == ref.n_frames == 343
    assert np.abs(out.time - EPOCH - ref.time).max() < 1e-6
    assert np.array_equal(out.valid, ref.valid)
    assert np.nanmax(np.abs(out.positions - ref.positions)) < 1e-6
    assert np.nanmax(np.abs(out.quats - ref.quats)) < 1e-6
    # Irregular rows with gaps: the same too (tolerance on the take's scale, not on |t|).
    take, _ = irregular_take(n=300)
    take.positions[50:60, 1] = np.nan
    take.quats[50:60, 1] = np.nan
    ref, out = resample_take(take), resample_take(_shifted(take))
    assert out.n_frames == ref.n_frames and np.array_equal(out.valid, ref.valid)
    assert np.nanmax(np.abs(out.positions - ref.positions)) < 1e-6
    assert len(output_times(take.time + EPOCH)) == len(output_times(take.time))


def test_epoch_times_synthesize_core_and_cli(sample, sample_duet, tmp_path):
    from dancing_points_addon.runtime import Synthesizer
    from dancing_points_addon.synthesis_options import SynthesisOptions
    duet = Synthesizer(SynthesisOptions(models=MODELS)).synthesize(_shifted(sample))
    assert duet.n_frames == sample_duet.n_frames == 343
    for k in ("leader_positions", "follower_positions"):
        assert np.abs(getattr(duet, k) - getattr(sample_duet, k)).max() < 1e-6, k
    src, out = tmp_path / "epoch.csv", tmp_path / "epoch.npz"
    write_take(src, _shifted(sample))
    res = run_cli("synthesize", src, "-o", out)
    assert res.returncode == 0, res.stderr
    z = np.load(out)
    assert z["time"].shape == (343,) and abs(z["time"][0] - EPOCH) < 1e-6
    # (the take written and read back: its quaternions differ by 5e-11, which the networks,
    # multiplied in float32, carry on to about 0.01 mm of her)
    for k in ("leader_positions", "follower_positions"):
        assert np.abs(z[k] - getattr(sample_duet, k)).max() < 1e-4, k


def test_times_round_trip_exactly(tmp_path):
    take, _ = irregular_take(n=200)
    take = _shifted(take)
    p = tmp_path / "epoch.csv"
    write_take(p, take)
    assert np.array_equal(read_take(p).time, take.time)
    # Through the command line (extract CSV -> CSV), and extract from a 60 Hz AMC: k/60 exactly.
    out = tmp_path / "out.csv"
    res = run_cli("extract", p, "-o", out)
    assert res.returncode == 0, res.stderr
    assert np.array_equal(read_take(out).time, take.time)
    res = run_cli("extract", SALSA / "60_01.amc", "-o", out)
    assert res.returncode == 0, res.stderr
    back = read_take(out)
    assert np.array_equal(back.time, np.arange(back.n_frames) / 60.0)
    # Times that 12 digits represent exactly are written as before.
    t = Take(np.array([0.0, 0.5, 1.25]), np.zeros((3, 3, 3)), np.tile([1.0, 0, 0, 0], (3, 3, 1)))
    write_take(p, t)
    assert [ln.split(",")[0] for ln in p.read_text().splitlines()[1:]] == ["0", "0.5", "1.25"]


# --------------------------------------------------------------------------- 3. height_m

@pytest.mark.parametrize("value", ["1e9", "0.001", "0.49", "3.01", "-1", "inf"])
def test_height_from_file_is_range_checked(tmp_path, value):
    p = write_lines(tmp_path / "h.csv", good_lines(6), comments=(f"# height_m={value}",))
    with pytest.raises(InputError) as ei:
        read_take(p)
    assert ei.value.line == 1 and str(ei.value).startswith(f"{p}:1: ") and "height_m" in str(ei.value)
    out = tmp_path / "out.npz"
    assert_bad_input(run_cli("synthesize", p, "-o", out), out, f"{p}:1: ", "height_m")


def test_height_limits_accepted_and_argument_checked(tmp_path):
    for value in ("0.5", "3.0", "1.78"):
        p = write_lines(tmp_path / "h.csv", good_lines(6), comments=(f"# height_m={value}",))
        assert read_take(p).height == float(value)
    with pytest.raises(InputError, match="between 0.5 and 3 m"):
        load_input(p, height=5.0)
    with pytest.raises(InputError, match="between 0.5 and 3 m"):
        load_input(p, height=0.1)


# --------------------------------------------------------------------------- 4. bounds

def _peak_mb(fn):
    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak / 1e6


@pytest.mark.parametrize("fps", [1e-300, 0.001, 0.5, 5000.0, 1e300])
def test_input_fps_range(tmp_path, fps):
    p = write_lines(tmp_path / "t.csv", good_lines(10))
    for path in (p, SALSA / "60_01.amc"):
        with pytest.raises(InputError, match="between 1 and 1000 Hz"):
            load_input(path, input_fps=fps)
    out = tmp_path / "out.csv"
    assert_bad_input(run_cli("extract", p, "-o", out, "--input-fps", repr(fps)), out, "1000 Hz")


def test_input_fps_limits_accepted(tmp_path):
    p = write_lines(tmp_path / "t.csv", good_lines(100))
    assert np.allclose(np.diff(load_input(p, input_fps=1.0).time), 1.0)
    assert np.allclose(np.diff(load_input(p, input_fps=1000.0).time), 1e-3)


@pytest.fixture(scope="module")
def small_bvh(tmp_path_factory):
    """A valid CMU-named BVH of 10 frames (60 Hz) and its lines."""
    m = load_amc(SALSA / "60_01.amc")
    m = Motion(m.positions[:10], m.rotations[:10], m.fps, m.bone_vectors)
    p = tmp_path_factory.mktemp("bvh") / "small.bvh"
    write_bvh(p, m)
    return p, p.read_text().splitlines()


def _with_line(tmp_path, lines, prefix, new, name="bad.bvh"):
    k = next(i for i, ln in enumerate(lines) if ln.startswith(prefix))
    out = list(lines)
    out[k] = new
    p = tmp_path / name
    p.write_text("\n".join(out) + "\n")
    return p, k + 1


@pytest.mark.parametrize("frame_time", ["1e6", "100", "2", "1e-300", "1e-5"])
def test_bvh_frame_time_range(tmp_path, small_bvh, frame_time):
    p, line = _with_line(tmp_path, small_bvh[1], "Frame Time:", f"Frame Time: {frame_time}")
    with pytest.raises(InputError) as ei:
        parse_bvh(p)
    assert ei.value.line == line and "1000 Hz" in str(ei.value), str(ei.value)
    out = tmp_path / "out.csv"
    assert_bad_input(run_cli("extract", p, "-o", out), out, f"{p}:{line}: ")
    # --input-fps overrides a bad Frame Time.
    assert load_input(p, input_fps=60).n_frames == 10


def test_bvh_declared_length_checked_before_rows(tmp_path, small_bvh):
    p, line = _with_line(tmp_path, small_bvh[1], "Frames:", "Frames: 100000000")
    peak = []

    def run():
        with pytest.raises(InputError) as ei:
            parse_bvh(p)
        peak.append(ei.value)
    mb = _peak_mb(run)
    err = peak[0]
    assert err.line == line + 1 and "4 hours" in str(err), str(err)  # named at the Frame Time line
    assert mb < 20, mb


def _take_lines(times):
    return [row(float(t)) for t in times]


@pytest.mark.parametrize("kind", ["1e300", "-1e300", "1e11", "day gap", "long", "1e300 late"])
def test_time_bounds_rejected_early(tmp_path, kind):
    t = np.arange(20) / 90.0
    if kind in ("1e300", "-1e300", "1e11"):
        t = t + float(kind) if kind != "-1e300" else t - 1e300
        if kind == "-1e300":
            t = -1e300 + np.arange(20) * 1e285
        line, frag = 3, "out of range"
        if kind == "1e300":
            t = 1e300 * (1 + np.arange(20) * 1e-15)
    elif kind == "1e300 late":
        t[7:] = 1e300 * (1 + np.arange(13) * 1e-15)
        line, frag = 3 + 7, "out of range"
    elif kind == "day gap":
        t[12:] += 86400.0
        line, frag = 3 + 12, "gap of 86400 s"
    else:  # 4 h and a bit, one row every 5 s
        t = np.arange(int(MAX_DURATION_S / 5) + 3) * 5.0
        line, frag = 3 + int(MAX_DURATION_S / 5) + 1, "4 hours"
    p = write_lines(tmp_path / "t.csv", _take_lines(t), comments=("# times",))
    errs = []

    def run():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                load_input(p)
        except InputError as e:
            errs.append(e)
    mb = _peak_mb(run)
    assert errs, "accepted"
    assert errs[0].line == line and frag in str(errs[0]), str(errs[0])
    assert mb < 20, mb
    out = tmp_path / "out.npz"
    assert_bad_input(run_cli("synthesize", p, "-o", out), out, f"{p}:{line}: ", frag)


def test_input_fps_duration_bound(tmp_path):
    p = write_lines(tmp_path / "t.csv", good_lines(20))
    with pytest.raises(InputError, match="between 1 and 1000 Hz"):
        load_input(p, input_fps=1e-3)
    # 20 rows at 1 Hz is fine; a take built in memory is checked the same way.
    assert load_input(p, input_fps=1.0).n_frames == 20
    n = 200
    take = Take(np.arange(n) * 100.0, np.zeros((n, 3, 3)), np.tile([1.0, 0, 0, 0], (n, 3, 1)))
    with pytest.raises(InputError, match="gap of 100 s"):
        check_take(take)
    take.time = np.arange(n) * (MAX_DURATION_S / (n - 1) * 1.01)
    with pytest.raises(InputError):
        check_take(take)


def test_csv_reader_streams(tmp_path):
    """Peak memory of reading a take is about its arrays (176 bytes a row),
    below the file's size; the old reader took 5.4 times the file."""
    n = 60_000
    rng = np.random.default_rng(2)
    q = rng.normal(size=(n, 3, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    take = Take(np.arange(n) / 90.0, rng.uniform(-2, 2, (n, 3, 3)), q)
    p = tmp_path / "big.csv"
    write_take(p, take)
    size = p.stat().st_size / 1e6
    out = []
    mb = _peak_mb(lambda: out.append(read_take(p)))
    print(f"\nreading a {size:.1f} MB take: peak {mb:.1f} MB traced ({mb / size:.2f} x the file)")
    assert out[0].n_frames == n and np.array_equal(out[0].time, take.time)
    assert mb < 1.0 * size + 8, (mb, size)
    # Chunk boundaries change nothing: the same take through a 1-chunk parse of the bytes.
    back = parse_take_bytes(p.read_bytes(), str(p))
    assert np.array_equal(back.positions, out[0].positions) and np.array_equal(back.quats, out[0].quats)


def test_chunked_reading_errors_name_the_line(tmp_path, monkeypatch):
    """Errors and line numbers are the same whatever the chunk size (CRLF, comments between rows)."""
    import dancing_points_addon.formats.take_read as T
    lines = good_lines(40)
    lines[10:10] = ["# a comment", ""]
    lines[30] = lines[29]  # equal time: rejected at this line
    p = tmp_path / "t.csv"
    p.write_bytes(("\r\n".join(["# height_m=1.7", ",".join(COLUMNS)] + lines) + "\r\n").encode())
    msgs = set()
    for chunk in (7, 64, 333, 1 << 20):
        monkeypatch.setattr(T, "CHUNK_BYTES", chunk)
        with pytest.raises(InputError) as ei:
            read_take(p)
        msgs.add(str(ei.value))
    assert msgs == {f"{p}:33: time 0.3 is not after the previous row's 0.3 "
                    "(time must increase strictly)"}, msgs
    del lines[30]
    p.write_bytes(("\r".join(["# height_m=1.7", ",".join(COLUMNS)] + lines)).encode())
    takes = []
    for chunk in (5, 100, 1 << 20):
        monkeypatch.setattr(T, "CHUNK_BYTES", chunk)
        takes.append(read_take(p))
    assert all(np.array_equal(t.time, takes[0].time) and t.n_frames == 39 for t in takes)


def test_overlong_line_is_rejected_without_reading_on(tmp_path):
    p = tmp_path / "one_line.csv"
    p.write_bytes(b"time," + b"x" * (3 << 20))
    with pytest.raises(InputError, match="line longer than"):
        read_take(p)


# --------------------------------------------------------------------------- 7. one rule for CLI and Blender

def _all_lost_lines(n=20):
    return [row(i / 90.0, head=("", "", ""), lhand=("", "", ""), rhand=("", "", ""),
                hq=("", "", "", ""), lq=("", "", "", ""), rq=("", "", "", "")) for i in range(n)]


RULES = [
    ("all lost", lambda: _all_lost_lines(), "no tracked samples"),
    ("head never tracked", lambda: [row(i / 90.0, head=("", "", "")) for i in range(20)],
     "the head is lost on every row"),
    ("too short", lambda: good_lines(3), "too short"),
    ("lost at 30 Hz", lambda: [row(0.0, head=("", "", ""), lhand=("", "", ""), rhand=("", "", ""))]
     + good_lines(2)[1:] + [row(0.1 * (k + 2) / 10 + 0.011, head=("", "", ""), lhand=("", "", ""),
                                rhand=("", "", "")) for k in range(8)], "no tracked samples at 30 Hz"),
]


@pytest.mark.parametrize("name,make,frag", RULES, ids=[r[0] for r in RULES])
def test_check_take_rule_on_the_command_line(tmp_path, name, make, frag):
    p = write_lines(tmp_path / "t.csv", make())
    read_take(p)  # a valid take file ...
    with pytest.raises(InputError, match=frag):  # ... that cannot be synthesised
        load_input(p)
    for cmd, out in (("synthesize", tmp_path / "o.npz"), ("extract", tmp_path / "o.csv")):
        assert_bad_input(run_cli(cmd, p, "-o", out), out, str(p), frag)


def test_extract_writes_only_readable_takes(tmp_path):
    """A motion whose points overflow is bad input, never a take the reader rejects."""
    m = load_amc(SALSA / "60_01.amc")
    pos = m.positions[:10].copy()
    pos[4] = 1e308
    take = take_from_motion(Motion(pos, m.rotations[:10], m.fps, m.bone_vectors))
    with pytest.raises(InputError, match="more than 1000 m"):
        check_take(take, "x.amc")


# --------------------------------------------------------------------------- 11. reader robustness

@pytest.mark.parametrize("col,value,frag", [
    ("head_px", "1e308", "head position is out of range"),
    ("lhand_pz", "-1e308", "lhand position is out of range"),
    ("rhand_qx", "1e308", "rhand quaternion is out of range"),
    ("head_qw", "1.7976931348623157e308", "head quaternion is out of range"),
    ("time", "1e308", "out of range"),
])
def test_huge_numbers_rejected_without_warnings(tmp_path, col, value, frag):
    lines = good_lines(8)
    f = lines[5].split(",")
    f[COLUMNS.index(col)] = value
    lines[5] = ",".join(f)
    p = write_lines(tmp_path / "t.csv", lines)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError) as ei:
            load_input(p)
    assert ei.value.line == 4 + 5 and frag in str(ei.value), str(ei.value)
    out = tmp_path / "o.csv"
    res = run_cli("extract", p, "-o", out)
    assert_bad_input(res, out, f"{p}:9: ", frag)
    assert "Warning" not in res.stderr


def test_huge_numbers_in_bvh_and_amc_without_warnings(tmp_path, small_bvh):
    lines = list(small_bvh[1])
    k = next(i for i, ln in enumerate(lines) if ln.startswith("Frame Time:")) + 3
    vals = lines[k].split()
    vals[0] = "1e308"
    vals[5] = "-1e308"
    lines[k] = " ".join(vals)
    p = tmp_path / "huge.bvh"
    p.write_text("\n".join(lines) + "\n")
    out = tmp_path / "o.csv"
    res = run_cli("extract", p, "-o", out)
    assert_bad_input(res, out, str(p), "out of range")
    assert "Warning" not in res.stderr
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="out of range"):
            load_input(p)


def test_symlink_loop(tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    os.symlink(b, a)
    os.symlink(a, b)
    for fn in (load_input, read_take, parse_bvh, read_text):
        with pytest.raises(InputError, match="symbolic link loop"):
            fn(a)
    out = tmp_path / "o.csv"
    assert_bad_input(run_cli("extract", a, "-o", out), out, str(a), "symbolic link loop")
    # A dangling link is "no such file", saying so.
    c = tmp_path / "c.csv"
    os.symlink(tmp_path / "gone.csv", c)
    with pytest.raises(InputError, match="no such file .broken symbolic link"):
        load_input(c)


def _in_thread(fn, timeout=10.0):
    """``fn()``'s exception (or None); fails if it blocks."""
    box = []

    def run():
        try:
            fn()
            box.append(None)
        except BaseException as e:  # noqa: BLE001
            box.append(e)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout)
    assert box, "blocked"
    return box[0]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_fifo_and_devices_rejected_before_opening(tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    for name in ("take.csv", "m.bvh", "60_01.amc", "x.asf"):
        os.mkfifo(d / name)
    for fn, path in ((load_input, d / "take.csv"), (load_input, d / "m.bvh"), (read_take, d / "take.csv"),
                     (parse_bvh, d / "m.bvh"), (read_text, d / "x.asf"),
                     (lambda p: load_input(p, asf=d / "x.asf"), SALSA / "60_01.amc"),
                     (lambda p: load_amc(p, d / "x.asf"), SALSA / "60_01.amc")):
        err = _in_thread(lambda: fn(path))
        assert isinstance(err, InputError) and "not a regular file" in str(err), repr(err)
    zero = d / "zero.csv"
    os.symlink("/dev/zero", zero)
    err = _in_thread(lambda: load_input(zero))
    assert isinstance(err, InputError) and "not a regular file (a device)" in str(err), repr(err)
    out = tmp_path / "o.csv"
    for src in (d / "take.csv", zero):
        assert_bad_input(run_cli("extract", src, "-o", out, timeout=30), out, str(src), "not a regular file")


# --------------------------------------------------------------------------- Blender: the same rules

@pytest.fixture
def blender():
    pytest.importorskip("bpy")
    from support import blender_scene_util as bsu
    from support.ext_util import enable_extension
    enable_extension()
    bsu.fresh_scene()
    return bsu


def _blender_import_error(bsu, path):
    import bpy
    state = bsu.scene_state()
    with pytest.raises(RuntimeError) as ei:
        bpy.ops.dancing_points.import_take(filepath=str(path))
    assert bsu.scene_state() == state
    return str(ei.value)


def test_blender_import_applies_the_core_rules(blender, tmp_path):
    cases = [(name, write_lines(tmp_path / f"{k}.csv", make()), frag) for k, (name, make, frag) in enumerate(RULES)]
    cases.append(("height", write_lines(tmp_path / "h.csv", good_lines(20), comments=("# height_m=1e9",)),
                  "height_m must be between 0.5 and 3 m"))
    lines = good_lines(20)
    lines[12:] = [row(i / 90.0 + 86400.0) for i in range(12, 20)]
    cases.append(("gap", write_lines(tmp_path / "g.csv", lines), "gap of 86400 s"))
    for name, p, frag in cases:
        cli = run_cli("extract", p, "-o", tmp_path / "o.csv")
        assert cli.returncode == 2 and frag in cli.stderr, (name, cli.stderr)
        msg = _blender_import_error(blender, p)
        assert frag in msg, (name, msg)


def test_blender_import_of_epoch_times(blender, sample, tmp_path):
    import bpy
    from support.ext_util import import_from_extension
    take_collection = import_from_extension("operators.take_collection")
    keys = []
    for name, take in (("zero", sample), ("epoch", _shifted(sample))):
        p = tmp_path / f"{name}.csv"
        write_take(p, take)
        before = {c.name for c in bpy.data.collections}
        assert bpy.ops.dancing_points.import_take(filepath=str(p)) == {'FINISHED'}
        (coll,) = [c for c in bpy.data.collections if c.name not in before]
        assert coll.dancing_points.n_frames == 343
        keys.append(take_collection.take_from_collection(bpy.context, coll))
    assert np.array_equal(keys[0].valid, keys[1].valid)
    assert np.nanmax(np.abs(keys[0].positions - keys[1].positions)) < 1e-6
