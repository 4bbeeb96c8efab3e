"""A song's beats and tempo, in numpy: the standard method of Ellis (2007),
"Beat tracking by dynamic programming" (J. New Music Research 36(1)).

1. **Onset strength**: log-magnitude spectral flux (a short-time Fourier
   transform every :data:`HOP_S` seconds, summed over 24 log-spaced bands, the
   increases only), its slow local mean taken away.
2. **Tempo**: the autocorrelation of the onset strength, weighted by a
   log-Gaussian prior around 120 bpm over 60–240 bpm; of a tempo and its
   double (or 3/2), the faster when its autocorrelation is nearly as strong
   (the prior alone would halve a 180 bpm click track, or take every third
   eighth of a song with loud hi-hats for its beat).
3. **Beats**: dynamic programming: each frame's best score is its onset
   strength plus the best score of a previous beat, less a penalty growing
   with the log of how far the gap is from the beat period; the best last beat
   is traced back. Each beat is then moved onto the strongest onset within 1/8
   of a period (sub-frame, by a parabola), and the tempo re-measured as the
   slope of the beats over their numbers.

:func:`track_beats` returns beat times in seconds of the song and the tempo in
beats per minute. A 5-minute song takes about a second.
"""
from __future__ import annotations

import numpy as np

HOP_S = 0.005  # onset-envelope frame step (s)
BPM_RANGE = (60.0, 240.0)
PRIOR_BPM, PRIOR_OCTAVES = 120.0, 1.0  # the tempo prior: log-Gaussian, centre and spread
TIGHTNESS = 100.0  # Ellis's alpha: how strongly the beats keep to the period
DOUBLE_RATIO = 0.95  # take the double tempo when its autocorrelation is at least this of the tempo's
N_BANDS = 24
BLOCK_FRAMES = 2048  # STFT frames computed at a time (memory: a block, not the whole song)


def onset_strength(samples: np.ndarray, rate: float) -> tuple[np.ndarray, float]:
    """``(envelope (F,), frame rate)``: the onset strength every ``hop`` samples;
    frame ``i`` is at time ``i * hop / rate`` (s)."""
    x = np.asarray(samples, dtype=np.float32)
    hop = max(1, int(round(rate * HOP_S)))
    n_fft = 1 << int(np.ceil(np.log2(max(16, 4 * hop))))
    n_frames = len(x) // hop + 1
    pad = np.concatenate([np.zeros(n_fft // 2, np.float32), x, np.zeros(n_fft, np.float32)])
    window = np.hanning(n_fft).astype(np.float32)
    freqs = np.fft.rfftfreq(n_fft, 1.0 / rate)
    edges = np.geomspace(30.0, min(rate / 2, 16000.0), N_BANDS + 1)
    band = np.clip(np.searchsorted(edges, freqs) - 1, -1, N_BANDS)
    keep = (band >= 0) & (band < N_BANDS)
    member = np.zeros((keep.sum(), N_BANDS), np.float32)
    member[np.arange(keep.sum()), band[keep]] = 1.0
    member /= np.maximum(member.sum(0, keepdims=True), 1.0)
    bands = np.empty((n_frames, N_BANDS), np.float32)
    for a in range(0, n_frames, BLOCK_FRAMES):
        b = min(n_frames, a + BLOCK_FRAMES)
        idx = (np.arange(a, b) * hop)[:, None] + np.arange(n_fft)[None, :]
        spec = np.abs(np.fft.rfft(pad[idx] * window, axis=1)).astype(np.float32)
        bands[a:b] = spec[:, keep] @ member
    logb = np.log1p(1000.0 * bands / max(float(bands.max()), 1e-12))
    flux = np.maximum(np.diff(logb, axis=0, prepend=logb[:1]), 0.0).sum(axis=1)
    # the flux rises while an onset enters the window: it peaks about a quarter window early
    shift = int(round(n_fft / 4 / hop))
    flux = np.concatenate([np.zeros(shift, np.float32), flux[:len(flux) - shift]]) if shift else flux
    fps = rate / hop
    width = max(1, int(round(0.4 * fps)))  # take away the slow local mean (a 0.4 s moving average)
    mean = np.convolve(flux, np.ones(2 * width + 1, np.float32) / (2 * width + 1), mode="same")
    env = np.maximum(flux - mean, 0.0)
    std = float(env.std())
    return (env / std if std > 0 else env).astype(np.float64), float(fps)


def _acf(env: np.ndarray, max_lag: int) -> np.ndarray:
    n = len(env)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(env - env.mean(), size)
    ac = np.fft.irfft(f * np.conj(f), size)[:max_lag + 1]
    return ac / np.maximum(n - np.arange(max_lag + 1), 1)  # unbiased: long lags are not penalised


def _peak(ac: np.ndarray, lag: float, halfwidth: int = 2) -> tuple[float, float]:
    """The autocorrelation's highest point within ``halfwidth`` frames of ``lag``: (lag, value)."""
    a = max(1, int(round(lag)) - halfwidth)
    b = min(len(ac) - 1, int(round(lag)) + halfwidth)
    if b < a:
        return lag, 0.0
    i = a + int(np.argmax(ac[a:b + 1]))
    return float(i), float(ac[i])


def estimate_tempo(env: np.ndarray, fps: float) -> float:
    """The tempo (bpm) of an onset envelope (see the module's step 2)."""
    lo, hi = BPM_RANGE
    min_lag, max_lag = int(np.floor(60.0 * fps / hi)), int(np.ceil(60.0 * fps / lo))
    if len(env) < 2 * min_lag:
        return PRIOR_BPM
    ac = _acf(env, min(max_lag + 2, len(env) - 1))
    lags = np.arange(min_lag, min(max_lag, len(ac) - 1) + 1)
    bpm = 60.0 * fps / lags
    prior = np.exp(-0.5 * (np.log2(bpm / PRIOR_BPM) / PRIOR_OCTAVES) ** 2)
    score = np.maximum(ac[lags], 0.0) * prior
    if not np.any(score > 0):
        return PRIOR_BPM
    lag, value = _peak(ac, float(lags[int(np.argmax(score))]))
    while True:  # a faster tempo whose period is half (or two thirds) of this one and as strong: that one
        for f in (0.5, 2.0 / 3.0):
            if lag * f >= min_lag:
                faster, fv = _peak(ac, lag * f)
                if fv >= DOUBLE_RATIO * value:
                    lag, value = faster, fv
                    break
        else:
            break
    # sub-frame: a parabola through the peak and its neighbours
    i = int(lag)
    if 1 <= i < len(ac) - 1:
        y0, y1, y2 = ac[i - 1], ac[i], ac[i + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            lag = i + 0.5 * (y0 - y2) / den
    return float(60.0 * fps / lag)


def _track(env: np.ndarray, period: float) -> np.ndarray:
    """Ellis's dynamic programme: beat frames (ints, increasing)."""
    n = len(env)
    sigma = max(period / 32.0, 1.0)
    k = np.arange(-int(4 * sigma), int(4 * sigma) + 1)
    local = np.convolve(env, np.exp(-0.5 * (k / sigma) ** 2), mode="same")
    lo, hi = max(1, int(round(period / 2))), max(2, int(round(2 * period)))
    gaps = np.arange(hi, lo - 1, -1)  # candidate previous beats: i - gaps
    penalty = -TIGHTNESS * np.log(gaps / period) ** 2
    score = local.copy()
    back = np.full(n, -1, dtype=np.int64)
    for i in range(lo, n):
        j = i - gaps
        ok = j >= 0
        if not ok.any():
            continue
        cand = np.where(ok, score[np.maximum(j, 0)] + penalty, -np.inf)
        best = int(np.argmax(cand))
        if cand[best] > 0:  # start anew where the past has nothing to give
            score[i] += cand[best]
            back[i] = j[best]
    # the last beat: the best-scoring local maximum in the last period
    tail = np.arange(max(0, n - int(np.ceil(period))), n)
    is_max = np.r_[False, (score[1:-1] >= score[:-2]) & (score[1:-1] >= score[2:]), False]
    cands = tail[is_max[tail]] if is_max[tail].any() else tail
    i = int(cands[np.argmax(score[cands])])
    beats = []
    while i >= 0:
        beats.append(i)
        i = int(back[i])
    beats = np.array(beats[::-1], dtype=np.int64)
    # trim the ends where the music is quiet (the tracker carries on through silence)
    if len(beats):
        strong = local[beats] > 0.5 * np.sqrt(np.mean(local[beats] ** 2))
        first, last = np.argmax(strong), len(strong) - np.argmax(strong[::-1])
        beats = beats[first:last]
    return beats


def _refine(env: np.ndarray, beats: np.ndarray, period: float) -> np.ndarray:
    """Each beat moved onto the strongest onset within period/8, sub-frame (a parabola)."""
    w = max(1, int(round(period / 8)))
    out = np.empty(len(beats), np.float64)
    for n, b in enumerate(beats):
        a, c = max(0, b - w), min(len(env), b + w + 1)
        i = a + int(np.argmax(env[a:c]))
        x = float(i)
        if 0 < i < len(env) - 1:
            y0, y1, y2 = env[i - 1], env[i], env[i + 1]
            den = y0 - 2 * y1 + y2
            if den < 0:
                x = i + float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5))
        out[n] = x if env[i] > 0 else float(b)
    return out


def track_beats(samples: np.ndarray, rate: float) -> tuple[np.ndarray, float]:
    """``(beats (B,) seconds, tempo bpm)`` of a mono song; no beats (and the
    tempo estimate) for a song without onsets."""
    env, fps = onset_strength(samples, rate)
    if len(env) < 4 or not np.any(env > 0):
        return np.zeros(0), 0.0
    tempo = estimate_tempo(env, fps)
    period = 60.0 * fps / tempo
    beats = _refine(env, _track(env, period), period) / fps
    if len(beats) >= 4:  # the tempo the beats keep: the slope of the beat times over their numbers
        n = np.arange(len(beats))
        idx = np.rint((beats - beats[0]) / (60.0 / tempo)).astype(np.int64)
        if np.all(np.diff(idx) > 0):
            n = idx
        slope = np.polyfit(n, beats, 1)[0]
        if slope > 0:
            tempo = 60.0 / slope
    return beats, float(tempo)


def count_labels(n: int, per_bar: int = 8) -> list:
    """The dancers' count of ``n`` beats: ``1 2 3 … 8 1 2 …``."""
    return [str(i % per_bar + 1) for i in range(n)]
