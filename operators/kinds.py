# SPDX-License-Identifier: GPL-3.0-or-later
"""What a collection the add-on made is: a take (three empties) or a duet (two
baked dancers), by its ``Collection.dancing_points.kind`` (:mod:`.props`).

Its own module, importing nothing of the add-on's, so that :mod:`.props` and
:mod:`.stage` (whose camera mode the scene's settings update) both import it
at the top.
"""

# Values of Collection.dancing_points.kind
KIND_NONE, KIND_TAKE, KIND_DUET = 'NONE', 'TAKE', 'DUET'


def _is_kind(coll, kind):
    return coll is not None and getattr(coll, "dancing_points", None) is not None \
        and coll.dancing_points.kind == kind


def is_take(coll):
    return _is_kind(coll, KIND_TAKE)


def is_duet(coll):
    return _is_kind(coll, KIND_DUET)
