"""Does an expression survive VCDGS? Input | trained Gaussians | extracted mesh | ground truth at the peak frames.

    python3 benchmarks/expression_view.py PROJECT [VIDEO ...] [--size 256] [--crop]

For each finished reconstruction (``PROJECT/recon/<video>/`` with state.pt; all of them when no VIDEO is named),
the frames where the expression peaks (largest non-rigid motion with each frame's head motion taken out: of the
ground truth when the grid has it, else of the reconstruction) are shown at the canonical view, one row each:
the input image, the trained Gaussians rendered at that (view, time) without RefineMLP, the extracted mesh, and the
true mesh (when known). ``--crop`` zooms on the region that moves. Writes ``PROJECT/recon/<video>/expression_view.png``
and prints one JSON line per video with the files and the expression metrics where the grid has ground truth.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402
import typer  # noqa: E402

from t2bs.cli.exits import run_command
from t2bs.errors import UserError  # noqa: E402


def peak_frames(displacements: np.ndarray, count: int) -> list[int]:
    """The ``count`` frames of non-rigid ``displacements`` [T, N, 3] with the largest mean motion, in time order."""
    disp = np.linalg.norm(displacements, axis=-1).mean(1)  # [T]
    return sorted(int(t) for t in np.argsort(disp)[::-1][:count])


def _crop_box(
    rest: np.ndarray, displacements: np.ndarray, camera, size: int, margin: float = 0.5
) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) pixels around the vertices whose non-rigid motion ``displacements`` [T, N, 3] exceeds 0.5 % of
    the diagonal, a square."""
    from t2bs.geometry.mesh import bbox_diagonal

    moving = np.linalg.norm(displacements, axis=-1).max(0) > 0.005 * bbox_diagonal(rest)
    if not moving.any():
        return 0, 0, size, size
    uv, _ = camera.project(rest[moving])
    lo, hi = uv.min(0), uv.max(0)
    half = max(float((hi - lo).max()) * (0.5 + margin), 12.0)
    cx, cy = (lo + hi) / 2
    x0, y0 = int(max(cx - half, 0)), int(max(cy - half, 0))
    return x0, y0, int(min(cx + half, size)), int(min(cy + half, size))


def view_video(project_dir: Path, video: str, size: int, peaks: int, crop: bool) -> dict:
    import torch
    from PIL import Image

    from t2bs.geometry.metrics import expression_metrics
    from t2bs.geometry.rigid import nonrigid_displacements
    from t2bs.project import Project, atomic_path
    from t2bs.recon.gaussians import camera_tensors
    from t2bs.recon.images import resize_stack
    from t2bs.recon.vcdgs import load_trained_model, render_model
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.grid import load_grid

    project = Project(project_dir)
    out_dir = project.path("recon", video)
    mesh = project.load_character()
    grid = load_grid(project.path("videos", video))
    verts = np.load(out_dir / "vertices.npy")
    model, cfg = load_trained_model(out_dir / "state.pt")
    gt = grid.gt_vertices
    # The expression (each frame's head motion taken out) of the truth where known, else of the reconstruction.
    disp = nonrigid_displacements(mesh.vertices, gt if gt is not None else verts)[0]  # [T, N, 3]
    frames = peak_frames(disp, peaks)
    c = grid.canonical_view
    cam = grid.cameras[c].resized(size, size)
    shading = str((grid.meta.get("grid_config") or {}).get("shading", "lambert"))
    shading = shading if shading in ("unlit", "lambert") else "lambert"
    box = _crop_box(mesh.vertices, disp, cam, size) if crop else (0, 0, size, size)
    inputs = resize_stack(grid.frames[c], (size, size)).numpy()  # [T, size, size, 3]
    vm, ks = camera_tensors([cam])
    rows = []
    with MeshRenderer() as renderer, torch.no_grad():
        for t in frames:
            out = model(torch.tensor([c]), torch.tensor([t]), refine=False)
            splat = render_model(model, out["splats"], vm, ks, size, size)["rgb"][0].numpy()
            tiles = [inputs[t], splat, renderer.render(mesh, cam, vertices=verts[t], shading=shading).rgb]
            if gt is not None:
                tiles.append(renderer.render(mesh, cam, vertices=gt[t], shading=shading).rgb)
            x0, y0, x1, y1 = box
            tiles = [
                np.asarray(
                    Image.fromarray((np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)[y0:y1, x0:x1]).resize((size, size))
                )
                for x in tiles
            ]
            rows.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(rows, axis=0)
    path = out_dir / "expression_view.png"
    with atomic_path(path) as tmp:
        Image.fromarray(sheet).save(tmp, format="PNG")
    info = {
        "video": video,
        "file": str(path),
        "frames": frames,
        "columns": ["input", "trained Gaussians", "extracted mesh"] + (["ground truth"] if gt is not None else []),
    }
    if gt is not None:
        info["expression"] = {k: round(v, 5) for k, v in expression_metrics(verts, gt, mesh.vertices).items()}
    return info


def main(
    project_dir: Path = typer.Argument(
        ..., help="Project folder with finished reconstructions (recon/<video>/state.pt)."
    ),
    videos: list[str] = typer.Argument(None, help="Video ids (default: every finished reconstruction)."),
    size: int = typer.Option(256, help="Tile size in pixels."),
    peaks: int = typer.Option(2, help="Peak frames shown per video."),
    crop: bool = typer.Option(False, "--crop", help="Zoom on the region that moves."),
) -> None:
    """Input | trained Gaussians | extracted mesh | ground truth at the peak frames of each video."""
    recon = project_dir / "recon"
    names = (
        list(videos)
        if videos
        else sorted(p.parent.name for p in recon.glob("*/state.pt") if (p.parent / "done.json").exists())
    )
    if not names:
        raise UserError(f"{project_dir}: no finished reconstructions in recon/ (run `t2bs reconstruct {project_dir}`)")
    for name in names:
        if not (recon / name / "done.json").exists():
            raise UserError(f"{recon / name}: not a finished reconstruction")
        print(json.dumps(view_video(project_dir, name, size, peaks, crop)), flush=True)


if __name__ == "__main__":
    run_command(main)
