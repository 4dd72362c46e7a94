"""Time the same VCDGS reconstructions with an earlier commit and with this checkout, one after the other.

    python3 benchmarks/speed_compare.py --base ce35722
    python3 benchmarks/speed_compare.py --base HEAD~1 --variant compile:compile=true --json /tmp/speed.json

The earlier commit runs from a git worktree (its own src/ and its own benchmarks/vcdgs.py); every case is the
quick preset on a clean grid with no time cap (``--time-budget 0``: every version runs all its steps, so the
seconds compare the same work and the quality columns compare the same schedule). Each version runs in its own
process, sequentially, on the same machine: a ratio from one run. A ``--variant NAME:KEY=VALUE[,KEY=VALUE]`` adds
a run of this checkout with VCDGS options set (e.g. ``compile:compile=true``); it gets a fresh inductor cache
folder, so its first case pays the compilation a first run on a new machine pays.

Prints, per case and version: seconds, p2p moving, expression p2p and its ratio to the rigid oracle, and the
ratios base / version, as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))  # this checkout's rule for the shared assets, whatever t2bs is installed

from t2bs.openmp import CHOSEN  # noqa: E402
from t2bs.shared_assets import ENV as SHARED_ENV  # noqa: E402
from t2bs.shared_assets import shared_assets_dir  # noqa: E402

# The OpenMP wait policy this process's t2bs chose (t2bs/openmp.py) is left out of the versions' environments: each
# version's own t2bs chooses its own (an older one sets OMP_WAIT_POLICY=PASSIVE, which a GOMP_SPINCOUNT passed on
# from here would override). A policy the user set stays.
_OWN_POLICY = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", CHOSEN) if CHOSEN in os.environ else ()


def _environment(checkout: Path, extra: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in _OWN_POLICY}
    # the base's worktree lives in a temporary folder, where "shared/ beside the checkout" is not: both versions read
    # the assets this checkout finds
    return {**env, SHARED_ENV: str(shared_assets_dir()), **extra, "PYTHONPATH": str(checkout / "src")}


def _build_kernel(checkout: Path, log) -> None:
    """Build (or find) the checkout's C++ splat kernel before anything is timed: a first build takes minutes and
    would count as the first case's seconds."""
    code = "from t2bs.render.splat.cpu import load_kernel, kernel_error; load_kernel(); print(kernel_error())"
    subprocess.run(
        [sys.executable, "-c", code],
        cwd=checkout,
        env=_environment(checkout, {}),
        stdout=log,
        stderr=subprocess.STDOUT,
        check=True,
    )


CASES = (
    "facecap|smiling",
    "facecap|opening the mouth extremely wide",
    "procedural:a cartoon fox with big ears|opening the mouth extremely wide",
)


def _run(checkout: Path, asset: str, prompt: str, options: list[str], env: dict, log) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rows.json"
        cmd = [
            sys.executable,
            str(checkout / "benchmarks" / "vcdgs.py"),
            "--asset",
            asset,
            "--prompts",
            prompt,
            "--defects",
            "clean",
            "--methods",
            "full,rigid",
            "--time-budget",
            "0",
            "--json",
            str(out),
        ]
        for o in options:
            cmd += ["--set", o]
        t0 = time.time()
        proc = subprocess.run(
            cmd,
            cwd=checkout,
            env=_environment(checkout, env),
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        wall = time.time() - t0
        if proc.returncode != 0:
            return {"error": f"rc {proc.returncode}", "wall_s": round(wall, 1)}
        rows = {r["method"]: r for r in json.loads(out.read_text())["rows"]}
    full = rows["full"]
    return {
        "seconds": full["seconds"],
        "wall_s": round(wall, 1),
        "p2p_moving": full["p2p_moving"],
        "expr_p2p": full["expr_p2p"],
        "expr_ratio": full["expr_ratio"],
        "steps": full.get("steps"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", required=True, help="the earlier commit (any git revision)")
    ap.add_argument(
        "--case",
        action="append",
        default=[],
        help="ASSET|PROMPT (repeatable; default: facecap smiling, facecap mouth wide, the demo fox mouth wide)",
    )
    ap.add_argument("--variant", action="append", default=[], help="NAME:KEY=VALUE[,KEY=VALUE] run of this checkout")
    ap.add_argument("--json", default="")
    ap.add_argument("--log", default="/tmp/speed_compare.log")
    a = ap.parse_args()
    sha = subprocess.run(
        ["git", "rev-parse", "--short", a.base], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.strip()
    base = Path(tempfile.gettempdir()) / f"t2bs-base-{sha}"
    if not base.exists():
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(base), sha], cwd=REPO, check=True, capture_output=True
        )
    versions = [(f"base {sha}", base, [], {}), ("this checkout", REPO, [], {})]
    for v in a.variant:
        name, _, opts = v.partition(":")
        cache = tempfile.mkdtemp(prefix="inductor-")
        versions.append((name, REPO, [o for o in opts.split(",") if o], {"TORCHINDUCTOR_CACHE_DIR": cache}))
    results = {"base": sha, "cases": []}
    with open(a.log, "a") as log:
        for checkout in {base, REPO}:
            _build_kernel(checkout, log)
        for case in a.case or CASES:
            asset, _, prompt = case.partition("|")
            row = {"asset": asset, "prompt": prompt, "versions": {}}
            for name, checkout, opts, env in versions:
                r = _run(checkout, asset, prompt, opts, env, log)
                row["versions"][name] = r
                print(f"{asset} | {prompt} | {name}: {r}", file=sys.stderr, flush=True)
            b = row["versions"][versions[0][0]]
            for name, *_ in versions[1:]:
                r = row["versions"][name]
                if "seconds" in r and "seconds" in b:
                    r["speedup"] = round(b["seconds"] / max(r["seconds"], 1e-9), 2)
                    r["p2p_change"] = round(r["p2p_moving"] / b["p2p_moving"] - 1, 4)
                    r["expr_change"] = round(r["expr_p2p"] / b["expr_p2p"] - 1, 4)
            results["cases"].append(row)
            if a.json:
                Path(a.json).write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
