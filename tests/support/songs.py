"""Songs the tests make: clicks at a known tempo, in several formats and rates,
and the clicks found back in a recording (a mixdown, a video's sound)."""

import os
import wave

import numpy as np

CLICK_S = 0.02  # each click: a 20 ms decaying 1.5 kHz tone


def click_samples(bpm, rate, duration_s, first_s=0.3, amplitude=0.6):
    """``(mono float32 samples, click times (s))``: a click every beat from ``first_s``."""
    n = int(round(duration_s * rate))
    x = np.zeros(n, np.float32)
    times = np.arange(first_s, duration_s - CLICK_S - 0.01, 60.0 / bpm)
    k = int(CLICK_S * rate)
    tone = (np.exp(-np.arange(k) / (0.004 * rate)) * np.sin(2 * np.pi * 1500 * np.arange(k) / rate)).astype(np.float32)
    for t in times:
        i = int(round(t * rate))
        x[i:i + k] += amplitude * tone[:len(x[i:i + k])]
    return x, times


def write_song(path, samples, rate):
    """A song file: WAV with Python's ``wave`` (16-bit), FLAC/OGG/MP3 with soundfile."""
    path = str(path)
    if os.path.splitext(path)[1].lower() == ".wav":
        pcm = np.clip(np.round(samples * 32767), -32768, 32767).astype("<i2")
        with wave.open(path, "wb") as w:
            w.setnchannels(1)
            w.setsampwidth(2)
            w.setframerate(int(rate))
            w.writeframes(pcm.tobytes())
    else:
        import soundfile
        soundfile.write(path, samples, int(rate))
    return path


def click_song(path, bpm=120.0, rate=44100, duration_s=6.0, first_s=0.3):
    """Write a click song; return its click times (s)."""
    x, times = click_samples(bpm, rate, duration_s, first_s)
    write_song(path, x, rate)
    return times


def click_onsets(samples, rate, threshold=0.1, gap_s=0.1):
    """The times (s) where the level first passes ``threshold`` (relative to the
    loudest sample) after ``gap_s`` of quiet: each click's start."""
    x = np.abs(np.asarray(samples, dtype=np.float64))
    if x.ndim > 1:
        x = x.max(axis=1)
    loud = np.flatnonzero(x > threshold * max(x.max(), 1e-12))
    if not len(loud):
        return np.zeros(0)
    starts = loud[np.r_[True, np.diff(loud) > gap_s * rate]]
    return starts / float(rate)


def band_samples(bpm, rate=44100, duration_s=12.0, first_s=0.5, seed=1):
    """``(samples, beat times)`` of a drum-kit groove: kick on the odd beats, snare
    on the even ones, a hi-hat on every eighth, a pulsing bass note and noise
    (what a click song is not: onsets of other sounds between the beats)."""
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * rate))
    t = np.arange(n) / rate
    period = 60.0 / bpm
    x = (0.02 * rng.standard_normal(n) + 0.1 * np.sin(2 * np.pi * 110 * t)
         * (0.5 + 0.5 * np.sin(2 * np.pi * t / (4 * period)))).astype(np.float32)

    def decay(seconds, tau, signal):
        k = np.arange(int(seconds * rate))
        return (signal(k) * np.exp(-k / (tau * rate))).astype(np.float32)

    kick = decay(0.15, 0.04, lambda k: np.sin(2 * np.pi * 60 * k / rate))
    snare = 0.5 * decay(0.1, 0.02, lambda k: rng.standard_normal(len(k)))
    hat = 0.2 * decay(0.03, 0.005, lambda k: rng.standard_normal(len(k)))
    beats = np.arange(first_s, duration_s - 0.5, period)
    for i, b in enumerate(beats):
        for at, sound in ((b, kick if i % 2 == 0 else snare), (b, hat), (b + period / 2, hat)):
            j = int(round(at * rate))
            x[j:j + len(sound)] += sound[:len(x[j:j + len(sound)])]
    return x, beats
