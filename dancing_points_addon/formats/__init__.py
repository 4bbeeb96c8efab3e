"""File formats: the SPEC §3 take (``take``), any input as a take and the rules
every take meets (``inputs``), the bounds on inputs (``limits``), BVH
(``bvh_parse`` reads the text, ``bvh`` the kinematics, tracked points and
writer), CMU ASF/AMC (``asf_amc``), meshopt-compressed glTF (``gltf_meshopt``),
bone naming (``naming``), length units (``units``) and files (``files``: safe
reading and atomic writing)."""
