"""The tracked dancer's feet stay planted on a body the networks never saw.

The follower's three points as a leader's take (SPEC §6 "on unseen dancers",
no height given): the output skeleton is the training leader's, whose feet sit
lower than hers against her floor, so a foot that slides or sweeps along the
floor in a catch-up step counts as skating (SPEC §6: on frames within 2.5 cm
of the floor level of her ground truth). The 6 s of take 01's val cut (the
last fifth of its train frames): his lock's skating stays within 1.2 × her
capture's (1.99 × before the tracked dancer's lock read the contact network,
stepped high and lifted a fast foot; 0.58 × with it), and the feet it holds
stand still.
"""
from __future__ import annotations

import numpy as np

from conftest import MODELS

from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.synthesis_options import SynthesisOptions
from dancing_points_addon.skeleton import FEET


def test_her_points_as_a_leader_take_do_not_skate(salsa_dir, tmp_path):
    from training import metrics as M
    from training.evaluate import SCORE_FROM, segment_take, test_segments

    seg = next(test_segments(str(salsa_dir), ("01",), "val", tracked="follower"))
    duet = Synthesizer(SynthesisOptions(models=MODELS)).synthesize(segment_take(seg, str(tmp_path)))
    pred = duet.leader_positions
    true = seg["lead"][0][:len(pred)]
    assert len(true) == len(pred) > 150
    mask = np.arange(len(pred)) / 30.0 >= SCORE_FROM
    skate = M.aggregate([M.foot_skating_spec(pred, true, mask)])
    truth = M.aggregate([M.foot_skating_spec(true, true, mask)])
    print(f"\nher points as a leader take, {len(pred) / 30:.0f} s: skating {skate:.1f} cm/s, her capture's {truth:.1f}")
    assert skate <= 1.2 * truth
    # the lock held her feet a good part of the time, and a held point stands still
    held = duet.planted[:, 0]
    assert 0.3 < held[mask].mean() < 0.95
    feet = pred[:, FEET][..., [0, 2]]
    still = held[1:] & held[:-1] & mask[1:, None]
    speed = np.linalg.norm(np.diff(feet, axis=0), axis=-1)[still] * 30.0
    assert np.median(speed) < 0.01  # m/s (a lock blending in or out still moves)
    assert pred[mask][:, FEET, 1].min() > -0.03  # no foot through the floor
