"""SV4D 2.0 backend: checkpoint layout, loading errors and sampling of a tiny random-weight model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from t2bs.errors import MissingCheckpointError, UserError

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("kornia")

from t2bs.video import sv4d2  # noqa: E402


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    return sv4d2.write_tiny_checkpoint(tmp_path_factory.mktemp("sv4d2"), seed=0)


def test_missing_checkpoint_names_file_folder_and_licence(tmp_path):
    with pytest.raises(MissingCheckpointError) as err:
        sv4d2.check_checkpoint(tmp_path / "nope")
    msg = str(err.value)
    assert "sv4d2.safetensors" in msg and str(tmp_path / "nope") in msg and "stabilityai/sv4d2.0" in msg
    assert "Community License" in msg and "\n" not in msg
    (tmp_path / "empty").mkdir()
    with pytest.raises(MissingCheckpointError, match="sv4d2.safetensors"):
        sv4d2.check_checkpoint(tmp_path / "empty")


def test_checkpoint_has_the_published_layout_and_loads_back(tiny_ckpt):
    from safetensors.torch import load_file

    sd = load_file(str(tiny_ckpt / sv4d2.CHECKPOINT_FILE))
    # The authors' DiffusionEngine names (see benchmarks/sv4d2_equivalence.py for the reference itself).
    for key in ("model.diffusion_model.input_blocks.0.0.weight", "model.diffusion_model.input_blocks.1.0.in_layers.0.weight",
                "model.diffusion_model.input_blocks.1.0.time_mix_blocks.in_layers.2.weight",
                "model.diffusion_model.input_blocks.1.1.time_mix_blocks.0.ff_in.net.0.proj.weight",
                "model.diffusion_model.input_blocks.1.1.motion_blocks.0.attn2.to_k.weight",
                "model.diffusion_model.input_blocks.1.1.time_mix_time_embed.0.weight",
                "model.diffusion_model.input_blocks.2.0.op.weight", "model.diffusion_model.label_emb.0.0.weight",
                "conditioner.embedders.0.open_clip.model.visual.transformer.resblocks.0.attn.in_proj_weight",
                "conditioner.embedders.1.encoder.encoder.down.0.block.0.conv1.weight",
                "conditioner.embedders.4.encoder.quant_conv.weight", "first_stage_model.decoder.mid.attn_1.q.weight"):
        assert key in sd, key
    assert sd["first_stage_model.decoder.mid.attn_1.q.weight"].ndim == 4  # LDM 1x1 conv, not linear
    model = sv4d2.load_model(tiny_ckpt, device="cpu", dtype="float32")
    again = sv4d2.published_state_dict(model)
    assert again.keys() == sd.keys()
    assert all(torch.equal(again[k], sd[k]) for k in sd)
    assert model.view_vae is None  # identical view encoder: shared


def test_a_wrong_or_broken_file_is_one_error(tiny_ckpt, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / sv4d2.CHECKPOINT_FILE).write_bytes((tiny_ckpt / sv4d2.CHECKPOINT_FILE).read_bytes())
    cfg = json.loads((tiny_ckpt / sv4d2.CONFIG_FILE).read_text())
    (bad / sv4d2.CONFIG_FILE).write_text(json.dumps({**cfg, "model_channels": 64, "sigma_embed_dim": 64, "camera_embed_dim": 96}))
    with pytest.raises(UserError, match="UNet weights do not fit") as err:
        sv4d2.load_model(bad, device="cpu")
    assert "\n" not in str(err.value)
    (bad / sv4d2.CHECKPOINT_FILE).write_bytes(b"not a safetensors file")
    with pytest.raises(UserError, match="not a readable safetensors file"):
        sv4d2.load_model(bad, device="cpu")
    from safetensors.torch import save_file

    save_file({"model.diffusion_model.x": torch.zeros(1)}, str(bad / sv4d2.CHECKPOINT_FILE))
    with pytest.raises(UserError, match="no CLIP image encoder, VAE encoder"):
        sv4d2.load_model(bad, device="cpu")


def test_one_pass_is_seeded_and_uses_every_condition(tiny_ckpt):
    model = sv4d2.load_model(tiny_ckpt, device="cpu", dtype="float32")
    cfg = model.cfg
    T, V, H = cfg.frames, cfg.views, cfg.image_size
    g = torch.Generator().manual_seed(0)
    motion = torch.rand(T, 3, H, H, generator=g) * 2 - 1
    views = torch.rand(V, 3, H, H, generator=g) * 2 - 1
    polar, azim = np.full(T * V, np.pi / 2), np.tile([0.3, 5.9], T)
    noise = torch.randn(T * V, 4, H // cfg.vae_factor, H // cfg.vae_factor, generator=g)
    steps = sv4d2.SV4D2SamplerConfig(steps=3)
    c, uc = model.conditioning(motion, views, polar, azim)
    assert c["crossattn"].shape == (1, T, cfg.context_dim) and c["vector"].shape == (T * V, cfg.adm_channels)
    assert c["concat"].shape == (T * V, 4, 8, 8) and c["cond_view"].shape == (V, 4, 8, 8)
    # The unconditional branch zeroes every image input but keeps the cameras.
    assert float(uc["concat"].abs().max()) == 0 and float(uc["crossattn"].abs().max()) == 0
    assert torch.equal(uc["vector"][:, cfg.sigma_embed_dim:], c["vector"][:, cfg.sigma_embed_dim:])
    z = model.sample(c, uc, noise, steps)
    assert torch.equal(z, model.sample(c, uc, noise, steps))
    c0, uc0 = model.conditioning(motion, None, polar, azim)
    assert float(c0["cond_view"].abs().max()) == 0
    c2, uc2 = model.conditioning(motion, views, polar, np.tile([1.0, 2.0], T))
    for other in (model.sample(c0, uc0, noise, steps), model.sample(c2, uc2, noise, steps)):
        assert float((other - z).abs().max()) > 1e-3  # the view images and the cameras both matter
    images = model.decode_latents(z)
    assert images.shape == (T * V, 3, H, H) and float(images.min()) >= 0 and float(images.max()) <= 1
    with pytest.raises(UserError, match=f"makes {T} frames per pass"):
        model.conditioning(motion[:1], views, polar, azim)
