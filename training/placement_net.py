"""Experiment (issue 13): a small *placement network* that sees its own previous
placement, against the shipped rule (the mapping's prediction steered into a
placement state, ``dancing_points_addon/follower.py``). Not shipped: it lost on
val (docs/experiments.md, "Her placement").

    python -m training.placement_net --data ../shared/data/cmu_salsa \
        --models .gpu/fit_models [--noise 0.15] [--ema 0.9]

Trained on the fit cut of the train frames (mirrored), scored closed-loop on
the val cut with the fit-trained networks of ``--models`` (SPEC §6 metrics of
``training.evaluate``). Input per frame: the mapping network's input (the
leader's past 0.5 s) and the follower's previous two placements relative to the
leader's root; output: the change of placement. During training the previous
placements are perturbed (``--noise``: metres, and twice that in radians) so
that the network learns to steer back; at run time its output can be
smoothed (``--ema``) and is fed back as its own state.
"""
from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
import torch

from dancing_points_addon import features as F
from dancing_points_addon.nets import load_nets
from dancing_points_addon.representation import root_compose, root_relative
from dancing_points_addon.runtime import SynthesisOptions, Synthesizer

from . import evaluate as E
from .data import mapping_inputs
from .dataset import SALSA_TAKES, load_clips


class PlacementNet(torch.nn.Module):
    def __init__(self, n_in: int, hidden: int = 256):
        super().__init__()
        self.f = torch.nn.Sequential(torch.nn.Linear(n_in, hidden), torch.nn.ELU(), torch.nn.Linear(hidden, hidden),
                                     torch.nn.ELU(), torch.nn.Linear(hidden, hidden), torch.nn.ELU(),
                                     torch.nn.Linear(hidden, 4))
        self.register_buffer("mu", torch.zeros(n_in))
        self.register_buffer("sd", torch.ones(n_in))
        self.register_buffer("ysd", torch.ones(4))

    def forward(self, x):
        return self.f((x - self.mu) / self.sd) * self.ysd


def samples(clips):
    """Per frame t >= 2: mapping input, her placements at t-1 and t-2, at t."""
    X, P1, P2, Y = [], [], [], []
    for c in clips:
        if c.follower is None:
            continue
        rel = root_relative(c.leader.roots, c.follower.roots)
        m = mapping_inputs(c)
        t = np.arange(2, c.n_frames)
        X.append(m[t]); P1.append(rel[t - 1]); P2.append(rel[t - 2]); Y.append(rel[t])
    return tuple(np.concatenate(a).astype(np.float32) for a in (X, P1, P2, Y))


def _perturb(p, off, ang):
    p = p.copy()
    p[:, :2] += off
    c, s = p[:, 2].copy(), p[:, 3].copy()
    p[:, 2], p[:, 3] = c * np.cos(ang) - s * np.sin(ang), s * np.cos(ang) + c * np.sin(ang)
    return p


def train(data, noise=0.15, epochs=15, seed=0, log=print):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    X, P1, P2, Y = data

    def batch(idx):
        k = len(idx)
        scale = rng.uniform(0, 1, (k, 1)) * noise
        off, ang = rng.normal(0, 1, (k, 2)) * scale, rng.normal(0, 1, k) * scale[:, 0] * 2.0
        p1, p2 = _perturb(P1[idx], off, ang), _perturb(P2[idx], off, ang)
        x = np.concatenate([X[idx], p1, p1 - p2], axis=1)
        return torch.from_numpy(x), torch.from_numpy((Y[idx] - p1).astype(np.float32))

    net = PlacementNet(X.shape[1] + 8)
    x0, y0 = batch(np.arange(len(X)))
    net.mu[:], net.sd[:], net.ysd[:] = x0.mean(0), x0.std(0) + 1e-3, y0.std(0) + 1e-4
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    for ep in range(epochs):
        perm, tot = rng.permutation(len(X)), 0.0
        for i in range(0, len(perm), 256):
            xb, yb = batch(perm[i:i + 256])
            loss = (((net(xb) - yb) / net.ysd) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            tot += loss.item() * len(xb)
        if ep == epochs // 2:
            for g in opt.param_groups:
                g["lr"] = 3e-4
        log(f"epoch {ep}: loss {tot / len(X):.4f}")
    return net.eval()


class PlacementNetSynth(Synthesizer):
    """The runtime with the placement network's output as the follower's target
    placement (``mix`` of it, the rest the mapping's)."""

    net: PlacementNet = None
    mix, ema = 1.0, 0.9

    def reset(self):
        super().reset()
        self._pn = None
        mapping_target = self._placement.target

        def target(leader_root, l_roots, f_roots):
            off0, _ = mapping_target(leader_root, l_roots, f_roots)
            x = F.mapping_input(self.hist_roots[None], self.hist_tracked[None])[0]
            p1, p2 = (np.array(off0), np.array(off0)) if self._pn is None else self._pn
            with torch.no_grad():
                d = self.net(torch.from_numpy(np.concatenate([x, p1, p1 - p2]).astype(np.float32))[None])[0]
            p = self.ema * p1 + (1.0 - self.ema) * (p1 + d.numpy().astype(np.float64))
            p[2:] /= max(np.linalg.norm(p[2:]), 1e-9)
            self._pn = (p, p1)
            off = (1.0 - self.mix) * np.array(off0) + self.mix * p
            off[2:] /= max(np.linalg.norm(off[2:]), 1e-9)
            return off.tolist(), root_compose(leader_root, off).tolist()

        self._placement.target = target


def score(factory, segments):
    with tempfile.TemporaryDirectory() as tmp:
        runs, _ = E.run_system(factory, segments, tmp)
    return E.score(runs)


def experiment_parser(prog, doc, models):
    """The command line of a placement experiment: data, fit-trained networks, cache."""
    ap = argparse.ArgumentParser(prog=prog, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/data/cmu_salsa")
    ap.add_argument("--models", default=models, help="networks trained on the fit cut")
    ap.add_argument("--cache", default="cache")
    return ap


def main(argv=None):
    ap = experiment_parser("python -m training.placement_net", __doc__, ".gpu/fit_models")
    ap.add_argument("--noise", type=float, default=0.15)
    ap.add_argument("--ema", type=float, default=0.9)
    ap.add_argument("--epochs", type=int, default=15)
    args = ap.parse_args(argv)
    t0 = time.time()
    data = samples(load_clips(args.data, "fit", True, cache_dir=args.cache))
    print(f"{len(data[0])} fit samples")
    PlacementNetSynth.net = train(data, args.noise, args.epochs)
    print(f"trained in {time.time() - t0:.0f} s")
    nets = load_nets(args.models)
    segments = list(E.test_segments(args.data, SALSA_TAKES, "val"))
    keys = ("follower_fullbody_cm", "heading_follower_deg", "hand_cm", "follower_skating_cm_s", "follower_jitter",
            "follower_contact_f1")
    rows = {"shipped rule (mapping -> placement state)": lambda: Synthesizer(SynthesisOptions(), nets=nets)}
    for mix in (1.0, 0.5):
        PlacementNetSynth.ema = args.ema
        rows[f"placement net (ema {args.ema}, mix {mix})"] = (
            lambda m=mix: type("S", (PlacementNetSynth,), {"mix": m})(SynthesisOptions(), nets=nets))
    for name, factory in rows.items():
        r = score(factory, segments)
        print(f"{name:45s} " + "  ".join(f"{k} {r[k]:.2f}" for k in keys), flush=True)


if __name__ == "__main__":
    main()
