"""Blendshape model (paper §3.3): uncentred PCA of captured meshes, fitting, named shapes, glTF/USD export.

- ``model``: ``BlendshapeModel`` (neutral + orthonormal basis), ``build_model``, ``save_model`` / ``load_model``.
- ``fit``: closed-form geometric fit and the L_geo + 0.1 L_rgb refinement (differentiable vertex splats).
- ``semantic``: one named shape per expression prompt (jaw_open, blink, smile, tongue_out, ...).
- ``export``: model.glb (morph targets + animation), model.usdc (UsdSkel blend shapes); ``vrm``: VRM 1.0.
- ``commands``: ``t2bs blendshapes DIR`` and ``t2bs bench blendshapes``.
"""
