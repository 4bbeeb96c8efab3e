"""Experiment (issue 13): her placement and heading read from classifiers over
bins instead of the mapping network's regression. Not shipped: on val it
traded her placement error for jitter, hand error and noise
(docs/experiments.md, "Her placement").

    python -m training.placement_classifier --data ../shared/data/cmu_salsa \
        --models .gpu/fit_c

Trained on the fit cut of the train frames (mirrored), scored closed-loop on
the val cut with the fit-trained networks of ``--models`` (SPEC §6 metrics of
``training.evaluate``). Each classifier is an MLP (195 → 256 → 256, ELU,
dropout 0.2, N(0, 0.05) input noise, cross-entropy, 30 epochs) on the mapping
network's input (the leader's past 0.5 s):

- position: her root relative to his, on a grid of 12 cm cells over ±2.4 m;
  with a head of 36 bins for her root (head) heading relative to his;
- hip heading: her *hip* heading relative to his root, 36 bins.

At run time the placement target's position is the position classifier's
expected cell centre (optionally smoothed in the world frame), and her target
root heading is either the mapping's (as shipped) or the hip classifier's
circular mean less her pose's current hip-to-head turn; ``keep_hands`` then
turns her key hands and head back so that the keys' world points stay the
mapping's.
"""
from __future__ import annotations

import time
from math import hypot

import numpy as np
import torch

from dancing_points_addon import features as F
from dancing_points_addon.follower import FollowerOptions, _compose, hip_bin_directions, hip_heading_bins
from dancing_points_addon.nets import load_nets
from dancing_points_addon.representation import root_relative, to_local, to_world
from dancing_points_addon.runtime import SynthesisOptions, Synthesizer

from . import evaluate as E
from .data import mapping_inputs
from .dataset import SALSA_TAKES, load_clips
from .metrics import hip_heading
from .placement_net import experiment_parser, score

CELL, REACH, BINS = 0.12, 2.4, 36


class BinNet(torch.nn.Module):
    """Logits over ``cells`` (position, may be 0) and ``BINS`` heading bins."""

    def __init__(self, cells: int, hidden: int = 256, dropout: float = 0.2):
        super().__init__()
        self.f = torch.nn.Sequential(torch.nn.Linear(F.MAP_IN, hidden), torch.nn.ELU(), torch.nn.Dropout(dropout),
                                     torch.nn.Linear(hidden, hidden), torch.nn.ELU(), torch.nn.Dropout(dropout))
        self.p = torch.nn.Linear(hidden, max(cells, 1))
        self.h = torch.nn.Linear(hidden, BINS)
        self.register_buffer("mu", torch.zeros(F.MAP_IN))
        self.register_buffer("sd", torch.ones(F.MAP_IN))

    def forward(self, x):
        z = self.f((x - self.mu) / self.sd)
        return self.p(z), self.h(z)

    def expect(self, x: np.ndarray):
        """Expected (dx, dz) of the position cells and the heading bins' mean (cos, sin)."""
        with torch.no_grad():
            a, b = self(torch.from_numpy(x.astype(np.float32))[None])
        pb = torch.softmax(b[0], 0).numpy() @ _bin_dirs()
        if self.p.out_features == 1:  # a heading classifier only
            return None, pb
        return torch.softmax(a[0], 0).numpy() @ _centres(), pb


def _n_side():
    return int(round(2 * REACH / CELL))


def _centres():
    c = (np.arange(_n_side()) + 0.5) * CELL - REACH
    return np.stack(np.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2)


def _bin_dirs():
    return hip_bin_directions(BINS)


def _bins(angle):
    return hip_heading_bins(angle, BINS)


def samples(clips):
    """Mapping input, her grid cell and her root and hip heading bins (relative to his root)."""
    X, cell, head, hip = [], [], [], []
    n = _n_side()
    for c in clips:
        if c.follower is None:
            continue
        rel = root_relative(c.leader.roots, c.follower.roots)
        i = np.clip(((rel[:, 0] + REACH) / CELL).astype(int), 0, n - 1)
        j = np.clip(((rel[:, 1] + REACH) / CELL).astype(int), 0, n - 1)
        his = np.arctan2(c.leader.roots[:, 3], c.leader.roots[:, 2])
        X.append(mapping_inputs(c))
        cell.append(i * n + j)
        head.append(_bins(np.arctan2(rel[:, 3], rel[:, 2])))
        hip.append(_bins(hip_heading(c.follower.positions) - his))
    return (np.concatenate(X).astype(np.float32),) + tuple(np.concatenate(a) for a in (cell, head, hip))


def train(X, cells, bins, n_cells, epochs=30, seed=0, noise=0.05):
    torch.manual_seed(seed)
    net = BinNet(n_cells)
    net.mu[:], net.sd[:] = torch.from_numpy(X.mean(0)), torch.from_numpy(X.std(0) + 1e-3)
    opt = torch.optim.AdamW(net.parameters(), 1e-3)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 1e-3, total_steps=epochs * ((len(X) + 255) // 256))
    Xt, ct, bt = torch.from_numpy(X), torch.from_numpy(cells), torch.from_numpy(bins)
    ce = torch.nn.functional.cross_entropy
    for _ in range(epochs):
        net.train()
        perm = torch.randperm(len(X))
        for k in range(0, len(X), 256):
            i = perm[k:k + 256]
            a, b = net(Xt[i] + noise * torch.randn(len(i), F.MAP_IN) * net.sd)
            loss = ce(b, bt[i]) + (ce(a, ct[i]) if n_cells else 0.0)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
    return net.eval()


class ClassifierSynth(Synthesizer):
    """The runtime with her placement target from the classifiers (settings as class attributes)."""

    position: BinNet = None  # None: the mapping's position
    hip: BinNet = None  # None: the mapping's heading
    world_ema = 0.0  # smoothing of the classifier's target position, world frame
    keep_hands = False

    def step(self, *args, **kwargs):
        out = super().step(*args, **kwargs)
        self._last_fol = out[1].positions
        return out

    def reset(self):
        super().reset()
        self._last_fol, self._world, self._off0 = None, None, None
        mapping_target = self._placement.target

        def target(leader_root, l_roots, f_roots):
            off0, _ = mapping_target(leader_root, l_roots, f_roots)
            self._off0 = off0
            off = list(off0)
            x = F.mapping_input(self.hist_roots[None], self.hist_tracked[None])[0]
            lr = leader_root.tolist()
            if self.position is not None:
                p, _ = self.position.expect(x)
                w = np.array(_compose(lr, [p[0], p[1], 1.0, 0.0])[:2])
                if self.world_ema > 0 and self._world is not None:
                    w = self.world_ema * self._world + (1.0 - self.world_ema) * w
                self._world = w
                dx, dz = w[0] - lr[0], w[1] - lr[1]  # back into his frame
                off[0], off[1] = lr[2] * dx - lr[3] * dz, lr[3] * dx + lr[2] * dz
            if self.hip is not None and self._last_fol is not None:
                _, h = self.hip.expect(x)
                r = self.follower.root
                turn = float(hip_heading(self._last_fol[None])[0]) - np.arctan2(r[3], r[2])
                a = np.arctan2(h[1], h[0]) - turn  # her root heading that puts her hips there
                off[2], off[3] = np.cos(a), np.sin(a)
            n = max(hypot(off[2], off[3]), 1e-9)
            off[2], off[3] = off[2] / n, off[3] / n
            return off, _compose(lr, off)

        self._placement.target = target

    def _follower_keys(self, f_roots, f_tr, l_roots, l_tr):
        roots, tracked = super()._follower_keys(f_roots, f_tr, l_roots, l_tr)
        if not self.keep_hands or self._off0 is None:
            return roots, tracked
        keep = self._fol_target
        self._fol_target = ([keep[0][0], keep[0][1], self._off0[2], self._off0[3]], keep[1])
        try:
            roots0, _ = super()._follower_keys(f_roots, f_tr, l_roots, l_tr)
        finally:
            self._fol_target = keep
        return roots, to_local(to_world(tracked, roots0), roots)


def main(argv=None):
    ap = experiment_parser("python -m training.placement_classifier", __doc__, ".gpu/fit_c")
    ap.add_argument("--epochs", type=int, default=30)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.time()
    X, cell, head, hip = samples(load_clips(args.data, "fit", True, cache_dir=args.cache))
    pos_net = train(X, cell, head, _n_side() ** 2, args.epochs)
    hip_net = train(X, cell, hip, 0, args.epochs)
    print(f"{len(X)} fit samples, two classifiers trained in {time.time() - t0:.0f} s", flush=True)

    # open loop on val: the classifiers against the truth
    Xv, cv, hv, pv = samples(load_clips(args.data, "val", False, cache_dir=args.cache))
    cen, dirs = _centres(), _bin_dirs()
    with torch.no_grad():
        a, b = pos_net(torch.from_numpy(Xv))
        _, c = hip_net(torch.from_numpy(Xv))
    pos = torch.softmax(a, 1).numpy() @ cen
    err = np.linalg.norm(pos - cen[cv], axis=1).mean() * 100  # against the true cell's centre

    def ang(probs, true_bins):  # mean |circular mean of the bins − the true bin's centre|, degrees
        mean = probs @ dirs
        d = np.arctan2(mean[:, 1], mean[:, 0]) - np.arctan2(dirs[true_bins, 1], dirs[true_bins, 0])
        return np.degrees(np.abs(np.angle(np.exp(1j * d)))).mean()

    print(f"val, open loop: position {err:.1f} cm, root heading {ang(torch.softmax(b, 1).numpy(), hv):.1f} deg, "
          f"hip heading {ang(torch.softmax(c, 1).numpy(), pv):.1f} deg (against the true bins' centres)")

    nets = load_nets(args.models)
    segments = list(E.test_segments(args.data, SALSA_TAKES, "val"))
    keys = ("follower_fullbody_cm", "heading_follower_deg", "hand_cm", "follower_skating_cm_s", "follower_jitter",
            "follower_contact_f1", "follower_pose_cm")

    def variant(pull_heading=0.05, **kw):
        cls = type("S", (ClassifierSynth,), kw)
        return lambda: cls(SynthesisOptions(), nets=nets, follower=FollowerOptions(pull_heading=pull_heading))

    rows = {
        "shipped rule (mapping -> placement state)": lambda: Synthesizer(SynthesisOptions(), nets=nets),
        "position classifier": variant(position=pos_net),
        "position classifier, world smoothing 0.5": variant(position=pos_net, world_ema=0.5),
        "position classifier, world smoothing 0.7": variant(position=pos_net, world_ema=0.7),
        "hip heading classifier": variant(hip=hip_net),
        "hip heading classifier, heading pull 0.1": variant(0.1, hip=hip_net),
        "hip heading classifier, pull 0.2, keys keep his hands": variant(0.2, hip=hip_net, keep_hands=True),
        "both, world smoothing 0.5, heading pull 0.1": variant(0.1, position=pos_net, hip=hip_net, world_ema=0.5),
    }
    for name, factory in rows.items():
        r = score(factory, segments)
        print(f"{name:55s} " + "  ".join(f"{k} {r[k]:.2f}" for k in keys), flush=True)


if __name__ == "__main__":
    main()
