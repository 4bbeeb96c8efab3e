"""``follower.HandHold`` on its own: where the follower's wrist is pulled in a
hold, how far her arm reaches, and what it does not do (fold her wrist onto
her own shoulder, sweep it across between his hands)."""
import numpy as np
import pytest

from dancing_points_addon.follower import HoldOptions
from dancing_points_addon.partner_pose import HandHold
from dancing_points_addon.skeleton import JOINT_INDEX, WRISTS

ARM = 0.55  # her arm, shoulder to wrist (m)
L_SH, R_SH = JOINT_INDEX["lclavicle"], JOINT_INDEX["rclavicle"]


def _poses(his_left_wrist, his_right_wrist=(5.0, 1.2, 5.0)):
    """Her: shoulders at ±0.18 m, arms hanging (wrists 0.5 m below the
    shoulders). Him: wrists where given."""
    her = np.zeros((31, 3))
    her[L_SH] = (0.18, 1.4, 0.0)
    her[R_SH] = (-0.18, 1.4, 0.0)
    her[WRISTS[0]] = (0.2, 0.9, 0.05)
    her[WRISTS[1]] = (-0.2, 0.9, 0.05)
    his = np.zeros((31, 3))
    his[WRISTS[0]] = his_left_wrist
    his[WRISTS[1]] = his_right_wrist
    return his, her


def _settle(hold, his, her, pred, frames=90):
    out = None
    for _ in range(frames):
        out = hold.targets(his, her, pred, np.array([ARM, ARM]))
    return out


PRED_HOLD = np.array([[0.1, 2.0], [2.0, 2.0]])  # his left and her left predicted close, nothing else


def test_a_hold_brings_her_wrist_to_his_hand():
    """A predicted hold, his hand in front of her shoulder within reach: her
    left wrist target settles at ``HoldOptions.gap`` from his wrist, on her side; her
    other hand is left alone."""
    o = HoldOptions()
    his, her = _poses((0.2, 1.2, 0.4))
    tg = _settle(HandHold(o), his, her, PRED_HOLD)
    assert tg[1] is None
    d = np.linalg.norm(tg[0] - his[WRISTS[0]])
    print(f"\nheld: her wrist target {d * 100:.2f} cm from his wrist (hold gap {o.gap * 100:.0f} cm)")
    assert d == pytest.approx(o.gap, abs=0.005)
    assert np.linalg.norm(tg[0] - her[L_SH]) < np.linalg.norm(his[WRISTS[0]] - her[L_SH])  # on her side


@pytest.mark.parametrize("where, pulled", [
    (1.02, True),  # past her arm's length: the clavicle helps, still held
    (1.25, True),  # past her arm's length, within reach - 0.1
    (1.45, False),  # past reach (1.4 of her arm): faded out
    (0.15, False),  # at her shoulder (his hand on her back): faded out
    (0.60, True),
])
def test_how_far_a_hold_reaches(where, pulled):
    """His hand ``where`` × her arm in front of her shoulder (the goal lies
    ``gap`` nearer): pulled or not."""
    o = HoldOptions()
    dist = where * ARM + o.gap
    his, her = _poses((0.18, 1.4, dist))  # straight in front of her left shoulder
    tg = _settle(HandHold(o), his, her, PRED_HOLD)
    moved = 0.0 if tg[0] is None else float(np.linalg.norm(tg[0] - her[WRISTS[0]]))
    print(f"\nhis hand {where:.2f} of her arm out: her wrist target moved {moved * 100:.1f} cm")
    assert (moved > 0.2) == pulled
    if not pulled:
        assert moved < 1e-3


def test_her_hand_goes_over_to_his_other_hand_gradually():
    """His two hands swap as the one predicted near hers: her wrist target goes
    over in many small steps (the soft partner changes by at most
    ``hold_soft_rate`` a frame, the pull is a spring), not in a sweep."""
    o = HoldOptions()
    his, her = _poses((0.35, 1.2, 0.45), (0.0, 1.2, 0.45))
    hold = HandHold(o)
    first = np.array([[0.1, 2.0], [0.4, 2.0]])
    then = np.array([[0.4, 2.0], [0.1, 2.0]])
    a = _settle(hold, his, her, first)[0]
    path = [a]
    for _ in range(60):
        path.append(hold.targets(his, her, then, np.array([ARM, ARM]))[0])
    path = np.array(path)
    step = np.linalg.norm(np.diff(path, axis=0), axis=-1).max()
    end = np.linalg.norm(path[-1] - his[WRISTS[1]])
    print(f"\npartner swap: largest per-frame step {step * 100:.2f} cm, ends {end * 100:.1f} cm from his other hand")
    assert end < o.gap + 0.01
    assert step < 0.03


def _follow_moving_hand(o, speed=0.3, frames=60):
    """His hand moves sideways at ``speed`` m/s in front of her left shoulder,
    held from the start: per frame, her wrist target's distance from where
    the hold puts it (``gap`` from his wrist on her side)."""
    hold = HandHold(o)
    lags = []
    for t in range(frames):
        his, her = _poses((0.18 - 0.3 + speed * t / 30.0, 1.2, 0.4))  # 30 cm either side of her shoulder
        tg = hold.targets(his, her, PRED_HOLD, np.array([ARM, ARM]))[0]
        v = her[L_SH] - his[WRISTS[0]]
        goal = his[WRISTS[0]] + v / np.linalg.norm(v) * o.gap
        lags.append(np.linalg.norm(tg - goal))
    return np.array(lags)


def test_the_hold_follows_a_moving_hand_without_trailing_it():
    """The spring's feed-forward (``hold_lead``): once his hand moves at a
    steady 0.3 m/s, her wrist target trails it by under half of what the
    spring alone leaves."""
    o = HoldOptions()
    assert o.lead > 0
    lead = _follow_moving_hand(o)
    plain = _follow_moving_hand(HoldOptions(lead=0.0))
    print(f"\nsteady 0.3 m/s, last second: trails {lead[30:].mean() * 100:.2f} cm with the feed-forward, "
          f"{plain[30:].mean() * 100:.2f} cm without")
    assert lead[30:].mean() < 0.5 * plain[30:].mean()
    assert lead[-1] < 0.5 * plain[-1]
