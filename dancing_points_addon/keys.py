"""Where the two trackers' keys come from (:class:`KeySource`): the hook for
studying the method, which the evaluation's ablations take."""
from __future__ import annotations

from . import features as F
from .duet import DuetFrame

# The mapping's index of frame t − 1 + k for the trackers' keys k >= 2 (index 0 is
# frame t + 1): where a key source reads a predicted trajectory.
KEY_INDEX = F.TRACK_KEYS[1:] - 2


class KeySource:
    """Where the two trackers' keys (the future trajectories they follow) come
    from: the hook for studying the method (the evaluation's ablations). This
    default returns None for both: the synthesizer's own keys, from the
    mapping's prediction (the tracked dancer's current input first, then his
    predicted trajectory; the partner's as her placement makes them). A
    subclass may return others, and :meth:`observe` sees every finished frame.
    Each method gets the synthesizer (``synth``) whose frame it serves, to read
    (its scale, its default poses), not to call back."""

    def reset(self, synth) -> None:
        """A fresh take begins (the synthesizer's own state is reset)."""

    def tracked(self, synth, root, cur_local, t_roots, t_tr):
        """The tracked dancer's keys: (roots (K, 4), tracked points (K, 3, 3)), or
        None: the synthesizer's own. ``root``, ``cur_local``: his root and three
        points now; ``t_roots``, ``t_tr``: the mapping's prediction of him."""
        return None

    def partner(self, synth, p_roots, p_tr, t_roots, t_tr):
        """The partner's keys: (roots (K, 4), tracked points (K, 3, 3)), or None:
        the synthesizer's own. ``p_roots``, ``p_tr``: the mapping's prediction
        of her (smoothed by her placement)."""
        return None

    def observe(self, synth, tracked: DuetFrame, partner: DuetFrame) -> None:
        """The frame just made (tracked dancer, partner), in the take's scale."""
