"""Dancing Points' core: everything that is not Blender.

Layers (each may import the ones above it, never the ones below):

1. **core** — this package: motion maths, file formats, features, the ONNX
   networks, the frame-by-frame synthesis, IK, skinning, retargeting maths and
   the batch scheduler, in numpy and onnxruntime. It never imports ``bpy``
   (``tests/test_layers.py`` imports every module with ``bpy`` made
   unimportable) and never imports a Blender-side module; the one link the
   other way is a path: the batch starts ``operators/batch_worker.py`` as a
   worker program when a take needs Blender. It is also the command line:
   ``python -m dancing_points_addon``.
2. **Blender side** — ``operators/``, ``panels/``, ``preferences.py`` at the
   extension's root: thin translation between Blender data and the core.
3. **training and tools** — ``training/`` (PyTorch; datasets, metrics,
   evaluation) and ``tools/`` (building the extension); they may import the core
   and are not part of the extension's zip.

The synthesis path is flat: ``rotations`` → ``skeleton`` → ``representation``
→ ``features`` → ``pose`` / ``ik`` → ``follower`` → ``nets`` → ``runtime``.
The parts with several modules are packages: ``formats/`` (take, BVH, ASF/AMC,
glTF meshopt, bone naming), ``retarget/`` and ``batch/``.
"""
