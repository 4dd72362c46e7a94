"""Grid folder format: round trip, strict shape checks, SV4D-style import."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from t2bs.errors import UserError
from t2bs.geometry.camera import canonical_view_index, orbit_cameras
from t2bs.video.grid import VideoGrid, import_image_grid, load_grid, save_grid
from t2bs.video.sheets import contact_sheet


def _grid(V=5, T=4, S=32, n=50, seed=0) -> VideoGrid:
    rng = np.random.default_rng(seed)
    return VideoGrid(
        frames=rng.integers(0, 256, (V, T, S, S, 3), dtype=np.uint8),
        cameras=orbit_cameras(V, S),
        times=np.arange(T, dtype=np.float32) / 8,
        canonical_view=canonical_view_index(V),
        masks=rng.random((V, T, S, S)) > 0.5,
        gt_vertices=rng.normal(size=(T, n, 3)).astype(np.float32),
        backend="test",
        meta={"expression": "blinking", "sample": 1, "fps": 8.0},
    )


def test_round_trip_is_lossless(tmp_path):
    g = _grid()
    save_grid(g, tmp_path / "g")
    h = load_grid(tmp_path / "g")
    assert h.frames.dtype == np.uint8 and np.array_equal(h.frames, g.frames)
    assert np.array_equal(h.masks, g.masks)
    assert np.array_equal(h.gt_vertices, g.gt_vertices)
    assert np.allclose(h.times, g.times) and h.canonical_view == g.canonical_view == 2
    assert h.backend == "test" and h.meta["expression"] == "blinking"
    for a, b in zip(g.cameras, h.cameras):
        assert np.allclose(a.K, b.K) and np.allclose(a.world_to_camera, b.world_to_camera)
    # Overwriting with a shorter grid leaves no stale frames behind.
    short = _grid(T=2)
    save_grid(short, tmp_path / "g")
    assert load_grid(tmp_path / "g").num_frames == 2


def test_optional_parts_and_mp4(tmp_path):
    g = _grid()
    g.masks, g.gt_vertices = None, None
    save_grid(g, tmp_path / "p")
    h = load_grid(tmp_path / "p")
    assert h.masks is None and h.gt_vertices is None
    smooth = _grid(S=32)
    smooth.frames[:] = np.linspace(0, 255, 32, dtype=np.uint8)[None, None, None, :, None]
    save_grid(smooth, tmp_path / "m", frame_format="mp4")
    m = load_grid(tmp_path / "m")
    assert m.frames.shape == smooth.frames.shape
    assert np.abs(m.frames.astype(int) - smooth.frames).mean() < 6  # lossy but the same picture


@pytest.mark.parametrize(
    "break_it, message",
    [
        (lambda d: (d / "frames" / "view01" / "0003.png").unlink(), "has 3 frames but grid.json says 4"),
        (lambda d: (d / "cameras.json").unlink(), "cameras.json missing"),
        (lambda d: (d / "grid.json").unlink(), "grid.json missing"),
        (lambda d: shutil.rmtree(d / "frames" / "view04"), "frames/view04/ missing"),
        (lambda d: _edit_json(d / "cameras.json", lambda c: c[:-1]), "4 cameras but grid.json says 5 views"),
        (
            lambda d: _edit_json(d / "grid.json", lambda c: {**c, "times": c["times"][:-1]}),
            "3 time stamps for 4 frames",
        ),
        (lambda d: _edit_json(d / "grid.json", lambda c: {**c, "width": 40}), "is 32x32 but grid.json says 40x32"),
        (lambda d: _edit_json(d / "grid.json", lambda c: {**c, "canonical_view": 9}), "canonical_view 9 is outside"),
        (lambda d: np.save(d / "gt_vertices.npy", np.zeros((3, 50, 3), np.float32)), "gt_vertices must be [4, N, 3]"),
        (
            lambda d: np.savez(d / "masks.npz", masks=np.zeros((5, 4, 16, 16), bool)),
            "masks must be bool [5, 4, 32, 32]",
        ),
        (lambda d: _png(d / "frames" / "view00" / "0001.png", 24), "view 0 frame 1 is 24x24"),
    ],
)
def test_malformed_folder_is_rejected(tmp_path, break_it, message):
    d = tmp_path / "g"
    save_grid(_grid(), d)
    break_it(d)
    with pytest.raises(UserError) as err:
        load_grid(d)
    text = str(err.value)
    assert message in text and "\n" not in text


def test_save_rejects_bad_grid(tmp_path):
    g = _grid()
    g.cameras = g.cameras[:3]
    with pytest.raises(UserError, match="3 cameras for 5 views"):
        save_grid(g, tmp_path / "x")
    g = _grid()
    g.times = np.array([0, 1, 1, 2], np.float32)
    with pytest.raises(UserError, match="strictly increasing"):
        save_grid(g, tmp_path / "x")


def _edit_json(path, fn):
    path.write_text(json.dumps(fn(json.loads(path.read_text()))))


def _png(path, size):
    from PIL import Image

    Image.fromarray(np.zeros((size, size, 3), np.uint8)).save(path)


def test_import_single_grid_image(tmp_path):
    from PIL import Image

    g = _grid(V=3, T=4, S=16)
    big = g.frames.transpose(0, 2, 1, 3, 4).reshape(3 * 16, 4 * 16, 3)  # rows = views, columns = times
    Image.fromarray(big).save(tmp_path / "grid.png")
    imp = import_image_grid(tmp_path / "grid.png", views=3, frames=4)
    assert np.array_equal(imp.frames, g.frames)
    assert imp.canonical_view == 1 and imp.backend == "sv4d-import" and imp.cameras[0].width == 16
    with pytest.raises(UserError, match="does not split into 5 rows"):
        import_image_grid(tmp_path / "grid.png", views=5, frames=4)
    with pytest.raises(UserError, match="needs --views and --frames"):
        import_image_grid(tmp_path / "grid.png")


def test_import_view_folders_and_flat_folder(tmp_path):
    from PIL import Image

    g = _grid(V=3, T=12, S=16)
    for v in range(3):
        for t in range(12):
            (tmp_path / "views" / f"v{v}").mkdir(parents=True, exist_ok=True)
            Image.fromarray(g.frames[v, t]).save(tmp_path / "views" / f"v{v}" / f"frame_{t}.png")  # 10 sorts after 9
            (tmp_path / "flat").mkdir(exist_ok=True)
            Image.fromarray(g.frames[v, t]).save(tmp_path / "flat" / f"{v * 12 + t:03d}.png")
    imp = import_image_grid(tmp_path / "views")
    assert np.array_equal(imp.frames, g.frames)
    flat = import_image_grid(tmp_path / "flat", views=3, cameras=orbit_cameras(3, 512))
    assert np.array_equal(flat.frames, g.frames) and flat.cameras[0].width == 16  # cameras rescaled
    save_grid(flat, tmp_path / "saved")
    assert load_grid(tmp_path / "saved").num_frames == 12
    (tmp_path / "views" / "v2" / "frame_11.png").unlink()
    with pytest.raises(UserError, match="different frame counts"):
        import_image_grid(tmp_path / "views")
    with pytest.raises(UserError, match="36 images do not split into 5 views"):
        import_image_grid(tmp_path / "flat", views=5)
    with pytest.raises(UserError, match="2 cameras for 3 views"):
        import_image_grid(tmp_path / "flat", views=3, cameras=orbit_cameras(2, 16))
    with pytest.raises(UserError, match="needs --views"):
        import_image_grid(tmp_path / "flat")


def test_contact_sheet_layout():
    g = _grid(V=3, T=20, S=16)
    sheet = contact_sheet(g, max_columns=8, tile=16, gap=2)
    assert sheet.shape == (3 * 18 + 2, 8 * 18 + 2, 3)
    assert np.array_equal(sheet[2:18, 2:18], g.frames[0, 0])  # first frame of view 0
    assert np.array_equal(sheet[2:18, -18:-2], g.frames[0, 19])  # last frame in the last column


def test_imported_grids_keep_masks_and_state_their_shading(tmp_path):
    from PIL import Image

    from t2bs.video.grid import masks_from_frames

    # Views as folders of RGBA PNGs: the masks come from alpha.
    rng = np.random.default_rng(0)
    alpha = np.zeros((2, 3, 16, 16), np.uint8)
    alpha[:, :, 4:12, 5:11] = 255
    for v in range(2):
        (tmp_path / "rgba" / f"v{v}").mkdir(parents=True)
        for t in range(3):
            rgba = np.dstack([rng.integers(0, 255, (16, 16, 3)).astype(np.uint8), alpha[v, t]])
            Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba" / f"v{v}" / f"{t}.png")
    g = import_image_grid(tmp_path / "rgba", cameras=orbit_cameras(2, 16), shading="unlit")
    assert g.masks.shape == (2, 3, 16, 16) and np.array_equal(g.masks, alpha > 127)
    assert g.meta["masks_from"] == "alpha" and g.meta["grid_config"]["shading"] == "unlit"
    save_grid(g, tmp_path / "saved")
    assert np.array_equal(load_grid(tmp_path / "saved").masks, alpha > 127)
    # RGB frames on a plain (grey) ground: keyed from the border colour.
    frames = np.full((1, 2, 20, 20, 3), 200, np.uint8)
    frames[0, :, 6:14, 8:12] = (30, 200, 90)
    keyed = masks_from_frames(frames)
    assert keyed.sum() == 2 * 8 * 4 and keyed[0, 0, 6:14, 8:12].all()
    with pytest.raises(UserError, match="shading must be unlit or lambert"):
        import_image_grid(tmp_path / "rgba", cameras=orbit_cameras(2, 16), shading="pbr")


def test_vcdgs_warns_when_a_grid_does_not_state_its_shading(capsys):
    from t2bs.recon.config import preset
    from t2bs.recon.vcdgs import prepare_data

    frames = np.full((3, 2, 16, 16, 3), 255, np.uint8)
    grid = VideoGrid(frames, orbit_cameras(3, 16), np.array([0.0, 0.125], np.float32), 1, backend="sv4d-import")
    cfg = preset("quick", resolution=16)
    assert prepare_data(grid, cfg).shading == "lambert"
    assert "warning: the grid (sv4d-import) does not say how it was lit" in capsys.readouterr().out
    grid.meta["grid_config"] = {"shading": "unlit"}
    assert prepare_data(grid, cfg).shading == "unlit"
    assert "warning" not in capsys.readouterr().out
