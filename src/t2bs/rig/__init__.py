"""Automatic face rig for static head meshes (issue 34): landmarks -> ARKit-named morph targets.

- ``face``: where the face is (20 landmarks in the 68-point order, optional named points, eyeballs).
- ``autorig``: deformers that behave like a face (jaw hinge, lids over the eyeball, geodesic
  falloff) written as ARKit morph targets.
- ``stage``: ``t2bs autorig MESH -o OUT.glb`` as a function, and the auto rig of a project's character.
"""
