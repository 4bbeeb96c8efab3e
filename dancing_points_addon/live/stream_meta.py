"""The calibration of a live session from the stream's metadata: which keys a
sender announced and which have come, when the calibration may be made
(:meth:`StreamCalibration._can_calibrate`), the tracked dancer's role and the
switch to its networks, and the warnings when metadata never came.
:class:`~.session.LiveSession` is one (see its module docstring, step 3)."""
from __future__ import annotations

import dataclasses

from ..errors import UserError
from ..formats.limits import FLOOR_RANGE_M, HEIGHT_RANGE_M
from . import ROLES
from .options import SOURCE_DEVICES
from .protocol import META_ANNOUNCE

META_WAIT_S = 2.0  # announced metadata not yet come: the calibration waits this long past its window
# the stream's metadata keys the calibration reads, and the option that overrides each
CALIBRATION_META = {"devices": "devices", "height_m": "height", "floor_y": "floor_y",
                    "head_offset_m": "head_offset", "lhand_offset_m": "hand_offset",
                    "rhand_offset_m": "hand_offset", "role": "role", "head_turn": "head_turn",
                    "lhand_turn": "hand_turn", "rhand_turn": "hand_turn"}


class StreamCalibration:
    """The session's calibration from its stream (a base of
    :class:`~.session.LiveSession`: it reads the session's ``options``,
    ``stream_meta``, ``rows``, ``synth`` and ``warnings``)."""

    def _known(self, key, option):
        if option is not None:
            return True
        return self.stream_meta.get(key) not in (None, "")

    def missing_meta(self) -> list:
        """The keys the sender announced (:data:`~.protocol.META_ANNOUNCE`) that
        the calibration reads, no option overrides and have not come yet."""
        announced = self.stream_meta.get(META_ANNOUNCE) or ""
        o = self.options
        return [k for k in dict.fromkeys(announced.split(","))
                if k in CALIBRATION_META and getattr(o, CALIBRATION_META[k]) is None and k not in self.stream_meta]

    def _can_calibrate(self, t) -> bool:
        o = self.options
        if self._hold_calibration:
            return False
        if self.missing_meta() and t < o.calibration_s + META_WAIT_S:
            return False  # announced and not come (lost on the way): it comes again
        return t >= o.calibration_s or (self._known("height_m", o.height) and self._known("floor_y", o.floor_y))

    def _meta(self) -> dict:
        """The stream's metadata the calibration reads (devices, height, floor,
        offsets), each only when it is a value a take file may carry."""
        from ..formats.devices import DEVICE_KINDS, META_OFFSET_KEYS, META_TURN_KEYS, parse_offset, parse_turn
        from ..formats.take import ORIENTATION_VALUES, ORIENTATIONS_KEY

        meta = {}
        for key, v in self.stream_meta.items():
            try:
                if key == "devices" and v in DEVICE_KINDS:
                    meta[key] = v
                elif key == "height_m" and HEIGHT_RANGE_M[0] <= float(v) <= HEIGHT_RANGE_M[1]:
                    meta[key] = float(v)
                elif key == "floor_y" and abs(float(v)) <= FLOOR_RANGE_M:
                    meta[key] = v
                elif key in META_OFFSET_KEYS:
                    parse_offset(v, key)
                    meta[key] = v
                elif key in META_TURN_KEYS:
                    parse_turn(v, key)
                    meta[key] = v
                elif key == ORIENTATIONS_KEY and v in ORIENTATION_VALUES:
                    meta[key] = v
            except (ValueError, UserError):
                continue
        meta.setdefault("devices", SOURCE_DEVICES.get(self.options.source, "joints"))
        meta["role"] = self.role()
        return meta

    def stream_role(self):
        """The ``role`` the stream's metadata say (None: none, or not a role)."""
        v = self.stream_meta.get("role")
        return v if v in ROLES else None

    def role(self) -> str:
        """The tracked dancer's role: the calibration's once made; before, the
        option's, else the stream's, else ``leader``."""
        if self.calibration is not None:
            return self.calibration.role
        return self.options.role or self.stream_role() or "leader"

    def _warn_role(self) -> None:
        """Once: the stream says another role than the one read (a role given
        wins; one that came after the duet started is too late)."""
        said = self.stream_meta.get("role")
        if self._role_warned or said in (None, "") or said == self.role():
            return
        self._role_warned = True
        why = ("not a role" if said not in ROLES else "the role given wins" if self.options.role
               else "it came after the duet had started")
        self.warnings.append(f"warning: the stream says role={said}; its points are read as the "
                             f"{self.role()}'s ({why})")

    def _switch_role(self, role) -> None:
        """The synthesizer's networks for ``role``, before any frame (timed)."""
        if role in self._unavailable:
            raise UserError(f"the stream's take is a {role}'s (role={role}), whose networks cannot be used: "
                            f"{self._unavailable[role]}")
        t0 = self.clock()
        try:
            self.synth.set_role(role)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        self._live_after = self.clock()
        self.role_switch_s = self._live_after - t0

    def _calibrate(self, n) -> None:
        """Calibrate on the first ``n`` rows (as a take: the options, the stream's
        metadata, else estimated), keep what the take's metadata will say, and
        read the rows so far into frames."""
        c = self.synth.calibrate(self.rows.take(n, self._meta()))
        meta = c.meta()
        # the height and floor as the take file will say them (rounded), the rest as calibrated
        calibration = dataclasses.replace(c, height=float(meta["height_m"]), floor_y=float(meta["floor_y"]))
        if c.role != self.synth.role:
            self._switch_role(c.role)
        self.calibration = calibration
        self.synth.set_calibration(calibration)
        self._catchup = n  # the rows before: read into frames at once, not live
        self._calibrated_t = float(self.rows.time[n - 1])
        missing = self.missing_meta()
        if missing:
            self._warn_missing(missing, self._calibrated_t)
        self._warn_role()

    def _warn_missing(self, missing, t) -> None:
        c = self.calibration
        said = []
        if "devices" in missing:
            said.append(f"devices {c.devices} (the {self.options.source} default)")
        if "height_m" in missing:
            said.append(f"height {c.height:.2f} m ({c.height_source})")
        if "floor_y" in missing:
            said.append(f"floor at y = {c.floor_y:+.3f} m ({c.floor_source})")
        if any(k.endswith("_offset_m") for k in missing):
            said.append("the default body offsets")
        if "role" in missing:
            said.append(f"role {c.role} (the default)")
        self.warnings.append(f"warning: the sender's take metadata ({', '.join(missing)}) had not come "
                             f"{t:.1f} s into the take (lost on the way?); calibrated without it: "
                             f"{', '.join(said)}")
