"""Network feature layouts shared by training and the runtime (one source of truth).

All functions are vectorised over a leading batch axis ``B``. Frames are 30 Hz.

Mapping network (paper §4.3)
    input   the leader's past 0.5 s (frames t−14 … t): per frame its root relative
            to the window's first root (4) and its three tracked points in that
            first root's frame (9)                                 -> 15 × 13 = 195
    output  the next 1 s (frames t+1 … t+30) of both dancers: per frame and
            dancer, the root relative to the leader's current root (4) and the
            three tracked points in that frame's own root (9)      -> 30 × 26 = 780

Placement network
    input   the mapping's (195)
    output  the mapping's layout (780); the runtime reads her roots from it

Tracking network (paper §4.2), one dancer
    input   current pose in its own root F0: positions (93), rotations as 6D (186),
            contacts (4); at the future keys ``TRACK_KEYS``: root relative to F0
            (4) and tracked points in that key's own root (9)
    output  at the same keys: root relative to F0 (4), positions (93) and 6D
            rotations (186) in that key's own root, contacts (4)
"""
from __future__ import annotations

import numpy as np

from .representation import (compose_rows, relative_rows, root_relative, rot6d, rot6d_to_matrix, rot_to_local,
                             to_local)

FPS = 30.0  # the networks' frame rate (every 30 Hz in the runtime, resampling and live is this one)
PAST = 15
FUTURE = 30
N_JOINTS = 31
TRACK_KEYS = np.array([1, 2, 4, 6, 9, 12, 15, 20, 25, 30])

ROOT_DIM = 4                   # a root: (x, z, cos, sin)
POINTS_DIM = 9                 # the three tracked points, (3, 3)
FRAME_DIM = ROOT_DIM + POINTS_DIM  # one dancer at one frame or key: root, then points
FRAME_ROOT = slice(0, ROOT_DIM)
FRAME_POINTS = slice(ROOT_DIM, FRAME_DIM)

MAP_IN = PAST * FRAME_DIM
MAP_OUT = FUTURE * 2 * FRAME_DIM
POSE_DIM = N_JOINTS * 3 + N_JOINTS * 6 + 4
TRACK_IN = POSE_DIM + len(TRACK_KEYS) * FRAME_DIM
KEY_OUT = ROOT_DIM + N_JOINTS * 3 + N_JOINTS * 6 + 4
TRACK_OUT = len(TRACK_KEYS) * KEY_OUT

# Named slices of a pose feature vector (POSE_DIM) and of one key of the
# tracking output (KEY_OUT): use these, never the numbers.
POSE_POS = slice(0, N_JOINTS * 3)                                   # 0:93 local joint positions
POSE_ROT = slice(POSE_POS.stop, POSE_POS.stop + N_JOINTS * 6)      # 93:279 6D rotations
POSE_CON = slice(POSE_ROT.stop, POSE_ROT.stop + 4)                 # 279:283 foot contacts
KEY_ROOT = slice(0, ROOT_DIM)                                       # 0:4 root relative to F0
KEY_POS = slice(KEY_ROOT.stop, KEY_ROOT.stop + N_JOINTS * 3)        # 4:97
KEY_ROT = slice(KEY_POS.stop, KEY_POS.stop + N_JOINTS * 6)          # 97:283
KEY_CON = slice(KEY_ROT.stop, KEY_ROT.stop + 4)                     # 283:287


def pose_positions(pose: np.ndarray) -> np.ndarray:
    """Local joint positions ``(..., 31, 3)`` of pose features ``(..., POSE_DIM)``."""
    return pose[..., POSE_POS].reshape(pose.shape[:-1] + (N_JOINTS, 3))


def pose_rotations(pose: np.ndarray) -> np.ndarray:
    """Local joint rotation matrices ``(..., 31, 3, 3)`` of pose features."""
    return rot6d_to_matrix(pose[..., POSE_ROT].reshape(pose.shape[:-1] + (N_JOINTS, 6)))


def layout() -> dict:
    """Feature layout, written into the ONNX metadata."""
    return {"fps": FPS, "past": PAST, "future": FUTURE, "track_keys": TRACK_KEYS.tolist(),
            "map_in": MAP_IN, "map_out": MAP_OUT,
            "track_in": TRACK_IN, "track_out": TRACK_OUT, "key_out": KEY_OUT, "pose_dim": POSE_DIM,
            "rotation": "6d (first two columns)", "root": "(x, z, cos, sin), heading from +Z towards +X"}


def mapping_input(roots: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """``roots (B, PAST, 4)``, ``tracked (B, PAST, 3, 3)`` world -> ``(B, MAP_IN)``."""
    B = len(roots)
    ref = roots[:, 0]
    out = np.empty((B * PAST, FRAME_DIM))
    out[:, FRAME_ROOT] = relative_rows(ref.T.repeat(PAST, axis=1), roots.reshape(-1, 4).T).T
    # all points of a window in one (N, 3) @ (3, 3) product
    p = to_local(tracked.reshape(-1, 3), ref[0]) if B == 1 else to_local(tracked.reshape(B, -1, 3), ref)
    out[:, FRAME_POINTS] = p.reshape(-1, POINTS_DIM)
    return out.reshape(B, MAP_IN)


def mapping_inputs(first_roots: np.ndarray, first_tracked: np.ndarray, roots: np.ndarray,
                   tracked: np.ndarray) -> np.ndarray:
    """:func:`mapping_input` of frames in a row, ``(B, MAP_IN)``: the first one's
    window ``(PAST, 4)``, ``(PAST, 3, 3)``, then each next frame's root ``(B − 1, 4)``
    and points ``(B − 1, 3, 3)`` (each window slid on by one). Each row has the
    bits its window alone gives."""
    r, p = np.concatenate([first_roots, roots]), np.concatenate([first_tracked, tracked])
    idx = np.arange(len(roots) + 1)[:, None] + np.arange(PAST)
    return mapping_input(r[idx], p[idx])


def _dancer_future(ref, roots, tracked):
    r = root_relative(ref[:, None], roots)
    p = to_local(tracked, roots).reshape(roots.shape[:2] + (POINTS_DIM,))
    return np.concatenate([r, p], axis=-1)


def mapping_target(lead_root_t, lead_roots, lead_tracked, fol_roots, fol_tracked) -> np.ndarray:
    """Future ``(B, FUTURE, …)`` world roots/tracked of both dancers -> ``(B, MAP_OUT)``."""
    a = _dancer_future(lead_root_t, lead_roots, lead_tracked)
    b = _dancer_future(lead_root_t, fol_roots, fol_tracked)
    return np.concatenate([a, b], axis=-1).reshape(len(lead_root_t), -1)


def splice_follower_roots(y: np.ndarray, roots_from: np.ndarray) -> np.ndarray:
    """The mapping output ``y`` ``(B, MAP_OUT)`` with the follower's predicted roots
    (position and heading, every future frame) taken from ``roots_from``, an
    output of the same layout (the placement network's); a new array."""
    out = np.array(y, copy=True)
    o = out.reshape(len(out), FUTURE, 2, FRAME_DIM)
    o[:, :, 1, FRAME_ROOT] = np.asarray(roots_from).reshape(o.shape)[:, :, 1, FRAME_ROOT]
    return out


def decode_mapping(y: np.ndarray, lead_root_t: np.ndarray):
    """``(B, MAP_OUT)`` -> per dancer (leader, follower): world roots ``(B, FUTURE, 4)``
    and tracked points in their own roots ``(B, FUTURE, 3, 3)``."""
    B = len(y)
    y = y.reshape(B * FUTURE * 2, FRAME_DIM)  # batch × frame × dancer
    rel = y[:, FRAME_ROOT].T.astype(np.float64, order="C")  # component rows (4, n): see compose_rows
    h = rel[2:4]
    h /= np.maximum(np.sqrt(np.einsum("ij,ij->j", h, h)), 1e-9)
    roots = compose_rows(lead_root_t.T.repeat(FUTURE * 2, axis=1), rel)  # both dancers at once
    roots = np.ascontiguousarray(roots.T).reshape(B, FUTURE, 2, 4)
    tracked = y[:, FRAME_POINTS].astype(np.float64).reshape(B, FUTURE, 2, 3, 3)
    return [(roots[:, :, d], tracked[:, :, d]) for d in range(2)]


def pose_features(pos_local, rot_local, contacts) -> np.ndarray:
    """``(B, 31, 3)``, ``(B, 31, 3, 3)``, ``(B, 4)`` -> ``(B, POSE_DIM)``."""
    B = len(pos_local)
    out = np.empty((B, POSE_DIM))
    out[:, POSE_POS] = pos_local.reshape(B, -1)
    out[:, POSE_ROT] = rot6d(rot_local).reshape(B, -1)
    out[:, POSE_CON] = contacts.reshape(B, 4)
    return out


def tracking_input(pose_feat, f0, key_roots, key_tracked_local) -> np.ndarray:
    """Pose features ``(B, POSE_DIM)``, current root ``f0 (B, 4)``, world roots at the
    keys ``(B, K, 4)`` and tracked points in their own roots ``(B, K, 3, 3)``."""
    B, K = len(pose_feat), len(TRACK_KEYS)
    out = np.empty((B, TRACK_IN))
    out[:, :POSE_DIM] = pose_feat
    fut = out[:, POSE_DIM:].reshape(B, K, FRAME_DIM)
    fut[..., FRAME_ROOT] = relative_rows(f0.T.repeat(K, axis=1), key_roots.reshape(-1, 4).T).T.reshape(B, K, 4)
    fut[..., FRAME_POINTS] = key_tracked_local.reshape(B, K, POINTS_DIM)
    return out


def tracking_target(f0, key_roots, key_pos_world, key_rot_world, key_contacts) -> np.ndarray:
    """Ground-truth future at the keys (world) -> ``(B, TRACK_OUT)``."""
    B, K = key_roots.shape[:2]
    r = root_relative(f0[:, None], key_roots)
    p = to_local(key_pos_world, key_roots).reshape(B, K, -1)
    q = rot6d(rot_to_local(key_rot_world, key_roots)).reshape(B, K, -1)
    return np.concatenate([r, p, q, key_contacts.reshape(B, K, 4)], axis=-1).reshape(B, -1)


def split_tracking_output(y: np.ndarray):
    """``(B, TRACK_OUT)`` -> rel roots ``(B,K,4)``, local positions ``(B,K,31,3)``,
    local rotations ``(B,K,31,3,3)``, contacts ``(B,K,4)``."""
    B = len(y)
    y = y.reshape(B, -1, KEY_OUT)  # all keys (training) or only the first (exported)
    rel = y[..., KEY_ROOT].copy()
    h = rel[..., 2:4]
    h /= np.maximum(np.sqrt(np.einsum("...i,...i->...", h, h)), 1e-9)[..., None]
    pos = y[..., KEY_POS].reshape(B, -1, N_JOINTS, 3)
    rot = rot6d_to_matrix(y[..., KEY_ROT].reshape(B, -1, N_JOINTS, 6))
    con = y[..., KEY_CON]
    return rel, pos, rot, con


def window_indices(t: np.ndarray, n: int, offsets: np.ndarray) -> np.ndarray:
    """Frame indices ``t + offsets`` clamped to ``[0, n)`` (padding by repetition)."""
    return np.clip(t[:, None] + offsets[None, :], 0, n - 1)
