"""Bone mappings: which target bone follows which source (SPEC §2) bones.

A mapping is a plain dict ``{target bone name: source chain}``; a source chain
is one SPEC bone (``"lfemur"``) or consecutive SPEC bones joined by ``+``
(``"lradius+lwrist"``: the elbow -> wrist segment), and ``"root"`` for the
pelvis (it carries the root motion). Several target bones mapped to the same
chain share it in proportion to their rest lengths (Rigify's
``DEF-upper_arm.L`` + ``DEF-upper_arm.L.001``, a 5-bone UE5 spine on the
3-bone CMU spine). Target bones that are not mapped keep their reference pose
relative to their parent. :func:`auto_mapping` guesses a mapping from the bone
names for the conventions in ``presets/*.json`` (CMU/BVH, Mixamo with or
without the ``mixamorig:`` prefix, Rigify ``DEF-`` and meta-rig, VRM as
exported by VRoid and VRM 1.0 humanoid names, Unreal; a rig no preset fits is
mapped by structure, :mod:`.structure`);
:func:`save_preset` / :func:`load_preset` write and read a mapping as JSON.
"""
from __future__ import annotations

import glob
import json
import os

from ..errors import UserError
from ..formats.naming import normalise_name
from ..formats.files import atomic_output
from ..skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS

PRESET_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "presets")
ROOT_CHAIN = "root"
SIDES = ("l", "r")


class RetargetError(UserError, ValueError):
    """A mapping or rig that cannot be retargeted (one user-facing line)."""


def parse_chain(chain: str):
    """SPEC bone indices of a chain string (``"a+b"``); raises on unknown or
    non-consecutive bones."""
    parts = [p.strip() for p in str(chain).split("+") if p.strip()]
    if not parts:
        raise RetargetError("empty source chain")
    idx = []
    for p in parts:
        if p not in JOINT_INDEX:
            raise RetargetError("unknown source bone {!r} (SPEC §2 names: {:s})".format(p, ", ".join(JOINT_NAMES)))
        idx.append(JOINT_INDEX[p])
    for a, b in zip(idx, idx[1:]):
        if PARENTS[b] != a:
            raise RetargetError("source chain {!r}: {:s} is not the child of {:s}".format(
                chain, JOINT_NAMES[b], JOINT_NAMES[a]))
    if idx[0] == 0 and len(idx) > 1:
        raise RetargetError("'root' cannot start a chain")
    return idx


def builtin_conventions():
    """``{name: preset dict}`` of the JSON presets shipped in ``retarget/presets/``."""
    out = {}
    for path in sorted(glob.glob(os.path.join(PRESET_DIR, "*.json"))):
        try:
            preset = load_preset(path)
        except (OSError, ValueError):
            continue
        out[preset.get("name") or os.path.splitext(os.path.basename(path))[0]] = preset
    return out


def load_preset(path) -> dict:
    """A preset: ``{"name", "convention", "signature", "bones": {target: chain}}``.
    Chains are validated; an unreadable file raises :class:`RetargetError`."""
    try:
        with open(path, "r", encoding="utf-8") as fh:
            data = json.load(fh)
    except OSError as exc:
        raise RetargetError("cannot read {:s}: {:s}".format(os.fspath(path), exc.strerror or str(exc))) from None
    except json.JSONDecodeError as exc:
        raise RetargetError("{:s}: not JSON ({:s})".format(os.fspath(path), str(exc))) from None
    except UnicodeDecodeError:  # a binary file (an .npz, a .blend, ...)
        raise RetargetError("{:s}: not a bone map (not UTF-8 text)".format(os.fspath(path))) from None
    except RecursionError:
        raise RetargetError("{:s}: not a bone map (JSON nested too deeply)".format(os.fspath(path))) from None
    if not isinstance(data, dict) or not isinstance(data.get("bones"), dict):
        raise RetargetError("{:s}: a preset needs a 'bones' object {{target bone: source chain}}".format(
            os.fspath(path)))
    for tgt, chain in data["bones"].items():
        if chain:
            parse_chain(chain)
    data.setdefault("name", os.path.splitext(os.path.basename(os.fspath(path)))[0])
    data.setdefault("signature", [])
    return data


def save_preset(path, mapping: dict, name: str = "", convention: str = "") -> None:
    """Write ``mapping`` ({target bone: source chain}) as a JSON preset."""
    for chain in mapping.values():
        parse_chain(chain)
    data = {"name": name or os.path.splitext(os.path.basename(os.fspath(path)))[0],
            "convention": convention, "bones": {k: mapping[k] for k in mapping}}
    with atomic_output(path, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")


def detect_convention(names, conventions=None):
    """``(convention name, matched bones)`` that fits ``names`` best: most
    signature bones found, then most bones found; ``(None, 0)`` when nothing matches."""
    conventions = builtin_conventions() if conventions is None else conventions
    norm = {normalise_name(n) for n in names}
    best, best_key = None, (0, 0)
    for cname, preset in conventions.items():
        table = {normalise_name(k) for k in preset["bones"]}
        sig = sum(1 for s in preset.get("signature", []) if normalise_name(s) in norm)
        hits = len(table & norm)
        key = (sig, hits)
        if hits and key > best_key:
            best, best_key = cname, key
    return best, best_key[1]


# Spine and neck chains that are split evenly when the rig's bone count differs.
_SPINE = "lowerback+upperback+thorax"
_NECK = "lowerneck+upperneck"


def auto_mapping(names, convention=None, conventions=None):
    """``(mapping, convention)``: target bone -> source chain guessed from the names.

    ``convention``: a preset name to use (default: :func:`detect_convention`).
    A spine (neck) whose number of bones differs from the preset's is mapped as
    one chain on the whole source spine (neck)."""
    conventions = builtin_conventions() if conventions is None else conventions
    if convention is None:
        convention, _ = detect_convention(names, conventions)
    if convention is None:
        return {}, None
    if convention not in conventions:
        raise RetargetError("unknown convention {!r} (known: {:s})".format(convention, ", ".join(conventions)))
    table = {normalise_name(k): v for k, v in conventions[convention]["bones"].items()}
    mapping = {}
    for n in names:
        chain = table.get(normalise_name(n))
        if chain:
            mapping[n] = chain
    # Spine / neck counts: 1:1 only when the rig has exactly as many bones.
    for whole, parts in ((_SPINE, ("lowerback", "upperback", "thorax")), (_NECK, ("lowerneck", "upperneck"))):
        members = [n for n, c in mapping.items() if c == whole or c in parts or set(c.split("+")) <= set(parts)]
        singles = [n for n in members if mapping[n] in parts]
        if members and not (len(singles) == len(members) == len(parts)
                            and sorted(mapping[n] for n in singles) == sorted(parts)):
            for n in members:
                mapping[n] = whole
    return mapping, convention


def validate_mapping(mapping: dict, names) -> dict:
    """The usable part of ``mapping``: known target bones, valid chains, at most
    one ``root``. Raises when nothing usable (no root or no leg) remains."""
    names = set(names)
    out = {}
    for tgt, chain in mapping.items():
        if tgt not in names or not chain:
            continue
        parse_chain(chain)
        out[tgt] = chain
    roots = [t for t, c in out.items() if c == ROOT_CHAIN]
    if len(roots) != 1:
        raise RetargetError("the mapping needs exactly one bone mapped to 'root' (the pelvis), found {:d}".format(
            len(roots)))
    for side in SIDES:
        for part in ("femur", "tibia"):
            if not any(side + part in c.split("+") for c in out.values()):
                raise RetargetError("the mapping has no bone for {:s}".format(side + part))
    return out
