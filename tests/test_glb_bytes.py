"""One glTF writer: ``t2bs.geometry.io.glb_bytes`` is what ``save_mesh`` writes and what the viewer sends to the browser."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from t2bs.geometry.io import glb_bytes, load_mesh, save_mesh
from t2bs.geometry.mesh import Mesh

sys.path.insert(0, str(Path(__file__).parent))
from viewer_fixture import build_fixture_project, colours, sphere  # noqa: E402


def _rigged_sphere() -> Mesh:
    v, f = sphere(2)
    rng = np.random.default_rng(3)
    # Names out of alphabetical order: the file keeps the rig's order (three.js indexes targets by position).
    targets = {
        "zeta": rng.normal(0, 0.02, v.shape).astype(np.float32),
        "alpha": rng.normal(0, 0.02, v.shape).astype(np.float32),
    }
    parts = (v[:, 1] > 0).astype(np.int32)
    return Mesh(v, f, vertex_colors=colours(v), morph_targets=targets, part_ids=parts, part_names=["low", "high"])


def test_glb_bytes_is_what_save_mesh_writes_and_loads_back(tmp_path):
    mesh = _rigged_sphere()
    data = glb_bytes(mesh)
    path = save_mesh(mesh, tmp_path / "m.glb")
    assert path.read_bytes() == data
    back = load_mesh(path)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.vertex_colors, mesh.vertex_colors, atol=1e-5)  # linear COLOR_0 and back
    assert back.morph_names == ["zeta", "alpha"]
    for name, offsets in mesh.morph_targets.items():
        np.testing.assert_allclose(back.morph_targets[name], offsets, atol=1e-6)
    gltf = pygltflib.GLTF2.load_from_bytes(data)
    assert gltf.meshes[0].extras["targetNames"] == ["zeta", "alpha"]  # where three.js's GLTFLoader reads the names
    assert gltf.meshes[0].weights == [0.0, 0.0]
    assert gltf.materials[0].pbrMetallicRoughness.roughnessFactor == 1.0


def test_viewer_serves_the_posed_mesh_in_the_same_format(tmp_path):
    """The GLB the viewer hands viser (three.js GLTFLoader in the browser) is glb_bytes of the posed mesh."""
    pytest.importorskip("viser", reason="viser not installed (pip install 't2bs[viewer]')")
    from t2bs.viewer.app import ViewerApp

    root = tmp_path / "proj"
    info = build_fixture_project(root)
    v0, basis, scale = info["neutral"], info["basis"], info["scale"]
    with ViewerApp(root, port=0) as app:
        app.set_weights({"pc000": 0.5 * scale[0]})
        served = app._mesh_handle.glb_data
    (tmp_path / "served.glb").write_bytes(served)
    back = load_mesh(tmp_path / "served.glb")
    np.testing.assert_allclose(back.vertices, v0 + 0.5 * scale[0] * basis[0], atol=1e-5)
    np.testing.assert_array_equal(back.faces, info["faces"])
    np.testing.assert_allclose(back.vertex_colors, info["colors"], atol=1e-5)
    assert back.morph_targets == {}  # the pose is baked into POSITION: one small mesh per change
    gltf = pygltflib.GLTF2.load_from_bytes(served)
    material = gltf.materials[0]
    assert material.doubleSided and material.pbrMetallicRoughness.metallicFactor == 0.0
    assert material.pbrMetallicRoughness.roughnessFactor == 0.75
    attrs = gltf.meshes[0].primitives[0].attributes
    assert attrs.POSITION is not None and attrs.NORMAL is not None and attrs.COLOR_0 is not None
