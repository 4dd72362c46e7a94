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


def create_command(
    prompt: str = typer.Argument(..., help="Text describing the character, e.g. \"a cartoon fox with big ears\"."),
    out: Path = typer.Option(..., "-o", "--out", help="Project folder (created, or resumed if it exists)."),
    preset: str = typer.Option("quick", help="quick (CPU minutes) or paper (§4.1 settings, GPU)."),
    prompts: str = typer.Option(None, help="Expression prompts: all, a comma list, or a prompt-list file (default: the preset's)."),
    samples: int = typer.Option(0, help="Videos per prompt (0 = the preset's)."),
    seed: int = typer.Option(0, help="Seed for the character, animation, defects and training."),
    character_backend: str = typer.Option("procedural", "--character-backend", help="procedural, diffusers, command or file."),
    mesh: Path = typer.Option(None, help="Bring your own mesh (character backend 'file')."),
    workers: int = typer.Option(1, help="Reconstruction jobs in parallel on this machine (process pool)."),
    ray: str = typer.Option(None, "--ray", help="Run reconstruction jobs on Ray: 'auto', 'local' or host:port."),
    frames: int = typer.Option(0, help="Frames per video (0 = the preset's)."),
    size: int = typer.Option(0, help="Grid frame side in pixels (0 = the preset's)."),
    views: int = typer.Option(0, help="Orbit views (0 = the paper's 15)."),
    defects: str = typer.Option(None, help="Simulated 4D-model defects: clean, mild, paper (default: the preset's)."),
    iterations: int = typer.Option(0, help="VCDGS steps per video (0 = the preset's)."),
    control_points: int = typer.Option(0, help="VCDGS control points (0 = the preset's)."),
) -> None:
    """Text -> animatable blendshape rig: runs every stage and writes DIR/report.md."""
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
    stage("character", character_command, prompt=prompt, out=out, backend=character_backend, seed=seed, mesh=mesh)
    grid = {"frames": frames or p.frames, "size": size or p.size, **({"views": views} if views else {})}
    stage("videos", videos_command, project_dir=out, prompts=prompts, samples=samples, defects=defects or p.defects,
          seed=seed, **grid)
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
    report = {
        "prompt": prompt,
        "preset": preset,
        "backends": {name: info.get("backend") for name, info in stages.items()},
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


def _write_markdown(project: Project, report: dict) -> None:
    from t2bs.project import atomic_path

    lines = [f"# t2bs report: {report['prompt']}", "", f"Preset `{report['preset']}`; total {report['total_seconds']:.0f} s.", "",
             "## Backends", ""]
    lines += [f"- {stage}: {backend}" for stage, backend in report["backends"].items()]
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
    lines += ["", "## Videos", "", "| video | p2p moving (static) | NC (static) | seconds | contact sheet |", "|---|---|---|---|---|"]
    for v in report["videos"]:
        p2p = f"{v['p2p_moving']:.4f} ({v['p2p_moving_static']:.4f})" if v.get("p2p_moving") is not None else "-"
        nc = f"{v['nc']:.4f} ({v['nc_static']:.4f})" if v.get("nc") is not None else "-"
        sheet = f"![{v['video']}]({v['contact_sheet']})" if v.get("contact_sheet") else "-"
        lines.append(f"| {v['video']} | {p2p} | {nc} | {v.get('seconds') or '-'} | {sheet} |")
    b = report["blendshapes"]
    lines += ["", "## Blendshape model", "", f"{b.get('components', 0)} shapes in blendshapes/model.glb."]
    if "explained_variance_first10" in b:
        lines.append(f"Explained variance of the first shapes: {', '.join(f'{x:.3f}' for x in b['explained_variance_first10'])}.")
    with atomic_path(project.path("report.md")) as tmp:
        tmp.write_text("\n".join(lines) + "\n")

