"""`t2bs bench raster` as a function: kept apart from render/splat/bench.py so that `t2bs --help` does not import
torch (the benchmark's module is imported only when it runs)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class BenchRasterConfig:
    cases: str = "a,b,c"  # comma-separated scene cases of t2bs.render.splat.bench.CASES (a, b, c)
    repeats: int = 5  # timed repeats of the fast path (the median is reported)
    threads: int = 2  # torch / OpenMP threads


def bench_raster(config: BenchRasterConfig = BenchRasterConfig()) -> dict:
    """Splat rasterizer: fast C++ vs autograd reference vs dense, ms per forward+backward.

    Prints one JSON line per case and then the report (t2bs.render.splat.bench.main) and returns the report
    ``{"cases": [...], "device": ...}``. Raises UserError for a case name not in ``CASES``.
    """
    from t2bs.errors import UserError
    from t2bs.render.splat.bench import CASES, main

    bad = [c for c in config.cases.split(",") if c.strip() not in CASES]
    if bad:
        raise UserError(f"unknown case(s) {', '.join(bad)}; choose from {', '.join(CASES)}")
    return main(config.cases, config.repeats, config.threads)
