"""`t2bs bench vcdgs`: VCDGS and its ablations against ground truth (paper §4.4, appendix table).

For each (asset, prompt, defect preset): the offline animator animates the asset with its own
morph targets (the ground truth), renders the 15-view grid (t2bs.video.synth) with the chosen
simulated generator defects, and VCDGS reconstructs it with every requested method. Two orbit
views (``--holdout``, default 4 and 10: azimuth -25.7 and +25.7 deg) are never trained on.

Columns, expression first (geometry.metrics.expression_metrics): each frame's head motion taken out of the truth and
out of the reconstruction, over the vertices whose true non-rigid motion exceeds 0.5 % of the diagonal: expr_p2p,
expr/rigid (its ratio to the rigid oracle: 1 = no better than perfect head tracking with a neutral face),
recovered (|recovered motion| / |true motion| there), cosine (its direction) and spurious (false motion of those
vertices in the frames where the truth leaves them still, in units of the true motion's mean). In the JSON only:
expr_ratio_seen, the same ratio over the vertices some training view sees (p2p_seen's), expr_seen_share, their share
of the expression error, and expr_seen_pairs, their share of the (frame, vertex) pairs: what the rest costs is lost
where no input pixel shows it. Then p2p_all / p2p_moving (mean vertex error / bbox diagonal over all (frame, vertex) pairs,
and over those whose true displacement from the rest pose exceeds 0.5 % of the diagonal), p2p_seen
(the moving pairs of vertices that some training view sees in some true frame, depth-tested at
1024 px; seen_fraction: their share. The rest, such as a mouth's back teeth, change no pixel of any
input, so their error measures a method's prior for hidden geometry, not what it recovered), NC
(mean 1 - cos of vertex normals), PSNR / SSIM of the reconstructed mesh rendered at the held-out
views against the true mesh rendered there (same renderer and shading, no defects), and wall
seconds per reconstruction. Baselines: "static" is the neutral mesh for every frame, "rigid" the neutral moved by the
true head motion (its robust rigid fit).

Output: a Markdown table and the JSON ``{"rows": [{asset, prompt, defects, method, expr_p2p,
expr_rigid, expr_ratio, recovered, cosine, expr_fraction, spurious, expr_ratio_seen, expr_seen_share, expr_seen_pairs, p2p_all, p2p_moving, p2p_seen, seen_fraction, nc, psnr, ssim, seconds, parts[, hidden_pick]}, ...], "summary": {...}, "settings": {...}}``
(also written to ``--json``, after every case; hidden_pick: what the pick of hidden parts' motion did, where it ran;
parts: the mesh parts holding the most of p2p moving, geometry.metrics.part_errors, with the rigid oracle's p2p there). The summary holds the mean per (defects, method), the full / static ratio per case,
and, when ablations ran, full against each of them over the cases both ran (``full_vs``: the paper's ablation
claim as mean expr_p2p / p2p_moving / p2p_seen / NC and the number of cases where full is lower; also printed as a second
table). Resume: a re-run with the same ``--json`` file and the same settings
(grid size, frames, held-out views, and the resolved VCDGS configuration, so a changed default
counts as a change) keeps the rows already there and runs only the missing (asset, prompt, defects,
method) combinations; ``--fresh`` starts over. Rows kept from a file written before a column existed
show it as "-" and are left out of its means.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.recon.config import iteration_overrides, parse_options, preset
from t2bs.shared_assets import shared_assets_dir

SHARED_ASSETS = shared_assets_dir()
DEFAULT_ASSETS = ("turtle", "facecap", "procedural:a cartoon fox with big ears")  # when no asset is given
DEFAULT_PROMPTS = ("blinking", "opening the mouth extremely wide", "smiling", "tongue sticking out the mouth")
ALL_METHODS = ("full", "no_view", "no_refine", "no_lbs", "no_global", "static", "rigid")
BASELINES = ("static", "rigid")  # no reconstruction: the neutral, and the neutral moved by the true head motion


def load_asset(spec: str):
    """'turtle' / 'facecap' (shared assets), a mesh path, or 'procedural:<prompt>' -> (name, Mesh)."""
    if spec.startswith("procedural:"):
        from t2bs.character.backends import generate

        prompt = spec.split(":", 1)[1] or "a cartoon fox with big ears"
        return spec, generate(prompt, "procedural").mesh
    from t2bs.character.render_stage import canonical_character

    path = Path(spec)
    if not path.exists() and not path.suffix:
        path = SHARED_ASSETS / f"{spec}.glb"
    if not path.exists():
        raise UserError(f"asset {spec!r} not found (a mesh path, a name in {SHARED_ASSETS}, or procedural:PROMPT)")
    mesh, _ = canonical_character(path)
    if not mesh.morph_targets:
        raise UserError(f"{path}: no morph targets, so no ground-truth motion to benchmark against")
    return path.stem, mesh


def heldout_images(mesh, vertices: np.ndarray, cameras, shading: str, renderer) -> np.ndarray:
    """[V_held, T, H, W, 3] mesh renders of ``vertices`` [T, N, 3] from ``cameras``."""
    return np.stack(
        [np.stack([renderer.render(mesh, c, vertices=v, shading=shading).rgb for v in vertices]) for c in cameras]
    )


def seen_vertices(mesh, frames: np.ndarray, cameras, renderer) -> np.ndarray:
    """[N] bool: vertices that some camera of ``cameras`` sees in some frame of ``frames`` [T, N, 3]."""
    from t2bs.recon.tracks import VISIBILITY_SIZE

    seen = np.zeros(mesh.num_vertices, bool)
    for verts in frames:
        for cam in cameras:
            seen |= renderer.vertex_visibility(mesh, cam, vertices=verts, min_size=VISIBILITY_SIZE)
    return seen


def case_config_overrides(preset_name: str, iterations: int, options: dict | None) -> dict:
    """VCDGS overrides shared by every method of a benchmark run (the method itself excluded)."""
    return {**(options or {}), **iteration_overrides(preset_name, iterations)}


def perfect_tracks_fn(truth: np.ndarray):
    """A ``tracks_fn`` for ``reconstruct_grid``: the optical-flow tracks' validity (visible at rest, round trip) with
    the truth's projected vertex motion in place of the flow's, ``truth`` [T, N, 3] (frame 0 the rest pose): the
    tracks perfect flow would give, so a run with them bounds what better tracks could buy."""
    import torch

    def make(mesh, data, cfg, progress=False):
        from t2bs.recon.vcdgs import vertex_tracks

        tracks = vertex_tracks(mesh, data, cfg, progress)
        for v in data.train_views:
            cam = data.cameras[v]
            at_rest = cam.project(truth[0])[0]
            for t in range(truth.shape[0]):
                tracks.displacement[v, t] = torch.from_numpy((cam.project(truth[t])[0] - at_rest).astype(np.float32))
        return tracks

    return make


def run_case(
    name: str,
    mesh,
    prompt: str,
    defects: str,
    methods: list[str],
    preset_name: str,
    size: int,
    frames: int,
    holdout: tuple[int, ...],
    iterations: int = 0,
    progress: bool = False,
    options: dict | None = None,
    perfect_tracks: bool = False,
    landmarks: dict | None = None,
) -> list[dict]:
    import torch

    from t2bs.geometry.metrics import expression_metrics, geometry_metrics, part_errors, psnr, ssim
    from t2bs.geometry.rigid import apply_motion, robust_rigid_motion
    from t2bs.recon.vcdgs import reconstruct_grid
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    gcfg = GridConfig(frames=frames, size=size)
    with MeshRenderer() as renderer:
        grid = make_grid(mesh, prompt, config=gcfg, defects=defect_preset(defects), renderer=renderer)
        gt = grid.gt_vertices
        held_cams = [grid.cameras[v] for v in holdout]
        gt_imgs = heldout_images(mesh, gt, held_cams, gcfg.shading, renderer)
        seen = seen_vertices(mesh, gt, [c for v, c in enumerate(grid.cameras) if v not in holdout], renderer)
        oracle = apply_motion(*robust_rigid_motion(mesh.vertices, gt), mesh.vertices).astype(np.float32)
        rows = []
        for method in methods:
            t0 = time.time()
            pick = None  # hidden_parts.HiddenPick.summary() where config.hidden_pick ran
            extra = {}  # steps run (and peak GPU memory) of a reconstruction
            if method == "static":
                verts = np.repeat(mesh.vertices[None], grid.num_frames, axis=0)
                seconds = 0.0
            elif method == "rigid":  # perfect head tracking, neutral face
                verts = oracle
                seconds = 0.0
            else:
                over = {
                    **case_config_overrides(preset_name, iterations, options),
                    "method": method,
                    "holdout_views": tuple(holdout),
                }
                cfg = preset(preset_name, **over)
                cuda = torch.cuda.is_available() and cfg.runtime.device != "cpu"
                if cuda:
                    torch.cuda.reset_peak_memory_stats()
                res = reconstruct_grid(
                    mesh,
                    grid,
                    cfg,
                    progress=progress,
                    landmarks_file=(landmarks or {}).get(name),
                    tracks_fn=perfect_tracks_fn(gt) if perfect_tracks else None,
                )
                verts, seconds, pick = res.vertices, time.time() - t0, res.hidden_pick
                # the expression basis's shapes (recon/expression_basis.py; [] when off or no face was found)
                extra = {
                    "steps": int(res.history.get("steps_run", 0)),
                    "joint_ms_per_step": res.history.get("joint_ms_per_step"),  # after the joint stage's first 50
                    "step_kind": res.history.get("step_kind"),  # eager | compiled | compiled, CUDA graphs
                    "compile_s": res.history.get("compile_s"),  # the compiled graphs' first steps (seconds)
                    "expression_shapes": res.expression["shapes"],
                    # seconds of data, tracks, basis, model (static fit), train, extract, pick; expression_picks and
                    # track_refits: seconds inside train
                    "phases": res.phases,
                }
                if cuda:
                    extra["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated() / 2**20)
            geo = geometry_metrics(verts, gt, mesh.vertices, mesh.faces, seen=seen)
            expr = expression_metrics(verts, gt, mesh.vertices)
            # the same over the vertices some training view sees: what the images could have recovered
            expr_seen = expression_metrics(verts, gt, mesh.vertices, select=seen)
            # the parts (teeth, eyeballs, the face) that hold the most of p2p moving, with the rigid oracle's there
            parts = part_errors(verts, gt, mesh.vertices, mesh.faces, seen=seen, oracle=oracle)
            imgs = heldout_images(mesh, verts, held_cams, gcfg.shading, renderer)
            rows.append(
                {
                    "asset": name,
                    "prompt": prompt,
                    "defects": defects,
                    "method": method,
                    "p2p_all": geo["p2p_all"],
                    "p2p_moving": geo["p2p_moving"],
                    "p2p_seen": geo["p2p_seen"],
                    "seen_fraction": geo["seen_fraction"],
                    "nc": geo["nc"],
                    **expr,
                    "expr_ratio_seen": expr_seen["expr_ratio"],
                    "expr_seen_share": expr_seen["expr_p2p"]
                    * expr_seen["expr_fraction"]
                    / max(expr["expr_p2p"] * expr["expr_fraction"], 1e-12),
                    "expr_seen_pairs": expr_seen["expr_fraction"] / max(expr["expr_fraction"], 1e-12),
                    "psnr": psnr(imgs, gt_imgs),
                    "ssim": ssim(imgs.reshape(-1, *imgs.shape[2:]), gt_imgs.reshape(-1, *gt_imgs.shape[2:])),
                    "seconds": round(seconds, 2),
                    **extra,
                    **({"hidden_pick": pick} if pick else {}),
                    "parts": [{k: round(v, 5) if isinstance(v, float) else v for k, v in p.items()} for p in parts],
                }
            )
            print(_row_line(rows[-1]), flush=True)
    return rows


def _fmt(r: dict, key: str, spec: str) -> str:
    """A cell, or "-" for a row kept from a file older than the column."""
    return format(r[key], spec) if key in r else "-"


def _cells(r: dict) -> list[str]:
    return [
        r["asset"],
        r["prompt"],
        r["defects"],
        r["method"],
        _fmt(r, "expr_p2p", ".5f"),
        _fmt(r, "expr_ratio", ".3f"),
        _fmt(r, "recovered", ".2f"),
        _fmt(r, "cosine", ".2f"),
        _fmt(r, "spurious", ".2f"),
        f"{r['p2p_moving']:.5f}",
        _fmt(r, "p2p_seen", ".5f"),
        f"{r['p2p_all']:.5f}",
        f"{r['nc']:.5f}",
        f"{r['psnr']:.2f}",
        f"{r['ssim']:.4f}",
        f"{r['seconds']:.1f}",
    ]


HEADER = (
    "asset",
    "prompt",
    "defects",
    "method",
    "expr_p2p",
    "expr/rigid",
    "recovered",
    "cosine",
    "spurious",
    "p2p_moving",
    "p2p_seen",
    "p2p_all",
    "NC",
    "PSNR",
    "SSIM",
    "seconds",
)


def _row_line(r: dict) -> str:
    c = _cells(r)
    return f"{c[0]:>10} | {c[1][:32]:<32} | {c[2]:<6} | {c[3]:<9} | " + " | ".join(c[4:])


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(HEADER) + " |\n" + "|---" * len(HEADER) + "|\n"
    return head + "\n".join("| " + " | ".join(_cells(r)) + " |" for r in rows)


METRIC_KEYS = (
    "expr_p2p",
    "expr_ratio",
    "recovered",
    "cosine",
    "spurious",
    "p2p_all",
    "p2p_moving",
    "p2p_seen",
    "nc",
    "psnr",
    "ssim",
    "seconds",
)


def summarise(rows: list[dict]) -> dict:
    """Mean per (defects, method), the full/static p2p_moving (and p2p_seen) ratio per case, and full against each
    ablation over the cases both ran (``full_vs``). A mean of a column is given only when every row it averages has
    it. The expression columns' ratio to the rigid oracle is ``expr_ratio`` itself (every row has it)."""
    out: dict = {"mean": {}, "ratio_full_over_static": {}}
    for d in sorted({r["defects"] for r in rows}):
        for m in [m for m in ALL_METHODS if any(r["method"] == m for r in rows)]:
            sel = [r for r in rows if r["defects"] == d and r["method"] == m]
            if sel:
                keys = [k for k in METRIC_KEYS if all(k in r for r in sel)]
                out["mean"][f"{d}/{m}"] = {k: float(np.mean([r[k] for r in sel])) for k in keys}
    for r in rows:
        if r["method"] != "full":
            continue
        st = [
            s
            for s in rows
            if s["method"] == "static"
            and (s["asset"], s["prompt"], s["defects"]) == (r["asset"], r["prompt"], r["defects"])
        ]
        if st:
            ratio = {k: r[k] / max(st[0][k], 1e-12) for k in ("p2p_moving", "p2p_seen") if k in r and k in st[0]}
            out["ratio_full_over_static"][f"{r['asset']}/{r['prompt']}/{r['defects']}"] = {
                **ratio,
                "nc_better": r["nc"] < st[0]["nc"],
            }
    out["full_vs"] = full_vs_ablations(rows)
    return out


def full_vs_ablations(rows: list[dict]) -> dict:
    """The paper's ablation claim (its table: p2p and NC), per (defects, ablation): over the (asset, prompt) cases where
    both the full method and the ablation ran, the mean p2p_moving, p2p_seen and NC of each, and in how many cases
    full is lower.
    ``{"paper/no_lbs": {"cases": 8, "p2p_moving": {"full": .., "ablation": .., "full_lower": 6}, ...}}``."""
    by_key = {_row_key(r): r for r in rows}
    out: dict = {}
    for d in sorted({r["defects"] for r in rows}):
        for m in ALL_METHODS:
            if m == "full" or m in BASELINES:
                continue
            pairs = [
                (by_key[(a, p, d, "full")], r)
                for (a, p, dd, mm), r in by_key.items()
                if dd == d and mm == m and (a, p, d, "full") in by_key
            ]
            if not pairs:
                continue
            entry: dict = {"cases": len(pairs)}
            for k in ("expr_p2p", "p2p_moving", "p2p_seen", "nc"):
                if all(k in f and k in r for f, r in pairs):
                    entry[k] = {
                        "full": float(np.mean([f[k] for f, _ in pairs])),
                        "ablation": float(np.mean([r[k] for _, r in pairs])),
                        "full_lower": sum(f[k] < r[k] for f, r in pairs),
                    }
            out[f"{d}/{m}"] = entry
    return out


def full_vs_markdown(full_vs: dict) -> str:
    """``full_vs_ablations`` as a table: one line per (defects, ablation, metric)."""
    lines = [
        "| defects | ablation | metric | cases | full mean | ablation mean | full lower by | full lower in |",
        "|---" * 8 + "|",
    ]
    for key, e in full_vs.items():
        d, m = key.split("/")
        for k in ("expr_p2p", "p2p_moving", "p2p_seen", "nc"):
            if k in e:
                v = e[k]
                lines.append(
                    f"| {d} | {m} | {k} | {e['cases']} | {v['full']:.5f} | {v['ablation']:.5f} | "
                    f"{100 * (1 - v['full'] / max(v['ablation'], 1e-12)):.1f} % | {v['full_lower']} of {e['cases']} |"
                )
    return "\n".join(lines)


def bench_settings(
    preset_name: str,
    size: int,
    frames: int,
    holdout: tuple[int, ...],
    iterations: int,
    options: dict | None,
    perfect_tracks: bool = False,
    landmarks: dict | None = None,
) -> dict:
    """What a benchmark row depends on besides its (asset, prompt, defects, method): rows are reused on resume only
    when these match, and the resolved configuration is part of them, so a changed default invalidates old rows."""
    # the configuration's leaves by name (flat, as --set names them), as before the configuration became a tree
    config = preset(preset_name, **case_config_overrides(preset_name, iterations, options)).flat()
    config.pop("method"), config.pop("holdout_views")
    return {
        "preset": preset_name,
        "size": size,
        "frames": frames,
        "holdout_views": list(holdout),
        "iterations": iterations or "preset",
        "options": options or {},
        "config": config,
        **({"tracks": "true"} if perfect_tracks else {}),  # the truth's image motion instead of the flow's
        **({"landmarks": {k: str(v) for k, v in landmarks.items()}} if landmarks else {}),  # given, not found
    }


def _row_key(r: dict) -> tuple:
    return r["asset"], r["prompt"], r["defects"], r["method"]


def code_commit() -> str | None:
    """The git commit of the t2bs code this process runs, ``+dirty`` when tracked files differ from it; None when that
    code is not a git checkout of t2bs (a wheel). Written into every new benchmark row: session 23's raw rows recorded
    no commit, and a row that its code no longer gives could not be traced (docs/BENCHMARKS.md, session 27)."""
    import subprocess

    package = Path(__file__).resolve().parents[1]  # .../src/t2bs

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(package), *args], capture_output=True, text=True, timeout=20, check=True
        ).stdout.strip()

    try:
        top = Path(git("rev-parse", "--show-toplevel"))
        if (top / "src" / "t2bs").resolve() != package:  # t2bs installed inside some other repository
            return None
        sha, dirty = git("rev-parse", "HEAD"), git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return sha + ("+dirty" if dirty else "")


def previous_rows(json_path: Path | None, settings: dict) -> dict[tuple, dict]:
    """Rows of an earlier run in ``json_path`` made with ``settings``, by (asset, prompt, defects, method)."""
    if json_path is None or not Path(json_path).exists():
        return {}
    from t2bs.project import read_json, to_jsonable

    try:
        old = read_json(json_path)
    except ValueError:
        print(f"not resuming: {json_path} is not valid JSON", flush=True)
        return {}
    if not isinstance(old, dict) or old.get("settings") != to_jsonable(settings):
        print(f"not resuming: {json_path} was made with other settings (it will be overwritten)", flush=True)
        return {}
    return {_row_key(r): r for r in old.get("rows", [])}


def _finished_cases(fn, cases: list[tuple], workers: int, *args):
    """Run ``fn(*case, *args)`` (``run_case``) for every case; yield each case's rows as it finishes. With workers > 1
    the cases run in that many spawned processes (spawned, not forked: a forked child inherits torch's thread pool
    and the parent's EGL context). Each reconstruction keeps its configured thread count, so its numbers do not
    depend on ``workers``; its wall seconds and, under a time budget, its step count do."""
    if workers <= 1:
        for case in cases:
            yield fn(*case, *args)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from t2bs.openmp import shared_cores

    with shared_cores(), ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(fn, *case, *args) for case in cases]
        for fut in as_completed(futures):
            yield fut.result()


def run_bench(
    assets: list[str],
    prompts: list[str],
    defects: list[str],
    methods: list[str],
    preset_name: str = "quick",
    size: int = 128,
    frames: int = 16,
    holdout: tuple[int, ...] = (4, 10),
    iterations: int = 0,
    json_path: Path | None = None,
    progress: bool = False,
    options: dict | None = None,
    resume: bool = True,
    workers: int = 1,
    perfect_tracks: bool = False,
    landmarks: dict | None = None,
) -> dict:
    """Every (asset, defects, prompt) case with every method; with ``json_path``, results are written after each case
    and (``resume``) rows already in that file with the same settings are kept instead of recomputed. Each new row
    carries the commit of the code that made it (``code_commit``). ``workers``:
    cases run in parallel processes; the rows keep the (asset, defects, prompt, method) order whatever finishes first."""
    from t2bs.project import write_json

    bad = [m for m in methods if m not in ALL_METHODS]
    if bad:
        raise UserError(f"unknown method {bad[0]!r}; use {', '.join(ALL_METHODS)}")
    if workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    loaded = [load_asset(a) for a in assets]
    from t2bs.rig.face import read_landmarks_file

    meshes = dict(loaded)
    for asset, file in (landmarks or {}).items():
        if asset not in meshes:
            raise UserError(f"--landmarks {asset}=...: no such --asset ({', '.join(meshes)})")
        read_landmarks_file(file, meshes[asset].num_vertices)  # the reconstruction's own check, before any case runs
    settings = bench_settings(preset_name, size, frames, holdout, iterations, options, perfect_tracks, landmarks)
    done = previous_rows(json_path, settings) if resume else {}
    print(f"{'asset':>10} | {'prompt':<32} | defect | method    | " + " | ".join(HEADER[4:]), flush=True)
    cases = [(name, mesh, p, d) for name, mesh in loaded for d in defects for p in prompts]
    todo = [[m for m in methods if (name, p, d, m) not in done] for name, _, p, d in cases]
    for (name, _, p, d), left in zip(cases, todo):
        for m in [m for m in methods if m not in left]:
            print(_row_line(done[(name, p, d, m)]) + "  (kept)", flush=True)
    new: dict[tuple, dict] = {}
    commit = code_commit()
    run = [i for i, left in enumerate(todo) if left]
    finished = _finished_cases(
        run_case,
        [(*cases[i], todo[i]) for i in run],
        min(workers, max(len(run), 1)),
        preset_name,
        size,
        frames,
        holdout,
        iterations,
        progress,
        options,
        perfect_tracks,
        landmarks,
    )

    def ordered() -> list[dict]:
        """Every row known so far (kept or new), in case order."""
        return [
            r
            for name, _, p, d in cases
            for m in methods
            for r in [new.get((name, p, d, m)) or done.get((name, p, d, m))]
            if r is not None
        ]

    for case_rows in finished:
        new.update({_row_key(r): {**r, "commit": commit} for r in case_rows})
        if json_path is not None:  # partial results survive an interruption and resume from here
            rows = ordered()
            write_json(json_path, {"rows": rows, "summary": summarise(rows), "settings": settings, "partial": True})
    rows = ordered()
    result = {"rows": rows, "summary": summarise(rows), "settings": settings}
    if json_path is not None:
        write_json(json_path, result)
    return result


@dataclass
class BenchVcdgsConfig:
    asset: tuple[str, ...] = ()  # turtle, facecap, a glb/vrm with morph targets, procedural:PROMPT; () = DEFAULT_ASSETS
    prompts: str = ",".join(DEFAULT_PROMPTS)  # comma-separated expression prompts
    defects: str = "clean"  # comma-separated defect presets: clean, mild, paper, only_<defect>, paper_without_<defect>
    methods: str = "full,static,rigid"  # comma-separated names of ALL_METHODS, or "all"
    preset_name: str = "quick"  # VCDGS preset: quick | paper
    size: int = 128  # grid frame size in pixels
    frames: int = 16  # frames per grid
    iterations: int = 0  # training steps instead of the preset's (0 = the preset's)
    track_weight: float | None = None  # weight of the optical-flow vertex-track term (None = the preset's)
    time_budget: float | None = None  # wall seconds per reconstruction, 0 = no cap (None = the preset's)
    seed: int | None = (
        None  # VCDGS seed, sampling and initialisation; the grids do not change with it (None = preset's)
    )
    hidden_pick: bool | None = None  # pick hidden parts' motion by render (recon/hidden_parts.py; None = the preset's)
    json_file: Path | None = None  # also write the JSON here, after every case; a re-run with it resumes
    fresh: bool = False  # recompute every row even if json_file holds them from the same settings
    set_options: tuple[str, ...] = ()  # other VCDGSConfig fields as "KEY=VALUE", for every method
    workers: int = 1  # cases run in this many parallel processes (rows do not change with it)
    progress: bool = False  # each reconstruction's progress bars on stderr (a run cut off by a timeout shows where)
    # the truth's projected vertex motion in place of the optical flow's tracks (same validity): what perfect flow
    # would buy, a ceiling for work on the tracks; the JSON's settings say "tracks": "true"
    perfect_tracks: bool = False
    # ASSET=FILE: an asset's 20 face points for its expression basis (`t2bs autorig --landmarks`, or a project's
    # landmarks/landmarks.json), else the face is found on a render (MediaPipe: absent on the lent GPU machines)
    landmarks: tuple[str, ...] = ()


def bench_vcdgs(config: BenchVcdgsConfig = BenchVcdgsConfig()) -> dict:
    """VCDGS vs ablations vs static on characters with ground truth (the module docstring says what each column is).

    Reads the assets (shared assets by name, mesh files or procedural characters) and, with ``json_file``, the rows
    of an earlier run made with the same settings (kept unless ``fresh``). Prints the table header and one line per
    row as it is made (``(kept)`` for a kept row); writes ``json_file`` after every case (with ``"partial": true``)
    and at the end. Returns ``{"rows": [...], "summary": {...}, "settings": {...}}`` (``markdown`` and
    ``full_vs_markdown`` format it). Raises UserError for an unknown asset, method or option, ``--set method`` /
    ``--set holdout_views`` (the benchmark sets them per row), or workers < 1.
    """
    assets = list(config.asset) if config.asset else list(DEFAULT_ASSETS)
    meths = (
        list(ALL_METHODS) if config.methods == "all" else [m.strip() for m in config.methods.split(",") if m.strip()]
    )
    options = {
        k: v
        for k, v in (
            ("track_weight", config.track_weight),
            ("time_budget_s", config.time_budget),
            ("seed", config.seed),
            ("hidden_pick", config.hidden_pick),
        )
        if v is not None
    }
    options.update(parse_options(config.set_options))
    if {"method", "holdout_views"} & set(options):
        raise UserError("--set method / holdout_views: the benchmark sets these per row (use --methods)")
    return run_bench(
        assets,
        [p.strip() for p in config.prompts.split(",") if p.strip()],
        [d.strip() for d in config.defects.split(",") if d.strip()],
        meths,
        config.preset_name,
        config.size,
        config.frames,
        iterations=config.iterations,
        json_path=config.json_file,
        options=options or None,
        resume=not config.fresh,
        workers=config.workers,
        progress=config.progress,
        perfect_tracks=config.perfect_tracks,
        landmarks=_landmark_files(config.landmarks),
    )


def _landmark_files(items: tuple[str, ...]) -> dict[str, Path]:
    """("ASSET=FILE", ...) -> {asset: Path}; UserError for an item without "="."""
    out = {}
    for item in items:
        asset, sep, file = item.partition("=")
        if not sep or not asset or not file:
            raise UserError(f"--landmarks {item!r}: use ASSET=FILE (e.g. facecap=facecap_landmarks.json)")
        out[asset] = Path(file)
    return out
