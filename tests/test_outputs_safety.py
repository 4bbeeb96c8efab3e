"""Outputs are safe: two batches on one output folder, pairs of files
written both or neither, reports and outputs never over an input, damaged
models named in one line, failed or interrupted writes without a traceback or
a leftover, worker and thread counts bounded, file names printed on one line,
Blender operator errors as their real last line.

Each test states the defect it pins down; all run real processes where the
defect needs them (two concurrent batches, SIGTERM, a file-size limit standing
in for a full disk).
"""
import argparse
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from conftest import MODELS, ROOT, SALSA
from dancing_points_addon import batch, cli, nets
from dancing_points_addon.errors import InputError
from support.helpers import assert_bad_input, run_cli

SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
LOCK = ".dancing_points_batch.lock"  # (batch.LOCK_NAME)

needs_proc = pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs Linux /proc")
needs_posix = pytest.mark.skipif(os.name != "posix", reason="needs POSIX signals and rlimits")


def hidden(folder):
    """Temporary, hidden or ``.part`` files under ``folder``."""
    return sorted(os.path.join(dp, n) for dp, dns, fns in os.walk(folder) for n in fns + dns
                  if n.startswith(".") or ".part" in n or n.endswith("@"))


def dead_pid():
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def file_size_limit(n_bytes):
    """A ``preexec_fn``: writes past ``n_bytes`` fail with EFBIG (a full disk, for one process)."""
    def apply():
        import resource
        resource.setrlimit(resource.RLIMIT_FSIZE, (n_bytes, resource.RLIM_INFINITY))
    return apply


# A stand-in worker (the real protocol): writes a few bytes to each temporary file.
FAKE_WORKER = r"""
import json, sys
P = "@@dancing_points.batch@@ "
print(P + json.dumps({"type": "ready"}), flush=True)
for line in sys.stdin:
    job = json.loads(line)
    for p in job["temps"].values():
        with open(p, "w") as f:
            f.write("converted")
    print(P + json.dumps({"type": "done", "id": job["id"], "frames": 7, "seconds": 0.01}), flush=True)
"""


def fake_args(out, inputs, **kw):
    d = dict(inputs=[str(p) for p in inputs], output_dir=str(out), format="npz", jobs=1, render=False,
             overwrite=False, resume=False, report=None, models=MODELS, threads=1, input_fps=None, asf=None,
             height=None, no_foot_lock=False, no_hand_ik=False, no_progress=True)
    d.update(kw)
    return argparse.Namespace(**d)


def fake_run(args, **kw):
    return batch.run(args, worker_cmd=[sys.executable, "-c", FAKE_WORKER], **kw)


def report_of(path):
    with open(path) as f:
        return json.load(f)


# --------------------------------------------------------------------------- 1. one batch per output folder

def test_second_batch_on_the_same_output_folder_is_refused(tmp_path):
    """Two batches into one folder used the same temporary names (``.NAME.part.EXT``)
    and corrupted each other's outputs (np.load: BadZipFile) while reporting them
    ok. Now the second one is refused at once (one line, exit 2) and the first
    one's outputs are all whole."""
    src = tmp_path / "in"
    src.mkdir()
    for i in range(12):
        shutil.copy(SAMPLE, src / f"t{i + 1:02d}.csv")
    out = tmp_path / "out"
    first = subprocess.Popen([sys.executable, "-m", "dancing_points_addon", "batch", src, "-o", out, "-j1",
                              "--models", MODELS, "--no-progress"], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while not (out / LOCK).exists():
            assert first.poll() is None, first.communicate()
            assert time.monotonic() - t0 < 120, "the first batch never took the lock"
            time.sleep(0.02)
        t1 = time.monotonic()
        second = run_cli("batch", src, "-o", out, "-j1", "--no-foot-lock", "--models", MODELS, "--no-progress")
        overlapped = first.poll() is None
        lines = second.stderr.splitlines()
        assert second.returncode == 2 and len(lines) == 1, (second.returncode, second.stdout, second.stderr)
        assert "another batch" in lines[0] and str(first.pid) in lines[0] and str(out) in lines[0], lines
        assert second.stdout == "" and time.monotonic() - t1 < 60
        assert overlapped, "the first batch ended too soon for this test"
        stdout, stderr = first.communicate(timeout=600)
    finally:
        if first.poll() is None:
            first.kill()
            first.communicate()
    assert first.returncode == 0, (stdout, stderr)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([batch.REPORT_NAME] + [f"t{i + 1:02d}.npz" for i in range(12)]), names
    for i in range(12):
        with np.load(out / f"t{i + 1:02d}.npz") as z:  # every one whole (was: BadZipFile)
            assert z["leader_positions"].shape == (343, 31, 3)
    assert report_of(out / batch.REPORT_NAME)["counts"]["ok"] == 12
    assert not hidden(out), hidden(out)  # the lock is gone with its batch


def test_temporary_names_are_unique_per_process(tmp_path):
    assert batch.temp_path("/o/t.npz", 11) != batch.temp_path("/o/t.npz", 12)
    assert batch.temp_path("/o/t.blend", 11).endswith(".blend")  # the real extension stays last
    task = batch.plan([(str(tmp_path / "t.csv"), "")], str(tmp_path), "npz")[0]
    assert task.temps == [str(tmp_path / f".t.part-{os.getpid()}.npz")]


@needs_posix
def test_lock_of_a_dead_batch_is_taken_over_and_its_temporaries_removed(tmp_path):
    """A batch killed on the spot leaves its lock and its temporary files: the next
    run on that folder takes the lock over and removes those temporaries (of its
    own outputs, from processes no longer running), nothing else."""
    (tmp_path / "a.csv").write_text("x")
    (tmp_path / "b.csv").write_text("x")
    out = tmp_path / "out"
    out.mkdir()
    gone = dead_pid()
    (out / LOCK).write_text(f"{gone}\n")
    stale = [out / f".a.part-{gone}.npz", out / f".a.part-{gone}.npz@"]
    for p in stale:
        p.write_text("partial")
    (out / f".a.part-{gone}.npz.d").mkdir()  # (a writer's folder, as the render's)
    (out / f".a.part-{gone}.npz.d" / "0001-0010.mp4").write_text("frames")
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        live = out / f".b.part-{sleeper.pid}.npz"  # a running process's: not ours to remove
        live.write_text("busy")
        other = out / f".zzz.part-{gone}.npz"  # not an output of this batch
        other.write_text("?")
        rc = fake_run(fake_args(out, [tmp_path / "a.csv", tmp_path / "b.csv"], resume=True),
                      out=io.StringIO(), err=io.StringIO())
        assert rc == 0
        assert not any(p.exists() for p in stale) and not (out / f".a.part-{gone}.npz.d").exists()
        assert live.read_text() == "busy" and other.read_text() == "?"
        assert not (out / LOCK).exists()
        assert (out / "a.npz").read_text() == "converted" and (out / "b.npz").read_text() == "converted"
    finally:
        sleeper.kill()
        sleeper.wait()


@needs_posix
def test_lock_held_by_a_live_process(tmp_path):
    """The lock itself: held, a second acquire is refused naming the holder; released, it is free."""
    from dancing_points_addon.batch.lock import acquire

    with acquire(str(tmp_path)):
        assert (tmp_path / LOCK).read_text().strip() == str(os.getpid())
        code = (f"import sys; sys.path.insert(0, {str(ROOT)!r}); from dancing_points_addon.batch.lock import acquire\n"
                f"try:\n    acquire({str(tmp_path)!r})\nexcept Exception as e:\n    print(e)")
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert f"another batch (process {os.getpid()})" in res.stdout, res.stdout + res.stderr
    assert not (tmp_path / LOCK).exists()
    with acquire(str(tmp_path)):
        pass


# --------------------------------------------------------------------------- 5. pairs: both or neither

def _fail_fsync_of(monkeypatch, fragment):
    """``os.fsync`` fails (no space left) for the file whose name holds ``fragment``."""
    real = os.fsync

    def fsync(fd):
        if fragment in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(28, "No space left on device")
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)


@needs_proc
@pytest.mark.parametrize("existing", [True, False])
def test_bvh_pair_is_written_both_or_neither(tmp_path, monkeypatch, capsys, existing):
    """``synthesize -o X.bvh``: the follower's write fails after the leader's (a full
    disk). Was: a new leader beside the old follower. Now neither is replaced
    (nor created) and nothing is left behind."""
    out = tmp_path / "x.bvh"
    leader, follower = tmp_path / "x_leader.bvh", tmp_path / "x_follower.bvh"
    if existing:
        leader.write_text("old leader")
        follower.write_text("old follower")
    _fail_fsync_of(monkeypatch, "x_follower.bvh")
    rc = cli.main(["synthesize", str(SAMPLE), "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.splitlines()) == 1 and "x_follower.bvh" in err and "No space left" in err, err
    if existing:
        assert leader.read_text() == "old leader" and follower.read_text() == "old follower"
    else:
        assert not leader.exists() and not follower.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["x_follower.bvh", "x_leader.bvh"] if existing else [])
    monkeypatch.undo()
    assert cli.main(["synthesize", str(SAMPLE), "-o", str(out)]) == 0  # replaced: both
    assert leader.read_text().startswith("HIERARCHY") and follower.read_text().startswith("HIERARCHY")


def test_install_all_puts_back_what_it_replaced(tmp_path, monkeypatch):
    """The rename step of a pair (batch commit, the command line): the second rename
    fails, the first output is restored (with --overwrite) or removed (without)."""
    from dancing_points_addon.formats import files

    for replace in (True, False):
        d = tmp_path / str(replace)
        d.mkdir()
        (d / "a").write_text("old a")
        (d / "ta").write_text("new a")
        (d / "tb").write_text("new b")
        real = os.replace

        def failing(src, dst):
            if str(dst).endswith("b"):
                raise OSError(28, "No space left on device")
            return real(src, dst)

        monkeypatch.setattr(os, "replace", failing)
        monkeypatch.setattr(os, "link", lambda *a: (_ for _ in ()).throw(OSError(1, "no links")))
        if not replace:
            (d / "a").unlink()
        with pytest.raises(OSError):
            files.install_all([(str(d / "ta"), str(d / "a")), (str(d / "tb"), str(d / "b"))], replace=replace)
        monkeypatch.undo()
        if replace:
            assert (d / "a").read_text() in ("old a", "new a")  # (no hard links: no backup to restore)
        else:
            assert not (d / "a").exists()
        assert not (d / "b").exists()
    # with hard links the old file comes back
    d = tmp_path / "links"
    d.mkdir()
    for n, t in (("a", "old a"), ("b", "old b"), ("ta", "new a"), ("tb", "new b")):
        (d / n).write_text(t)
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda s, t: (_ for _ in ()).throw(OSError(28, "full"))
                        if str(s).endswith("tb") else real(s, t))
    with pytest.raises(OSError):
        files.install_all([(str(d / "ta"), str(d / "a")), (str(d / "tb"), str(d / "b"))])
    monkeypatch.undo()
    assert (d / "a").read_text() == "old a" and (d / "b").read_text() == "old b"
    assert sorted(p.name for p in d.iterdir()) == ["a", "b", "tb"]  # no backup left; the temporary is the caller's


# --------------------------------------------------------------------------- 6. --report

def test_report_never_over_an_input_or_a_foreign_file(tmp_path):
    """``batch a.csv -o out --report a.csv`` overwrote the take with the report. Now:
    refused before any work; so is an existing file that is not a report
    (unless --overwrite); an earlier report is replaced as before."""
    take = tmp_path / "a.csv"
    shutil.copy(SAMPLE, take)
    old = take.read_bytes()
    out = tmp_path / "out"
    res = run_cli("batch", take, "-o", out, "--report", take, "--models", MODELS)
    assert_bad_input(res, take, "is the input", old=old)
    assert not out.exists()
    res = run_cli("batch", take, "-o", out, "--report", take, "--overwrite", "--models", MODELS)
    assert_bad_input(res, take, "is the input", old=old)  # --overwrite never replaces an input
    notes = tmp_path / "notes.json"
    notes.write_text('{"my": "notes"}')
    res = run_cli("batch", take, "-o", out, "--report", notes, "--models", MODELS)
    assert_bad_input(res, notes, "not a Dancing Points batch report", "--overwrite", old=b'{"my": "notes"}')
    assert not out.exists()
    # in-process (fake workers): an earlier report is replaced; a foreign file with --overwrite
    rep = tmp_path / "rep.json"
    assert fake_run(fake_args(out, [take], report=str(rep)), out=io.StringIO()) == 0
    assert batch.is_report(rep)
    assert fake_run(fake_args(out, [take], report=str(rep), overwrite=True), out=io.StringIO()) == 0
    assert fake_run(fake_args(out, [take], report=str(notes), overwrite=True), out=io.StringIO()) == 0
    assert batch.is_report(notes) and take.read_bytes() == old
    with pytest.raises(InputError, match="one of the outputs"):
        fake_run(fake_args(tmp_path / "o2", [take], report=str(tmp_path / "o2" / "a.npz")))


# --------------------------------------------------------------------------- 8. models

@pytest.fixture
def bad_models(tmp_path):
    """``bad_models(kind)``: a models folder with one damaged network; returns (folder, the bad file)."""

    def make(kind):
        d = tmp_path / f"models_{kind}"
        d.mkdir()
        for f in nets.MODEL_FILES.values():
            shutil.copy(os.path.join(MODELS, f), d / f)
        bad = d / nets.MODEL_FILES["leader"]
        if kind == "old folder":  # made before the contact network: the message names what is missing
            (d / nets.MODEL_FILES["contacts"]).unlink()
            return d, "missing contacts.onnx"
        if kind == "contacts without floors":  # loads, takes the mapping's input, but has no floor levels
            bad = d / nets.MODEL_FILES["contacts"]
            shutil.copy(os.path.join(MODELS, nets.MODEL_FILES["mapping"]), bad)
            return d, bad
        if kind == "empty":
            bad.write_bytes(b"")
        elif kind == "truncated":
            bad.write_bytes(bad.read_bytes()[:100_000])
        else:  # another network: loads, but is not the leader tracker
            shutil.copy(os.path.join(MODELS, nets.MODEL_FILES["mapping"]), bad)
        return d, bad

    return make


@pytest.mark.parametrize("kind", ["empty", "truncated", "foreign", "old folder", "contacts without floors"])
def test_synthesize_names_the_bad_model_file(tmp_path, bad_models, kind):
    """A damaged model gave exit 1 and ONNX Runtime's (or a ValueError's) text. Now
    one line naming the file, exit 2, through --models and $DP_MODEL_DIR alike."""
    models, bad = bad_models(kind)
    out = tmp_path / "duet.npz"
    assert_bad_input(run_cli("synthesize", SAMPLE, "-o", out, "--models", models), out, str(bad))
    env = dict(os.environ, DP_MODEL_DIR=str(models))
    res = subprocess.run([sys.executable, "-m", "dancing_points_addon", "synthesize", str(SAMPLE), "-o", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert_bad_input(res, out, str(bad))  # synthesize honours $DP_MODEL_DIR


@pytest.mark.parametrize("kind", ["empty", "truncated"])
def test_batch_checks_the_models_once_at_start_up(tmp_path, bad_models, kind):
    """A batch ran every file against a damaged model (each failing, exit 1). Now it
    stops at start-up: one line naming the file, exit 2, nothing made."""
    models, bad = bad_models(kind)
    src = tmp_path / "in"
    src.mkdir()
    for i in range(3):
        shutil.copy(SAMPLE, src / f"t{i}.csv")
    out = tmp_path / "out"
    res = run_cli("batch", src, "-o", out, "--models", models, "--no-progress")
    lines = res.stderr.splitlines()
    assert res.returncode == 2 and len(lines) == 1 and str(bad) in lines[0], (res.returncode, res.stderr)
    assert res.stdout == "" and "Traceback" not in res.stderr and not out.exists()


# --------------------------------------------------------------------------- 9. failed and stopped writes

@needs_posix
@pytest.mark.parametrize("existing", [False, True])
def test_failed_npz_write_is_one_line_and_leaves_nothing(tmp_path, existing):
    """A full disk (here: a file-size limit) during the npz write printed the error
    and then ``Exception ignored in ZipFile.__del__ ... Traceback``. Now one line."""
    out = tmp_path / "duet.npz"
    if existing:
        out.write_bytes(b"old")
    res = subprocess.run([sys.executable, "-m", "dancing_points_addon", "synthesize", str(SAMPLE), "-o", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=120, preexec_fn=file_size_limit(200_000))
    assert_bad_input(res, out, "cannot write output", old=b"old" if existing else None)
    assert "Exception ignored" not in res.stderr and not hidden(tmp_path)


@needs_posix
def test_failed_npz_write_in_a_batch_worker(tmp_path):
    """The same in a batch worker (``write_duet_files``): the take fails with one
    reason and the worker's log holds no ``Exception ignored``."""
    out = tmp_path / "out"
    env = dict(os.environ, DP_DEBUG="1")  # keep the worker logs
    res = subprocess.run([sys.executable, "-m", "dancing_points_addon", "batch", str(SAMPLE), "-o", str(out),
                          "--models", MODELS, "--no-progress"], cwd=ROOT, capture_output=True, text=True,
                         timeout=300, env=env, preexec_fn=file_size_limit(200_000))
    assert res.returncode == 1, (res.stdout, res.stderr)
    r = report_of(out / batch.REPORT_NAME)["files"][0]
    assert r["status"] == "failed" and f"{out}: cannot write output (File too large)" in r["error"], r
    logs = [ln.split("worker logs: ", 1)[1] for ln in res.stderr.splitlines() if ln.startswith("worker logs: ")]
    assert logs, res.stderr
    try:
        text = "".join(open(os.path.join(logs[0], f), errors="replace").read() for f in os.listdir(logs[0]))
        assert "Exception ignored" not in text, text
    finally:
        shutil.rmtree(logs[0], ignore_errors=True)
    assert sorted(p.name for p in out.iterdir()) == [batch.REPORT_NAME]


# The command line in a process that sends itself SIGTERM in the middle of a write.
SELF_TERM = """
import os, signal, sys
sys.path.insert(0, {root!r})
import numpy.lib.format as fmt
import dancing_points_addon.formats.bvh as bvh
from dancing_points_addon import cli
calls = [0]
real_write_array, real_bvh_text = fmt.write_array, bvh.bvh_text
def write_array(*a, **k):
    calls[0] += 1
    if calls[0] == 3:
        os.kill(os.getpid(), signal.SIGTERM)
    return real_write_array(*a, **k)
def bvh_text(motion):
    text = real_bvh_text(motion)
    if motion.source == "follower":
        os.kill(os.getpid(), signal.SIGTERM)
    return text
fmt.write_array, bvh.bvh_text = write_array, bvh_text
sys.exit(cli.main(sys.argv[1:]))
"""


@needs_posix
@pytest.mark.parametrize("name", ["duet.npz", "duet.bvh"])
def test_sigterm_during_a_write_leaves_no_part_file(tmp_path, name):
    """SIGTERM in the middle of the command line's write killed it with the hidden
    ``.part`` file left. Now it unwinds like Ctrl-C: no temporary file, the old
    outputs untouched, ``error: terminated``, exit 143."""
    out = tmp_path / name
    olds = [out] if name.endswith(".npz") else [tmp_path / "duet_leader.bvh", tmp_path / "duet_follower.bvh"]
    for p in olds:
        p.write_text("old")
    res = subprocess.run([sys.executable, "-c", SELF_TERM.format(root=str(ROOT)), "synthesize", str(SAMPLE),
                          "-o", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 143, (res.returncode, res.stderr)
    assert res.stderr.splitlines() == ["error: terminated"], res.stderr
    assert not hidden(tmp_path), hidden(tmp_path)
    assert all(p.read_text() == "old" for p in olds)


@needs_posix
def test_sigterm_from_outside_mid_run(tmp_path):
    """A real ``python -m dancing_points_addon synthesize`` sent SIGTERM while it works."""
    out = tmp_path / "duet.npz"
    proc = subprocess.Popen([sys.executable, "-m", "dancing_points_addon", "synthesize", str(SAMPLE), "-o", str(out)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(0.5)  # loading the take or the networks, or synthesising
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip("the synthesis finished before the signal")
    assert proc.returncode == 143, (proc.returncode, stderr)
    assert stderr.splitlines() == ["error: terminated"] and not out.exists() and not hidden(tmp_path)


@needs_posix
def test_sigterm_swallowed_by_a_library_import_still_ends_as_terminated(tmp_path, monkeypatch):
    """SIGTERM while onnxruntime's C extension imports came back as a bare ImportError,
    and the command said ``onnxruntime is not installed`` (exit 2). The handler now
    remembers the signal: ``error: terminated``, exit 143, nothing written."""
    out = tmp_path / "duet.npz"

    def importing_onnxruntime(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)  # the handler runs here and raises Terminated
        except KeyboardInterrupt:
            pass  # what the extension's import does with it
        raise ImportError("")

    monkeypatch.setattr(nets, "_CACHE", {})  # (networks loaded by earlier tests)
    monkeypatch.setattr(nets, "OnnxNet", importing_onnxruntime)
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    rc = cli.main(["synthesize", str(SAMPLE), "-o", str(out)])
    assert rc == 143, err.getvalue()
    assert err.getvalue().splitlines() == ["error: terminated"]
    assert not out.exists() and not hidden(tmp_path)
    assert cli._on_signal not in (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT))  # put back


@needs_posix
@pytest.mark.parametrize("sig, rc, line", [("SIGTERM", 143, "error: terminated"),
                                           ("SIGINT", 130, "error: interrupted")])
def test_a_signal_during_an_import_waits_for_the_import(tmp_path, monkeypatch, sig, rc, line):
    """SIGTERM or Ctrl-C landing while a module imports is raised only once the import
    has finished (within a few 50 ms retries), so no extension sees it half-loaded."""
    out = tmp_path / "duet.npz"
    (tmp_path / "slow_extension.py").write_text(
        f"import os, signal, time\nos.kill(os.getpid(), signal.{sig})\ntime.sleep(0.3)\nLOADED = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "slow_extension", raising=False)
    seen = {}

    def loading_networks(*args, **kwargs):
        import slow_extension
        seen["loaded"] = slow_extension.LOADED
        time.sleep(2.0)  # the signal, sent again, is raised here
        seen["slept"] = True

    monkeypatch.setattr(nets, "_CACHE", {})  # (networks loaded by earlier tests)
    monkeypatch.setattr(nets, "OnnxNet", loading_networks)
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    assert cli.main(["synthesize", str(SAMPLE), "-o", str(out)]) == rc, err.getvalue()
    assert err.getvalue().splitlines() == [line]
    assert seen == {"loaded": True} and not out.exists() and not hidden(tmp_path)


# --------------------------------------------------------------------------- 11. bounds, names, inputs

def test_jobs_capped_at_the_files_and_warned_above_the_cores(tmp_path, monkeypatch):
    """``--jobs 1000`` started a process per file, silently. Now the workers are capped
    at the files and one warning line says when that is more than the cores."""
    names = ["a.csv", "b.csv", "c.csv"]
    for n in names:
        (tmp_path / n).write_text("x")
    monkeypatch.setattr(batch, "default_jobs", lambda: 2)
    err = io.StringIO()
    rc = fake_run(fake_args(tmp_path / "out", [tmp_path / n for n in names], jobs=1000), out=io.StringIO(), err=err)
    assert rc == 0
    assert report_of(tmp_path / "out" / batch.REPORT_NAME)["jobs"] == 3
    warn = [ln for ln in err.getvalue().splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "--jobs 1000" in warn[0] and "3 worker processes on 2 cores" in warn[0], err.getvalue()
    err = io.StringIO()  # at or below the cores: no warning
    assert fake_run(fake_args(tmp_path / "out2", [tmp_path / n for n in names[:2]], jobs=1000),
                    out=io.StringIO(), err=err) == 0
    assert "warning" not in err.getvalue()


@pytest.mark.parametrize("args", [["synthesize", "{sample}", "-o", "{tmp}/o.npz", "--threads", "65"],
                                  ["benchmark", "--threads", "1000"],
                                  ["batch", "{sample}", "-o", "{tmp}/o", "--threads", "100000"]])
def test_threads_have_an_upper_bound(tmp_path, args):
    """``--threads`` took any number (ONNX Runtime then made that many threads)."""
    res = run_cli(*[a.format(sample=SAMPLE, tmp=tmp_path) for a in args], timeout=60)
    lines = res.stderr.splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "at most 64" in lines[0], res.stderr
    assert list(tmp_path.iterdir()) == []


@needs_posix
def test_file_names_with_control_characters_stay_on_one_line(tmp_path):
    """Names with a newline, an escape code or bytes that are no UTF-8 were printed
    raw: broken result lines, a recoloured terminal, or a crash on the
    undecodable name. Now escaped, one result line per file."""
    src = tmp_path / "in"
    src.mkdir()
    for name in ("new\nline.csv", "esc\x1b[31mred.csv"):
        (src / name).write_text("not a take\n")
    with open(os.path.join(os.fsencode(src), b"bytes\xff.csv"), "w") as f:
        f.write("not a take\n")
    out = tmp_path / "out"
    res = run_cli("batch", src, "-o", out, "--models", MODELS, "-j1", timeout=300)
    assert res.returncode == 1, (res.returncode, res.stdout, res.stderr)
    lines = res.stdout.splitlines()
    assert len(lines) == 4 and all(ln.startswith("FAILED ") for ln in lines[:3]), res.stdout
    assert "\x1b" not in res.stdout + res.stderr and "Traceback" not in res.stderr
    text = "\n".join(lines)
    assert "new\\nline.csv" in text and "esc\\x1b[31mred.csv" in text and "bytes\\udcff.csv" in text, text
    assert report_of(out / batch.REPORT_NAME)["counts"]["failed"] == 3


def test_result_lines_in_completion_order_report_in_input_order(tmp_path):
    """As documented (batch --help, batch/progress.py, README): a line per file as it
    finishes (the largest files go first), the report in input order."""
    for n, size in (("a.csv", 1), ("b.csv", 300), ("c.csv", 20)):
        (tmp_path / n).write_text("x" * size)
    out = io.StringIO()
    assert fake_run(fake_args(tmp_path / "out", [tmp_path / n for n in ("a.csv", "b.csv", "c.csv")]), out=out) == 0
    done = [os.path.basename(ln.split()[1]) for ln in out.getvalue().splitlines()[:-1]]
    assert done == ["b.csv", "c.csv", "a.csv"]
    files = report_of(tmp_path / "out" / batch.REPORT_NAME)["files"]
    assert [os.path.basename(r["input"]) for r in files] == ["a.csv", "b.csv", "c.csv"]
    assert "as it finishes" in run_cli("batch", "--help").stdout.replace("\n", " ").replace("  ", " ")


@pytest.fixture(scope="module")
def leader_bvh(tmp_path_factory):
    """A real full-body BVH named like a synthesize output (``take_leader.bvh``)."""
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.formats.bvh import write_bvh
    from dancing_points_addon.skeleton import Motion

    m = load_amc(SALSA / "60_01.amc")
    d = tmp_path_factory.mktemp("bvh_in")
    write_bvh(d / "take_leader.bvh", Motion(m.positions[:240], m.rotations[:240], m.fps, m.bone_vectors, m.source))
    return d / "take_leader.bvh"


def test_synthesize_never_writes_over_its_input(tmp_path, leader_bvh):
    """``synthesize a_leader.bvh -o a.bvh`` replaced its own input with the synthesised
    leader. Now refused before any work; other existing outputs are still replaced."""
    src = tmp_path / "take_leader.bvh"
    shutil.copy(leader_bvh, src)
    old = src.read_bytes()
    res = run_cli("synthesize", src, "-o", tmp_path / "take.bvh")
    assert_bad_input(res, src, "is the input file", old=old)
    assert not (tmp_path / "take_follower.bvh").exists()
    link = tmp_path / "link.npz"  # the same file under another name
    os.link(src, link)
    assert_bad_input(run_cli("synthesize", src, "-o", link), link, "is the input file", old=old)


def test_extract_never_writes_over_its_input(tmp_path):
    take = tmp_path / "take.csv"
    shutil.copy(SAMPLE, take)
    old = take.read_bytes()
    assert_bad_input(run_cli("extract", take, "-o", take), take, "is the input file", old=old)
    alias = tmp_path / "alias.csv"
    alias.symlink_to(take)
    assert_bad_input(run_cli("extract", take, "-o", alias), alias, "is the input file", old=old)
    other = tmp_path / "other.csv"  # an existing output that is no input: replaced, as documented
    other.write_text("old")
    res = run_cli("extract", take, "-o", other)
    assert res.returncode == 0, res.stderr
    assert other.read_text() != "old"


def test_batch_never_writes_over_an_input(tmp_path, leader_bvh):
    """Outputs into the input folder: ``take.csv`` -> ``take_leader.bvh`` is the input
    ``take_leader.bvh`` (which --overwrite replaced). Now refused before any work."""
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(SAMPLE, src / "take.csv")
    shutil.copy(leader_bvh, src / "take_leader.bvh")
    old = (src / "take_leader.bvh").read_bytes()
    for extra in ([], ["--overwrite"], ["--resume"]):
        res = run_cli("batch", src, "-o", src, "--format", "bvh", "--models", MODELS, *extra)
        assert_bad_input(res, src / "take_leader.bvh", "is the input", old=old)
        assert sorted(p.name for p in src.iterdir()) == ["take.csv", "take_leader.bvh"]


# --------------------------------------------------------------------------- 11. Blender's FBX error text

def test_fbx_export_error_is_its_real_last_line(tmp_path):
    """A failed FBX export was reported as ``Python: Traceback (most recent call
    last):`` (the first line), and the last line is Blender's ``Location: ...``:
    the reason is the exception's own line."""
    pytest.importorskip("bpy")
    code = textwrap.dedent(f"""
        import importlib, json, sys
        sys.path.insert(0, {str(ROOT / 'tests')!r})
        import bpy
        from support.ext_util import enable_extension
        mod = enable_extension()
        batch_cli = importlib.import_module(mod + ".operators.batch_cli")
        bpy.ops.wm.read_homefile(use_empty=True)
        bpy.ops.object.armature_add()
        try:
            bpy.ops.export_scene.fbx(filepath={str(tmp_path / 'missing' / 'x.fbx')!r}, check_existing=False)
            print("\\nRESULT " + json.dumps(None))
        except RuntimeError as exc:
            print("\\nRESULT " + json.dumps([str(exc), str(batch_cli._op_error(exc, "take.csv"))]))
        """)
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    found = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")]
    assert found, res.stdout[-3000:] + res.stderr[-3000:]
    got = json.loads(found[-1][len("RESULT "):])
    assert got is not None, "the export did not fail"
    raw, msg = got
    assert "Traceback" in raw  # what Blender gives
    assert msg.startswith("take.csv: FileNotFoundError:") and "x.fbx" in msg, msg
    assert "Traceback" not in msg and "Location" not in msg and "\n" not in msg


@pytest.mark.skipif(os.name != "posix", reason="the folder lock is an flock (POSIX)")
def test_a_pair_of_outputs_is_installed_under_a_folder_lock(tmp_path):
    """Two runs writing the same pair (``-o x.bvh``: x_leader.bvh, x_follower.bvh)
    could leave one run's leader beside the other's follower (4 of 400 rounds
    of a stress test). The pair is installed under a lock on its folder: while
    another process holds it, nothing is installed; then the whole pair is."""
    import fcntl

    pair = [tmp_path / "x_leader.bvh", tmp_path / "x_follower.bvh"]
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from dancing_points_addon.formats.files import atomic_outputs
        atomic_outputs([({str(pair[0])!r}, lambda f: f.write("B")), ({str(pair[1])!r}, lambda f: f.write("B"))])
    """)
    fd = os.open(tmp_path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        proc = subprocess.Popen([sys.executable, "-c", code])
        time.sleep(1.5)
        assert proc.poll() is None and not any(p.exists() for p in pair)  # waiting for the lock
    finally:
        os.close(fd)
    assert proc.wait(timeout=60) == 0
    assert [p.read_text() for p in pair] == ["B", "B"]
