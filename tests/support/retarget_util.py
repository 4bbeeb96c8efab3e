"""Retarget test helpers that need ``bpy`` (shared by test_retarget and
test_retarget_rigs): the duet's take, landmarks, Blender's evaluation of rigs
and the per-frame check of a retargeted rig."""
from __future__ import annotations

import bpy
import numpy as np

from dancing_points_addon import retarget as rt
from .ext_util import import_from_extension

from .helpers import CM, SECONDS, SRC_POINTS, START, TGT_POINTS, cut


def baked_salsa_duet(folder, models):
    """Seconds ``START .. START + SECONDS`` of CMU salsa take 60_10 written as a
    take in ``folder``, imported and synthesised in a fresh scene: ``(duet
    collection, {role: DP armature})``."""
    from conftest import SALSA
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.formats.take import take_from_motion, write_take

    from . import blender_scene_util as bsu

    m = load_amc(SALSA / "60_10.amc")
    csv = folder / "salsa_5s.csv"
    write_take(csv, take_from_motion(cut(m, int(START * m.fps), int(SECONDS * m.fps))))
    bsu.fresh_scene()
    assert bpy.ops.dancing_points.import_take(filepath=str(csv)) == {'FINISHED'}
    assert bpy.ops.dancing_points.synthesize(model_dir=models) == {'FINISHED'}
    duet = next(c for c in bpy.data.collections if c.dancing_points.kind == 'DUET')
    return duet, import_from_extension("operators.retarget").duet_armatures(duet)


def reference(arm):
    """Rest data and the reference pose (world) of a rig before retargeting."""
    names = [b.name for b in arm.data.bones]
    mw = np.array(arm.matrix_world)
    return {"rest": {n: np.array(arm.data.bones[n].matrix_local) for n in names},
            "world": {n: mw @ np.array(arm.pose.bones[n].matrix) for n in names}}


def evaluate(objs, frames):
    """Blender-evaluated world matrices ``{obj name: (T, B, 4, 4)}`` of armatures'
    pose bones at ``frames``, and bone names."""
    scene = bpy.context.scene
    out = {o.name: np.empty((len(frames), len(o.pose.bones), 4, 4)) for o in objs}
    for i, f in enumerate(frames):
        scene.frame_set(int(f))
        for o in objs:
            mw = np.array(o.matrix_world)
            for j, pb in enumerate(o.pose.bones):
                out[o.name][i, j] = mw @ np.array(pb.matrix)
    return out


def points(W, names, table, tails=False, lengths=None):
    idx = {n: i for i, n in enumerate(names)}
    out = {}
    for key, bone in table.items():
        m = W[:, idx[bone]]
        if tails:
            y = np.array([0.0, lengths[bone], 0.0, 1.0])
            out[key] = np.einsum("tij,j->ti", m, y)[:, :3]
        else:
            out[key] = m[:, :3, 3]
    out["hips"] = 0.5 * (out.pop("lhip") + out.pop("rhip"))
    return out


def source_height(arm, ankles):
    """Standing height of the skull base of a DP armature: ankle floor level + leg + rest torso."""
    b = arm.data.bones
    leg = np.mean([b[s + "femur"].length + b[s + "tibia"].length for s in "lr"])
    hip = 0.5 * (np.array(b["lhipjoint"].tail_local) + np.array(b["rhipjoint"].tail_local))
    skull = np.array(b["upperneck"].tail_local)
    floor = float(np.mean(np.percentile(ankles[..., 2], 5, axis=0)))
    return floor + leg + (skull[2] - hip[2])


def check_rig(sc, role, target, ref, convention, label):
    frames = sc["frames"]
    src = sc["dp"][role]
    W = evaluate([src, target], frames)
    s_names = [pb.name for pb in src.pose.bones]
    t_names = [pb.name for pb in target.pose.bones]
    sp_blender = points(W[src.name], s_names, SRC_POINTS, tails=True,
                         lengths={n: src.data.bones[n].length for n in s_names})
    tp = points(W[target.name], t_names, TGT_POINTS[convention])
    # The source as the retarget reads it (its action's keys, SPEC positions): the
    # contacts are thresholds, so both sides must see the very same numbers. It is
    # Blender's evaluation of the source to well under a millimetre.
    rmod = import_from_extension("operators.retarget")
    _, pos, rot, _, mat = rmod.source_motion(src)
    sp = rt.source_landmarks(rt.source_world(pos, rot, mat)[0])
    sp = {k: sp[k] for k in sp_blender}
    worst = max(np.abs(sp[k] - sp_blender[k]).max() for k in sp)
    assert worst < 1e-3, worst
    ankles = np.stack([sp["lankle"], sp["rankle"]], 1)
    Hs = source_height(src, ankles)
    tgt = TGT_POINTS[convention]
    Ht = float(ref["world"][tgt["head"]][2, 3])  # skull base, standing reference, floor z=0
    print(f"\n[{label}] {len(frames)} frames; height (skull base) source {Hs:.3f} m, target {Ht:.3f} m")
    # 1. Landmarks follow the source after normalising by height: horizontally about the
    # duet's centre, vertically above the floor, times Hs / Ht (errors at the source's size).
    # "standing-relative": the hips' and ankles' heights counted from their own standing
    # height, which differs between rigs by where they put these joints and by their
    # leg-to-height proportion (the pelvis height follows the leg length by design).
    c = np.append(sc["centre"], 0.0)
    a_floor = float(np.mean(np.percentile(ankles[..., 2], 5, axis=0)))
    b = src.data.bones
    stand_s = {"hips": a_floor + np.mean([b[x + "femur"].length + b[x + "tibia"].length for x in "lr"]),
               "lankle": a_floor, "rankle": a_floor}
    stand_t = {"hips": 0.5 * (ref["world"][tgt["lhip"]][2, 3] + ref["world"][tgt["rhip"]][2, 3]),
               "lankle": ref["world"][tgt["lankle"]][2, 3], "rankle": ref["world"][tgt["rankle"]][2, 3]}
    groups = {"hips": ["hips"], "hands": ["lwrist", "rwrist"], "feet": ["lankle", "rankle"], "head": ["head"]}
    means, raw, horizontal = {}, {}, {}
    for g, keys in groups.items():
        e_abs, e_rel, e_hor = [], [], []
        for k in keys:
            d = (tp[k] - c) * (Hs / Ht) - (sp[k] - c)
            e_abs.append(np.linalg.norm(d, axis=-1))
            e_hor.append(np.linalg.norm(d[:, :2], axis=-1))
            d[:, 2] -= stand_t.get(k, 0.0) * (Hs / Ht) - stand_s.get(k, 0.0)
            e_rel.append(np.linalg.norm(d, axis=-1))
        e_abs, e_rel, e_hor = np.concatenate(e_abs), np.concatenate(e_rel), np.concatenate(e_hor)
        raw[g], means[g], horizontal[g] = e_abs.mean(), e_rel.mean(), e_hor.mean()
        print(f"  {g:5s}: normalised position error mean {e_abs.mean() / CM:.2f} cm (max {e_abs.max() / CM:.2f}); "
              f"standing-relative mean {e_rel.mean() / CM:.2f} cm (max {e_rel.max() / CM:.2f}); "
              f"horizontal mean {e_hor.mean() / CM:.2f} cm")
    # Horizontally nothing is measured from a standing height: there the plain
    # height-normalised error must be under 3 cm too.
    assert max(horizontal.values()) < 3 * CM, horizontal
    # 2. No foot point slides while in contact: the source's foot points are in contact
    # where they are planted (SPEC §6 contact — low and slow — and within 2 cm of where the
    # contact began; a foot pivoting on its ball or gliding is low and slow but not planted).
    # Also reported: the same over the SPEC §6 contacts alone.
    feet = ("lankle", "lball", "rankle", "rball")
    fp = np.stack([sp[k] for k in feet], 1)
    spec = rt.detect_contacts(fp, fps=30.0)
    results = {}
    for label_c, contact in (("planted", rt.planted(spec, fp)), ("SPEC-only", spec)):
        slide_t, slide_s = [0.0], [0.0]
        for j, k in enumerate(feet):
            c = contact[:, j]
            t = 0
            while t < len(c):
                if not c[t]:
                    t += 1
                    continue
                s0 = t
                while t < len(c) and c[t]:
                    t += 1
                slide_t.append(np.linalg.norm(tp[k][s0:t, :2] - tp[k][s0, :2], axis=-1).max())
                slide_s.append(np.linalg.norm(sp[k][s0:t, :2] - sp[k][s0, :2], axis=-1).max())
        results[label_c] = max(slide_t)
        print(f"  {label_c} contacts: {contact.mean() * 100:.0f}% of foot-point frames, {len(slide_t) - 1} runs; "
              f"largest slide target {max(slide_t) / CM:.2f} cm (source {max(slide_s) / CM:.2f} cm)")
    slide_t = [results["planted"]]
    # 3. No bone flips.
    steps = rt.rotation_steps_deg(W[target.name])
    print(f"  largest frame-to-frame bone rotation {steps.max():.1f} deg")
    # 4. Rest pose untouched.
    for n, m in ref["rest"].items():
        np.testing.assert_allclose(np.array(target.data.bones[n].matrix_local), m, atol=1e-6)
    return means, max(slide_t), steps.max()
