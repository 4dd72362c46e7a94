"""CogVideoX image-to-video backend: a tiny random-weight pipeline saved and loaded from disk."""

from __future__ import annotations

import numpy as np
import pytest

from t2bs.errors import MissingCheckpointError
from t2bs.geometry.camera import frontal_camera
from t2bs.video.cogvideox import CogVideoXConfig, check_checkpoint, fixed_view_grid, letterbox


def test_missing_checkpoint_names_the_model(tmp_path):
    with pytest.raises(MissingCheckpointError, match="THUDM/CogVideoX-5b-I2V") as err:
        check_checkpoint(tmp_path / "nope")
    assert str(tmp_path / "nope") in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "model_index.json").write_text("{}")
    with pytest.raises(MissingCheckpointError, match="transformer, vae, text_encoder"):
        check_checkpoint(tmp_path / "half")


def test_letterbox_keeps_the_square_in_the_middle():
    img = np.zeros((32, 32, 3), np.uint8)
    out, (x0, y0, side) = letterbox(img, 48, 72)
    assert out.shape == (48, 72, 3) and (x0, y0, side) == (12, 0, 48)
    assert out[:, :12].min() == 255 and out[:, 12:60].max() == 0


def _tiny_checkpoint(folder):
    """Save a random-weight CogVideoX I2V pipeline (configs as in diffusers' own fast tests)."""
    import torch
    from diffusers import (
        AutoencoderKLCogVideoX,
        CogVideoXImageToVideoPipeline,
        CogVideoXTransformer3DModel,
        DDIMScheduler,
    )
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, T5Config, T5EncoderModel

    torch.manual_seed(0)
    transformer = CogVideoXTransformer3DModel(
        num_attention_heads=2,
        attention_head_dim=16,
        in_channels=8,
        out_channels=4,
        time_embed_dim=2,
        text_embed_dim=32,
        num_layers=1,
        sample_width=2,
        sample_height=2,
        sample_frames=9,
        patch_size=2,
        temporal_compression_ratio=4,
        max_text_seq_length=16,
        use_rotary_positional_embeddings=True,
        use_learned_positional_embeddings=True,
    )
    vae = AutoencoderKLCogVideoX(
        in_channels=3,
        out_channels=3,
        down_block_types=("CogVideoXDownBlock3D",) * 4,
        up_block_types=("CogVideoXUpBlock3D",) * 4,
        block_out_channels=(8, 8, 8, 8),
        latent_channels=4,
        layers_per_block=1,
        norm_num_groups=2,
        temporal_compression_ratio=4,
    )
    text_encoder = T5EncoderModel(T5Config(vocab_size=64, d_model=32, d_kv=8, d_ff=37, num_layers=2, num_heads=4))
    # A word-level tokenizer built here: the real T5 tokenizer would need a download.
    vocab = {"<pad>": 0, "</s>": 1, "<unk>": 2}
    for w in "a turtle blinking static camera the is holding still ,".split():
        vocab.setdefault(w, len(vocab))
    tk = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tk.pre_tokenizer = pre_tokenizers.Whitespace()
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=tk, pad_token="<pad>", eos_token="</s>", unk_token="<unk>")
    pipe = CogVideoXImageToVideoPipeline(
        tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, transformer=transformer, scheduler=DDIMScheduler()
    )
    pipe.save_pretrained(folder)
    return folder


@pytest.mark.slow
def test_tiny_pipeline_makes_a_fixed_view_video(tmp_path):
    pytest.importorskip("diffusers")
    from t2bs.video.cogvideox import generate_fixed_view, load_pipeline
    from t2bs.video.grid import load_grid, save_grid

    ckpt = _tiny_checkpoint(tmp_path / "cog")
    pipe = load_pipeline(ckpt, device="cpu")
    cfg = CogVideoXConfig(frames=9, steps=2, height=16, width=16, max_sequence_length=16)
    image = np.full((32, 32, 3), 180, np.uint8)
    video = generate_fixed_view(
        pipe, image, "a turtle, blinking, static camera, the camera is holding still", cfg, seed=0
    )
    again = generate_fixed_view(
        pipe, image, "a turtle, blinking, static camera, the camera is holding still", cfg, seed=0
    )
    assert video.shape == (9, 32, 32, 3) and video.dtype == np.uint8
    assert np.array_equal(video, again)  # seeded
    grid = fixed_view_grid(video, frontal_camera(512), cfg.fps, {"expression": "blinking"})
    save_grid(grid, tmp_path / "v")
    loaded = load_grid(tmp_path / "v")
    assert loaded.num_views == 1 and loaded.backend == "cogvideox" and loaded.cameras[0].width == 32
