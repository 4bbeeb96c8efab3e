"""File formats: the SPEC §3 take (``take``), BVH (``bvh_parse`` reads the text,
``bvh`` the kinematics, tracked points and writer), CMU ASF/AMC (``asf_amc``),
meshopt-compressed glTF (``gltf_meshopt``), bone naming (``naming``) and
atomic output files (``files``)."""
