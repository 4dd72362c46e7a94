"""Benchmark the Gaussian splat rasterizer (issue 3): fast C++ CPU path vs autograd reference vs
dense all-pairs baseline, ms per forward+backward (median of repeats), torch threads = 2.

    python3 benchmarks/raster.py [--cases a,b,c] [--repeats 5] [--threads 2]

The last line printed is one JSON object: {"cases": [...], "device": "..."} (same as
`t2bs bench raster`).
"""

from __future__ import annotations

import argparse
import os

# Before torch loads libgomp: idle OpenMP workers sleep instead of spinning. On this shared,
# oversubscribed 2-core machine spinning made every 2-thread torch op 3-10x slower (measured).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from t2bs.render.splat.bench import main  # noqa: E402

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="a,b,c", help="comma-separated subset of a,b,c")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats of the fast path (median)")
    ap.add_argument("--threads", type=int, default=2, help="torch/OpenMP threads")
    args = ap.parse_args()
    main(args.cases, args.repeats, args.threads)
