"""The song in Blender: the import puts it in the scene as a sound strip lined up
with the take (24, 30 and 60 fps scenes, a later start frame), a marker on
every beat counted in eights; the scene's sound (a mixdown) and the preview
video's sound (AAC, decoded back) have every click on the frame of its take
time; ``batch --render`` too; a bad song is reported and changes nothing;
removing the take removes its strip and markers, not the user's; Live plays
the song from the start frame and records the offset in the kept take.

The clicks are measured on the sound itself (each click's first loud sample),
never on what the add-on says it placed."""
from __future__ import annotations

import os

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from conftest import MODELS, ROOT  # noqa: E402
from support import blender_scene_util as bsu  # noqa: E402
from support.helpers import read_report, run_batch  # noqa: E402
from support.songs import click_onsets, click_song  # noqa: E402
from support.ext_util import import_from_extension  # noqa: E402

SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
OFFSET = 0.25  # the song's time at the take's time 0
BPM = 120.0


def short_take(path, seconds, meta=()):
    lines = SAMPLE.read_text().splitlines()
    body = [ln for ln in lines if not ln.startswith("#")]
    path.write_text("\n".join(list(meta) + body[:1 + int(seconds * 60)]) + "\n")
    return path


@pytest.fixture
def song_take(dp_extension, tmp_path):
    """A 4 s take naming a 6 s click song (120 bpm, FLAC, first click at 0.3 s) at offset 0.25 s."""
    bsu.fresh_scene()
    clicks = click_song(tmp_path / "clicks.flac", BPM, 44100, duration_s=6.0, first_s=0.3)
    take = short_take(tmp_path / "take.csv", 4.0, ["# audio=clicks.flac", "# audio_offset_s={:g}".format(OFFSET)])
    return take, clicks


def _strips(scene):
    """Every strip of the scene's sequencer (Blender 4.4 renamed sequences_all to strips_all)."""
    ed = scene.sequence_editor
    if ed is None:
        return []
    return list(ed.strips_all if hasattr(ed, "strips_all") else ed.sequences_all)


def _click_frames(clicks, frame_start, fps):
    return frame_start + (clicks - OFFSET) * fps  # the take's time 0 (its first row) on frame_start


def _compare(onsets_s, clicks, scene, take_start, fps):
    """Each click heard against its frame: errors in frames (the sound's time 0 is scene.frame_start)."""
    want = (_click_frames(clicks, take_start, fps) - scene.frame_start) / fps
    heard_until = (scene.frame_end - scene.frame_start + 1) / fps - 0.03
    want = want[(want >= 0) & (want <= heard_until)]
    assert len(onsets_s) == len(want), (onsets_s, want)
    return (np.asarray(onsets_s) - want) * fps


@pytest.mark.parametrize("fps", [24, 30, 60])
def test_the_song_plays_in_sync(song_take, tmp_path, fps):
    import soundfile

    take, clicks = song_take
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = fps, 1.0
    assert bpy.ops.dancing_points.import_take(filepath=str(take), update_scene_fps=False,
                                              frame_start=10) == {'FINISHED'}
    strips = _strips(scene)
    assert len(strips) == 1 and strips[0].type == 'SOUND' and strips[0]["dp_take"] == "DP Take take"
    assert scene.sync_mode == 'AUDIO_SYNC' and scene.use_audio_scrub
    # Update Scene Duration as ever: the take's 120 samples at 30 Hz (the song is longer)
    assert scene.frame_start == 10 and scene.frame_end == 10 + int(np.ceil(119 * fps / 30 - 1e-6))
    mix = str(tmp_path / "mix.wav")
    assert bpy.ops.sound.mixdown(filepath=mix, container='WAV', codec='PCM', format='S16') == {'FINISHED'}
    x, rate = soundfile.read(mix)
    err = _compare(click_onsets(x, rate), clicks, scene, 10, fps)
    print(f"\n{fps} fps: {len(err)} clicks heard, worst {np.abs(err).max():.3f} frames from their take frames")
    assert np.abs(err).max() < 1.0
    # markers: one per beat of the take, on its frame (within half a frame), counted 1-8
    marks = sorted((m.frame, m.name) for m in scene.timeline_markers)
    want = _click_frames(clicks, 10, fps)
    want = want[(want >= 10 - fps / 60) & (want <= 10 + 119 * fps / 30 + fps / 60)]
    assert len(marks) == len(want)
    assert np.abs(np.array([f for f, _ in marks]) - want).max() <= 0.5 + 1e-6
    assert [n for _, n in marks] == [str(i % 8 + 1) for i in range(len(marks))]


def test_preview_video_has_the_song(song_take, tmp_path):
    import aud

    take, clicks = song_take
    scene = bpy.context.scene
    assert bpy.ops.dancing_points.import_take(filepath=str(take), frame_start=5) == {'FINISHED'}
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.location, cam.rotation_euler = (0.0, -4.0, 1.2), (1.45, 0.0, 0.0)
    bpy.ops.mesh.primitive_cube_add(location=(0.0, 0.0, 1.0))
    scene.render.resolution_x, scene.render.resolution_y = 96, 64
    scene.frame_end = scene.frame_start + 59  # 2 s of it
    res = bpy.ops.dancing_points.render_preview(filepath=str(tmp_path / "v") + os.sep, file_format='FFMPEG',
                                                resolution_percentage=100)
    assert res == {'FINISHED'}
    assert scene.render.ffmpeg.audio_codec == 'NONE' and not scene.render.use_stamp_marker  # put back
    (video,) = os.listdir(tmp_path / "v")
    sound = aud.Sound(str(tmp_path / "v" / video))
    x = sound.data()
    err = _compare(click_onsets(x, sound.specs[0]), clicks, scene, 5, 30)
    print(f"\npreview video: {len(err)} clicks, worst {np.abs(err).max():.3f} frames from their take frames")
    assert np.abs(err).max() < 1.0
    # PNG frames stay silent: only the images are written
    res = bpy.ops.dancing_points.render_preview(filepath=str(tmp_path / "p") + os.sep, file_format='PNG',
                                                frame_start=5, frame_end=6, resolution_percentage=100)
    assert res == {'FINISHED'} and sorted(os.listdir(tmp_path / "p")) == ["0005.png", "0006.png"]


def test_bad_songs_in_blender(dp_extension, tmp_path):
    """Given to the import: an error and nothing made; named by the take: a
    warning and the take without it; Set Song with a bad file: nothing changed."""
    bsu.fresh_scene()
    scene = bpy.context.scene
    (tmp_path / "text.mp3").write_text("no song here\n" * 50)
    take = short_take(tmp_path / "take.csv", 1.0, ["# audio=text.mp3"])
    before = set(bpy.data.collections.keys())
    with pytest.raises(RuntimeError, match="text.mp3: not a readable song"):
        bpy.ops.dancing_points.import_take(filepath=str(take), audio=str(tmp_path / "text.mp3"))
    with pytest.raises(RuntimeError, match="missing.wav: no such file"):
        bpy.ops.dancing_points.import_take(filepath=str(take), audio=str(tmp_path / "missing.wav"))
    assert set(bpy.data.collections.keys()) == before and not _strips(scene)
    assert bpy.ops.dancing_points.import_take(filepath=str(take)) == {'FINISHED'}  # the warning, the take
    coll = scene.dancing_points.take
    assert coll is not None and coll.get("dp_song") is None
    assert not _strips(scene) and len(scene.timeline_markers) == 0
    click_song(tmp_path / "good.wav", 100, 22050, duration_s=3.0)
    assert bpy.ops.dancing_points.set_song(filepath=str(tmp_path / "good.wav"), offset=0.5) == {'FINISHED'}
    state = [(s.name, s.frame_start, s.sound_offset) for s in _strips(scene)], len(scene.timeline_markers)
    (tmp_path / "empty.ogg").write_bytes(b"")
    with pytest.raises(RuntimeError, match="empty.ogg: empty file"):
        bpy.ops.dancing_points.set_song(filepath=str(tmp_path / "empty.ogg"))
    assert ([(s.name, s.frame_start, s.sound_offset) for s in _strips(scene)], len(scene.timeline_markers)) == state
    assert coll["dp_song"]["offset_s"] == 0.5


def test_removing_the_take_keeps_the_users_strips(song_take, tmp_path):
    take, _ = song_take
    scene = bpy.context.scene
    ed = scene.sequence_editor_create()
    strips = ed.strips if hasattr(ed, "strips") else ed.sequences
    mine = strips.new_sound("My Song", str(tmp_path / "clicks.flac"), 3, 1).name
    scene.timeline_markers.new("1", frame=11)  # the user's, on a beat's frame with a beat's name
    assert bpy.ops.dancing_points.import_take(filepath=str(take), frame_start=10) == {'FINISHED'}
    assert len(_strips(scene)) == 2 and len(scene.timeline_markers) > 5
    assert bpy.ops.dancing_points.remove_take() == {'FINISHED'}
    assert [s.name for s in _strips(scene)] == [mine]
    assert [(m.name, m.frame) for m in scene.timeline_markers] == [("1", 11)]
    assert "DP Take take" not in bpy.data.collections
    # a take deleted in the Outliner: its strip and markers go when the next song is placed
    assert bpy.ops.dancing_points.import_take(filepath=str(take), frame_start=10) == {'FINISHED'}
    from support.ext_util import import_from_extension as ext
    ext("operators.take_collection").remove_collection(bpy.data.collections["DP Take take"])
    assert len(_strips(scene)) == 2
    assert bpy.ops.dancing_points.import_take(filepath=str(take), frame_start=40) == {'FINISHED'}
    assert sorted(s.name for s in _strips(scene)) == sorted([mine, "DP Song take"])
    assert min(m.frame for m in scene.timeline_markers if (m.name, m.frame) != ("1", 11)) >= 40


def test_live_plays_the_song_and_keeps_its_offset(song_take, tmp_path, monkeypatch):
    """Blender Live (its VR source, stood in for) on a scene with the song: the
    kept take names the song and the song's time at the take's time 0."""
    from dancing_points_addon.formats.take_read import read_take

    take, _ = song_take
    monkeypatch.setenv("DP_MODEL_DIR", MODELS)
    live = import_from_extension("operators.live")
    scene = bpy.context.scene
    assert bpy.ops.dancing_points.import_take(filepath=str(take), frame_start=1) == {'FINISHED'}
    scene.frame_start = 31  # the dance starts one second into the take: song time 1.25 s
    tk = read_take(take)
    for t in (-0.5, 1.25):  # played on Blender's device (here its null device), from before or into the song
        player = live.SongPlayer(str(take.parent / "clicks.flac"), t)
        player.play(0.0)
        assert player.handle is not None and player.error == "", player.error
        player.stop()
    played = []
    monkeypatch.setattr(live.SongPlayer, "play", lambda self, clock: (played.append(self.song_t),
                                                                       setattr(self, "started", clock)))
    monkeypatch.setattr(live, "xr_session_state", lambda context: None)
    s = scene.dancing_points_live
    s.source = 'XR'
    run = live.start(bpy.context, s)
    from dancing_points_addon.live.receiver import Sample
    for i in range(0, 120):
        t = 100.0 + i / 60.0
        run.session.put(Sample(t, {d: (tk.positions[i, d], tk.quats[i, d]) for d in range(3)}))
        live.tick(now=t + 0.004)  # each sample seen 4 ms after it came
    out = live.stop(bpy.context, folder=str(tmp_path), bake_duet=False)
    assert played and abs(played[0] - 1.25) < 1e-6
    kept = read_take(out["csv"])
    assert kept.meta["audio"] == "clicks.flac"
    assert abs(float(kept.meta["audio_offset_s"]) - (1.25 - 0.004)) < 1e-6
    strips = [st for st in _strips(scene) if not st.mute]
    assert len(strips) == 1 and strips[0]["dp_take"] == out["take"].name  # the kept take's song plays


def test_batch_render_has_the_song(tmp_path):
    """``batch --render`` (a bpy worker, Blender in the background): the video's clicks on their frames."""
    import aud

    clicks = click_song(tmp_path / "clicks.wav", BPM, 48000, duration_s=4.0, first_s=0.3)
    short_take(tmp_path / "t.csv", 1.0)
    out = tmp_path / "out"
    res = run_batch(tmp_path / "t.csv", out, "npz", "--render", "--audio", tmp_path / "clicks.wav",
                    "--audio-offset", str(OFFSET), jobs=1)
    assert res.returncode == 0, res.stdout + res.stderr
    assert read_report(out)["files"][0]["status"] == "ok"
    d = np.load(out / "t.npz")
    assert float(d["audio_offset_s"]) == OFFSET and abs(float(d["tempo_bpm"]) - BPM) < 1.2
    sound = aud.Sound(str(out / "t.mp4"))
    on = click_onsets(sound.data(), sound.specs[0])
    want = clicks - OFFSET  # the batch's scene: the take's time 0 on its first frame, 30 fps, 31 frames
    want = want[(want >= 0) & (want <= 31 / 30 - 0.03)]
    assert len(on) == len(want) >= 2
    err = (on - want) * 30
    print(f"\nbatch --render: {len(err)} clicks, worst {np.abs(err).max():.3f} frames")
    assert np.abs(err).max() < 1.0
