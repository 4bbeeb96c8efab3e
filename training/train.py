"""Train the shipped networks (and optionally the ablations) from scratch.

    python -m training.train --data ../shared/data/cmu_salsa --out models

Trains, on the SPEC §5 train split only (mirror augmented): the mapping
network, the follower's placement network (the mapping's recipe, also on the
clips played backwards), the contact network (both dancers' foot contacts from
the mapping's input; it times the follower's steps), the follower's pose anchor
and hip-heading network, and one tracking network per dancer (leader,
follower), then exports them to ONNX (``--only`` picks some). ``--ablations DIR``
also trains ablation (a), a vanilla MLP tracker, and (b), a tracker fed the past
instead of the future three-point trajectory, for both dancers, under the same
settings, into ``DIR``.
No validation split is carved from the test frames: training runs a fixed
number of epochs, so test data cannot steer it.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
import torch

from dancing_points_addon import features as F
from dancing_points_addon.calibration import TRAIN_HEIGHT
from dancing_points_addon.partner_pose import HIP_BINS
from dancing_points_addon.nets import MODEL_FILES
from training.dataset import load_clips, solo_clips, swap_roles

from .data import (anchor_samples, body_clips, contact_samples, default_pose, device_offset_clips, floor_levels_of,
                   head_height, hip_heading_samples, mapping_samples, sample_times, time_reverse, tracking_samples)
from .export import export
from .model import ContactNet, HipHeadingNet, MappingNet, PoseAnchorNet, TrackingNet, VanillaTracker


def save_checkpoint(model, path, meta):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    torch.save({"state_dict": model.state_dict(), "meta": meta}, path)


def train_model(model, x, y, epochs, batch=256, lr=1e-3, device="cpu", log=None, seed=0, weight_decay=1e-4,
                w=None):
    """``w``: per-sample loss weights passed to ``model.loss`` (the mapping's per
    dancer, ``(n, 2)``), or None."""
    torch.manual_seed(seed)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    wt = None if w is None else torch.from_numpy(np.asarray(w, dtype=np.float32)).to(device)
    model.fit_normalizers(xt, yt)  # normalisation statistics of the (train split) samples
    model.to(device)
    xt, yt = xt.to(device), yt.to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    steps = max(1, epochs * math.ceil(len(xt) / batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.05)
    g = torch.Generator(device="cpu").manual_seed(seed)
    model.train()
    t0 = time.time()
    hist = []
    for ep in range(epochs):
        perm = torch.randperm(len(xt), generator=g).to(device)
        tot, n = {}, 0
        for i in range(0, len(xt) - batch + 1, batch):
            idx = perm[i:i + batch]
            losses = model.loss(xt[idx], yt[idx]) if wt is None else model.loss(xt[idx], yt[idx], wt[idx])
            loss = sum(losses.values())
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            for k, v in losses.items():
                tot[k] = tot.get(k, 0.0) + v.item()
            n += 1
        rec = {k: v / max(n, 1) for k, v in tot.items()}
        hist.append(rec)
        if log:
            log(f"  epoch {ep + 1}/{epochs} " + " ".join(f"{k}={v:.4f}" for k, v in rec.items())
                + f" ({time.time() - t0:.0f}s)")
    model.eval()
    return {"seconds": time.time() - t0, "final": hist[-1] if hist else {}, "epochs": epochs,
            "samples": int(len(xt))}


# the placement network's loss weights on the clips played backwards, per dancer (leader,
# follower) and output group (root position, heading, three points: ``MappingNet.GROUPS``):
# only her outputs count
REVERSE_WEIGHTS = [[0] * 5, [1] * 5]

# what ``--only`` names for the shipped networks: the runtime's kinds
SHIPPED = tuple(MODEL_FILES)

CONFIGS = {
    # hidden units, epochs
    # Teacher-forced ground-truth keys; the trackers' width and current-pose noise
    # (standard deviation up to 0.3 units) per dancer, chosen on the val frames
    # (train --split fit, evaluate --split val; the comparisons are in
    # models/README.md and docs/experiments.md, "Smaller trackers"). The ablations
    # get their dancer's settings.
    "full": {"map_hidden": 384, "map_epochs": 60, "track_hidden": {"leader": 96, "follower": 192}, "track_epochs": 60,
             "pose_noise": {"leader": 0.3, "follower": 0.3},
             # the bodies each dancer's tracker learns from (data.body_clips): each its own. Every body
             # the split allows (--tracker-bodies leader,follower,solo) lost on val: docs/experiments.md
             "bodies": {"leader": ("leader",), "follower": ("follower",)},
             # body-shape copies of every clip (bone groups within ±spread) for a tracker of several bodies
             "shape": {"spread": 0.08, "copies": 1},
             "contacts": {"hidden": 256, "layers": 3, "epochs": 30, "noise": 0.05, "dropout": 0.2},
             "anchor": {"hidden": 512, "layers": 3, "epochs": 30, "noise": 0.05, "dropout": 0.2},
             # her hip heading over bins (chosen on val: open-loop 39-41 degrees off her hips against
             # 42-43 for 256 units or 30 epochs)
             "hip": {"hidden": 512, "layers": 3, "epochs": 60, "noise": 0.05, "dropout": 0.2}},
    "tiny": {"map_hidden": 32, "map_epochs": 1, "track_hidden": 32, "track_epochs": 1,
             "pose_noise": 0.3,
             "bodies": {"leader": ("leader",), "follower": ("follower",)},
             "shape": {"spread": 0.08, "copies": 1},
             "contacts": {"hidden": 32, "layers": 3, "epochs": 1, "noise": 0.05, "dropout": 0.2},
             "anchor": {"hidden": 32, "layers": 3, "epochs": 1, "noise": 0.05, "dropout": 0.2},
             "hip": {"hidden": 32, "layers": 3, "epochs": 1, "noise": 0.05, "dropout": 0.2}},
}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m training.train", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/data/cmu_salsa")
    ap.add_argument("--out", default="models")
    ap.add_argument("--config", choices=sorted(CONFIGS), default="full")
    ap.add_argument("--ablations", default=None, help="also train ablations (a), (b) into this folder")
    ap.add_argument("--only", default=None,
                    help=f"comma list of what to train: {', '.join(SHIPPED)} (the shipped models)"
                         " and, with --ablations, vanilla, pastinput (default: all)")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: all cores)")
    ap.add_argument("--device", default="auto", help="cpu, cuda or auto")
    ap.add_argument("--cache", default="cache")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--split", choices=("train", "fit"), default="train",
                    help="fit: train on the first 80 %% of the train frames only, to compare recipes on the "
                         "rest (evaluate --split val); the shipped models use train")
    ap.add_argument("--map-noise", type=float, default=None, help="mapping input noise (default 0.1)")
    ap.add_argument("--map-dropout", type=float, default=None, help="mapping dropout (default 0.1)")
    ap.add_argument("--map-epochs", type=int, default=None)
    ap.add_argument("--map-hidden", type=int, default=None, help="mapping hidden units (default: the config's)")
    ap.add_argument("--map-wd", type=float, default=None, help="mapping AdamW weight decay (default 1e-4)")
    ap.add_argument("--track-epochs", type=int, default=None)
    ap.add_argument("--track-hidden", type=int, default=None,
                    help="trackers' hidden units (both dancers; default: the config's, per dancer)")
    ap.add_argument("--pose-noise", type=float, default=None,
                    help="trackers (both dancers): perturb the current-pose input with Gaussian noise of a "
                         "standard deviation up to this many POSE_NOISE_UNITS (default: the config's, per dancer)")
    ap.add_argument("--roles", default="leader,follower",
                    help="comma list of dancers whose trackers (and ablations) to train (default: both)")
    ap.add_argument("--tracked", choices=("leader", "follower"), default="leader",
                    help="whose three points the networks read: the leader's (models/, the default) or the "
                         "follower's (role reversal, models/follower/: the clips' dancers swapped, so the "
                         "networks on the mapping's input learn her lead and his answer; the trackers are each "
                         "dancer's own and serve both roles, so none is trained)")
    ap.add_argument("--device-aug", default="0.03,0.03", metavar="OFFSET,SCALE",
                    help="the networks on the mapping's input also learn from a copy of every clip with the "
                         "leader's three points moved by a constant offset of up to OFFSET m per axis of each "
                         "device and the couple scaled by up to ±SCALE (a wrong body offset or height), their "
                         "epochs halved (the same steps); default 0.03,0.03 (chosen on val: models/README.md); "
                         "none: not")
    ap.add_argument("--solo", default="../shared/data/cmu_solo_dance",
                    help="the solo takes' folder (SPEC §5: 05_01-05_10 trained on, by the trackers only); none: not")
    ap.add_argument("--tracker-bodies", default=None, metavar="BODIES",
                    help="comma list of the bodies his tracker learns from: leader, follower (the salsa dancers), "
                         "solo (SPEC §5: 05_01-05_10); the first gives the start-up pose and so the output "
                         "skeleton (default: the config's, leader)")
    ap.add_argument("--body-shape", default=None, metavar="SPREAD,COPIES",
                    help="a tracker of several bodies also learns from COPIES copies of every clip with each bone "
                         "group within ±SPREAD of its length (default: the config's, 0.08,1); none: not")
    ap.add_argument("--weights", choices=("int8", "fp32"), default="int8",
                    help="exported weights: int8 (quantised, shipped) or float32")
    args = ap.parse_args(argv)
    if args.split == "fit" and (os.path.abspath(args.out) == os.path.abspath("models")
                                or os.path.abspath(args.cache) == os.path.abspath("cache")):
        ap.error("--split fit trains comparison models: give an --out and a --cache of their own "
                 "(not the shipped models/ and cache/)")

    roles = [r for r in args.roles.split(",") if r]
    if not roles or set(roles) - {"leader", "follower"}:
        ap.error(f"--roles: leader and/or follower, not {args.roles!r}")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    cfg = dict(CONFIGS[args.config])
    if args.pose_noise is not None:
        cfg["pose_noise"] = args.pose_noise
    if args.track_hidden is not None:
        cfg["track_hidden"] = args.track_hidden
    if args.tracker_bodies is not None:
        bodies = tuple(b for b in args.tracker_bodies.split(",") if b)
        if not bodies or set(bodies) - {"leader", "follower", "solo"}:
            ap.error(f"--tracker-bodies: leader, follower and/or solo, not {args.tracker_bodies!r}")
        cfg["bodies"] = {**cfg["bodies"], "leader": bodies}
    if args.body_shape is not None:
        spread, copies = (0.0, 0) if args.body_shape == "none" else args.body_shape.split(",")
        cfg["shape"] = {"spread": float(spread), "copies": int(copies)}
    os.makedirs(args.out, exist_ok=True)
    log = lambda s: print(s, flush=True)  # noqa: E731
    t_all = time.time()
    clips = load_clips(args.data, args.split, mirror_aug=True, cache_dir=args.cache)
    lead_head = head_height(c.leader.positions for c in clips)
    if args.tracked == "follower":  # role reversal: her three points in, his motion synthesised
        clips = swap_roles(clips)
    log(f"train clips: {len(clips)}, frames: {sum(c.n_frames for c in clips)}; device {device}")
    # the tracked dancer's upright head height and the standing height it stands for (calibration.py):
    # the training leader's is TRAIN_HEIGHT; another dancer's in proportion to their heads
    head = head_height(c.leader.positions for c in clips)
    tracked_meta = {"tracked_role": args.tracked,
                    "calibration": {"height_m": round(TRAIN_HEIGHT * head / lead_head, 4),
                                    "head_height_m": round(head, 4)}}
    # the networks on the mapping's input: also the clips as another wearer's headset gives them
    input_clips, input_copies = clips, 1
    if args.device_aug != "none":
        offset_m, scale = (float(v) for v in args.device_aug.split(","))
        input_clips = clips + device_offset_clips(clips, np.random.default_rng(args.seed), offset_m, scale)
        input_copies = 2
    only = set(args.only.split(",")) if args.only else {*SHIPPED, "vanilla", "pastinput"}
    # the recipe options given on the command line (paths and machine settings aside)
    overrides = {k: v for k, v in vars(args).items() if v != ap.get_default(k)
                 and k not in ("data", "out", "cache", "ablations", "only", "threads", "device", "split", "config")}
    report = {"config": args.config, **cfg, "overrides": overrides, "device": device, "split": args.split,
              "models": {}}
    split_meta = {"tracked_role": args.tracked}
    if args.tracked == "follower":  # the trackers belong to the dancers, not the roles: models/ holds them
        only -= {"leader", "follower", "vanilla", "pastinput"}
        split_meta.update(tracked_meta)
    if args.split != "train":
        split_meta["data_split"] = ("CMU salsa takes 01-13 at 30 Hz, the first 80% of each take's train frames "
                                    "(split 'fit', for comparing recipes); mirror augmented")

    def mapping_like(name):
        """The mapping network (``name`` mapping), or the placement network (the
        same network and recipe, also trained on the clips played backwards with
        the loss on the follower's outputs only: ``placement``)."""
        x, y = mapping_samples(input_clips)
        w = None
        if name == "placement":  # the clips played backwards, only her outputs counting
            xr, yr = mapping_samples(time_reverse(input_clips))
            w = np.ones((len(x) + len(xr), 2, len(MappingNet.GROUPS)), dtype=np.float32)
            w[len(x):] = REVERSE_WEIGHTS
            x, y = np.concatenate([x, xr]), np.concatenate([y, yr])
        log(f"{name}: {x.shape} -> {y.shape}")
        noise = 0.1 if args.map_noise is None else args.map_noise
        dropout = 0.1 if args.map_dropout is None else args.map_dropout
        epochs = max(1, (args.map_epochs or cfg["map_epochs"]) // input_copies)  # the same steps
        hidden = args.map_hidden or cfg["map_hidden"]
        wd = 1e-4 if args.map_wd is None else args.map_wd
        m = MappingNet(F.MAP_IN, F.MAP_OUT, hidden, noise=noise, dropout=dropout, loss="norm")
        info = train_model(m, x, y, epochs, device=device, log=log, seed=args.seed, weight_decay=wd, w=w)
        info.update(noise=noise, dropout=dropout, weight_decay=wd, loss="norm",
                    reverse="follower" if name == "placement" else "none")
        extra = {}
        if name == "placement":
            extra = {"outputs": "the mapping's layout; the runtime reads the follower's roots (position, heading) "
                                "only"}
        export(m, name, os.path.join(args.out, f"{name}.onnx"), F.MAP_IN,
               {"hidden": hidden, "train": info, **extra, **split_meta}, weights=args.weights)
        save_checkpoint(m, os.path.join(args.cache, "checkpoints", f"{name}.pt"),
                        {"hidden": hidden, **extra, **split_meta})
        report["models"][name] = info

    if "mapping" in only:
        mapping_like("mapping")
    if "placement" in only:  # her placement: where she stands and faces (models/README.md)
        mapping_like("placement")

    def input_net(key, cls, samples, kind, name, extra):
        """A small network on the mapping's input (the contact network, the pose
        anchor): trained, exported as ``name``.onnx, checkpointed, reported."""
        x, y = samples(input_clips)
        log(f"{key}: {x.shape} -> {y.shape}")
        c = cfg[key]
        m = cls(F.MAP_IN, y.shape[1], c["hidden"], c["layers"], noise=c["noise"], dropout=c["dropout"])
        info = train_model(m, x, y, max(1, c["epochs"] // input_copies), device=device, log=log, seed=args.seed)
        info.update({k: v for k, v in c.items() if k != "epochs"})
        meta = {"hidden": c["hidden"], "layers": c["layers"], "train": info, **extra, **split_meta}
        export(m, kind, os.path.join(args.out, f"{name}.onnx"), F.MAP_IN, meta, weights=args.weights)
        save_checkpoint(m, os.path.join(args.cache, "checkpoints", f"{name}.pt"), meta)
        report["models"][key] = info

    if "contacts" in only:
        # each dancer's floor level per foot point (the follower's lock plants her feet there)
        input_net("contacts", ContactNet, contact_samples, "contacts", "contacts",
                  {"outputs": json.dumps([f"{r} {p}" for r in ("leader", "follower")
                                          for p in ("ltibia", "lfoot", "rtibia", "rfoot")]),
                   "floor_levels": {r: floor_levels_of(clips, r) for r in ("leader", "follower")}})
    if "anchor" in only:
        input_net("anchor", PoseAnchorNet, anchor_samples, "anchor", "pose_anchor",
                  {"outputs": "the follower's lower body (skeleton.LOWER_BODY, x y z each) in her hip frame"})
    if "hip" in only:
        input_net("hip", HipHeadingNet, hip_heading_samples, "hip_heading", "hip_heading",
                  {"outputs": f"the follower's hip heading relative to the leader's root heading: the probabilities "
                              f"of {HIP_BINS} bins, bin k from -pi + 2 pi k / {HIP_BINS}", "bins": HIP_BINS})

    solo = None

    def tracker(cls, role, name, out_path, past_input=False, extra=None):
        """Train a tracker on teacher-forced samples (keys: the ground-truth future)
        of the bodies ``cfg["bodies"][role]``, the steps of its own body's."""
        nonlocal solo
        bodies = tuple(cfg["bodies"][role])
        if "solo" in bodies and args.solo != "none" and solo is None:
            solo = solo_clips(args.solo, args.split)
        n_own = sum(len(sample_times(c.n_frames)) for c in clips if getattr(c, role) is not None)
        if bodies == (role,):
            own, n_first, held = clips, len(clips), role
        else:
            own, n_first = body_clips(clips, solo, bodies, lead_head, np.random.default_rng(args.seed),
                                      cfg["shape"]["spread"], cfg["shape"]["copies"])
            held = "leader"  # the body clips hold each dancer in the leader's place
        x, y, where = tracking_samples(own, held, past_input=past_input)
        epochs = args.track_epochs or cfg["track_epochs"]
        epochs = max(1, round(epochs * n_own / len(x)))  # the steps of the dancer's own clips
        log(f"{name}: {x.shape} -> {y.shape} ({', '.join(bodies)}; {epochs} epochs)")
        pose_noise, hidden = (cfg[k][role] if isinstance(cfg[k], dict) else cfg[k]
                              for k in ("pose_noise", "track_hidden"))
        m = cls(F.TRACK_IN, F.TRACK_OUT, hidden, pose_dim=F.POSE_DIM, pose_noise=pose_noise)
        info1 = train_model(m, x, y, epochs, device=device, log=log, seed=args.seed)
        info = {"stage1": info1, "seconds": info1["seconds"]}
        # the start-up pose (and so the output skeleton): the first body's, unmirrored, unreshaped
        sel = where[:, 0] < n_first
        meta = {"hidden": hidden, "role": role, "pose_noise": pose_noise, "train": info,
                **split_meta, "bodies": ",".join(bodies), "shape": cfg["shape"] if bodies != (role,) else None,
                "default_pose": default_pose(x[sel], where[sel], own)}
        meta.update(extra or {})
        save_checkpoint(m, os.path.join(args.cache, "checkpoints", f"{name}.pt"), meta)
        export(m, f"tracker_{role}", out_path, F.TRACK_IN, meta, weights=args.weights)
        report["models"][name] = info

    for role in roles:
        if role in only:
            tracker(TrackingNet, role, f"tracker_{role}", os.path.join(args.out, f"tracker_{role}.onnx"))
        if not args.ablations:
            continue
        os.makedirs(args.ablations, exist_ok=True)
        if "vanilla" in only:  # ablation (a): no latent, L_rec only
            tracker(VanillaTracker, role, f"vanilla_{role}", os.path.join(args.ablations, f"vanilla_{role}.onnx"),
                    extra={"ablation": "a"})
        if "pastinput" in only:  # ablation (b): fed the past three points, no mapping
            tracker(TrackingNet, role, f"pastinput_{role}", os.path.join(args.ablations, f"pastinput_{role}.onnx"),
                    past_input=True, extra={"ablation": "b", "input": "past three-point trajectory"})
    report["seconds_total"] = time.time() - t_all  # this run
    report_dir = args.out if only & set(SHIPPED) else args.ablations
    path = os.path.join(report_dir, "training_report.json")
    if report["models"]:
        if os.path.exists(path):  # a partial run (--only, --roles) keeps the other models' entries
            with open(path) as f:
                old = json.load(f).get("models", {})
            report["models"] = {**old, **report["models"]}
        report["seconds_models"] = sum(m.get("seconds", 0.0) for m in report["models"].values())
        with open(path, "w") as f:
            json.dump(report, f, indent=1)
    log(f"done in {report['seconds_total']:.0f}s -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
