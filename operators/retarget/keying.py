# SPDX-License-Identifier: GPL-3.0-or-later
"""Writing the retargeted motion as keys on the target rig (a new action, marked
as the retarget's output), and reading a keyed rig's world matrices back from
its action. The rig's previous action is kept (a fake user when it would have
none) unless it is an earlier output of the retarget: that one is removed once
the new one is in place, when nothing else uses it (:func:`release`)."""

import bpy
import numpy as np

from ...dancing_points_addon import retarget as rt
from ...dancing_points_addon.rotations import axis_angle_to_quat, euler_to_matrix, quat_to_axis_angle, quat_to_matrix
from .. import compat
from .props import OUTPUT_PROP
from .rig import mat


def _path(name, prop):
    return 'pose.bones["{:s}"].{:s}'.format(bpy.utils.escape_identifier(name), prop)


def is_output(action):
    """Whether ``action`` is a retarget's output as it made it (:func:`mark_output`;
    renamed or copied, it is the user's)."""
    return action is not None and action.get(OUTPUT_PROP) == action.name


def mark_output(action):
    """Mark ``action`` as made by the retarget (:func:`release` may remove it once replaced)."""
    action[OUTPUT_PROP] = action.name


def release(action):
    """Remove ``action``, a retarget's output that a new one replaced, when nothing
    uses it any more; one the user assigned elsewhere or gave a fake user (Blender's
    "keep this") stays. (The retarget gives its outputs no fake user.)"""
    if is_output(action) and action.users == 0:
        bpy.data.actions.remove(action)


def key_rig(obj, basis, frames, action_name, bones=None, extra=()):
    """A NEW action on ``obj`` keying every bone's location, rotation (in the pose
    bone's own rotation mode) and scale from ``matrix_basis (T, B, 4, 4)``.
    ``bones``: the names of the bones of ``basis`` (default: all the rig's
    bones); ``extra``: more channels to key, ``(data path, index, values (T,), group)``."""
    names = [b.name for b in obj.data.bones] if bones is None else list(bones)
    modes = [obj.pose.bones[n].rotation_mode for n in names]
    loc, rot, scale = rt.channels(basis, modes)
    old, _ = compat.assigned_action(obj)
    if old is not None and old.users <= 1 and not old.use_fake_user and not is_output(old):
        old.use_fake_user = True  # keep the rig's own previous action when the new one replaces it
    action, slot = compat.new_action_for(obj, action_name)

    def key(name, prop, values):
        for i in range(values.shape[-1]):
            compat.write_keys(compat.ensure_fcurves(action, slot, _path(name, prop), i, name), frames, values[:, i])

    for b, name in enumerate(names):
        mode = modes[b]
        key(name, "location", loc[:, b, :3])
        if mode == 'QUATERNION':
            key(name, "rotation_quaternion", rot[:, b, :4])
        elif mode == 'AXIS_ANGLE':
            key(name, "rotation_axis_angle", quat_to_axis_angle(rot[:, b]))
        else:
            key(name, "rotation_euler", rot[:, b, :3])
        key(name, "scale", scale[:, b, :3])
    for path, index, values, group in extra:
        compat.write_keys(compat.ensure_fcurves(action, slot, path, index, group), frames, np.asarray(values))
    return action


def keyed_world(obj, ret, frames):
    """World matrices ``(T, B, 4, 4)`` of a rig keyed by :func:`key_rig`, read back
    from its action (numpy forward kinematics, no scene evaluation)."""
    action, slot = compat.assigned_action(obj)
    names = [b.name for b in obj.data.bones]
    T, B = len(frames), len(names)
    basis = np.broadcast_to(np.eye(4), (T, B, 4, 4)).copy()
    for b, name in enumerate(names):
        pb = obj.pose.bones[name]

        def get(prop, n):
            default = getattr(pb, prop)
            out = []
            for i in range(n):
                fc = compat.find_fcurve(action, slot, _path(name, prop), i)
                out.append(compat.sample_fcurve(fc, frames) if fc is not None else np.full(T, default[i]))
            return np.stack(out, -1)

        loc = get("location", 3)
        scl = get("scale", 3)
        if pb.rotation_mode == 'QUATERNION':
            R = quat_to_matrix(get("rotation_quaternion", 4))
        elif pb.rotation_mode == 'AXIS_ANGLE':
            R = quat_to_matrix(axis_angle_to_quat(get("rotation_axis_angle", 4)))
        else:
            xyz = get("rotation_euler", 3)
            R = euler_to_matrix(xyz[:, ["XYZ".index(a) for a in pb.rotation_mode]], pb.rotation_mode)
        basis[:, b, :3, :3] = R * scl[:, None, :]
        basis[:, b, :3, 3] = loc
    pose = rt.pose_from_basis(ret.target.rest, ret.target.parents, basis, ret.target.order)
    return mat(obj.matrix_world)[None, None] @ pose
