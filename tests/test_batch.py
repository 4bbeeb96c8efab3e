"""Headless batch conversion (``python -m dancing_points_addon batch`` and
``blender --command dancing_points convert``), as a user runs it.

A folder of real takes (CSV, BVH and AMC cut from the CMU salsa data, some in
sub-folders) plus broken files is converted to each format on two workers; the
good outputs load back (npz: SPEC §4; BVH: re-imported; .blend opened and
.fbx imported by Blender in a fresh process), the broken files are in the report
with their reason. Existing outputs are never overwritten without
``--overwrite``; ``--resume`` skips them; a run stopped with SIGINT / SIGTERM
(or a worker killed) leaves no partial file, and ``--resume`` finishes the rest.

The throughput figure (``--jobs 2`` vs ``--jobs 1``) is a benchmark, not a
test: ``.venv/bin/python benchmarks/bench_batch.py``.
"""
import argparse
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import MODELS, ROOT
from support.helpers import (N60, cut, leftovers, make_takes, proc_table, read_report, run_batch, run_bpy_script,
                             run_cli_long as run_cli)
from dancing_points_addon import batch
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.formats.bvh import load_bvh
from dancing_points_addon.skeleton import JOINT_NAMES
from dancing_points_addon.formats.take import take_from_motion, write_take

N30 = N60 // 2


# input (relative) -> output base (relative); and input -> a fragment of its failure reason
GOOD = {"a.csv": "a", "c.csv": "c", "sub/b.bvh": "sub/b", "amc/60_03.amc": "amc/60_03"}
BAD = {"broken.csv": "unknown header column", "sub/trunc.bvh": "trunc.bvh", "noasf/61_09.amc": "ASF",
       "empty.csv": "empty.csv"}


# --------------------------------------------------------------------------- helpers

def by_input(report, root):
    return {os.path.relpath(r["input"], root): r for r in report["files"]}


# --------------------------------------------------------------------------- data

@pytest.fixture(scope="module")
def takes(tmp_path_factory, salsa_dir):
    """A folder of real takes (CSV, BVH, AMC; sub-folders) plus broken and ignored files."""
    return make_takes(tmp_path_factory.mktemp("takes"), salsa_dir)


_RUNS = {}


@pytest.fixture(scope="module")
def converted(takes, tmp_path_factory):
    """``converted(fmt)``: the folder converted to ``fmt`` on 2 workers (once per format)."""

    def get(fmt):
        if fmt not in _RUNS:
            out = tmp_path_factory.mktemp("out_" + fmt)
            t0 = time.perf_counter()
            res = run_batch(takes, out, fmt)
            dt = time.perf_counter() - t0
            print(f"\nbatch --format {fmt} --jobs 2: {len(GOOD)} takes + {len(BAD)} broken in {dt:.2f} s")
            _RUNS[fmt] = (out, res)
        return _RUNS[fmt]

    yield get
    _RUNS.clear()


def check_run(takes, out, res, fmt):
    """Exit 1, every file in the report (good ones ok, bad ones with their reason),
    one result line per file, no traceback, no temporary files."""
    assert res.returncode == 1, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stdout + res.stderr, res.stderr
    report = read_report(out)
    assert report["format"] == fmt and report["interrupted"] is False
    files = by_input(report, takes)
    assert set(files) == set(GOOD) | set(BAD), sorted(files)
    assert report["counts"]["ok"] == len(GOOD) and report["counts"]["failed"] == len(BAD)
    suffix = {"npz": [".npz"], "blend": [".blend"], "fbx": [".fbx"],
              "bvh": ["_leader.bvh", "_follower.bvh"]}[fmt]
    for rel, base in GOOD.items():
        r = files[rel]
        assert r["status"] == "ok" and r["error"] is None, r
        assert r["frames"] == N30 and r["seconds"] > 0, r
        assert r["outputs"] == [str(out / (base + s)) for s in suffix] and r["output"] == r["outputs"][0]
        assert all(os.path.isfile(p) for p in r["outputs"])
    for rel, why in BAD.items():
        r = files[rel]
        assert r["status"] == "failed" and why in r["error"], r
        assert "\n" not in r["error"]
        assert not any(os.path.exists(p) for p in r["outputs"]), r
    lines = res.stdout.splitlines()
    assert len(lines) == len(GOOD) + len(BAD) + 1, res.stdout  # one per file + the summary
    assert sum(ln.startswith("ok ") for ln in lines) == len(GOOD)
    assert sum(ln.startswith("FAILED ") for ln in lines) == len(BAD)
    for ln in lines:  # each failure names its input once, with the reader's line where it has one
        if ln.startswith("FAILED "):
            path = ln[len("FAILED "):].lstrip().split(":", 1)[0]
            assert os.path.isabs(path) and ln.count(path) == 1, ln
    assert lines[-1].startswith(f"{len(GOOD) + len(BAD)} file(s): {len(GOOD)} ok, {len(BAD)} failed")
    assert not leftovers(out), leftovers(out)
    produced = sorted(os.path.relpath(os.path.join(dp, f), out) for dp, _, fs in os.walk(out) for f in fs)
    assert produced == sorted([batch.REPORT_NAME] + [b + s for b in GOOD.values() for s in suffix])
    return files


# --------------------------------------------------------------------------- each format

def test_npz(takes, converted):
    out, res = converted("npz")
    files = check_run(takes, out, res, "npz")
    for rel, base in GOOD.items():
        with np.load(out / (base + ".npz")) as z:
            assert set(z.files) == {"fps", "time", "joint_names", "leader_positions", "follower_positions",
                                    "leader_rotations", "follower_rotations", "leader_contacts",
                                    "follower_contacts", "tracked_role", "height_m", "height_source", "floor_y",
                                    "floor_source", "devices", "orientations_followed", "device_turns"}
            assert str(z["tracked_role"]) == "leader" and str(z["height_source"]) == "estimated"
            T = files[rel]["frames"]
            assert float(z["fps"]) == 30.0 and z["fps"].shape == ()
            assert np.allclose(z["time"], z["time"][0] + np.arange(T) / 30.0)
            assert list(z["joint_names"]) == list(JOINT_NAMES)
            for role in ("leader", "follower"):
                pos, rot, con = z[role + "_positions"], z[role + "_rotations"], z[role + "_contacts"]
                assert pos.shape == (T, 31, 3) and rot.shape == (T, 31, 3, 3) and con.shape == (T, 4)
                assert np.isfinite(pos).all() and np.isfinite(rot).all()
                assert np.allclose(rot @ np.swapaxes(rot, -1, -2), np.eye(3), atol=1e-5)
                assert ((con >= 0) & (con <= 1)).all()
                assert 0.5 < np.median(pos[:, JOINT_NAMES.index("head"), 1]) < 2.5  # Y up, metres
    # The same arrays as the single-file command.
    res = run_cli("synthesize", takes / "sub" / "b.bvh", "-o", out / "single.npz", "--models", MODELS)
    assert res.returncode == 0, res.stderr
    with np.load(out / "single.npz") as a, np.load(out / "sub" / "b.npz") as b:
        for k in a.files:
            assert np.array_equal(a[k], b[k]), k
    (out / "single.npz").unlink()


def test_bvh(takes, converted):
    out, res = converted("bvh")
    files = check_run(takes, out, res, "bvh")
    npz_out, _ = converted("npz")
    for rel, base in GOOD.items():
        with np.load(npz_out / (base + ".npz")) as z:
            ref = {r: (z[r + "_positions"], z[r + "_rotations"]) for r in ("leader", "follower")}
        for role in ("leader", "follower"):
            m = load_bvh(out / f"{base}_{role}.bvh")  # re-import with the core BVH reader
            assert m.n_frames == files[rel]["frames"] and m.fps == pytest.approx(30.0)
            assert m.positions.shape == (N30, 31, 3)
            # The same duet as the npz run (deterministic): root path and bone rotations.
            assert np.abs(m.positions[:, 0] - ref[role][0][:, 0]).max() < 1e-6, (rel, role)
            assert np.abs(m.rotations - ref[role][1]).max() < 1e-5, (rel, role)
    # Blender's own BVH importer reads them too: 31 joints, one key per frame.
    paths = [str(out / f"{b}_{r}.bvh") for b in GOOD.values() for r in ("leader", "follower")]
    got = run_bpy_script(f"""
        import json, bpy
        res = []
        for path in {paths!r}:
            bpy.ops.wm.read_homefile(use_empty=True)
            assert bpy.ops.import_anim.bvh(filepath=path, update_scene_fps=True) == {{'FINISHED'}}
            arm = bpy.context.object
            res.append([len(arm.data.bones), [int(round(x)) for x in arm.animation_data.action.frame_range],
                        bpy.context.scene.render.fps])
        print("RESULT " + json.dumps(res))
        """)
    for bones, (f0, f1), fps in got:
        assert bones == 31 and f1 - f0 + 1 == N30 and fps == 30, (bones, f0, f1, fps)
    # Byte for byte what the single-file command writes.
    res = run_cli("synthesize", takes / "a.csv", "-o", out / "single.bvh", "--models", MODELS)
    assert res.returncode == 0, res.stderr
    for role in ("leader", "follower"):
        single = out / f"single_{role}.bvh"
        assert single.read_bytes() == (out / f"a_{role}.bvh").read_bytes()
        single.unlink()


@pytest.mark.parametrize("fmt", ["blend", "fbx"])
def test_blend_fbx(takes, converted, fmt):
    out, res = converted(fmt)
    files = check_run(takes, out, res, fmt)
    paths = {rel: str(out / (base + "." + fmt)) for rel, base in GOOD.items()}
    got = run_bpy_script(f"""
        import json, bpy
        paths = {paths!r}
        res = {{}}
        for rel, path in paths.items():
            if {fmt!r} == "blend":
                bpy.ops.wm.open_mainfile(filepath=path)
            else:
                bpy.ops.wm.read_homefile(use_empty=True)
                assert bpy.ops.import_scene.fbx(filepath=path) == {{'FINISHED'}}
            arms = {{}}
            for o in bpy.data.objects:
                if o.type == 'ARMATURE':
                    act = o.animation_data.action if o.animation_data else None
                    keys = 0
                    if act is not None:
                        keys = max(len(fc.keyframe_points) for fc in action_fcurves(act))
                    arms[o.name] = [len(o.data.bones), keys]
            meshes = sorted(o.name for o in bpy.data.objects if o.type == 'MESH' and not o.get("dp_method")
                            and not o.get("dp_stage"))
            method = sorted((o["dp_method"], o.hide_render) for o in bpy.data.objects if o.get("dp_method"))
            res[rel] = [arms, meshes, [c.name for c in bpy.data.collections], method]
        print("RESULT " + json.dumps(res))
        """)
    for rel, (arms, meshes, colls, method) in got.items():
        name = os.path.splitext(os.path.basename(rel))[0]
        assert set(arms) == {"DP Leader", "DP Follower"}, (rel, arms)
        for bones, keys in arms.values():
            assert bones == 31 and keys == files[rel]["frames"], (rel, arms)  # one key per frame
        assert meshes == ["DP Follower Body", "DP Leader Body"], (rel, meshes)
        if fmt == "blend":
            assert {"DP Take " + name, "DP Duet " + name} <= set(colls), colls
            # the method view (operators/method_view.py), hidden in renders; never in the FBX
            assert sorted({k for k, _ in method}) == ["contacts", "inputs", "predictions"], method
            assert all(hidden for _, hidden in method), method
        else:
            assert method == [], method


def test_render(tmp_path, salsa_dir):
    """--render: a Workbench preview video beside the output (a very short take: renders are slow)."""
    write_take(tmp_path / "short.csv", take_from_motion(cut(load_amc(salsa_dir / "60_05.amc"), 0, 24)))
    out = tmp_path / "out"
    res = run_batch(tmp_path / "short.csv", out, "npz", "--render", jobs=1)
    assert res.returncode == 0, res.stdout + res.stderr
    r = read_report(out)["files"][0]
    assert r["outputs"] == [str(out / "short.npz"), str(out / "short.mp4")] and r["frames"] == 12
    head = (out / "short.mp4").read_bytes()[:12]
    assert head[4:8] == b"ftyp", head  # an MPEG-4 file
    assert sorted(os.listdir(out)) == [batch.REPORT_NAME, "short.mp4", "short.npz"]


def test_rigs_get_the_duet(tmp_path, salsa_dir):
    """--leader-rig / --follower-rig: the two avatars of ../shared/assets (GLB)
    are imported into each .blend and keyed on every frame with the retargeted
    duet; the default bodies are hidden."""
    from conftest import ASSETS

    rigs = {"leader": ASSETS / "White_M_1_Casual.glb", "follower": ASSETS / "White_F_1_Casual.glb"}
    if not all(p.is_file() for p in rigs.values()):
        pytest.skip("no avatars in ../shared/assets")
    write_take(tmp_path / "short.csv", take_from_motion(cut(load_amc(salsa_dir / "60_06.amc"), 0, 120)))
    out = tmp_path / "out"
    res = run_batch(tmp_path / "short.csv", out, "blend", "--leader-rig", rigs["leader"],
                    "--follower-rig", rigs["follower"], jobs=1)
    assert res.returncode == 0, res.stdout + res.stderr
    frames = read_report(out)["files"][0]["frames"]
    got = run_bpy_script(f"""
        import json, bpy
        bpy.ops.wm.open_mainfile(filepath={str(out / "short.blend")!r})
        arms = {{}}
        for o in bpy.data.objects:
            if o.type != 'ARMATURE':
                continue
            fcs = action_fcurves(o.animation_data.action if o.animation_data else None)
            keys = sorted({{int(round(k.co[0])) for fc in fcs for k in fc.keyframe_points}})
            skinned = [m.name for m in bpy.data.objects if m.type == 'MESH' and
                       any(md.type == 'ARMATURE' and md.object == o for md in m.modifiers)]
            arms[o.name] = [len(o.data.bones), len(keys), skinned]
        hidden = sorted(o.name for o in bpy.data.objects if o.type == 'MESH' and o.hide_render
                        and not o.get("dp_method"))  # the method view is hidden in renders too
        print("RESULT " + json.dumps([arms, hidden]))
        """)
    arms, hidden = got
    rig_arms = {k: v for k, v in arms.items() if k not in ("DP Leader", "DP Follower")}
    assert {"DP Leader", "DP Follower"} <= set(arms) and len(rig_arms) == 2, arms
    for name, (bones, keys, skinned) in rig_arms.items():
        assert bones > 20 and keys == frames and skinned, (name, arms[name])  # keyed on every frame
    assert hidden == ["DP Follower Body", "DP Leader Body"], hidden
    # a rig with a format that holds no armature: one line, exit 2, nothing written
    res = run_batch(tmp_path / "short.csv", tmp_path / "out2", "npz", "--leader-rig", rigs["leader"])
    assert res.returncode == 2 and "--leader-rig works with the blend and fbx formats" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "out2").exists()


# --------------------------------------------------------------------------- existing outputs

def test_never_overwrites_without_overwrite(takes, tmp_path):
    src = takes / "a.csv"
    out = tmp_path / "out"
    res = run_batch(src, out, jobs=1)
    assert res.returncode == 0, res.stderr
    target = out / "a.npz"
    old = target.read_bytes()
    os.utime(target, (1e9, 1e9))
    res = run_batch(src, out, jobs=1)  # again: refused, untouched
    assert res.returncode == 1, res.stdout + res.stderr
    r = read_report(out)["files"][0]
    assert r["status"] == "failed" and "output exists" in r["error"] and "--overwrite" in r["error"]
    assert target.read_bytes() == old and target.stat().st_mtime == 1e9
    res = run_batch(src, out, "npz", "--resume", jobs=1)  # skipped
    assert res.returncode == 0, res.stderr
    r = read_report(out)["files"][0]
    assert r["status"] == "skipped" and target.stat().st_mtime == 1e9
    assert res.stdout.startswith("skipped ")
    res = run_batch(src, out, "npz", "--overwrite", jobs=1)  # replaced
    assert res.returncode == 0, res.stderr
    assert read_report(out)["files"][0]["status"] == "ok" and target.stat().st_mtime > 1e9
    assert not leftovers(out)
    mtime = target.stat().st_mtime
    res = run_batch(src, out, "npz", "--resume", "--overwrite", jobs=1)  # skip or replace: refused, not guessed
    assert res.returncode == 2 and "not allowed with argument" in res.stderr, res.stdout + res.stderr
    assert target.stat().st_mtime == mtime


def test_report_option_and_name_clashes(takes, tmp_path):
    """Two takes with the same stem get the source extension appended; --report elsewhere."""
    d = tmp_path / "in"
    d.mkdir()
    shutil.copy(takes / "a.csv", d / "take.csv")
    shutil.copy(takes / "sub" / "b.bvh", d / "take.bvh")
    out, rep = tmp_path / "out", tmp_path / "rep.json"
    res = run_batch(d, out, "npz", "--report", rep)
    assert res.returncode == 0, res.stdout + res.stderr
    files = {os.path.basename(r["input"]): r for r in json.loads(rep.read_text())["files"]}
    assert files["take.csv"]["output"] == str(out / "take_csv.npz")
    assert files["take.bvh"]["output"] == str(out / "take_bvh.npz")
    assert sorted(os.listdir(out)) == ["take_bvh.npz", "take_csv.npz"]
    # a report that cannot be written there is refused before any work (it used to run every take, exit 0);
    # /proc: a folder where no file can be made, even by root (Linux)
    if sys.platform.startswith("linux"):
        res = run_batch(d, tmp_path / "out2", "npz", "--report", "/proc/dp_report.json")
        assert res.returncode == 2 and "cannot write the report there" in res.stderr, res.stdout + res.stderr
        assert not (tmp_path / "out2").exists()


# --------------------------------------------------------------------------- stopping

@pytest.fixture(scope="module")
def long_takes(tmp_path_factory, salsa_dir):
    """Six 20 s CSV takes (600 duet frames each)."""
    d = tmp_path_factory.mktemp("long")
    for i in range(6):
        m = load_amc(salsa_dir / f"60_{i + 1:02d}.amc")
        write_take(d / f"take{i}.csv", take_from_motion(cut(m, 0, 1200)))
    return d


def _start(args):
    return subprocess.Popen([sys.executable, "-m", "dancing_points_addon", "batch", *map(str, args)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_output(proc, out, pattern_ext, timeout=300):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if out.is_dir() and any(p.suffix == pattern_ext and not p.name.startswith(".") for p in out.rglob("*")):
            return
        if proc.poll() is not None:
            raise AssertionError("the batch ended before its first output: " + proc.stderr.read())
        time.sleep(0.01)
    raise AssertionError("no output appeared")


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs /proc to find the workers")
@pytest.mark.parametrize("sig,fmt", [(signal.SIGINT, "npz"), (signal.SIGTERM, "blend")])
def test_stop_leaves_no_partial_output_and_resume_finishes(long_takes, tmp_path, sig, fmt):
    out = tmp_path / "out"
    ext = "." + fmt
    proc = _start([long_takes, "-o", out, "--format", fmt, "--jobs", 2, "--models", MODELS])
    _wait_for_output(proc, out, ext)
    time.sleep(0.3)  # the other worker is mid-file
    workers = _children_alive(proc.pid)
    assert len(workers) == 2
    proc.send_signal(sig)  # Ctrl-C reaches the parent (workers run in their own session)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == (130 if sig == signal.SIGINT else 143), (proc.returncode, stdout, stderr)
    assert "Traceback" not in stdout + stderr, stderr
    assert "--resume" in stderr
    assert not leftovers(out), leftovers(out)
    report = read_report(out)
    assert report["interrupted"] is True
    status = {os.path.basename(r["input"]): r["status"] for r in report["files"]}
    done = sorted(p.name for p in out.glob("*" + ext))
    assert done == sorted(n.replace(".csv", ext) for n, s in status.items() if s == "ok")
    assert 1 <= len(done) < 6, status
    assert set(status.values()) <= {"ok", "interrupted", "pending"}
    if fmt == "npz":
        for p in out.glob("*.npz"):  # every output there is complete
            with np.load(p) as z:
                assert z["leader_positions"].shape == (600, 31, 3)
    # No worker survives the parent.
    assert not [pid for pid in workers if _running(pid)]

    res = run_batch(long_takes, out, fmt, "--resume")
    assert res.returncode == 0, res.stdout + res.stderr
    report = read_report(out)
    status2 = {os.path.basename(r["input"]): r["status"] for r in report["files"]}
    assert {n for n, s in status2.items() if s == "skipped"} == {n for n, s in status.items() if s == "ok"}
    assert {n for n, s in status2.items() if s == "ok"} == {n for n, s in status.items() if s != "ok"}
    assert sorted(p.name for p in out.glob("*" + ext)) == [f"take{i}{ext}" for i in range(6)]
    assert not leftovers(out)


def _running(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _children_alive(pid):
    """Processes whose parent was ``pid`` (Linux /proc), still running."""
    return [p for p, (parent, state, _) in proc_table().items() if parent == pid and state != "Z"]


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs /proc to find the worker")
def test_worker_killed_is_reported_and_the_rest_go_on(long_takes, tmp_path):
    out = tmp_path / "out"
    proc = _start([long_takes, "-o", out, "--jobs", 1, "--models", MODELS, "--no-progress"])
    _wait_for_output(proc, out, ".npz")
    kids = _children_alive(proc.pid)
    assert len(kids) == 1
    os.kill(kids[0], signal.SIGKILL)  # mid-file: its temporary file stays behind
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 1, (stdout, stderr)
    report = read_report(out)
    died = [r for r in report["files"] if r["status"] == "failed"]
    assert len(died) == 1 and "worker process died" in died[0]["error"], report["files"]
    assert report["counts"]["ok"] == 5
    assert not leftovers(out), leftovers(out)  # the parent removed it


# A stand-in worker (the real protocol) that leaves temporary files behind the
# way a worker killed mid-write would: "crash*" inputs exit without a word,
# "stop*" inputs signal the parent (as Ctrl-C would) and hang.
FAKE_WORKER = r"""
import json, os, signal, sys, time
P = "@@dancing_points.batch@@ "
print("some library chatter on stdout", flush=True)
print(P + json.dumps({"type": "ready"}), flush=True)
for line in sys.stdin:
    job = json.loads(line)
    for p in job["temps"].values():
        with open(p, "w") as f:
            f.write("partial")
        with open(p + "@", "w") as f:
            f.write("a writer's own temporary file")
    name = os.path.basename(job["input"])
    if name.startswith("crash"):
        os._exit(3)
    if name.startswith("stop"):
        os.kill(os.getppid(), int(os.environ["FAKE_SIGNAL"]))
        time.sleep(60)
    print(P + json.dumps({"type": "progress", "id": job["id"], "fraction": 0.5}), flush=True)
    print(P + json.dumps({"type": "done", "id": job["id"], "frames": 7, "seconds": 0.01}), flush=True)
"""


# A real worker loop whose converter is sent SIGTERM while it "imports", the way
# onnxruntime's extension does it: the signal swallowed, an ImportError raised.
SWALLOWING_WORKER = r"""
import os, signal, sys, time
sys.path.insert(0, sys.argv[1])
from dancing_points_addon.batch import worker
class Converter:
    def __call__(self, job, progress):
        for p in job["temps"].values():
            with open(p, "w") as f:
                f.write("partial")
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)
        except BaseException:
            pass
        raise ImportError("")
worker.CoreConverter = Converter
sys.exit(worker.worker_main())
"""


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_worker_ends_on_a_sigterm_a_library_swallowed(tmp_path):
    """The worker's SIGTERM turned by an import into an ImportError ended the job as
    'failed' and the worker went on; now it removes the job's files and exits 143."""
    temp = tmp_path / ".a.npz.part"
    job = {"type": "job", "id": 1, "input": str(tmp_path / "a.csv"), "temps": {"npz": str(temp)},
           "needs_bpy": False, "options": {}}
    res = subprocess.run([sys.executable, "-c", SWALLOWING_WORKER, str(ROOT)], input=json.dumps(job) + "\n",
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 143, (res.returncode, res.stdout, res.stderr)
    assert '"error"' not in res.stdout and not temp.exists()


def _fake_args(tmp_path, inputs, **kw):
    # (real models: the parent checks them once at start-up, nets.check_models)
    d = dict(inputs=[str(p) for p in inputs], output_dir=str(tmp_path / "out"), format="bvh", jobs=1,
             render=False, overwrite=False, resume=False, report=None, models=MODELS, threads=1,
             input_fps=None, asf=None, height=None, no_foot_lock=False, no_hand_ik=False, no_progress=True)
    d.update(kw)
    return argparse.Namespace(**d)


def test_a_report_that_cannot_be_written_fails_the_run(tmp_path, capsys, monkeypatch):
    """Every take converted, but the report not written at the end (say the
    disk filled since the check): the run says so and exits 1, not 0."""
    (tmp_path / "a.csv").write_text("")

    def full(path, data):
        raise batch.InputError(path, "cannot write (No space left on device)")

    monkeypatch.setattr(batch, "write_report", full)
    rc = batch.run(_fake_args(tmp_path, [tmp_path / "a.csv"]), worker_cmd=[sys.executable, "-c", FAKE_WORKER])
    assert rc == 1 and "cannot write the report" in capsys.readouterr().err


def test_parent_removes_what_a_dead_worker_left(tmp_path, capsys):
    names = ["a.csv", "crash.csv", "b.csv"]
    for n in names:
        (tmp_path / n).write_text("")
    rc = batch.run(_fake_args(tmp_path, [tmp_path / n for n in names]),
                   worker_cmd=[sys.executable, "-c", FAKE_WORKER])
    assert rc == 1
    out = tmp_path / "out"
    st = {os.path.basename(r["input"]): (r["status"], r["error"]) for r in read_report(out)["files"]}
    assert st["a.csv"] == ("ok", None) and st["b.csv"] == ("ok", None)  # a new worker took over
    assert st["crash.csv"][0] == "failed" and "worker process died (exit status 3)" in st["crash.csv"][1]
    assert sorted(os.listdir(out)) == ["a_follower.bvh", "a_leader.bvh", "b_follower.bvh", "b_leader.bvh",
                                       batch.REPORT_NAME]
    assert "chatter" not in capsys.readouterr().out


@pytest.mark.parametrize("cmd,why", [(["/nonexistent/blender"], "cannot start a worker process"),
                                     ([sys.executable, "-c", "import sys; print('boom', file=sys.stderr)"],
                                      "boom")])
def test_workers_that_cannot_start(tmp_path, cmd, why):
    names = ["a.csv", "b.csv", "c.csv"]
    for n in names:
        (tmp_path / n).write_text("")
    rc = batch.run(_fake_args(tmp_path, [tmp_path / n for n in names], jobs=2), worker_cmd=cmd)
    assert rc == 1
    files = read_report(tmp_path / "out")["files"]
    assert [r["status"] for r in files] == ["failed"] * 3 and all(why in r["error"] for r in files), files
    assert sorted(os.listdir(tmp_path / "out")) == [batch.REPORT_NAME]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_stop_removes_temporary_files(tmp_path, monkeypatch, sig):
    (tmp_path / "in" / "sub").mkdir(parents=True)
    for n in ("sub/stop.csv", "a.csv", "b.csv", "c.csv"):
        (tmp_path / "in" / n).write_text("x" * (100 if n.startswith("sub/stop") else 1))
    monkeypatch.setenv("FAKE_SIGNAL", str(int(sig)))
    old = signal.getsignal(sig)
    rc = batch.run(_fake_args(tmp_path, [tmp_path / "in"], format="npz", jobs=2),
                   worker_cmd=[sys.executable, "-c", FAKE_WORKER])
    assert rc == (130 if sig == signal.SIGINT else 143)
    assert signal.getsignal(sig) == old  # handler restored
    out = tmp_path / "out"
    report = read_report(out)
    assert report["interrupted"] is True
    st = {os.path.relpath(r["input"], tmp_path / "in"): r["status"] for r in report["files"]}
    assert st["sub/stop.csv"] == "interrupted"  # the largest file went first
    assert not leftovers(out), leftovers(out)
    assert not (out / "sub").exists()  # the folder made for it was empty again
    assert sorted(os.listdir(out)) == sorted([batch.REPORT_NAME] + [n.replace(".csv", ".npz")
                                                                    for n, s in st.items() if s == "ok"])


# --------------------------------------------------------------------------- bad command lines

def test_bad_command_lines(tmp_path, takes):
    (tmp_path / "nothing_here").mkdir()
    (tmp_path / "nothing_here" / "notes.txt").write_text("")
    cases = [
        (["batch", tmp_path / "nothing_here", "-o", tmp_path / "o", "--models", MODELS],
         "no input files found"),
        (["batch", takes / "a.csv", "-o", tmp_path / "o", "--models", tmp_path], "no synthesis models"),
        (["batch", takes / "a.csv", "-o", tmp_path / "o", "--jobs", "0"], "at least 1"),
        (["batch", takes / "a.csv", "-o", tmp_path / "o", "--format", "obj"], "invalid choice"),
        (["batch", takes / "a.csv", "-o", takes / "a.csv"], "not a folder"),
    ]
    for args, frag in cases:
        res = run_cli(*args)
        assert res.returncode == 2, (args, res.stdout, res.stderr)
        lines = res.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and frag in lines[0], (args, res.stderr)
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- Blender command

def test_blender_command(takes, tmp_path):
    """The ``dancing_points`` command is registered with ``register_cli_command`` when
    the extension is enabled; ``convert`` runs a batch; ``worker`` is the worker loop
    that ``blender --background --command dancing_points worker`` runs."""
    out1, out2 = tmp_path / "o1", tmp_path / "o2"
    got = run_bpy_script(f"""
        import argparse, importlib, io, json, os, sys, contextlib
        sys.path.insert(0, {str(ROOT / 'tests')!r})
        import bpy
        from support.ext_util import enable_extension
        mod = enable_extension()
        cli = importlib.import_module(mod + ".operators.batch_cli")
        core = importlib.import_module(mod + ".dancing_points_addon.batch")
        res = {{"registered": cli._handle is not None}}
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            res["usage"] = cli.cli([])
            res["bogus"] = cli.cli(["bogus"])
            res["bad"] = cli.cli(["convert", "--jobs", "x"])
        res["err"] = err.getvalue()
        res["convert"] = cli.cli(["convert", {str(takes / 'a.csv')!r}, {str(takes / 'sub')!r}, "-o", {str(out1)!r},
                                  "--format", "npz", "--jobs", "2", "--models", {MODELS!r}, "--no-progress"])
        # Workers as Blender starts them: the extension enabled, then the 'worker' command.
        boot = ("import sys; sys.path.insert(0, {str(ROOT / 'tests')!r}); import importlib; "
                "from support.ext_util import enable_extension; m = enable_extension(); "
                "sys.exit(importlib.import_module(m + '.operators.batch_cli').cli(['worker']))")
        args = argparse.Namespace(inputs=[{str(takes / 'c.csv')!r}], output_dir={str(out2)!r}, format="blend",
                                  jobs=1, render=False, overwrite=False, resume=False, report=None,
                                  models={MODELS!r}, threads=1, input_fps=None, asf=None, height=None,
                                  no_foot_lock=False, no_hand_ik=False, no_progress=True)
        res["worker"] = core.run(args, worker_cmd=[sys.executable, "-c", boot], in_blender=True)
        bpy.ops.preferences.addon_disable(module=mod)
        res["unregistered"] = cli._handle is None
        print("RESULT " + json.dumps(res))
        """)
    assert got["registered"] and got["unregistered"]
    assert got["usage"] == 2 and got["bogus"] == 2 and got["bad"] == 2
    assert "unknown subcommand" in got["err"] and "not a whole number" in got["err"]
    assert got["convert"] == 1  # trunc.bvh fails
    st = {os.path.basename(r["input"]): r["status"] for r in read_report(out1)["files"]}
    assert st == {"a.csv": "ok", "b.bvh": "ok", "trunc.bvh": "failed"}
    assert sorted(os.listdir(out1)) == ["a.npz", "b.npz", batch.REPORT_NAME]
    assert got["worker"] == 0
    assert (out2 / "c.blend").is_file() and read_report(out2)["files"][0]["frames"] == N30


# --------------------------------------------------------------------------- the bpy-free pieces

def test_discover(tmp_path):
    (tmp_path / "in" / "deep" / "er").mkdir(parents=True)
    (tmp_path / "in" / ".git").mkdir()
    (tmp_path / "in" / "out").mkdir()
    for rel in ("a.csv", "B.BVH", "c.amc", "60.asf", "x.txt", "deep/er/d.csv", ".h.csv", ".git/e.csv",
                "out/old.bvh", "other.fbx"):
        (tmp_path / "in" / rel).write_text("")
    (tmp_path / "lone.txt").write_text("")
    got = batch.discover([tmp_path / "in", tmp_path / "lone.txt", tmp_path / "in" / "a.csv"],
                         batch.CORE_INPUTS, exclude=[tmp_path / "in" / "out"])
    rel = [(os.path.relpath(p, tmp_path), r) for p, r in got]
    assert rel == [("in/B.BVH", ""), ("in/a.csv", ""), ("in/c.amc", ""),
                   (os.path.join("in", "deep", "er", "d.csv"), os.path.join("deep", "er")),
                   ("lone.txt", "")]  # a file given explicitly is kept; duplicates once
    assert "in/other.fbx" in [os.path.relpath(p, tmp_path) for p, _ in
                              batch.discover([tmp_path / "in"], batch.BPY_INPUTS)]


def test_output_names_and_temps(tmp_path):
    entries = [("/x/take.csv", ""), ("/x/take.bvh", ""), ("/y/take.csv", ""), ("/x/s/take.csv", "s"),
               ("/x/other.amc", "")]
    assert batch.output_bases(entries) == ["take_csv", "take_bvh", "take_csv_2", os.path.join("s", "take"),
                                           "other"]
    assert batch.output_kinds("bvh", True) == [("bvh_leader", "_leader.bvh"), ("bvh_follower", "_follower.bvh"),
                                               ("mp4", ".mp4")]
    assert batch.temp_path("/o/sub/take.blend", 123) == "/o/sub/.take.part-123.blend"  # unique per process
    tasks = batch.plan([(str(tmp_path / "t.csv"), "")], str(tmp_path), "bvh")
    assert tasks[0].outputs == [str(tmp_path / "t_leader.bvh"), str(tmp_path / "t_follower.bvh")]
    pid = os.getpid()
    assert tasks[0].temps == [str(tmp_path / f".t_leader.part-{pid}.bvh"),
                              str(tmp_path / f".t_follower.part-{pid}.bvh")]
    # existing outputs: failed / skipped (--resume) / replace (--overwrite; --resume over an incomplete set)
    (tmp_path / "t_leader.bvh").write_text("")
    args = ([(str(tmp_path / "t.csv"), "")], str(tmp_path), "bvh")
    assert batch.plan(*args)[0].status == "failed"
    t = batch.plan(*args, resume=True)[0]
    assert t.status == "pending" and t.replace
    assert batch.plan(*args, overwrite=True)[0].replace
    (tmp_path / "t_follower.bvh").write_text("")
    assert batch.plan(*args, resume=True)[0].status == "skipped"
    # temporary leftovers of every writer are removed
    tmp = tasks[0].temps[0]
    for p in batch.temp_leftovers(tmp)[:2]:
        open(p, "w").close()
    os.mkdir(tmp + ".d")
    open(os.path.join(tmp + ".d", "0001-0010.mp4"), "w").close()
    batch.remove_temps([tmp])
    assert not any(os.path.exists(p) for p in batch.temp_leftovers(tmp))


class _Stream(io.StringIO):
    def __init__(self, tty):
        super().__init__()
        self._tty = tty

    def isatty(self):
        return self._tty


def test_progress_display():
    assert batch.fmt_duration(None) == "--:--" and batch.fmt_duration(75.4) == "1:15"
    assert batch.fmt_duration(3725) == "1:02:05"
    assert batch.eta(10.0, 0.25) == pytest.approx(30.0) and batch.eta(3.0, 0.0) is None
    err, out = _Stream(True), _Stream(True)
    p = batch.Progress(4, stream=err, out=out)
    p.t0 -= 10.0  # 10 s elapsed
    p.update(1, [("a.csv", 0.5), ("b.bvh", 0.5)], force=True)
    text = err.getvalue()
    assert text.startswith("\r\x1b[K[") and "\n" not in text
    assert "1/4 files" in text and " 50%" in text and "ETA 0:10" in text and "a.csv 50%" in text
    p.result("ok      a.csv -> a.npz")
    assert err.getvalue().endswith("\r\x1b[K") and out.getvalue() == "ok      a.csv -> a.npz\n"
    # not a terminal: plain lines, once per finished file
    err = _Stream(False)
    p = batch.Progress(2, stream=err, out=_Stream(False))
    p.update(0, [("a.csv", 0.1)], force=True)
    p.update(0, [("a.csv", 0.2)], force=True)
    p.update(1, [], force=True)
    lines = err.getvalue().splitlines()
    assert len(lines) == 2 and all(ln.startswith("progress: [") for ln in lines) and "\r" not in err.getvalue()
    p = batch.Progress(2, stream=err, out=_Stream(False), enabled=False)
    p.update(1, [], force=True)
    assert len(err.getvalue().splitlines()) == 2
