"""Retargeting benchmark (issue 8): same as `t2bs bench retarget --target PATH --json FILE`.

python benchmarks/retarget.py [TARGET ...]  (default: ../shared/assets/turtle.glb) prints the JSON
{"rows": [{"target", "driver_shape", "target_direction", "pearson"}], ...}.
"""

import json
import sys

from t2bs.retarget.bench import run_bench

if __name__ == "__main__":
    targets = sys.argv[1:] or ["../shared/assets/turtle.glb"]
    print(json.dumps(run_bench(targets), indent=2))
