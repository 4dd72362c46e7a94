"""Hostile and broken inputs (issue 39): nothing in a project folder or a prompt is executed, every
bad input is one `error:` line with exit 2 and no traceback, and a good project beside it is left
byte-for-byte as it was.

The corpus is built here, on the fly, from small files; each family is one parametrised test.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from t2bs.errors import UserError

# ------------------------------------------------------------------------------------ helpers


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """`t2bs ARGV` through the real entry point (t2bs.cli.main), in this process: (rc, stdout, stderr).

    An exception that escapes main() (a traceback for the user) fails the test as itself."""
    from t2bs import cli

    old = sys.argv
    sys.argv = ["t2bs", *map(str, argv)]
    try:
        cli.main()
        rc = 0
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = old
    out = capsys.readouterr()
    return rc, out.out, out.err


def assert_one_error(rc: int, err: str, *needles: str) -> None:
    """rc 2, exactly one `error:` line (which holds every needle), no traceback."""
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert rc == 2, (rc, err)
    assert len(lines) == 1, err
    assert "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones too) by relative path -> bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------- small glTF files on the fly


def tetra_gltf(folder: Path, name: str = "m.gltf", bin_name: str = "m.bin") -> tuple[Path, dict, bytes]:
    """A valid tetrahedron .gltf with an external buffer; returns (path, json dict, buffer bytes)."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    idx = np.array([0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3], np.uint32)
    blob = pos.tobytes() + idx.tobytes()
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"uri": bin_name, "byteLength": len(blob)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 48}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 1]},
                      {"bufferView": 1, "componentType": 5125, "count": 12, "type": "SCALAR"}],
    }
    folder.mkdir(parents=True, exist_ok=True)
    (folder / bin_name).write_bytes(blob)
    path = folder / name
    path.write_text(json.dumps(doc))
    return path, doc, blob


def test_valid_tetra_gltf_loads(tmp_path):
    from t2bs.geometry.io import load_mesh

    path, _, _ = tetra_gltf(tmp_path)
    mesh = load_mesh(path)
    assert mesh.num_vertices == 4 and mesh.faces.shape == (4, 3)


# ------------------------------------------------------------------- code execution: checkpoints


def _tiny_recon_setup():
    sys.path.insert(0, str(Path(__file__).parent))
    from test_recon import sphere_mesh, splat_grid

    from t2bs.recon.config import preset

    mesh = sphere_mesh(1)
    v = mesh.vertices
    frames = np.stack([v, v + [0.02, 0.0, 0.0], v + [0.04, 0.01, 0.0]]).astype(np.float32)
    grid, _ = splat_grid(mesh, frames, size=32, views=3)
    cfg = preset("quick", face_gaussians=False, silhouette_band=0, mask_weight=0.5, resolution=32, static_iters=5,
                 iterations=12, global_iters=4, num_control_points=8, checkpoint_every=5, perceptual="none",
                 hidden_pick=False, track_weight=0)
    return mesh, grid, cfg


class _Payload:
    """Pickles as a call of os.system: what an attacker puts in a checkpoint."""

    def __init__(self, command: str):
        self.command = command

    def __reduce__(self):
        import os

        return (os.system, (self.command,))


def test_pickled_code_in_a_checkpoint_is_not_executed(tmp_path, capsys):
    """Regression (issue 39): a checkpoint holding a pickled os.system call used to run it on resume."""
    import torch

    from t2bs.recon.vcdgs import reconstruct_grid

    mesh, grid, cfg = _tiny_recon_setup()
    ckpt, marker = tmp_path / "ck.pt", tmp_path / "pwned"
    torch.save({"key": "k", "step": 5, "model": _Payload(f"touch {marker}")}, ckpt)
    with pytest.raises(Exception):  # the safe loader refuses it (the unsafe one would run it)
        torch.load(ckpt, weights_only=True)
    result = reconstruct_grid(mesh, grid, cfg, progress=False, checkpoint=ckpt, key="k")
    assert not marker.exists()  # the payload never ran
    assert "refused unexecuted; discarded, training starts fresh" in capsys.readouterr().err
    assert result.history["step"][0] == 0  # trained from scratch, all 12 steps
    assert np.isfinite(result.vertices).all()


def test_a_real_checkpoint_resumes_and_a_corrupt_one_is_discarded(tmp_path, capsys):
    import torch

    from t2bs.recon.vcdgs import reconstruct_grid

    mesh, grid, cfg = _tiny_recon_setup()
    ckpt = tmp_path / "ck.pt"
    reconstruct_grid(mesh, grid, cfg, progress=False, checkpoint=ckpt, key="k")
    assert ckpt.exists() and torch.load(ckpt, weights_only=True)["step"] == 10  # the safe loader reads it
    resumed = reconstruct_grid(mesh, grid, cfg, progress=False, checkpoint=ckpt, key="k")
    assert resumed.history["steps_run"] == 12 and resumed.history["step"][:2] == [0, 10]  # went on from step 10
    for bad in (b"", b"PK\x03\x04 truncated", ckpt.read_bytes()[:200]):
        ckpt.write_bytes(bad)
        again = reconstruct_grid(mesh, grid, cfg, progress=False, checkpoint=ckpt, key="k")
        assert again.history["step"][0] == 0 and "discarded, training starts fresh" in capsys.readouterr().err
    reconstruct_grid(mesh, grid, cfg, progress=False, checkpoint=ckpt, key="other")  # another key: not used
    assert "its key differs" in capsys.readouterr().err


# ------------------------------------------------------------- code execution: command templates

_WRITE_MESH = """
import sys
open(sys.argv[1] + "/mesh.obj", "w").write("v 0 0 0\\nv 1 0 0\\nv 0 1 0\\nv 0 0 1\\nf 1 3 2\\nf 1 2 4\\nf 1 4 3\\nf 2 3 4\\n")
"""

_HOSTILE_PROMPTS = ["a fox $(touch {m})", "a fox `touch {m}`", "a fox; touch {m}", "a fox' ; touch {m} ; '",
                    'a fox" ; touch {m} ; "', "a fox && touch {m} #", "a fox\n touch {m}"]


@pytest.mark.parametrize("quote", ["{prompt}", "'{prompt}'", '"{prompt}"', "--prompt={prompt}", "'--prompt {prompt}'"])
def test_command_template_never_runs_the_prompt(tmp_path, monkeypatch, quote):
    """Regression (issue 39): a template that quoted {prompt} itself let $(...), backticks and ; run."""
    from t2bs.character import backends

    script = tmp_path / "gen.py"
    script.write_text(_WRITE_MESH)
    seen = []
    real = backends.run_command

    def spy(argv, timeout, env=None):
        seen.append(argv)
        return real(argv, timeout, env)

    monkeypatch.setattr(backends, "run_command", spy)
    for i, hostile in enumerate(_HOSTILE_PROMPTS):
        marker = tmp_path / f"pwned{i}"
        prompt = hostile.format(m=marker)
        backends.generate(prompt, backend="command", command=f"{sys.executable} -S -I {script} {{out}} {quote}")
        assert not marker.exists(), (quote, prompt)
        # the prompt arrives as exactly one argument, verbatim
        want = quote.strip("'\"").replace("{prompt}", prompt)
        assert seen[-1][5:] == [want]


def test_command_template_refusals_and_timeout(tmp_path):
    from t2bs.character.backends import generate

    for tmpl, says in ((f"sh -c 'gen --prompt {{prompt}} --out {{out}}'", "shell script"),
                       (f"bash -lc \"x {{prompt}}\" {{out}}", "shell script"),
                       ("gen {prompt.__class__} {out}", "unknown placeholder {prompt.__class__}"),
                       ("gen {prompt!r} {out}", "unknown placeholder {prompt!r}"),
                       ("gen {0} {out}", "unknown placeholder {0}"),
                       ("gen 'unbalanced {out}", "cannot be parsed"),
                       ("gen {prompt {out}", "malformed placeholder"),
                       ("/no/such/program {out}", "cannot start '/no/such/program'")):
        with pytest.raises(UserError, match=re_escape(says)):
            generate("a fox", backend="command", command=tmpl)
    import time

    t0 = time.monotonic()
    with pytest.raises(UserError, match="did not finish within 1 s"):
        generate("x", backend="command", command=f"{sys.executable} -c 'import time; time.sleep(60)' {{out}}",
                 command_timeout=1)
    assert time.monotonic() - t0 < 15


def re_escape(text: str) -> str:
    import re

    return re.escape(text)


# ------------------------------------------------------------------------ glTF uri containment


@pytest.mark.parametrize("uri", ["../outside.bin", "../../../../../../etc/passwd", "/etc/passwd", ".", "sub/../../outside.bin",
                                 "file:///etc/passwd", "http://example.com/m.bin", "link.bin"])
def test_gltf_buffer_uri_stays_in_its_folder(tmp_path, uri):
    from t2bs.geometry.io import load_mesh

    inner = tmp_path / "inner"
    path, doc, blob = tetra_gltf(inner)
    (tmp_path / "outside.bin").write_bytes(blob)  # a readable, valid buffer outside the folder
    (inner / "link.bin").symlink_to(tmp_path / "outside.bin")
    doc["buffers"][0]["uri"] = uri
    path.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="outside the glTF file's folder|not a relative file name"):
        load_mesh(path)
