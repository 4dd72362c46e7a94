"""What one VCDGS training step costs: operator calls (torch profiler) and milliseconds, per preset, as JSON.

    python3 benchmarks/step_cost.py                       # quick and paper presets on facecap, this checkout
    python3 benchmarks/step_cost.py --src /tmp/base/src   # the same measurement of another checkout's code
    python3 benchmarks/step_cost.py --device cuda --json $OUT/step_cost.json

It calls only ``train`` and the functions around it that every version of t2bs has, so that the
same script measures the commit before a change (``--src`` of a git worktree) and the change.
The step does not depend on what the pixels show, so two things are cheaper than a real run:
the static fit runs one step (``static_iters=1``), which gives the model what a whole fit gives it (the
splat offsets' ring of edges around each vertex Gaussian, which every step deforms: rows before session
48 skipped the fit, and with it that part of the step), and the vertex tracks are synthetic (every track
valid, zero motion): the same tensors, shapes and operators as real tracks.
The events a run holds once or a few times, not every step (the expression picks by render, the tracks
measured again), are switched off where the checkout has them: in a run of 10-30 steps they would fall inside
the counted steps and weigh as much as a hundred steps (``vcdgs.py`` rows time them: the seconds of a video).

Per preset and stage (the global warm-up, the joint stage) it reports
- ``ops_per_step``: aten operator calls per step, nested ones included (forward, backward, optimiser);
  deterministic for a given torch version, so it compares across machines;
- ``kernels_per_step`` (CUDA only): device kernel launches per step;
- ``ms_per_step``: wall time per step over a timed run after a warm-up (device synchronised).
A run of n warm-up steps ends with one joint step (``train`` always runs the joint stage at least once): the
warm-up figures carry 1/n of a joint step.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path


def _args():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--asset", default="facecap", help="shared asset name or mesh path (needs morph targets)")
    ap.add_argument("--presets", default="quick,paper")
    ap.add_argument("--prompt", default="opening the mouth extremely wide")
    ap.add_argument("--stages", default="warmup,joint", help="which stages to measure: warmup, joint")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--profile-steps", type=int, default=10, help="steps counted under the profiler per stage")
    ap.add_argument(
        "--timed-steps", type=int, default=0, help="steps timed per stage (0: 30 quick / 10 paper on CPU, 200 on CUDA)"
    )
    ap.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="VCDGS option for every preset (repeatable)"
    )
    ap.add_argument("--src", default="", help="a t2bs src/ folder to measure instead of this checkout's")
    ap.add_argument("--json", default="", help="also write the JSON here")
    ap.add_argument(
        "--table", default="", help="also write the profiler's top 40 operators by device and by CPU time to this file"
    )
    return ap.parse_args()


# Options that schedule work a few times a run, not every step (empty = none): the expression picks, the track refit.
ONCE_A_RUN = ("expression_pick", "track_refit")


def _has_option(name: str) -> bool:
    from t2bs.recon.config import parse_options

    try:
        parse_options([f"{name}="])
    except Exception:  # an older checkout: an unknown option
        return False
    return True


def main() -> None:
    a = _args()
    src = Path(a.src).resolve() if a.src else Path(__file__).resolve().parents[1] / "src"
    sys.path.insert(0, str(src))
    import t2bs  # first: it chooses how torch's OpenMP threads wait before torch loads (t2bs/openmp.py), as in a run

    import torch
    from torch.profiler import ProfilerActivity, profile

    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.recon.config import parse_options, preset
    from t2bs.recon.tracks import VertexTracks
    from t2bs.recon.vcdgs import build_model, prepare_data, train
    from t2bs.video.synth import GridConfig, make_grid

    cuda = a.device.startswith("cuda")
    over = {**parse_options(a.set), "static_iters": 1, "device": a.device, "checkpoint_every": 0, "time_budget_s": 0.0}
    for event in ONCE_A_RUN:  # only where this checkout has the option (a --src before it has not)
        if event not in over and _has_option(event):
            over[event] = ()
    name, mesh = load_asset(a.asset)
    results = {
        "options": a.set,
        "t2bs": str(Path(t2bs.__file__).resolve().parents[1]),
        "asset": name,
        "prompt": a.prompt,
        "device": torch.cuda.get_device_name() if cuda else "cpu",
        "torch": torch.__version__,
        "presets": {},
    }
    grids = {}
    for pname in a.presets.split(","):
        pover = dict(over)
        if "compile" not in pover and getattr(getattr(preset(pname), "runtime", None), "compile", False):
            # the paper preset compiles its step (and replays it as CUDA graphs): the rows compare the eager step
            # with --set compile=true, as before it did
            pover.update(compile=False, cuda_graphs=False)
        cfg = preset(pname, **pover)
        # the grid at the training resolution, --set resolution=... included (--src: a checkout before the tree)
        size = cfg.data.resolution if hasattr(cfg, "data") else cfg.resolution
        if size not in grids:
            grids[size] = make_grid(mesh, a.prompt, config=GridConfig(frames=16, size=size))
        data = prepare_data(grids[size], cfg)
        v, t, n = data.views, data.frames, mesh.num_vertices
        data.tracks = VertexTracks(torch.zeros(v, t, n, 2), torch.ones(v, t, n), torch.ones(v, n, dtype=torch.bool))
        torch.manual_seed(cfg.runtime.seed if hasattr(cfg, "runtime") else cfg.seed)
        model, _ = build_model(mesh, data, cfg)
        timed = a.timed_steps or (200 if cuda else (30 if pname == "quick" else 10))
        row = {
            "resolution": size,
            "gaussians": int(model.means.shape[0] + (0 if model.faces is None else len(model.faces))),
            "control_points": int(model.cp.shape[0]),
            "batch_size": cfg.optim.batch_size if hasattr(cfg, "optim") else cfg.batch_size,
        }
        for stage, global_iters in (("warmup", 10**6), ("joint", 0)):
            if stage not in a.stages.split(","):
                continue

            def run(steps: int):
                # A fresh copy per run: every run starts from the same untrained model.
                m = copy.deepcopy(model)
                c = preset(pname, **{**pover, "iterations": steps, "global_iters": global_iters})
                if cuda:
                    torch.cuda.synchronize()
                t0 = time.perf_counter()
                train(m, data, c, progress=False)
                if cuda:
                    torch.cuda.synchronize()
                return time.perf_counter() - t0

            # With global_iters huge every step but the last is warm-up; with 0 every step is joint.
            run(3)  # warm-up: kernel builds, allocator, first-call costs
            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
            with profile(activities=acts) as prof:
                run(a.profile_steps)
            if a.table:  # where a step's time goes (appended: one table per preset and stage)
                averages = prof.key_averages()
                with open(a.table, "a") as f:
                    for sort in (["self_device_time_total"] if cuda else []) + ["self_cpu_time_total"]:
                        f.write(f"== {pname} {stage}, {a.profile_steps} steps, by {sort}\n")
                        f.write(averages.table(sort_by=sort, row_limit=40, max_name_column_width=60) + "\n")
            events = prof.events()
            ops = sum(1 for e in events if e.name.startswith("aten::"))
            kernels = sum(
                1
                for e in events
                if getattr(e, "device_type", None) is not None
                and str(e.device_type).endswith("CUDA")
                and not e.name.startswith(("aten::", "cuda"))
            )
            seconds = run(timed)
            stage_row = {
                "ops_per_step": round(ops / a.profile_steps, 1),
                "ms_per_step": round(1000 * seconds / timed, 2),
                "timed_steps": timed,
            }
            if cuda:
                stage_row["kernels_per_step"] = round(kernels / a.profile_steps, 1)
                stage_row["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated() / 2**20)
            row[stage] = stage_row
            print(f"{pname} {stage}: {stage_row}", file=sys.stderr, flush=True)
        results["presets"][pname] = row
    text = json.dumps(results, indent=1)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
