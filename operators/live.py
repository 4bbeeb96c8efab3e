# SPDX-License-Identifier: GPL-3.0-or-later
"""Dance live in Blender: ``bpy.ops.dancing_points.live_start`` / ``live_stop``.

The work is the core's (``dancing_points_addon.live``). A network stream (VMC,
OSC) is received by a thread (it stamps each packet's arrival); Blender's own
VR session is read on each tick. A timer on the main thread (:func:`tick`)
runs the live loop on what came (``LiveSession.pump``: at most
:data:`PUMP_BUDGET_S` of synthesis a tick, so the first second's catch-up never
blocks the UI) and poses the two live armatures ("DP Live Leader", "DP Live
Follower", in the collection "DP Live") from the latest duet frame: pose bones
set directly, no keyframes. The loop runs on the main thread rather than in a
second thread of its own: a thread would contend with the UI for Python's
lock, which measured three times the latency. Timers do not run in
background mode; :func:`tick` is the function to call there.

**Stop keeps the take**: the rows the loop used are written as a take file
(SPEC §3, with ``devices``, ``role``, ``height_m``, ``floor_y``) beside the
.blend (in the temporary folder while the file is unsaved), imported as a take
collection (``dancing_points.import_take``), and, optionally, the duet the
loop made is baked on it: the duet ``synthesize`` makes of that file. The live
armatures are removed. When the duet cannot be made (the calibration or the
synthesis fails), Stop still writes every row received and says where. A
failing tick, loading another file (or disabling the extension) while live
stop it the same way, keeping the take file only.
"""

import os
import time

import bpy
import numpy as np
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon.errors import UserError, error_message
from ..dancing_points_addon.formats.limits import FLOOR_RANGE_M, HEIGHT_RANGE_M
from ..dancing_points_addon.live import OSC_PORT, ROLES, VMC_PORT
from ..dancing_points_addon.live.senders import FOLLOW_RESTART_S
from ..dancing_points_addon.live.xr import read_xr_state, xr_to_motion
from . import bake
from .song import SongPlayer, scene_song
from .props import ROLE_PROP, check_dancer

TICK_S = 1.0 / 120.0  # the timer's interval: poses at most this late after their frame
PUMP_BUDGET_S = 0.010  # synthesis a tick at most (frames left over are made on the next ticks)
STATUS_S = 0.25  # the sidebar's status is redrawn this often
XR_REPEAT_S = 0.05  # a VR pose polled again unchanged within this is not a new sample
LIVE_COLLECTION = "DP Live"


def _port_default(source):
    return OSC_PORT if source == 'OSC' else VMC_PORT


def _source_update(self, context):
    if self.port in (VMC_PORT, OSC_PORT):
        self.port = _port_default(self.source)


class DP_LiveSettings(bpy.types.PropertyGroup):
    source: EnumProperty(
        name="Source", default='VMC', update=_source_update,
        items=(('VMC', "VMC", "The VMC protocol over UDP (VirtualMotionCapture, SlimeVR, ...)"),
               ('OSC', "OSC", "Dancing Points' own OSC layout over UDP (/dancing_points/head, lhand, rhand)"),
               ('XR', "Blender VR", "Blender's own VR session (VR Scene Inspection): the headset and "
                                    "controllers as OpenXR reports them")),
    )
    port: IntProperty(name="Port", default=VMC_PORT, min=1, max=65535,
                      description="UDP port to receive on (VMC: 39539, OSC: 39540)")
    address: StringProperty(name="Address", default="0.0.0.0",
                            description="Address to receive on (0.0.0.0: every network; 127.0.0.1: this "
                                        "computer only)")
    role: EnumProperty(name="Role", default=ROLES[0],
                       items=tuple((r, r.capitalize(), "The stream carries the {:s}'s head and hands".format(r))
                                   for r in ROLES))
    height: FloatProperty(name="Dancer Height", default=0.0, min=0.0, max=HEIGHT_RANGE_M[1], soft_max=2.5,
                          unit='LENGTH', precision=3,
                          description="The dancer's standing height, {:g} to {:g} m (0: estimate it from the "
                                      "first second before the duet starts)".format(*HEIGHT_RANGE_M))
    use_floor_y: BoolProperty(name="Floor Given", default=False,
                              description="The real floor's height is known (else: estimated when the height "
                                          "is given, else 0)")
    floor_y: FloatProperty(name="Floor Height", default=0.0, min=-FLOOR_RANGE_M, max=FLOOR_RANGE_M, soft_min=-0.5,
                           soft_max=0.5, unit='LENGTH', precision=3,
                           description="Height of the real floor in the stream's frame, within ±{:g} m".format(
                               FLOOR_RANGE_M))
    sender: StringProperty(name="Sender", default="",
                           description="Take only this sender's samples, ADDR or ADDR:PORT (empty: the first sender "
                                       "whose samples carry a head); every other sender is ignored and counted")
    follow_restart: FloatProperty(name="Follow Restart", default=FOLLOW_RESTART_S, min=0.0, soft_max=10.0,
                                  unit='TIME_ABSOLUTE', precision=1,
                                  description="When the sender has been silent this long, follow it to another "
                                              "port of its address (it started again); 0: never")
    left_serial: StringProperty(name="Left Hand", default="",
                                description="VMC: the left hand's serial (empty: guessed)")
    right_serial: StringProperty(name="Right Hand", default="",
                                 description="VMC: the right hand's serial (empty: guessed)")
    bake: BoolProperty(name="Bake on Stop", default=True,
                       description="Stop bakes the duet onto a new duet collection (the take is kept either way)")


class LiveRun:
    """A running live session and what it made in the scene."""

    def __init__(self, session, receiver, source):
        self.session = session
        self.receiver = receiver
        self.source = source
        self.created = bake.Created()
        self.rigs = {}  # role -> (object name, rest rotations, rest heads)
        self.scale = None  # the armatures' object scale (the dancer's height / the networks')
        self.last_k = -1
        self.posed = None  # the frame last posed: (k, leader, follower DuetFrame, its packet's arrival)
        self.tick_s = []  # seconds per tick that posed a frame
        self.latency_s = []  # seconds from a frame's packet arrival to its posed bones
        self.last_xr = None  # (time, poses) of the last VR poll fed
        self.xr_active = False  # Blender's VR session answered on the last tick
        self.timer = False
        self.next_status = 0.0
        self.error = None
        self.song = None  # the scene's song (song.SongPlayer), played when the dance starts


class StopReport(UserError):
    """Stop could not make the duet: the message says why and what became of the take."""


_RUN = None
_LAST_ERROR = ""  # why the last live recording stopped on its own (a failing tick), and where its take went


def running():
    return _RUN


def last_error():
    """The line saying why the last live recording stopped on its own ("" when it did not)."""
    return _LAST_ERROR


def xr_session_state(context):
    """Blender's VR session state (None without a session). A stand-in replaces
    this in the tests (no headset there)."""
    wm = getattr(context, "window_manager", None)
    return getattr(wm, "xr_session_state", None)


def _options(settings, prefs_threads=1, models=None):
    from ..dancing_points_addon.live.options import LiveOptions

    check_dancer("Live", settings.height, settings.use_floor_y, settings.floor_y)
    source = settings.source.lower()
    return LiveOptions(source=source, height=settings.height or None,
                       floor_y=settings.floor_y if settings.use_floor_y else None, role=settings.role,
                       models=models, threads=prefs_threads, record_predictions=True)


def _build_rigs(context, run, synth):
    coll = run.created.add(bpy.data.collections.new(LIVE_COLLECTION))
    context.scene.collection.children.link(coll)
    bones = synth.role_bone_vectors()
    for role in bake.ROLES:
        label = bake.ROLE_LABEL[role]
        bv = bones[role]  # the networks' size; the object's scale makes the dancer's
        arm = bake.build_armature(context, "DP Live " + label, bv, coll, run.created)
        body = bake.build_body("DP Live {:s} Body".format(label), arm, bv, bake.ROLE_COLOUR[role], coll,
                               run.created)
        arm[ROLE_PROP] = body[ROLE_PROP] = role
        arm.hide_viewport = body.hide_viewport = True  # shown from the first frame
        rest_rot, rest_heads = bake.rest_frames(arm)
        run.rigs[role] = (arm.name, rest_rot, rest_heads)


def start(context, settings):
    """Start a live session with ``settings`` (``Scene.dancing_points_live``)."""
    global _RUN, _LAST_ERROR
    if _RUN is not None:
        raise UserError("a live session is already running: stop it first")
    _LAST_ERROR = ""
    from ..dancing_points_addon.live.protocol import decoder_for
    from ..dancing_points_addon.live.receiver import Counters, UdpReceiver
    from ..dancing_points_addon.live.senders import SenderGate, parse_sender
    from ..dancing_points_addon.live.session import LiveSession
    from .synthesize import _preferences, make_synthesizer, model_dir_choice

    prefs = _preferences(context)
    threads = int(getattr(prefs, "onnx_threads", 1)) if prefs else 1
    options = _options(settings, threads, model_dir_choice(context))
    counters = Counters()
    receiver = gate = None
    sink = []
    if settings.source != 'XR':
        fmt = settings.source.lower()
        want = parse_sender(settings.sender) if settings.sender.strip() else None
        left, right = settings.left_serial or None, settings.right_serial or None
        gate = SenderGate(lambda: decoder_for(fmt, left, right), lambda s: sink[0].put(s), counters, want=want,
                          follow_s=settings.follow_restart)
        receiver = UdpReceiver(gate, settings.port, settings.address or "0.0.0.0")
        receiver.open()  # the port first: a clear error before anything is built
    run = None
    try:
        synth = make_synthesizer(options.synthesis_options())
        describe = "{:s} :{:d} ".format(settings.source.lower(), receiver.port) if receiver else "blender vr "
        session = LiveSession(options, synth, counters, describe=describe)
        session.gate = gate
        run = LiveRun(session, receiver, settings.source)
        _build_rigs(context, run, synth)
    except BaseException:
        if receiver is not None:
            receiver.stop()
        if run is not None:
            run.created.remove_all()
        raise
    sink.append(session)
    if receiver is not None:
        session.listen_to(receiver)
        receiver.start()
    found = scene_song(context.scene)
    if found is not None:
        run.song = SongPlayer(*found)
    _RUN = run
    return run


def _pose(run, frames):
    """Pose both live armatures from one duet frame (leader, follower)."""
    for role, frame in zip(bake.ROLES, frames):
        name, rest_rot, rest_heads = run.rigs[role]
        obj = bpy.data.objects.get(name)
        if obj is None:
            continue
        quats, loc = bm.pose_channels(frame.positions[None] / run.scale, frame.rotations[None], rest_rot, rest_heads)
        bones = obj.pose.bones
        bones.foreach_set("rotation_quaternion", quats[0].ravel())
        bones[0].location = loc[0]
        obj.update_tag(refresh={'OBJECT', 'DATA'})


def tick(context=None, now=None):
    """One tick of the main thread: the VR session polled (Blender VR), the
    latest duet frame posed. ``now``: the sample clock (default the loop's).
    Returns the seconds to the next tick (the timer's), or None when stopped."""
    run = _RUN
    if run is None:
        return None
    context = context or bpy.context
    t0 = time.perf_counter()
    s = run.session
    now = s.clock() if now is None else now
    if run.source == 'XR':
        from ..dancing_points_addon.live.receiver import Sample

        got = read_xr_state(xr_session_state(context), context)
        run.xr_active = got is not None
        if got is not None:
            pos, quats = xr_to_motion(*got)
            poses = {d: (pos[d], quats[d]) for d in range(3) if np.isfinite(pos[d]).all()}
            last = run.last_xr
            if last is None or now - last[0] > XR_REPEAT_S or not _same(last[1], poses):
                run.last_xr = (now, poses)
                s.put(Sample(now, poses))
    elif run.receiver.error is not None and run.error is None:
        run.error = run.receiver.error
    s.pump(now, PUMP_BUDGET_S)
    if run.song is not None and run.song.started is None and s.t_first is not None:
        run.song.play(now)  # the dance starts: the song from the scene's start frame
    latest = s.latest
    if latest is not None and latest[0] != run.last_k:
        if run.scale is None:
            run.scale = 1.0 / s.synth.scale()
            for name, _, _ in run.rigs.values():
                obj = bpy.data.objects.get(name)
                if obj is not None:
                    obj.scale = (run.scale,) * 3
                    obj.hide_viewport = False
                    for child in obj.children:
                        child.hide_viewport = False
        _pose(run, latest[1:3])
        run.last_k = latest[0]
        run.posed = latest
        done = time.perf_counter()
        run.tick_s.append(done - t0)
        run.latency_s.append(done - latest[3])
    if time.perf_counter() >= run.next_status:
        run.next_status = time.perf_counter() + STATUS_S
        _redraw(context)
    return TICK_S


def _same(a, b):
    if a.keys() != b.keys():
        return False
    return all(np.array_equal(a[d][0], b[d][0]) and np.array_equal(a[d][1], b[d][1]) for d in a)


def _redraw(context):
    screen = getattr(context, "screen", None)
    for area in getattr(screen, "areas", ()):
        if area.type == 'VIEW_3D':
            area.tag_redraw()


def _timer():
    try:
        return tick()
    except Exception as exc:  # noqa: BLE001 - a failing tick stops the session, the take kept
        _stop_on_error(exc)
        return None


def _stop_on_error(exc):
    """A tick failed (e.g. the calibration: a height that puts the floor out of
    reach): stop the session, keeping the take file (not imported: this runs
    in a timer), and keep the one line to show (:func:`last_error`)."""
    global _LAST_ERROR
    msg = error_message(exc, "the live tick failed")
    try:
        out = stop(keep=True, collection=False)
        if out is not None:
            msg += "; Live stopped, the take is in " + out["csv"]
    except StopReport as report:  # the duet failed at the stop too: it says why, and where the rows went
        msg = error_message(report)
    except Exception as stop_exc:  # noqa: BLE001 - the tick's error, then the stop's
        msg += "; " + error_message(stop_exc, "the take could not be kept")
    _LAST_ERROR = msg
    print("Dancing Points live: " + msg)
    _redraw(bpy.context)


def start_timer(run):
    if not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=0.0)
    run.timer = True


def status(run=None):
    """The status the sidebar shows: the session's, the posed latency (ms, the
    median of the last frames) and the time per tick."""
    run = run or _RUN
    if run is None:
        return None
    st = run.session.status()
    if run.source == 'XR' and not run.xr_active:
        st["state"] = "waiting for Blender's VR session (start it in the VR sidebar tab)"
    lat = run.latency_s[-60:]
    st["posed_ms"] = 1000.0 * float(np.median(lat)) if lat else float("nan")
    st["tick_ms"] = 1000.0 * float(np.median(run.tick_s[-60:])) if run.tick_s else float("nan")
    st["error"] = error_message(run.error) if run.error is not None else ""
    st["warnings"] = list(run.session.warnings)  # e.g. the stream's role not the one set, metadata lost
    gate = run.session.gate
    st["events"] = list(gate.events) if gate is not None else []  # the sender locked onto, followed
    return st


def take_folder():
    """Beside the .blend; the temporary folder while it is unsaved."""
    path = bpy.data.filepath
    return os.path.dirname(os.path.abspath(path)) if path else bpy.app.tempdir or os.path.abspath(".")


def stop(context=None, keep=True, collection=True, bake_duet=None, folder=None):
    """Stop the session: no thread, socket or timer left. ``keep``: write the
    take file (``folder``, default :func:`take_folder`); ``collection``: import
    it as a take and (``bake_duet``, default the settings') bake the duet.
    Returns ``{"csv", "take", "duet", "result"}`` or None. When the duet cannot
    be made (calibration, synthesis), the rows received are written all the
    same and a :class:`UserError` says why and where."""
    global _RUN
    run, _RUN = _RUN, None
    if run is None:
        return None
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)
    run.timer = False
    try:
        if run.song is not None:
            run.song.stop()
        if run.receiver is not None:
            run.receiver.stop()
        run.session.stop()
    finally:
        try:
            run.created.remove_all()
        except Exception:  # noqa: BLE001 - the file may be going away
            pass
    if not keep:
        return None
    from ..dancing_points_addon.formats.take import write_take

    name = "dancing_points_live_{:s}.csv".format(time.strftime("%Y%m%d-%H%M%S"))
    path = os.path.join(folder or take_folder(), name)
    try:
        result = run.session.finish()
    except Exception as exc:
        # The duet could not be made (the calibration or the synthesis failed):
        # the rows received are written all the same, never lost with it.
        raw = run.session.received_take()
        if raw is None:
            raise  # nothing to keep ("nothing recorded")
        why = error_message(exc, "the live duet failed")
        try:
            write_take(path, raw)
        except Exception as write_exc:  # noqa: BLE001 - both causes in one line
            raise StopReport("{:s}; Live stopped, and the take ({:d} rows) could not be saved: {:s}".format(
                why, raw.n_frames, error_message(write_exc, "writing it failed"))) from exc
        raise StopReport("{:s}; Live stopped: the take ({:d} rows, no duet made) was saved to {:s}".format(
            why, raw.n_frames, path)) from exc
    if run.song is not None and run.song.started is not None and run.session.t_first is not None:
        from ..dancing_points_addon.audio import song_reference
        result.take.meta["audio"] = song_reference(run.song.path, path)  # the song as it played
        result.take.meta["audio_offset_s"] = "{:.6f}".format(run.song.offset_at(run.session.t_first))
    write_take(path, result.take)
    gate = run.session.gate
    out = {"csv": path, "take": None, "duet": None, "result": result, "warnings": list(run.session.warnings),
           "sender": gate.sender() if gate is not None else "", "ignored": gate.ignored() if gate is not None else []}
    if not collection:
        return out
    context = context or bpy.context
    before = {c.name for c in bpy.data.collections}
    if bpy.ops.dancing_points.import_take(filepath=path) != {'FINISHED'}:
        raise UserError("the live take {:s} was written but could not be imported".format(path))
    take = next(c for c in bpy.data.collections if c.name not in before and c.dancing_points.kind == 'TAKE')
    out["take"] = take
    settings = getattr(context.scene, "dancing_points_live", None)
    if bake_duet is None:
        bake_duet = bool(getattr(settings, "bake", True))
    if bake_duet and result.duet is not None:
        from . import method_view

        start_frame = take.dancing_points.frame_start
        duet_coll, _ = bake.bake_duet(context, result.duet, take.name, start_frame)
        try:
            method_view.build_method_view(context, duet_coll, result.duet, take, start_frame)
        except Exception as exc:  # noqa: BLE001 - the duet stands without it
            print("Dancing Points live: " + error_message(exc, "method view not built"))
        c = result.duet.calibration
        s = take.dancing_points
        s.height_used, s.height_source = c.height, c.height_source
        s.floor_used, s.floor_source = c.floor_y, c.floor_source
        out["duet"] = duet_coll
    return out


@persistent
def _on_load_pre(*_args):
    """Another file is loaded while live: stop, keeping the take file only
    (the last recording's error is the old file's: not shown any more)."""
    global _LAST_ERROR
    _LAST_ERROR = ""
    if _RUN is None:
        return
    try:
        out = stop(bpy.context, keep=True, collection=False)
        if out:
            print("Dancing Points live: stopped (a file was loaded); the take is in " + out["csv"])
    except Exception as exc:  # noqa: BLE001 - never block loading
        print("Dancing Points live: " + error_message(exc, "stopped; the take could not be kept"))


# --------------------------------------------------------------------------- operators

class DANCING_POINTS_OT_live_start(bpy.types.Operator):
    """Start dancing live: receive the stream (or Blender's VR session) and pose the live duet as it comes"""

    bl_idname = "dancing_points.live_start"
    bl_label = "Start Live"
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        return _RUN is None and getattr(context.scene, "dancing_points_live", None) is not None

    def execute(self, context):
        settings = context.scene.dancing_points_live
        try:
            run = start(context, settings)
        except Exception as exc:  # noqa: BLE001 - one line, never a traceback
            self.report({'ERROR'}, error_message(exc, "Dancing Points live could not start"))
            return {'CANCELLED'}
        start_timer(run)
        where = "Blender's VR session" if settings.source == 'XR' else \
            "UDP {:s}:{:d} ({:s}), {:s}".format(settings.address, run.receiver.port, settings.source,
                                                "the sender " + settings.sender.strip() if settings.sender.strip()
                                                else "the first sender with a head")
        self.report({'INFO'}, "Live: receiving from " + where)
        return {'FINISHED'}


class DANCING_POINTS_OT_live_stop(bpy.types.Operator):
    """Stop dancing live: keep the take (a take file beside the .blend, imported) and bake the duet"""

    bl_idname = "dancing_points.live_stop"
    bl_label = "Stop Live"
    bl_options = {'REGISTER', 'UNDO'}

    keep: BoolProperty(name="Keep Take", default=True,
                       description="Write the take file and import it (off: discard what was received)")

    @classmethod
    def poll(cls, context):
        return _RUN is not None

    def execute(self, context):
        try:
            out = stop(context, keep=self.keep)
        except Exception as exc:  # noqa: BLE001
            self.report({'ERROR'}, error_message(exc, "Dancing Points live stopped; the take was not kept"))
            return {'CANCELLED'}
        if out is None:
            self.report({'INFO'}, "Live stopped")
        else:
            r = out["result"]
            for line in out["warnings"]:
                self.report({'WARNING'}, line)
            ignored = "".join("; ignored the sender {:s} ({:d} packets)".format(*i) for i in out["ignored"])
            self.report({'INFO'}, "Live stopped: take {:s} ({:d} rows{:s}){:s}{:s}".format(
                out["csv"], r.take.n_frames, ", from " + out["sender"] if out["sender"] else "",
                ", duet baked" if out["duet"] is not None else "", ignored))
        return {'FINISHED'}


classes = (DP_LiveSettings, DANCING_POINTS_OT_live_start, DANCING_POINTS_OT_live_stop)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.dancing_points_live = bpy.props.PointerProperty(type=DP_LiveSettings)
    if _on_load_pre not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_on_load_pre)


def unregister():
    if _RUN is not None:
        try:
            stop(bpy.context, keep=True, collection=False)
        except Exception as exc:  # noqa: BLE001
            print("Dancing Points live: " + error_message(exc, "stopped; the take could not be kept"))
    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
    del bpy.types.Scene.dancing_points_live
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
