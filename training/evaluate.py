"""Closed-loop evaluation per SPEC §6, with the paper's ablations.

    python -m training.evaluate --data ../shared/data/cmu_salsa --models models \
        [--ablations cache/ablations] [--json out.json] [--markdown table.md]

For each of the 13 takes the leader's *test* frames are written as a take file
(SPEC §3, native 60 Hz, time from 0), read back, and run through the product
runtime from its default initial state; the 30 Hz output is compared with both
dancers' ground truth. The first 1.0 s is not scored; every metric is
frame-weighted over all takes.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
import os
import tempfile
import time

import numpy as np

from dancing_points_addon import features as F
from training import metrics as M
from dancing_points_addon.formats.asf_amc import load_amc
from training.dataset import FOLLOWER, LEADER, SALSA_TAKES, split_range
from dancing_points_addon.representation import device_rotation, root_from_head, to_local, to_world
from dancing_points_addon.nets import OnnxNet, load_nets
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.keys import KEY_INDEX, KeySource
from dancing_points_addon.synthesis_options import SynthesisOptions
from dancing_points_addon.skeleton import HEAD_BONE, TRACKED, WRISTS, bone_lengths_from_positions
from dancing_points_addon.formats.take import take_from_motion, write_take
from dancing_points_addon.formats.take_read import read_take
from dancing_points_addon.calibration import TRAIN_HEIGHT, headset_take, height_from_head
from dancing_points_addon.formats.devices import DeviceOffsets
from dancing_points_addon.inputs import HAND_BONES

SCORE_FROM = 1.0  # seconds


def test_segments(data_dir, takes=SALSA_TAKES, split="test", tracked="leader"):
    """Per take: (name, leader 60 Hz test Motion slice, leader 30 Hz GT, follower 30 Hz GT, bone lengths).
    ``split="train"`` gives the train frames instead: what the runtime's own
    settings (foot locking, IK) are tuned on, never the test frames.
    ``tracked="follower"``: the follower's frames in the leader's place (SPEC §6
    "on unseen dancers": her three points as a leader's take; only the
    "leader" figures then mean anything, and they are hers)."""
    subjects = (LEADER, FOLLOWER) if tracked == "leader" else (FOLLOWER, LEADER)
    ref = None
    for take in takes:
        lead = load_amc(os.path.join(data_dir, f"{subjects[0]}_{take}.amc"))
        fol = load_amc(os.path.join(data_dir, f"{subjects[1]}_{take}.amc"))
        ref = ref if ref is not None else (lead if tracked == "leader" else fol).bone_vectors
        a, b = split_range(lead.n_frames, split)
        lead60 = type(lead)(lead.positions[2 * a:2 * b], lead.rotations[2 * a:2 * b], lead.fps, lead.bone_vectors,
                            lead.source)
        yield {"take": take, "lead60": lead60,
               "lead": (lead.positions[::2][a:b], lead.rotations[::2][a:b]),
               "fol": (fol.positions[::2][a:b], fol.rotations[::2][a:b]),
               "lead_len": lead.bone_lengths(), "fol_len": fol.bone_lengths(),
               "lead_vec": lead.bone_vectors, "ref_vec": ref}


def solo_segments(solo_dir, split="test", ref_dir=None):
    """The solo dancer's segments (SPEC §6 "on unseen dancers"): ``split="test"``
    the held-out takes 05_11-05_20 whole, at their native 120 Hz; "val" the
    last 20 % of 05_01-05_10 (the trackers' fit cut learns the rest). Only the
    leader's figures mean anything (his slot is the solo dancer; the follower's
    "truth" is a copy of his)."""
    from training.dataset import FIT_SHARE, SOLO_HELD_OUT, SOLO_TRAIN_TAKES

    if split not in ("test", "val"):
        raise ValueError("the solo takes are scored on test (05_11-05_20) or val (the end of 05_01-05_10)")
    ref = load_amc(os.path.join(ref_dir, f"{LEADER}_01.amc")).bone_vectors if ref_dir else None
    for take in (SOLO_HELD_OUT if split == "test" else SOLO_TRAIN_TAKES):
        m = load_amc(os.path.join(solo_dir, f"{take}.amc"))
        step = int(round(m.fps / F.FPS))
        a = 0 if split == "test" else int(np.floor(FIT_SHARE * m.n_frames))
        native = type(m)(m.positions[a:], m.rotations[a:], m.fps, m.bone_vectors, m.source)
        gt = (m.positions[a::step], m.rotations[a::step])
        yield {"take": take, "lead60": native, "lead": gt, "fol": gt,
               "lead_len": m.bone_lengths(), "fol_len": m.bone_lengths(),
               "lead_vec": m.bone_vectors, "ref_vec": ref if ref is not None else m.bone_vectors}


# -- ablations -----------------------------------------------------------------
class PastInputKeys(KeySource):
    """(b) trackers fed the past three-point trajectory instead of a future one:
    the leader its own input, the follower (``follower_past``) its own
    predicted past."""

    HIST = int(F.TRACK_KEYS.max()) + 2

    def __init__(self, follower_past: bool = True):
        self.follower_past = follower_past  # False: the follower keeps the full model (not ablated)

    def reset(self, synth):
        self._lh = []  # leader (root, tracked local) per frame
        self._fh = []

    @staticmethod
    def _past(hist):
        n = len(hist)
        idx = [max(n - 1 - k, 0) for k in F.TRACK_KEYS]  # frames (t - 1) - k relative to the last entry
        return np.stack([hist[i][0] for i in idx]), np.stack([hist[i][1] for i in idx])

    def tracked(self, synth, root, cur_local, t_roots, t_tr):
        self._lh.append((root, cur_local))
        self._lh = self._lh[-self.HIST:]
        return self._past(self._lh[:-1] or self._lh)

    def partner(self, synth, p_roots, p_tr, t_roots, t_tr):
        if not self._fh or not self.follower_past:
            return None  # the synthesizer's own
        return self._past(self._fh)

    def observe(self, synth, tracked, partner):
        tr = partner.positions[TRACKED] * synth.scale()
        root = root_from_head(tr[0], device_rotation(partner.rotations[HEAD_BONE]))
        self._fh.append((root, to_local(tr, root)))
        self._fh = self._fh[-self.HIST:]


class LeaderTrajKeys(KeySource):
    """(c) the follower tracked from the leader's predicted future trajectory
    (no follower mapping)."""

    def reset(self, synth):
        self._prev_lead = None

    def partner(self, synth, p_roots, p_tr, t_roots, t_tr):
        prev = self._prev_lead if self._prev_lead is not None else (t_roots[0], t_tr[0])
        self._prev_lead = (t_roots[0], t_tr[0])
        return (np.concatenate([prev[0][None], t_roots[KEY_INDEX]]),
                np.concatenate([prev[1][None], t_tr[KEY_INDEX]]))


class FixedPose:
    """(d) a fixed pose carried along under the head; the follower's at its mean
    placement relative to the leader in the train split."""

    def __init__(self, synth: Synthesizer, follower_offset):
        self.synth = synth
        self.lead_pose = synth.default_pose["tracked"]
        self.fol_pose = synth.default_pose["partner"]
        self.offset = follower_offset

    def run(self, take):
        from dancing_points_addon.calibration import apply_calibration
        from dancing_points_addon.representation import root_compose, rot_to_world
        from dancing_points_addon.resample import resample_take
        from dancing_points_addon.rotations import quat_to_matrix

        calib = self.synth.calibrate(take)
        tk = resample_take(apply_calibration(take, calib), F.FPS)
        roots = root_from_head(tk.positions[:, 0], quat_to_matrix(tk.quats[:, 0]))
        out = []
        for pose, rts in ((self.lead_pose, roots), (self.fol_pose, root_compose(roots, self.offset[None]))):
            p = F.pose_positions(pose)
            r = F.pose_rotations(pose)
            pw = to_world(np.broadcast_to(p, (len(rts), 31, 3)), rts)
            pw[..., 1] += calib.floor_y
            rw = rot_to_world(np.broadcast_to(r, (len(rts), 31, 3, 3)), rts)
            out.append((pw, rw))
        return out


def mean_follower_offset(data_dir):
    from training.dataset import load_clips
    from dancing_points_addon.representation import root_relative

    clips = load_clips(data_dir, "train", mirror_aug=True)
    rel = np.concatenate([root_relative(c.leader.roots, c.follower.roots) for c in clips])
    m = rel.mean(0)
    m[2:] /= np.linalg.norm(m[2:])
    return m


# -- scoring -------------------------------------------------------------------
def score(runs):
    """runs: list of dicts with pred/true leader/follower positions (T, 31, 3), mask."""
    agg = {k: [] for k in ("track", "lead", "fol", "hand", "head_l", "head_f", "skate", "skate_gt",
                           "jit", "jit_gt", "fskate", "fjit", "skate_own", "fskate_gt", "fjit_gt", "pen",
                           "pen_gt", "pose_l", "pose_f", "mean_l", "mean_f")}
    counts, fcounts = [], []
    pred_corr, true_corr = [], []
    for r in runs:
        pl, pf, tl, tf, m = r["pl"], r["pf"], r["tl"], r["tf"], r["mask"]
        agg["track"].append(M.tracking_error(pl, tl, m))
        agg["lead"].append(M.fullbody_error(pl, tl, m))
        agg["fol"].append(M.fullbody_error(pf, tf, m))
        # the pose with placement factored out, beside a mean-pose prior's (the
        # train pose nearest the mean, carried along)
        agg["pose_l"].append(M.placed_pose_error(pl, tl, m))
        agg["pose_f"].append(M.placed_pose_error(pf, tf, m))
        if r.get("mean_poses") is not None:
            for key, pose, true in (("mean_l", r["mean_poses"][0], tl), ("mean_f", r["mean_poses"][1], tf)):
                agg[key].append(M.placed_pose_error(np.broadcast_to(pose, true.shape), true, m))
        agg["hand"].append(M.hand_error(pl, pf, tl, tf, m))
        agg["head_l"].append(M.heading_error(pl, tl, m))
        agg["head_f"].append(M.heading_error(pf, tf, m))
        counts.append(M.contact_counts(pl, tl, m))
        fcounts.append(M.contact_counts(pf, tf, m))
        # SPEC §6: each foot point's floor level from the ground truth of the take
        agg["skate"].append(M.foot_skating_spec(pl, tl, m))
        agg["skate_gt"].append(M.foot_skating_spec(tl, tl, m))
        agg["skate_own"].append(M.foot_skating(pl, m))  # floor from the prediction itself (earlier tables)
        agg["fskate"].append(M.foot_skating_spec(pf, tf, m))
        agg["fskate_gt"].append(M.foot_skating_spec(tf, tf, m))
        agg["jit"].append(M.jitter(pl, m))
        agg["jit_gt"].append(M.jitter(tl, m))
        agg["fjit"].append(M.jitter(pf, m))
        agg["fjit_gt"].append(M.jitter(tf, m))
        agg["pen"].append(M.interpenetration(pl, pf, m))
        agg["pen_gt"].append(M.interpenetration(tl, tf, m))
        pred_corr.append(M.circular_correlation(M.hip_heading(pl)[m], M.hip_heading(pf)[m]))
        true_corr.append(M.circular_correlation(M.hip_heading(tl)[m], M.hip_heading(tf)[m]))
    w = np.array([int(r["mask"].sum()) for r in runs], dtype=float)
    cm = 100.0
    return {
        "leader_tracking_cm": M.aggregate(agg["track"]) * cm,
        "leader_fullbody_cm": M.aggregate(agg["lead"]) * cm,
        "follower_fullbody_cm": M.aggregate(agg["fol"]) * cm,
        "hand_cm": M.aggregate(agg["hand"]) * cm,
        "leader_pose_cm": M.aggregate(agg["pose_l"]) * cm,
        "follower_pose_cm": M.aggregate(agg["pose_f"]) * cm,
        "leader_mean_pose_cm": M.aggregate(agg["mean_l"]) * cm,
        "follower_mean_pose_cm": M.aggregate(agg["mean_f"]) * cm,
        "heading_leader_deg": M.aggregate(agg["head_l"]),
        "heading_follower_deg": M.aggregate(agg["head_f"]),
        "heading_corr": float(np.average(pred_corr, weights=w)),
        "heading_corr_gt": float(np.average(true_corr, weights=w)),
        "contact_f1": M.f1(counts),
        "follower_contact_f1": M.f1(fcounts),
        "skating_cm_s": M.aggregate(agg["skate"]),
        "skating_gt_cm_s": M.aggregate(agg["skate_gt"]),
        "skating_own_floor_cm_s": M.aggregate(agg["skate_own"]),
        "follower_skating_cm_s": M.aggregate(agg["fskate"]),
        "follower_skating_gt_cm_s": M.aggregate(agg["fskate_gt"]),
        "jitter": M.aggregate(agg["jit"]),
        "jitter_gt": M.aggregate(agg["jit_gt"]),
        "follower_jitter": M.aggregate(agg["fjit"]),
        "follower_jitter_gt": M.aggregate(agg["fjit_gt"]),
        "torsos_closer_15cm_pct": 100.0 * M.aggregate(agg["pen"]),
        "torsos_closer_15cm_gt_pct": 100.0 * M.aggregate(agg["pen_gt"]),
        "frames": int(w.sum()),
    }


def stability(runs):
    """Worst leader-root distance from the input head's floor projection, NaNs,
    worst relative bone-length deviation (bones longer than 2 cm)."""
    worst_root, worst_len, nan = 0.0, 0.0, False
    for r in runs:
        for key, lens in (("pl", r["lead_len"]), ("pf", r["fol_len"])):
            p = r[key]
            nan |= bool(~np.isfinite(p).all())
            bl = bone_lengths_from_positions(p)
            sel = lens > 0.02
            worst_len = max(worst_len, float(np.max(np.abs(bl[:, sel] / lens[sel] - 1.0))))
        head = r["input_head"]
        worst_root = max(worst_root, float(np.max(np.linalg.norm(
            r["pl"][:, TRACKED[0]][:, [0, 2]] - head[:, [0, 2]], axis=-1))))
    return {"max_root_from_head_cm": worst_root * 100, "nan": nan, "max_bone_length_dev": worst_len}


def cut_last(runs, seconds=2.0):
    """The same runs scored without each take's last ``seconds`` (where the
    couple separates at the end of a recording)."""
    out = []
    for r in runs:
        n = len(r["mask"])
        keep = np.arange(n) < n - int(round(seconds * F.FPS))
        out.append(dict(r, mask=r["mask"] & keep))
    return out


@dataclass(frozen=True)
class Scenario:
    """How the tracked dancer's take of a segment is written and read: SPEC §6
    writes the leader's test frames as a ``joints`` take and gives no height;
    its variants write them as a headset records them (``devices="openxr"``),
    read them with body offsets ``offset_error`` metres wrong (a 3-vector in
    each device's own axes), move the floor by ``floor_shift`` metres (the
    truth moves with it), or give a ``height`` (metres, or ``"skeleton"``: the
    dancer's own, :func:`skeleton_height`)."""

    devices: str = "joints"
    offset_error: tuple | None = None
    floor_shift: float = 0.0
    height: float | str | None = None
    role: str = "leader"  # the take's role (SPEC §6 "reversed": the follower's frames as a role=follower take)

    def options(self, seg, **kw) -> SynthesisOptions:
        height = skeleton_height(seg["lead_vec"], seg["ref_vec"]) if self.height == "skeleton" else self.height
        offsets = None
        if self.offset_error is not None:  # the offsets the take was written with, each one off
            true = DeviceOffsets().at(seg["writer_height"])
            offsets = DeviceOffsets(*(tuple(v) for v in true + np.asarray(self.offset_error)))
        return SynthesisOptions(height=height, offsets=offsets, role=self.role, **kw)


def skeleton_height(bone_vectors, reference_vectors) -> float:
    """A CMU skeleton's standing height in the runtime's convention: the
    training leader's :data:`~dancing_points_addon.calibration.TRAIN_HEIGHT`
    times the ratio of the rest height of the head point above the balls of
    the feet, this skeleton's to his (``reference_vectors``)."""
    from dancing_points_addon.skeleton import JOINT_INDEX, rest_joints

    def rest_head(vec):
        j = rest_joints(np.asarray(vec))
        return float(j[TRACKED[0], 1] - j[JOINT_INDEX["lfoot"], 1])

    return TRAIN_HEIGHT * rest_head(bone_vectors) / rest_head(reference_vectors)


def segment_take(seg, tmpdir, scenario: Scenario = Scenario()):
    """The leader's frames of a segment written as a take file (SPEC §3, native
    60 Hz, time from 0) and read back, as SPEC §6 asks; as ``scenario`` says."""
    path = os.path.join(tmpdir, f"lead_{seg['take']}.csv")
    motion = seg["lead60"]
    take = take_from_motion(motion)
    take.time = take.time - take.time[0]
    seg["writer_height"] = height_from_head(take.positions[:, 0, 1])
    if scenario.devices == "openxr":
        take = headset_take(take, motion.rotations[:, list(HAND_BONES)])
    if scenario.floor_shift:
        take.positions[..., 1] += scenario.floor_shift
    if scenario.role != "leader":
        take.meta["role"] = scenario.role
    write_take(path, take)
    return read_take(path)


def noise_robustness(factory, segments, tmpdir, sigma=0.001, draws=1, seed=0, scenario=Scenario()):
    """Per-frame change of each dancer (mean over joints, cm) when Gaussian noise
    of ``sigma`` metres is added to every tracked position of the take: mean
    and 99th percentile over all frames of all takes and draws."""
    rng = np.random.default_rng(seed)
    diffs = {"leader": [], "follower": []}
    for seg in segments:
        take = segment_take(seg, tmpdir, scenario)
        clean = factory(seg).synthesize(take)
        for _ in range(draws):
            noisy = type(take)(take.time, take.positions + rng.normal(0.0, sigma, take.positions.shape),
                               take.quats, take.meta, take.source)
            out = factory(seg).synthesize(noisy)
            for role in diffs:
                a, b = getattr(clean, f"{role}_positions"), getattr(out, f"{role}_positions")
                diffs[role].append(np.linalg.norm(a - b, axis=-1).mean(-1))
    res = {}
    for role, d in diffs.items():
        d = np.concatenate(d) * 100.0
        res[f"noise_{role}_mean_cm"] = float(d.mean())
        res[f"noise_{role}_p99_cm"] = float(np.percentile(d, 99))
        res[f"noise_{role}_max_cm"] = float(d.max())
    return res


def run_system(factory, segments, tmpdir, fixed=None, scenario=Scenario()):
    """Each segment's take (``scenario``) through ``factory(seg)``'s synthesizer
    (or ``fixed``); per take the predicted and true positions to score, and what
    the device and robustness figures need (:func:`device_figures`)."""
    runs = []
    t0 = time.time()
    frames = leashed = 0
    for seg in segments:
        take = segment_take(seg, tmpdir, scenario)
        lr = devices = None
        if fixed is not None:
            (pl, _), (pf, _) = fixed.run(take)
            poses = fixed.lead_pose, fixed.fol_pose
        else:
            synth = factory(seg)
            duet = synth.synthesize(take)
            pl, pf, lr = duet.leader_positions, duet.follower_positions, duet.leader_rotations
            if duet.tracked_role == "follower":  # scored as tracked ("leader_*") and partner ("follower_*")
                pl, pf, lr = duet.follower_positions, duet.leader_positions, duet.follower_rotations
            devices = device_rotations(take, duet.calibration)
            placement = getattr(synth, "_placement", None)
            leashed += placement.leashed if placement is not None else 0
            poses = synth.default_pose["tracked"], synth.default_pose["partner"]
        if scenario.floor_shift:  # against the equally shifted truth
            pl, pf = pl.copy(), pf.copy()
            pl[..., 1] -= scenario.floor_shift
            pf[..., 1] -= scenario.floor_shift
        # each dancer's train pose nearest the mean (the networks' default_pose), as a prior to beat
        mean_poses = tuple(F.pose_positions(np.asarray(p, dtype=np.float64)) for p in poses)
        tl, tf = seg["lead"][0], seg["fol"][0]
        n = min(len(pl), len(tl))
        mask = np.arange(n) / F.FPS >= SCORE_FROM
        runs.append({"pl": pl[:n], "pf": pf[:n], "tl": tl[:n], "tf": tf[:n], "mask": mask,
                     "lead_len": seg["lead_len"], "fol_len": seg["fol_len"],
                     "input_head": tl[:n, TRACKED[0]], "mean_poses": mean_poses,
                     "lr": None if lr is None else lr[:n], "devices": None if devices is None else devices[:n]})
        frames += n
    return runs, {"seconds": time.time() - t0, "frames": frames, "leash_frames": leashed}


def device_rotations(take, calib):
    """``(T, 3, 3, 3)`` at 30 Hz: the rotation each device measures, as the
    bone it turns (the skull; the ``*wrist`` bones, or for ``openxr`` the
    ``*hand`` bones); NaN where a device is lost."""
    from dancing_points_addon.calibration import apply_calibration
    from dancing_points_addon.representation import DEVICE_FROM_HEAD
    from dancing_points_addon.resample import resample_take
    from dancing_points_addon.rotations import quat_to_matrix

    tk = resample_take(apply_calibration(take, calib), F.FPS)
    R = quat_to_matrix(np.nan_to_num(tk.quats))
    R[:, 0] = R[:, 0] @ DEVICE_FROM_HEAD
    R[~tk.valid] = np.nan
    return R


def device_figures(runs, devices="joints"):
    """How far the tracked dancer's head and hands are turned from the devices
    (mean degrees over scored frames), the largest frame-to-frame step of his
    wrists and of both pelvises (m), and the lowest foot point of each dancer
    (cm; its floor at y = 0)."""
    from dancing_points_addon.skeleton import JOINT_INDEX as J

    hands = ("lwrist", "rwrist") if devices == "joints" else ("lhand", "rhand")
    head, wrist = [], []
    for r in runs:
        if r.get("lr") is None:
            continue
        head.append(M.rotation_error_deg(r["lr"][:, J["head"]], r["devices"][:, 0], r["mask"]))
        for i, b in enumerate(hands):
            wrist.append(M.rotation_error_deg(r["lr"][:, J[b]], r["devices"][:, 1 + i], r["mask"]))
    every = [np.ones(len(r["mask"]), dtype=bool) for r in runs]
    return {"head_off_device_deg": M.aggregate(head), "wrists_off_devices_deg": M.aggregate(wrist),
            "max_wrist_step_m": max(M.max_step(r["pl"][:, list(WRISTS)], m) for r, m in zip(runs, every)),
            "max_pelvis_step_m": max(max(M.max_step(r[k][:, :1], m) for k in ("pl", "pf"))
                                     for r, m in zip(runs, every)),
            "lowest_foot_leader_cm": 100 * min(M.lowest_foot(r["pl"], m) for r, m in zip(runs, every)),
            "lowest_foot_follower_cm": 100 * min(M.lowest_foot(r["pf"], m) for r, m in zip(runs, every))}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m training.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/data/cmu_salsa")
    ap.add_argument("--models", default="models")
    ap.add_argument("--ablations", default=None, help="folder with vanilla_*.onnx and pastinput_*.onnx")
    ap.add_argument("--takes", default=None, help="comma list of take numbers (default: all 13)")
    ap.add_argument("--no-foot-lock", action="store_true")
    ap.add_argument("--split", choices=("test", "train", "val"), default="test",
                    help="train / val: score the train frames or their last 20 %% (for choosing settings "
                         "and recipes; the reported table is test)")
    ap.add_argument("--noise", type=float, default=0.0,
                    help="also measure the full system's change under Gaussian noise of this many metres on "
                         "every tracked position (e.g. 0.001)")
    ap.add_argument("--noise-draws", type=int, default=1)
    ap.add_argument("--only-full", action="store_true", help="score the full system only (no ablations)")
    ap.add_argument("--devices", choices=("joints", "openxr"), default="joints",
                    help="write the takes as the SPEC §2 points (joints) or as a headset records them (openxr)")
    ap.add_argument("--offset-error", default=None, metavar="AXIS:M",
                    help="openxr: read the takes with every body offset wrong by M metres along AXIS of each "
                         "device, e.g. +x:0.02 or -z:0.02")
    ap.add_argument("--floor-shift", type=float, default=0.0, metavar="M",
                    help="move the takes' floor by M metres (scored against the equally moved truth)")
    ap.add_argument("--height", default=None,
                    help="give the tracked dancer's height: metres, or 'skeleton' (the dancer's own; default: none, "
                         "estimated)")
    ap.add_argument("--floor-y", type=float, default=None, metavar="Y",
                    help="give the floor's height (default: none; estimated when a height is given)")
    ap.add_argument("--tracked", choices=("leader", "follower"), default="leader",
                    help="follower: her three points as a leader's take (SPEC §6 'on unseen dancers'; only the "
                         "leader's figures mean anything, and they are hers)")
    ap.add_argument("--solo", default=None, metavar="DIR",
                    help="the solo dancer's takes instead of the salsa takes (SPEC §6 'on unseen dancers'): "
                         "with --split test the held-out 05_11-05_20, with --split val the end of 05_01-05_10; "
                         "only the leader's figures mean anything")
    ap.add_argument("--role", choices=("leader", "follower"), default="leader",
                    help="follower: SPEC §6 'reversed', the follower's frames as a role=follower take; the figures "
                         "named leader_* are then the tracked dancer's (hers), follower_* the partner's (his)")
    ap.add_argument("--no-device-follow", action="store_true", help="his head and hands not turned as the devices")
    ap.add_argument("--compute", choices=("float", "int8"), default=None,
                    help="how the int8 networks multiply (default: the runtime's, float; see nets.COMPUTE_MODES)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args(argv)

    takes = tuple(args.takes.split(",")) if args.takes else SALSA_TAKES
    tracked = "follower" if args.role == "follower" else args.tracked
    if args.solo:
        if tracked != "leader" or args.split == "train":
            ap.error("--solo scores a leader's take on --split test or val")
        args.only_full = True
        segments = list(solo_segments(args.solo, args.split, args.data))
    else:
        segments = list(test_segments(args.data, takes, args.split, tracked))
    nets = load_nets(args.models, role=args.role, compute=args.compute)
    error = None
    if args.offset_error:
        axis, metres = args.offset_error.split(":")
        error = np.zeros(3)
        error["xyz".index(axis[-1])] = float(metres) * (-1.0 if axis.startswith("-") else 1.0)
        error = tuple(error)
    height = args.height if args.height in (None, "skeleton") else float(args.height)
    scenario = Scenario(args.devices, error, args.floor_shift, height, args.role)
    kw = dict(foot_lock=not args.no_foot_lock, follow_devices=not args.no_device_follow, floor_y=args.floor_y)
    opts = lambda seg: scenario.options(seg, **kw)  # noqa: E731
    systems = {"full": lambda seg: Synthesizer(opts(seg), nets=nets)}
    partial = {}
    if args.ablations:
        for tag in ("vanilla", "pastinput"):
            paths = {r: os.path.join(args.ablations, f"{tag}_{r}.onnx") for r in ("leader", "follower")}
            paths = {r: p for r, p in paths.items() if os.path.exists(p)}
            if paths:  # an ablation trained for one dancer only keeps the full model's other tracker
                abl = dict(nets, **{r: OnnxNet(p, compute=next(iter(nets.values())).compute)
                                    for r, p in paths.items()})
                partial[tag] = sorted(set(("leader", "follower")) - set(paths))
                # (b) ablates the mapping for the follower too: her placement state,
                # separation and holds (built on the mapping's prediction) go with it
                kw = {"follower": None} if tag == "pastinput" and "follower" not in partial[tag] else {}
                past = tag == "pastinput"
                follower_past = "follower" not in partial[tag]
                systems[{"vanilla": "(a) vanilla MLP tracker", "pastinput": "(b) no mapping, past input"}[tag]] = \
                    (lambda seg, a=abl, kw=kw, past=past, fp=follower_past: Synthesizer(
                        opts(seg), nets=a, keys=PastInputKeys(fp) if past else None, **kw))
    if not args.only_full:
        # (c): no follower mapping, so none of the placement built on it either
        systems["(c) follower from leader trajectory"] = lambda seg: Synthesizer(opts(seg), nets=nets, follower=None,
                                                                                 keys=LeaderTrajKeys())
    names = {"vanilla": "(a) vanilla MLP tracker", "pastinput": "(b) no mapping, past input"}
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, factory in systems.items():
            runs, info = run_system(factory, segments, tmp, scenario=scenario)
            results[name] = {**score(runs), **stability(runs), **info}
            if name == "full":
                results[name].update(device_figures(runs, args.devices))
            cut = cut_last(runs)
            if sum(int(r["mask"].sum()) for r in cut):  # (short takes, the solo dancer's val, have none left)
                results[name]["without_last_2s"] = score(cut)
            tag = next((t for t, n in names.items() if n == name), None)
            if tag in partial and partial[tag]:
                results[name]["not_ablated"] = partial[tag]  # these dancers use the full model
            print(name, json.dumps({k: round(v, 3) if isinstance(v, float) else v
                                    for k, v in results[name].items() if k != "without_last_2s"}), flush=True)
        if args.noise > 0:
            results["full"].update(noise_robustness(systems["full"], segments, tmp, args.noise, args.noise_draws,
                                                    scenario=scenario))
            print("noise", json.dumps({k: round(v, 3) for k, v in results["full"].items() if k.startswith("noise")}),
                  flush=True)
        if not args.only_full:
            fixed = FixedPose(Synthesizer(SynthesisOptions(foot_lock=False), nets=nets),
                              mean_follower_offset(args.data))
            runs, info = run_system(None, segments, tmp, fixed=fixed, scenario=scenario)
            results["(d) fixed pose under the head"] = {**score(runs), **stability(runs), **info}
            print("(d)", json.dumps({k: round(v, 3) if isinstance(v, float) else v
                                     for k, v in results["(d) fixed pose under the head"].items()}), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(markdown_table(results))
    return 0


COLUMNS = [("leader_tracking_cm", "Leader tracking (cm)"), ("leader_fullbody_cm", "Leader full-body (cm)"),
           ("follower_fullbody_cm", "Follower full-body (cm)"), ("hand_cm", "Hand (cm)"),
           ("heading_leader_deg", "Heading L (°)"), ("heading_follower_deg", "Heading F (°)"),
           ("heading_corr", "Heading corr."), ("contact_f1", "Contact F1"),
           ("skating_cm_s", "Skating L (cm/s)"), ("jitter", "Jitter L (m/s³)")]


def markdown_table(results):
    head = "| System | " + " | ".join(c[1] for c in COLUMNS) + " |\n"
    head += "|---" * (len(COLUMNS) + 1) + "|\n"
    rows = []
    follower_cols = {"follower_fullbody_cm", "hand_cm", "heading_follower_deg", "heading_corr"}
    leader_cols = {k for k, _ in COLUMNS} - follower_cols
    for name, r in results.items():
        skip = set()
        if "follower" in r.get("not_ablated", []):
            skip |= follower_cols
        if "leader" in r.get("not_ablated", []):
            skip |= leader_cols
        rows.append(f"| {name} | " + " | ".join("–" if k in skip else f"{r[k]:.2f}" for k, _ in COLUMNS) + " |")
    gt = next(iter(results.values()))
    rows.append("| ground truth | 0 | 0 | 0 | 0 | 0 | 0 | "
                f"{gt['heading_corr_gt']:.2f} | 1 | {gt['skating_gt_cm_s']:.2f} | {gt['jitter_gt']:.2f} |")
    tail = ("\nPose with placement factored out (each body turned and moved onto the true pelvis and hip "
            "heading), full model against each dancer's train pose nearest the mean (`default_pose`): leader "
            f"{gt['leader_pose_cm']:.2f} cm (mean pose {gt['leader_mean_pose_cm']:.2f}), follower "
            f"{gt['follower_pose_cm']:.2f} cm (mean pose {gt['follower_mean_pose_cm']:.2f}).\n")
    return head + "\n".join(rows) + "\n" + tail


if __name__ == "__main__":
    raise SystemExit(main())
