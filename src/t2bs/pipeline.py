"""`t2bs create "PROMPT" -o DIR`: every stage, text to rig, resumable, local or on a cluster.

Stages run in order, each through its own subcommand's function so that `create` and the
single-stage commands behave the same: character (+ renders) -> expression videos -> VCDGS per
video (independent jobs: in-process, a process pool or Ray) -> blendshape model -> landmarks ->
report. Every stage skips what is already done for the same inputs and settings, so a re-run
after a crash, a Ctrl-C or a kill -9 redoes only the unfinished job, and a changed prompt list
makes only the new videos and rebuilds the model.
"""

from __future__ import annotations

import inspect
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

from t2bs.errors import UserError
from t2bs.project import Project, read_json, write_json
from t2bs.project import locked

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


def invoke(command, **kwargs):
    """Call a typer command function from Python: given arguments, declared defaults for the rest."""
    args = {}
    for name, param in inspect.signature(command).parameters.items():
        if name in kwargs:
            args[name] = kwargs[name]
            continue
        default = param.default
        if isinstance(default, typer.models.ParameterInfo):
            default = default.default
        if default is ... or default is inspect.Parameter.empty:
            raise TypeError(f"{command.__name__}: argument {name!r} is required")
        args[name] = default
    return command(**args)


@locked("out", "create")  # one run at a time per project (issue 39)
def create_command(
    prompt: str = typer.Argument(..., help="Text describing the character, e.g. \"a cartoon fox with big ears\"."),
    out: Path = typer.Option(..., "-o", "--out", help="Project folder (created, or resumed if it exists)."),
    preset: str = typer.Option("quick", help="quick (CPU minutes) or paper (§4.1 settings, GPU)."),
    prompts: str = typer.Option(None, help="Expression prompts: all, a comma list, or a prompt-list file (default: the preset's)."),
    samples: int = typer.Option(0, help="Videos per prompt (0 = the preset's)."),
    seed: int = typer.Option(0, help="Seed for the character, animation, defects and training."),
    character_backend: str = typer.Option("procedural", "--character-backend", help="procedural, diffusers (Shap-E weights, MIT licence), command or file."),
    mesh: Path = typer.Option(None, help="Bring your own mesh (character backend 'file')."),
    workers: int = typer.Option(1, help="Reconstruction jobs in parallel on this machine (process pool)."),
    ray: str = typer.Option(None, "--ray", help="Run reconstruction jobs on Ray: 'auto', 'local' or host:port."),
    frames: int = typer.Option(0, help="Frames per video (0 = the preset's)."),
    size: int = typer.Option(0, help="Grid frame side in pixels (0 = the preset's)."),
    views: int = typer.Option(0, help="Orbit views (0 = the paper's 15)."),
    defects: str = typer.Option(None, help="Simulated 4D-model defects: clean, mild, paper (default: the preset's)."),
    iterations: int = typer.Option(0, help="VCDGS steps per video (0 = the preset's)."),
    control_points: int = typer.Option(0, help="VCDGS control points (0 = the preset's)."),
    video_backend: str = typer.Option("procedural", "--video-backend", help="procedural (offline animator), "
                                      "cogvideox+sv4d2 (the paper's chain: CogVideoX image-to-video, then SV4D 2.0 "
                                      "for the 15-view grid) or procedural+sv4d2 (the animator's front view into SV4D 2.0)."),
    checkpoints: Path = typer.Option(None, "--checkpoints", help="Folder of the video models' weights: cogvideox/ "
                                     "(THUDM/CogVideoX-5b-I2V, diffusers layout) and sv4d2/ (sv4d2.safetensors from "
                                     "stabilityai/sv4d2.0, Stability AI Community License). See docs/SV4D2.md."),
    video_steps: int = typer.Option(0, help="Denoising steps of the video models (0 = their defaults, 50)."),
) -> None:
    """Text -> animatable blendshape rig: runs every stage and writes DIR/report.md."""
    if video_backend not in VIDEO_BACKENDS:
        raise UserError(f"--video-backend must be one of {', '.join(VIDEO_BACKENDS)}, got {video_backend!r}")
    fixed_backend, four_d = (video_backend.split("+") + [None])[:2]
    if four_d:
        if checkpoints is None:
            raise UserError(f"--video-backend {video_backend} needs --checkpoints DIR (with cogvideox/ and sv4d2/ inside)")
        from t2bs.video.sv4d2 import check_checkpoint

        check_checkpoint(checkpoints / "sv4d2")  # before hours of other stages
        if fixed_backend == "cogvideox":
            from t2bs.video.cogvideox import check_checkpoint as check_cogvideox

            check_cogvideox(checkpoints / "cogvideox")
    if preset not in CREATE_PRESETS:
        raise UserError(f"unknown preset {preset!r}; use one of {', '.join(CREATE_PRESETS)}")
    if workers < 1:
        raise UserError("--workers must be >= 1")
    p = CREATE_PRESETS[preset]
    prompts = prompts or p.prompts
    samples = samples or p.samples
    project = Project(out)
    times: dict[str, float] = {}

    def stage(name: str, fn, **kwargs) -> None:
        print(f"\n== {name} ==", flush=True)
        t0 = time.perf_counter()
        invoke(fn, **kwargs)
        times[name] = round(time.perf_counter() - t0, 2)

    from t2bs.blendshapes.commands import blendshapes_command
    from t2bs.character.commands import character_command
    from t2bs.recon.commands import reconstruct_command
    from t2bs.retarget.commands import landmarks_command
    from t2bs.video.commands import videos_command

    if character_backend == "file" and mesh is None:
        raise UserError("--character-backend file needs --mesh PATH")
    grid = {"frames": frames or p.frames, "size": size or p.size, **({"views": views} if views else {})}
    # A 4D model's grid uses the character's orbit renders: render them at the grid's size.
    render_size = {"size": grid["size"]} if four_d else {}
    stage("character", character_command, prompt=prompt, out=out, backend=character_backend, seed=seed, mesh=mesh, **render_size)
    steps = {"steps": video_steps} if video_steps else {}
    if fixed_backend == "cogvideox":
        stage("videos", videos_command, project_dir=out, prompts=prompts, samples=samples, seed=seed, backend="cogvideox",
              checkpoint=checkpoints / "cogvideox", **grid, **steps)
    else:
        stage("videos", videos_command, project_dir=out, prompts=prompts, samples=samples, defects=defects or p.defects,
              seed=seed, **grid)
    if four_d:
        stage("videos_4d", videos_command, project_dir=out, prompts=prompts, samples=samples, seed=seed, backend="sv4d2",
              checkpoint=checkpoints / "sv4d2", **steps)
    stage("reconstruct", reconstruct_command, project_dir=out, preset_name=p.recon, seed=seed, workers=workers,
          ray=ray, iterations=iterations, control_points=control_points)
    stage("blendshapes", blendshapes_command, project_dir=out, components=p.components)
    stage("landmarks", landmarks_command, project_dir=out, show=True)
    report = write_report(project, prompt, preset, times)
    print(f"\nrig:     {project.path('blendshapes', 'model.glb')}  ({report['blendshapes'].get('components')} shapes)")
    print(f"report:  {project.path('report.md')}")
    print(f"view:    t2bs view {out}")


def write_report(project: Project, prompt: str, preset: str, times: dict[str, float]) -> dict:
    """report.json + report.md: backends, per-stage times, per-video metrics, explained variance."""
    manifest = project.manifest()
    stages = manifest.get("stages", {})
    videos = []
    for recon_dir in sorted(project.path("recon").glob("*")):
        if not (recon_dir / "done.json").exists():
            continue
        metrics = read_json(recon_dir / "metrics.json") if (recon_dir / "metrics.json").exists() else {}
        row = {"video": recon_dir.name, "seconds": metrics.get("seconds"), "perceptual_loss": metrics.get("perceptual_loss")}
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

    lines = [f"# t2bs report: {report['prompt']}", "", f"Preset `{report['preset']}`; total {report['total_seconds']:.0f} s.", "",
             "## Backends", ""]
    ckpts = report.get("checkpoints", {})
    lines += [f"- {stage}: {backend}" + (f" (checkpoints: {', '.join(ckpts[stage])})" if stage in ckpts else "")
              for stage, backend in report["backends"].items()]
    if report.get("motion_source") == "autorig" and report.get("autorig"):
        a = report["autorig"]
        lines += ["", f"Motion source: the **auto rig** (the mesh had no face rig): {len(a['shapes'])} ARKit shapes from "
                  f"{a['landmarks']} landmarks in character/autorig.glb; mouth: {a.get('mouth')}."]
        why: dict[str, list[str]] = {}
        for name, reason in (a.get("missing") or {}).items():
            why.setdefault(reason, []).append(name)
        lines += [f"- missing {', '.join(names)}: {reason}" for reason, names in why.items()]
    lines += ["", "## Stage times (s)", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.1f} |" for k, v in report["stage_seconds"].items()]
    lines += ["", "## Videos", "",
              "Expression: each frame's head motion taken out, over the vertices whose true non-rigid motion exceeds "
              "0.5 % of the diagonal; rigid = the neutral moved by the true head motion (geometry/metrics.py).", "",
              "| video | expression p2p (rigid) | recovered / cosine | p2p moving (static) | NC (static) | seconds | contact sheet |",
              "|---|---|---|---|---|---|---|"]
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
        lines.append(f"Explained variance of the first shapes: {', '.join(f'{x:.3f}' for x in b['explained_variance_first10'])}.")
    if "arkit" in b:
        lines += ["", "## ARKit shapes", "", f"{len(b['arkit'])} of the 52 present: {', '.join(b['arkit']) or 'none'}.",
                  "Absent, and why: blendshapes/arkit.json.", "", "![ARKit shapes](blendshapes/arkit_sheet.png)"]
    lines += ["", "## Opening the rig", "",
              f"- `t2bs view {project.root}`: sliders for the ARKit shapes (grouped), the named shapes and the PCA components.",
              "- Blender: File > Import > glTF 2.0, pick blendshapes/model.glb; the shapes are the mesh's shape keys.",
              "- three.js: `GLTFLoader` loads blendshapes/model.glb; `mesh.morphTargetDictionary` maps the names "
              "(`jawOpen`, `eyeBlinkLeft`, ...) to `mesh.morphTargetInfluences`.",
              f"- VRM (VTubing apps, three-vrm): `t2bs export {project.root} --format vrm --license CC-BY-4.0`.",
              f"- Live Link Face capture: `t2bs retarget {project.root} --driver take.csv`."]
    with atomic_path(project.path("report.md")) as tmp:
        tmp.write_text("\n".join(lines) + "\n")

