"""The runtime's key hook (:class:`keys.KeySource`): the default is the
mapping's keys, bit for bit; a source sees every frame and every reset; the
evaluation's ablations run through it and change what they ablate."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import ROOT
from dancing_points_addon.formats.take import Take
from dancing_points_addon.formats.take_read import read_take
from dancing_points_addon.nets import load_nets
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.keys import KeySource
from dancing_points_addon.synthesis_options import SynthesisOptions
from training.evaluate import LeaderTrajKeys, PastInputKeys

SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"


@pytest.fixture(scope="module")
def short_take():
    tk = read_take(SAMPLE)
    n = 240  # 4 s at the file's 60 Hz
    return Take(tk.time[:n], tk.positions[:n], tk.quats[:n], tk.meta, tk.source)


@pytest.fixture(scope="module")
def nets():
    return load_nets()


def _synth(nets, **kw):
    return Synthesizer(SynthesisOptions(), nets=nets, **kw)


@pytest.fixture(scope="module")
def plain(nets, short_take):
    return _synth(nets).synthesize(short_take)


class Recording(KeySource):
    def __init__(self):
        self.resets = self.tracked_calls = self.partner_calls = 0
        self.seen = []

    def reset(self, synth):
        self.resets += 1
        self.seen = []

    def tracked(self, synth, root, cur_local, t_roots, t_tr):
        self.tracked_calls += 1
        return super().tracked(synth, root, cur_local, t_roots, t_tr)

    def partner(self, synth, p_roots, p_tr, t_roots, t_tr):
        self.partner_calls += 1
        return super().partner(synth, p_roots, p_tr, t_roots, t_tr)

    def observe(self, synth, tracked, partner):
        self.seen.append((tracked.positions.copy(), partner.positions.copy()))


def test_default_source_is_the_mapping_bit_for_bit(nets, short_take, plain):
    rec = Recording()
    duet = _synth(nets, keys=rec).synthesize(short_take)
    for k in ("leader_positions", "leader_rotations", "follower_positions", "follower_rotations"):
        assert np.array_equal(getattr(duet, k), getattr(plain, k)), k
    n = duet.n_frames
    assert rec.tracked_calls == rec.partner_calls == n
    assert len(rec.seen) == n and rec.resets >= 1
    # what it observed is what the take gets (a leader's take: tracked = leader, floor at y = 0)
    assert np.allclose(rec.seen[-1][0], duet.leader_positions[-1])
    assert np.allclose(rec.seen[-1][1], duet.follower_positions[-1])
    # a second take starts the source afresh
    before = rec.resets
    synth = _synth(nets, keys=rec)
    synth.synthesize(short_take)
    synth.synthesize(short_take)
    assert rec.resets > before and len(rec.seen) == n


def test_ablations_change_what_they_ablate(nets, short_take, plain):
    past = _synth(nets, keys=PastInputKeys()).synthesize(short_take)
    lead_only = _synth(nets, keys=PastInputKeys(follower_past=False)).synthesize(short_take)
    traj = _synth(nets, keys=LeaderTrajKeys(), follower=None).synthesize(short_take)
    moved = lambda a, b: float(np.abs(a - b).max())  # noqa: E731
    # (b): both trackers follow the past instead of the mapping's future
    assert moved(past.leader_positions, plain.leader_positions) > 0.01
    assert moved(past.follower_positions, plain.follower_positions) > 0.01
    # (b) for him alone: his body as (b)'s, her keys the mapping's again
    assert np.array_equal(lead_only.leader_positions, past.leader_positions)
    assert moved(lead_only.follower_positions, past.follower_positions) > 0.01
    # (c): his keys untouched, hers from his predicted trajectory
    assert moved(traj.follower_positions, plain.follower_positions) > 0.01
    for duet in (past, lead_only, traj):
        assert np.isfinite(duet.leader_positions).all() and np.isfinite(duet.follower_positions).all()
