"""Is our SV4D 2.0 (t2bs.video.sv4d2) the authors' model? Same small config, same random weights, same inputs.

Builds the reference from a checkout of Stability-AI/generative-models (its sgm/ classes, configured
as scripts/sampling/configs/sv4d2.yaml but small) and ours from ``tiny_config()``; writes the
reference's weights as a single-file checkpoint in the published layout and loads it with our
``load_model`` (the real loading code); then prints the max abs difference of
  - the conditioner outputs (CLIP context, concat latents, vector, view latents; cond and uncond),
  - the denoiser outputs (classifier-free batch, views given),
  - the sampled latents for the same noise (Euler EDM, linear guidance 1 -> 2), first pass
    (no view images: cond_view zeroed) and a chained pass (view images given),
  - the decoded images.

The reference's CLIP tower comes from a checkout of mlfoundations/open_clip (its VisionTransformer,
the class the authors' FrozenOpenCLIPImageEmbedder wraps; the pretrained download is replaced by
random weights). Packages the reference imports but these classes never call (open_clip's package
__init__, torchvision) are replaced by empty modules; ``pip install einops omegaconf kornia
pytorch_lightning`` covers the rest. Run:

    PYTHONPATH=src OMP_NUM_THREADS=1 python3 benchmarks/sv4d2_equivalence.py \
        --reference /path/to/generative-models --open-clip /path/to/open_clip

Without the checkouts it prints why it skips and exits 0.
"""

from __future__ import annotations

import importlib
import sys
import tempfile
import time
import types
from pathlib import Path

import typer

from t2bs.cli.exits import run_command


def _stub_package(name: str, path: Path | None = None):
    mod = types.ModuleType(name)
    if path is not None:
        mod.__path__ = [str(path)]  # import submodules from here without running the package __init__
    sys.modules[name] = mod
    return mod


def setup_reference(reference: Path, open_clip: Path):
    sys.path.insert(0, str(reference))
    for name in ("sgm", "sgm.modules", "sgm.models"):
        _stub_package(name, reference / name.replace(".", "/"))
    _stub_package("open_clip", open_clip / "src" / "open_clip")
    mods = {
        n: importlib.import_module(n)
        for n in (
            "sgm.modules.diffusionmodules.video_model",
            "sgm.modules.diffusionmodules.denoiser",
            "sgm.modules.diffusionmodules.wrappers",
            "sgm.modules.diffusionmodules.sampling",
            "sgm.modules.encoders.modules",
            "sgm.models.autoencoder",
        )
    }
    # open_clip.utils names torchvision's FrozenBatchNorm2d (unused by the ViT): stub it for this one
    # import only, so that transformers' own torchvision probe keeps working.
    tv = _stub_package("torchvision")
    ops = _stub_package("torchvision.ops")
    misc = _stub_package("torchvision.ops.misc")
    misc.FrozenBatchNorm2d = type("FrozenBatchNorm2d", (), {})
    tv.ops, ops.misc = ops, misc
    try:
        mods["open_clip.transformer"] = importlib.import_module("open_clip.transformer")
    finally:
        for name in ("torchvision.ops.misc", "torchvision.ops", "torchvision"):
            sys.modules.pop(name, None)
    return mods


def tiny_open_clip_embedder(width: int, layers: int, heads: int, patch: int, image_size: int, embed_dim: int):
    """The authors' FrozenOpenCLIPImageEmbedder around a random open_clip ViT (its __init__ would download)."""
    import torch

    enc = sys.modules["sgm.modules.encoders.modules"]
    oc = sys.modules["open_clip.transformer"]
    emb = enc.FrozenOpenCLIPImageEmbedder.__new__(enc.FrozenOpenCLIPImageEmbedder)
    enc.AbstractEmbModel.__init__(emb)
    emb.model = torch.nn.Module()
    emb.model.visual = oc.VisionTransformer(
        image_size=image_size,
        patch_size=patch,
        width=width,
        layers=layers,
        heads=heads,
        mlp_ratio=4.0,
        output_dim=embed_dim,
        act_layer=torch.nn.GELU,
    )
    emb.max_crops, emb.pad_to_max_len, emb.repeat_to_max_len = 0, False, False
    emb.device, emb.max_length, emb.antialias = "cpu", 77, True
    emb.register_buffer("mean", torch.Tensor([0.48145466, 0.4578275, 0.40821073]), persistent=False)
    emb.register_buffer("std", torch.Tensor([0.26862954, 0.26130258, 0.27577711]), persistent=False)
    emb.ucg_rate, emb.unsqueeze_dim, emb.stored_batch = 0.0, False, None
    emb.model.visual.output_tokens, emb.output_tokens = False, False
    return emb


def build_reference(cfg, mods):
    """DiffusionEngine's parts as sv4d2.yaml builds them, at the small size of ``cfg``."""
    import torch

    vm = mods["sgm.modules.diffusionmodules.video_model"]
    unet = vm.SpatialUNetModelWithTime(
        in_channels=cfg.in_channels,
        model_channels=cfg.model_channels,
        out_channels=cfg.out_channels,
        num_res_blocks=cfg.num_res_blocks,
        attention_resolutions=list(cfg.attention_resolutions),
        channel_mult=list(cfg.channel_mult),
        num_classes="sequential",
        adm_in_channels=cfg.adm_channels,
        num_head_channels=cfg.num_head_channels,
        context_dim=cfg.context_dim,
        motion_context_dim=cfg.motion_context_dim,
        extra_ff_mix_layer=True,
        legacy=False,
        use_linear_in_transformer=True,
        use_spatial_context=True,
        use_spatial_transformer=True,
        separate_motion_merge_factor=True,
        use_motion_attention=True,
        use_3d_attention=True,
        use_camera_emb=True,
        replicate_time_mix_bug=True,
        # "softmax": the yaml's "softmax-xformers" attention with the same weights on PyTorch's kernel
        # (xformers needs CUDA; the time-mix blocks have no fallback of their own).
        spatial_transformer_attn_type="softmax",
        time_block_merge_factor=0.0,
        time_block_merge_strategy="learned_with_images",
        time_kernel_size=[3, 1, 1],
        time_mix_legacy=False,
        transformer_depth=cfg.transformer_depth,
        use_checkpoint=False,
    )
    n = len(cfg.vae_channels)
    ch = cfg.vae_channels[0]
    # "vanilla": the same attention block as the yaml's "vanilla-xformers" (same weights), on PyTorch's kernel;
    # xformers needs CUDA.
    ddconfig = {
        "attn_resolutions": [],
        "attn_type": "vanilla",
        "ch": ch,
        "ch_mult": [c // ch for c in cfg.vae_channels],
        "double_z": True,
        "dropout": 0.0,
        "in_channels": 3,
        "num_res_blocks": cfg.vae_layers_per_block,
        "out_ch": 3,
        "resolution": cfg.image_size,
        "z_channels": cfg.latent_channels,
    }
    assert n == len(ddconfig["ch_mult"])
    ae = {
        "target": "sgm.models.autoencoder.AutoencoderKLModeOnly",
        "params": {
            "embed_dim": cfg.latent_channels,
            "ddconfig": ddconfig,
            "lossconfig": {"target": "torch.nn.Identity"},
        },
    }
    zero = {"target": "sgm.modules.diffusionmodules.sigma_sampling.ZeroSampler"}
    T, V = cfg.frames, cfg.views
    emb_models = [
        {
            "input_key": "cond_frames_without_noise",
            "target": "sgm.modules.encoders.modules.FrozenOpenCLIPImagePredictionEmbedder",
            "params": {
                "n_cond_frames": T,
                "n_copies": 1,
                "open_clip_embedding_config": {
                    "target": "__main__.tiny_open_clip_embedder",
                    "params": {
                        "width": cfg.clip_width,
                        "layers": cfg.clip_layers,
                        "heads": cfg.clip_heads,
                        "patch": cfg.clip_patch,
                        "image_size": cfg.clip_image_size,
                        "embed_dim": cfg.context_dim,
                    },
                },
            },
        },
        {
            "input_key": "cond_frames",
            "target": "sgm.modules.encoders.modules.VideoPredictionEmbedderWithEncoder",
            "params": {
                "is_ae": True,
                "n_cond_frames": T * V,
                "n_copies": 1,
                "encoder_config": ae,
                "sigma_cond_config": {
                    "target": "sgm.modules.encoders.modules.ConcatTimestepEmbedderND",
                    "params": {"outdim": cfg.sigma_embed_dim},
                },
                "sigma_sampler_config": zero,
            },
        },
        {
            "input_key": "polar_rad",
            "target": "sgm.modules.encoders.modules.ConcatTimestepEmbedderND",
            "params": {"outdim": cfg.camera_embed_dim},
        },
        {
            "input_key": "azimuth_rad",
            "target": "sgm.modules.encoders.modules.ConcatTimestepEmbedderND",
            "params": {"outdim": cfg.camera_embed_dim},
        },
        {
            "input_key": "cond_view",
            "target": "sgm.modules.encoders.modules.VideoPredictionEmbedderWithEncoder",
            "params": {
                "is_ae": True,
                "n_cond_frames": V,
                "n_copies": 1,
                "encoder_config": ae,
                "sigma_sampler_config": zero,
            },
        },
        {
            "input_key": "cond_motion",
            "target": "sgm.modules.encoders.modules.VideoPredictionEmbedderWithEncoder",
            "params": {
                "is_ae": True,
                "n_cond_frames": T,
                "n_copies": 1,
                "encoder_config": ae,
                "sigma_sampler_config": zero,
            },
        },
    ]
    conditioner = mods["sgm.modules.encoders.modules"].GeneralConditioner(emb_models)
    first_stage = mods["sgm.models.autoencoder"].AutoencodingEngine(
        encoder_config={"target": "torch.nn.Identity"},
        decoder_config={"target": "sgm.modules.diffusionmodules.model.Decoder", "params": ddconfig},
        loss_config={"target": "torch.nn.Identity"},
        regularizer_config={"target": "sgm.modules.autoencoding.regularizers.DiagonalGaussianRegularizer"},
    )
    engine = torch.nn.Module()  # the DiffusionEngine's naming: model.diffusion_model, conditioner, first_stage_model
    engine.model = mods["sgm.modules.diffusionmodules.wrappers"].OpenAIWrapper(unet)
    engine.conditioner = conditioner
    engine.first_stage_model = first_stage
    denoiser = mods["sgm.modules.diffusionmodules.denoiser"].Denoiser(
        {"target": "sgm.modules.diffusionmodules.denoiser_scaling.VScalingWithEDMcNoise"}
    )
    return engine.eval(), denoiser


def full_size_layout(mods) -> tuple[int, int]:
    """The published size (sv4d2.yaml): every reference weight maps to one of ours, same shape.

    Both models are built on the meta device (no memory, no compute). Returns (weights compared,
    parameters). Raises AssertionError naming the first mismatch.
    """
    import contextlib
    import io

    import torch

    from t2bs.video import sv4d2

    cfg = sv4d2.SV4D2Config()
    with torch.device("meta"), contextlib.redirect_stdout(io.StringIO()):
        engine, _ = build_reference(cfg, mods)
        ours = sv4d2.build_model(cfg)
    ref = engine.state_dict()

    def group(prefix):
        return {k[len(prefix) :]: v for k, v in ref.items() if k.startswith(prefix)}

    def same(mapped: dict, module, what: str, skip=()):
        want = {k: v for k, v in module.state_dict().items() if not k.endswith(skip or ("\0",))}
        assert mapped.keys() == want.keys(), (what, sorted(set(mapped) ^ set(want))[:5])
        for k in want:
            assert tuple(mapped[k].shape) == tuple(want[k].shape), (what, k, mapped[k].shape, want[k].shape)
        return len(want)

    n = same({sv4d2.unet_key_to_ours(k): v for k, v in group(sv4d2.UNET_PREFIX).items()}, ours.unet, "UNet")
    n += same(
        sv4d2.clip_to_ours(group(sv4d2.CLIP_PREFIX), cfg.clip_layers),
        ours.image_encoder,
        "CLIP",
        skip=("position_ids",),
    )
    enc = {k: v for k, v in group(sv4d2.FRAMES_VAE_PREFIX).items() if k.startswith(("encoder.", "quant_conv."))}
    dec = {f"decoder.{k}": v for k, v in group(sv4d2.DECODER_PREFIX).items()}
    n += same(sv4d2.vae_to_ours({**enc, **dec}, ours.vae), ours.vae, "VAE")
    unused = [
        k
        for k in ref
        if not k.startswith(
            (sv4d2.UNET_PREFIX, sv4d2.CLIP_PREFIX, sv4d2.FRAMES_VAE_PREFIX, sv4d2.VIEW_VAE_PREFIX, sv4d2.DECODER_PREFIX)
        )
    ]
    # What the loader leaves out: the motion-frame encoder (its latents reach no layer of the network).
    assert all(k.startswith("conditioner.embedders.5.") for k in unused), unused[:5]
    return n, sum(v.numel() for v in ours.parameters())


def main(
    reference: Path = typer.Option(Path("../generative-models"), help="Checkout of Stability-AI/generative-models."),
    open_clip: Path = typer.Option(Path("../open_clip"), help="Checkout of mlfoundations/open_clip."),
    steps: int = typer.Option(4, help="Sampler steps for the latent comparison."),
    device: str = typer.Option("cpu", help="cpu or cuda (float32 throughout)."),
    seed: int = typer.Option(0, help="Seed of weights, images and noise."),
) -> None:
    if not (reference / "sgm" / "modules" / "spacetime_attention.py").exists():
        print(f"skipped: no generative-models checkout with SV4D 2.0 at {reference} (pass --reference)")
        return
    if not (open_clip / "src" / "open_clip" / "transformer.py").exists():
        print(f"skipped: no open_clip checkout at {open_clip} (pass --open-clip)")
        return
    import numpy as np
    import torch

    from t2bs.video import sv4d2

    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    import contextlib
    import io
    import logging
    import warnings

    warnings.filterwarnings("ignore")  # the reference's CUDA-autocast and deprecation notices on a CPU run
    logging.disable(logging.WARNING)
    mods = setup_reference(reference.resolve(), open_clip.resolve())
    sampling = mods["sgm.modules.diffusionmodules.sampling"]
    cfg = sv4d2.tiny_config()
    T, V = cfg.frames, cfg.views
    torch.manual_seed(seed)
    with contextlib.redirect_stdout(io.StringIO()):  # its per-embedder "Initialized ..." lines
        engine, denoiser = build_reference(cfg, mods)
    with torch.no_grad():
        for p in engine.parameters():
            p.copy_(torch.randn_like(p) * 0.2)  # non-zero everywhere, mix factors included
    sd = {k: v for k, v in engine.state_dict().items()}
    with tempfile.TemporaryDirectory() as tmp:
        from safetensors.torch import save_file

        save_file({k: v.contiguous() for k, v in sd.items()}, f"{tmp}/{sv4d2.CHECKPOINT_FILE}")
        (Path(tmp) / sv4d2.CONFIG_FILE).write_text(__import__("json").dumps(__import__("dataclasses").asdict(cfg)))
        ours = sv4d2.load_model(tmp, device=device, dtype="float32")
    engine.to(device)
    print(
        f"reference: {reference} ({len(sd)} tensors, {sum(v.numel() for v in sd.values())} weights); "
        f"ours loaded the same file; separate view encoder: {ours.view_vae is not None}"
    )

    g = torch.Generator().manual_seed(seed + 1)
    H = cfg.image_size
    motion = (torch.rand(T, 3, H, H, generator=g) * 2 - 1).to(device)  # the input view's T frames
    views = (torch.rand(V, 3, H, H, generator=g) * 2 - 1).to(device)  # the V views at the first frame
    az = np.deg2rad([35.0, 300.0, 80.0, 200.0][:V])
    polar = np.tile(np.full(V, np.pi / 2), T)
    azim = np.tile(az, T)
    rows = []

    def diff(name, a, b):
        a, b = a.detach().float().cpu(), b.detach().float().cpu()
        assert a.shape == b.shape, (name, a.shape, b.shape)
        rows.append((name, float((a - b).abs().max()), float(b.abs().max())))

    def reference_conditioning(first_pass: bool):
        batch = {
            "cond_frames_without_noise": motion,
            "cond_frames": motion[:, None].repeat(1, V, 1, 1, 1).flatten(0, 1),
            "polar_rad": torch.tensor(polar, device=device).float(),
            "azimuth_rad": torch.tensor(azim, device=device).float(),
            "cond_view": views,
            "cond_motion": motion,
            "num_video_frames": T * V,
        }
        batch_uc = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in batch.items()}
        c, uc = engine.conditioner.get_unconditional_conditioning(
            batch,
            batch_uc=batch_uc,
            force_uc_zero_embeddings=["cond_frames", "cond_frames_without_noise", "cond_view", "cond_motion"],
        )
        if first_pass:  # run_img2vid with cond_mv=False: image_only_indicator 0 zeroes the view latents
            c["cond_view"] = c["cond_view"] * 0
            uc["cond_view"] = uc["cond_view"] * 0
        return c, uc

    def ref_denoiser(indicator):
        extra = {"num_video_frames": T * V, "image_only_indicator": torch.full((2, T * V), indicator, device=device)}
        return lambda x, s, c: denoiser(engine.model, x, s, c, **extra)

    def ref_sampler():
        return sampling.EulerEDMSampler(
            num_steps=steps,
            device=device,
            s_churn=0.0,
            s_tmin=0.0,
            s_tmax=999.0,
            s_noise=1.0,
            verbose=False,
            discretization_config={
                "target": "sgm.modules.diffusionmodules.discretizer.EDMDiscretization",
                "params": {"sigma_min": 0.002, "sigma_max": 700.0, "rho": 7.0},
            },
            guider_config={
                "target": "sgm.modules.diffusionmodules.guiders.LinearPredictionGuider",
                "params": {"max_scale": 2.0, "num_frames": T * V, "additional_cond_keys": ["cond_view", "cond_motion"]},
            },
        )

    h = H // cfg.vae_factor
    t0 = time.perf_counter()
    with torch.no_grad():
        c, uc = reference_conditioning(first_pass=False)
        oc, ouc = ours.conditioning(motion, views, polar, azim)
        for k in ("crossattn", "concat", "vector", "cond_view"):
            diff(f"conditioner cond {k}", oc[k], c[k])
            diff(f"conditioner uncond {k}", ouc[k], uc[k])
        x = torch.randn(T * V, 4, h, h, generator=g).to(device)
        guider = ref_sampler().guider
        for sigma in (0.05, 3.0, 400.0):
            s = torch.full((T * V,), sigma, device=device)
            xx, ss, cc = guider.prepare_inputs(x, s, c, uc)
            ref_out = ref_denoiser(1.0)(xx, ss, cc)
            both = {k: torch.cat([ouc[k], oc[k]]) for k in oc}
            diff(f"denoiser output (sigma {sigma:g})", ours._denoise(xx, ss, both), ref_out)
        noise = torch.randn(T * V, 4, h, h, generator=g).to(device)
        made = []
        for first in (True, False):
            c, uc = reference_conditioning(first_pass=first)
            ref_z = ref_sampler()(ref_denoiser(0.0 if first else 1.0), noise.clone(), cond=c, uc=uc)
            oc, ouc = ours.conditioning(motion, None if first else views, polar, azim)
            z = ours.sample(oc, ouc, noise, sv4d2.SV4D2SamplerConfig(steps=steps))
            what = "first pass (no view images)" if first else "chained pass (view images)"
            diff(f"sampled latents, {what}, {steps} steps", z, ref_z)
            made.append(z)
        ref_img = torch.clamp((engine.first_stage_model.decode(ref_z / cfg.scale_factor) + 1) / 2, 0, 1)
        diff("decoded images (chained pass)", ours.decode_latents(z), ref_img)
    print(
        f"tiny config: {T} frames x {V} views per pass, {H} px, UNet width {cfg.model_channels}; device {device}; "
        f"float32; {time.perf_counter() - t0:.1f} s"
    )
    print(f"{'compared':58s} {'max |ours - ref|':>16s} {'max |ref|':>10s}")
    for name, d, m in rows:
        print(f"{name:58s} {d:16.3e} {m:10.3e}")
    # The view images must matter (else the chained-pass comparison would test nothing new).
    print(
        f"{'(check) ours: chained vs first-pass latents differ by':58s} {float((made[1] - made[0]).abs().max()):16.3e}"
    )
    n, params = full_size_layout(mods)
    print(
        f"published size (sv4d2.yaml, meta device): all {n} weights of UNet, CLIP and VAE map 1:1 with equal shapes "
        f"({params / 1e9:.2f} B parameters)"
    )
    worst = max(d / max(m, 1e-12) for _, d, m in rows)
    print(
        f"worst relative difference: {worst:.2e} ({'EQUAL within float32 tolerance' if worst < 1e-4 else 'DIFFERENT'})"
    )
    if worst >= 1e-4:
        raise SystemExit(1)


if __name__ == "__main__":
    run_command(main)
