"""Profile: where a duet frame's time goes, stage by stage.

    .venv/bin/python benchmarks/profile_frame.py [--take 08] [--rounds 2]

Synthesises the leader of CMU salsa take ``--take`` (AMC, whole, 30 Hz) in
this process on one thread (ONNX Runtime, OpenMP and BLAS; pin it with
``taskset -c 0`` for figures to compare), once to warm up, then ``--rounds``
times with a wall clock round each named stage of the frame (the networks'
calls, the trackers' step, the two dancers' last stages and what they call,
the partner's placement, keys and holds, pose recovery, ...). Prints the
whole frame's cost without the clocks, then per stage its milliseconds per
duet frame and calls per frame, largest first (nested stages count inside
their callers too; each clock adds about a microsecond a call). Not
collected by pytest; ``bench_frame_loop_vs.py`` is the speed check.
"""
from __future__ import annotations

import argparse
import collections
import os
import pathlib
import sys
import time

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SALSA = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared")) / "data" / "cmu_salsa"


def stages():
    """``[(owner, attribute, label)]``: the callables the profile clocks."""
    from dancing_points_addon import (dancer_state, device_follow, features, follower, foot_lock, ik, nets,
                                      partner_pose, pose, runtime, tracked_pose)

    S = runtime.Synthesizer
    return [
        (nets.OnnxNet, "__call__", "networks (ONNX calls)"),
        (S, "_read", "input read"), (S, "_input_nets", "input networks (per block)"),
        (features, "decode_mapping", "mapping decoded"),
        (S, "_tracked_keys", "his keys"), (S, "_partner_keys", "her keys"),
        (runtime, "tracker_step", "trackers' step"), (runtime, "settle_step", "settle"),
        (tracked_pose.TrackedPose, "__call__", "his last stage"),
        (partner_pose.PartnerPose, "__call__", "her last stage"),
        (pose.Recoveries, "__call__", "pose recovery"),
        (pose.LegJoints, "twist", "her legs' twist"), (pose.LegJoints, "hips", "her hip joints"),
        (tracked_pose, "move_keeping_feet", "his head's reach"),
        (pose.FloorGuard, "__call__", "floor guard"),
        (foot_lock.FootLocker, "step", "foot lock"),
        (foot_lock.KinematicContacts, "__call__", "his kinematic evidence"),
        (device_follow.DeviceFollow, "step", "device follow"), (ik.EndEffectorIK, "step", "end-effector IK"),
        (ik.ArmTurnLimit, "step", "her arms' turn limit"), (pose.OutputSmoothing, "__call__", "output smoothing"),
        (follower.Placement, "smooth", "placement: smoothing"), (follower.Placement, "target", "placement: target"),
        (follower.Placement, "key_roots", "placement: key roots"), (follower.Placement, "step", "placement: step"),
        (follower.Separation, "push", "separation"), (partner_pose.HandHold, "wrist_targets", "holds"),
        (partner_pose.HipTwist, "step", "her hips' turn"), (runtime, "set_poses", "state set"),
        (dancer_state.DancerState, "keep_footing", "footing"), (runtime.DuetFrames, "put", "frames kept"),
    ]


def clock(targets, spent, calls):
    """Wrap each target so that its wall time and calls add up under its label."""
    for owner, name, label in targets:
        f = getattr(owner, name)

        def timed(*a, _f=f, _label=label, **k):
            t = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                spent[_label] += time.perf_counter() - t
                calls[_label] += 1

        setattr(owner, name, timed)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--take", default="08", help="CMU salsa take number (its leader, 60_<take>.amc)")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args(argv)
    from dancing_points_addon.inputs import load_input
    from dancing_points_addon.runtime import Synthesizer
    from dancing_points_addon.synthesis_options import SynthesisOptions

    take = load_input(str(SALSA / f"60_{args.take}.amc"), asf=str(SALSA / "60.asf"))
    synth = Synthesizer(SynthesisOptions(threads=1))
    synth.synthesize(take)  # warm-up
    bare = []
    for _ in range(args.rounds):
        t = time.perf_counter()
        n = synth.synthesize(take).n_frames
        bare.append((time.perf_counter() - t) / n)
    spent, calls = collections.Counter(), collections.Counter()
    clock(stages(), spent, calls)
    t = time.perf_counter()
    frames = sum(synth.synthesize(take).n_frames for _ in range(args.rounds))
    clocked = (time.perf_counter() - t) / frames
    print(f"take 60_{args.take}: {frames // args.rounds} frames; a duet frame {1e3 * min(bare):.3f} ms "
          f"(best of {args.rounds}; {1e3 * clocked:.3f} ms with the clocks below)")
    for label, s in spent.most_common():
        print(f"  {label:28s} {1e3 * s / frames:7.3f} ms   {calls[label] / frames:5.2f} calls a frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
