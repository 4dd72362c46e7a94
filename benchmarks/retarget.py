"""Retargeting benchmark (issue 8): same as `t2bs bench retarget --target PATH --json FILE`.

python benchmarks/retarget.py [TARGET ...]  (default: the shared turtle.glb, t2bs.shared_assets) prints the JSON
{"rows": [{"target", "driver_shape", "target_direction", "pearson"}], ...}.
"""

import json
import sys

from t2bs.eval.bench_retarget import run_bench
from t2bs.shared_assets import shared_asset

if __name__ == "__main__":
    targets = sys.argv[1:] or [str(shared_asset("turtle.glb"))]
    print(json.dumps(run_bench(targets), indent=2))
