"""Blender's own VR session as a live source: the poses of
``context.window_manager.xr_session_state`` (OpenXR through Blender's VR Scene
Inspection) in motion space.

The viewer pose (``viewer_pose_location`` / ``viewer_pose_rotation``, the
point between the eyes) and the grip poses (``controller_grip_location_get`` /
``controller_grip_rotation_get``, controller 0 the left hand, 1 the right: the
order of the default VR action map's ``/user/hand/left``, ``/user/hand/right``)
are SPEC §3 ``devices=openxr`` poses in Blender's world. Only the world's axes
change at this boundary (Z up -> Y up, :data:`~..blender_math.C`); the
devices' own axes stay OpenXR's (a view looks along its local −Z in Blender as
in OpenXR), so a rotation ``R`` in Blender is ``Cᵀ R`` in motion space.
"""
from __future__ import annotations

import numpy as np

from ..blender_math import C
from ..rotations import matrix_to_quat, quat_to_matrix


def xr_to_motion(locations, rotations):
    """``(positions (3, 3), quats (3, 4) w,x,y,z)`` in motion space of three
    Blender-world poses (head, left grip, right grip): ``locations (3, 3)``,
    ``rotations (3, 4)`` w,x,y,z; a row of NaN stays lost."""
    loc = np.asarray(locations, dtype=np.float64)
    q = np.asarray(rotations, dtype=np.float64)
    ok = np.isfinite(loc).all(-1) & np.isfinite(q).all(-1)
    pos = np.full((3, 3), np.nan)
    quats = np.full((3, 4), np.nan)
    if ok.any():
        pos[ok] = loc[ok] @ C
        quats[ok] = matrix_to_quat(C.T @ quat_to_matrix(q[ok]))
    return pos, quats


def motion_to_xr(positions, quats):
    """The inverse of :func:`xr_to_motion` (what Blender would report)."""
    p = np.asarray(positions, dtype=np.float64)
    q = np.asarray(quats, dtype=np.float64)
    ok = np.isfinite(p).all(-1) & np.isfinite(q).all(-1)
    loc = np.full(p.shape, np.nan)
    rot = np.full(q.shape, np.nan)
    if ok.any():
        loc[ok] = p[ok] @ C.T
        rot[ok] = matrix_to_quat(C @ quat_to_matrix(q[ok]))
    return loc, rot


def read_xr_state(state, context) -> tuple | None:
    """``(locations (3, 3), rotations (3, 4))`` Blender world of a running VR
    session (``xr_session_state``), or None without one. A value Blender
    cannot give (no controller) is a row of NaN."""
    if state is None:
        return None
    loc = np.full((3, 3), np.nan)
    rot = np.full((3, 4), np.nan)
    try:
        loc[0] = tuple(state.viewer_pose_location)
        rot[0] = tuple(state.viewer_pose_rotation)
    except (AttributeError, TypeError, ValueError, RuntimeError):
        return None
    for i in (0, 1):
        try:
            loc[1 + i] = tuple(state.controller_grip_location_get(context, i))
            rot[1 + i] = tuple(state.controller_grip_rotation_get(context, i))
        except (AttributeError, TypeError, ValueError, RuntimeError, IndexError):
            loc[1 + i] = rot[1 + i] = np.nan
    return loc, rot
