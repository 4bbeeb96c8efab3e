# SPDX-License-Identifier: GPL-3.0-or-later
"""The song of a take in the scene: a sound strip in the scene's sequencer,
placed so that the song lines up with the take, and a timeline marker on every
beat, named by the dancers' count (1 to 8).

The song's analysis (:func:`..dancing_points_addon.audio.analyse_song`: tempo
and beats) is kept on the take's collection (``["dp_song"]``, ``["dp_beats"]``),
so a .blend never analyses its song again. The strip carries
``["dp_take"]`` (its take's name) and the take and its strip list the
markers it made (``["dp_beat_markers"]``): removing the take
(:func:`remove_take`) removes them, never a strip or marker of the user's; a
take deleted otherwise (the Outliner) leaves its strip until the next song is
placed (:func:`sweep_orphans`).

Where the song plays: a take's sample ``k`` (time ``t0 + k/30``) is keyed on
scene frame ``frame_start + k * frame_step``; the song's time ``s`` is the
take's time ``s - audio_offset_s``, so the song's time 0 plays on frame
``frame_start - (audio_offset_s + t0) * 30 * frame_step``. A strip starts on
a whole frame: the fraction is the strip's sound offset (a delay, seconds).
"""

import math
import os

import bpy
import numpy as np
from bpy.props import FloatProperty, StringProperty

from ..dancing_points_addon.audio import Song, analyse_song
from ..dancing_points_addon.beats import count_labels
from ..dancing_points_addon.errors import error_message
from ..dancing_points_addon.resample import NET_FPS
from .kinds import is_take

SONG_PROP = "dp_song"
BEATS_PROP = "dp_beats"
MARKERS_PROP = "dp_beat_markers"
STRIP_TAKE_PROP = "dp_take"


# --------------------------------------------------------------------------- the song on a take

def store_song(coll, song: Song):
    """Keep a song's analysis on its take (saved in the .blend)."""
    coll[SONG_PROP] = {"path": song.path, "offset_s": float(song.offset_s), "duration_s": float(song.duration_s),
                       "tempo_bpm": float(song.tempo_bpm)}
    coll[BEATS_PROP] = [float(b) for b in song.beats]
    s = coll.dancing_points
    s.audio = song.path
    s.audio_offset = float(song.offset_s)


def song_of(coll):
    """The :class:`Song` kept on a take, or None."""
    info = coll.get(SONG_PROP) if coll is not None else None
    if not info:
        return None
    beats = np.array([float(b) for b in coll.get(BEATS_PROP, [])], dtype=np.float64)
    return Song(str(info["path"]), float(info["offset_s"]), float(info.get("duration_s", 0.0)), beats,
                float(info["tempo_bpm"]))


def take_rate(coll):
    """Scene frames per second of a take's keys (30 × its frame step)."""
    step = coll.dancing_points.frame_step
    return NET_FPS * (step if step > 0 else 1.0)


def song_start_frame(coll, song):
    """The scene frame (a float) on which the song's time 0 plays."""
    s = coll.dancing_points
    return s.frame_start - (song.offset_s + s.t0) * take_rate(coll)


def take_time_frame(coll, t):
    """The scene frame (float) of the take's time ``t`` (s)."""
    s = coll.dancing_points
    return s.frame_start + (np.asarray(t, dtype=np.float64) - s.t0) * take_rate(coll)


# --------------------------------------------------------------------------- the strip and markers

def _strips(scene, every=False):
    ed = scene.sequence_editor
    if ed is None:
        return None
    if every:  # (Blender 4.4 renamed sequences to strips; 5.0 dropped the old names)
        return ed.strips_all if hasattr(ed, "strips_all") else ed.sequences_all
    return ed.strips if hasattr(ed, "strips") else ed.sequences


def song_strips(scene, take_name=None):
    """The sound strips Dancing Points placed in ``scene`` (of ``take_name`` only, when given)."""
    strips = _strips(scene, every=True)
    if strips is None:
        return []
    return [st for st in strips if st.get(STRIP_TAKE_PROP) and (take_name is None
                                                                 or st.get(STRIP_TAKE_PROP) == take_name)]


def _remove_markers(scene, holder):
    """Remove the beat markers listed on ``holder`` (a take, or its strip)."""
    made = holder.get(MARKERS_PROP)
    if not made:
        return
    wanted = {}
    for frame, name in zip(made.get("frames", []), str(made.get("names", "")).split(",")):
        wanted[(int(frame), str(name))] = wanted.get((int(frame), str(name)), 0) + 1
    for m in list(scene.timeline_markers):
        key = (m.frame, m.name)
        if wanted.get(key):
            wanted[key] -= 1
            scene.timeline_markers.remove(m)
    del holder[MARKERS_PROP]


def remove_song(scene, coll):
    """Take a take's strip and beat markers out of ``scene`` (the song stays kept on the take)."""
    strips = _strips(scene)
    mine = song_strips(scene, coll.name)
    for st in mine:  # each strip lists the markers placed with it (also a deleted take's, of the same name)
        _remove_markers(scene, st)
        strips.remove(st)
    if mine:
        coll.pop(MARKERS_PROP, None)  # (the same markers: gone with the strip)
    else:
        _remove_markers(scene, coll)  # the strip was deleted by hand: the take's list


def sweep_orphans(scene):
    """Remove the strips (and their beat markers) of takes no longer in the file
    (a take deleted in the Outliner, not with Remove Take)."""
    strips = _strips(scene)
    for st in song_strips(scene):
        if not is_take(bpy.data.collections.get(st[STRIP_TAKE_PROP])):
            _remove_markers(scene, st)
            strips.remove(st)


def place_song(scene, coll, song):
    """Put the take's song in ``scene``: its sound strip and a marker on every beat
    of the take; playback then keeps to the song (AV sync) and scrubbing plays it."""
    remove_song(scene, coll)
    sweep_orphans(scene)
    for other in song_strips(scene):  # one song at a time: the newest take's
        other.mute = True
    start = song_start_frame(coll, song)
    first = math.floor(start + 1e-9)
    scene.sequence_editor_create()
    strips = _strips(scene)
    channel = max((st.channel for st in strips), default=0) + 1
    st = strips.new_sound("DP Song " + coll.name[len("DP Take "):] if coll.name.startswith("DP Take ")
                          else "DP Song " + coll.name, song.path, channel, first)
    try:
        st[STRIP_TAKE_PROP] = coll.name
        if st.frame_start != first:  # (new_sound's start is an int; say a start past the strip range)
            st.frame_start = first
        if hasattr(st, "sound_offset"):
            st.sound_offset = (start - first) / take_rate(coll)  # the fraction of a frame, as a delay
        if st.sound is None or st.frame_final_duration <= 1:
            raise RuntimeError("Blender could not read the song {:s}".format(song.path))
    except Exception:
        strips.remove(st)
        raise
    _add_markers(scene, coll, song)
    st[MARKERS_PROP] = coll[MARKERS_PROP]  # (a copy: the strip's markers go with it if the take goes alone)
    scene.sync_mode = 'AUDIO_SYNC'
    scene.use_audio_scrub = True
    return st


def _add_markers(scene, coll, song):
    s = coll.dancing_points
    t_last = s.t0 + (max(int(s.n_frames), 1) - 1) / NET_FPS
    take_t = np.asarray(song.beats, dtype=np.float64) - song.offset_s
    labels = count_labels(len(take_t))
    keep = np.flatnonzero((take_t >= s.t0 - 0.5 / NET_FPS) & (take_t <= t_last + 0.5 / NET_FPS))
    frames = np.rint(take_time_frame(coll, take_t[keep])).astype(np.int64)
    names = [labels[i] for i in keep.tolist()]
    for name, f in zip(names, frames.tolist()):
        scene.timeline_markers.new(name, frame=int(f))
    coll[MARKERS_PROP] = {"frames": [int(f) for f in frames.tolist()], "names": ",".join(names)}


def remove_take(coll):
    """Delete a take with its song's strip and markers in every scene."""
    from .take_collection import remove_collection

    for scene in bpy.data.scenes:
        remove_song(scene, coll)
    remove_collection(coll)


def scene_song(scene):
    """The song the scene plays from its start frame: ``(path, song time (s) at
    scene.frame_start)`` of its unmuted sound strip (a take's first), or None."""
    strips = _strips(scene, every=True)
    if strips is None:
        return None
    sounds = [st for st in strips if st.type == 'SOUND' and not st.mute and st.sound is not None]
    if not sounds:
        return None
    st = sorted(sounds, key=lambda x: (not x.get(STRIP_TAKE_PROP), x.channel))[0]
    fps = scene.render.fps / (scene.render.fps_base or 1.0)
    t = (scene.frame_start - st.frame_start) / fps - float(getattr(st, "sound_offset", 0.0))
    return bpy.path.abspath(st.sound.filepath, library=st.sound.library), float(t)


class SongPlayer:
    """The scene's song played from a time (s; before its start: silence first)
    on Blender's audio device, for Live; :attr:`started` is the clock then."""

    def __init__(self, path, song_t):
        self.path, self.song_t = path, float(song_t)
        self.handle = None
        self.started = None
        self.error = ""

    def play(self, clock):
        import aud

        self.started = clock
        try:
            sound = aud.Sound(self.path)
            if self.song_t < 0:
                sound = sound.delay(-self.song_t)
            elif self.song_t > 0:
                sound = sound.limit(self.song_t, 1e9)  # from song_t on (cut, not seeked: any device can)
            self.handle = aud.Device().play(sound)
        except Exception as exc:  # noqa: BLE001 - no audio device (a headless Blender): the take still records it
            self.error = error_message(exc, "the song could not be played")
            print("Dancing Points live: " + self.error)

    def offset_at(self, clock):
        """The song's time at the clock time ``clock`` (the take's time 0)."""
        return self.song_t + (clock - self.started)

    def stop(self):
        if self.handle is not None:
            try:
                self.handle.stop()
            except Exception:  # noqa: BLE001 - already ended
                pass
            self.handle = None


def has_song(scene):
    """Whether a take in ``scene`` has its song there (a strip of ours)."""
    return any(not st.mute for st in song_strips(scene))


def load_song(path, offset_s, take_path=None):
    """:func:`analyse_song` of a path as Blender writes it (``//`` relative to the .blend)."""
    return analyse_song(bpy.path.abspath(path), offset_s, take_path)


# --------------------------------------------------------------------------- operators

class DANCING_POINTS_OT_set_song(bpy.types.Operator):
    """Set the song the take was danced to: a sound strip lined up with the take, and its beats as markers"""

    bl_idname = "dancing_points.set_song"
    bl_label = "Set Song"
    bl_options = {'REGISTER', 'UNDO'}

    filepath: StringProperty(name="Song", subtype='FILE_PATH', description="WAV, FLAC, OGG or MP3")
    filter_glob: StringProperty(default="*.wav;*.flac;*.ogg;*.mp3", options={'HIDDEN'})
    offset: FloatProperty(name="Song Offset", default=0.0, min=-3600.0, max=3600.0, unit='TIME_ABSOLUTE',
                          description="The time in the song (s) at the take's time 0")
    take: StringProperty(name="Take", default="", description="The take's collection (empty: the active take)")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def invoke(self, context, event):
        from .props import active_take
        coll = active_take(context, self.take)
        if coll is not None and not self.properties.is_property_set("offset"):
            self.offset = coll.dancing_points.audio_offset
        context.window_manager.fileselect_add(self)
        return {'RUNNING_MODAL'}

    def execute(self, context):
        from .props import active_take
        coll = active_take(context, self.take)
        if coll is None:
            self.report({'ERROR'}, "no take to set the song of: import one")
            return {'CANCELLED'}
        try:
            source = coll.dancing_points.source
            song = load_song(self.filepath, self.offset, source if os.path.isfile(source) else None)
            place_song(context.scene, coll, song)
        except Exception as exc:  # noqa: BLE001 - one line; nothing changed
            self.report({'ERROR'}, error_message(exc, "the song could not be set"))
            return {'CANCELLED'}
        store_song(coll, song)
        self.report({'INFO'}, "Song {:s}: {:.1f} bpm, {:d} beats".format(
            os.path.basename(song.path), song.tempo_bpm, len(song.beats)))
        return {'FINISHED'}


class DANCING_POINTS_OT_remove_take(bpy.types.Operator):
    """Delete the take: its empties, its song's strip and its beat markers (the baked duets stay)"""

    bl_idname = "dancing_points.remove_take"
    bl_label = "Remove Take"
    bl_options = {'REGISTER', 'UNDO'}

    take: StringProperty(name="Take", default="", description="The take's collection (empty: the active take)")

    def execute(self, context):
        from .props import active_take
        coll = active_take(context, self.take)
        if not is_take(coll):
            self.report({'ERROR'}, "no take to remove")
            return {'CANCELLED'}
        name = coll.name
        remove_take(coll)
        self.report({'INFO'}, "Removed take '{:s}'".format(name))
        return {'FINISHED'}


classes = (DANCING_POINTS_OT_set_song, DANCING_POINTS_OT_remove_take)
register, unregister = bpy.utils.register_classes_factory(classes)
