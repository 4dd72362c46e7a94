"""Smooth scalar ramps shared by the procedural characters, the auto rig's weights and the animator's curves.

numpy in, numpy (float64) out.
"""

from __future__ import annotations

import numpy as np


def smoothstep(edge0, edge1, x) -> np.ndarray:
    """Hermite ramp of ``x`` (any shape): 0 at ``edge0``, 1 at ``edge1``, flat at both (no crease where it starts or
    stops); ``edge0 > edge1`` gives the falling ramp."""
    t = np.clip((np.asarray(x, np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3 - 2 * t)
