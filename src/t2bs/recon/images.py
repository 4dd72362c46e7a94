"""Image stacks at the training resolution (shared by the training data and the previews)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def resize_stack(x: np.ndarray, size: tuple[int, int]) -> torch.Tensor:
    """[..., H, W, C] uint8/float -> float tensor [..., h, w, C] (area filter), size = (w, h)."""
    t = torch.as_tensor(np.ascontiguousarray(x))
    lead = t.shape[:-3]
    t = t.reshape(-1, *t.shape[-3:]).permute(0, 3, 1, 2).float()
    if t.shape[-2:] != (size[1], size[0]):
        t = F.interpolate(t, size=(size[1], size[0]), mode="area")
    if x.dtype == np.uint8:
        t = t / 255.0
    return t.permute(0, 2, 3, 1).reshape(*lead, size[1], size[0], -1).contiguous()
