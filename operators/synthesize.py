# SPDX-License-Identifier: GPL-3.0-or-later
"""``bpy.ops.dancing_points.synthesize`` (SPEC §8): take in, baked duet out.

From a script (``execute``) it runs to completion. From the UI (``invoke``) it
is modal: the core loop runs in a worker thread (numpy and ONNX Runtime only,
no ``bpy``), a timer shows progress in the status bar and Esc cancels; nothing
in the scene changes before the loop has finished, so cancelling leaves the
scene as it was. The bake then happens on the main thread as one undo step.
"""

import os
import threading
import time

import bpy
from bpy.props import BoolProperty, StringProperty

from ..dancing_points_addon.errors import InputError, UserError, error_message
from ..dancing_points_addon.nets import MODEL_DIR, MODEL_ENV, ModelError
from ..dancing_points_addon.runtime import Synthesizer
from ..dancing_points_addon.synthesis_options import SynthesisOptions
from . import bake, method_view
from .props import active_take
from .take_collection import take_from_collection


def _preferences(context):
    try:
        from ..preferences import get_preferences
        return get_preferences(context)
    except (ImportError, AttributeError):
        return None


def model_dir_choice(context, explicit=""):
    """The models folder the user chose: operator property > ``$DP_MODEL_DIR`` >
    preferences > the bundled ``models/`` (Blender's ``//`` paths made absolute;
    checked by :func:`~.nets.load_nets`)."""
    prefs = _preferences(context)
    for cand in (explicit, os.environ.get(MODEL_ENV, ""), getattr(prefs, "model_dir", "") if prefs else ""):
        if cand:
            return os.path.abspath(bpy.path.abspath(cand))
    return MODEL_DIR


def make_synthesizer(options: SynthesisOptions):
    """A :class:`Synthesizer` for ``options`` (networks from the one cache);
    :class:`ModelError` when the models cannot be loaded."""
    try:
        # the mapping's predictions are kept for the method view (operators/method_view.py); the
        # networks come from the one cache, those of a follower's take when the take says so
        return Synthesizer(options, record_predictions=True)
    except InputError as exc:
        raise ModelError(exc.reason + " in " + exc.path) from None
    except ValueError as exc:
        raise ModelError(str(exc)) from None


class DANCING_POINTS_OT_synthesize(bpy.types.Operator):
    """Synthesise the duet of the active take and bake it into leader and follower armatures"""

    bl_idname = "dancing_points.synthesize"
    bl_label = "Synthesise Duet"
    bl_options = {'REGISTER', 'UNDO'}

    take: StringProperty(name="Take", description="Take collection to use (empty: the active take)",
                         options={'SKIP_SAVE'})
    foot_lock: BoolProperty(name="Foot Locking", default=True,
                            description="Pin feet in contact with the floor (contact-based IK)")
    hand_ik: BoolProperty(name="Hand IK", default=True,
                          description="Put the leader's head and wrists exactly on the tracked points")
    follow_devices: BoolProperty(name="Follow Devices", default=True,
                                 description="Turn the tracked dancer's head and hands as the devices are turned")
    model_dir: StringProperty(name="Model Folder", subtype='DIR_PATH', options={'HIDDEN', 'SKIP_SAVE'},
                              description="Folder with the ONNX models (empty: $DP_MODEL_DIR, the "
                                          "preferences, else the bundled models)")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    # -- shared ------------------------------------------------------------------
    def _prepare(self, context):
        coll = active_take(context, self.take)
        if coll is None:
            if self.take:
                raise UserError("no take named '{:s}'".format(self.take))
            raise UserError("no active take: import one (File > Import > Dancing Points take) "
                            "or select one of its empties")
        take = take_from_collection(context, coll)
        prefs = _preferences(context)
        threads = int(getattr(prefs, "onnx_threads", 1)) if prefs else 1
        synth = make_synthesizer(SynthesisOptions(models=model_dir_choice(context, self.model_dir), threads=threads,
                                                  height=take.height, foot_lock=self.foot_lock, hand_ik=self.hand_ik,
                                                  follow_devices=self.follow_devices))
        return coll, take, synth

    def _error(self, exc):
        self.report({'ERROR'}, error_message(exc, "Dancing Points synthesis failed"))
        return {'CANCELLED'}

    def _finish(self, context, coll, duet, t_synth):
        with bake.user_mode_kept(context):  # the user's object back in its edit or pose mode
            return self._bake(context, coll, duet, t_synth)

    def _bake(self, context, coll, duet, t_synth):
        t0 = time.perf_counter()
        try:
            duet_coll, _ = bake.bake_duet(context, duet, coll.name, coll.dancing_points.frame_start)
        except Exception as exc:
            return self._error(exc)
        t_bake = time.perf_counter() - t0
        try:
            method_view.build_method_view(context, duet_coll, duet, coll, coll.dancing_points.frame_start)
        except Exception as exc:  # the duet stands; the method view is left out whole
            self.report({'WARNING'}, error_message(exc, "Dancing Points method view not built"))
        c = duet.calibration
        if c is not None:  # what was estimated, on the take (the panel shows it)
            s = coll.dancing_points
            s.height_used, s.height_source = c.height, c.height_source
            s.floor_used, s.floor_source = c.floor_y, c.floor_source
            s.orientations_used = c.notice() or ""
        self.report({'INFO'}, "Baked '{:s}': {:d} frames (synthesis {:.1f} s, bake {:.1f} s); {:s}".format(
            duet_coll.name, duet.n_frames, t_synth, t_bake, c.describe() if c is not None else ""))
        if c is not None and c.notice():
            self.report({'WARNING'}, c.notice())
        from .stage import obstacles
        in_the_way = obstacles(context.scene)
        if in_the_way:
            names = ", ".join("'{:s}'".format(o.name) for o in in_the_way)
            self.report({'WARNING'}, "{:s} {:s} where the dancers dance and will hide them in the preview: "
                                     "Preview > Hide in Previews hides {:s} there (nothing is deleted)".format(
                                         names, "stands" if len(in_the_way) == 1 else "stand",
                                         "it" if len(in_the_way) == 1 else "them"))
        return {'FINISHED'}

    # -- from a script -------------------------------------------------------------
    def execute(self, context):
        try:
            coll, take, synth = self._prepare(context)
        except Exception as exc:
            return self._error(exc)
        wm = context.window_manager
        t0 = time.perf_counter()
        wm.progress_begin(0, 100)
        try:
            duet = synth.synthesize(take, progress=lambda i, n: wm.progress_update(100.0 * i / max(n, 1)))
        except KeyboardInterrupt:
            self.report({'WARNING'}, "Synthesis cancelled")
            return {'CANCELLED'}
        except Exception as exc:
            return self._error(exc)
        finally:
            wm.progress_end()
        return self._finish(context, coll, duet, time.perf_counter() - t0)

    # -- from the UI: modal with a worker thread -----------------------------------
    def invoke(self, context, event):
        if context.window is None:
            return self.execute(context)
        try:
            coll, take, synth = self._prepare(context)
        except Exception as exc:
            return self._error(exc)
        self._coll_name = coll.name
        self._state = {"i": 0, "n": max(take.n_frames, 1), "cancel": False, "duet": None, "error": None}
        self._t0 = time.perf_counter()
        state = self._state

        def progress(i, n):
            state["i"], state["n"] = i, n
            return not state["cancel"]

        def work():
            try:
                state["duet"] = synth.synthesize(take, progress=progress)
            except KeyboardInterrupt:
                state["error"] = "cancelled"
            except Exception as exc:  # reported on the main thread
                state["error"] = exc

        self._thread = threading.Thread(target=work, name="dancing_points_synthesis", daemon=True)
        self._thread.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        self._status(context, "Dancing Points: synthesising... (Esc to cancel)")
        return {'RUNNING_MODAL'}

    def _status(self, context, text):
        try:
            context.workspace.status_text_set(text)
        except AttributeError:
            pass

    def _cleanup(self, context):
        wm = context.window_manager
        if getattr(self, "_timer", None) is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        self._status(context, None)

    def modal(self, context, event):
        state = self._state
        if event.type == 'ESC' and event.value == 'PRESS':
            state["cancel"] = True
            self._thread.join()
            self._cleanup(context)
            self.report({'WARNING'}, "Synthesis cancelled; the scene is unchanged")
            return {'CANCELLED'}
        if event.type != 'TIMER':
            return {'PASS_THROUGH'}
        i, n = state["i"], state["n"]
        context.window_manager.progress_update(100.0 * i / max(n, 1))
        self._status(context, "Dancing Points: synthesising frame {:d} / {:d} (Esc to cancel)".format(i, n))
        if self._thread.is_alive():
            return {'RUNNING_MODAL'}
        self._cleanup(context)
        if state["error"] == "cancelled":
            self.report({'WARNING'}, "Synthesis cancelled; the scene is unchanged")
            return {'CANCELLED'}
        if state["error"] is not None:
            return self._error(state["error"])
        coll = bpy.data.collections.get(self._coll_name)
        if coll is None:
            self.report({'ERROR'}, "the take '{:s}' was removed during synthesis".format(self._coll_name))
            return {'CANCELLED'}
        return self._finish(context, coll, state["duet"], time.perf_counter() - self._t0)

    def cancel(self, context):  # the window closed or the file was reloaded
        state = getattr(self, "_state", None)
        if state is not None:
            state["cancel"] = True
            self._thread.join()
        self._cleanup(context)


classes = (DANCING_POINTS_OT_synthesize,)
register, unregister = bpy.utils.register_classes_factory(classes)
