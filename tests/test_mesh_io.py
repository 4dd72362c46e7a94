import numpy as np
import pytest

from conftest import asset
from t2bs.errors import UserError
from t2bs.geometry.io import load_mesh, save_mesh
from t2bs.geometry.mesh import CANONICAL_DIAGONAL, Mesh, detect_facing, merge_meshes, normalize


@pytest.mark.parametrize(
    "name,vertices,targets", [("turtle.glb", 1922, 11), ("facecap.glb", None, 52), ("vipe_hero_head.glb", None, 16)]
)
def test_assets_load_with_named_morph_targets(name, vertices, targets):
    mesh = load_mesh(asset(name))
    assert len(mesh.morph_targets) == targets
    if vertices:
        assert mesh.num_vertices == vertices
    assert mesh.texture is not None and mesh.uv is not None
    assert all(d.shape == mesh.vertices.shape for d in mesh.morph_targets.values())


def test_turtle_morph_targets_round_trip(tmp_path):
    mesh = load_mesh(asset("turtle.glb"))
    assert mesh.morph_names[:3] == ["smileRight", "smileLeft", "eyeBrowLeftDown"]
    save_mesh(mesh, tmp_path / "t.glb")
    again = load_mesh(tmp_path / "t.glb")
    assert again.morph_names == mesh.morph_names
    for name in mesh.morph_names:
        np.testing.assert_allclose(again.morph_targets[name], mesh.morph_targets[name], atol=1e-6)
    np.testing.assert_allclose(again.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(again.faces, mesh.faces)
    np.testing.assert_array_equal(again.texture, mesh.texture)


def test_multi_primitive_asset_is_merged_with_part_labels_and_transforms():
    mesh = load_mesh(asset("facecap.glb"))
    # Head, two eyes and teeth: four labelled parts; node transforms (cm -> m scale, rotation) applied.
    assert len(mesh.part_names) == 4 and mesh.part_ids is not None
    assert set(np.unique(mesh.part_ids)) == {0, 1, 2, 3}
    assert 1.0 < mesh.bbox_diagonal() < 5.0
    # Morph targets exist only on the head: other parts get zero offsets.
    head = max(range(4), key=lambda i: (mesh.part_ids == i).sum())
    jaw = mesh.morph_targets["jawOpen"]
    assert np.abs(jaw[mesh.part_ids != head]).max() == 0 and np.abs(jaw[mesh.part_ids == head]).max() > 0


def test_two_textures_are_packed_into_one_atlas():
    mesh = load_mesh(asset("vipe_hero_head.glb"))
    assert mesh.texture.shape[1] == 2 * mesh.texture.shape[0]  # two 1024x1024 textures side by side
    left = mesh.part_ids == 0
    assert mesh.uv[left, 0].max() <= 0.5 and mesh.uv[~left, 0].min() >= 0.5


def test_part_labels_round_trip(tmp_path):
    mesh = load_mesh(asset("facecap.glb"))
    save_mesh(mesh, tmp_path / "f.glb")
    again = load_mesh(tmp_path / "f.glb")
    assert again.part_names == mesh.part_names
    np.testing.assert_array_equal(again.part_ids, mesh.part_ids)


def test_normalize_canonical_frame_and_facing():
    mesh = load_mesh(asset("vipe_hero_head.glb"))
    assert detect_facing(mesh) == "-z"
    assert detect_facing(load_mesh(asset("turtle.glb"))) == "+z"
    canon, transform = normalize(mesh, "-z")
    lo, hi = canon.vertices.min(0), canon.vertices.max(0)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-5)
    assert abs(np.linalg.norm(hi - lo) - CANONICAL_DIAGONAL) < 1e-5
    # Morph offsets are rotated and scaled with the mesh.
    k = "blink_l"
    np.testing.assert_allclose(
        canon.morph_targets[k], mesh.morph_targets[k] @ np.diag([-1, 1, -1]).T * transform["scale"], atol=1e-6
    )


def test_ply_save_and_load(tmp_path):
    mesh = load_mesh(asset("turtle.glb"))
    save_mesh(mesh, tmp_path / "t.ply")
    again = load_mesh(tmp_path / "t.ply")
    np.testing.assert_allclose(again.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_allclose(again.vertex_colors, mesh.vertex_rgb(), atol=1 / 255 + 1e-6)


def test_obj_load(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\n")
    mesh = load_mesh(tmp_path / "tri.obj")
    assert mesh.vertices.shape == (4, 3) and mesh.faces.shape == (2, 3)


@pytest.mark.parametrize(
    "content,message",
    [(None, "no such file"), (b"", "empty"), (b"this is a text file, not a glb", "not a readable glTF")],
)
def test_bad_files_give_one_line_errors(tmp_path, content, message):
    path = tmp_path / "bad.glb"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(UserError, match=message):
        load_mesh(path)


def test_nan_and_faceless_meshes_are_rejected(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    f = np.array([[0, 1, 2]], np.int32)
    nan = Mesh(v.copy(), f)
    nan.vertices[1, 0] = np.nan
    with pytest.raises(UserError, match="NaN"):
        nan.validate()
    with pytest.raises(UserError, match="no faces"):
        Mesh(v, np.zeros((0, 3), np.int32)).validate()


def test_merge_keeps_vertex_colours_and_union_of_targets():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    f = np.array([[0, 1, 2]], np.int32)
    a = Mesh(v, f, vertex_colors=np.ones((3, 3), np.float32), morph_targets={"x": np.ones((3, 3), np.float32)})
    b = Mesh(v + 2, f, vertex_colors=np.zeros((3, 3), np.float32))
    m = merge_meshes([("a", a), ("b", b)])
    assert m.part_names == ["a", "b"] and m.faces.max() == 5
    np.testing.assert_array_equal(m.morph_targets["x"][3:], 0)
    np.testing.assert_array_equal(m.vertex_colors[:3], 1)
