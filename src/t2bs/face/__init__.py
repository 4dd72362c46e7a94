"""Faces, below the stages: landmarks on a character's render, human face tracking, motion transfer, the
blendshape-weight solve, ARKit-52 shapes and Live Link Face CSVs (paper §3.3). Used by the auto rig, the
blendshapes stage (ARKit names) and the retarget stage; imports no stage."""
