"""Grounding-DINO + SAM (paper §3.3) via transformers, from local checkpoints only.

Grounding-DINO turns the text prompts ("left eye", "right eye", "mouth") into boxes on the
frontal render; SAM turns each box into a mask. Weights are never downloaded: put
IDEA-Research/grounding-dino-tiny and facebook/sam-vit-base (any compatible pair) in
``$T2BS_CHECKPOINTS/grounding-dino`` and ``$T2BS_CHECKPOINTS/sam`` (default ~/.cache/t2bs/checkpoints),
or pass the folders.

Which eye is which: the prompts are spatially ambiguous for a detector, so the two best "eye"
boxes are sorted by x: the image-left one is the character's right eye (68-scheme 36-41).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from t2bs.errors import MissingCheckpointError, UserError

DEFAULT_ROOT = Path(os.environ.get("T2BS_CHECKPOINTS", Path.home() / ".cache" / "t2bs" / "checkpoints"))
DINO_ID, SAM_ID = "IDEA-Research/grounding-dino-tiny", "facebook/sam-vit-base"


class GroundingSamSegmenter:
    """Callable: frontal render [H, W, 3] uint8 -> {"right_eye", "left_eye", "mouth"} masks [H, W] bool."""

    def __init__(self, dino_model, dino_processor, sam_model, sam_processor, box_threshold: float = 0.2):
        self.dino, self.dino_proc = dino_model.eval(), dino_processor
        self.sam, self.sam_proc = sam_model.eval(), sam_processor
        self.box_threshold = box_threshold

    @staticmethod
    def from_pretrained(
        dino_dir: str | os.PathLike | None = None, sam_dir: str | os.PathLike | None = None
    ) -> "GroundingSamSegmenter":
        dino_dir = Path(dino_dir or DEFAULT_ROOT / "grounding-dino")
        sam_dir = Path(sam_dir or DEFAULT_ROOT / "sam")
        for what, where, hub in (("Grounding-DINO weights", dino_dir, DINO_ID), ("SAM weights", sam_dir, SAM_ID)):
            if not (where / "config.json").exists():
                raise MissingCheckpointError(
                    what,
                    str(where),
                    f"download {hub} (e.g. `huggingface-cli download {hub} --local-dir {where}`) "
                    "on a machine with internet and copy it there, or set T2BS_CHECKPOINTS",
                )
        try:
            from transformers import AutoModelForZeroShotObjectDetection, AutoProcessor, SamModel, SamProcessor
        except ImportError:
            raise UserError("the grounding-sam backend needs transformers: pip install -e '.[diffusers]'") from None
        dino = AutoModelForZeroShotObjectDetection.from_pretrained(dino_dir, local_files_only=True)
        dproc = AutoProcessor.from_pretrained(dino_dir, local_files_only=True)
        sam = SamModel.from_pretrained(sam_dir, local_files_only=True)
        sproc = SamProcessor.from_pretrained(sam_dir, local_files_only=True)
        return GroundingSamSegmenter(dino, dproc, sam, sproc)

    def boxes(self, image: np.ndarray) -> dict[str, np.ndarray]:
        """Best box [4] (x0, y0, x1, y1 pixels) per region; eyes split by x (see module docstring)."""
        import torch
        from PIL import Image

        pil = Image.fromarray(image)
        h, w = image.shape[:2]
        out: dict[str, np.ndarray] = {}
        with torch.no_grad():
            for label in ("eye", "mouth"):
                inputs = self.dino_proc(images=pil, text=f"{label}.", return_tensors="pt")
                res = self.dino(**inputs)
                det = self.dino_proc.post_process_grounded_object_detection(
                    res, inputs["input_ids"], threshold=0.0, text_threshold=0.0, target_sizes=[(h, w)]
                )[0]
                scores, boxes = det["scores"].numpy(), det["boxes"].numpy()
                order = np.argsort(-scores)
                boxes = np.clip(boxes[order], 0, [w - 1, h - 1, w - 1, h - 1])
                if label == "mouth":
                    if len(boxes):
                        out["mouth"] = boxes[0]
                    continue
                picked = []
                for b in boxes:  # two best eye boxes that do not overlap much
                    if all(_iou(b, p) < 0.3 for p in picked):
                        picked.append(b)
                    if len(picked) == 2:
                        break
                picked.sort(key=lambda b: b[0] + b[2])
                if len(picked) == 2:
                    out["right_eye"], out["left_eye"] = picked
        return out

    def __call__(self, image: np.ndarray) -> dict[str, np.ndarray]:
        import torch
        from PIL import Image

        h, w = image.shape[:2]
        boxes = self.boxes(image)
        masks = {k: np.zeros((h, w), bool) for k in ("right_eye", "left_eye", "mouth")}
        if not boxes:
            return masks
        names = list(boxes)
        inputs = self.sam_proc(
            Image.fromarray(image), input_boxes=[[boxes[n].tolist() for n in names]], return_tensors="pt"
        )
        with torch.no_grad():
            res = self.sam(**inputs, multimask_output=False)
        post = self.sam_proc.post_process_masks(
            res.pred_masks, inputs["original_sizes"], inputs["reshaped_input_sizes"]
        )[0]
        for i, n in enumerate(names):
            m = post[i, 0].numpy().astype(bool)
            x0, y0, x1, y1 = np.round(boxes[n]).astype(int)
            m[:, :] &= _box_mask((h, w), x0, y0, x1, y1)  # keep SAM inside its prompt box
            masks[n] = m
        return masks


def _box_mask(shape, x0, y0, x1, y1) -> np.ndarray:
    m = np.zeros(shape, bool)
    m[max(y0, 0) : y1 + 1, max(x0, 0) : x1 + 1] = True
    return m


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0
