# SPDX-License-Identifier: GPL-3.0-or-later
"""The sidebar's *Live* section: the source, Start / Stop and the status."""

import math

import bpy

from .common import SubPanel, split_layout

MAX_NAMED = 4  # ignored senders named in the panel (the rest counted)


class VIEW3D_PT_dancing_points_live(SubPanel, bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points_live"
    bl_label = "Live"
    bl_options = {'DEFAULT_CLOSED'}

    def draw(self, context):
        from ..operators import live

        layout, settings = split_layout(self.layout, context, "dancing_points_live")
        if settings is None:
            return
        run = live.running()
        col = layout.column()
        col.enabled = run is None
        col.prop(settings, "source")
        if settings.source != 'XR':
            col.prop(settings, "port")
            col.prop(settings, "address")
            col.prop(settings, "sender")
            col.prop(settings, "follow_restart")
        if settings.source == 'VMC':
            col.prop(settings, "left_serial")
            col.prop(settings, "right_serial")
        col.prop(settings, "role")
        col.prop(settings, "height")
        row = col.row(heading="Floor")
        row.prop(settings, "use_floor_y", text="")
        sub = row.row()
        sub.active = settings.use_floor_y
        sub.prop(settings, "floor_y", text="")
        layout.prop(settings, "bake")
        if run is None:
            layout.operator("dancing_points.live_start", text="Start", icon='PLAY')
            if live.last_error():  # the last recording stopped on an error: why, and where its take went
                layout.box().label(text=live.last_error(), icon='ERROR')
            return
        layout.operator("dancing_points.live_stop", text="Stop (Keep Take)", icon='SNAP_FACE')
        st = live.status(run)
        box = layout.box().column(align=True)
        box.label(text="{:s}, {:.1f} s".format(st["state"].capitalize(), st["seconds"]))
        box.label(text="Input {:.0f} Hz{:s}, duet frame {:d}".format(
            st["rate_hz"], " from " + st["sender"] if st["sender"] else "", st["frames"]))
        box.label(text="Dropped {:d} (late {:d}, bad {:d}), lost {:d}".format(
            st["dropped"], st["late"], st["malformed"], st["lost"]))
        posed = st["posed_ms"]
        box.label(text="Latency {:s}".format("-" if math.isnan(posed) else "{:.1f} ms".format(posed)))
        ignored = st["ignored_senders"]
        if ignored:
            box.label(text="Ignored {:d} other sender{:s}:".format(len(ignored), "s" if len(ignored) > 1 else ""),
                      icon='INFO')
            for name, packets in ignored[:MAX_NAMED]:
                box.label(text="  {:s}: {:d} packets".format(name, packets))
            if len(ignored) > MAX_NAMED:
                box.label(text="  and {:d} more ({:d} packets)".format(
                    len(ignored) - MAX_NAMED, sum(p for _, p in ignored[MAX_NAMED:])))
        for line in st["events"][-1:]:  # the sender locked onto (or followed)
            box.label(text=line)
        if st["error"]:
            box.label(text=st["error"], icon='ERROR')
        for line in st["warnings"]:
            box.label(text=line, icon='INFO')


classes = (VIEW3D_PT_dancing_points_live,)
