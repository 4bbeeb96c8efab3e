"""``python -m dancing_points_addon extract`` as a user runs it (SPEC §7)."""
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, SALSA, SOLO
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.formats.take import take_from_motion, write_take
from dancing_points_addon.formats.take_read import read_take
from support.helpers import (REJECTIONS, assert_bad_input, bad_number, bone_missing, broken_amc, frame_truncated,
                             frames_missing, frames_swapped, non_finite, root_far, irregular_take, quat_angle_deg,
                             run_cli, short_bone, unknown_bone, write_case)


@pytest.fixture(scope="module")
def salsa_motion():
    return load_amc(SALSA / "60_01.amc")


def test_extract_amc(tmp_path, salsa_motion):
    out = tmp_path / "take.csv"
    res = run_cli("extract", SALSA / "60_01.amc", "-o", out, "--height", "1.75")
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""
    take = read_take(out)
    ref = take_from_motion(salsa_motion)
    assert take.n_frames == salsa_motion.n_frames
    assert np.allclose(take.time, ref.time, atol=1e-9)
    assert np.abs(take.positions - ref.positions).max() < 1e-6
    assert quat_angle_deg(take.quats, ref.quats).max() < 1e-4
    assert take.meta == {"height_m": 1.75}
    assert take.valid.all()


def test_extract_amc_options(tmp_path):
    work = tmp_path / "data"
    work.mkdir()
    shutil.copy(SOLO / "05_02.amc", work / "clip.amc")  # no ASF beside it
    out = tmp_path / "t.csv"
    res = run_cli("extract", work / "clip.amc", "-o", out)
    assert_bad_input(res, out, "clip.amc", "--asf")
    res = run_cli("extract", work / "clip.amc", "-o", out, "--asf", SOLO / "05.asf", "--input-fps", "60")
    assert res.returncode == 0, res.stderr
    take = read_take(out)
    ref = load_amc(SOLO / "05_02.amc")
    assert take.n_frames == ref.n_frames
    assert np.allclose(np.diff(take.time), 1 / 60)  # 120 Hz clip declared 60 Hz
    assert np.abs(take.positions[:, 0] - ref.positions[:, 15]).max() < 1e-6
    # a salsa take renamed: its rate is still its subject's (60 Hz, from 60.asf), not the 120 Hz default
    shutil.copy(SALSA / "60.asf", work / "60.asf")
    shutil.copy(SALSA / "60_08.amc", work / "my take.amc")
    res = run_cli("extract", work / "my take.amc", "-o", out)
    assert res.returncode == 0, res.stderr
    assert np.allclose(np.diff(read_take(out).time), 1 / 60)


def test_extract_bvh(tmp_path, salsa_motion):
    from dancing_points_addon.formats.bvh import write_bvh

    bvh = tmp_path / "60_01.bvh"
    write_bvh(bvh, salsa_motion)
    out = tmp_path / "take.csv"
    res = run_cli("extract", bvh, "-o", out)
    assert res.returncode == 0, res.stderr
    take = read_take(out)
    ref = take_from_motion(salsa_motion)
    assert take.n_frames == ref.n_frames
    assert np.allclose(take.time, ref.time, atol=1e-9)
    pos_err = np.linalg.norm(take.positions - ref.positions, axis=-1).max()
    ang_err = quat_angle_deg(take.quats, ref.quats).max()
    print(f"\nBVH round trip: tracked points {pos_err * 1000:.2e} mm, orientations {ang_err:.2e} deg")
    assert pos_err < 1e-3 and ang_err < 0.5
    res = run_cli("extract", bvh, "-o", out, "--input-fps", "120")
    assert res.returncode == 0, res.stderr
    assert np.allclose(np.diff(read_take(out).time), 1 / 120)


def test_extract_csv_input(tmp_path):
    take, _ = irregular_take()
    src = tmp_path / "in.csv"
    write_take(src, take)
    out = tmp_path / "out.csv"
    res = run_cli("extract", src, "-o", out, "--input-fps", "72")
    assert res.returncode == 0, res.stderr
    back = read_take(out)
    assert np.allclose(back.time, take.time[0] + np.arange(take.n_frames) / 72)
    assert np.abs(back.positions - take.positions).max() < 1e-6
    assert back.meta["height_m"] == 1.8


@pytest.mark.parametrize("kind", REJECTIONS)
def test_bad_take_files(tmp_path, kind):
    src = tmp_path / "bad.csv"
    line, frag = write_case(src, kind)
    out = tmp_path / "out.csv"
    msg = assert_bad_input(run_cli("extract", src, "-o", out), out, f"{src}:{line}: ", frag)
    # A pre-existing output survives the failed run byte for byte.
    out.write_bytes(b"precious\n")
    assert assert_bad_input(run_cli("extract", src, "-o", out), out, old=b"precious\n") == msg


@pytest.mark.parametrize("edit", [bad_number, short_bone, unknown_bone, frames_missing, frames_swapped,
                                  frame_truncated, bone_missing, non_finite, root_far])
def test_broken_amc(tmp_path, edit):
    amc, lineno = broken_amc(tmp_path, edit)
    out = tmp_path / "out.csv"
    out.write_bytes(b"keep me")
    assert_bad_input(run_cli("extract", amc, "-o", out), out, f"{amc}:{lineno}: ", old=b"keep me")


def test_bvh_frame_out_of_range_names_its_row(tmp_path, salsa_motion):
    """A BVH frame whose root is far out is refused at that frame's row."""
    from dancing_points_addon.formats.bvh import write_bvh

    bvh = tmp_path / "far.bvh"
    write_bvh(bvh, salsa_motion)
    lines = bvh.read_text().splitlines()
    row = next(k for k, ln in enumerate(lines) if ln.lower().startswith("frame time")) + 1 + 40
    vals = lines[row].split()
    lines[row] = " ".join(["1e30"] + vals[1:])
    bvh.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out.csv"
    assert_bad_input(run_cli("extract", bvh, "-o", out), out, f"{bvh}:{row + 1}: ", "frame 41 is out of range")


def test_garbage_inputs(tmp_path):
    out = tmp_path / "out.csv"
    d = tmp_path / "g"
    d.mkdir()
    shutil.copy(SALSA / "60.asf", d / "60.asf")
    (d / "60_01.amc").write_bytes(bytes(range(256)) * 10)
    assert_bad_input(run_cli("extract", d / "60_01.amc", "-o", out), out, "60_01.amc")
    (d / "x.bvh").write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0\n")
    assert_bad_input(run_cli("extract", d / "x.bvh", "-o", out), out, "x.bvh")
    (d / "x.npz").write_text("?")
    assert_bad_input(run_cli("extract", d / "x.npz", "-o", out), out, "unsupported input type")
    (d / "bin.csv").write_bytes(b"\x00\xff" * 100)
    assert_bad_input(run_cli("extract", d / "bin.csv", "-o", out), out, "bin.csv")


def test_missing_input_and_bad_outputs(tmp_path):
    out = tmp_path / "out.csv"
    assert_bad_input(run_cli("extract", tmp_path / "nope.amc", "-o", out), out, "nope.amc", "no such file")
    amc = SALSA / "60_01.amc"
    bad_dir = tmp_path / "missing" / "out.csv"
    assert_bad_input(run_cli("extract", amc, "-o", bad_dir), bad_dir, "output folder does not exist")
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    under_file = blocker / "out.csv"
    assert_bad_input(run_cli("extract", amc, "-o", under_file), under_file, "output folder does not exist")
    folder = tmp_path / "adir"
    folder.mkdir()
    res = run_cli("extract", amc, "-o", folder)
    assert res.returncode == 2 and len(res.stderr.splitlines()) == 1 and "is a folder" in res.stderr
    assert list(folder.iterdir()) == []
    duet = tmp_path / "duet.npz"  # a take written under another format's name would replace that file
    duet.write_bytes(b"a duet")
    for path, old in ((duet, b"a duet"), (tmp_path / "take", None)):
        assert_bad_input(run_cli("extract", amc, "-o", path), path, "must end in .csv", old=old)
    if sys.platform.startswith("linux"):  # a folder where no file can be made, even by root (sysfs)
        res = run_cli("synthesize", amc, "-o", "/sys/dp_out.npz")
        assert res.returncode == 2 and "/sys/dp_out.npz: output folder is not writable" in res.stderr, res.stderr
        assert "leader tracked" not in res.stdout  # refused before the work, not after it


@pytest.mark.parametrize("args,frag", [
    (["extract"], "required"),
    (["extract", "x.amc"], "-o/--output"),
    (["extract", "x.amc", "-o", "o.csv", "--input-fps", "-3"], "--input-fps"),
    (["extract", "x.amc", "-o", "o.csv", "--input-fps", "abc"], "--input-fps"),
    (["extract", "x.amc", "-o", "o.csv", "--height", "17"], "--height"),
    (["frobnicate"], "invalid choice"),
    ([], "required"),
])
def test_bad_command_lines(tmp_path, args, frag):
    res = run_cli(*args)
    assert res.returncode == 2
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and frag in lines[0], res.stderr
    assert "Traceback" not in res.stderr


def test_help():
    res = run_cli("extract", "--help")
    assert res.returncode == 0
    for opt in ("--input-fps", "--asf", "--height", "-o"):
        assert opt in res.stdout


def test_the_entry_point_loads_no_numpy_before_its_thread_settings():
    """``python -m dancing_points_addon benchmark`` (SPEC §6 latency: one
    thread) sets one BLAS thread before numpy loads; what ``__main__`` imports
    before that (``argtypes`` and the bounds it shares) must not load numpy."""
    code = "import sys, dancing_points_addon.argtypes; print('numpy' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stdout + r.stderr
