"""The tracked dancer's pose after his tracker's step and pose recovery, the
last stage of his frame (:class:`TrackedPose`): his body moved towards his
head device (``head_reach``), his feet locked on the evidence of his
tracker, the contact network and his own motion, no foot through the floor,
his head and wrists put on the input (IK) and turned as the devices are
(:mod:`.device_follow`). His settings, all in one :class:`TrackedOptions`
(the partner's are :class:`~.follower.FollowerOptions`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from math import sqrt

import numpy as np

from .dancer_state import FootingOptions
from .device_follow import DeviceFollowOptions
from .foot_lock import TRACKED_FOOT_LOCK, FootLockOptions, KinematicContacts, KinematicOptions
from .input_cleaning import ReturnOptions
from .option_checks import check_kinds, check_range
from .pose import move_keeping_feet
from .skeleton import TRACKED


@dataclass(frozen=True)
class TrackedOptions:
    """What the runtime does with the tracked dancer, each setting chosen on val
    (figures in models/README.md, the variants in docs/experiments.md).

    ``head_reach``: before his foot lock his body moves this share of the way
    to his head device (at most ``head_reach_max`` metres), his legs keeping his
    ankles (:func:`~.pose.move_keeping_feet`); the neck then turns the rest.
    ``lock_floor``: his feet are planted at most this high (m, training scale)
    above his floor levels (the contact network's), which his swing clearance
    lifts from; ``foot_lock``: his lock (:data:`~.foot_lock.TRACKED_FOOT_LOCK`),
    which reads the highest of his tracker's contacts, the contact network's
    and ``kinematic`` evidence; ``footing``: when his tracker state is pulled
    back onto its feet; ``returns``: how a device that comes back blends in;
    ``devices``: how far his head and hands turn as the devices do."""

    head_reach: float = 0.7
    head_reach_max: float = 0.05
    lock_floor: float = 0.01
    foot_lock: FootLockOptions = TRACKED_FOOT_LOCK
    kinematic: KinematicOptions = field(default_factory=KinematicOptions)
    footing: FootingOptions = field(default_factory=FootingOptions)
    returns: ReturnOptions = field(default_factory=ReturnOptions)
    devices: DeviceFollowOptions = field(default_factory=DeviceFollowOptions)

    def __post_init__(self):
        check_range("TrackedOptions", "head_reach", self.head_reach, 0.0, 1.0)
        check_range("TrackedOptions", "head_reach_max", self.head_reach_max, 0.0)
        check_range("TrackedOptions", "lock_floor", self.lock_floor, 0.0, 0.1)
        check_kinds(self, {"foot_lock": FootLockOptions, "kinematic": KinematicOptions, "footing": FootingOptions,
                           "returns": ReturnOptions, "devices": DeviceFollowOptions})


class TrackedPose:
    """The stage, one take: ``locker`` (a :class:`~.foot_lock.FootLocker`, or
    None without foot locking), ``guard`` (a :class:`~.pose.FloorGuard`),
    ``effector`` (his head and wrists onto the input, :class:`~.ik.EndEffectorIK`;
    None without) and ``follow`` (a :class:`~.device_follow.DeviceFollow`; None:
    the devices' turns not followed), ``options`` a :class:`TrackedOptions`.
    :attr:`devices`: this frame's measured device rotations (head, hands; None
    where not followed)."""

    def __init__(self, locker, guard, effector, follow, options: TrackedOptions = TrackedOptions()):
        self.locker, self.guard, self.effector, self.follow = locker, guard, effector, follow
        self.reach, self.reach_max = options.head_reach, options.head_reach_max
        self.kinematic = KinematicContacts(options.kinematic)
        self.devices = (None, None, None)

    def __call__(self, pos, rot, contacts, targets, contact_p):
        """His pose ``(31, 3)``, ``(31, 3, 3)`` after the stage; ``contacts``:
        his tracker's, ``targets``: his three points at the tracker's scale,
        ``contact_p``: the contact network's probabilities (his four first;
        None without it)."""
        if self.effector is not None and self.reach > 0.0 and targets is not None:
            d = (targets[0] - pos[TRACKED[0]]) * self.reach
            n = sqrt(float(d @ d))
            if n > 1e-9 and n == n:  # (NaN: no head target)
                pos, rot = move_keeping_feet(pos, rot, d if n <= self.reach_max else d * (self.reach_max / n))
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
