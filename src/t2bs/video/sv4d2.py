"""SV4D 2.0 (Stability AI, 2025): the 4D video model that turns the fixed-view video into novel views.

Our own implementation of the published network, conditioner, VAE use and sampler, written on
diffusers' building blocks (``SpatioTemporalResBlock``, ``BasicTransformerBlock``,
``TemporalBasicTransformerBlock``, ``AlphaBlender``, ``AutoencoderKL``) and transformers'
``CLIPVisionModelWithProjection``. It loads the published single-file checkpoint
``sv4d2.safetensors`` (model hub ``stabilityai/sv4d2.0``, Stability AI Community License) by
renaming its keys; ``benchmarks/sv4d2_equivalence.py`` proves the port equal to the authors'
code (Stability-AI/generative-models) on a small random-weight configuration.

One pass of the model makes ``views`` (4) novel views x ``frames`` (12) frames, ordered
time-major ([T, V] flattened), from
  - the input video's T frames at the input view ("cond_motion": CLIP embeddings as the
    cross-attention context, VAE latents concatenated to the noisy latents),
  - the V novel views' images at the pass's first frame ("cond_view", VAE latents attended to
    by the motion attention; zeroed when no such images exist yet),
  - the V cameras relative to the input view (polar and azimuth, sinusoidal embeddings added
    to the time embedding).
Sampling is the authors' default for sv4d2 (scripts/sampling/simple_video_sample_4d2.py):
Euler EDM, 50 steps, sigma 700 -> 0.002 (rho 7), v-prediction scaling with EDM c_noise,
classifier-free guidance rising linearly from 1 to 2 over the T*V outputs, the unconditional
branch with every image input zeroed.

Tensor layout: frames and latents are [N, C, H, W] with N = B * T * V (time-major, views
inner); images in [-1, 1] unless said otherwise.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from t2bs.errors import MissingCheckpointError, UserError

HF_REPO = "stabilityai/sv4d2.0"
CHECKPOINT_FILE = "sv4d2.safetensors"
CONFIG_FILE = "sv4d2_config.json"  # optional: a non-published model shape (the tests' tiny model)
LICENCE = (
    "Stability AI Community License (accept it on the model page of stabilityai/sv4d2.0 before "
    "downloading; free for research and for organisations under USD 1M annual revenue, others need "
    "an enterprise licence from Stability AI)"
)

# Prefixes of the published single-file checkpoint (the authors' DiffusionEngine state dict).
UNET_PREFIX = "model.diffusion_model."
CLIP_PREFIX = "conditioner.embedders.0.open_clip.model.visual."
FRAMES_VAE_PREFIX = "conditioner.embedders.1.encoder."  # encodes the input video (concat input)
VIEW_VAE_PREFIX = "conditioner.embedders.4.encoder."  # encodes the views at the pass's first frame
DECODER_PREFIX = "first_stage_model.decoder."


@dataclass
class SV4D2Config:
    """Shape of the network and its encoders; the defaults are the published sv4d2 model."""

    frames: int = 12  # frames per pass (T)
    views: int = 4  # novel views per pass (V)
    in_channels: int = 8  # noisy latents (4) + input-video latents (4)
    out_channels: int = 4  # latent channels predicted
    model_channels: int = 320  # UNet width at full latent resolution
    channel_mult: tuple = (1, 2, 4, 4)  # width multipliers per resolution level
    num_res_blocks: int = 2  # residual blocks per level
    attention_resolutions: tuple = (4, 2, 1)  # downsampling factors that get attention blocks
    num_head_channels: int = 64  # channels per attention head
    transformer_depth: int = 1  # transformer blocks per attention block
    context_dim: int = 1024  # CLIP image embedding width (cross-attention context)
    motion_context_dim: int = 4  # view-latent channels attended to by the motion attention
    sigma_embed_dim: int = 256  # sinusoidal width of the (zero) conditioning-noise level
    camera_embed_dim: int = 512  # sinusoidal width of each of polar and azimuth
    clip_width: int = 1280  # OpenCLIP ViT-H/14 visual tower
    clip_layers: int = 32
    clip_heads: int = 16
    clip_patch: int = 14
    clip_image_size: int = 224
    vae_channels: tuple = (128, 256, 512, 512)  # SD/SVD image VAE
    vae_layers_per_block: int = 2
    latent_channels: int = 4
    scale_factor: float = 0.18215  # latent scaling of the diffusion model's outputs
    image_size: int = 576  # training resolution (pixels, square)

    @property
    def adm_channels(self) -> int:
        """Width of the vector conditioning: noise level + polar + azimuth embeddings."""
        return self.sigma_embed_dim + 2 * self.camera_embed_dim

    @property
    def vae_factor(self) -> int:
        return 2 ** (len(self.vae_channels) - 1)

    def check(self) -> "SV4D2Config":
        if self.adm_channels != 4 * self.model_channels:
            # The camera attention embeds the UNet's time embedding (width 4 * model_channels) with
            # a layer sized for the vector conditioning: the published model relies on both being 1280.
            raise UserError(
                f"SV4D 2.0 config: sigma_embed_dim + 2 * camera_embed_dim ({self.adm_channels}) must equal "
                f"4 * model_channels ({4 * self.model_channels})"
            )
        return self

    @classmethod
    def from_dict(cls, data: dict) -> "SV4D2Config":
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise UserError(f"{CONFIG_FILE}: unknown fields {', '.join(unknown)}")
        data = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**data).check()


def tiny_config(**overrides) -> SV4D2Config:
    """A few-kilobyte model of the same architecture, for tests and the equivalence check."""
    base = dict(
        frames=3,
        views=2,
        model_channels=32,
        channel_mult=(1, 2),
        num_res_blocks=1,
        attention_resolutions=(1, 2),
        num_head_channels=16,
        context_dim=32,
        sigma_embed_dim=32,
        camera_embed_dim=48,
        clip_width=32,
        clip_layers=2,
        clip_heads=2,
        clip_patch=32,
        clip_image_size=224,
        vae_channels=(32, 32),
        vae_layers_per_block=1,
        image_size=16,
    )
    base.update(overrides)
    return SV4D2Config(**base).check()


@dataclass
class SV4D2SamplerConfig:
    """The authors' default sampler for sv4d2 (simple_video_sample_4d2.py)."""

    steps: int = 50  # Euler EDM steps
    sigma_max: float = 700.0  # first noise level
    sigma_min: float = 0.002  # last noise level before 0
    rho: float = 7.0  # EDM schedule curvature
    cfg_min: float = 1.0  # guidance scale of the first (time, view) output
    cfg_max: float = 2.0  # guidance scale of the last (time, view) output (linear in between)


# ---------------------------------------------------------------------------------------------
# Network


def _torch():
    try:
        import torch  # noqa: F401
        from diffusers.models.attention import BasicTransformerBlock  # noqa: F401
        from transformers import CLIPVisionConfig  # noqa: F401
    except ImportError as exc:
        raise UserError(
            f"the SV4D 2.0 backend needs diffusers and transformers ({exc}); "
            "install them with `pip install -e .[diffusers]`"
        ) from None
    import torch

    return torch


def build_model(config: SV4D2Config):
    """An SV4D2Model with freshly initialised weights (load a checkpoint into it)."""
    _torch()
    return _model_class()(config.check())


_CACHE: dict = {}


def _model_class():
    """The torch module classes, defined on first use so that importing t2bs needs no torch."""
    if "model" in _CACHE:
        return _CACHE["model"]
    import torch
    import torch.nn.functional as F
    from diffusers.models.attention import BasicTransformerBlock, TemporalBasicTransformerBlock
    from diffusers.models.embeddings import TimestepEmbedding, Timesteps
    from diffusers.models.resnet import AlphaBlender, Downsample2D, SpatioTemporalResBlock, Upsample2D
    from torch import nn

    class MotionTransformer(nn.Module):
        """Spatial attention, then 'camera' attention and motion (time) attention across the pass.

        Written to reproduce the published network's tensor layout exactly (its weights were
        trained with it): with 3D attention on, the camera attention runs over groups of
        ``views`` consecutive tokens of the (view, pixel) order, the motion attention over the
        ``frames`` of each (view, pixel), whose cross-attention reads the view latents.
        """

        def __init__(self, ch: int, heads: int, dim_head: int, cfg: SV4D2Config):
            super().__init__()
            inner = heads * dim_head
            depth = cfg.transformer_depth
            temb = 4 * cfg.model_channels
            self.norm = nn.GroupNorm(32, ch, eps=1e-6)
            self.proj_in = nn.Linear(ch, inner)
            self.transformer_blocks = nn.ModuleList(
                [
                    BasicTransformerBlock(
                        inner, heads, dim_head, cross_attention_dim=cfg.context_dim, activation_fn="geglu"
                    )
                    for _ in range(depth)
                ]
            )
            self.time_mix_blocks = nn.ModuleList(  # camera attention
                [
                    TemporalBasicTransformerBlock(inner, inner, heads, dim_head, cross_attention_dim=cfg.context_dim)
                    for _ in range(depth)
                ]
            )
            self.motion_blocks = nn.ModuleList(
                [
                    TemporalBasicTransformerBlock(
                        inner, inner, heads, dim_head, cross_attention_dim=cfg.motion_context_dim
                    )
                    for _ in range(depth)
                ]
            )
            self.time_mix_time_embed = TimestepEmbedding(temb, 4 * ch, out_dim=ch)  # camera (view) embedding
            self.time_mix_motion_embed = TimestepEmbedding(ch, 4 * ch, out_dim=ch)  # frame-index embedding
            self.frame_proj = Timesteps(ch, flip_sin_to_cos=True, downscale_freq_shift=0)
            self.time_mixer = AlphaBlender(0.0, "learned_with_images")
            self.time_mixer_motion = AlphaBlender(0.5, "learned_with_images")
            self.proj_out = nn.Linear(inner, ch)

        def forward(self, x, emb, context, cond_view):
            # x [B*T*V, C, H, W]; emb [B*T*V, 4*model_channels]; context [B, T, D]; cond_view [B*V, 4, h, w]
            b, t, d1 = context.shape
            v = cond_view.shape[0] // b
            n, c, h, w = x.shape
            hw = h * w
            x_in = x
            cond_view = F.interpolate(cond_view, size=(h, w), mode="bilinear")
            spatial_ctx = context[:, :, None].expand(b, t, v, d1).reshape(-1, 1, d1)  # [B*T*V, 1, D]
            camera_ctx = context[:, :, None].expand(b, t, hw, d1).reshape(-1, 1, d1)  # [B*T*H*W, 1, D]
            motion_ctx = cond_view.permute(0, 2, 3, 1).reshape(-1, 1, cond_view.shape[1])  # [B*V*H*W, 1, 4]
            x = self.proj_in(self.norm(x).permute(0, 2, 3, 1).reshape(n, hw, c))  # [N, H*W, C]
            frame_ids = torch.arange(t, device=x.device).repeat(b)
            emb_time = self.time_mix_motion_embed(self.frame_proj(frame_ids).to(x.dtype))[:, None]  # [B*T, 1, C]
            emb_view = self.time_mix_time_embed(emb.view(b, t, v, -1)[:, 0].reshape(b * v, -1))  # [B*V, C]
            emb_view = emb_view[:, None].expand(b * v, hw, c).reshape(-1, 1, c)  # [B*V*H*W, 1, C]
            for spatial, camera, motion in zip(self.transformer_blocks, self.time_mix_blocks, self.motion_blocks):
                x = spatial(x, encoder_hidden_states=spatial_ctx)
                x = x.view(b, t, v, hw, c).permute(0, 2, 3, 1, 4).reshape(-1, t, c)  # [B*V*H*W, T, C]
                mixed = camera(x + emb_view, num_frames=v, encoder_hidden_states=camera_ctx)
                x = self.time_mixer(x, mixed, x.new_zeros(x.shape[0], 1))
                x = x.view(b, v, hw, t, c).permute(0, 3, 1, 2, 4).reshape(b * t, -1, c)  # [B*T, V*H*W, C]
                mixed = motion(x + emb_time, num_frames=t, encoder_hidden_states=motion_ctx)
                x = self.time_mixer_motion(x, mixed, x.new_zeros(x.shape[0], 1))
                x = x.reshape(-1, hw, c)  # [B*T*V, H*W, C]
            x = self.proj_out(x).reshape(n, h, w, c).permute(0, 3, 1, 2)
            return x + x_in

    class SV4D2UNet(nn.Module):
        """The spatio-temporal UNet; module indices follow the published checkpoint's."""

        def __init__(self, cfg: SV4D2Config):
            super().__init__()
            mc = cfg.model_channels
            temb = 4 * mc
            self.cfg = cfg
            self.time_proj = Timesteps(mc, flip_sin_to_cos=True, downscale_freq_shift=0)
            self.time_embed = TimestepEmbedding(mc, temb)
            self.label_emb = TimestepEmbedding(cfg.adm_channels, temb)

            def res(cin, cout):
                # eps 1e-5: the published ResBlocks' GroupNorm default; temporal kernel (3, 1, 1)
                return SpatioTemporalResBlock(cin, cout, temb, eps=1e-5, merge_factor=0.0)

            def attn(ch):
                heads = ch // cfg.num_head_channels
                return MotionTransformer(ch, heads, cfg.num_head_channels, cfg)

            self.input_blocks = nn.ModuleList([nn.ModuleList([nn.Conv2d(cfg.in_channels, mc, 3, padding=1)])])
            chans, ch, ds = [mc], mc, 1
            for level, mult in enumerate(cfg.channel_mult):
                for _ in range(cfg.num_res_blocks):
                    layers = [res(ch, mult * mc)]
                    ch = mult * mc
                    if ds in cfg.attention_resolutions:
                        layers.append(attn(ch))
                    self.input_blocks.append(nn.ModuleList(layers))
                    chans.append(ch)
                if level != len(cfg.channel_mult) - 1:
                    self.input_blocks.append(
                        nn.ModuleList([Downsample2D(ch, use_conv=True, out_channels=ch, padding=1, name="op")])
                    )
                    chans.append(ch)
                    ds *= 2
            self.middle_block = nn.ModuleList([res(ch, ch), attn(ch), res(ch, ch)])
            self.output_blocks = nn.ModuleList()
            for level, mult in list(enumerate(cfg.channel_mult))[::-1]:
                for i in range(cfg.num_res_blocks + 1):
                    layers = [res(ch + chans.pop(), mc * mult)]
                    ch = mc * mult
                    if ds in cfg.attention_resolutions:
                        layers.append(attn(ch))
                    if level and i == cfg.num_res_blocks:
                        layers.append(Upsample2D(ch, use_conv=True, out_channels=ch))
                        ds //= 2
                    self.output_blocks.append(nn.ModuleList(layers))
            self.out = nn.Sequential(
                nn.GroupNorm(32, ch, eps=1e-5), nn.SiLU(), nn.Conv2d(mc, cfg.out_channels, 3, padding=1)
            )

        @staticmethod
        def _run(layers, h, emb, context, cond_view, indicator):
            for layer in layers:
                if isinstance(layer, SpatioTemporalResBlock):
                    h = layer(h, emb, image_only_indicator=indicator)
                elif isinstance(layer, MotionTransformer):
                    h = layer(h, emb, context, cond_view)
                else:
                    h = layer(h)
            return h

        def forward(self, x, c_noise, context, y, cond_view):
            # x [B*T*V, in, h, w]; c_noise [B*T*V]; context [B, T, D]; y [B*T*V, adm]; cond_view [B*V, 4, h, w]
            b = context.shape[0]
            emb = self.time_embed(self.time_proj(c_noise).to(x.dtype)) + self.label_emb(y)
            # All-zero indicator: the published blocks always blend with their learned factors.
            indicator = x.new_zeros(b, x.shape[0] // b)
            hs, h = [], x
            for layers in self.input_blocks:
                h = self._run(layers, h, emb, context, cond_view, indicator)
                hs.append(h)
            h = self._run(self.middle_block, h, emb, context, cond_view, indicator)
            for layers in self.output_blocks:
                h = self._run(layers, torch.cat([h, hs.pop()], dim=1), emb, context, cond_view, indicator)
            return self.out(h)

    class SV4D2Model(nn.Module):
        """UNet + CLIP image encoder + VAE, with the conditioning and sampler of SV4D 2.0."""

        def __init__(self, cfg: SV4D2Config):
            super().__init__()
            from diffusers import AutoencoderKL
            from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

            self.cfg = cfg
            self.unet = SV4D2UNet(cfg)
            self.image_encoder = CLIPVisionModelWithProjection(
                CLIPVisionConfig(
                    hidden_size=cfg.clip_width,
                    intermediate_size=4 * cfg.clip_width,
                    num_hidden_layers=cfg.clip_layers,
                    num_attention_heads=cfg.clip_heads,
                    patch_size=cfg.clip_patch,
                    image_size=cfg.clip_image_size,
                    projection_dim=cfg.context_dim,
                    hidden_act="gelu",
                    layer_norm_eps=1e-5,
                )
            )

            def vae():
                n = len(cfg.vae_channels)
                return AutoencoderKL(
                    down_block_types=("DownEncoderBlock2D",) * n,
                    up_block_types=("UpDecoderBlock2D",) * n,
                    block_out_channels=tuple(cfg.vae_channels),
                    layers_per_block=cfg.vae_layers_per_block,
                    latent_channels=cfg.latent_channels,
                    use_post_quant_conv=False,
                    scaling_factor=cfg.scale_factor,
                )

            self.vae = vae()  # encoder: the input video; decoder: the outputs
            self.view_vae = None  # a second encoder only if the checkpoint's view encoder differs
            self.execution_device = None  # set by enable_cpu_offload
            self.register_buffer("clip_mean", torch.tensor([0.48145466, 0.4578275, 0.40821073]), persistent=False)
            self.register_buffer("clip_std", torch.tensor([0.26862954, 0.26130258, 0.27577711]), persistent=False)

        # -- device handling ------------------------------------------------------------------
        def enable_cpu_offload(self, device: str) -> "SV4D2Model":
            """Keep the weights on the CPU and move each part to ``device`` only while it runs."""
            self.to("cpu")
            self.execution_device = torch.device(device)
            return self

        @contextlib.contextmanager
        def _on(self, *modules):
            dev = self.execution_device
            if dev is None:
                yield self.clip_mean.device
                return
            for m in modules:
                m.to(dev)
            try:
                yield dev
            finally:
                for m in modules:
                    m.to("cpu")
                if dev.type == "cuda":
                    torch.cuda.empty_cache()

        # -- encoders ---------------------------------------------------------------------------
        def clip_embed(self, images):
            """[N, 3, H, W] in [-1, 1] -> [N, context_dim] CLIP image embeddings."""
            import kornia

            with self._on(self.image_encoder) as dev:
                enc = self.image_encoder
                x = images.to(dev, torch.float32)
                size = (self.cfg.clip_image_size,) * 2
                # The authors' preprocessing: antialiased bicubic resize, then CLIP normalisation.
                x = kornia.geometry.resize(x, size, interpolation="bicubic", align_corners=True, antialias=True)
                x = kornia.enhance.normalize((x + 1.0) / 2.0, self.clip_mean.to(dev), self.clip_std.to(dev))
                out = enc(pixel_values=x.to(enc.dtype)).image_embeds.float()
            return out

        def encode_latents(self, images, views: bool = False):
            """[N, 3, H, W] in [-1, 1] -> [N, 4, H/f, W/f] latent means (unscaled, as the conditioner gives)."""
            vae = self.view_vae if (views and self.view_vae is not None) else self.vae
            with self._on(vae.encoder, vae.quant_conv) as dev:
                x = images.to(dev, vae.dtype)
                moments = vae.quant_conv(vae.encoder(x))
                return moments[:, : self.cfg.latent_channels].float()

        def decode_latents(self, latents, chunk: int = 4):
            """[N, 4, h, w] sampled latents -> [N, 3, H, W] images in [0, 1]."""
            with self._on(self.vae.decoder) as dev:
                out = [
                    self.vae.decoder(z.to(dev, self.vae.dtype) / self.cfg.scale_factor).float()
                    for z in latents.split(chunk)
                ]
            return ((torch.cat(out) + 1.0) / 2.0).clamp(0, 1)

        # -- conditioning ----------------------------------------------------------------------
        def conditioning(self, motion_frames, view_frames, polar, azimuth):
            """Conditional and unconditional inputs of one pass.

            motion_frames [T, 3, H, W] the input view at the pass's times; view_frames [V, 3, H, W]
            the novel views at the first time, or None; polar, azimuth [T*V] radians relative to the
            input view (time-major). Returns (cond, uncond) dicts of crossattn [1, T, D],
            concat [T*V, 4, h, w], vector [T*V, adm], cond_view [V, 4, h, w].
            """
            cfg = self.cfg
            t, v = motion_frames.shape[0], cfg.views
            if t != cfg.frames:
                raise UserError(f"SV4D 2.0 makes {cfg.frames} frames per pass, got {t}")
            crossattn = self.clip_embed(motion_frames)[None]  # [1, T, D]
            lat = self.encode_latents(motion_frames)  # [T, 4, h, w]
            concat = lat[:, None].expand(t, v, *lat.shape[1:]).reshape(t * v, *lat.shape[1:])
            if view_frames is None:
                cond_view = torch.zeros(v, *lat.shape[1:], device=lat.device)
            else:
                if view_frames.shape[0] != v:
                    raise UserError(f"SV4D 2.0 makes {v} views per pass, got {view_frames.shape[0]} view images")
                cond_view = self.encode_latents(view_frames, views=True)
            dev = lat.device
            polar = torch.as_tensor(np.asarray(polar, np.float64), dtype=torch.float32, device=dev)
            azimuth = torch.as_tensor(np.asarray(azimuth, np.float64), dtype=torch.float32, device=dev)
            if polar.shape != (t * v,) or azimuth.shape != (t * v,):
                raise UserError(f"SV4D 2.0 needs {t * v} polar and azimuth values per pass")
            # The conditioning images' noise level: the authors' "zero" sampler gives 1e-5 (and adds noise of
            # that size to the images before encoding, which we leave out: it changes latents by ~1e-5).
            sigma_emb = _sinusoid(torch.full((t * v,), 1e-5, device=dev), cfg.sigma_embed_dim)
            cam = [_sinusoid(polar, cfg.camera_embed_dim), _sinusoid(azimuth, cfg.camera_embed_dim)]
            cond = {
                "crossattn": crossattn,
                "concat": concat,
                "vector": torch.cat([sigma_emb, *cam], 1),
                "cond_view": cond_view,
            }
            # Unconditional branch: every image-derived input zeroed, cameras kept.
            uncond = {
                "crossattn": torch.zeros_like(crossattn),
                "concat": torch.zeros_like(concat),
                "vector": torch.cat([torch.zeros_like(sigma_emb), *cam], 1),
                "cond_view": torch.zeros_like(cond_view),
            }
            return cond, uncond

        # -- denoiser and sampler --------------------------------------------------------------
        def denoise(self, x, sigma, cond):
            """Denoised latents D(x; sigma) [N, 4, h, w] (v-prediction, EDM c_noise), float32."""
            with self._on(self.unet) as dev:
                return self._denoise(x.to(dev), sigma.to(dev), {k: c.to(dev) for k, c in cond.items()})

        def _denoise(self, x, sigma, cond):
            s = sigma.float().view(-1, 1, 1, 1)
            c_skip, c_out, c_in = 1.0 / (s**2 + 1.0), -s / (s**2 + 1.0) ** 0.5, 1.0 / (s**2 + 1.0) ** 0.5
            c_noise = 0.25 * sigma.float().log()
            dt = next(self.unet.parameters()).dtype
            inp = torch.cat([x * c_in, cond["concat"]], 1).to(dt)
            out = self.unet(inp, c_noise, cond["crossattn"].to(dt), cond["vector"].to(dt), cond["cond_view"].to(dt))
            return out.float() * c_out + x * c_skip

        def sample(self, cond, uncond, noise, sampler: SV4D2SamplerConfig = SV4D2SamplerConfig(), progress=None):
            """Euler EDM with linearly rising guidance: noise [T*V, 4, h, w] -> latents [T*V, 4, h, w]."""
            with self._on(self.unet) as dev:
                n = noise.shape[0]
                ramp = torch.linspace(0, 1, sampler.steps, device=dev)
                lo, hi = sampler.sigma_min ** (1 / sampler.rho), sampler.sigma_max ** (1 / sampler.rho)
                sigmas = torch.cat([(hi + ramp * (lo - hi)) ** sampler.rho, ramp.new_zeros(1)])
                scale = torch.linspace(sampler.cfg_min, sampler.cfg_max, n, device=dev).view(-1, 1, 1, 1)
                both = {k: torch.cat([uncond[k], cond[k]]).to(dev) for k in cond}
                x = noise.to(dev, torch.float32) * torch.sqrt(1.0 + sigmas[0] ** 2)
                for i in range(sampler.steps):
                    sigma = sigmas[i].expand(2 * n)
                    d_u, d_c = self._denoise(torch.cat([x, x]), sigma, both).chunk(2)
                    denoised = d_u + scale * (d_c - d_u)
                    x = x + (sigmas[i + 1] - sigmas[i]) * (x - denoised) / sigmas[i]
                    if progress is not None:
                        progress(i + 1, sampler.steps)
            return x

    _CACHE["model"] = SV4D2Model
    return SV4D2Model


def _sinusoid(x, dim: int):
    """[N] -> [N, dim] sinusoidal embedding (cos first, max period 10000), as the conditioner uses."""
    from diffusers.models.embeddings import get_timestep_embedding

    return get_timestep_embedding(x, dim, flip_sin_to_cos=True, downscale_freq_shift=0)


# ---------------------------------------------------------------------------------------------
# Checkpoint: the published single file <-> our modules


_RES_SPATIAL = {
    "in_layers.0": "norm1",
    "in_layers.2": "conv1",
    "emb_layers.1": "time_emb_proj",
    "out_layers.0": "norm2",
    "out_layers.3": "conv2",
    "skip_connection": "conv_shortcut",
}


def unet_key_to_ours(key: str) -> str:
    """A key of the published UNet (without its prefix) -> the same weight in SV4D2UNet."""
    for old, new in (
        ("time_embed.0.", "time_embed.linear_1."),
        ("time_embed.2.", "time_embed.linear_2."),
        ("label_emb.0.0.", "label_emb.linear_1."),
        ("label_emb.0.2.", "label_emb.linear_2."),
    ):
        if key.startswith(old):
            return new + key[len(old) :]
    m = re.match(r"(.*)\.time_mix_blocks\.(in_layers\.[02]|emb_layers\.1|out_layers\.[03]|skip_connection)\.(.*)$", key)
    if m:
        return f"{m[1]}.temporal_res_block.{_RES_SPATIAL[m[2]]}.{m[3]}"
    m = re.match(r"(.*)\.(in_layers\.[02]|emb_layers\.1|out_layers\.[03]|skip_connection)\.(.*)$", key)
    if m:
        return f"{m[1]}.spatial_res_block.{_RES_SPATIAL[m[2]]}.{m[3]}"
    key = re.sub(r"\.op\.(weight|bias)$", r".conv.\1", key)  # downsampling conv
    return re.sub(
        r"\.(time_mix_time_embed|time_mix_motion_embed)\.([02])\.",
        lambda m: f".{m[1]}.linear_{1 if m[2] == '0' else 2}.",
        key,
    )


def unet_key_to_published(key: str, downsample_keys: set[str]) -> str:
    """Inverse of ``unet_key_to_ours`` (``downsample_keys``: our keys of downsampling convs)."""
    inv = {v: k for k, v in _RES_SPATIAL.items()}
    for old, new in (
        ("time_embed.linear_1.", "time_embed.0."),
        ("time_embed.linear_2.", "time_embed.2."),
        ("label_emb.linear_1.", "label_emb.0.0."),
        ("label_emb.linear_2.", "label_emb.0.2."),
    ):
        if key.startswith(old):
            return new + key[len(old) :]
    m = re.match(r"(.*)\.temporal_res_block\.(\w+)\.(.*)$", key)
    if m:
        return f"{m[1]}.time_mix_blocks.{inv[m[2]]}.{m[3]}"
    m = re.match(r"(.*)\.spatial_res_block\.(\w+)\.(.*)$", key)
    if m:
        return f"{m[1]}.{inv[m[2]]}.{m[3]}"
    if key in downsample_keys:
        return re.sub(r"\.conv\.(weight|bias)$", r".op.\1", key)
    return re.sub(
        r"\.(time_mix_time_embed|time_mix_motion_embed)\.linear_([12])\.",
        lambda m: f".{m[1]}.{0 if m[2] == '1' else 2}.",
        key,
    )


def _clip_renames(layers: int) -> list[tuple[str, str]]:
    """(OpenCLIP key, transformers key) of every CLIP weight that is only renamed: all but the projection
    (transposed) and the fused q/k/v input projection of each layer (split in three)."""
    pairs = [
        ("conv1.weight", "vision_model.embeddings.patch_embedding.weight"),
        ("class_embedding", "vision_model.embeddings.class_embedding"),
        ("positional_embedding", "vision_model.embeddings.position_embedding.weight"),
    ]
    for p in ("weight", "bias"):
        pairs += [
            (f"ln_pre.{p}", f"vision_model.pre_layrnorm.{p}"),
            (f"ln_post.{p}", f"vision_model.post_layernorm.{p}"),
        ]
        for i in range(layers):
            src, dst = f"transformer.resblocks.{i}.", f"vision_model.encoder.layers.{i}."
            pairs += [
                (f"{src}{old}.{p}", f"{dst}{new}.{p}")
                for old, new in (
                    ("attn.out_proj", "self_attn.out_proj"),
                    ("ln_1", "layer_norm1"),
                    ("ln_2", "layer_norm2"),
                    ("mlp.c_fc", "mlp.fc1"),
                    ("mlp.c_proj", "mlp.fc2"),
                )
            ]
    return pairs


def clip_to_ours(sd: dict, layers: int) -> dict:
    """OpenCLIP visual tower keys -> transformers CLIPVisionModelWithProjection keys."""
    out = {ours: sd[theirs] for theirs, ours in _clip_renames(layers)}
    out["visual_projection.weight"] = sd["proj"].t().contiguous()
    for i in range(layers):
        src, dst = f"transformer.resblocks.{i}.", f"vision_model.encoder.layers.{i}."
        for p in ("weight", "bias"):
            for n, part in zip("qkv", sd[f"{src}attn.in_proj_{p}"].chunk(3)):
                out[f"{dst}self_attn.{n}_proj.{p}"] = part
    return out


def clip_to_published(sd: dict, layers: int) -> dict:
    """Inverse of ``clip_to_ours``."""
    import torch

    out = {theirs: sd[ours] for theirs, ours in _clip_renames(layers)}
    out["proj"] = sd["visual_projection.weight"].t().contiguous()
    for i in range(layers):
        dst, src = f"transformer.resblocks.{i}.", f"vision_model.encoder.layers.{i}."
        for p in ("weight", "bias"):
            out[f"{dst}attn.in_proj_{p}"] = torch.cat([sd[f"{src}self_attn.{n}_proj.{p}"] for n in "qkv"])
    return out


def vae_to_ours(ldm: dict, model) -> dict:
    """LDM-layout VAE keys (encoder.*, quant_conv.*, decoder.*) -> diffusers AutoencoderKL keys."""
    from diffusers.loaders.single_file_utils import convert_ldm_vae_checkpoint

    return convert_ldm_vae_checkpoint(ldm, dict(model.config))


def vae_to_published(sd: dict, n_levels: int) -> dict:
    """Inverse of ``vae_to_ours`` (diffusers AutoencoderKL -> LDM layout)."""
    out = {}
    for key, val in sd.items():
        k = key
        k = re.sub(r"^encoder\.down_blocks\.(\d+)\.resnets\.", r"encoder.down.\1.block.", k)
        k = re.sub(r"^encoder\.down_blocks\.(\d+)\.downsamplers\.0\.", r"encoder.down.\1.downsample.", k)
        k = re.sub(
            r"^decoder\.up_blocks\.(\d+)\.resnets\.", lambda m: f"decoder.up.{n_levels - 1 - int(m[1])}.block.", k
        )
        k = re.sub(
            r"^decoder\.up_blocks\.(\d+)\.upsamplers\.0\.",
            lambda m: f"decoder.up.{n_levels - 1 - int(m[1])}.upsample.",
            k,
        )
        k = re.sub(r"\.mid_block\.resnets\.(\d+)\.", lambda m: f".mid.block_{int(m[1]) + 1}.", k)
        k = k.replace(".mid_block.attentions.0.", ".mid.attn_1.").replace(".conv_shortcut.", ".nin_shortcut.")
        k = k.replace(".conv_norm_out.", ".norm_out.")
        if ".mid.attn_1." in k:
            for old, new in (
                ("group_norm", "norm"),
                ("to_q", "q"),
                ("to_k", "k"),
                ("to_v", "v"),
                ("to_out.0", "proj_out"),
            ):
                k = k.replace(f".attn_1.{old}.", f".attn_1.{new}.")
            if val.ndim == 2:
                val = val[:, :, None, None]  # the LDM attention projections are 1x1 convs
        out[k] = val
    return out


def check_checkpoint(path: str | os.PathLike) -> Path:
    """The checkpoint file inside folder ``path``, or MissingCheckpointError naming file and folder."""
    path = Path(path)
    how = (
        f"accept the {LICENCE.split(' (')[0]} on the model page of {HF_REPO}, then "
        f"`huggingface-cli download {HF_REPO} {CHECKPOINT_FILE} --local-dir {path}` and pass --checkpoint {path}"
    )
    if path.is_file() and path.name.endswith(".safetensors"):
        path = path.parent
    if not path.is_dir():
        raise MissingCheckpointError(f"SV4D 2.0 checkpoint folder ({CHECKPOINT_FILE} from {HF_REPO})", str(path), how)
    if not (path / CHECKPOINT_FILE).is_file():
        raise MissingCheckpointError(f"SV4D 2.0 checkpoint {CHECKPOINT_FILE} ({HF_REPO})", str(path), how)
    return path / CHECKPOINT_FILE


def checkpoint_config(path: str | os.PathLike) -> SV4D2Config:
    """The model shape of a checkpoint folder: sv4d2_config.json if present, else the published one."""
    folder = check_checkpoint(path).parent
    cfg_path = folder / CONFIG_FILE
    if not cfg_path.exists():
        return SV4D2Config()
    try:
        return SV4D2Config.from_dict(json.loads(cfg_path.read_text()))
    except (ValueError, TypeError) as exc:
        raise UserError(f"{cfg_path}: unreadable model config ({exc})") from None


def load_model(checkpoint: str | os.PathLike, device: str | None = None, dtype: str = "auto", offload: bool = False):
    """SV4D2Model with the weights of ``checkpoint`` (a folder holding sv4d2.safetensors); never downloads.

    dtype: auto (bf16 on CUDA, float32 on CPU), float32, bfloat16 or float16 for the UNet (the
    VAE and CLIP stay float32, as the authors run them). offload: keep weights on the CPU and
    move each part to the GPU only while it runs (for GPUs under ~24 GB).
    """
    torch = _torch()
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    file = check_checkpoint(checkpoint)
    cfg = checkpoint_config(checkpoint)
    try:
        sd = load_file(str(file))
    except (SafetensorError, OSError) as exc:
        raise UserError(f"{file}: not a readable safetensors file ({exc}); download it again from {HF_REPO}") from None
    model = build_model(cfg)
    load_state_dict(model, sd, str(file))
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    names = {
        "auto": torch.bfloat16 if device.startswith("cuda") else torch.float32,
        "float32": torch.float32,
        "bfloat16": torch.bfloat16,
        "bf16": torch.bfloat16,
        "float16": torch.float16,
        "fp16": torch.float16,
    }
    if dtype not in names:
        raise UserError(f"--dtype must be one of {', '.join(names)}, got {dtype!r}")
    model.unet.to(names[dtype])
    model.eval().requires_grad_(False)
    return model.enable_cpu_offload(device) if offload else model.to(device)


def load_state_dict(model, sd: dict, source: str = "checkpoint") -> None:
    """Fill ``model`` from a state dict in the published layout; one UserError naming what is wrong."""
    import torch

    cfg = model.cfg
    groups = {}
    for name, prefix in (
        ("UNet", UNET_PREFIX),
        ("CLIP image encoder", CLIP_PREFIX),
        ("VAE encoder", FRAMES_VAE_PREFIX),
        ("view VAE encoder", VIEW_VAE_PREFIX),
        ("VAE decoder", DECODER_PREFIX),
    ):
        groups[name] = {k[len(prefix) :]: v.float() for k, v in sd.items() if k.startswith(prefix)}
    missing = [n for n, g in groups.items() if not g]
    if missing:
        raise UserError(
            f"{source}: no {', '.join(missing)} weights (keys {UNET_PREFIX}*, {CLIP_PREFIX}*, "
            f"{FRAMES_VAE_PREFIX}*, {VIEW_VAE_PREFIX}*, {DECODER_PREFIX}*): not the SV4D 2.0 file from {HF_REPO}"
        )

    def put(module, state, what):
        try:
            module.load_state_dict(state, strict=True)
        except (RuntimeError, KeyError) as exc:
            first = str(exc).replace("\n", " ").replace("\t", "")[:300]
            raise UserError(f"{source}: the {what} weights do not fit the SV4D 2.0 model ({first})") from None

    put(model.unet, {unet_key_to_ours(k): v for k, v in groups["UNet"].items()}, "UNet")
    try:
        clip = clip_to_ours(groups["CLIP image encoder"], cfg.clip_layers)
    except KeyError as exc:
        raise UserError(f"{source}: CLIP image encoder weight {exc} missing") from None
    ours_clip = model.image_encoder.state_dict()
    for k in ours_clip:
        if k.endswith("position_ids") and k not in clip:
            clip[k] = ours_clip[k]  # a buffer, not a weight
    put(model.image_encoder, clip, "CLIP image encoder")

    def encoder_part(g):
        return {k: v for k, v in g.items() if k.startswith(("encoder.", "quant_conv."))}

    frames_enc = encoder_part(groups["VAE encoder"])
    view_enc = encoder_part(groups["view VAE encoder"])
    dec = {f"decoder.{k}": v for k, v in groups["VAE decoder"].items()}
    put(model.vae, vae_to_ours({**frames_enc, **dec}, model.vae), "VAE")
    same = frames_enc.keys() == view_enc.keys() and all(torch.equal(frames_enc[k], view_enc[k]) for k in frames_enc)
    if not same:
        import copy

        model.view_vae = copy.deepcopy(model.vae)
        model.view_vae.decoder = None  # only its encoder is used
        full = vae_to_ours({**view_enc, **dec}, model.vae)
        put(model.view_vae, {k: v for k, v in full.items() if not k.startswith("decoder.")}, "view VAE encoder")


def published_state_dict(model) -> dict:
    """Our model's weights in the published single-file layout (to write test checkpoints)."""
    cfg = model.cfg
    unet = model.unet.state_dict()
    down = {
        k
        for k in unet
        if re.match(r"input_blocks\.\d+\.0\.conv\.(weight|bias)$", k)
        and "Downsample" in type(model.unet.input_blocks[int(k.split(".")[1])][0]).__name__
    }
    out = {UNET_PREFIX + unet_key_to_published(k, down): v for k, v in unet.items()}
    clip = clip_to_published(model.image_encoder.state_dict(), cfg.clip_layers)
    out.update({CLIP_PREFIX + k: v for k, v in clip.items()})
    vae = vae_to_published(model.vae.state_dict(), len(cfg.vae_channels))
    for prefix in (FRAMES_VAE_PREFIX, VIEW_VAE_PREFIX):
        out.update({prefix + k: v for k, v in vae.items()})  # the conditioner keeps whole VAEs
    out.update({DECODER_PREFIX + k[len("decoder.") :]: v for k, v in vae.items() if k.startswith("decoder.")})
    return {k: v.detach().clone().contiguous() for k, v in out.items()}  # no shared storage (safetensors)


def write_checkpoint(model, folder: str | os.PathLike, config: SV4D2Config | None = None) -> Path:
    """Save ``model`` as a checkpoint folder (sv4d2.safetensors [+ sv4d2_config.json for other shapes])."""
    from safetensors.torch import save_file

    from t2bs.project import atomic_path, write_json

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / CHECKPOINT_FILE) as tmp:
        save_file(published_state_dict(model), str(tmp))
    cfg = config or model.cfg
    if cfg != SV4D2Config():
        write_json(folder / CONFIG_FILE, asdict(cfg))
    return folder


def write_tiny_checkpoint(folder: str | os.PathLike, seed: int = 0, **overrides) -> Path:
    """A random-weight tiny SV4D 2.0 checkpoint folder (tests, CI): every weight non-zero."""
    torch = _torch()
    torch.manual_seed(seed)
    model = build_model(tiny_config(**overrides))
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn_like(p) * 0.2)  # zero-initialised output layers would hide the network
    return write_checkpoint(model, folder)


# ---------------------------------------------------------------------------------------------
# The V x T grid by chaining passes


@dataclass
class SV4D2GridConfig:
    steps: int = 50  # sampler steps per pass (authors' default)
    guidance: float = 2.0  # guidance scale of the last output of a pass (rises linearly from 1; authors': 2)
    seed: int = 0  # seed of every pass's noise (pass k uses seed * 1000 + k)
    # +1: SV4D's azimuth grows in the direction of our orbit's (camera toward the character's left,
    # +X). Not checked against the real weights (none on this machine): -1 mirrors it.
    azimuth_sign: float = 1.0
    dtype: str = "auto"  # UNet precision: auto (bf16 on CUDA, float32 on CPU), float32, bfloat16, float16
    offload: bool = False  # keep weights on the CPU between parts (GPUs under ~24 GB)


@dataclass
class Pass:
    frames: list  # [T_p] time indices of the grid made in this pass
    views: list  # [V_p] view indices of the grid made in this pass
    anchor: int  # the time whose view images condition the pass (its first frame)


def plan_passes(num_frames: int, novel_views: list[int], frames_per_pass: int, views_per_pass: int) -> list[Pass]:
    """Cover (novel views) x (all times) with passes of views_per_pass x frames_per_pass.

    Views go in groups of ``views_per_pass`` in the given order, the last group shifted back to stay
    full (it re-makes a few views, whose earlier results are kept). Within a group, time windows
    start at 0 and overlap by one frame: each window's first frame was made by the previous window
    (or is the static mesh's render, for frame 0), so every pass is conditioned on the novel views
    at its first frame, the authors' way of continuing a longer video. The last window is shifted
    back to end on the last frame.
    """
    if num_frames < frames_per_pass:
        raise UserError(
            f"SV4D 2.0 makes {frames_per_pass} frames per pass: the input video has {num_frames} "
            f"frames; make at least {frames_per_pass} (--frames)"
        )
    if len(novel_views) < views_per_pass:
        raise UserError(
            f"SV4D 2.0 makes {views_per_pass} views per pass: the grid needs at least that many "
            f"views besides the input one, got {len(novel_views)}"
        )
    starts, t0 = [], 0
    while True:
        t0 = min(t0, num_frames - frames_per_pass)
        starts.append(t0)
        if t0 + frames_per_pass >= num_frames:
            break
        t0 += frames_per_pass - 1
    groups, i = [], 0
    while i < len(novel_views):
        j = min(i, len(novel_views) - views_per_pass)
        groups.append(list(novel_views[j : j + views_per_pass]))
        i += views_per_pass
    return [Pass(list(range(s, s + frames_per_pass)), g, s) for g in groups for s in starts]


def make_grid_frames(
    model,
    video: np.ndarray,
    orbit: np.ndarray,
    azimuths_deg,
    canonical: int,
    config: SV4D2GridConfig = SV4D2GridConfig(),
    progress=None,
) -> tuple[np.ndarray, list[Pass]]:
    """Fixed-view video + fixed-time orbit renders -> the V x T grid's frames.

    video [T, S, S, 3] uint8 (the canonical view over time); orbit [V, S, S, 3] uint8 (the static
    mesh from every grid view, frame 0 of the novel views); azimuths_deg [V] of the grid's views
    (all at the same elevation). Returns frames [V, T, S, S, 3] uint8 and the passes made.
    """
    torch = _torch()
    import torch.nn.functional as F

    video, orbit = np.asarray(video, np.uint8), np.asarray(orbit, np.uint8)
    nt, size = video.shape[0], video.shape[1]
    nv = orbit.shape[0]
    if video.shape[1:] != (size, size, 3) or orbit.shape[1:] != (size, size, 3):
        raise UserError(
            f"SV4D 2.0 needs square frames of one size: video {video.shape[1:]}, orbit renders {orbit.shape[1:]}"
        )
    cfg = model.cfg
    res = cfg.image_size

    def to_model(x):  # [N, S, S, 3] uint8 -> [N, 3, res, res] in [-1, 1]
        t = torch.from_numpy(np.ascontiguousarray(x)).permute(0, 3, 1, 2).float() / 127.5 - 1.0
        return (
            F.interpolate(t, size=(res, res), mode="bicubic", align_corners=False, antialias=True).clamp(-1, 1)
            if res != size
            else t
        )

    def to_grid(x):  # [N, 3, res, res] in [0, 1] -> [N, S, S, 3] uint8
        if res != size:
            x = F.interpolate(x, size=(size, size), mode="bicubic", align_corners=False, antialias=True)
        return (x.clamp(0, 1) * 255 + 0.5).byte().permute(0, 2, 3, 1).numpy()

    made = np.zeros((nv, nt), bool)  # [V, T] which grid images exist
    out = np.zeros((nv, nt, size, size, 3), np.uint8)  # [V, T, S, S, 3]
    out[canonical] = video
    made[canonical] = True
    out[:, 0] = orbit  # the static mesh: every view at the first time
    out[canonical, 0] = video[0]
    made[:, 0] = True
    model_in = {}  # (v, t) -> [3, res, res] model-resolution image, [-1, 1]: outputs stay unrounded
    vid_in = to_model(video)
    orbit_in = to_model(orbit)
    for v in range(nv):
        model_in[(v, 0)] = orbit_in[v]
    for t in range(nt):
        model_in[(canonical, t)] = vid_in[t]
    az = np.asarray(azimuths_deg, np.float64)
    novel = [v for v in range(nv) if v != canonical]
    passes = plan_passes(nt, novel, cfg.frames, cfg.views)
    sampler = SV4D2SamplerConfig(steps=config.steps, cfg_max=config.guidance)
    lat = res // cfg.vae_factor
    for k, ps in enumerate(passes):
        motion = torch.stack([model_in[(canonical, t)] for t in ps.frames])
        views = torch.stack([model_in[(v, ps.anchor)] for v in ps.views])
        rel = np.mod(config.azimuth_sign * np.deg2rad(az[ps.views] - az[canonical]), 2 * np.pi)  # [V_p]
        polar = np.full(cfg.frames * cfg.views, np.pi / 2)  # same elevation as the input view
        azim = np.tile(rel, cfg.frames)  # time-major, views inner
        g = torch.Generator().manual_seed(config.seed * 1000 + k)
        noise = torch.randn(cfg.frames * cfg.views, cfg.latent_channels, lat, lat, generator=g)
        with torch.no_grad():
            c, uc = model.conditioning(motion, views, polar, azim)
            z = model.sample(c, uc, noise, sampler)
            images = model.decode_latents(z).cpu()  # [T_p * V_p, 3, res, res] in [0, 1]
        tiles = to_grid(images).reshape(cfg.frames, cfg.views, size, size, 3)
        for i, t in enumerate(ps.frames):
            for j, v in enumerate(ps.views):
                if not made[v, t]:
                    out[v, t] = tiles[i, j]
                    model_in[(v, t)] = images[i * cfg.views + j] * 2 - 1
                    made[v, t] = True
        if progress is not None:
            progress(k + 1, len(passes))
    assert made.all()
    return out, passes


__all__ = [
    "SV4D2Config",
    "SV4D2SamplerConfig",
    "tiny_config",
    "build_model",
    "load_model",
    "check_checkpoint",
    "write_checkpoint",
    "write_tiny_checkpoint",
    "published_state_dict",
    "load_state_dict",
    "HF_REPO",
    "CHECKPOINT_FILE",
    "LICENCE",
    "SV4D2GridConfig",
    "Pass",
    "plan_passes",
    "make_grid_frames",
]
