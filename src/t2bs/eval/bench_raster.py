"""`t2bs bench raster`: kept apart from bench.py so that `t2bs --help` does not import torch."""

from __future__ import annotations


def bench_raster_command(cases: str = "a,b,c", repeats: int = 5, threads: int = 2) -> None:
    """Splat rasterizer: fast C++ vs autograd reference vs dense, ms per forward+backward (JSON)."""
    from t2bs.errors import UserError
    from t2bs.render.splat.bench import CASES, main

    bad = [c for c in cases.split(",") if c.strip() not in CASES]
    if bad:
        raise UserError(f"unknown case(s) {', '.join(bad)}; choose from {', '.join(CASES)}")
    main(cases, repeats, threads)
