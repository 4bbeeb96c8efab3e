"""The song a take was danced to (SPEC §3 ``audio``, ``audio_offset_s``): reading
it, checking it, and its beats (:mod:`.beats`) as they go into a duet (SPEC §4
``audio``, ``audio_offset_s``, ``beats``, ``tempo_bpm``).

The synthesis never reads the song: it serves the scene, the preview and the
animator's eye. A song is decoded by ``soundfile`` (libsndfile: WAV, FLAC, OGG,
MP3), the one extra package of the extension; without it, WAV files are still
read by Python's own :mod:`wave`.

A song given on the command line (``--audio``) that cannot be read is bad input
(:class:`~.errors.InputError`: one line, exit 2, nothing written); one named in
a take's metadata that cannot be read is a one-line warning, and the duet is
made without it (:func:`take_song`).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import struct
from dataclasses import dataclass

import numpy as np

from .errors import InputError

AUDIO_TYPES = (".wav", ".flac", ".ogg", ".mp3")
MAX_SONG_S = 3600.0  # an hour: longer is not a song to dance to (and its samples would fill the memory)
MAX_OFFSET_S = 3600.0  # |audio_offset_s| at most this
CACHE_VERSION = 1


@dataclass
class Song:
    """A song, read and analysed: ``path`` absolute, ``offset_s`` the song's time
    at the take's time 0, ``beats`` (B,) in the song's time (s), ``tempo_bpm``."""

    path: str
    offset_s: float
    duration_s: float
    beats: np.ndarray
    tempo_bpm: float

    def beats_in_take(self, t_first=-math.inf, t_last=math.inf) -> np.ndarray:
        """The beats in take time (``song time - offset``) from ``t_first`` to ``t_last``."""
        b = np.asarray(self.beats, dtype=np.float64) - self.offset_s
        return b[(b >= t_first - 1e-9) & (b <= t_last + 1e-9)]

    def arrays(self, time=None) -> dict:
        """The SPEC §4 keys of this song for a duet on ``time`` (its beats within the duet's time)."""
        if time is not None and len(time):  # within half a 30 Hz frame of the duet's ends
            beats = self.beats_in_take(float(time[0]) - 1 / 60, float(time[-1]) + 1 / 60)
        else:
            beats = self.beats_in_take()
        return {"audio": np.array(self.path), "audio_offset_s": np.float64(self.offset_s),
                "beats": beats.astype(np.float64), "tempo_bpm": np.float64(self.tempo_bpm)}


# --------------------------------------------------------------------------- reading

def _riff_truncation(path, f) -> str | None:
    """What is cut off in a WAV (RIFF/RF64) file whose data chunk says more bytes
    than the file holds (libsndfile reads such a file silently), else None."""
    head = f.read(12)
    if len(head) < 12 or head[:4] not in (b"RIFF", b"RF64") or head[8:12] != b"WAVE":
        return None
    size = os.fstat(f.fileno()).st_size
    pos = 12
    while pos + 8 <= size:
        f.seek(pos)
        cid, n = struct.unpack("<4sI", f.read(8))
        if cid == b"data":
            if head[:4] == b"RF64":
                return None  # its real size is in the ds64 chunk; libsndfile checks it
            if pos + 8 + n > size:
                return "truncated: its audio data stops at byte {:d} of {:d}".format(size, pos + 8 + n)
            return None
        pos += 8 + n + (n & 1)
    return "truncated: no audio data chunk" if pos < size or size <= 12 else None


def check_song_file(path) -> str:
    """The absolute path of a readable song file; an :class:`InputError` naming
    it when it is missing, not a file, empty, of another type or cut off."""
    from .formats.files import regular_file

    path = os.path.abspath(os.path.expanduser(os.fspath(path)))
    regular_file(path, "a song", missing="no such file")
    if os.path.splitext(path)[1].lower() not in AUDIO_TYPES:
        raise InputError(path, "not a song file type (expected {:s})".format(", ".join(AUDIO_TYPES)))
    try:
        if os.path.getsize(path) == 0:
            raise InputError(path, "empty file: not a song")
        with open(path, "rb") as f:
            cut = _riff_truncation(path, f)
    except OSError as exc:
        raise InputError(path, "cannot read song ({:s})".format(exc.strerror or str(exc))) from None
    if cut:
        raise InputError(path, cut)
    return path


def read_song(path) -> tuple[np.ndarray, float]:
    """A song's samples, mixed to mono, float32, and its sample rate; every
    failure an :class:`InputError` naming the file."""
    path = check_song_file(path)
    try:
        import soundfile
    except ImportError:
        soundfile = None
    if soundfile is None:
        return _read_wav_stdlib(path)
    with _quiet_stderr():  # libmpg123 prints notes about damaged MP3 frames on the C stderr
        return _read_soundfile(soundfile, path)


@contextlib.contextmanager
def _quiet_stderr():
    """The process's C-level stderr sent to the null device for a while (not in a
    thread other than the main one: the stream is shared)."""
    import sys
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    try:
        sys.stderr.flush()
        fd = sys.__stderr__.fileno() if sys.__stderr__ is not None else 2
        saved = os.dup(fd)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, fd)
        finally:
            os.close(null)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


def _read_soundfile(soundfile, path):
    try:
        info = soundfile.info(path)
        if info.samplerate <= 0 or info.frames <= 0:
            raise InputError(path, "no audio in it")
        if info.frames / info.samplerate > MAX_SONG_S:
            raise InputError(path, "longer than {:g} minutes: not a song".format(MAX_SONG_S / 60))
        data, rate = soundfile.read(path, dtype="float32", always_2d=True)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - libsndfile's errors: not audio, damaged, cut off
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        msg = msg.replace("Error opening {!r}: ".format(path), "").strip().rstrip(".")
        if "not recognised" in msg or "does not exist" in msg or "not a regular file" in msg:
            msg = "not audio, or damaged"
        raise InputError(path, "not a readable song (WAV, FLAC, OGG or MP3): {:s}".format(msg)) from None
    if len(data) == 0:
        raise InputError(path, "no audio in it")
    if info.frames > 0 and len(data) < 0.99 * info.frames - 1:  # libsndfile stops short of a cut-off MP3
        raise InputError(path, "truncated: {:.2f} s of the {:.2f} s it announces".format(
            len(data) / rate, info.frames / rate))
    if not np.isfinite(data).all():
        raise InputError(path, "damaged: samples that are not numbers")
    return data.mean(axis=1, dtype=np.float32), float(rate)


def _read_wav_stdlib(path) -> tuple[np.ndarray, float]:
    import wave

    if os.path.splitext(path)[1].lower() != ".wav":
        raise InputError(path, "reading FLAC, OGG and MP3 needs the soundfile package (pip install soundfile)")
    try:
        with wave.open(path, "rb") as w:
            n, ch, width, rate = w.getnframes(), w.getnchannels(), w.getsampwidth(), w.getframerate()
            raw = w.readframes(n)
    except (wave.Error, EOFError, OSError) as exc:
        raise InputError(path, "not a readable WAV song: {:s}".format(str(exc) or type(exc).__name__)) from None
    if n == 0 or rate <= 0:
        raise InputError(path, "no audio in it")
    if width not in (1, 2, 4):
        raise InputError(path, "{:d}-bit WAV needs the soundfile package".format(8 * width))
    dtype = {1: np.uint8, 2: np.int16, 4: np.int32}[width]
    x = np.frombuffer(raw[:len(raw) // (width * ch) * width * ch], dtype=dtype).astype(np.float32)
    if width == 1:
        x -= 128.0
    x /= float(2 ** (8 * width - 1))
    return x.reshape(-1, ch).mean(axis=1), float(rate)


# --------------------------------------------------------------------------- analysing, with a cache

def _song_key(path) -> dict:
    st = os.stat(path)
    return {"version": CACHE_VERSION, "song": os.path.abspath(path), "size": int(st.st_size),
            "mtime_ns": int(st.st_mtime_ns)}


def cache_path(take_path, song_path) -> str | None:
    """Where a take keeps its song's analysis: ``.<take file>.<song hash>.beats.json``
    beside the take (None when there is no take file)."""
    if not take_path or not os.path.isfile(take_path):
        return None
    folder, name = os.path.split(os.path.abspath(take_path))
    tag = hashlib.sha1(os.path.abspath(song_path).encode("utf-8", "surrogatepass")).hexdigest()[:10]
    return os.path.join(folder, ".{:s}.{:s}.beats.json".format(name, tag))


def _read_cache(cache, key):
    try:
        with open(cache, encoding="utf-8") as f:
            data = json.load(f)
        if data.get("key") != key:
            return None
        beats = np.asarray(data["beats"], dtype=np.float64)
        tempo, duration = float(data["tempo_bpm"]), float(data["duration_s"])
        if beats.ndim != 1 or not np.isfinite(beats).all() or not math.isfinite(tempo):
            return None
        return beats, tempo, duration
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _write_cache(cache, key, beats, tempo, duration) -> None:
    tmp = cache + ".{:d}.tmp".format(os.getpid())
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump({"key": key, "tempo_bpm": tempo, "duration_s": duration,
                       "beats": [round(float(b), 6) for b in beats]}, f)
        os.replace(tmp, cache)
    except OSError:  # a read-only take folder: no cache, the song is analysed again next time
        try:
            os.remove(tmp)
        except OSError:
            pass


def analyse_song(path, offset_s=0.0, take_path=None) -> Song:
    """Read and beat-track a song (:func:`.beats.track_beats`); the result is
    cached beside ``take_path`` (a take file) and reused while the song file is
    unchanged (same path, size and modification time)."""
    from .beats import track_beats

    path = check_song_file(path)
    offset_s = check_offset(offset_s, path)
    key = _song_key(path)
    cache = cache_path(take_path, path)
    hit = _read_cache(cache, key) if cache else None
    if hit is None:
        samples, rate = read_song(path)
        beats, tempo = track_beats(samples, rate)
        duration = len(samples) / rate
        if cache:
            _write_cache(cache, key, beats, tempo, duration)
    else:
        beats, tempo, duration = hit
    return Song(path, offset_s, float(duration), beats, float(tempo))


def check_offset(value, path="<song>", lineno=None) -> float:
    """``audio_offset_s`` as a float within ±:data:`MAX_OFFSET_S` s, else an :class:`InputError`."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(path, "audio_offset_s is not a number: {!r}".format(value), lineno) from None
    if not (math.isfinite(x) and abs(x) <= MAX_OFFSET_S):
        raise InputError(path, "audio_offset_s must be seconds within ±{:g}, got {!r}".format(MAX_OFFSET_S, value),
                         lineno)
    return x


def take_song_path(take) -> str | None:
    """The absolute path of the song a take's metadata names (relative to the take file), or None."""
    name = str(take.meta.get("audio") or "").strip()
    if not name:
        return None
    base = os.path.dirname(os.path.abspath(take.source)) if take.source else os.getcwd()
    return os.path.normpath(os.path.join(base, os.path.expanduser(name)))


def take_song(take, audio=None, audio_offset=None, warn=None) -> Song | None:
    """The song of a take: ``audio`` (a path given by the user: an unreadable one
    is an :class:`InputError`) else the take's ``audio`` metadata (an unreadable
    one is a warning passed to ``warn``, and None); ``audio_offset`` overrides
    the take's ``audio_offset_s``."""
    offset = audio_offset if audio_offset is not None else take.meta.get("audio_offset_s", 0.0)
    take_file = take.source if take.source and os.path.isfile(take.source) else None
    if audio:
        return analyse_song(audio, check_offset(offset, take.source or audio), take_file)
    path = take_song_path(take)
    if path is None:
        return None
    try:
        return analyse_song(path, check_offset(offset, take.source or path), take_file)
    except InputError as exc:
        if warn is not None:
            from .errors import error_message
            warn("{:s}: its song is left out: {:s}".format(take.source or "<take>", error_message(exc)))
        return None


def song_reference(song_path, take_path) -> str:
    """How a take file at ``take_path`` names a song (SPEC §3: relative to the take;
    absolute when they are on different drives)."""
    song_path = os.path.abspath(song_path)
    try:
        return os.path.relpath(song_path, os.path.dirname(os.path.abspath(take_path))).replace(os.sep, "/")
    except ValueError:
        return song_path


def record_song(take, song_path, offset_s, take_path) -> Song:
    """Name a song in a take that will be written at ``take_path`` (its ``audio``
    and ``audio_offset_s`` metadata) and return it analysed (for the duet)."""
    song = analyse_song(song_path, offset_s)
    take.meta["audio"] = song_reference(song.path, take_path)
    take.meta["audio_offset_s"] = "{:.6f}".format(song.offset_s).rstrip("0").rstrip(".") or "0"
    return song
