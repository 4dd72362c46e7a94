"""The benchmarks as functions (t2bs.eval.bench_*: a config dataclass in, the JSON the command prints out)."""

from __future__ import annotations

import json

import pytest
from conftest import asset
from t2bs.errors import UserError


def _fake_case(name, mesh, prompt, defects, methods, *args):
    """A benchmark case without a reconstruction: fixed metrics per method."""
    return [
        {
            "asset": name,
            "prompt": prompt,
            "defects": defects,
            "method": m,
            "p2p_all": 0.1,
            "p2p_moving": 0.2,
            "nc": 0.01,
            "psnr": 30.0,
            "ssim": 0.9,
            "seconds": 0.0,
        }
        for m in methods
    ]


def test_bench_vcdgs_function(tmp_path, monkeypatch, capsys):
    from t2bs.eval import bench_vcdgs
    from t2bs.eval.bench_vcdgs import BenchVcdgsConfig

    monkeypatch.setattr(bench_vcdgs, "run_case", _fake_case)
    monkeypatch.setattr(bench_vcdgs, "load_asset", lambda spec: (spec, None))
    out = tmp_path / "bench.json"
    config = BenchVcdgsConfig(
        asset=("a", "b"),
        prompts="smiling, blinking",
        methods="full,static",
        json_file=out,
        seed=3,
        set_options=("knn=4",),
    )
    result = bench_vcdgs.bench_vcdgs(config)
    assert [(r["asset"], r["prompt"], r["method"]) for r in result["rows"]] == [
        (a, p, m) for a in "ab" for p in ("smiling", "blinking") for m in ("full", "static")
    ]
    assert result["settings"]["options"] == {"seed": 3, "knn": 4} and result["settings"]["config"]["knn"] == 4
    assert json.loads(out.read_text())["rows"] == result["rows"]
    assert "(kept)" not in capsys.readouterr().out
    bench_vcdgs.bench_vcdgs(config)  # same file and settings: every row kept
    assert capsys.readouterr().out.count("(kept)") == 8


def test_bench_vcdgs_bad_config(tmp_path):
    from t2bs.eval.bench_vcdgs import BenchVcdgsConfig, bench_vcdgs

    with pytest.raises(UserError, match="--set method / holdout_views"):
        bench_vcdgs(BenchVcdgsConfig(asset=("turtle",), set_options=("holdout_views=1",)))
    with pytest.raises(UserError, match="unknown method 'bogus'"):
        bench_vcdgs(BenchVcdgsConfig(asset=("turtle",), methods="full,bogus"))
    fox = "procedural:a cartoon fox"
    with pytest.raises(UserError, match="--landmarks 'fox.json': use ASSET=FILE"):
        bench_vcdgs(BenchVcdgsConfig(asset=(fox,), landmarks=("fox.json",)))
    with pytest.raises(UserError, match=r"--landmarks turtle=\.\.\.: no such --asset"):
        bench_vcdgs(BenchVcdgsConfig(asset=(fox,), landmarks=("turtle=t.json",)))
    with pytest.raises(UserError, match="landmarks file nowhere.json does not exist"):
        bench_vcdgs(BenchVcdgsConfig(asset=(fox,), landmarks=(f"{fox}=nowhere.json",)))
    bad = tmp_path / "ten.json"
    bad.write_text('{"vertex_ids": [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]}')
    with pytest.raises(UserError, match="vertex_ids must be 20 integers"):  # its contents too, before any case runs
        bench_vcdgs(BenchVcdgsConfig(asset=(fox,), landmarks=(f"{fox}={bad}",)))


def test_bench_raster_bad_case():
    from t2bs.eval.bench_raster import BenchRasterConfig, bench_raster

    with pytest.raises(UserError, match=r"unknown case\(s\) z"):
        bench_raster(BenchRasterConfig(cases="a,z"))


def test_bench_blendshapes_function(tmp_path):
    from t2bs.eval.bench_blendshapes import BenchBlendshapesConfig, bench_blendshapes

    turtle = asset("turtle.glb")
    out = tmp_path / "bench.json"
    result = bench_blendshapes(
        BenchBlendshapesConfig(
            asset=str(turtle), json_out=out, prompts=6, frames=6, held_out=2, rgb_steps=0, image_size=64
        )
    )
    (row,) = result["rows"]
    assert row["asset"] == "turtle" and row["held_out_captures"] == 2 and row["held_out_frames"] == 12
    assert 0 <= row["p2p"] < 0.05 and row["image_size"] == 64
    assert json.loads(out.read_text())["rows"][0]["p2p"] == pytest.approx(row["p2p"])
    with pytest.raises(UserError, match="unknown --source 'x'; use gt or vcdgs"):
        bench_blendshapes(BenchBlendshapesConfig(asset=str(turtle), source="x"))
