"""Dance live in Blender (``operators/live.py``), the extension enabled in
``bpy``: the per-tick function called directly (timers do not run in
background mode) while ``stream`` sends the sample take over 127.0.0.1 — the
time per tick, the latency from a packet's arrival to posed bones, the bones
where the duet frame puts them; Stop keeping the take (a take file beside the
.blend, a take collection, a baked duet that is ``synthesize``'s of that file);
Blender's VR session through a stand-in for ``xr_session_state``; Start / Stop
/ Start again and loading another file while live leaving no thread, socket or
timer; a taken port.
"""
from __future__ import annotations

import glob
import os
import re
import socket
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from support import blender_scene_util as bsu  # noqa: E402
from conftest import MODELS, ROOT  # noqa: E402
from support.ext_util import import_from_extension  # noqa: E402
from support.helpers import free_udp_port  # noqa: E402

from dancing_points_addon.blender_math import C  # noqa: E402
from dancing_points_addon.calibration import headset_take  # noqa: E402
from dancing_points_addon.formats.take import Take, take_to_text  # noqa: E402
from dancing_points_addon.formats.take_read import parse_take_bytes, read_take  # noqa: E402
from dancing_points_addon.live import protocol as P  # noqa: E402
from dancing_points_addon.live.receiver import Sample  # noqa: E402
from dancing_points_addon.live.stream import stream_rows  # noqa: E402
from dancing_points_addon.live.xr import motion_to_xr  # noqa: E402
from dancing_points_addon.runtime import Synthesizer  # noqa: E402
from dancing_points_addon.synthesis_options import SynthesisOptions  # noqa: E402
from dancing_points_addon.skeleton import JOINT_NAMES  # noqa: E402

SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
SPEC_KEYS = ("leader_positions", "leader_rotations", "leader_contacts", "follower_positions", "follower_rotations",
             "follower_contacts", "height_m", "floor_y")
FRAME_MS = 1000.0 / 30.0


@pytest.fixture
def live(dp_extension, monkeypatch):
    monkeypatch.setenv("DP_MODEL_DIR", MODELS)
    bsu.fresh_scene()
    mod = import_from_extension("operators.live")
    yield mod
    if mod.running() is not None:
        mod.stop(keep=False)


def _port_free(port):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("127.0.0.1", port))
        return True
    except OSError:
        return False
    finally:
        s.close()


def _live_threads():
    return [t.name for t in threading.enumerate() if t.name.startswith("dancing_points_live")]


def _settings(source='VMC', port=None, height=0.0, floor=None):
    s = bpy.context.scene.dancing_points_live
    s.source = source
    if port is not None:
        s.port = port
    s.address = "127.0.0.1"
    s.height = height
    s.use_floor_y = floor is not None
    s.floor_y = floor or 0.0
    return s


def _bones(arm):
    """World positions of the SPEC joints of a live armature (the root's head, the others' tails)."""
    mw = np.array(arm.matrix_world)
    pts = [arm.pose.bones[n].head if n == "root" else arm.pose.bones[n].tail for n in JOINT_NAMES]
    return np.array([(mw @ np.array([*p, 1.0]))[:3] for p in pts])


def _offline(path):
    tk = read_take(path)
    return Synthesizer(SynthesisOptions(models=MODELS, height=tk.height)).synthesize(tk)


def _max_diff(a, b):
    a, b = a.arrays(), b.arrays()
    return max(float(np.max(np.abs(np.asarray(a[k], float) - np.asarray(b[k], float)))) for k in SPEC_KEYS)


def _no_leftovers(live, port=None):
    assert live.running() is None
    assert not _live_threads()
    assert not bpy.app.timers.is_registered(live._timer)
    assert bpy.data.collections.get(live.LIVE_COLLECTION) is None
    assert not [o for o in bpy.data.objects if o.name.startswith("DP Live")]
    if port is not None:
        assert _port_free(port)


def test_tick_latency_and_stop_keeps_the_take(live, tmp_path):
    """The sample take streamed at 72 Hz for 8 s; the tick called every 1/120 s
    as the timer would, each followed by the depsgraph update a redraw makes."""
    blend = tmp_path / "scene.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(blend)) == {'FINISHED'}
    port = free_udp_port()
    run = live.start(bpy.context, _settings('VMC', port))
    sender = subprocess.Popen([sys.executable, "-m", "dancing_points_addon", "stream", str(SAMPLE), "--port",
                               str(port), "--rate", "72", "--duration", "8"], cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE, text=True)
    ticks, posed = [], []  # seconds per tick; per posed frame (arrival -> evaluated bones, synthesis, update, k)
    last = -1
    checked = 0
    end = None
    while end is None or time.perf_counter() < end:
        if end is None and sender.poll() is not None:
            end = time.perf_counter() + 0.3
        t0 = time.perf_counter()
        live.tick()
        t1 = time.perf_counter()
        bpy.context.view_layer.update()  # what the redraw that follows evaluates: the armatures, the skinned bodies
        t2 = time.perf_counter()
        ticks.append(t2 - t0)
        if run.posed is not None and run.posed[0] != last:
            last = run.posed[0]
            posed.append((t2 - run.posed[3], run.session.compute_s[last], t2 - t1, last))
            if len(posed) % 10 == 1:  # the bones are where the frame puts them
                for role, frame in zip(("Leader", "Follower"), run.posed[1:3]):
                    err = np.abs(_bones(bpy.data.objects["DP Live " + role]) - frame.positions @ C.T).max()
                    assert err < 1e-5, (role, err)
                checked += 1
        time.sleep(max(0.0, 1.0 / 120.0 - (time.perf_counter() - t0)))
    assert sender.wait() == 0 and checked >= 4
    st = live.status()
    ms = lambda v: f"median {np.median(v):.1f} ms, p99 {np.percentile(v, 99):.1f} ms"  # noqa: E731
    steady = np.array([p for p in posed if p[3] / 30.0 > 2.0]) * [1000.0, 1000.0, 1000.0, 1e-3]
    lat, synth_ms, update_ms = steady[:, 0], steady[:, 1], steady[:, 2]
    ours = lat - synth_ms - update_ms  # the rest: the wait for the tick, reading the rows, posing
    print(f"\nticks: {len(ticks)}, per tick (with the evaluation) {ms(np.array(ticks) * 1000.0)}; ticks that posed "
          f"a frame (with its synthesis): {ms(np.array(run.tick_s) * 1000.0)}")
    print(f"arrival -> posed, evaluated bones, {len(lat)} frames after the first 2 s (of {len(posed)} posed, "
          f"{st['frames']} made): {ms(lat)}; of which synthesis {ms(synth_ms)}, Blender's evaluation of the "
          f"armatures and bodies {ms(update_ms)}, the rest {ms(ours)}")
    assert st["late"] == st["malformed"] == st["ignored"] == 0 and st["used"] == st["datagrams"] > 500
    # What the live path adds to the synthesis and Blender's evaluation stays under one 30 Hz frame,
    # and the loop keeps up (no backlog). The synthesis runs at the machine's speed (about 1 ms a
    # frame when the machine is free); the figures are printed.
    assert np.median(ours) < FRAME_MS
    assert np.median(lat) < 4 * FRAME_MS
    out = live.stop(bpy.context)
    _no_leftovers(live, port)
    # the take file beside the .blend, the take collection, the baked duet
    assert os.path.dirname(out["csv"]) == str(tmp_path)
    tk = read_take(out["csv"])
    assert {"height_m", "floor_y", "devices", "role"} <= set(tk.meta) and tk.meta["devices"] == "joints"
    take, duet_coll = out["take"], out["duet"]
    assert take.dancing_points.kind == 'TAKE' and take.dancing_points.source == out["csv"]
    duet = out["result"].duet
    assert take.dancing_points.n_frames == duet.n_frames
    off = _offline(out["csv"])
    print(f"live duet vs synthesize of its take: {duet.n_frames} frames, max difference {_max_diff(duet, off):g}")
    assert _max_diff(duet, off) <= 1e-9
    arm = next(o for o in duet_coll.objects if o.type == 'ARMATURE' and o.get("dp_role") == "leader")
    frames = [take.dancing_points.frame_start + k for k in (0, duet.n_frames // 2, duet.n_frames - 1)]
    heads, tails = bsu.posed_heads_tails(arm, frames, JOINT_NAMES[1:])
    want = off.leader_positions[[0, duet.n_frames // 2, duet.n_frames - 1]][:, 1:] @ C.T
    assert np.abs(tails - want).max() < 1e-3  # the bake (float32 keys) is that duet


class _XrStandIn:
    """What ``xr_session_state`` offers, fed from a headset take (Blender
    world): ``float32`` gives mathutils values (float32, as Blender's), else
    plain float64 tuples."""

    def __init__(self, float32=True):
        self.loc = self.rot = None
        self.float32 = float32

    def _vec(self, v):
        import mathutils
        return mathutils.Vector(v) if self.float32 else tuple(float(x) for x in v)

    def _quat(self, q):
        import mathutils
        return mathutils.Quaternion(q) if self.float32 else tuple(float(x) for x in q)

    @property
    def viewer_pose_location(self):
        return self._vec(self.loc[0])

    @property
    def viewer_pose_rotation(self):
        return self._quat(self.rot[0])

    def controller_grip_location_get(self, context, index):
        return self._vec(self.loc[1 + index])

    def controller_grip_rotation_get(self, context, index):
        return self._quat(self.rot[1 + index])


@pytest.mark.parametrize("float32", [False, True])
def test_blender_vr_source_gives_the_openxr_takes_duet(live, tmp_path, monkeypatch, float32):
    """Blender's VR session, stood in for by the poses of the sample take as a
    headset records it (SPEC §3 devices=openxr) at 72 Hz: the live duet is
    the duet of that openxr take (height and floor given, as on the panel)."""
    hx = headset_take(read_take(SAMPLE), height=1.75)
    t, pos, quats = stream_rows(hx, 72.0)
    n = 72 * 6
    stand = _XrStandIn(float32)
    monkeypatch.setattr(live, "xr_session_state", lambda context: stand)
    run = live.start(bpy.context, _settings('XR', height=1.75, floor=0.0))
    assert run.receiver is None and not _live_threads()  # all on the main thread
    for i in range(n):
        stand.loc, stand.rot = motion_to_xr(pos[i], quats[i])
        live.tick(now=500.0 + float(t[i]))
    bpy.context.view_layer.update()
    k, a, _, _ = run.posed
    assert np.abs(_bones(bpy.data.objects["DP Live Leader"]) - a.positions @ C.T).max() < 1e-5
    out = live.stop(bpy.context, folder=str(tmp_path), bake_duet=False)
    _no_leftovers(live)
    duet = out["result"].duet
    tk = read_take(out["csv"])
    assert tk.meta["devices"] == "openxr" and float(tk.meta["height_m"]) == 1.75 and float(tk.meta["floor_y"]) == 0
    assert _max_diff(duet, _offline(out["csv"])) <= 1e-9
    # the equivalent take, made from what the stand-in was given: the same rows (times to the
    # microsecond, as the live take keeps them) written as a headset's take file and read back
    equiv = Take(np.round(t[:n] - t[0], 6), pos[:n], quats[:n], {"devices": "openxr", "height_m": 1.75,
                                                                   "floor_y": "0"})
    equiv = parse_take_bytes(take_to_text(equiv).encode(), "<equivalent take>")
    ref = Synthesizer(SynthesisOptions(models=MODELS, height=1.75)).synthesize(equiv)
    assert ref.n_frames == duet.n_frames
    d = {k: float(np.abs(duet.arrays()[k] - ref.arrays()[k]).max()) for k in SPEC_KEYS}
    print(f"\nBlender VR stand-in ({'float32' if float32 else 'float64'} poses) vs the openxr take "
          f"({duet.n_frames} frames): {d}")
    if not float32:  # the same numbers through Blender's axes and back: the same duet
        assert max(d.values()) <= 1e-9
    else:
        # Blender's float32 poses (7 digits) are not the take's; the runtime turns input changes of
        # 1e-9 m into millimetres (its int8 networks round differently), so this differs by more
        assert d["leader_positions"] < 0.02 and d["follower_positions"] < 0.1


def test_start_stop_start_again_and_a_taken_port(live):
    port = free_udp_port()
    tk = read_take(SAMPLE)
    good = P.sample_datagrams("vmc", 0, 0.0, tk.positions[0], tk.quats[0])[0]
    for _ in range(2):
        _settings('VMC', port)
        assert bpy.ops.dancing_points.live_start() == {'FINISHED'}
        run = live.running()
        assert run is not None and run.timer and bpy.app.timers.is_registered(live._timer)
        assert len(_live_threads()) == 1 and not _port_free(port)  # the receiver; the loop runs in the tick
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.sendto(good, ("127.0.0.1", port))
        tx.close()
        deadline = time.perf_counter() + 5
        while run.session.counters.datagrams < 1 and time.perf_counter() < deadline:
            time.sleep(0.01)
        assert run.session.counters.used == 1
        live.tick()
        assert bpy.ops.dancing_points.live_stop(keep=False) == {'FINISHED'}
        _no_leftovers(live, port)
    # the port in use: one clear message, nothing built, nothing left running
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", port))
    try:
        _settings('VMC', port)
        with pytest.raises(Exception, match=f"UDP port {port} is already in use"):
            live.start(bpy.context, bpy.context.scene.dancing_points_live)
        with pytest.raises(RuntimeError, match=f"UDP port {port} is already in use"):  # the operator's one line
            bpy.ops.dancing_points.live_start()
        assert live.running() is None and not _live_threads()
        assert not [o for o in bpy.data.objects if o.name.startswith("DP Live")]
    finally:
        s.close()


def test_loading_another_file_while_live_stops_it(live):
    """Closing the file (read_homefile: load_pre) while live: no thread, socket or
    timer left; the take is kept as a file (the temporary folder: the file was unsaved)."""
    port = free_udp_port()
    _settings('VMC', port)
    assert bpy.ops.dancing_points.live_start() == {'FINISHED'}
    take = read_take(SAMPLE)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for i in range(45):  # 0.5 s of samples
        tx.sendto(P.sample_datagrams("vmc", i, i / 90, take.positions[i], take.quats[i])[0], ("127.0.0.1", port))
        time.sleep(1 / 90)
    tx.close()
    time.sleep(0.2)
    before = set(glob.glob(os.path.join(bpy.app.tempdir, "dancing_points_live_*.csv")))
    bsu.fresh_scene()
    _no_leftovers(live, port)
    (kept,) = set(glob.glob(os.path.join(bpy.app.tempdir, "dancing_points_live_*.csv"))) - before
    assert read_take(kept).n_frames >= 30


class _Layout:
    """A panel's layout that logs what is drawn: ``(kind, name or text)``."""

    def __init__(self, log):
        self.log = log
        self.use_property_split = self.use_property_decorate = False
        self.enabled = self.active = True

    def __getattr__(self, name):  # row, column, box
        return lambda *a, **k: _Layout(self.log)

    def prop(self, data, name, **_):
        self.log.append(("prop", name))

    def operator(self, op, **_):
        self.log.append(("op", op))

    def label(self, text="", **_):
        self.log.append(("label", text))


def test_live_panel_draws(live):
    panel = bpy.types.Panel.bl_rna_get_subclass_py("VIEW3D_PT_dancing_points_live")
    assert panel is not None
    log = []

    class Fake:
        layout = _Layout(log)

    panel.draw(Fake, bpy.context)
    assert ("op", "dancing_points.live_start") in log and ("prop", "port") in log
    port = free_udp_port()
    live.start(bpy.context, _settings('VMC', port))
    log.clear()
    panel.draw(Fake, bpy.context)
    assert ("op", "dancing_points.live_stop") in log
    assert any(k == "label" and t.startswith("Dropped 0") for k, t in log), log
    live.stop(keep=False)


def test_start_refuses_a_height_or_floor_out_of_range(live):
    """Live's Dancer Height and Floor Height have the command line's ranges: hard
    bounds on the properties, and Start refuses in one line what a script or
    an older file holds past them, before anything is built."""
    from dancing_points_addon.formats.limits import FLOOR_RANGE_M
    from dancing_points_addon.formats.limits import HEIGHT_RANGE_M

    port = free_udp_port()
    s = _settings('VMC', port)
    props = s.bl_rna.properties
    assert props["height"].hard_max == HEIGHT_RANGE_M[1]
    assert (props["floor_y"].hard_min, props["floor_y"].hard_max) == (-FLOOR_RANGE_M, FLOOR_RANGE_M)
    for key, value, match in (("height", 50.0, "Live: Dancer Height must be between 0.5 and 3 m, got 50"),
                              ("height", 0.3, "Live: Dancer Height must be between 0.5 and 3 m, got 0.3"),
                              ("floor_y", -50.0, "Live: Floor Height must be within ±1 m, got -50")):
        _settings('VMC', port, floor=0.0)
        s[key] = value  # past the property's bounds
        with pytest.raises(RuntimeError, match=match):
            bpy.ops.dancing_points.live_start()
        _no_leftovers(live, port)


def test_a_failing_calibration_keeps_the_take(live, tmp_path, monkeypatch):
    """Dancer Height 3 m (in range, so Start accepts it) puts the floor of the
    sample take more than 1 m down: the calibration fails on a tick. Stop
    still writes every row received, and says where in one line; a failing
    tick of the timer stops the session the same way (the panel says so)."""
    hx = headset_take(read_take(SAMPLE), height=1.75)
    t, pos, quats = stream_rows(hx, 72.0)
    stand = _XrStandIn(False)
    monkeypatch.setattr(live, "xr_session_state", lambda context: stand)
    real_tick = live.tick
    for by_timer in (False, True):
        folder = tmp_path / ("timer" if by_timer else "stop")
        folder.mkdir()
        assert bpy.ops.wm.save_as_mainfile(filepath=str(folder / "scene.blend")) == {'FINISHED'}
        live.start(bpy.context, _settings('XR', height=3.0))
        fed = iter(range(len(t)))

        def tick(context=None, now=None):
            i = next(fed)
            stand.loc, stand.rot = motion_to_xr(pos[i], quats[i])
            return real_tick(context, now=500.0 + float(t[i]))

        if by_timer:
            monkeypatch.setattr(live, "tick", tick)
            for n in range(1, 200):
                if live._timer() is None:
                    break
            monkeypatch.setattr(live, "tick", real_tick)
            message = live.last_error()
        else:
            with pytest.raises(Exception, match="with a height of 3.00 m the floor would lie"):
                for n in range(1, 200):
                    tick()
            for _ in range(30):  # more rows after the failure (the stream goes on), read at Stop
                i = next(fed)
                live.running().session.put(Sample(500.0 + float(t[i]), {d: (pos[i][d], quats[i][d]) for d in range(3)}))
                n += 1
            with pytest.raises(RuntimeError) as info:
                bpy.ops.dancing_points.live_stop()
            message = str(info.value).strip()
        _no_leftovers(live)
        (csv,) = glob.glob(str(folder / "dancing_points_live_*.csv"))
        assert "\n" not in message
        assert message.endswith(f"Live stopped: the take ({n} rows, no duet made) was saved to {csv}"), message
        assert "with a height of 3.00 m the floor would lie" in message
        kept = read_take(csv)
        assert kept.n_frames == n and kept.height == 3.0 and kept.meta["devices"] == "openxr"
        assert np.allclose(kept.positions, pos[:n], atol=1e-8)
        if by_timer:
            assert not bpy.app.timers.is_registered(live._timer)
            log = []
            panel = bpy.types.Panel.bl_rna_get_subclass_py("VIEW3D_PT_dancing_points_live")
            panel.draw(SimpleNamespace(layout=_Layout(log)), bpy.context)
            assert ("label", message) in log


def test_the_sessions_warnings_are_shown(live, tmp_path, capfd):
    """A stream that says ``role=follower`` into Live set to Leader: the
    session's warning (the role set wins) is in the status the panel draws,
    and Stop reports it (it used to sit in a list nothing showed)."""
    t, pos, quats = stream_rows(read_take(SAMPLE), 72.0)
    assert bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend")) == {'FINISHED'}
    live.start(bpy.context, _settings('OSC', free_udp_port()))
    for i in range(int(2.0 * 72)):
        live.running().session.put(Sample(500.0 + float(t[i]), {d: (pos[i][d], quats[i][d]) for d in range(3)},
                                          meta={"role": "follower", "devices": "joints"}))
        live.tick(now=500.0 + float(t[i]))
    said = "warning: the stream says role=follower; its points are read as the leader's (the role given wins)"
    assert live.status()["warnings"] == [said]
    log = []
    panel = bpy.types.Panel.bl_rna_get_subclass_py("VIEW3D_PT_dancing_points_live")
    panel.draw(SimpleNamespace(layout=_Layout(log)), bpy.context)
    assert ("label", said) in log
    capfd.readouterr()
    assert bpy.ops.dancing_points.live_stop(keep=True) == {'FINISHED'}
    assert said in capfd.readouterr().out
    _no_leftovers(live)


def test_other_senders_are_ignored_and_named(live, tmp_path):
    """Live (VMC) with two senders to its port: the dancer (the sample take,
    72 Hz, 3 s; the sender chosen in *Sender* by its address and port) and the
    same take 1 m aside at 500 Hz, started first. The take kept is the
    dancer's, row for row; the other sender is named with its packets in the
    panel and in Stop's result; the duet is ``synthesize``'s of the take."""
    other = tmp_path / "other.csv"
    tk = read_take(SAMPLE)
    aside = Take(tk.time, tk.positions + np.array([1.0, 0.0, 0.0]), tk.quats, dict(tk.meta))
    other.write_text(take_to_text(aside))
    port, source = free_udp_port(), free_udp_port()
    s = _settings('VMC', port)
    s.sender = "127.0.0.1:{:d}".format(source)
    live.start(bpy.context, s)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    stream = [sys.executable, "-m", "dancing_points_addon", "stream", "--port", str(port)]
    procs = [subprocess.Popen(stream + [str(other), "--rate", "500", "--duration", "4"], cwd=ROOT, env=env,
                              stdout=subprocess.PIPE, text=True)]
    time.sleep(0.3)
    procs.append(subprocess.Popen(stream + [str(SAMPLE), "--rate", "72", "--duration", "3", "--source-port",
                                            str(source)], cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True))
    try:
        while any(p.poll() is None for p in procs):
            live.tick()
            time.sleep(1.0 / 120.0)
        for _ in range(30):
            live.tick()
            time.sleep(0.01)
        st = live.status()
        log = []
        panel = bpy.types.Panel.bl_rna_get_subclass_py("VIEW3D_PT_dancing_points_live")
        panel.draw(SimpleNamespace(layout=_Layout(log)), bpy.context)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    outs = [p.communicate()[0] for p in procs]
    other_sent, other_port = (int(v) for v in re.search(r"sent (\d+) packets.* from port (\d+)", outs[0]).groups())
    assert st["sender"] == "127.0.0.1:{:d}".format(source)
    assert st["ignored_senders"] == [("127.0.0.1:{:d}".format(other_port), other_sent)]
    assert ("label", "  127.0.0.1:{:d}: {:d} packets".format(other_port, other_sent)) in log
    assert any(k == "label" and t.startswith("Input") and "from 127.0.0.1:{:d}".format(source) in t for k, t in log)
    assert st["lost"] == st["late"] == 0 and st["others"] == other_sent
    out = live.stop(bpy.context, folder=str(tmp_path), bake_duet=False)
    _no_leftovers(live, port)
    assert out["ignored"] == st["ignored_senders"] and out["sender"] == st["sender"]
    kept = read_take(out["csv"])
    _, pos, _ = stream_rows(tk, 72.0)
    assert kept.n_frames >= 72 * 3 - 1
    d = np.abs(kept.positions - pos[:kept.n_frames]).max()
    print(f"\nBlender, two senders: kept {kept.n_frames} rows, largest difference from the dancer's {d:g} m; ignored "
          f"{st['ignored_senders']}")
    assert d < 1e-4
    assert _max_diff(out["result"].duet, _offline(out["csv"])) <= 1e-9
