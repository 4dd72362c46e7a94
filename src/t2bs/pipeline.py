"""`create`: every stage, text (or a mesh) to rig, resumable, local or on a cluster; `t2bs create "PROMPT" -o DIR`.

The stages run in order through their library functions (``run(project, config)``), so `create` and the
single-stage commands behave the same: character (+ renders) -> expression videos -> VCDGS per video (independent
jobs: in-process, a process pool or Ray) -> blendshape model -> landmarks -> report. Every stage skips what is
already done for the same inputs and settings, so a re-run after a crash, a Ctrl-C or a kill -9 redoes only the
unfinished job, and a changed prompt list makes only the new videos and rebuilds the model.

    from t2bs.pipeline import CreateConfig, create
    create("runs/fox", CreateConfig(prompt="a cartoon fox with big ears", preset="quick"))
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.project import Project, project_lock, read_json, write_json

# The quick preset's default prompt subset: the expressions that move the most distinct regions
# (eyes, jaw, mouth corners), so the blendshape model spans them within the CPU time budget.
QUICK_PROMPTS = "blinking,opening the mouth extremely wide,smiling"


@dataclass
class CreatePreset:
    prompts: str  # expression prompts ("all" or a comma list)
    samples: int  # videos per prompt (paper: 3)
    frames: int  # frames per video
    size: int  # grid frame side, pixels
    defects: str  # simulated 4D-model defects on side views: clean, mild, paper
    recon: str  # VCDGS preset name (t2bs.recon.config)
    components: int  # blendshapes kept (paper: 100)


CREATE_PRESETS = {
    # CPU minutes: 3 videos of 16 frames at 128 px, 15 views.
    "quick": CreatePreset(QUICK_PROMPTS, 1, 16, 128, "mild", "quick", 100),
    # The paper's setting (§4.1): 20 prompts x 3 samples at 512 px; needs a GPU for VCDGS.
    "paper": CreatePreset("all", 3, 16, 512, "mild", "paper", 100),
}


# The expression-video chains `create` runs: the fixed-view video's backend [+ the 4D model's].
VIDEO_BACKENDS = ("procedural", "cogvideox+sv4d2", "procedural+sv4d2")


@dataclass
class CreateConfig:
    prompt: str  # text describing the character, e.g. "a cartoon fox with big ears"
    preset: str = "quick"  # quick (CPU minutes) | paper (§4.1 settings, GPU): the defaults of the fields below
    prompts: str | None = None  # expression prompts: all, a comma list or a prompt-list file (None: the preset's)
    samples: int = 0  # videos per prompt (0 = the preset's)
    seed: int = 0  # seed of the character, animation, defects and training
    character_backend: str = "procedural"  # procedural | diffusers (Shap-E) | command | file
    mesh: Path | None = None  # bring your own mesh (character backend "file")
    workers: int = 1  # reconstruction jobs in parallel on this machine (process pool)
    ray: str | None = None  # run reconstruction jobs on Ray: auto | local | host:port
    frames: int = 0  # frames per video (0 = the preset's)
    size: int = 0  # grid frame side in pixels (0 = the preset's)
    views: int = 0  # orbit views (0 = the paper's 15)
    defects: str | None = None  # simulated 4D-model defects: clean | mild | paper (None: the preset's)
    iterations: int = 0  # VCDGS steps per video (0 = the preset's)
    control_points: int = 0  # VCDGS control points (0 = the preset's)
    video_backend: str = "procedural"  # procedural | cogvideox+sv4d2 (the paper's chain) | procedural+sv4d2
    checkpoints: Path | None = None  # folder with cogvideox/ and sv4d2/ weights (the sv4d2 chains)
    video_steps: int = 0  # denoising steps of the video models (0 = their defaults, 50)


@dataclass
class CreateResult:
    rig: Path  # DIR/blendshapes/model.glb
    report: Path  # DIR/report.md
    components: int | None  # shapes in the rig
    stage_seconds: dict = field(default_factory=dict)  # wall seconds per stage of this run


def create(project: Project | str | os.PathLike, config: CreateConfig) -> CreateResult:
    """Text (or a mesh) -> animatable blendshape rig: runs every stage on one project folder.

    Writes everything the stages write (docs/ARCHITECTURE.md, "The project folder"): character/mesh.glb and its
    renders, videos/<id>/ grids, recon/<id>/vertices.npy [T, N, 3], blendshapes/model.npz + model.glb (the rig,
    with ARKit-named shapes where the landmarks allow), landmarks/, and last report.json + report.md (backends,
    stage seconds, per-video metrics). Resumable: finished work is skipped. Holds the project lock. Raises
    UserError for an unknown preset or video backend, a missing checkpoint folder (checked before any stage runs),
    or any stage's input error."""
    from t2bs.blendshapes import stage as blendshapes_stage
    from t2bs.character import stage as character_stage
    from t2bs.recon import stage as recon_stage
    from t2bs.retarget import landmarks_stage
    from t2bs.video import stage as video_stage

    c = config
    if c.video_backend not in VIDEO_BACKENDS:
        raise UserError(f"--video-backend must be one of {', '.join(VIDEO_BACKENDS)}, got {c.video_backend!r}")
    fixed_backend, four_d = (c.video_backend.split("+") + [None])[:2]
    if four_d:
        if c.checkpoints is None:
            raise UserError(
                f"--video-backend {c.video_backend} needs --checkpoints DIR (with cogvideox/ and sv4d2/ inside)"
            )
        from t2bs.video.sv4d2 import check_checkpoint

        check_checkpoint(Path(c.checkpoints) / "sv4d2")  # before hours of other stages
        if fixed_backend == "cogvideox":
            from t2bs.video.cogvideox import check_checkpoint as check_cogvideox

            check_cogvideox(Path(c.checkpoints) / "cogvideox")
    if c.preset not in CREATE_PRESETS:
        raise UserError(f"unknown preset {c.preset!r}; use one of {', '.join(CREATE_PRESETS)}")
    if c.workers < 1:
        raise UserError("--workers must be >= 1")
    if c.character_backend == "file" and c.mesh is None:
        raise UserError("--character-backend file needs --mesh PATH")
    p = CREATE_PRESETS[c.preset]
    prompts, samples = c.prompts or p.prompts, c.samples or p.samples
    project = project if isinstance(project, Project) else Project(project)
    times: dict[str, float] = {}

    def stage(name: str, fn, *args) -> None:
        print(f"\n== {name} ==", flush=True)
        t0 = time.perf_counter()
        fn(*args)
        times[name] = round(time.perf_counter() - t0, 2)

    with project_lock(project.root, "create"):
        grid = {"frames": c.frames or p.frames, "size": c.size or p.size, **({"views": c.views} if c.views else {})}
        # A 4D model's grid uses the character's orbit renders: render them at the grid's size.
        render_size = {"size": grid["size"]} if four_d else {}
        stage(
            "character",
            character_stage.run,
            project,
            character_stage.CharacterConfig(
                prompt=c.prompt, backend=c.character_backend, seed=c.seed, mesh=c.mesh, **render_size
            ),
        )
        steps = {"steps": c.video_steps} if c.video_steps else {}
        if fixed_backend == "cogvideox":
            videos = video_stage.VideosConfig(
                prompts=prompts,
                samples=samples,
                seed=c.seed,
                backend="cogvideox",
                checkpoint=Path(c.checkpoints) / "cogvideox",
                **grid,
                **steps,
            )
        else:
            videos = video_stage.VideosConfig(
                prompts=prompts, samples=samples, defects=c.defects or p.defects, seed=c.seed, **grid
            )
        stage("videos", video_stage.run, project, videos)
        if four_d:
            stage(
                "videos_4d",
                video_stage.run,
                project,
                video_stage.VideosConfig(
                    prompts=prompts,
                    samples=samples,
                    seed=c.seed,
                    backend="sv4d2",
                    checkpoint=Path(c.checkpoints) / "sv4d2",
                    **steps,
                ),
            )
        stage(
            "reconstruct",
            recon_stage.run,
            project,
            recon_stage.ReconstructConfig(
                preset_name=p.recon,
                seed=c.seed,
                workers=c.workers,
                ray=c.ray,
                iterations=c.iterations,
                control_points=c.control_points,
            ),
        )
        stage(
            "blendshapes", blendshapes_stage.run, project, blendshapes_stage.BlendshapesConfig(components=p.components)
        )
        stage("landmarks", landmarks_stage.run, project, landmarks_stage.LandmarksConfig(show=True))
        report = write_report(project, c.prompt, c.preset, times)
    rig = project.path("blendshapes", "model.glb")
    print(f"\nrig:     {rig}  ({report['blendshapes'].get('components')} shapes)")
    print(f"report:  {project.path('report.md')}")
    print(f"view:    t2bs view {project.root}")
    return CreateResult(rig, project.path("report.md"), report["blendshapes"].get("components"), times)


def write_report(project: Project, prompt: str, preset: str, times: dict[str, float]) -> dict:
    """report.json + report.md: backends, per-stage times, per-video metrics, explained variance."""
    manifest = project.manifest()
    stages = manifest.get("stages", {})
    videos = []
    for recon_dir in sorted(project.path("recon").glob("*")):
        if not (recon_dir / "done.json").exists():
            continue
        metrics = read_json(recon_dir / "metrics.json") if (recon_dir / "metrics.json").exists() else {}
        row = {
            "video": recon_dir.name,
            "seconds": metrics.get("seconds"),
            "perceptual_loss": metrics.get("perceptual_loss"),
        }
        geometry = metrics.get("geometry") or {}
        static = metrics.get("geometry_static") or {}
        expression = metrics.get("expression") or {}
        for key in ("expr_p2p", "expr_rigid", "expr_ratio", "recovered", "cosine"):
            if key in expression:
                row[key] = expression[key]
        for key in ("p2p_all", "p2p_moving", "nc"):
            if key in geometry:
                row[key] = geometry[key]
                row[f"{key}_static"] = static.get(key)
        sheet = project.path("videos", recon_dir.name, "contact_sheet.png")
        row["contact_sheet"] = str(sheet.relative_to(project.root)) if sheet.exists() else None
        row["preview"] = "recon/" + recon_dir.name + "/preview.mp4" if (recon_dir / "preview.mp4").exists() else None
        videos.append(row)
    blend = {}
    model_path = project.path("blendshapes", "model.npz")
    if model_path.exists():
        with np.load(model_path, allow_pickle=False) as data:
            blend["components"] = int(data["basis"].shape[0])
            if "explained_variance" in data:  # fraction of the captures' squared offsets per shape
                ratio = np.asarray(data["explained_variance"], float)
                blend["explained_variance_first10"] = [round(float(x), 4) for x in ratio[:10]]
                blend["explained_variance_total"] = round(float(ratio.sum()), 6)
    arkit_path = project.path("blendshapes", "arkit.json")
    if arkit_path.exists():
        arkit = read_json(arkit_path)
        blend["arkit"] = arkit.get("names", [])
        blend["arkit_absent"] = {n: r.get("why") for n, r in arkit.get("report", {}).items() if not r.get("present")}
    report = {
        "prompt": prompt,
        "preset": preset,
        "backends": {name: _backend_chain(info) for name, info in stages.items()},
        "checkpoints": {name: c for name, c in ((n, _checkpoints(info)) for n, info in stages.items()) if c},
        "stage_seconds": times,
        "total_seconds": round(sum(times.values()), 2),
        "videos": videos,
        "blendshapes": blend,
        "versions": manifest.get("versions", {}),
        "motion_source": stages.get("videos", {}).get("motion_source", "rig"),
        "autorig": stages.get("videos", {}).get("autorig"),
    }
    write_json(project.path("report.json"), report)
    _write_markdown(project, report)
    return report


def _backend_chain(info: dict) -> str | None:
    """A stage's backend; for a 4D video stage, the fixed-view backend first (cogvideox+sv4d2)."""
    first = (info.get("fixed_view_stage") or {}).get("backend")
    return f"{first}+{info.get('backend')}" if first else info.get("backend")


def _checkpoints(info: dict) -> list[str]:
    """The checkpoints a stage used (the fixed-view model's first)."""
    found = [(info.get("fixed_view_stage") or {}).get("checkpoint"), info.get("checkpoint")]
    return [str(c) for c in found if c]


def _write_markdown(project: Project, report: dict) -> None:
    from t2bs.project import atomic_path

    lines = [
        f"# t2bs report: {report['prompt']}",
        "",
        f"Preset `{report['preset']}`; total {report['total_seconds']:.0f} s.",
        "",
        "## Backends",
        "",
    ]
    ckpts = report.get("checkpoints", {})
    lines += [
        f"- {stage}: {backend}" + (f" (checkpoints: {', '.join(ckpts[stage])})" if stage in ckpts else "")
        for stage, backend in report["backends"].items()
    ]
    if report.get("motion_source") == "autorig" and report.get("autorig"):
        a = report["autorig"]
        lines += [
            "",
            f"Motion source: the **auto rig** (the mesh had no face rig): {len(a['shapes'])} ARKit shapes from "
            f"{a['landmarks']} landmarks in character/autorig.glb; mouth: {a.get('mouth')}.",
        ]
        why: dict[str, list[str]] = {}
        for name, reason in (a.get("missing") or {}).items():
            why.setdefault(reason, []).append(name)
        lines += [f"- missing {', '.join(names)}: {reason}" for reason, names in why.items()]
    lines += ["", "## Stage times (s)", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.1f} |" for k, v in report["stage_seconds"].items()]
    lines += [
        "",
        "## Videos",
        "",
        "Expression: each frame's head motion taken out, over the vertices whose true non-rigid motion exceeds "
        "0.5 % of the diagonal; rigid = the neutral moved by the true head motion (geometry/metrics.py).",
        "",
        "| video | expression p2p (rigid) | recovered / cosine | p2p moving (static) | NC (static) | seconds | contact sheet |",
        "|---|---|---|---|---|---|---|",
    ]
    for v in report["videos"]:
        expr = f"{v['expr_p2p']:.4f} ({v['expr_rigid']:.4f})" if v.get("expr_p2p") is not None else "-"
        rec = f"{v['recovered']:.2f} / {v['cosine']:.2f}" if v.get("recovered") is not None else "-"
        p2p = f"{v['p2p_moving']:.4f} ({v['p2p_moving_static']:.4f})" if v.get("p2p_moving") is not None else "-"
        nc = f"{v['nc']:.4f} ({v['nc_static']:.4f})" if v.get("nc") is not None else "-"
        sheet = f"![{v['video']}]({v['contact_sheet']})" if v.get("contact_sheet") else "-"
        lines.append(f"| {v['video']} | {expr} | {rec} | {p2p} | {nc} | {v.get('seconds') or '-'} | {sheet} |")
    b = report["blendshapes"]
    lines += ["", "## Blendshape model", "", f"{b.get('components', 0)} shapes in blendshapes/model.glb."]
    if "explained_variance_first10" in b:
        lines.append(
            f"Explained variance of the first shapes: {', '.join(f'{x:.3f}' for x in b['explained_variance_first10'])}."
        )
    if "arkit" in b:
        lines += [
            "",
            "## ARKit shapes",
            "",
            f"{len(b['arkit'])} of the 52 present: {', '.join(b['arkit']) or 'none'}.",
            "Absent, and why: blendshapes/arkit.json.",
            "",
            "![ARKit shapes](blendshapes/arkit_sheet.png)",
        ]
    lines += [
        "",
        "## Opening the rig",
        "",
        f"- `t2bs view {project.root}`: sliders for the ARKit shapes (grouped), the named shapes and the PCA components.",
        "- Blender: File > Import > glTF 2.0, pick blendshapes/model.glb; the shapes are the mesh's shape keys.",
        "- three.js: `GLTFLoader` loads blendshapes/model.glb; `mesh.morphTargetDictionary` maps the names "
        "(`jawOpen`, `eyeBlinkLeft`, ...) to `mesh.morphTargetInfluences`.",
        f"- VRM (VTubing apps, three-vrm): `t2bs export {project.root} --format vrm --license CC-BY-4.0`.",
        f"- Live Link Face capture: `t2bs retarget {project.root} --driver take.csv`.",
    ]
    with atomic_path(project.path("report.md")) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
