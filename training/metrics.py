"""SPEC §6 evaluation metrics, each on one take; :func:`aggregate` frame-weights them.

Every function takes positions ``(T, 31, 3)`` at 30 Hz in motion space (metres)
and returns ``(sum, count)`` so that averages over several takes are
frame-weighted, as the SPEC asks. Scored frames: ``mask`` (bool ``(T,)``).
"""
from __future__ import annotations

import numpy as np

from dancing_points_addon.representation import (CONTACT_HEIGHT, CONTACT_SPEED, floor_levels, foot_speeds,
                                                  hip_frame, hip_heading, segments_gap, to_local, to_world)
from dancing_points_addon.skeleton import FEET, JOINT_INDEX, TRACKED, WRISTS

SKATE_HEIGHT = 0.025


def _masked(values, mask):
    v = values[mask]
    return float(np.sum(v)), int(v.size)


def tracking_error(pred, true, mask):
    d = np.linalg.norm(pred[:, TRACKED] - true[:, TRACKED], axis=-1).mean(-1)
    return _masked(d, mask)


def fullbody_error(pred, true, mask):
    d = np.linalg.norm(pred - true, axis=-1).mean(-1)
    return _masked(d, mask)


def hand_error(pred_lead, pred_follow, true_lead, true_follow, mask, near=0.15):
    """On frames where the closest true leader/follower wrist pair is < 15 cm apart:
    |predicted distance − true distance| of that pair."""
    tl, tf = true_lead[:, WRISTS], true_follow[:, WRISTS]
    pl, pf = pred_lead[:, WRISTS], pred_follow[:, WRISTS]
    td = np.linalg.norm(tl[:, :, None] - tf[:, None, :], axis=-1).reshape(len(tl), 4)
    pd = np.linalg.norm(pl[:, :, None] - pf[:, None, :], axis=-1).reshape(len(pl), 4)
    pair = np.argmin(td, axis=1)
    rows = np.arange(len(td))
    sel = mask & (td[rows, pair] < near)
    return _masked(np.abs(pd[rows, pair] - td[rows, pair]), sel)


def placed(pred, true):
    """``pred`` moved onto ``true``'s placement, per frame: turned about the
    vertical through its pelvis by the hip heading difference, then shifted so
    that its pelvis's floor projection is the true one (heights kept). What is
    left of the difference is the pose."""
    return to_world(to_local(pred, hip_frame(pred)), hip_frame(true))


def placed_pose_error(pred, true, mask):
    """Full-body error with placement factored out: mean joint
    distance after :func:`placed`."""
    return fullbody_error(placed(pred, true), true, mask)


def heading_error(pred, true, mask):
    d = np.angle(np.exp(1j * (hip_heading(pred) - hip_heading(true))))
    return _masked(np.degrees(np.abs(d)), mask)


def circular_correlation(a, b):
    """Circular correlation coefficient (Jammalamadaka–SenGupta) of two angle series."""
    ma = np.angle(np.mean(np.exp(1j * a)))
    mb = np.angle(np.mean(np.exp(1j * b)))
    sa, sb = np.sin(a - ma), np.sin(b - mb)
    den = np.sqrt(np.sum(sa * sa) * np.sum(sb * sb))
    return float(np.sum(sa * sb) / den) if den > 0 else 0.0


def contacts_spec(pos, floor, fps=30.0):
    """SPEC §6 contacts of a motion given the floor levels (from the ground truth)."""
    feet = pos[:, FEET]
    return ((feet[..., 1] - floor) < CONTACT_HEIGHT) & (foot_speeds(feet, fps) < CONTACT_SPEED)


def contact_counts(pred, true, mask, fps=30.0):
    """(tp, fp, fn) of predicted vs true contacts; floor from the ground truth."""
    floor = floor_levels(true[:, FEET, 1])
    pc = contacts_spec(pred, floor, fps)[mask]
    tc = contacts_spec(true, floor, fps)[mask]
    return int(np.sum(pc & tc)), int(np.sum(pc & ~tc)), int(np.sum(~pc & tc))


def foot_skating(pos, mask, floor=None, fps=30.0):
    """Mean horizontal speed (cm/s) of foot points on frame pairs where the point
    is < 2.5 cm above its floor level (both frames of the pair)."""
    feet = pos[:, FEET]
    if floor is None:
        floor = floor_levels(feet[..., 1])
    low = (feet[..., 1] - floor) < SKATE_HEIGHT
    pair_low = low[1:] & low[:-1] & mask[1:, None] & mask[:-1, None]
    v = np.linalg.norm(np.diff(feet[..., [0, 2]], axis=0), axis=-1) * fps * 100.0
    return float(np.sum(v[pair_low])), int(np.sum(pair_low))


def foot_skating_spec(pred, true, mask, fps=30.0):
    """SPEC §6 foot skating of ``pred``: each foot point's floor level from the
    ground truth ``true`` of the take (the 5th percentile of its height)."""
    return foot_skating(pred, mask, floor_levels(true[:, FEET, 1]), fps)


def torso_distance(a, b):
    """Per frame ``(T,)``: closest distance between the two dancers' torso axes
    (the segment from the pelvis to the lower neck, ends of ``root`` and
    ``lowerneck``)."""
    n = JOINT_INDEX["lowerneck"]
    return np.linalg.norm(segments_gap(a[:, 0], a[:, n], b[:, 0], b[:, n]), axis=-1)


def interpenetration(lead, follow, mask, limit=0.15):
    """Frames whose torso axes are closer than ``limit`` (m): ``(count, frames)``."""
    d = torso_distance(lead, follow)
    return _masked((d < limit).astype(float), mask)


def jitter(pos, mask, fps=30.0):
    """Mean norm of the third finite difference of joint positions × fps³ (m/s³)."""
    if len(pos) < 4:
        return 0.0, 0
    j = np.linalg.norm(np.diff(pos, n=3, axis=0), axis=-1).mean(-1) * fps ** 3
    m = mask[3:] & mask[2:-1] & mask[1:-2] & mask[:-3]
    return _masked(j, m)


def aggregate(pairs):
    """Frame-weighted mean of a list of ``(sum, count)``."""
    s = sum(p[0] for p in pairs)
    n = sum(p[1] for p in pairs)
    return s / n if n else float("nan")


def f1(counts):
    tp = sum(c[0] for c in counts)
    fp = sum(c[1] for c in counts)
    fn = sum(c[2] for c in counts)
    return 2 * tp / max(2 * tp + fp + fn, 1)


def rotation_error_deg(pred_rot, target_rot, mask):
    """Mean angle (degrees) between predicted and target rotations ``(T, 3, 3)``
    on the frames of ``mask`` where the target is known (finite)."""
    ok = mask & np.isfinite(target_rot).all(axis=(-1, -2))
    if not ok.any():
        return 0.0, 0
    rel = np.swapaxes(pred_rot[ok], -1, -2) @ target_rot[ok]
    tr = np.trace(rel, axis1=-2, axis2=-1)
    return float(np.degrees(np.arccos(np.clip((tr - 1.0) * 0.5, -1.0, 1.0))).sum()), int(ok.sum())


def max_step(points, mask):
    """Largest per-frame displacement (m) of any of ``points (T, K, 3)`` between
    two frames of ``mask``."""
    d = np.linalg.norm(np.diff(points, axis=0), axis=-1).max(-1)
    m = mask[1:] & mask[:-1]
    return float(d[m].max()) if m.any() else 0.0


def lowest_foot(pos, mask):
    """The lowest height (m) of a foot contact point over the frames of ``mask``."""
    return float(pos[mask][:, FEET, 1].min()) if mask.any() else float("nan")
