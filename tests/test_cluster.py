"""Batch conversion on a Dask cluster (``batch ... --cluster ADDRESS``), as a farm runs it.

A real ``dask scheduler`` and two ``dask worker`` processes (each a nanny and
its worker process) run on 127.0.0.1 on free ports, started for this module and
stopped at its end (also when a test fails). On them:

* a folder of good and broken takes converted to npz and to bvh gives the
  local batch's outputs byte for byte (and its report's statuses, frames and
  reasons, and exit status 1);
* a worker killed mid-take (SIGKILL; its nanny starts a new one) costs that
  take one more attempt only: every take converted once, nothing partial, the
  report says which take ran twice and where;
* Ctrl-C on the client cancels the cluster's tasks, leaves no partial file and
  ``--resume`` finishes the rest;
* a worker of another version refuses: one line, exit status 2, nothing written.

Dask is an optional dependency of the command line (requirements-dev.txt):
this module is skipped only where it is not installed. The throughput figure
is a benchmark: ``.venv/bin/python benchmarks/bench_cluster.py``.
"""
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from conftest import MODELS, ROOT
from support.helpers import N60, cut, leftovers, make_takes, read_report

distributed = pytest.importorskip("distributed", reason="dask's distributed package is not installed")

from dancing_points_addon import batch  # noqa: E402
from dancing_points_addon.batch import cluster as dp_cluster  # noqa: E402
from dancing_points_addon.batch import cluster_connect, cluster_identity, cluster_worker  # noqa: E402
from dancing_points_addon.formats.asf_amc import load_amc  # noqa: E402
from dancing_points_addon.formats.take import take_from_motion, write_take  # noqa: E402

SIGKILL = getattr(signal, "SIGKILL", signal.SIGTERM)
DASK = os.path.join(os.path.dirname(sys.executable), "dask")
GOOD = {"a.csv": "a", "c.csv": "c", "sub/b.bvh": "sub/b", "amc/60_03.amc": "amc/60_03"}
BAD = {"broken.csv": "unknown header column", "sub/trunc.bvh": "trunc.bvh", "noasf/61_09.amc": "ASF",
       "empty.csv": "empty.csv"}
SUFFIXES = {"npz": [".npz"], "bvh": ["_leader.bvh", "_follower.bvh"]}


# --------------------------------------------------------------------------- the cluster

class DaskProcesses:
    """A ``dask scheduler`` and ``dask worker`` processes on 127.0.0.1, each in its
    own session (so that a group can be stopped whole), logs in ``folder``."""

    def __init__(self, folder, pythonpath=ROOT):
        self.folder = folder
        self.pythonpath = str(pythonpath)
        self.procs = []
        self.address = None

    def _start(self, name, args):
        log = open(os.path.join(self.folder, name + ".log"), "w+b")
        env = dict(os.environ, PYTHONPATH=self.pythonpath)
        proc = subprocess.Popen([DASK, *args], cwd=self.pythonpath, stdin=subprocess.DEVNULL, stdout=log,
                                stderr=subprocess.STDOUT, env=env, start_new_session=True)
        self.procs.append((proc, log, name))
        return proc

    def log(self, name):
        with open(os.path.join(self.folder, name + ".log"), "rb") as f:
            return f.read().decode("utf-8", "replace")

    def start(self, n_workers, timeout=90):
        self._start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                  "--dashboard-address", "127.0.0.1:0"])
        t0 = time.monotonic()
        while self.address is None:
            for line in self.log("scheduler").splitlines():
                if "Scheduler at:" in line:
                    self.address = line.split("Scheduler at:")[1].strip()
            if self.address is None:
                assert self.procs[0][0].poll() is None, self.log("scheduler")
                assert time.monotonic() - t0 < timeout, "no scheduler: " + self.log("scheduler")
                time.sleep(0.05)
        for i in range(n_workers):
            self._start(f"worker{i}", ["worker", self.address, "--nthreads", "1", "--host", "127.0.0.1",
                                       "--no-dashboard", "--local-directory", os.path.join(self.folder, f"w{i}")])
        with distributed.Client(self.address, timeout=timeout, set_as_default=False) as c:
            try:
                c.wait_for_workers(n_workers, timeout=timeout)
            except TimeoutError:
                raise AssertionError("workers did not start: " + " | ".join(
                    self.log(f"worker{i}")[-2000:] for i in range(n_workers))) from None
        return self

    def stop(self):
        for proc, _, _ in reversed(self.procs):  # workers first
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                except OSError:
                    pass
        for proc, log, _ in self.procs:
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except OSError:
                    pass
                proc.wait(timeout=15)
            log.close()
        # a worker process its nanny started lives in the nanny's group: gone with it
        self.procs = []


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    procs = DaskProcesses(str(tmp_path_factory.mktemp("dask")))
    try:
        procs.start(2)
        yield procs
    finally:
        procs.stop()


@pytest.fixture
def client(dask_cluster):
    with distributed.Client(dask_cluster.address, timeout=60, set_as_default=False) as c:
        yield c


# --------------------------------------------------------------------------- data and runs



@pytest.fixture(scope="module")
def takes(tmp_path_factory, salsa_dir):
    """Good takes (CSV, BVH, AMC; sub-folders) and broken ones (as tests/test_batch.py)."""
    return make_takes(tmp_path_factory.mktemp("takes"), salsa_dir)


@pytest.fixture(scope="module")
def long_takes(tmp_path_factory, salsa_dir):
    """Six 20 s CSV takes (600 duet frames each, about 2 s of work each)."""
    d = tmp_path_factory.mktemp("long")
    for i in range(6):
        write_take(d / f"take{i}.csv", take_from_motion(cut(load_amc(salsa_dir / f"60_{i + 1:02d}.amc"), 0, 1200)))
    return d


def batch_args(inputs, out, fmt, *extra):
    inputs = inputs if isinstance(inputs, (list, tuple)) else [inputs]
    return ["batch", *map(str, inputs), "-o", str(out), "--format", fmt, "--models", MODELS, "--no-progress",
            *map(str, extra)]


def run_cli(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "dancing_points_addon", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def start_cli(*args):
    return subprocess.Popen([sys.executable, "-m", "dancing_points_addon", *map(str, args)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def produced(folder):
    return sorted(os.path.relpath(os.path.join(dp, f), folder) for dp, _, fs in os.walk(folder) for f in fs)


def result_lines(stdout):
    """``{(status word, input)}`` of the result lines (the times differ between runs)."""
    got = set()
    for ln in stdout.splitlines()[:-1]:
        word, rest = ln.split(None, 1)
        got.add((word, rest.split(" -> ")[0].split(": ")[0].split(" (")[0]))
    return got


def wait_until(cond, what, proc=None, timeout=120):
    t0 = time.monotonic()
    while not cond():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the batch ended before {what}: " + proc.stdout.read() + proc.stderr.read())
        assert time.monotonic() - t0 < timeout, f"timed out waiting for {what}"
        time.sleep(0.02)


def executing(client):
    """``{worker address: [keys of the takes it is converting now]}``."""
    keys = client.run(lambda dask_worker: [ts.key for ts in dask_worker.state.executing])
    return {a: [k for k in ks if str(k).startswith("dancing-points-")] for a, ks in keys.items()}


# --------------------------------------------------------------------------- the same outputs as the local batch

@pytest.mark.parametrize("fmt", ["npz", "bvh"])
def test_cluster_outputs_are_the_local_batch_outputs(dask_cluster, takes, tmp_path, fmt):
    local, remote = tmp_path / "local", tmp_path / "cluster"
    t0 = time.perf_counter()
    res_l = run_cli(*batch_args(takes, local, fmt, "--jobs", 2))
    t1 = time.perf_counter()
    res_c = run_cli(*batch_args(takes, remote, fmt, "--cluster", dask_cluster.address))
    t2 = time.perf_counter()
    print(f"\n{fmt}: local --jobs 2 {t1 - t0:.2f} s, --cluster (2 workers) {t2 - t1:.2f} s")
    for res in (res_l, res_c):
        assert res.returncode == 1, (res.returncode, res.stdout, res.stderr)  # the broken takes failed
        assert "Traceback" not in res.stdout + res.stderr, res.stderr
    assert res_c.stderr == "", res_c.stderr  # no Dask chatter
    # Every output byte for byte the local batch's (the npz writer is deterministic: fixed zip times).
    want = sorted([batch.REPORT_NAME] + [b + s for b in GOOD.values() for s in SUFFIXES[fmt]])
    assert produced(local) == want and produced(remote) == want, (produced(local), produced(remote))
    for rel in (r for r in want if r != batch.REPORT_NAME):
        assert (remote / rel).read_bytes() == (local / rel).read_bytes(), rel
        if fmt == "npz":
            with np.load(local / rel) as a, np.load(remote / rel) as b:
                assert a.files == b.files
                for k in a.files:
                    assert np.array_equal(a[k], b[k]), (rel, k)
    assert not leftovers(remote), leftovers(remote)
    # The same report (statuses, frames, reasons naming the client's paths), plus the cluster's part.
    rl, rc = read_report(local), read_report(remote)
    assert rc["counts"] == rl["counts"] == {"ok": len(GOOD), "failed": len(BAD), "skipped": 0, "interrupted": 0,
                                            "pending": 0}
    for fl, fc in zip(rl["files"], rc["files"]):
        assert fc["input"] == fl["input"]
        assert fc["outputs"] == [p.replace(str(local), str(remote)) for p in fl["outputs"]]
        assert (fc["status"], fc["frames"], fc["error"]) == (fl["status"], fl["frames"], fl["error"]), (fl, fc)
        assert fc["attempts"] == 1 and len(fc["workers"]) == 1, fc
    for rel, why in BAD.items():
        rec = next(f for f in rc["files"] if f["input"] == str(takes / rel))
        assert why in rec["error"] and "dp-take-" not in rec["error"], rec  # no worker scratch path
    assert rc["cluster"]["scheduler"] == dask_cluster.address and len(rc["cluster"]["workers"]) == 2
    assert rc["jobs"] == 2 and rc["cluster"]["allowed_failures"] == 3
    assert {f["workers"][0] for f in rc["files"]} == set(rc["cluster"]["workers"])  # both workers took takes
    assert result_lines(res_c.stdout) == result_lines(res_l.stdout)
    assert res_c.stdout.splitlines()[-1].startswith(f"{len(GOOD) + len(BAD)} file(s): {len(GOOD)} ok, "
                                                    f"{len(BAD)} failed, 0 skipped in ")


# --------------------------------------------------------------------------- a worker killed mid-take

def test_worker_killed_mid_take_costs_one_attempt(dask_cluster, client, long_takes, tmp_path):
    out = tmp_path / "out"
    proc = start_cli(*batch_args(long_takes, out, "npz", "--cluster", dask_cluster.address))
    try:
        busy = {}

        def converting():
            busy.clear()
            busy.update({a: ks for a, ks in executing(client).items() if ks})
            return bool(busy)

        wait_until(converting, "a take started", proc)
        time.sleep(0.3)
        wait_until(converting, "a take converting", proc)  # (again: mid-take now)
        victim, keys = next(iter(sorted(busy.items())))
        pids = client.run(os.getpid, workers=[victim])
        os.kill(pids[victim], SIGKILL)  # the worker process; its nanny starts a new one
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    print("\n" + stdout)
    assert proc.returncode == 0, (proc.returncode, stdout, stderr)
    assert stderr == "", stderr
    report = read_report(out)
    assert report["counts"]["ok"] == 6 and report["interrupted"] is False
    # Each take converted once: one output each, complete; one result line each.
    assert produced(out) == sorted([batch.REPORT_NAME] + [f"take{i}.npz" for i in range(6)])
    assert not leftovers(out), leftovers(out)
    for i in range(6):
        with np.load(out / f"take{i}.npz") as z:
            assert z["leader_positions"].shape == (600, 31, 3) and np.isfinite(z["follower_positions"]).all()
    lines = stdout.splitlines()
    assert len(lines) == 7 and sum(ln.startswith("ok ") for ln in lines) == 6, stdout
    # Honest: the killed take ran twice, the second time elsewhere; the others once.
    killed_ids = {int(str(k).rsplit("-", 1)[1]) for k in keys}
    by_id = {i: r for i, r in enumerate(report["files"])}
    for i, r in by_id.items():
        if i in killed_ids:
            assert r["attempts"] == 2 and r["workers"][0] == victim and r["workers"][1] != victim, r
        else:  # (a take the victim had just finished, its result not yet fetched, would run again too)
            assert r["attempts"] == 1 or (r["attempts"] == 2 and r["workers"][0] == victim), r
    retried = [ln for ln in lines if "[ran 2 times: 1 worker died running it]" in ln]
    assert len(retried) == sum(r["attempts"] == 2 for r in by_id.values()) >= 1, stdout
    client.wait_for_workers(2, timeout=60)  # the nanny's new worker is back for the other tests


# --------------------------------------------------------------------------- Ctrl-C

def test_ctrl_c_cancels_the_cluster_tasks_and_resume_finishes(dask_cluster, client, long_takes, tmp_path):
    out = tmp_path / "out"
    proc = start_cli(*batch_args(long_takes, out, "npz", "--cluster", dask_cluster.address))
    try:
        wait_until(lambda: out.is_dir() and any(p.suffix == ".npz" and not p.name.startswith(".")
                                                for p in out.iterdir()), "the first output", proc)
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, (proc.returncode, stdout, stderr)
    assert "Traceback" not in stdout + stderr and "--resume" in stderr, stderr
    assert not leftovers(out), leftovers(out)
    report = read_report(out)
    assert report["interrupted"] is True
    status = {os.path.basename(r["input"]): r["status"] for r in report["files"]}
    done = sorted(p.name for p in out.glob("*.npz"))
    assert done == sorted(n.replace(".csv", ".npz") for n, s in status.items() if s == "ok")
    assert 1 <= len(done) < 6 and set(status.values()) <= {"ok", "interrupted", "pending"}, status
    # The cluster drops the run's tasks (a running take stops at its next progress step).
    wait_until(lambda: not any(executing(client).values()), "the cluster to drop the cancelled takes",
               timeout=30)
    res = run_cli(*batch_args(long_takes, out, "npz", "--cluster", dask_cluster.address, "--resume"))
    assert res.returncode == 0, res.stdout + res.stderr
    status2 = {os.path.basename(r["input"]): r["status"] for r in read_report(out)["files"]}
    assert {n for n, s in status2.items() if s == "skipped"} == {n for n, s in status.items() if s == "ok"}
    assert {n for n, s in status2.items() if s == "ok"} == {n for n, s in status.items() if s != "ok"}
    assert produced(out) == sorted([batch.REPORT_NAME] + [f"take{i}.npz" for i in range(6)])
    assert not leftovers(out)


# --------------------------------------------------------------------------- another version

def test_worker_of_another_version_refuses(tmp_path, takes):
    """A worker running a copy of the project with another version: one line, exit 2, nothing written."""
    other = tmp_path / "other"
    other.mkdir()
    shutil.copytree(ROOT / "dancing_points_addon", other / "dancing_points_addon",
                    ignore=shutil.ignore_patterns("__pycache__"))
    os.symlink(ROOT / "models", other / "models")
    text = (ROOT / "blender_manifest.toml").read_text()
    (other / "blender_manifest.toml").write_text(text.replace('\nversion = "', '\nversion = "0.0.1-other+', 1))
    procs = DaskProcesses(str(tmp_path), pythonpath=other)
    try:
        procs.start(1)
        out = tmp_path / "out"
        res = run_cli(*batch_args(takes / "a.csv", out, "npz", "--cluster", procs.address))
    finally:
        procs.stop()
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: --cluster {procs.address}: worker tcp://"), res.stderr
    assert "runs Dancing Points 0.0.1-other+" in lines[0] and "install the client's version" in lines[0]
    assert res.stdout == "" and not out.exists()


def test_a_task_checks_the_identity(tmp_path, takes):
    """The check every task makes on its worker (for workers that join later): in-process."""
    mine = cluster_identity.identity(MODELS)
    spec = {"id": 0, "topic": None, "input": str(takes / "a.csv"), "input_name": "a.csv",
            "input_bytes": (takes / "a.csv").read_bytes(), "beside": None, "files": {}, "needs_bpy": False,
            "options": batch.options.job_options(
                type("A", (), dict(threads=1, height=None, input_fps=None, asf=None, no_foot_lock=False,
                                   no_hand_ik=False))(), MODELS),
            "outputs": {"npz": "a.npz"}}
    for other, why in [(dict(mine, version="9.9"), "this client 9.9"),
                       (dict(mine, code="0" * 64), "(code 000000000000)"),
                       (dict(mine, models="f" * 64), "has no models matching")]:
        res = cluster_worker.run_take(dict(spec, identity=other))
        assert res["status"] == "refused" and why in res["error"], res
    res = cluster_worker.run_take(dict(spec, identity=mine))
    assert res["status"] == "ok" and res["frames"] == N60 // 2 and res["outputs"]["npz"][:2] == b"PK"


# --------------------------------------------------------------------------- the command line

def test_bad_cluster_options(takes, tmp_path, monkeypatch):
    for value, frag in [("local:0", "local:N takes a number of workers"), ("a b", "not a scheduler address")]:
        res = run_cli(*batch_args(takes / "a.csv", tmp_path / "o", "npz", "--cluster", value), timeout=60)
        assert res.returncode == 2 and res.stderr.startswith("error: ") and frag in res.stderr, res.stderr
        assert len(res.stderr.splitlines()) == 1
    assert cluster_connect.cluster_spec("farm-head") == "tcp://farm-head:8786"
    assert cluster_connect.cluster_spec("10.0.0.5:9000") == "tcp://10.0.0.5:9000"
    assert cluster_connect.cluster_spec("local") == "local" and cluster_connect.cluster_spec("local:3") == "local:3"
    # nobody listening: one line (in-process, with a short connect timeout)
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(cluster_connect, "CONNECT_TIMEOUT", 2.0)
    with pytest.raises(cluster_connect.ClusterError, match="cannot reach the Dask scheduler"):
        cluster_connect.connect(f"tcp://127.0.0.1:{port}", MODELS)
    assert not (tmp_path / "o").exists()


def test_without_cluster_dask_is_never_imported(takes, tmp_path):
    """The local batch runs where Dask cannot be imported; --cluster there is one line, exit 2."""
    code = textwrap.dedent(f"""
        import contextlib, io, sys
        class NoDask:
            def find_spec(self, name, path=None, target=None):
                if name.split('.')[0] in ('dask', 'distributed'):
                    raise ImportError('no ' + name + ' here')
        sys.meta_path.insert(0, NoDask())
        from dancing_points_addon.cli import main
        args = ['batch', {str(takes / 'a.csv')!r}, '--models', {MODELS!r}, '--no-progress', '--jobs', '1']
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            local = main(args + ['-o', {str(tmp_path / 'local')!r}])
            remote = main(args + ['-o', {str(tmp_path / 'remote')!r}, '--cluster', 'local:1'])
        assert not any(m.split('.')[0] in ('dask', 'distributed') for m in sys.modules), 'dask imported'
        print(local, remote, repr(err.getvalue()))
        """)
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    local, remote, err = res.stdout.strip().split(" ", 2)
    assert (local, remote) == ("0", "2"), res.stdout
    assert "needs Dask's distributed package" in err and err.count("\\n") == 1, err
    assert (tmp_path / "local" / "a.npz").is_file() and not (tmp_path / "remote").exists()


def test_local_cluster(takes, tmp_path):
    """``--cluster local:N``: a LocalCluster of N worker processes started for the run."""
    out = tmp_path / "out"
    res = run_cli(*batch_args([takes / "a.csv", takes / "broken.csv"], out, "bvh", "--cluster", "local:1"))
    assert res.returncode == 1, (res.returncode, res.stdout, res.stderr)
    assert res.stderr == "", res.stderr
    report = read_report(out)
    assert [r["status"] for r in report["files"]] == ["ok", "failed"] and report["cluster"]["spec"] == "local:1"
    assert produced(out) == sorted([batch.REPORT_NAME, "a_leader.bvh", "a_follower.bvh"])


def test_how_task_outcomes_are_reported(tmp_path):
    """What the client makes of a finished task (in-process, stand-in futures): a take
    whose workers all died (KilledWorker after the scheduler's allowed failures), a
    task the scheduler lost, a refusal (stops the run: exit 2), bytes that come back."""
    import types

    from distributed.scheduler import KilledWorker

    class Future:
        def __init__(self, status, result=None, exc=None):
            self.status, self._result, self._exc = status, result, exc

        def result(self, timeout=None):
            return self._result

        def exception(self, timeout=None):
            return self._exc

    fake = types.SimpleNamespace(threads=lambda: 2, identity={}, allowed_failures=3, address="tcp://s:1",
                                 spec="tcp://s:1", workers={})
    tasks = batch.plan([(str(tmp_path / f"t{i}.csv"), "") for i in range(4)], str(tmp_path / "out"), "bvh")
    os.makedirs(tmp_path / "out")
    cb = dp_cluster.ClusterBatch(tasks, fake, {}, "bvh", None, str(tmp_path / "out"))
    cb.attempts = {0: 4}
    killed = KilledWorker("dancing-points-x-0", types.SimpleNamespace(address="tcp://w:9"), 3)
    cb._done(tasks[0], Future("error", exc=killed))
    assert tasks[0].status == "failed" and tasks[0].error.startswith("worker died while converting it, 4 times")
    assert "tcp://w:9" in tasks[0].error
    cb._done(tasks[1], Future("cancelled"))
    assert tasks[1].status == "failed" and "cancelled" in tasks[1].error
    cb._done(tasks[2], Future("finished", {"status": "ok", "frames": 7, "seconds": 0.5,
                                           "outputs": {"bvh_leader": b"L\n", "bvh_follower": b"F\n"}}))
    assert tasks[2].status == "ok" and tasks[2].frames == 7
    assert [open(p, "rb").read() for p in tasks[2].outputs] == [b"L\n", b"F\n"]
    assert not leftovers(tmp_path / "out")
    cb._done(tasks[3], Future("finished", {"status": "refused", "error": "worker tcp://w:9 runs ..."}))
    assert cb.refused and cb.fatal == "worker tcp://w:9 runs ..." and tasks[3].status == "pending"
