import numpy as np
import pytest

from conftest import asset
from t2bs.character.render_stage import canonical_character
from t2bs.geometry.camera import frontal_camera, orbit_cameras
from t2bs.geometry.mesh import Mesh


def _cube(size=0.2):
    v = np.array([[x, y, z] for x in (-size, size) for y in (-size, size) for z in (-size, size)], np.float32)
    f = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ],
        np.int32,
    )
    return Mesh(v, f, vertex_colors=np.tile([[1.0, 0.0, 0.0]], (8, 1)).astype(np.float32))


def test_cube_depth_normals_mask_and_colour(mesh_renderer):
    cam = frontal_camera(128, elevation_deg=0.0)
    res = mesh_renderer.render(_cube(), cam, shading="unlit", background=(0, 0, 1))
    # Centre pixel sees the front face z = +0.2 at distance 2.25 - 0.2.
    assert res.depth[64, 64] == pytest.approx(2.05, abs=1e-3)
    np.testing.assert_allclose(res.normal[64, 64], [0, 0, 1], atol=1e-4)
    np.testing.assert_allclose(res.rgb[64, 64], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(res.rgb[0, 0], [0, 0, 1])
    assert res.face_id[0, 0] == -1 and res.face_id[64, 64] in (10, 11)  # the +Z face's two triangles
    # Silhouette matches the projected square: half-width f * 0.5 / 1.75 pixels.
    f = cam.K[0, 0]
    expected = (2 * f * 0.2 / 2.05) ** 2 / 128**2
    assert res.mask.mean() == pytest.approx(expected, rel=0.05)


def test_render_rgb_is_renders_colour_from_every_camera(mesh_renderer):
    """One upload drawn from several cameras gives each camera's ``render(...).rgb`` pixel for pixel, both shadings,
    a posed mesh, and the renderer's state after it is as before (a full render still reads depth and face ids)."""
    cube = _cube()
    posed = cube.vertices @ np.array([[0.8, 0.0, 0.6], [0.0, 1.0, 0.0], [-0.6, 0.0, 0.8]], np.float32).T
    cams = orbit_cameras(views=3, size=64)
    for shading in ("lambert", "unlit"):
        rgbs = mesh_renderer.render_rgb(cube, cams, posed, shading)
        for cam, rgb in zip(cams, rgbs):
            ref = mesh_renderer.render(cube, cam, vertices=posed, shading=shading).rgb
            assert np.array_equal(rgb, ref) and (rgb != 1.0).any()  # the cube is in the picture
    res = mesh_renderer.render(cube, frontal_camera(128, elevation_deg=0.0), shading="unlit")
    assert res.face_id[0, 0] == -1 and res.face_id[64, 64] in (10, 11)


def test_vertex_visibility_depth_test(mesh_renderer):
    cam = frontal_camera(128, elevation_deg=0.0)
    vis = mesh_renderer.vertex_visibility(_cube(), cam)
    front = _cube().vertices[:, 2] > 0
    np.testing.assert_array_equal(vis, front)


@pytest.mark.parametrize("name", ["turtle.glb", "facecap.glb", "vipe_hero_head.glb"])
def test_assets_are_centred_and_face_the_camera(mesh_renderer, name):
    mesh, info = canonical_character(asset(name))
    cams = orbit_cameras(15, 128)
    front = mesh_renderer.render(mesh, frontal_camera(128))
    cov = front.mask.mean()
    assert 0.15 < cov < 0.8, cov
    centre = np.argwhere(front.mask).mean(0)
    assert np.all(np.abs(centre - 64) < 0.12 * 128), centre
    # The front is where the expressions are: more morph motion visible from the front camera
    # than from behind, and the frontal image differs from both +-60 degree views.
    visible = mesh_renderer.vertex_visibility(mesh, frontal_camera(128))
    motion = np.max([np.linalg.norm(d, axis=1) for d in mesh.morph_targets.values()], axis=0)
    behind = mesh_renderer.vertex_visibility(
        mesh, frontal_camera(128).__class__(cams[7].K, cams[7].world_to_camera @ np.diag([-1.0, 1, -1, 1]), 128, 128)
    )
    assert motion[visible].sum() > 3 * motion[behind].sum()
    for side in (cams[0], cams[-1]):
        diff = np.abs(mesh_renderer.render(mesh, side).rgb - front.rgb).mean()
        assert diff > 0.02


def test_texture_orientation(mesh_renderer):
    # A quad textured top-red / bottom-green must render red on top (glTF v = 0 is the image top).
    v = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:4, :, 0] = 255
    tex[4:, :, 1] = 255
    res = mesh_renderer.render(Mesh(v, f, uv=uv, texture=tex), frontal_camera(64, elevation_deg=0.0), shading="unlit")
    assert res.rgb[22, 32, 0] > 0.9 and res.rgb[42, 32, 1] > 0.9
