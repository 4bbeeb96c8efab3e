"""Any input as a take: the SPEC §3 take file, a CMU AMC, a BVH or an FBX motion
(:func:`load_input`), and the one set of rules every take must meet before it
is synthesised (:func:`check_take`), wherever it came from: the command line,
the batch and the Blender import all apply them."""
from __future__ import annotations

import os
import sys

import numpy as np

from .errors import InputError
from .formats.files import regular_file
from .formats.limits import MAX_ABS_TIME_S, MAX_GAP_S, check_duration, check_height, check_rate
from .resample import NET_FPS, resample_plan, tracked_after_resampling
from .formats.rig_rest import asf_rest_corrections, rig_problem_line
from .formats.take import DEVICES, MAX_DISTANCE_M, ORIENTATIONS_PROBLEM_KEY, Take, take_from_motion, take_from_tracked
from .formats.take_read import read_take
from .skeleton import HEAD_BONE, JOINT_INDEX, WRISTS

HAND_BONES = (JOINT_INDEX["lhand"], JOINT_INDEX["rhand"])  # what the grips of openxr devices are rigid on

def check_take(take: Take, path=None) -> Take:
    """The rules every input must meet before it is resampled and synthesised,
    wherever it came from (the command line, batch and the Blender import all
    apply them, through :func:`load_input` or directly):

    * at least 2 rows, finite and strictly increasing times within
      ±:data:`MAX_ABS_TIME_S` s, no gap over :data:`MAX_GAP_S` s, at most
      :data:`MAX_DURATION_S` s from first to last row;
    * no position farther than :data:`MAX_DISTANCE_M` from the origin;
    * at least two frames at the networks' 30 Hz (a duration of 1/30 s);
    * some device tracked on some 30 Hz frame (not every device lost on every row),
      and the head on some row (the duet is placed and turned by it).

    Returns ``take``; raises :class:`InputError` naming ``path`` (default
    ``take.source``).
    """
    path = path if path is not None else (take.source or "<take>")
    n = take.n_frames
    if n < 2:
        raise InputError(path, f"only {n} frame(s); a take needs at least 2")
    time = np.asarray(take.time, dtype=np.float64)
    with np.errstate(all="ignore"):
        if not np.isfinite(time).all():
            raise InputError(path, "time values must be finite")
        big = np.abs(time) > MAX_ABS_TIME_S
        if big.any():
            r = int(np.flatnonzero(big)[0])
            raise InputError(path, f"time {time[r]:.6g} s of frame {r + 1} is out of range (more than "
                                   f"{MAX_ABS_TIME_S:g} s from 0; time is in seconds)")
        dt = np.diff(time)
        if not (dt > 0).all():
            r = int(np.flatnonzero(~(dt > 0))[0])
            raise InputError(path, f"time must increase strictly (frame {r + 2})")
        if dt.max() > MAX_GAP_S:
            r = int(np.argmax(dt))
            raise InputError(path, f"gap of {dt[r]:.6g} s between frames {r + 1} and {r + 2} "
                                   f"(more than {MAX_GAP_S:g} s; split the take there)")
    check_duration(path, float(time[-1] - time[0]))
    with np.errstate(all="ignore"):
        far = np.linalg.norm(np.asarray(take.positions, dtype=np.float64), axis=-1) > MAX_DISTANCE_M
    if far.any():
        r, d = (int(x) for x in np.argwhere(far)[0])
        raise InputError(path, f"{DEVICES[d]} position of frame {r + 1} is more than {MAX_DISTANCE_M:g} m "
                               f"from the origin")
    valid = take.valid
    if not valid.any():
        raise InputError(path, "no tracked samples: every device is lost on every row")
    if not valid[:, 0].any():
        raise InputError(path, "the head is lost on every row: a take needs the head device (the duet is "
                               "placed and turned by it)")
    _, i, a = resample_plan(time, NET_FPS)
    if len(i) < 2:
        raise InputError(path, f"too short: {float(time[-1] - time[0]):.4g} s gives {len(i)} frame at "
                               f"{NET_FPS:g} Hz; a take needs at least 2 (1/{NET_FPS:g} s)")
    if not tracked_after_resampling(valid, i, a).any():
        raise InputError(path, f"no tracked samples at {NET_FPS:g} Hz: no device is tracked on any "
                               f"frame of the resampled take")
    return take


INPUT_TYPES = (".csv", ".amc", ".bvh", ".fbx")


def load_input(path, asf=None, input_fps=None, height=None, role=None) -> Take:
    """Any supported input as a take at its source rate (see :func:`_load`);
    ``role``: of a file with several dancers (an FBX duet), whose to read."""
    return _load(path, asf, input_fps, height, role=role)[0]


def load_headset_input(path, asf=None, input_fps=None, height=None, offsets=None, role=None) -> Take:
    """What a headset and two controllers would record of the input's dancer
    (SPEC §3 ``devices=openxr``: ``extract --devices openxr``), through
    :func:`~..calibration.headset_take`: from a full-body motion (AMC, a CMU
    BVH) with the hand bones' own rotations, from a take or another BVH with
    its hand orientations taken as the hands'. A take already ``openxr`` is
    returned as it is."""
    from .calibration import headset_take

    take, hands = _load(path, asf, input_fps, height, want_hands=True, role=role)
    if take.meta.get("devices") == "openxr":
        return take
    return headset_take(take, hands, height=height, offsets=offsets)


def _load(path, asf=None, input_fps=None, height=None, want_hands=False, role=None):
    """:func:`load_input`, and with ``want_hands`` the hand bones' global
    rotations ``(T, 2, 3, 3)`` where the input has them (else None)."""
    """Any supported input as a take at its source rate.

    * ``.csv`` take file (SPEC §3). ``input_fps`` replaces the time column by
      ``t0 + k / input_fps`` (``t0`` the first row's time): the rows are taken
      as regular samples at that rate.
    * ``.amc`` CMU motion (ASF beside it or ``asf``); ``input_fps`` overrides
      the default rate (60 Hz for subjects 60/61, else 120 Hz).
    * ``.bvh`` motion; ``input_fps`` overrides its Frame Time.
    * ``.fbx`` motion, read by Blender's FBX importer in a ``bpy`` process
      (:func:`.fbx.load_fbx`; without the ``bpy`` module, an :class:`InputError`
      saying how); ``input_fps`` overrides the file's frame rate.

    ``height`` (metres, within :data:`HEIGHT_RANGE_M`) is stored as
    ``meta['height_m']``; ``input_fps`` must be within :data:`INPUT_FPS_RANGE`.
    Only regular files are read (not a FIFO or device). The result passes
    :func:`check_take`. Anything wrong with the input is an :class:`InputError`
    (checked before anything the size of the take's duration is allocated),
    including unexpected failures of a parser on a malformed file.
    """
    path = os.fspath(path)
    if input_fps is not None:
        input_fps = check_rate(path, input_fps)
    if height is not None:
        height = check_height(path, height)
    regular_file(path, "an input file", missing="no such file")
    ext = os.path.splitext(path)[1].lower()
    if ext not in INPUT_TYPES:
        raise InputError(path, f"unsupported input type {ext or '(no extension)'!r} "
                               f"(expected {', '.join(INPUT_TYPES)})")
    hands = None
    try:
        with np.errstate(all="ignore"):  # overflows are checked for and reported, never warned
            if ext == ".csv":
                take = read_take(path)
                if input_fps is not None:
                    check_duration(path, (take.n_frames - 1) / input_fps,
                                   what=f"the take ({take.n_frames} rows at {input_fps:g} Hz)")
                    take.time = take.time[0] + np.arange(take.n_frames) / input_fps
            elif ext == ".fbx":
                from .formats.fbx import load_fbx
                take = _checked_motion_take(path, load_fbx(path, input_fps, role))
            elif ext == ".amc":
                if asf is not None:
                    regular_file(os.fspath(asf), "an ASF file", missing="no such ASF file")
                from .formats.asf_amc import load_amc
                motion = load_amc(path, asf, fps=input_fps)
                take = _checked_motion_take(path, _amc_take(motion), ext)
                hands = motion.rotations[:, list(HAND_BONES)] if want_hands else None
            else:
                take, hands = _take_from_bvh(path, input_fps, want_hands)
                take = _checked_motion_take(path, take, ext)
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "file too large to load") from None
    except Exception as exc:  # a parser tripped over a malformed file
        raise InputError(path, f"cannot read {ext[1:].upper()} file "
                               f"({type(exc).__name__}: {exc})") from None
    if height is not None:
        take.meta["height_m"] = height
    problem = take.meta.pop(ORIENTATIONS_PROBLEM_KEY, None)
    if problem:  # a full-body rig whose orientations cannot be read: said once, where it is read
        print("warning: " + rig_problem_line(path, problem), file=sys.stderr)
    take.source = path
    return check_take(take, path), hands


def _checked_motion_take(path, take: Take, ext=".fbx") -> Take:
    """A take computed from a full-body motion (BVH, AMC, FBX): every value
    finite and every point within :data:`MAX_DISTANCE_M` (what :func:`read_take`
    accepts, so ``extract`` never writes a take it would reject). The message
    names the frame's line in a BVH or AMC file (one frame a row: the take is
    at the file's own rate)."""
    with np.errstate(all="ignore"):
        bad = ~(np.isfinite(take.positions).all(-1) & np.isfinite(take.quats).all(-1))
        bad |= np.linalg.norm(take.positions, axis=-1) > MAX_DISTANCE_M
    if bad.any():
        r, d = (int(x) for x in np.argwhere(bad)[0])
        line = None
        if ext == ".amc":
            from .formats.asf_amc import frame_line
            line = frame_line(path, r)
        elif ext == ".bvh":
            from .formats.bvh_parse import frame_line
            line = frame_line(path, r)
        raise InputError(path, f"{DEVICES[d]} point of frame {r + 1} is out of range (more than "
                               f"{MAX_DISTANCE_M:g} m from the origin, or not a finite number)", line)
    return take


def _amc_take(motion) -> Take:
    """The take of an AMC motion: :func:`take_from_motion`, its orientations
    relative to the SPEC rest pose when the ASF rests otherwise (an A-pose;
    the CMU skeletons rest in the SPEC's T-pose and are read as they are)."""
    take = take_from_motion(motion)
    Q, problem = asf_rest_corrections(motion.bone_vectors)
    if Q is not None and np.array_equal(Q, np.broadcast_to(np.eye(3), Q.shape)):
        return take
    rot = motion.rotations
    r = [rot[:, HEAD_BONE], rot[:, WRISTS[0]], rot[:, WRISTS[1]]]
    if Q is not None:
        r = [r[k] @ Q[k] for k in range(3)]
    return take_from_tracked(take.time, take.positions, *r, take.meta, take.source, problem)


def _take_from_bvh(path, input_fps=None, want_hands=False):
    """The take of a BVH file, and (``want_hands``, CMU naming) its hand bones' rotations."""
    from .formats import bvh

    data = bvh.parse_bvh(path, input_fps=input_fps)
    if want_hands and bvh.detect_naming(data) == "cmu":
        motion = bvh.bvh_to_motion(data)
        take = take_from_motion(motion)
        take.source = path
        return take, motion.rotations[:, list(HAND_BONES)]
    tp = bvh.tracked_points(data)
    positions = np.asarray(tp.positions, dtype=np.float64)
    rotations = np.asarray(tp.rotations, dtype=np.float64)
    # tp.fps is 1 / Frame Time, snapped to a whole rate when the file rounded it.
    time = np.arange(positions.shape[0]) / float(tp.fps)
    return take_from_tracked(time, positions, rotations[:, 0], rotations[:, 1], rotations[:, 2],
                             {}, path, tp.problem), None
