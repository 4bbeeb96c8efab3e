"""File formats: the SPEC §3 take (``take``), the bounds on inputs (``limits``), BVH
(``bvh_parse`` reads the text, ``bvh`` the kinematics, tracked points and
writer), CMU ASF/AMC (``asf_amc``), meshopt-compressed glTF (``gltf_meshopt``),
bone naming (``naming``), length units (``units``) and files (``files``: safe
reading and atomic writing). Any input as a take, with the rules every take
meets, is :mod:`..inputs` (it resamples and calibrates: above this layer).
This package imports only itself, the errors and the body's maths
(``rotations``, ``skeleton``) and the song's checks (``audio``)."""
