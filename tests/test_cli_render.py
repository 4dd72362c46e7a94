import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from conftest import asset

T2BS = [sys.executable, "-m", "t2bs.cli"]


def run(*args):
    return subprocess.run([*T2BS, *map(str, args)], capture_output=True, text=True)


@pytest.mark.parametrize("name", ["turtle.glb", "facecap.glb", "vipe_hero_head.glb"])
def test_render_writes_16_images_and_manifest(tmp_path, name):
    out = tmp_path / "proj"
    r = run("render", asset(name), "-o", out, "--size", 128)
    assert r.returncode == 0, r.stderr
    images = [out / "renders" / "front.png", *sorted((out / "renders" / "orbit").glob("view*.png"))]
    assert len(images) == 16
    front = np.asarray(Image.open(images[0]), np.float32) / 255
    mask = (front < 0.98).any(-1)
    assert 0.15 < mask.mean() < 0.8
    yx = np.argwhere(mask).mean(0)
    assert np.all(np.abs(yx - 64) < 16)
    manifest = json.loads((out / "manifest.json").read_text())
    stage = manifest["stages"]["render"]
    assert stage["backend"] == "file" and stage["config"]["size"] == 128 and "t2bs" in manifest["versions"]
    # Same inputs again: nothing is redone.
    done = (out / "renders" / "done.json").read_text()
    r = run("render", asset(name), "-o", out, "--size", 128)
    assert r.returncode == 0 and "up to date" in r.stdout
    assert (out / "renders" / "done.json").read_text() == done


def _nan_obj(path):
    path.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")


def _faceless_obj(path):
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")


@pytest.mark.parametrize(
    "name,make,needle",
    [
        ("missing.glb", None, "no such file"),
        ("empty.glb", lambda p: p.write_bytes(b""), "empty"),
        ("text.glb", lambda p: p.write_text("hello, I am not a mesh"), "not a readable glTF"),
        ("nan.obj", _nan_obj, "NaN"),
        ("nofaces.obj", _faceless_obj, "no faces"),
    ],
)
def test_bad_input_one_line_error_exit_2_nothing_written(tmp_path, name, make, needle):
    path = tmp_path / name
    if make:
        make(path)
    out = tmp_path / "proj"
    r = run("render", path, "-o", out)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], r.stderr
    assert "Traceback" not in r.stderr
    assert not out.exists()
