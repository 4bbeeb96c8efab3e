"""One dancer's tracker state (:class:`DancerState`) and the step that
advances the tracked dancer and the partner together: their trackers
(:func:`tracker_step`), then their new roots and world poses (:func:`settle_step`),
with what keeps a pose state on its root on any length of take
(:func:`limit_drift`, :func:`recentre`)."""
from __future__ import annotations

from dataclasses import dataclass
from math import sqrt

import numpy as np

from . import features as F
from .option_checks import check_range
from .representation import DEVICE_FROM_HEAD, pose_to_local, pose_to_world, root_from_head
from .skeleton import FEET, HEAD_BONE, TRACKED


@dataclass(frozen=True)
class FootingOptions:
    """When a tracker state has lost its footing (:meth:`DancerState.keep_footing`):
    all four foot points more than ``height`` metres (tracker scale) above the
    floor for more than ``frames`` frames, a closed-loop drift of the
    autoregressive tracker that long takes showed after 20-30 s (legs folded
    under a raised pelvis, the feet floating 25-90 cm up, never recovering); it
    is then pulled ``share`` of the way to the start-up pose each frame until a
    foot is down. (Chosen on closed-loop runs of each take's train frames, and
    never active on the SPEC §6 val segments: docs/experiments.md.)"""

    height: float = 0.15
    frames: int = 5
    share: float = 0.5

    def __post_init__(self):
        check_range("FootingOptions", "height", self.height, 0.0, low_open=True)
        check_range("FootingOptions", "frames", self.frames, 0)
        check_range("FootingOptions", "share", self.share, 0.0, 1.0, low_open=True)


# Where the four foot points' heights lie in a pose feature vector (read every frame).
_FOOT_Y = tuple(int(F.POSE_POS.start + 3 * j + 1) for j in FEET)


class DancerState:
    """Autoregressive state of one dancer's tracker."""

    def __init__(self, net, default_pose: np.ndarray):
        self.net = net
        self.default_pose = default_pose
        self.root = None  # F0 (4,)
        self.pose = None  # (POSE_DIM,)
        self.off_floor = 0  # frames in a row with every foot point over the footing's height
        self.footing_pulls = 0  # frames the state was pulled back (keep_footing)

    def place(self, root):
        self.root = np.asarray(root, dtype=np.float64).copy()
        self.pose = self.default_pose.copy()
        self.off_floor = 0

    def keep_footing(self, footing: FootingOptions = FootingOptions()) -> bool:
        """After a step: a state that has lost its footing (:class:`FootingOptions`)
        is pulled towards the start-up pose. Returns whether it was."""
        height, frames, share = footing.height, footing.frames, footing.share
        pose = self.pose
        low = min(float(pose[i]) for i in _FOOT_Y)
        self.off_floor = self.off_floor + 1 if low > height else 0
        if self.off_floor <= frames:
            return False
        self.pose = self.pose + share * (self.default_pose - self.pose)
        self.footing_pulls += 1
        return True

    def set_pose(self, pos_world, rot_world, contacts):
        """Replace the state's pose (world) by a post-processed one."""
        set_poses((self,), pos_world[None], rot_world[None], contacts[None])


def set_poses(dancers, pos_world, rot_world, contacts):
    """Each dancer's :meth:`DancerState.set_pose` at once: world poses ``(D, 31, 3)``,
    ``(D, 31, 3, 3)`` and contacts ``(D, 4)`` (per pose, the same products as one's)."""
    roots = np.array([d.root for d in dancers])
    for d, pose in zip(dancers, F.pose_features(*pose_to_local(pos_world, rot_world, roots), contacts)):
        d.pose = pose


def limit_drift(pos, limit):
    """Local poses ``(D, 31, 3)`` translated horizontally so that the head point
    is at most ``limit`` metres from the root's origin (a tracker state that
    has wandered off its root is brought back; a nearer one is untouched)."""
    out = pos.copy()
    for i in range(len(pos)):
        x, z = float(pos[i, TRACKED[0], 0]), float(pos[i, TRACKED[0], 2])
        d = sqrt(x * x + z * z)
        if d > limit:
            f = (d - limit) / d
            out[i, :, 0] -= x * f
            out[i, :, 2] -= z * f
    return out


def recentre(pos, rot):
    """Each local pose ``(D, 31, 3)``, ``(D, 31, 3, 3)`` moved into the frame its
    own head defines (SPEC root: the head's floor point, the head device's
    heading): the frame every training pose is given in. The tracker's pose
    state cannot then wander away from its root, however long the take."""
    out_p, out_r = np.empty_like(pos), np.empty_like(rot)
    for i in range(len(pos)):
        frame = root_from_head(pos[i, TRACKED[0]], rot[i, HEAD_BONE] @ DEVICE_FROM_HEAD)
        out_p[i], out_r[i] = pose_to_local(pos[i], rot[i], frame)
    return out_p, out_r


def tracker_step(dancers, key_roots, key_tracked):
    """The trackers' step of several dancers: their networks one after the
    other, the feature work around them batched over the dancers (at these
    sizes numpy's cost is per call, not per element). ``key_roots (D, K, 4)``,
    ``key_tracked (D, K, 3, 3)``. Returns per dancer the root change its
    tracker proposes ``(D, 4)`` and its new local pose: positions
    ``(D, 31, 3)``, rotations ``(D, 31, 3, 3)``, contacts ``(D, 4)``. The
    dancers' state is not touched (:func:`settle_step` does)."""
    x = F.tracking_input(np.array([d.pose for d in dancers]), np.array([d.root for d in dancers]),
                         key_roots, key_tracked)
    y = np.concatenate([d.net(x[i:i + 1]) for i, d in enumerate(dancers)], dtype=np.float64)
    rel, pos, rot, con = F.split_tracking_output(y[:, :F.KEY_OUT])
    return rel[:, 0], pos[:, 0], rot[:, 0], con[:, 0]


def settle_step(dancers, roots, pos, rot, con, recentre_pose=(False, False)):
    """The step's end: each dancer's new ``root`` (as its caller chose it: the
    one the input shows, or its tracker's proposal placed; :func:`root_compose`
    of the old root and the proposed change) made its state, its local pose
    kept on it (``recentre_pose`` per dancer: True, re-centred on its own head;
    a distance, the head's drift limited to it; False, as it is). Returns world
    positions ``(D, 31, 3)``, rotations ``(D, 31, 3, 3)`` and contacts
    ``(D, 4)``; the caller makes the pose (after its own stages) the state's
    (:meth:`DancerState.set_pose`)."""
    for d, root in zip(dancers, roots):
        d.root = root
    for i, on in enumerate(recentre_pose):
        if on is True:
            pos[i:i + 1], rot[i:i + 1] = recentre(pos[i:i + 1], rot[i:i + 1])
        elif on is not False and on is not None:  # a distance: limit the drift to it
            pos[i:i + 1] = limit_drift(pos[i:i + 1], float(on))
    con = np.minimum(np.maximum(con, 0.0), 1.0)  # np.clip(con, 0, 1), cheaper
    return pose_to_world(pos, rot, np.array([d.root for d in dancers])) + (con,)
