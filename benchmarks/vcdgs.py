"""VCDGS quality benchmark (same as `t2bs bench vcdgs`): prints a Markdown table and JSON.

python3 benchmarks/vcdgs.py --asset turtle --asset facecap --defects clean --methods full,static --json /tmp/vcdgs.json
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from t2bs.cli.exits import run_command  # noqa: E402
from t2bs.cli.bench import bench_vcdgs_command  # noqa: E402

if __name__ == "__main__":
    run_command(bench_vcdgs_command)
