"""t2bs: text (or any character mesh) to an animatable blendshape rig (T2Bs, ICCV 2025)."""

__version__ = "0.1.0"
