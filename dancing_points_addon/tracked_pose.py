"""The tracked dancer's pose after his tracker's step and pose recovery, the
last stage of his frame (:class:`TrackedPose`): his body moved towards his
head device (:data:`HEAD_REACH`), his feet locked on the evidence of his
tracker, the contact network and his own motion, no foot through the floor,
his head and wrists put on the input (IK) and turned as the devices are
(:mod:`.device_follow`)."""
from __future__ import annotations

from math import sqrt

import numpy as np

from .foot_lock import KinematicContacts
from .pose import move_keeping_feet
from .skeleton import TRACKED

# The tracked dancer's head point reaches its device: before his foot lock, his body moves this share
# of the way there (at most HEAD_REACH_MAX metres), his legs keeping his ankles (pose.move_keeping_feet);
# the neck then turns the rest (without it the rigid spine left the head off its device; the shares
# tried are in docs/experiments.md).
HEAD_REACH, HEAD_REACH_MAX = 0.7, 0.05


class TrackedPose:
    """The stage, one take: ``locker`` (a :class:`~.foot_lock.FootLocker`, or
    None without foot locking), ``guard`` (a :class:`~.pose.FloorGuard`),
    ``effector`` (his head and wrists onto the input, :class:`~.ik.EndEffectorIK`;
    None without) and ``follow`` (a :class:`~.device_follow.DeviceFollow`; None:
    the devices' turns not followed). :attr:`devices`: this frame's measured
    device rotations (head, hands; None where not followed)."""

    def __init__(self, locker, guard, effector, follow):
        self.locker, self.guard, self.effector, self.follow = locker, guard, effector, follow
        self.kinematic = KinematicContacts()
        self.devices = (None, None, None)

    def __call__(self, pos, rot, contacts, targets, contact_p):
        """His pose ``(31, 3)``, ``(31, 3, 3)`` after the stage; ``contacts``:
        his tracker's, ``targets``: his three points at the tracker's scale,
        ``contact_p``: the contact network's probabilities (his four first;
        None without it)."""
        if self.effector is not None and HEAD_REACH > 0.0 and targets is not None:
            d = (targets[0] - pos[TRACKED[0]]) * HEAD_REACH
            n = sqrt(float(d @ d))
            if n > 1e-9 and n == n:  # (NaN: no head target)
                pos, rot = move_keeping_feet(pos, rot, d if n <= HEAD_REACH_MAX else d * (HEAD_REACH_MAX / n))
        if self.locker is not None:
            contacts = np.maximum(contacts, self.kinematic(pos))
            if contact_p is not None:  # his steps: the contact network's too
                contacts = np.maximum(contacts, contact_p[:4])
            pos, rot = self.locker.step(pos, rot, contacts)
        pos, rot = self.guard(pos, rot)  # no foot through the floor
        if targets is not None and self.effector is not None:
            pos, rot = self.effector.step(pos, rot, targets)
        if self.follow is not None:  # his head and hands turned as the devices are
            head, lh, rh = self.devices
            pos, rot = self.follow.step(pos, rot, head, (lh, rh))
        return pos, rot
