"""Retarget a dancer of the duet (SPEC §2 skeleton) onto any humanoid rig
(numpy only, no ``bpy``; the Blender side is ``operators/retarget/``).

Everything happens in Blender *world* space (Z up, metres), per frame and
vectorised over the frames.

- :mod:`.mapping`: bone mappings {target bone: source chain}, the naming
  conventions (``presets/*.json``), automatic mapping, validation.
- :mod:`.source`: the source dancer (SPEC pose from an armature's channels, in
  world space), its landmarks, the duet's centre.
- :mod:`.rig`: the target rig as arrays, ``matrix_basis`` <-> pose, channels.
- :mod:`.solver`: :class:`Retargeter` (rest-pose alignment, proportions, head
  and arms).
- :mod:`.contacts`: foot contacts and foot locks.
- :mod:`.holds`: hands that hold each other (:func:`close_hands`).

The names below are the package's API (``from . import retarget as rt; rt.X``).
"""
from .contacts import detect_contacts, planted
from .holds import close_hands
from .mapping import RetargetError, auto_mapping, builtin_conventions, load_preset, save_preset, validate_mapping
from .rig import TargetRig, channels, pose_from_basis, rotation_steps_deg
from .solver import Retargeter
from .source import FOOT_POINTS, duet_origin, source_landmarks, source_world, source_wrists, spec_pose_from_channels

__all__ = [
    "RetargetError", "auto_mapping", "builtin_conventions", "load_preset", "save_preset", "validate_mapping",
    "FOOT_POINTS", "duet_origin", "source_landmarks", "source_world", "source_wrists", "spec_pose_from_channels",
    "TargetRig", "channels", "pose_from_basis", "rotation_steps_deg",
    "Retargeter", "detect_contacts", "planted", "close_hands",
]
