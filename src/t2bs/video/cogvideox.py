"""Real image-to-video backend (paper §3.1.1): diffusers ``CogVideoXImageToVideoPipeline``.

Loads a local checkpoint folder (the diffusers layout of THUDM/CogVideoX-5b-I2V: model_index.json,
transformer/, vae/, text_encoder/, tokenizer/, scheduler/) and turns the frontal render plus the
expression prompt into the fixed-view video. This is the fixed-view video only: the multi-view
grid then comes from a 4D video model's output, imported with ``t2bs.video.grid.import_image_grid``.

The paper renders 512 x 512 and crops "as required by video models": the square render is
letterboxed (white, the render background) into the model's frame (480 x 720 for CogVideoX), and
the generated frames are cropped back to the square and resized to the render size, so the
result lines up pixel for pixel with the frontal camera.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t2bs.errors import MissingCheckpointError, UserError
from t2bs.geometry.camera import Camera
from t2bs.video.grid import VideoGrid

HF_REPO = "THUDM/CogVideoX-5b-I2V"
REQUIRED = ("model_index.json", "transformer", "vae", "text_encoder", "tokenizer", "scheduler")


@dataclass
class CogVideoXConfig:
    frames: int = 49  # frames to generate (CogVideoX-5b-I2V: 49 = 6 s at 8 fps; 4k + 1)
    steps: int = 50  # denoising steps
    guidance: float = 6.0  # classifier-free guidance scale
    height: int = 480  # model frame height (the checkpoint's training resolution)
    width: int = 720  # model frame width
    fps: float = 8.0  # time stamps of the frames
    max_sequence_length: int = 226  # T5 tokens (CogVideoX default)
    negative_prompt: str = ""  # optional negative prompt


def check_checkpoint(path: str | os.PathLike) -> Path:
    """The checkpoint folder, or MissingCheckpointError saying what to download and where."""
    path = Path(path)
    how = (
        f"download {HF_REPO} on a machine with internet access "
        f"(`huggingface-cli download {HF_REPO} --local-dir {path}`) and pass --checkpoint {path}"
    )
    if not path.is_dir():
        raise MissingCheckpointError(f"CogVideoX image-to-video checkpoint ({HF_REPO})", str(path), how)
    missing = [m for m in REQUIRED if not (path / m).exists()]
    if missing:
        raise MissingCheckpointError(f"CogVideoX checkpoint parts {', '.join(missing)} ({HF_REPO})", str(path), how)
    return path


def load_pipeline(checkpoint: str | os.PathLike, device: str | None = None, dtype=None):
    """A ready ``CogVideoXImageToVideoPipeline`` from a local folder (never downloads)."""
    path = check_checkpoint(checkpoint)
    try:
        import torch
        from diffusers import CogVideoXImageToVideoPipeline
    except ImportError as exc:
        raise UserError(
            f"the CogVideoX backend needs diffusers and transformers ({exc}); "
            "install them with `pip install -e .[diffusers]`"
        ) from None
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    if dtype is None:
        dtype = torch.bfloat16 if device.startswith("cuda") else torch.float32
    import warnings

    with warnings.catch_warnings():
        # Newer diffusers renamed torch_dtype to dtype; the old name works in every supported version.
        warnings.simplefilter("ignore", FutureWarning)
        pipe = CogVideoXImageToVideoPipeline.from_pretrained(str(path), torch_dtype=dtype, local_files_only=True)
    pipe.to(device)
    if device.startswith("cuda"):
        # The 5B model's VAE decode of 49 frames needs tiling/slicing to fit in ~24 GB.
        pipe.vae.enable_tiling()
        pipe.vae.enable_slicing()
    pipe.set_progress_bar_config(disable=True)
    return pipe


def letterbox(image: np.ndarray, height: int, width: int) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Square [S, S, 3] uint8 -> [height, width, 3] on white, scaled to fit; returns (image, (x0, y0, side))."""
    from PIL import Image

    side = min(height, width)
    img = np.asarray(Image.fromarray(image).resize((side, side), Image.BICUBIC))
    out = np.full((height, width, 3), 255, np.uint8)
    y0, x0 = (height - side) // 2, (width - side) // 2
    out[y0 : y0 + side, x0 : x0 + side] = img
    return out, (x0, y0, side)


def generate_fixed_view(
    pipe, image: np.ndarray, prompt: str, config: CogVideoXConfig = CogVideoXConfig(), seed: int = 0
) -> np.ndarray:
    """Frontal render [S, S, 3] uint8 + prompt -> fixed-view video [T, S, S, 3] uint8."""
    import torch
    from PIL import Image

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] != image.shape[1] or image.dtype != np.uint8:
        raise UserError(f"the frontal render must be a square uint8 RGB image, got {image.dtype} {image.shape}")
    size = image.shape[0]
    boxed, (x0, y0, side) = letterbox(image, config.height, config.width)
    generator = torch.Generator(device="cpu").manual_seed(int(seed))
    out = pipe(
        image=Image.fromarray(boxed),
        prompt=prompt,
        negative_prompt=config.negative_prompt or None,
        height=config.height,
        width=config.width,
        num_frames=config.frames,
        num_inference_steps=config.steps,
        guidance_scale=config.guidance,
        max_sequence_length=config.max_sequence_length,
        generator=generator,
        output_type="np",
    ).frames[0]  # [T, H, W, 3] float in [0, 1]
    video = (np.clip(np.asarray(out, np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    crop = video[:, y0 : y0 + side, x0 : x0 + side]
    if side != size:
        crop = np.stack([np.asarray(Image.fromarray(f).resize((size, size), Image.BICUBIC)) for f in crop])
    return crop


def fixed_view_grid(video: np.ndarray, camera: Camera, fps: float, meta: dict | None = None) -> VideoGrid:
    """A one-view VideoGrid (the fixed-view video) for the project's videos/ folder."""
    video = np.asarray(video, np.uint8)  # [T, H, W, 3]
    if (camera.width, camera.height) != (video.shape[2], video.shape[1]):
        camera = camera.resized(video.shape[2], video.shape[1])
    times = (np.arange(video.shape[0]) / fps).astype(np.float32)
    return VideoGrid(video[None], [camera], times, 0, None, None, "cogvideox", {"fps": fps, **(meta or {})}).validate(
        "cogvideox video"
    )
