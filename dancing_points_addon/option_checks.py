"""The checks every options object of the synthesis makes of itself on
creation (:class:`~.follower.FollowerOptions`, :class:`~.tracked_pose.TrackedOptions`
and their parts): one ``ValueError`` or ``TypeError`` naming ``Owner.field``."""
from __future__ import annotations


def check_range(owner: str, name: str, value, low=None, high=None, low_open: bool = False) -> None:
    """``value`` within ``low`` .. ``high`` (``low`` excluded when ``low_open``), or
    a ValueError naming ``owner.name``."""
    ok = (low is None or (value > low if low_open else value >= low)) and (high is None or value <= high)
    if not ok:
        lo = "" if low is None else (f"> {low}" if low_open else f">= {low}")
        hi = "" if high is None else f"<= {high}"
        raise ValueError(f"{owner}.{name} must be {' and '.join(x for x in (lo, hi) if x)}, not {value!r}")


def check_kinds(options, kinds: dict) -> None:
    """Each field ``name`` of ``options`` an instance of ``kinds[name]``, or a
    TypeError naming it."""
    owner = type(options).__name__
    for name, kind in kinds.items():
        value = getattr(options, name)
        if not isinstance(value, kind):
            raise TypeError(f"{owner}.{name} must be a {kind.__name__}, not {value!r}")
