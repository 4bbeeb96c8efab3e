"""The song a take was danced to, without Blender: songs the tests make (clicks
at a known tempo in WAV, FLAC, OGG and MP3 at several rates) read back, their
beats and tempo found, and the song's keys in the duet (SPEC §4) written by
``synthesize``, ``batch`` and ``live``; a bad song given with ``--audio`` is
one line and exit 2, one named by a take a warning beside the duet."""
import os

import numpy as np
import pytest

from conftest import MODELS, ROOT
from support.helpers import assert_bad_input, run_cli
from support.songs import band_samples, click_song
from dancing_points_addon import audio
from dancing_points_addon.beats import count_labels, track_beats
from dancing_points_addon.errors import InputError
from dancing_points_addon.formats.take_read import parse_take_bytes

SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
BEAT_TOL_S = 0.020
TEMPO_TOL = 0.01


def short_take(path, seconds=3.0, meta=()):
    """The sample take's first ``seconds`` (60 Hz rows) with extra metadata lines."""
    lines = SAMPLE.read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    body = [ln for ln in lines if not ln.startswith("#")]
    path.write_text("\n".join(list(meta) + head + body[:1 + int(seconds * 60)]) + "\n")
    return path


def _match(found, truth):
    """The worst distance (s) from each true beat to a found one and back."""
    a = np.abs(found[:, None] - truth[None, :])
    return float(max(a.min(0).max(), a.min(1).max()))


@pytest.mark.parametrize("ext,rate", [(".wav", 22050), (".flac", 44100), (".ogg", 48000), (".mp3", 44100)])
@pytest.mark.parametrize("bpm", [90, 120, 150, 180])
def test_beats_of_click_songs(tmp_path, ext, rate, bpm):
    """Tempo within 1 % and every beat within 20 ms of the clicks, in every format."""
    truth = click_song(tmp_path / ("s" + ext), bpm, rate, duration_s=8.0, first_s=0.37)
    samples, got_rate = audio.read_song(tmp_path / ("s" + ext))
    assert got_rate == rate and abs(len(samples) / rate - 8.0) < 0.1
    beats, tempo = track_beats(samples, got_rate)
    worst = _match(beats, truth)
    print(f"{ext} {rate} Hz {bpm} bpm: tempo {tempo:.3f} ({100 * abs(tempo - bpm) / bpm:.3f} %), "
          f"{len(beats)}/{len(truth)} beats, worst {1000 * worst:.1f} ms")
    assert abs(tempo - bpm) <= TEMPO_TOL * bpm
    assert worst <= BEAT_TOL_S
    assert len(beats) == len(truth)


@pytest.mark.parametrize("bpm", [90, 128, 170])
def test_beats_of_a_drum_groove(bpm):
    """Kick, snare and hi-hats on the eighths: the beat, not the eighths nor every third eighth."""
    x, truth = band_samples(bpm)
    beats, tempo = track_beats(x, 44100)
    print(f"groove {bpm} bpm: tempo {tempo:.3f}, worst {1000 * _match(beats, truth):.1f} ms")
    assert abs(tempo - bpm) <= TEMPO_TOL * bpm
    assert _match(beats, truth) <= BEAT_TOL_S


def test_no_beats_in_silence():
    beats, tempo = track_beats(np.zeros(44100 * 3, np.float32), 44100)
    assert len(beats) == 0 and tempo == 0.0


def test_count_in_eights():
    assert count_labels(10) == ["1", "2", "3", "4", "5", "6", "7", "8", "1", "2"]


def test_take_metadata(tmp_path):
    body = SAMPLE.read_bytes().split(b"\n", 2)[2]
    take = parse_take_bytes(b"# audio=music/song.mp3\n# audio_offset_s=12.5\n" + body,
                            str(tmp_path / "take.csv"))
    assert take.meta["audio"] == "music/song.mp3" and take.meta["audio_offset_s"] == "12.5"
    assert audio.take_song_path(take) == str(tmp_path / "music" / "song.mp3")
    with pytest.raises(InputError, match=r"take.csv:2: audio_offset_s is not a number"):
        parse_take_bytes(b"# audio=a.wav\n# audio_offset_s=soon\n" + body, str(tmp_path / "take.csv"))
    with pytest.raises(InputError, match=r"take.csv:1: audio_offset_s must be seconds"):
        parse_take_bytes(b"# audio_offset_s=inf\n" + body, str(tmp_path / "take.csv"))


def test_analysis_is_cached_with_the_take(tmp_path, monkeypatch):
    song = tmp_path / "s.flac"
    click_song(song, 128, 44100, duration_s=5.0)
    take = short_take(tmp_path / "t.csv", 1.0)
    first = audio.analyse_song(song, 0.5, take)
    cache = audio.cache_path(take, song)
    assert os.path.isfile(cache) and os.path.basename(cache).startswith(".t.csv.")

    def no_reading(path):
        raise AssertionError("read again")

    monkeypatch.setattr(audio, "read_song", no_reading)
    again = audio.analyse_song(song, 0.25, take)
    assert np.allclose(again.beats, first.beats, atol=1e-6) and again.offset_s == 0.25
    os.utime(song, ns=(0, 0))  # the song changed: analysed anew
    with pytest.raises(AssertionError, match="read again"):
        audio.analyse_song(song, 0.5, take)


# --------------------------------------------------------------------------- the command line

def test_synthesize_records_the_song(tmp_path):
    """``--audio`` / ``--audio-offset`` override the take's; the npz has the song's
    path, offset, tempo and its beats in take time within the duet."""
    truth = click_song(tmp_path / "clicks.ogg", 120, 48000, duration_s=8.0, first_s=0.3)
    take = short_take(tmp_path / "take.csv", 3.0, meta=["# audio=nowhere.wav", "# audio_offset_s=9"])
    out = tmp_path / "duet.npz"
    res = run_cli("synthesize", take, "-o", out, "--models", MODELS, "--audio", tmp_path / "clicks.ogg",
                  "--audio-offset", "0.8")
    assert res.returncode == 0, res.stderr
    assert "warning" not in res.stderr and "120.0 bpm" in res.stdout
    d = np.load(out)
    assert str(d["audio"]) == str(tmp_path / "clicks.ogg") and float(d["audio_offset_s"]) == 0.8
    assert abs(float(d["tempo_bpm"]) - 120) < 1.2
    expected = truth - 0.8
    expected = expected[(expected >= d["time"][0] - 1 / 60) & (expected <= d["time"][-1] + 1 / 60)]
    assert len(d["beats"]) == len(expected) >= 5
    assert np.abs(d["beats"] - expected).max() < BEAT_TOL_S


def test_a_take_names_its_song(tmp_path):
    """The take's own ``audio`` (relative to it) and offset; an unreadable one: a
    one-line warning and the duet without the song's keys."""
    (tmp_path / "music").mkdir()
    click_song(tmp_path / "music" / "song.wav", 100, 22050, duration_s=6.0)
    good = short_take(tmp_path / "good.csv", 2.0, meta=["# audio=music/song.wav", "# audio_offset_s=1.5"])
    res = run_cli("synthesize", good, "-o", tmp_path / "good.npz", "--models", MODELS)
    assert res.returncode == 0, res.stderr
    d = np.load(tmp_path / "good.npz")
    assert str(d["audio"]) == str(tmp_path / "music" / "song.wav") and float(d["audio_offset_s"]) == 1.5
    assert abs(float(d["tempo_bpm"]) - 100) < 1.0
    (tmp_path / "music" / "noise.mp3").write_text("not a song at all\n")
    bad = short_take(tmp_path / "bad.csv", 2.0, meta=["# audio=music/noise.mp3"])
    res = run_cli("synthesize", bad, "-o", tmp_path / "bad.npz", "--models", MODELS)
    assert res.returncode == 0, res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "noise.mp3" in lines[0], res.stderr
    d = np.load(tmp_path / "bad.npz")
    assert "audio" not in d.files and "beats" not in d.files and len(d["time"]) > 30


def _bad_songs(folder):
    good = folder / "good.wav"
    click_song(good, 120, 44100, duration_s=3.0)
    raw = good.read_bytes()
    (folder / "empty.wav").write_bytes(b"")
    (folder / "cut.wav").write_bytes(raw[:len(raw) // 3])
    (folder / "text.flac").write_text("these are not the samples you are looking for\n" * 20)
    return {"missing.wav": "no such file", "empty.wav": "empty file", "cut.wav": "truncated",
            "text.flac": "not a readable song"}


def test_bad_songs_given(tmp_path):
    """Missing, empty, truncated or not audio, with ``--audio``: one line, exit 2,
    nothing written, on synthesize, batch and live."""
    take = short_take(tmp_path / "take.csv", 1.0)
    for name, why in _bad_songs(tmp_path).items():
        out = tmp_path / "duet.npz"
        res = run_cli("synthesize", take, "-o", out, "--models", MODELS, "--audio", tmp_path / name)
        assert_bad_input(res, out, name, why)
    cut = audio.read_song  # a truncated MP3: libsndfile reads less than it announces
    click_song(tmp_path / "whole.mp3", 120, 44100, duration_s=6.0)
    raw = (tmp_path / "whole.mp3").read_bytes()
    (tmp_path / "half.mp3").write_bytes(raw[:len(raw) // 2])
    with pytest.raises(InputError, match="half.mp3: truncated"):
        cut(tmp_path / "half.mp3")
    res = run_cli("batch", take, "-o", tmp_path / "out", "--models", MODELS, "--no-progress",
                  "--audio", tmp_path / "text.flac")
    assert res.returncode == 2 and len(res.stderr.splitlines()) == 1 and "text.flac" in res.stderr, res.stderr
    assert not (tmp_path / "out").exists()
    res = run_cli("live", "--port", "45931", "--duration", "1", "-o", tmp_path / "live.npz", "--models", MODELS,
                  "--audio", tmp_path / "cut.wav")
    assert res.returncode == 2 and "cut.wav: truncated" in res.stderr and len(res.stderr.splitlines()) == 1
    assert not (tmp_path / "live.npz").exists() and not (tmp_path / "live.csv").exists()


def test_batch_records_the_song(tmp_path):
    click_song(tmp_path / "song.flac", 150, 44100, duration_s=5.0)
    take = short_take(tmp_path / "take.csv", 2.0, meta=["# audio=song.flac", "# audio_offset_s=0.2"])
    res = run_cli("batch", take, "-o", tmp_path / "out", "--models", MODELS, "--no-progress", "--jobs", "1",
                  timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    d = np.load(tmp_path / "out" / "take.npz")
    assert str(d["audio"]) == str(tmp_path / "song.flac") and float(d["audio_offset_s"]) == 0.2
    assert abs(float(d["tempo_bpm"]) - 150) < 1.5 and len(d["beats"]) == 5


def test_live_records_the_song_in_its_take(tmp_path):
    """What headless ``live`` writes: the take names the song relative to itself."""
    click_song(tmp_path / "song.wav", 120, 22050, duration_s=4.0)
    take = parse_take_bytes(short_take(tmp_path / "t.csv", 1.0).read_bytes(), str(tmp_path / "t.csv"))
    (tmp_path / "rec").mkdir()
    song = audio.record_song(take, tmp_path / "song.wav", 2.25, tmp_path / "rec" / "live.csv")
    assert take.meta["audio"] == "../song.wav" and take.meta["audio_offset_s"] == "2.25"
    assert song.offset_s == 2.25 and abs(song.tempo_bpm - 120) < 1.2


def test_extract_keeps_the_song_named_from_the_new_take(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    take = short_take(tmp_path / "a" / "take.csv", 0.5, meta=["# audio=song.ogg", "# audio_offset_s=3"])
    res = run_cli("extract", take, "-o", tmp_path / "b" / "copy.csv")
    assert res.returncode == 0, res.stderr
    meta = parse_take_bytes((tmp_path / "b" / "copy.csv").read_bytes(), str(tmp_path / "b" / "copy.csv")).meta
    assert meta["audio"] == "../a/song.ogg" and meta["audio_offset_s"] == "3"
