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
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"uri": bin_name, "byteLength": len(blob)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 48},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 1]},
            {"bufferView": 1, "componentType": 5125, "count": 12, "type": "SCALAR"},
        ],
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
    cfg = preset(
        "quick",
        face_gaussians=False,
        silhouette_band=0,
        mask_weight=0.5,
        resolution=32,
        static_iters=5,
        iterations=12,
        global_iters=4,
        num_control_points=8,
        checkpoint_every=5,
        perceptual="none",
        hidden_pick=False,
        track_weight=0,
    )
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

_HOSTILE_PROMPTS = [
    "a fox $(touch {m})",
    "a fox `touch {m}`",
    "a fox; touch {m}",
    "a fox' ; touch {m} ; '",
    'a fox" ; touch {m} ; "',
    "a fox && touch {m} #",
    "a fox\n touch {m}",
]


@pytest.mark.parametrize("quote", ["{prompt}", "'{prompt}'", '"{prompt}"', "--prompt={prompt}", "'--prompt {prompt}'"])
def test_command_template_never_runs_the_prompt(tmp_path, monkeypatch, quote):
    """Regression (issue 39): a template that quoted {prompt} itself let $(...), backticks and ; run."""
    from t2bs.character import backends

    script = tmp_path / "gen.py"
    script.write_text(_WRITE_MESH)
    seen = []
    real = backends.run_argv

    def spy(argv, timeout, env=None):
        seen.append(argv)
        return real(argv, timeout, env)

    monkeypatch.setattr(backends, "run_argv", spy)
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

    for tmpl, says in (
        ("sh -c 'gen --prompt {prompt} --out {out}'", "shell script"),
        ('bash -lc "x {prompt}" {out}', "shell script"),
        ("python3 -c \"print('{prompt}')\" {out}", "inline code"),
        ("/usr/bin/env perl -e 'print q({prompt})' {out}", "inline code"),
        ("gen {prompt.__class__} {out}", "unknown placeholder {prompt.__class__}"),
        ("gen {prompt!r} {out}", "unknown placeholder {prompt!r}"),
        ("gen {0} {out}", "unknown placeholder {0}"),
        ("gen 'unbalanced {out}", "cannot be parsed"),
        ("gen {prompt {out}", "malformed placeholder"),
        ("/no/such/program {out}", "cannot start '/no/such/program'"),
    ):
        with pytest.raises(UserError, match=re_escape(says)):
            generate("a fox", backend="command", command=tmpl)
    import time

    t0 = time.monotonic()
    with pytest.raises(UserError, match="did not finish within 1 s"):
        generate(
            "x",
            backend="command",
            command=f"{sys.executable} -c 'import time; time.sleep(60)' {{out}}",
            command_timeout=1,
        )
    assert time.monotonic() - t0 < 15


def re_escape(text: str) -> str:
    import re

    return re.escape(text)


# ------------------------------------------------------------------------ glTF uri containment


@pytest.mark.parametrize(
    "uri",
    [
        "../outside.bin",
        "../../../../../../etc/passwd",
        "/etc/passwd",
        "sub/../../outside.bin",
        "file:///etc/passwd",
        "http://example.com/m.bin",
        "link.bin",
    ],
)
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


# ------------------------------------------------------------------------ a good project, once

GOOD_PROMPT = "a cartoon fox"


@pytest.fixture(scope="module")
def good_project(tmp_path_factory):
    """A small finished project (character, one 3-view 3-frame grid, its reconstruction, blendshapes),
    made through the CLI; the reconstruction is the grid's ground truth (VCDGS itself is tested elsewhere)."""
    import pytest as _pytest

    from t2bs.project import mark_done

    root = tmp_path_factory.mktemp("good") / "proj"
    capsys = _NullCapture()
    for argv in (
        ["character", GOOD_PROMPT, "-o", root, "--size", 32],
        ["videos", root, "--prompts", "smiling", "--samples", 1, "--frames", 3, "--size", 32, "--views", 3],
    ):
        rc, _, err = run_cli(argv, capsys)
        assert rc == 0, err
    recon = root / "recon" / "smiling-s0"
    recon.mkdir(parents=True)
    np.save(recon / "vertices.npy", np.load(root / "videos" / "smiling-s0" / "gt_vertices.npy"))
    mark_done(recon, "fixture")
    rc, _, err = run_cli(["blendshapes", root], capsys)
    assert rc == 0, err
    # A previous retargeting result: a refused re-run must leave all four files as they are.
    drv = root / "retarget" / "drv"
    drv.mkdir(parents=True)
    (drv / "weights.csv").write_text("frame,time,s0\n0,0.0000,0.100000\n")
    (drv / "animation.glb").write_bytes((root / "blendshapes" / "model.glb").read_bytes())
    (drv / "preview.mp4").write_bytes(b"\0\0\0\x18ftypmp42 previous preview")
    (drv / "report.json").write_text('{"frames": 1}\n')
    if not (root / "blendshapes" / "model.npz").exists():
        _pytest.fail("fixture project incomplete")
    return root


class _NullCapture:
    """capsys stand-in for the module fixture (output is not checked there)."""

    def readouterr(self):
        class _R:
            out = err = ""

        return _R()


def project_files(root: Path) -> dict[str, bytes]:
    """snapshot() without the lock file (its text names the last holder; it is not project data)."""
    from t2bs.project import LOCK_NAME

    return {k: v for k, v in snapshot(root).items() if k != LOCK_NAME}


@pytest.fixture
def project(good_project, tmp_path):
    """A private copy of the good project, and its files as they were."""
    import shutil

    root = tmp_path / "proj"
    shutil.copytree(good_project, root)
    return root, project_files(root)


# ------------------------------------------------------------------- family: broken mesh files


def _glb_bytes(doc: dict, blob: bytes) -> bytes:
    """A .glb container around a glTF JSON dict and a binary chunk (no external uri)."""
    doc = json.loads(json.dumps(doc))
    doc["buffers"] = [{"byteLength": len(blob)}]
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + blob
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


def _gltf_case(edit):
    """A case that writes the tetrahedron .gltf, applies ``edit(doc, folder) -> blob or None`` and returns the path."""

    def make(folder: Path) -> Path:
        path, doc, blob = tetra_gltf(folder)
        new_blob = edit(doc, folder)
        if new_blob is not None:
            (folder / "m.bin").write_bytes(new_blob)
        path.write_text(json.dumps(doc))
        return path

    return make


def _file_case(name: str, data: bytes | str):
    def make(folder: Path) -> Path:
        path = folder / name
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
        return path

    return make


def _set(doc, keys, value):
    node = doc
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value


def _big_obj(folder: Path) -> Path:
    path = folder / "big.obj"
    n = 40  # 40 x 40 grid: 1600 vertices, over the T2BS_MAX_VERTICES=1000 the test sets
    lines = [f"v {i % n} {i // n} {(i * 7) % 3}" for i in range(n * n)]
    lines += [f"f {i + 1} {i + 2} {i + n + 1}" for i in range(n * (n - 1)) if (i + 1) % n]
    path.write_text("\n".join(lines))
    return path


def _tetra_glb(doc, folder):
    blob = (folder / "m.bin").read_bytes()
    (folder / "m.glb").write_bytes(_glb_bytes(doc, blob)[:-20])  # a GLB cut short
    return None


MESH_CASES = {
    "truncated buffer": _gltf_case(lambda d, f: (f / "m.bin").read_bytes()[:60]),
    "index count not a multiple of 3": _gltf_case(lambda d, f: _set(d, ["accessors", 1, "count"], 11)),
    "bad componentType": _gltf_case(lambda d, f: _set(d, ["accessors", 0, "componentType"], 9999)),
    "float indices": _gltf_case(lambda d, f: _set(d, ["accessors", 1, "componentType"], 5126)),
    "bad accessor type": _gltf_case(lambda d, f: _set(d, ["accessors", 0, "type"], "VEC7")),
    "node is its own child": _gltf_case(lambda d, f: _set(d, ["nodes", 0, "children"], [0])),
    "node cycle of two": _gltf_case(
        lambda d, f: d.__setitem__("nodes", [{"mesh": 0, "children": [1]}, {"children": [0]}])
    ),
    "node index out of range": _gltf_case(lambda d, f: _set(d, ["scenes", 0, "nodes"], [5])),
    "negative node index": _gltf_case(lambda d, f: _set(d, ["scenes", 0, "nodes"], [-1])),
    "mesh index out of range": _gltf_case(lambda d, f: _set(d, ["nodes", 0, "mesh"], 3)),
    "scene index out of range": _gltf_case(lambda d, f: d.__setitem__("scene", 4)),
    "accessor index out of range": _gltf_case(
        lambda d, f: _set(d, ["meshes", 0, "primitives", 0, "attributes", "POSITION"], 9)
    ),
    "bufferView index out of range": _gltf_case(lambda d, f: _set(d, ["accessors", 0, "bufferView"], 7)),
    "buffer index out of range": _gltf_case(lambda d, f: _set(d, ["bufferViews", 0, "buffer"], 2)),
    "material index out of range": _gltf_case(lambda d, f: _set(d, ["meshes", 0, "primitives", 0, "material"], 3)),
    "missing texture file": _gltf_case(
        lambda d, f: (
            d.update(
                {
                    "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
                    "textures": [{"source": 0}],
                    "images": [{"uri": "gone.png"}],
                }
            ),
            _set(d, ["meshes", 0, "primitives", 0, "attributes", "TEXCOORD_0"], 0),
            _set(d, ["meshes", 0, "primitives", 0, "material"], 0),
        )[-1]
    ),
    "texture index out of range": _gltf_case(
        lambda d, f: (
            d.update({"materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 5}}}]}),
            _set(d, ["meshes", 0, "primitives", 0, "attributes", "TEXCOORD_0"], 0),
            _set(d, ["meshes", 0, "primitives", 0, "material"], 0),
        )[-1]
    ),
    "buffer uri '.'": _gltf_case(lambda d, f: _set(d, ["buffers", 0, "uri"], ".")),
    "buffer uri outside the folder": _gltf_case(lambda d, f: _set(d, ["buffers", 0, "uri"], "../../../../etc/passwd")),
    "buffer file missing": _gltf_case(lambda d, f: _set(d, ["buffers", 0, "uri"], "nope.bin")),
    "buffer .bin is a folder": _gltf_case(
        lambda d, f: ((f / "dir.bin").mkdir(), _set(d, ["buffers", 0, "uri"], "dir.bin"))[1]
    ),
    "malformed data uri": _gltf_case(
        lambda d, f: _set(d, ["buffers", 0, "uri"], "data:application/octet-stream;base64,@@@")
    ),
    "huge accessor count": _gltf_case(lambda d, f: _set(d, ["accessors", 0, "count"], 1 << 40)),
    "NaN vertex": _gltf_case(
        lambda d, f: np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32).tobytes()
        + (f / "m.bin").read_bytes()[48:]
    ),
    "face index past the vertices": _gltf_case(
        lambda d, f: (f / "m.bin").read_bytes()[:48]
        + np.array([0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 9], np.uint32).tobytes()
    ),
    "zero-area faces": _gltf_case(
        lambda d, f: np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], np.float32).tobytes()
        + (f / "m.bin").read_bytes()[48:]
    ),
    "no meshes": _gltf_case(lambda d, f: d.__setitem__("meshes", [])),
    "points, not triangles": _gltf_case(lambda d, f: _set(d, ["meshes", 0, "primitives", 0, "mode"], 0)),
    "json garbage .gltf": _file_case("x.gltf", "{not json"),
    "empty .glb": _file_case("e.glb", b""),
    "random bytes .glb": _file_case("r.glb", bytes(range(256)) * 4),
    "truncated .glb": _gltf_case(_tetra_glb),
    "obj text garbage": _file_case("g.obj", "hello world\nthis is not a mesh\n"),
    "ply with points only": _file_case(
        "p.ply",
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n",
    ),
    "unsupported suffix": _file_case("m.txt", "v 0 0 0"),
    "mesh over the size limit": _big_obj,
}


def _mesh_path(name: str, folder: Path) -> Path:
    path = MESH_CASES[name](folder)
    if name == "truncated .glb":
        path = folder / "m.glb"
    return path


@pytest.mark.parametrize("name", list(MESH_CASES))
def test_broken_mesh_is_one_error_line(name, good_project, tmp_path, capsys, monkeypatch):
    """`t2bs render BAD -o GOOD`: refused before anything in the good project is touched."""
    monkeypatch.setenv("T2BS_MAX_VERTICES", "1000")
    before = project_files(good_project)
    folder = tmp_path / "in" / "deep"
    folder.mkdir(parents=True)
    bad = _mesh_path(name, folder)
    rc, _, err = run_cli(["render", bad, "-o", good_project, "--size", 32], capsys)
    assert_one_error(rc, err)
    assert project_files(good_project) == before


def test_size_limit_message_names_counts_and_decimation(tmp_path, monkeypatch):
    from t2bs.geometry.io import load_mesh

    monkeypatch.setenv("T2BS_MAX_VERTICES", "1000")
    with pytest.raises(UserError, match=r"1,5\d\d vertices .* over the limit of 1,000 vertices.*Decimate"):
        load_mesh(_big_obj(tmp_path))
    monkeypatch.setenv("T2BS_MAX_VERTICES", "2000")
    assert load_mesh(_big_obj(tmp_path)).num_vertices == 1599  # trimesh drops the one unused vertex


# -------------------------------------------------------- family: bad options and command lines

BAD_OPTIONS = {
    # reconstruct: NaN / out-of-range --set values and options (issue 39: tracebacks or silent acceptance)
    "set lr_deform=nan": ["reconstruct", "{P}", "--set", "lr_deform=nan"],
    "set huber_delta=nan": ["reconstruct", "{P}", "--set", "huber_delta=nan"],
    "set time_budget_s=nan": ["reconstruct", "{P}", "--set", "time_budget_s=nan"],
    "set threads=-1": ["reconstruct", "{P}", "--set", "threads=-1"],
    "set holdout_views=99": ["reconstruct", "{P}", "--set", "holdout_views=99", "--iterations", "2"],
    "set lr_final_ratio=2": ["reconstruct", "{P}", "--set", "lr_final_ratio=2"],
    "set canonical_fraction=inf": ["reconstruct", "{P}", "--set", "canonical_fraction=inf"],
    "set knn=0": ["reconstruct", "{P}", "--set", "knn=0"],
    "set perceptual=bogus": ["reconstruct", "{P}", "--set", "perceptual=bogus"],
    "set unknown key": ["reconstruct", "{P}", "--set", "no_such=1"],
    "set without =": ["reconstruct", "{P}", "--set", "knn"],
    "set 10k-character value": ["reconstruct", "{P}", "--set", "knn=" + "9" * 10000 + "x"],
    "device cuda without a GPU": ["reconstruct", "{P}", "--device", "cuda"],
    "device bogus": ["reconstruct", "{P}", "--device", "tpu"],
    "iterations -5": ["reconstruct", "{P}", "--iterations", "-5"],
    "workers 0": ["reconstruct", "{P}", "--workers", "0"],
    "unknown preset": ["reconstruct", "{P}", "--preset", "nope"],
    "unknown method": ["reconstruct", "{P}", "--method", "bogus"],
    "unknown video id": ["reconstruct", "{P}", "--videos", "nope"],
    # videos
    "videos --size abc": ["videos", "{P}", "--size", "abc"],
    "videos --size 0": ["videos", "{P}", "--size", "0"],
    "videos 1 frame": [
        "videos",
        "{P}",
        "--frames",
        "1",
        "--size",
        "32",
        "--views",
        "3",
        "--prompts",
        "smiling",
        "--samples",
        "1",
    ],
    "videos even views": ["videos", "{P}", "--views", "4"],
    "videos 0 samples": ["videos", "{P}", "--samples", "0"],
    "videos unknown defects": ["videos", "{P}", "--defects", "bogus"],
    "videos unknown expression": ["videos", "{P}", "--prompts", "juggling wildly"],
    "videos unknown backend": ["videos", "{P}", "--backend", "nope"],
    "videos unknown shading": ["videos", "{P}", "--shading", "nope"],
    "videos import text as .mp4": ["videos", "{P}", "--import-grid", "{T}/views", "--expression", "smiling"],
    "videos 10k-character expression": ["videos", "{P}", "--prompts", "smiling " * 1250],
    "videos import missing": ["videos", "{P}", "--import-grid", "{T}/nothing", "--expression", "smiling"],
    # character / render / create
    "character --size abc": ["character", "a fox", "-o", "{P}", "--size", "abc"],
    "character --size 3": ["character", "a fox", "-o", "{P}", "--size", "3"],
    "character empty prompt": ["character", "  ", "-o", "{P}"],
    "character unknown backend": ["character", "a fox", "-o", "{P}", "--backend", "nope"],
    "character sh -c template": [
        "character",
        "a fox",
        "-o",
        "{P}",
        "--backend",
        "command",
        "--command",
        "sh -c 'gen {prompt} {out}'",
    ],
    "character {prompt.foo} template": [
        "character",
        "a fox",
        "-o",
        "{P}",
        "--backend",
        "command",
        "--command",
        "gen {prompt.foo} {out}",
    ],
    "character template without {out}": [
        "character",
        "a fox",
        "-o",
        "{P}",
        "--backend",
        "command",
        "--command",
        "gen {prompt}",
    ],
    "character command timeout nan": [
        "character",
        "a fox",
        "-o",
        "{P}",
        "--backend",
        "command",
        "--command",
        "gen {out}",
        "--command-timeout",
        "nan",
    ],
    "character missing diffusers weights": [
        "character",
        "a fox",
        "-o",
        "{P}",
        "--backend",
        "diffusers",
        "--checkpoint",
        "{T}/none",
    ],
    "render unreadable mesh path": ["render", "{T}/none.glb", "-o", "{P}"],
    "render mesh is a folder": ["render", "{T}", "-o", "{P}"],
    "render --views 0": ["render", "{T}/ok.obj", "-o", "{P}", "--views", "0"],
    "render unknown shading": ["render", "{T}/ok.obj", "-o", "{P}", "--shading", "nope"],
    "render unknown facing": ["render", "{T}/ok.obj", "-o", "{P}", "--facing", "sideways"],
    "render into a file": ["render", "{T}/ok.obj", "-o", "{T}/ok.obj"],
    "create unknown preset": ["create", "a fox", "-o", "{P}", "--preset", "nope"],
    "create workers 0": ["create", "a fox", "-o", "{P}", "--workers", "0"],
    # blendshapes
    "blendshapes components 0": ["blendshapes", "{P}", "--components", "0"],
    "blendshapes fps nan": ["blendshapes", "{P}", "--fps", "nan", "--force"],
    "blendshapes unknown source": ["blendshapes", "{P}", "--source", "bogus"],
    "blendshapes unknown animation": ["blendshapes", "{P}", "--animation", "nope", "--force"],
    # landmarks / retarget
    "landmarks unknown backend": ["landmarks", "{P}", "--backend", "bogus"],
    "landmarks override missing": ["landmarks", "{P}", "--override", "{T}/none.json"],
    "landmarks override garbage": ["landmarks", "{P}", "--override", "{T}/garbage.json"],
    "retarget driver missing": ["retarget", "{P}", "--driver", "{T}/none.mp4"],
    "retarget text file named .mp4": ["retarget", "{P}", "--driver", "{T}/text.mp4"],
    "retarget empty driver folder": ["retarget", "{P}", "--driver", "{T}/empty"],
    "retarget smooth nan": ["retarget", "{P}", "--driver", "{T}/text.mp4", "--smooth", "nan"],
    "retarget size 0": ["retarget", "{P}", "--driver", "{T}/text.mp4", "--size", "0"],
    "retarget max-frames 0": ["retarget", "{P}", "--driver", "{T}/text.mp4", "--max-frames", "0"],
    # the viewer
    "view unbindable host": ["view", "{P}", "--host", "10.255.255.1"],
    "view unresolvable host": ["view", "{P}", "--host", "no-such-host.invalid"],
    "view port 70000": ["view", "{P}", "--port", "70000"],
    "view missing project": ["view", "{T}/none"],
    # the command line itself
    "unknown command": ["frobnicate", "{P}"],
    "unknown option": ["render", "--bogus"],
    "missing argument": ["reconstruct"],
}


def _inputs(folder: Path) -> None:
    """The small files the option cases point at ({T})."""
    (folder / "text.mp4").write_text("this is a text file, not a video\n" * 20)
    (folder / "garbage.json").write_text("{garbage")
    (folder / "empty").mkdir()
    (folder / "views").mkdir()
    (folder / "views" / "view00.mp4").write_text("not a video")
    (folder / "ok.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")


@pytest.mark.parametrize("name", list(BAD_OPTIONS))
def test_bad_option_is_one_error_line(name, good_project, tmp_path, capsys):
    before = project_files(good_project)
    _inputs(tmp_path)
    argv = [a.replace("{P}", str(good_project)).replace("{T}", str(tmp_path)) for a in BAD_OPTIONS[name]]
    rc, _, err = run_cli(argv, capsys)
    assert_one_error(rc, err)
    assert project_files(good_project) == before


# ------------------------------------------------- family: broken files inside a project folder


def _npy_bytes(arr) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def _nan_model(root: Path) -> bytes:
    with np.load(root / "blendshapes" / "model.npz", allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    data["basis"] = data["basis"].copy()
    data["basis"][0, 0, 0] = np.nan
    import io

    buf = io.BytesIO()
    np.savez(buf, **data)
    return buf.getvalue()


def _recon_vertices(root: Path, fn) -> bytes:
    return _npy_bytes(fn(np.load(root / "recon" / "smiling-s0" / "vertices.npy")))


GRID = "videos/smiling-s0"
PROJECT_CASES = {
    # (file in the project, new bytes from the project root, command)
    "mesh.glb truncated -> reconstruct": (
        "character/mesh.glb",
        lambda r: (r / "character/mesh.glb").read_bytes()[:500],
        ["reconstruct", "{P}", "--iterations", "2"],
    ),
    "mesh.glb truncated -> blendshapes": (
        "character/mesh.glb",
        lambda r: (r / "character/mesh.glb").read_bytes()[:500],
        ["blendshapes", "{P}", "--force"],
    ),
    "mesh.glb empty -> videos": ("character/mesh.glb", lambda r: b"", ["videos", "{P}", "--seed", "4"]),
    "mesh.glb garbage -> landmarks": ("character/mesh.glb", lambda r: b"glTF garbage" * 9, ["landmarks", "{P}"]),
    "mesh.glb garbage -> view": ("character/mesh.glb", lambda r: b"glTF garbage" * 9, ["view", "{P}", "--port", "0"]),
    "grid.json garbage -> reconstruct": (
        f"{GRID}/grid.json",
        lambda r: b"{garbage",
        ["reconstruct", "{P}", "--iterations", "2"],
    ),
    "grid.json a list -> reconstruct": (
        f"{GRID}/grid.json",
        lambda r: b"[1, 2]",
        ["reconstruct", "{P}", "--iterations", "2"],
    ),
    "cameras.json garbage -> reconstruct": (
        f"{GRID}/cameras.json",
        lambda r: b"\xff\xfe",
        ["reconstruct", "{P}", "--iterations", "2"],
    ),
    "frame png truncated -> reconstruct": (
        f"{GRID}/frames/view00/0001.png",
        lambda r: (r / GRID / "frames/view00/0001.png").read_bytes()[:40],
        ["reconstruct", "{P}", "--iterations", "2"],
    ),
    "masks.npz garbage -> reconstruct": (
        f"{GRID}/masks.npz",
        lambda r: b"PK\x03\x04garbage",
        ["reconstruct", "{P}", "--iterations", "2"],
    ),
    "gt_vertices.npy empty -> blendshapes": (
        f"{GRID}/gt_vertices.npy",
        lambda r: b"",
        ["blendshapes", "{P}", "--source", "gt", "--force"],
    ),
    "gt_vertices.npy NaN -> blendshapes": (
        f"{GRID}/gt_vertices.npy",
        lambda r: _npy_bytes(np.full((3, 4, 3), np.nan, np.float32)),
        ["blendshapes", "{P}", "--source", "gt", "--force"],
    ),
    "vertices.npy empty -> blendshapes": (
        "recon/smiling-s0/vertices.npy",
        lambda r: b"",
        ["blendshapes", "{P}", "--force"],
    ),
    "vertices.npy zero frames -> blendshapes": (
        "recon/smiling-s0/vertices.npy",
        lambda r: _recon_vertices(r, lambda v: v[:0]),
        ["blendshapes", "{P}", "--force"],
    ),
    "vertices.npy NaN -> blendshapes": (
        "recon/smiling-s0/vertices.npy",
        lambda r: _recon_vertices(r, lambda v: v * np.nan),
        ["blendshapes", "{P}", "--force"],
    ),
    "vertices.npy [T, N, 2] -> blendshapes": (
        "recon/smiling-s0/vertices.npy",
        lambda r: _recon_vertices(r, lambda v: v[..., :2]),
        ["blendshapes", "{P}", "--force"],
    ),
    "vertices.npy wrong N -> blendshapes": (
        "recon/smiling-s0/vertices.npy",
        lambda r: _recon_vertices(r, lambda v: v[:, :7]),
        ["blendshapes", "{P}", "--force"],
    ),
    "vertices.npy pickled object -> blendshapes": (
        "recon/smiling-s0/vertices.npy",
        lambda r: _npy_bytes(np.array([{"a": 1}], dtype=object)),
        ["blendshapes", "{P}", "--force"],
    ),
    "model.npz NaN -> retarget": (
        "blendshapes/model.npz",
        _nan_model,
        ["retarget", "{P}", "--driver", "{T}/text.mp4", "-o", "{P}/retarget/drv"],
    ),
    "model.npz garbage -> retarget": (
        "blendshapes/model.npz",
        lambda r: b"garbage",
        ["retarget", "{P}", "--driver", "{T}/text.mp4", "-o", "{P}/retarget/drv"],
    ),
    "model.npz garbage -> landmarks": ("blendshapes/model.npz", lambda r: b"garbage", ["landmarks", "{P}"]),
}


@pytest.mark.parametrize("name", list(PROJECT_CASES))
def test_broken_project_file_is_one_error_line(name, project, tmp_path, capsys):
    """A damaged file in a project: one error line naming it, and the command changes nothing."""
    root, _ = project
    rel, make, argv = PROJECT_CASES[name]
    (root / rel).write_bytes(make(root))
    before = project_files(root)
    _inputs(tmp_path)
    argv = [a.replace("{P}", str(root)).replace("{T}", str(tmp_path)) for a in argv]
    rc, _, err = run_cli(argv, capsys)
    assert_one_error(rc, err)
    assert project_files(root) == before


def test_nan_model_leaves_the_previous_retarget_outputs(project, tmp_path, capsys):
    """Issue 39: a NaN in model.npz wrote an all-NaN weights.csv over the good one."""
    root, _ = project
    (root / "blendshapes" / "model.npz").write_bytes(_nan_model(root))
    before = snapshot(root / "retarget" / "drv")
    _inputs(tmp_path)
    rc, _, err = run_cli(["retarget", root, "--driver", tmp_path / "text.mp4"], capsys)
    assert_one_error(rc, err, "model.npz", "NaN")
    assert snapshot(root / "retarget" / "drv") == before and len(before) == 4


def test_corrupt_manifest_landmarks_and_done_markers_recover(project, capsys):
    """Derived files that can be remade are remade, with a warning, instead of failing every re-run."""
    from t2bs.project import Project, is_done
    from t2bs.retarget.stage import _read_landmarks

    root, _ = project
    (root / "manifest.json").write_text("{torn")
    assert Project(root).manifest() == {"stages": {}}
    assert "manifest.json: not valid JSON" in capsys.readouterr().err
    (root / "landmarks").mkdir(exist_ok=True)
    for bad in (
        "{torn",
        '{"vertex_ids": [1, 2]}',
        '{"vertex_ids": ' + json.dumps(list(range(10**6, 10**6 + 20))) + "}",
    ):
        (root / "landmarks" / "landmarks.json").write_text(bad)
        assert _read_landmarks(root / "landmarks" / "landmarks.json", 100) is None
        assert "detecting the landmarks again" in capsys.readouterr().out
    for bad in ("{torn", "[]", '"text"'):
        (root / GRID / "done.json").write_text(bad)
        assert not is_done(root / GRID, "any")


# ------------------------------------------------- family: faults (read-only, full disk, permission)


def _fail_on(monkeypatch, what: str, err: int):
    import errno
    import os as _os
    import tempfile as _tempfile

    import t2bs.project as proj

    text = _os.strerror(err)
    if what == "mkstemp":  # no file can be created (read-only file system, no permission)

        def fake(*a, **k):
            raise OSError(err, text, str(k.get("dir", "?")))

        monkeypatch.setattr(_tempfile, "mkstemp", fake)
    elif what == "replace":  # the disk fills up while the outputs are put in place

        def fake(src, dst, *a, **k):
            raise OSError(err, text, str(src), str(dst))

        monkeypatch.setattr(_os, "replace", fake)
    elif what == "lock":  # the project folder itself is not writable

        def fake(path, *a, **k):
            raise OSError(err, text, str(path))

        monkeypatch.setattr(proj, "open", fake, raising=False)
    assert errno.errorcode[err]


FAULTS = {"read-only": ("mkstemp", 30), "disk full": ("replace", 28), "no permission": ("lock", 13)}
FAULT_COMMANDS = {
    "render": ["render", "{T}/ok.obj", "-o", "{P}", "--size", "16", "--views", "1"],
    "character": ["character", "a fox", "-o", "{P}", "--size", "16"],
    "videos": [
        "videos",
        "{P}",
        "--seed",
        "5",
        "--frames",
        "2",
        "--size",
        "16",
        "--views",
        "1",
        "--prompts",
        "smiling",
        "--samples",
        "1",
    ],
    "blendshapes": ["blendshapes", "{P}", "--force"],
    "landmarks": ["landmarks", "{P}", "--backend", "parts"],
}


@pytest.mark.parametrize("command", list(FAULT_COMMANDS))
@pytest.mark.parametrize("fault", list(FAULTS))
def test_fault_is_one_error_line_with_the_path(fault, command, project, tmp_path, capsys, monkeypatch):
    import errno
    import os as _os

    root, _ = project
    _inputs(tmp_path)
    before = project_files(root)
    what, err = FAULTS[fault]
    argv = [a.replace("{P}", str(root)).replace("{T}", str(tmp_path)) for a in FAULT_COMMANDS[command]]
    _fail_on(monkeypatch, what, err)
    rc, _, out = run_cli(argv, capsys)
    monkeypatch.undo()
    assert_one_error(rc, out, _os.strerror(err) if what != "lock" else "cannot write to the project folder", str(root))
    after = project_files(root)
    if what == "replace":  # the staged outputs never reached the project: nothing there changed
        assert after == before
    else:
        assert after == before
    assert errno.errorcode[err]


# --------------------------------------------------------------- two runs, a kill, an interrupt


_HOLD_LOCK = """
import sys, time
from t2bs.project import project_lock
with project_lock(sys.argv[1], "reconstruct"):
    print("locked", flush=True)
    time.sleep(120)
"""


def test_second_run_on_a_project_is_refused_while_the_first_holds_it(project, capsys):
    import os as _os

    root, before = project
    env = {**_os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}
    holder = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(root)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert holder.stdout.readline().strip() == "locked"
        rc, _, err = run_cli(["blendshapes", root, "--force"], capsys)
        assert_one_error(
            rc, err, "another t2bs command is working on this project", f"pid {holder.pid}", "t2bs reconstruct"
        )
        assert project_files(root) == before
    finally:
        holder.kill()  # kill -9: the kernel drops the lock with the process
        holder.wait()
    rc, _, err = run_cli(["blendshapes", root, "--force"], capsys)
    assert rc == 0, err


def _grid_files(root: Path) -> dict[str, bytes]:
    return {k: v for k, v in snapshot(root / GRID).items() if not k.startswith(".")}


def test_videos_rerun_killed_midway_leaves_the_previous_grid_whole(project, capsys):
    """Issue 39: a re-run killed while regenerating a grid left the old done.json beside new frames."""
    import os as _os
    import signal
    import time

    from t2bs.project import content_key

    root, _ = project
    grid_before, key_before = _grid_files(root), content_key(root / GRID)
    settings = ["--prompts", "smiling", "--samples", "1", "--size", "32", "--views", "3"]
    env = {**_os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src"), "OMP_NUM_THREADS": "1"}
    # Other settings (more frames) regenerate the grid; kill -9 once its new frames are being written.
    run = subprocess.Popen(
        [sys.executable, "-m", "t2bs.cli", "videos", str(root), *settings, "--frames", "40"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not list((root / GRID).glob(".t2bs-staging-*/frames/view00/0000.png")):
        time.sleep(0.01)
    run.send_signal(signal.SIGKILL)
    run.wait()
    assert run.returncode == -signal.SIGKILL
    assert _grid_files(root) == grid_before  # the previous grid and its done.json, untouched
    assert content_key(root / GRID) == key_before  # the killed run's staging folder is not content
    # The next run with the old settings: up to date, and the grid loads; the new settings: made.
    rc, out, err = run_cli(["videos", root, *settings, "--frames", "3"], capsys)
    assert rc == 0 and "0 made, 1 up to date" in out, err
    from t2bs.video.grid import load_grid

    assert load_grid(root / GRID).num_frames == 3
    rc, out, err = run_cli(["videos", root, *settings, "--frames", "4"], capsys)
    assert rc == 0 and "1 made" in out, err
    assert load_grid(root / GRID).num_frames == 4 and not list((root / GRID).glob(".t2bs-staging-*"))


def test_ctrl_c_prints_the_interrupted_message(project, capsys, monkeypatch):
    import t2bs.video.stage as vc
    from t2bs.errors import INTERRUPTED

    root, before = project

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(vc, "make_grid", interrupted)
    rc, _, err = run_cli(
        [
            "videos",
            root,
            "--seed",
            "9",
            "--frames",
            "2",
            "--size",
            "16",
            "--views",
            "1",
            "--prompts",
            "smiling",
            "--samples",
            "1",
        ],
        capsys,
    )
    assert rc == 130 and INTERRUPTED in err and "Traceback" not in err
    assert project_files(root) == before


def test_outputs_get_the_users_umask(tmp_path):
    import os as _os

    from t2bs.project import write_json

    old = _os.umask(0o027)
    try:
        write_json(tmp_path / "a.json", {"x": 1})
    finally:
        _os.umask(old)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o640
    write_json(tmp_path / "b.json", {"x": 1})
    assert (tmp_path / "b.json").stat().st_mode & 0o777 == 0o666 & ~old


def test_viewer_exits_at_once_on_an_unbindable_host(good_project):
    import os as _os
    import time

    env = {**_os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-m", "t2bs.cli", "view", str(good_project), "--host", "10.255.255.1"],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert r.returncode == 2 and r.stderr.count("error:") == 1 and "cannot listen" in r.stderr, r.stderr
    assert time.monotonic() - t0 < 30


def test_import_grid_takes_a_flat_folder_with_the_default_views(project, tmp_path, capsys):
    """Issue 39: a flat folder of V x T images was refused even with --views (15, the default)."""
    from PIL import Image

    from t2bs.video.grid import load_grid

    root, _ = project
    flat = tmp_path / "flat"
    flat.mkdir()
    for i in range(15 * 2):  # view-major: view 0's two frames first
        Image.fromarray(np.full((16, 16, 3), i * 8, np.uint8)).save(flat / f"img{i:03d}.png")
    rc, out, err = run_cli(
        [
            "videos",
            root,
            "--import-grid",
            flat,
            "--expression",
            "smiling",
            "--sample",
            1,
            "--views",
            15,
            "--shading",
            "unlit",
        ],
        capsys,
    )
    assert rc == 0, err
    grid = load_grid(root / "videos" / "smiling-s1")
    assert grid.frames.shape == (15, 2, 16, 16, 3) and grid.frames[1, 0, 0, 0, 0] == 16  # view 1, frame 0 = image 2


def test_lock_is_reentrant_and_a_failed_command_leaves_no_new_folder(tmp_path, capsys):
    from t2bs.project import LOCK_NAME, project_lock

    with project_lock(tmp_path / "p", "create"):
        with project_lock(tmp_path / "p", "character"):  # `t2bs create` runs the stage commands
            assert (tmp_path / "p" / LOCK_NAME).read_text().startswith("pid ")
    rc, _, err = run_cli(["render", tmp_path / "none.glb", "-o", tmp_path / "new"], capsys)
    assert_one_error(rc, err, "no such file")
    assert not (tmp_path / "new").exists()


def test_output_set_replaces_a_set_whole_or_not_at_all(tmp_path):
    import gc

    from t2bs.project import STAGING_PREFIX, OutputSet, output_set

    final = tmp_path / "out"
    final.mkdir()
    for name, text in (("weights.csv", "old"), ("report.json", "old"), ("mine.txt", "the user's")):
        (final / name).write_text(text)
    with pytest.raises(RuntimeError):  # a failure half-way: nothing in `final` changed, no staging left
        with output_set(final, marker="report.json") as stage:
            (stage / "weights.csv").write_text("new")
            raise RuntimeError("solve failed")
    assert {p.name: p.read_text() for p in final.iterdir()} == {
        "weights.csv": "old",
        "report.json": "old",
        "mine.txt": "the user's",
    }
    staged = OutputSet(final, marker="report.json")  # never committed: removed when the object goes
    (staged.folder / "weights.csv").write_text("half")
    del staged
    gc.collect()
    assert not list(final.glob(STAGING_PREFIX + "*"))
    with output_set(final, marker="report.json") as stage:
        for name in ("weights.csv", "report.json"):
            (stage / name).write_text("new")
    assert {p.name: p.read_text() for p in final.iterdir()} == {
        "weights.csv": "new",
        "report.json": "new",
        "mine.txt": "the user's",
    }
    with output_set(final, marker="done.json", exclusive=True) as stage:  # a folder that holds only this set
        (stage / "done.json").write_text("{}")
    assert sorted(p.name for p in final.iterdir()) == ["done.json"]
