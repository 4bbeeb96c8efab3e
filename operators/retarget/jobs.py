# SPDX-License-Identifier: GPL-3.0-or-later
"""Retargeting the dancers of a baked duet: one dancer (:func:`retarget_one`,
its hands closed onto the partner's rig when that one was already retargeted),
both at once (:func:`retarget_pair`, hands closed symmetrically) and a whole
duet collection (:func:`retarget_duet_onto`, the batch command's way)."""

import bpy
import numpy as np

from ...dancing_points_addon import retarget as rt
from ...dancing_points_addon.retarget import RetargetError
from ...dancing_points_addon.retarget import rigify as rgf
from ...dancing_points_addon.errors import UserError, error_message
from .. import bake
from ..kinds import is_duet
from ..props import ROLE_PROP, ROLES
from . import apply
from .keying import key_rig, keyed_world, mark_output, release
from .mapping import mapping_for, stored_mapping
from .props import SOURCE_PROP, TARGET_PROP
from .rig import source_motion, target_rig


class _Job:
    """One dancer: its DP armature, the target rig and the solved pose."""

    def __init__(self, source, target, preset="", foot_lock=True, origin=None):
        if source is None or source.type != 'ARMATURE':
            raise RetargetError("the source must be a Dancing Points armature")
        if target is None or target.type != 'ARMATURE':
            raise RetargetError("the target must be an armature")
        if source == target:
            raise RetargetError("source and target are the same armature")
        if target.get(ROLE_PROP) in ROLES:  # a duet's own armature: its baked dance would be replaced
            raise RetargetError("'{:s}' is a Dancing Points armature (a duet's dancer), not a rig to "
                                "retarget onto".format(target.name))
        self.source, self.target = source, target
        self.stored = apply.stored_state(target)  # bone map, reference pose, ...: put back by undo()
        self.snap = self.action = None
        try:
            self._solve(preset, foot_lock, origin)
        except BaseException:
            self.undo()
            raise

    def _solve(self, preset, foot_lock, origin):
        source, target = self.source, self.target
        bpy.context.view_layer.update()  # up-to-date matrix_world of objects moved since the last evaluation
        self.frames, self.pos, self.rot, bv, self.src_matrix = source_motion(source)
        self.notes = []
        try:
            mapping = mapping_for(target, preset, self.notes)
            controls = apply.uses_controls(target, mapping)
            self.ret = rt.Retargeter(bv, target_rig(target, deform_parents=controls), mapping, foot_lock=foot_lock,
                                     rigid=rgf.rigid_segments(mapping) if controls else ())
        except RetargetError as exc:
            raise RetargetError("{:s}: {:s}".format(target.name, error_message(exc))) from None
        if origin is None:
            origin = _duet_origin(source)
        self.pose = self.ret.solve(self.pos, self.rot, self.src_matrix, fps=_fps(), origin=origin)

    def src_wrists(self):
        return rt.source_wrists(rt.source_world(self.pos, self.rot, self.src_matrix)[0])

    def key(self):
        """Key the solved pose (a new action; on a Rigify rig its controls), then
        check with Blender's evaluation that the rig follows it; when it does not,
        the rig is put back as it was and :class:`RetargetError` raised. Returns the
        action (the rig's previous one is still there: see :func:`_commit`)."""
        self.name = name = "DP {:s} {:s}".format(self.target.name, self.source.name)
        self.snap = apply.snapshot(self.target)
        self.src_prev = self.source.get(TARGET_PROP)
        self.action = None
        self.controls = apply.uses_controls(self.target, self.ret.mapping)
        try:
            if self.controls:
                self.action = apply.key_controls(self.target, self.pose.W, self.frames, name)
            else:
                self.action = key_rig(self.target, self.ret.basis(self.pose.W), self.frames, name)
            mark_output(self.action)
            self.verified_error = apply.verify(self.target, self.ret, self.pose.W, self.frames)
        except Exception:
            self.undo()
            raise
        self.target[SOURCE_PROP] = self.source.name
        self.source[TARGET_PROP] = self.target.name
        self.action[SOURCE_PROP] = self.source.name
        return self.action

    def undo(self):
        """Put the target back as it was before this job: its action, pose, bone
        map and custom properties (and the source's link to it)."""
        if self.snap is not None:
            apply.restore(self.target, self.snap, self.action)
            if self.src_prev is None:
                self.source.pop(TARGET_PROP, None)
            else:
                self.source[TARGET_PROP] = self.src_prev
            self.snap = self.action = None
        apply.restore_stored(self.target, self.stored)

    def info(self):
        out = {"action": self.action, "scale": self.ret.scale, "pose": self.pose, "retargeter": self.ret,
               "frames": self.frames, "verified_error": self.verified_error, "controls": self.controls}
        if self.notes:
            out["note"] = " ".join(self.notes)
        return out


def _commit(jobs):
    """Once every rig of the run is keyed: the actions the new ones replaced go when
    they were earlier outputs of the retarget that nothing uses any more (each once:
    two rigs may have played the same one)."""
    new, old = [job.action for job in jobs], []
    for job in jobs:
        prev = job.snap["action"]
        if prev is not None and prev not in new and prev not in old:
            old.append(prev)
    for prev in old:
        release(prev)
    for job in jobs:  # made while the output it replaced still had the name ("… .001"): take it back
        if job.action.name != job.name and job.name not in bpy.data.actions:
            job.action.name = job.name
            mark_output(job.action)


def _duet_origin(*sources):
    """Centre of the duet of ``sources`` (DP armatures; the partner of a single one
    is found in its duet collection) about which root motion is scaled."""
    if len(sources) == 1:
        partner = _partner_of(sources[0])
        sources = sources + ((partner,) if partner is not None else ())
    pts = []
    for src in sources:
        try:
            _, pos, rot, _, mat = source_motion(src)
        except RetargetError:
            continue
        pts.append(rt.source_world(pos, rot, mat)[0])
    return rt.duet_origin(*pts) if pts else None


def _fps():
    scene = bpy.context.scene
    return scene.render.fps / scene.render.fps_base if scene is not None else 30.0


def _dancers(coll, kind='ARMATURE'):
    """The objects of ``coll`` of type ``kind`` that are a dancer (leader or follower)."""
    return [o for o in coll.objects if o.type == kind and o.get(ROLE_PROP) in ROLES]


def _partner_of(source):
    """The other DP armature of ``source``'s duet collection, or None."""
    role = source.get(ROLE_PROP)
    for coll in source.users_collection:
        if is_duet(coll):
            for o in _dancers(coll):
                if o != source and o.get(ROLE_PROP) != role:
                    return o
    return None


def _close_onto_partners_rig(job, info):
    """Close ``job``'s hands onto the rig its source's partner was retargeted onto, if any."""
    source, target = job.source, job.target
    partner = _partner_of(source)
    prig = bpy.data.objects.get(partner.get(TARGET_PROP, "")) if partner is not None else None
    if prig is None or prig.type != 'ARMATURE' or prig == target \
            or prig.get(SOURCE_PROP) != partner.name or not stored_mapping(prig):
        return
    try:
        pframes, ppos, prot, pbv, pmat = source_motion(partner)
        if len(pframes) == len(job.frames) and np.allclose(pframes, job.frames):
            pmap = stored_mapping(prig)
            pctl = apply.uses_controls(prig, pmap)
            prest = target_rig(prig, store=False, deform_parents=pctl)
            pret = rt.Retargeter(pbv, prest, pmap, foot_lock=False,
                                 rigid=rgf.rigid_segments(pmap) if pctl else ())
            if apply.uses_controls(prig, pret.mapping):  # keyed on controls: Blender's evaluation
                pw = pret.wrists(apply.evaluated_world(prig, job.frames))
            else:
                pw = pret.wrists(keyed_world(prig, pret, job.frames))
            src_b = rt.source_wrists(rt.source_world(ppos, prot, pmat)[0])
            before, after = rt.close_hands(job.ret, job.pose, job.src_wrists(), src_b, wrists_b=pw)
            info["hand_gap_before"], info["hand_gap_after"] = before, after
    except UserError as exc:
        info["warning"] = "hands not closed: {:s}".format(error_message(exc))


def retarget_one(context, source, target, preset="", foot_lock=True, close_hands=True):
    """Retarget ``source`` (a DP armature) onto ``target``; the hands close onto the
    partner's rig when the partner dancer was already retargeted. Returns a dict of figures."""
    bake.ensure_object_mode(context)
    job = _Job(source, target, preset, foot_lock)
    info = {"scale": job.ret.scale, "frames": len(job.frames)}
    try:
        if close_hands:
            _close_onto_partners_rig(job, info)
        job.key()
    except BaseException:
        job.undo()
        raise
    _commit([job])
    info.update(job.info())
    info["frames"] = len(job.frames)
    return info


def retarget_pair(context, pairs, preset=("", ""), foot_lock=True, close_hands=True):
    """Retarget ``pairs`` = ((leader DP armature, rig), (follower DP armature, rig))
    jointly (hands closed symmetrically). Returns ``{role: info}``."""
    if len(pairs) == 2 and pairs[0][1] == pairs[1][1]:
        raise RetargetError("'{:s}' is picked for both dancers: one rig can dance one part".format(pairs[0][1].name))
    bake.ensure_object_mode(context)
    origin = _duet_origin(*[s for s, _ in pairs]) if len(pairs) == 2 else None
    jobs, out = [], {}
    try:
        for (s, t), p in zip(pairs, preset):
            jobs.append(_Job(s, t, p, foot_lock, origin))
        if close_hands and len(jobs) == 2 and len(jobs[0].frames) == len(jobs[1].frames):
            a, b = jobs
            before, after = rt.close_hands(a.ret, a.pose, a.src_wrists(), b.src_wrists(), b.ret, b.pose)
            out["hand_gap_before"], out["hand_gap_after"] = before, after
        for job in jobs:
            job.key()
    except BaseException:
        for job in reversed(jobs):  # all or nothing: the other rig back as it was too
            job.undo()
        raise
    _commit(jobs)
    for job, role in zip(jobs, ROLES):
        out[role] = job.info()
    return out


def duet_armatures(duet_collection):
    """``{role: DP armature}`` of a duet collection."""
    out = {}
    for o in _dancers(duet_collection):
        out.setdefault(o[ROLE_PROP], o)
    return out


def retarget_duet_onto(leader_rig_obj, follower_rig_obj, duet_collection, context=None, foot_lock=True,
                       close_hands=True, hide_bodies=True):
    """Retarget the duet in ``duet_collection`` (made by ``dancing_points.synthesize``)
    onto two armature objects (either may be None to skip that dancer). With
    ``hide_bodies`` the duet's default bodies are hidden in renders and the
    viewport. Returns ``{role: {"action", "scale", ...}}``; raises
    :class:`RetargetError` with a one-line message."""
    context = context or bpy.context
    if duet_collection is None or not is_duet(duet_collection):
        raise RetargetError("not a Dancing Points duet collection")
    arms = duet_armatures(duet_collection)
    pairs = [(arms.get(role), rig) for role, rig in zip(ROLES, (leader_rig_obj, follower_rig_obj))
             if rig is not None]
    if not pairs:
        raise RetargetError("no rig to retarget onto")
    for src, rig in pairs:
        if src is None:
            raise RetargetError("the duet has no armature for a dancer")
    if len(pairs) == 2:
        out = retarget_pair(context, pairs, foot_lock=foot_lock, close_hands=close_hands)
    else:
        src, rig = pairs[0]
        out = {src[ROLE_PROP]: retarget_one(context, src, rig, foot_lock=foot_lock, close_hands=close_hands)}
    if hide_bodies:
        hide_duet_bodies(duet_collection)
    return out


def hide_duet_bodies(duet_collection, hide=True):
    """Hide (or show) the duet's default bodies in the viewport and renders (the
    armatures stay: they drive the retargeted rigs' source data)."""
    for o in _dancers(duet_collection, 'MESH'):
        o.hide_render = hide
        o.hide_viewport = hide
