"""What a user chooses for a synthesis (:class:`SynthesisOptions`): one object
from the command line, the batch jobs, live and the Blender operators to the
:class:`~.runtime.Synthesizer`. The partner's own settings are
:class:`~.follower.FollowerOptions`."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SynthesisOptions:
    """What a user chooses for a synthesis: one object from the command line,
    the batch jobs and the Blender operator to the :class:`~.runtime.Synthesizer`.

    ``models``: the folder of the networks (None: ``$DP_MODEL_DIR``, else the
    bundled ``models/``); ``threads``: ONNX Runtime threads; ``height``: the
    tracked dancer's standing height in metres (None or "auto": the take's
    ``height_m``, else estimated from the take, see :mod:`.calibration`);
    ``floor_y``: where the real floor lies in the take (None: the take's
    ``floor_y``, else estimated when the height is given, else y = 0);
    ``devices``: what the take's poses are, SPEC §3 (None: the take's
    ``devices``, else ``joints``); ``head_offset`` / ``hand_offset``: the
    wearer's own body offsets for ``openxr`` devices (x, y, z metres; see
    :mod:`.formats.devices`), or ``offsets``, all three at once (a
    :class:`~.formats.devices.DeviceOffsets`); ``foot_lock``: contact-based foot locking;
    ``hand_ik``: put the leader's head and wrists exactly on the input
    (two-bone arm IK, neck turn; on by default: it is what the paper scores,
    and the measured full-body error falls from 13.8 to 8.3 cm);
    ``follow_devices``: the tracked dancer's head and hands turn as the devices
    do (:mod:`.device_follow`); ``role``: whose three points the take holds,
    SPEC §3 (None: the take's ``role``, else ``leader``).
    """

    models: str | None = None
    threads: int = 1
    height: float | str | None = None
    foot_lock: bool = True
    hand_ik: bool = True
    floor_y: float | None = None
    devices: str | None = None
    head_offset: tuple | None = None
    hand_offset: tuple | None = None
    offsets: object | None = None
    head_turn: tuple | None = None
    hand_turn: tuple | None = None
    follow_devices: bool = True
    role: str | None = None
