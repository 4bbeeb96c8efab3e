"""A smooth procedural mannequin and linear blend skinning, in numpy.

:func:`make_body` builds a default body — a smooth, proportioned mannequin —
around the rest pose of the SPEC §2 skeleton (the ASF T-pose in motion space,
root at the origin, facing +Z, left = +X, Y up):

1. *Shape*: an implicit surface, the signed distance field of round cones
   (limbs, neck, shoulders, thumbs; flattened ones for the mitten hands and
   the feet) and ellipsoids (pelvis, belly, chest, head) placed on the bones
   and sized from the skeleton's height (``proportions``). Parts of one limb meet in a hard union
   (the round cones share their sphere at the joint: no seam, no bulge);
   different parts meet in a polynomial smooth union (no crease).
2. *Surface*: the field is sampled on a grid of 1.4 cm cells (for the
   reference skeleton, CMU subject 60; scaled with the skeleton, so every
   body has the same mesh, only sized) and polygonised by naive surface nets
   (one vertex per cell the surface crosses, one quad per grid edge it
   crosses, split along its shorter diagonal), after cells whose corners would
   make the surface non-manifold are resolved. Vertices are then relaxed
   (umbrella smoothing) and projected back onto the implicit surface (Newton
   steps): one closed, consistently outward-facing, 2-manifold genus-0 triangle
   mesh of about 11,500 vertices and 23,000 triangles.
3. *Weights*: every skinned bone has a "weight capsule", a round cone along
   its segment with the body's radius there; a vertex's weight for bone ``b``
   is a soft-min of the capsules' signed distances,
   ``exp(-(d_b - min_b d_b) / tau)``, kept for the 4 largest (minus the 5th,
   so weights stay continuous where the ranking changes), normalised and
   rounded to multiples of 1/1024 (rows still sum to exactly 1). Joints
   blend over a few centimetres; the skull is nearly rigid on ``head``. The
   hip joint and finger tip bones carry no weight (the pelvis moves with
   ``root``, the finger tips with ``hand``), nor does the thumb (the mitten's
   thumb moves with the palm, ``wrist``).

Deterministic; about 0.5 s per body on one core (cached per skeleton).

:func:`lbs` poses it with the per-bone rigid transforms of
:func:`dancing_points_addon.ik.bone_transforms`.

The modules: :mod:`.sdf` the distance field's primitives, :mod:`.proportions`
the mannequin's parts and weight capsules, :mod:`.mesher` the surface nets,
:mod:`.weights` the skin weights, :mod:`.mannequin` the body (:func:`make_body`),
:mod:`.lbs` the skinning.
"""
from .lbs import lbs, lbs_frame
from .mannequin import Body, make_body
from .proportions import BodyError, weight_capsules
from .weights import bone_segment_distances

__all__ = ["Body", "make_body", "lbs", "lbs_frame", "bone_segment_distances", "BodyError",
           "weight_capsules"]
