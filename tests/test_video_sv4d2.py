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
    for key in (
        "model.diffusion_model.input_blocks.0.0.weight",
        "model.diffusion_model.input_blocks.1.0.in_layers.0.weight",
        "model.diffusion_model.input_blocks.1.0.time_mix_blocks.in_layers.2.weight",
        "model.diffusion_model.input_blocks.1.1.time_mix_blocks.0.ff_in.net.0.proj.weight",
        "model.diffusion_model.input_blocks.1.1.motion_blocks.0.attn2.to_k.weight",
        "model.diffusion_model.input_blocks.1.1.time_mix_time_embed.0.weight",
        "model.diffusion_model.input_blocks.2.0.op.weight",
        "model.diffusion_model.label_emb.0.0.weight",
        "conditioner.embedders.0.open_clip.model.visual.transformer.resblocks.0.attn.in_proj_weight",
        "conditioner.embedders.1.encoder.encoder.down.0.block.0.conv1.weight",
        "conditioner.embedders.4.encoder.quant_conv.weight",
        "first_stage_model.decoder.mid.attn_1.q.weight",
    ):
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
    (bad / sv4d2.CONFIG_FILE).write_text(
        json.dumps({**cfg, "model_channels": 64, "sigma_embed_dim": 64, "camera_embed_dim": 96})
    )
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
    assert torch.equal(uc["vector"][:, cfg.sigma_embed_dim :], c["vector"][:, cfg.sigma_embed_dim :])
    z = model.sample(c, uc, noise, steps)
    assert torch.equal(z, model.sample(c, uc, noise, steps))
    c0, uc0 = model.conditioning(motion, None, polar, azim)
    assert float(c0["cond_view"].abs().max()) == 0
    c2, uc2 = model.conditioning(motion, views, polar, np.tile([1.0, 2.0], T))
    for other in (model.sample(c0, uc0, noise, steps), model.sample(c2, uc2, noise, steps)):
        assert float((other - z).abs().max()) > 1e-3  # the view images and the cameras both matter
    images = model.decode_latents(z)
    assert images.shape == (T * V, 3, H, H) and float(images.min()) >= 0 and float(images.max()) <= 1
    # CPU offload (parts moved to the execution device only while they run) gives the same numbers;
    # a bf16 UNet gives nearly the same (the sampler's state stays float32).
    off = sv4d2.load_model(tiny_ckpt, device="cpu", dtype="float32", offload=True)
    assert off.execution_device is not None and torch.equal(off.sample(c, uc, noise, steps), z)
    half = sv4d2.load_model(tiny_ckpt, device="cpu", dtype="bfloat16")
    assert next(half.unet.parameters()).dtype == torch.bfloat16 and next(half.vae.parameters()).dtype == torch.float32
    zh = half.sample(c, uc, noise, steps)
    assert zh.dtype == torch.float32 and float((zh - z).abs().max()) < 0.1 * float(z.abs().max())
    with pytest.raises(UserError, match=f"makes {T} frames per pass"):
        model.conditioning(motion[:1], views, polar, azim)


def test_plan_covers_the_grid_with_anchored_passes():
    passes = sv4d2.plan_passes(21, [0, 1, 2, 3, 4, 5, 6, 8, 9, 10, 11, 12, 13, 14], 12, 4)
    assert [p.frames[0] for p in passes[:2]] == [0, 9] and passes[1].frames[-1] == 20
    assert [p.views for p in passes[::2]] == [[0, 1, 2, 3], [4, 5, 6, 8], [9, 10, 11, 12], [11, 12, 13, 14]]
    covered = {(v, t) for p in passes for v in p.views for t in p.frames}
    assert covered == {(v, t) for v in [0, 1, 2, 3, 4, 5, 6, 8, 9, 10, 11, 12, 13, 14] for t in range(21)}
    for p in passes:  # every pass starts from a frame already made (the renders at 0, else an earlier pass)
        assert p.anchor == p.frames[0]
    long = sv4d2.plan_passes(40, [0, 1, 2, 3], 12, 4)
    assert [p.frames[0] for p in long] == [0, 11, 22, 28]
    with pytest.raises(UserError, match="12 frames per pass: the input video has 9 frames"):
        sv4d2.plan_passes(9, [0, 1, 2, 3], 12, 4)


def _tiny_project(tmp_path, frames: int = 5):
    """A rendered sphere (5 orbit views, 32 px, unlit) with a one-view fixed-view video for 'blinking'."""
    from test_recon import sphere_mesh

    from t2bs.character.render_stage import RenderConfig, render_project
    from t2bs.geometry.camera import frontal_camera
    from t2bs.project import Project
    from t2bs.video.cogvideox import fixed_view_grid
    from t2bs.video.grid import read_rgb, save_grid

    project = Project(tmp_path / "proj")
    render_project(sphere_mesh(1), project.root, {"backend": "file"}, RenderConfig(size=32, views=5, shading="unlit"))
    front = read_rgb(project.path("renders", "front.png"))
    rng = np.random.default_rng(0)
    video = np.stack([np.roll(front, t, axis=1) for t in range(frames)])  # the "expression": a slide
    video[1:, :2, :2] = rng.integers(0, 255, (frames - 1, 2, 2, 3))
    grid = fixed_view_grid(video, frontal_camera(32), 8.0, {"expression": "blinking", "prompt": "p"})
    save_grid(grid, project.path("videos", "blinking-s0"))
    return project, video


def test_videos_sv4d2_makes_the_grid_that_reconstruct_runs_on(tmp_path, tiny_ckpt, capsys):
    from t2bs.geometry.camera import orbit_cameras
    from t2bs.recon.stage import reconstruct_video
    from t2bs.recon.config import preset
    from t2bs.video.stage import VideosConfig, run
    from t2bs.video.grid import load_grid, read_rgb

    project, video = _tiny_project(tmp_path)
    kw = dict(
        prompts="blinking",
        samples=1,
        defects="mild",
        frames=16,
        size=512,
        views=15,
        seed=0,
        shading=None,
        backend="sv4d2",
        checkpoint=tiny_ckpt,
        steps=2,
        video=None,
        dtype="float32",
        offload=False,
        import_grid=None,
        expression=None,
        sample=0,
    )
    run(project.root, VideosConfig(**kw))
    assert "1 made, 0 up to date, 5 views each" in capsys.readouterr().out
    vdir = project.path("videos", "blinking-s0")
    g = load_grid(vdir)
    assert g.backend == "sv4d2" and g.frames.shape == (5, 5, 32, 32, 3) and g.canonical_view == 2
    assert np.array_equal(g.frames[2], video)  # the fixed-view video is the canonical view, untouched
    for v in range(5):  # frame 0 of every view: the static mesh's orbit render
        assert np.array_equal(g.frames[v, 0], read_rgb(project.path("renders", "orbit", f"view{v:02d}.png")))
    assert np.allclose(g.times, np.arange(5) / 8.0)
    for cam, ref in zip(g.cameras, orbit_cameras(5, size=32)):
        assert np.allclose(cam.world_to_camera, ref.world_to_camera) and np.allclose(cam.K, ref.K)
    assert g.masks is not None and g.masks.shape == (5, 5, 32, 32) and g.masks[2, 0].any() and not g.masks[2, 0].all()
    assert g.meta["grid_config"]["shading"] == "unlit" and g.meta["source_backend"] == "cogvideox"
    # 4 novel views in groups of 2, 5 frames in windows of 3 overlapping by one: 2 x 2 passes.
    assert [(p["frames"], p["views"]) for p in g.meta["passes"]] == [
        ([0, 2], [0, 1]),
        ([2, 4], [0, 1]),
        ([0, 2], [3, 4]),
        ([2, 4], [3, 4]),
    ]
    novel = g.frames[[0, 1, 3, 4], 1:]
    assert novel.std() > 1.0  # the model drew them (random weights: noise, but not a constant)
    stage = project.manifest()["stages"]["videos"]
    assert stage["backend"] == "sv4d2" and stage["checkpoint"].endswith("sv4d2.safetensors")
    run(project.root, VideosConfig(**kw))  # unchanged: skipped (its input is now the grid's canonical view)
    assert "0 made, 1 up to date" in capsys.readouterr().out
    cfg = preset(
        "quick",
        face_gaussians=False,
        silhouette_band=0,
        mask_weight=0.5,
        resolution=32,
        static_iters=3,
        iterations=4,
        global_iters=2,
        num_control_points=8,
        checkpoint_every=5,
        perceptual="none",
    )
    out, ran = reconstruct_video(project, vdir, cfg, progress=False, preview=False)
    verts = np.load(out / "vertices.npy")
    assert ran and verts.shape[0] == 5 and np.isfinite(verts).all()


def test_videos_sv4d2_errors_are_one_line(tmp_path, tiny_ckpt):
    from t2bs.video.stage import VideosConfig, run

    project, _ = _tiny_project(tmp_path, frames=2)
    kw = dict(
        prompts="blinking",
        samples=1,
        defects="mild",
        frames=16,
        size=512,
        views=15,
        seed=0,
        shading=None,
        backend="sv4d2",
        checkpoint=tmp_path / "nowhere",
        steps=2,
        video=None,
        dtype="float32",
        offload=False,
        import_grid=None,
        expression=None,
        sample=0,
    )
    with pytest.raises(MissingCheckpointError, match="sv4d2.safetensors"):
        run(project.root, VideosConfig(**kw))
    with pytest.raises(UserError, match="3 frames per pass: the input video has 2 frames"):
        run(project.root, VideosConfig(**{**kw, "checkpoint": tiny_ckpt}))
    with pytest.raises(UserError, match="no fixed-view video for smiling-s0"):
        run(project.root, VideosConfig(**{**kw, "checkpoint": tiny_ckpt, "prompts": "smiling"}))
    with pytest.raises(UserError, match="--video needs --expression"):
        run(project.root, VideosConfig(**{**kw, "checkpoint": tiny_ckpt, "video": tmp_path / "v.mp4"}))


def test_cli_help_names_backend_files_and_licence_and_import_asks_for_shading(tmp_path):
    import os
    import subprocess
    import sys

    env = {**os.environ, "COLUMNS": "200", "PYTHONPATH": os.pathsep.join(sys.path)}
    out = subprocess.run(
        [sys.executable, "-m", "t2bs.cli", "videos", "--help"], capture_output=True, text=True, env=env
    )
    text = " ".join(out.stdout.replace("│", " ").split())
    assert out.returncode == 0
    for words in ("sv4d2", "sv4d2.safetensors", "stabilityai/sv4d2.0", "Stability AI Community License", "--offload"):
        assert words in text, words
    (tmp_path / "grid.png").write_bytes(b"")
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "t2bs.cli",
            "videos",
            str(tmp_path / "p"),
            "--import-grid",
            str(tmp_path / "grid.png"),
            "--expression",
            "smiling",
        ],
        capture_output=True,
        text=True,
        env=env,
    )
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0
    assert bad.stderr.startswith("error: --import-grid needs --shading unlit or lambert")


def test_create_runs_the_chain_and_reports_backends_and_checkpoints(tmp_path, tiny_ckpt, monkeypatch, capsys):
    """`t2bs create --video-backend procedural+sv4d2`: the video stages for real, the later stages
    (tested on their own, minutes on a CPU) replaced by recorders."""
    import shutil

    from test_recon import sphere_mesh

    import t2bs.blendshapes.stage as bc
    import t2bs.recon.stage as rc
    import t2bs.retarget.landmarks_stage as lc
    from t2bs.geometry.io import save_mesh
    from t2bs.pipeline import CreateConfig, create
    from t2bs.video.grid import load_grid

    called = []

    def recorder(name):
        def run(project, config):
            called.append((name, type(config).__name__))

        return run

    monkeypatch.setattr(rc, "run", recorder("reconstruct"))
    monkeypatch.setattr(bc, "run", recorder("blendshapes"))
    monkeypatch.setattr(lc, "run", recorder("landmarks"))
    sphere = sphere_mesh(1)
    # A rig the offline animator can play (without one the video stage would auto-rig it, and a plain sphere has
    # no face to find): its lower half drops as "jaw_open".
    low = sphere.vertices[:, 1] < 0
    sphere.morph_targets = {"jaw_open": np.where(low[:, None], [0.0, -0.05, 0.0], 0.0).astype(np.float32)}
    save_mesh(sphere, tmp_path / "sphere.glb")
    shutil.copytree(tiny_ckpt, tmp_path / "ckpts" / "sv4d2")
    out = tmp_path / "out"
    kw = dict(
        prompt="a sphere",
        character_backend="file",
        mesh=tmp_path / "sphere.glb",
        prompts="blinking",
        frames=5,
        size=32,
        video_backend="procedural+sv4d2",
        checkpoints=tmp_path / "ckpts",
        video_steps=2,
    )
    create(out, CreateConfig(**kw))
    assert called == [
        ("reconstruct", "ReconstructConfig"),
        ("blendshapes", "BlendshapesConfig"),
        ("landmarks", "LandmarksConfig"),
    ]
    g = load_grid(out / "videos" / "blinking-s0")
    assert g.backend == "sv4d2" and g.frames.shape == (15, 5, 32, 32, 3) and g.gt_vertices is not None
    report = json.loads((out / "report.json").read_text())
    assert report["backends"]["videos"] == "procedural+sv4d2"
    assert report["checkpoints"]["videos"] == [str(tmp_path / "ckpts" / "sv4d2" / "sv4d2.safetensors")]
    assert "videos: procedural+sv4d2 (checkpoints: " in (out / "report.md").read_text()
    capsys.readouterr()
    create(out, CreateConfig(**kw))  # a re-run redoes neither the fixed-view video nor the 4D grid
    text = capsys.readouterr().out
    assert "videos: 0 made, 1 up to date" in text and "videos (sv4d2): 0 made, 1 up to date" in text
    with pytest.raises(MissingCheckpointError, match="cogvideox"):
        create(out, CreateConfig(**{**kw, "video_backend": "cogvideox+sv4d2"}))
    with pytest.raises(UserError, match="--video-backend must be one of"):
        create(out, CreateConfig(**{**kw, "video_backend": "sv4d"}))


def test_videos_sv4d2_from_a_video_file_keeps_its_frame_rate(tmp_path, tiny_ckpt):
    import imageio.v2 as iio

    from t2bs.video.stage import VideosConfig, run
    from t2bs.video.grid import load_grid

    project, video = _tiny_project(tmp_path)
    wide = np.pad(video, ((0, 0), (0, 0), (8, 8), (0, 0)), constant_values=255)  # 48 x 32: cropped to the square
    iio.mimwrite(tmp_path / "clip.mp4", list(wide), fps=10, macro_block_size=1)
    run(
        project.root,
        VideosConfig(
            prompts="blinking",
            samples=1,
            defects="mild",
            frames=16,
            size=512,
            views=15,
            seed=0,
            shading=None,
            backend="sv4d2",
            checkpoint=tiny_ckpt,
            steps=1,
            video=tmp_path / "clip.mp4",
            dtype="float32",
            offload=False,
            import_grid=None,
            expression="raising the eyebrows",
            sample=1,
        ),
    )
    g = load_grid(project.path("videos", "raising-the-eyebrows-s1"))
    assert g.frames.shape == (5, 5, 32, 32, 3) and np.allclose(g.times, np.arange(5) / 10.0)
    assert np.abs(g.frames[2].astype(int) - video).mean() < 8  # the clip (lossy mp4), centre-cropped
    assert project.manifest()["stages"]["videos"]["fixed_view_stage"]["backend"] == "file"
