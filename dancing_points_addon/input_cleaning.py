"""The first stage of a frame: the tracked dancer's three devices cleaned.

A device that is lost (SPEC §3 gaps) is stood in for from the mapping
network's last prediction of this frame (the tracked dancer's future
trajectory): the head follows the predicted root and height, turning its last
orientation by the predicted change of heading; a hand takes its predicted
place relative to the head. Before any prediction exists, devices are held.
A device that comes back blends in from where its stand-in was
(:class:`ReturnOptions`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .option_checks import check_range
from .device_follow import limit_rotation
from .representation import root_from_head, root_relative, to_local, to_world
from .rotations import quat_to_matrix, rotation_angle


@dataclass(frozen=True)
class ReturnOptions:
    """How a device that comes back after a loss blends in from where its
    stand-in was: the gap closes by ``rate`` a frame, at least ``least`` and at
    most ``most`` metres (the head's turn at most ``turn`` radians): a hand
    0.9 m off is back within 0.6 s, moving no faster than the dancer plus 4 cm
    a frame."""

    rate: float = 0.3
    least: float = 0.003
    most: float = 0.04
    turn: float = 0.1

    def __post_init__(self):
        check_range("ReturnOptions", "rate", self.rate, 0.0, 1.0, low_open=True)
        check_range("ReturnOptions", "least", self.least, 0.0, low_open=True)
        check_range("ReturnOptions", "most", self.most, self.least)
        check_range("ReturnOptions", "turn", self.turn, 0.0, low_open=True)


class InputCleaner:
    """The devices of one frame after another, cleaned (:meth:`clean`).
    ``default_points``: the tracker's default pose's three points (3, 3),
    training scale: where a device never seen stands; ``options``: a
    :class:`ReturnOptions`."""

    def __init__(self, default_points, options: ReturnOptions = ReturnOptions()):
        self.default_points = np.asarray(default_points, dtype=np.float64)
        self.o = options
        self.reset()

    def reset(self) -> None:
        self.last_valid = None  # last valid (head position, head rotation), input space
        self.last_hand = [None, None]  # last valid (hand position, head root) per hand
        self._prev_used = None  # the (tracked points, head rotation) used on the last frame
        self._prev_valid = None
        self._return = [None, None, None]  # per device: the gap left when it came back (a 3-vector)
        self._return_turn = None  # the head's turn left when it came back (3, 3)

    def clean(self, positions, quats, valid, pred, inv):
        """Fill lost devices (SPEC §3 gaps) from the mapping network's last
        prediction of this frame (the leader's future trajectory): the head
        follows the predicted root and height, turning its last orientation by the
        predicted change of heading; a hand takes its predicted place relative to
        the head. Before any prediction exists, devices are held. Returns tracked
        positions (3, 3), the head device rotation and its root (input space).
        ``pred``: the mapping's last prediction of this frame (its root and
        tracked points, None before the first); ``inv``: the input's scale over
        the tracker's."""
        if valid[0]:
            head_pos = np.asarray(positions[0], dtype=np.float64)
            head_rot = quat_to_matrix(quats[0])
            root = root_from_head(head_pos, head_rot)
        elif pred is not None and self.last_valid is not None:
            root = pred[0] * np.array([inv, inv, 1.0, 1.0])
            head_pos = to_world(pred[1][:1] * inv, root)[0]
            last_rot = self.last_valid[1]
            last_root = root_from_head(self.last_valid[0], last_rot)
            turn = root_relative(last_root, root)  # heading change as (cos, sin)
            head_rot = np.array([[turn[2], 0.0, turn[3]], [0.0, 1.0, 0.0], [-turn[3], 0.0, turn[2]]]) @ last_rot
        elif self.last_valid is not None:
            head_pos, head_rot = self.last_valid
            root = root_from_head(head_pos, head_rot)
        else:
            head_pos = np.array([0.0, self.default_points[0, 1] * inv, 0.0])
            head_rot = np.diag([-1.0, 1.0, -1.0])
            root = root_from_head(head_pos, head_rot)
        if valid[0]:
            self.last_valid = (head_pos, head_rot)
        tracked = np.array(positions, dtype=np.float64)  # rows of lost devices are replaced below
        if not valid[0]:
            tracked[0] = head_pos
        if self._prev_used is not None and (valid[0] and not self._prev_valid[0] or self._return[0] is not None
                                            or self._return_turn is not None):
            tracked[0], head_rot = self._blend_head(tracked[0], head_rot, valid[0])
            root = root_from_head(tracked[0], head_rot)
        for i in (1, 2):
            if valid[i]:
                self.last_hand[i - 1] = (tracked[i].copy(), root)
                if self._prev_used is not None and (not self._prev_valid[i] or self._return[i] is not None):
                    tracked[i] = self._blend_point(i, tracked[i])
                continue
            self._return[i] = None
            if pred is not None:
                local = pred[1][i] * inv
            elif self.last_hand[i - 1] is not None:
                local = to_local(self.last_hand[i - 1][0][None], self.last_hand[i - 1][1])[0]
            else:  # never seen: the default pose's hand
                local = self.default_points[i] * inv
            tracked[i] = to_world(local[None], root)[0]
        self._prev_used = (tracked, head_rot)
        self._prev_valid = tuple(bool(v) for v in valid)
        return tracked, head_rot, root

    def _blend_point(self, i, real):
        """Device ``i``'s point this frame: where it really is, plus what is left of
        the gap to its stand-in when it came back (:class:`ReturnOptions`)."""
        gap = self._return[i]
        if gap is None:  # it is back on this frame: the gap from last frame's stand-in
            gap = self._prev_used[0][i] - real
        n = float(np.sqrt(gap @ gap))
        o = self.o
        if n <= o.least:
            self._return[i] = None
            return real
        self._return[i] = gap * (1.0 - min(o.most, max(o.least, o.rate * n)) / n)
        return real + self._return[i]

    def _blend_head(self, head_pos, head_rot, valid):
        """The head's point and rotation this frame, blended in after a loss like
        the hands' (:meth:`_blend_point`), its turn too."""
        if not valid:
            self._return[0] = self._return_turn = None
            return head_pos, head_rot
        pos = self._blend_point(0, head_pos)
        turn = self._return_turn
        if turn is None:
            turn = self._prev_used[1] @ head_rot.T
        a = float(rotation_angle(turn))
        if a <= 1e-3:
            self._return_turn = None
            return pos, head_rot
        self._return_turn = limit_rotation(turn, a - min(self.o.turn, max(1e-3, self.o.rate * a)))
        return pos, self._return_turn @ head_rot
