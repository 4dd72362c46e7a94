"""Retargeting (issue 8): landmarks, MediaPipe tracking, transfer + solve, CLI errors, end to end."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset

from t2bs.errors import MissingCheckpointError, UserError
from t2bs.geometry.mesh import normalize

mp = pytest.importorskip("t2bs.face.face_tracking")
needs_mp = pytest.mark.skipif(not mp.mediapipe_available(), reason="MediaPipe venv not installed (scripts/setup.sh)")


@pytest.fixture(scope="module")
def turtle():
    from t2bs.geometry.io import load_mesh

    return normalize(load_mesh(asset("turtle.glb")))[0]


def test_mapping_table_is_consistent():
    assert len(mp.LANDMARKS_68) == 20 and len(set(mp.MEDIAPIPE_20)) == 20
    assert mp.LANDMARKS_68 == list(range(36, 48)) + list(range(60, 68))


@needs_mp
def test_mediapipe_on_astronaut():
    skimage_data = pytest.importorskip("skimage.data")
    img = skimage_data.astronaut()  # [512, 512, 3] a real photo
    lm, found = mp.run_face_mesh(img[None], static=True)
    assert found[0]
    p = lm[0, mp.MEDIAPIPE_20, :2]
    right_eye, left_eye, mouth = p[mp.RIGHT_EYE], p[mp.LEFT_EYE], p[mp.MOUTH]
    assert right_eye[:, 1].max() < mouth[:, 1].min() and left_eye[:, 1].max() < mouth[:, 1].min()  # eyes above mouth
    assert right_eye[:, 0].mean() < left_eye[:, 0].mean()  # subject's right eye on the image left
    assert right_eye[:, 0].mean() < mouth[:, 0].mean() < left_eye[:, 0].mean()
    # The face is around (225, 120) in this photo; eyes ~40 px apart.
    assert 150 < p[:, 0].mean() < 300 and 60 < p[:, 1].mean() < 180
    assert 25 < left_eye[:, 0].mean() - right_eye[:, 0].mean() < 80
    # Corners are the extreme x of each eye; upper lids above lower lids.
    assert right_eye[0, 0] < right_eye[3, 0] and left_eye[0, 0] < left_eye[3, 0]
    assert mp.eye_openness(p, "left") > 0 and mp.mouth_openness(p) > -0.05


def test_motion_landmarks_turtle(turtle):
    from t2bs.face.landmarks import detect_landmarks

    lm, regions = detect_landmarks(turtle, "motion")
    pos = lm.positions
    assert lm.vertex_ids.shape == (20,)
    assert pos[:6, 0].mean() < 0 < pos[6:12, 0].mean()  # 36-41 on the character's right (-X)
    assert pos[12:, 1].max() < pos[:12, 1].min()  # mouth below the eyes
    # Upper-lid landmarks above lower-lid ones; each eye's landmarks move under its own blink shape.
    for eye, shape in ((slice(0, 6), "eyeRightClose"), (slice(6, 12), "eyeLeftClose")):
        p = pos[eye]
        assert p[1:3, 1].min() > p[4:6, 1].max()
        moved = np.linalg.norm(turtle.morph_targets[shape][lm.vertex_ids[eye]], axis=1)
        assert (moved[[1, 2, 4, 5]] > 0).all()
    # Lower-lip landmarks move down under mouthOpen much more than the upper lip.
    d = turtle.morph_targets["mouthOpen"][lm.vertex_ids[12:]]
    assert d[5:8, 1].mean() < 3 * min(d[1:4, 1].mean(), 0) - 0.01
    assert lm.eyeballs["left"].size > 0 and lm.eyeballs["right"].size > 0


@pytest.fixture(scope="module")
def fox():
    from t2bs.eval.bench_retarget import load_target

    label, mesh, procedural = load_target("procedural:a cartoon fox")  # the bench's loader: the real generator
    assert procedural and label == "procedural:a cartoon fox"
    return mesh


def test_parts_landmarks_procedural(fox, mesh_renderer):
    """Parts backend on a procedural character: 6 / 6 points on the lids, 8 on the inner lip contour."""
    from t2bs.face.landmarks import detect_landmarks

    lm, regions = detect_landmarks(fox, "parts", size=256, renderer=mesh_renderer)
    assert lm.backend == "parts" and lm.vertex_ids.shape == (20,)
    part = np.array(fox.part_names)[fox.part_ids[lm.vertex_ids]]
    assert (part[:6] == "eyelid_right").all() and (part[6:12] == "eyelid_left").all()
    assert (part[13:16] == "lip_upper").all() and (part[17:20] == "lip_lower").all()
    assert set(part[[12, 16]]) <= {"lip_upper", "lip_lower"}
    pos = lm.positions
    # Mirror: 36-41 on the character's right (-X, image left), 42-47 on its left (+X, image right).
    assert pos[:6, 0].max() < 0 < pos[6:12, 0].min()
    assert pos[12, 0] < 0 < pos[16, 0] and pos[12:, 1].max() < pos[:12, 1].min()
    # Each eye's points surround its visible eyeball in the image (centroid within a third of its
    # radius, every point within 1.5 radii); the mouth's straddle the lip line.
    uv = lm.camera.project(pos)[0]
    for sl, region in ((slice(0, 6), "right_eye"), (slice(6, 12), "left_eye"), (slice(12, 20), "mouth")):
        ys, xs = np.nonzero(regions[region].mask)
        centre, radius = np.array([xs.mean(), ys.mean()]), np.ptp(xs) / 2
        assert np.linalg.norm(uv[sl].mean(0) - centre) < radius / 3, region
        assert (np.linalg.norm(uv[sl] - centre, axis=1) < 1.5 * radius).all(), region
    # The rig moves exactly the landmarks it should: blink_left the left lids (upper down), not the
    # right ones; jaw_open the lower lip down and not the upper; smile pulls both corners up.
    blink = fox.morph_targets["blink_left"][lm.vertex_ids]
    assert (blink[7:9, 1] < -0.01).all() and np.abs(blink[:6]).max() < 1e-6
    jaw = fox.morph_targets["jaw_open"][lm.vertex_ids]
    assert (jaw[17:20, 1] < -0.05).all() and np.abs(jaw[13:16]).max() < 1e-6
    smile = fox.morph_targets["smile"][lm.vertex_ids]
    assert smile[12, 1] > 0.005 and smile[16, 1] > 0.005 and smile[12, 0] < 0 < smile[16, 0]


def test_arap_rotations_match_dense():
    """The solver's sparse local step (active vertices only) equals the plain per-vertex fit."""
    from t2bs.character.primitives import icosphere
    from t2bs.geometry.mesh import mesh_edges
    from t2bs.face.solve import RetargetSolver

    v, f = icosphere(2)
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(3, len(v), 3)) * (v[None, :, 1:2] > 0.3)  # shapes move only the top cap
    solver = RetargetSolver(v, basis, f, np.arange(20))
    w = rng.normal(size=3) * 0.1
    e = mesh_edges(f)
    pose = v + np.tensordot(w, basis, axes=1)
    cov = np.einsum("ea,eb->eab", v[e[:, 0]] - v[e[:, 1]], pose[e[:, 0]] - pose[e[:, 1]])
    s = np.zeros((len(v), 3, 3))
    np.add.at(s, e[:, 0], cov)
    np.add.at(s, e[:, 1], cov)
    u, _, vt = np.linalg.svd(s)
    u[np.linalg.det(np.einsum("nba,ncb->nac", vt, u)) < 0, :, 2] *= -1  # nearest proper rotation
    dense = np.einsum("nba,ncb->nac", vt, u)
    rot = solver._rotations(w)
    assert 0 < len(solver._active_v) < len(v)
    assert np.allclose(rot, dense, atol=1e-8)


def test_arap_welds_uv_seams():
    """A mesh cut along a seam (duplicated vertices, as exporters write UV seams) solves exactly
    like the uncut mesh: ARAP sees whole neighbourhoods, not two halves."""
    from t2bs.character.primitives import icosphere
    from t2bs.face.solve import RetargetSolver

    v, f = icosphere(2)
    rng = np.random.default_rng(1)
    basis = rng.normal(size=(4, len(v), 3)) * 0.05
    # Cut: every vertex with x > 0.2 gets a copy that the faces on the z > 0 side use instead.
    side = np.flatnonzero(v[:, 0] > 0.2)
    copy = np.arange(len(v))
    copy[side] = len(v) + np.arange(len(side))
    cut_f = np.where((v[f].mean(1)[:, 2] > 0)[:, None], copy[f], f)
    cut_v = np.concatenate([v, v[side]])
    cut_basis = np.concatenate([basis, basis[:, side]], axis=1)
    ids = np.arange(0, 40, 2)
    targets = rng.normal(size=(3, 20, 2)) * 0.05 + v[ids, :2]
    whole = RetargetSolver(v, basis, f, ids).solve(targets)
    cut = RetargetSolver(cut_v, cut_basis, cut_f, ids).solve(targets)
    assert len(np.unique(cut_f)) > len(v)  # the cut really splits vertices
    np.testing.assert_allclose(cut, whole, atol=1e-10)


def _known_frames(turtle):
    """The turtle's morph model, its landmarks, and three frames made by known morph weights (mouth open 0.8, left
    eye closed, right eye 0.6 closed): (model, landmarks, true vertices [3, N, 3], landmark targets [3, 20, 2],
    eye openness [3, 2])."""
    from t2bs.eval.bench_retarget import morph_model
    from t2bs.face.landmarks import detect_landmarks

    model = morph_model(turtle)
    lm, _ = detect_landmarks(turtle, "motion")
    names = list(turtle.morph_targets)
    truth = np.zeros((3, len(names)))
    truth[0, names.index("mouthOpen")] = 0.8
    truth[1, names.index("eyeLeftClose")] = 1.0
    truth[2, names.index("eyeRightClose")] = 0.6
    verts = turtle.vertices[None] + np.einsum("tm,mnc->tnc", truth, np.stack([turtle.morph_targets[n] for n in names]))
    gaps = np.array([[1, 1], [1, 0.0], [0.4, 1]])  # (right, left) openness consistent with the truth
    return model, lm, verts, verts[:, lm.vertex_ids, :2], gaps


def test_solver_recovers_model_weights(turtle):
    """Targets generated by known weights are matched (landmarks) with the right shapes."""
    from t2bs.eval.bench_retarget import project_directions
    from t2bs.face.solve import RetargetSolver

    model, lm, _, targets, gaps = _known_frames(turtle)
    solver = RetargetSolver(model.neutral, model.basis, turtle.faces, lm.vertex_ids, lm.eyeballs)
    w = solver.solve(targets, gaps)
    coef = project_directions(model.offsets(w), turtle)
    assert coef["mouthOpen"][0] > 0.5 and abs(coef["eyeLeftClose"][0]) < 0.2
    assert coef["eyeLeftClose"][1] > 0.7 and abs(coef["eyeRightClose"][1]) < 0.2
    assert coef["eyeRightClose"][2] > 0.3 and abs(coef["mouthOpen"][2]) < 0.2


def test_the_pca_prior_keeps_the_whole_mesh_near_the_truth(turtle):
    """20 landmarks cannot pin every component: the plain solve matches them with components the captures barely
    use, moving the rest of the mesh; with the PCA's prior (what retargeting solves) the whole mesh stays near the
    true frames (measured: mean vertex error 0.0033 -> 0.00055 of the diagonal)."""
    from t2bs.face.solve import RetargetSolver

    model, lm, verts, targets, gaps = _known_frames(turtle)
    diag = np.linalg.norm(turtle.vertices.max(0) - turtle.vertices.min(0))

    def error(solver) -> float:
        return float(np.linalg.norm(model.neutral + model.offsets(solver.solve(targets, gaps)) - verts, axis=-1).mean())

    plain = error(RetargetSolver(model.neutral, model.basis, turtle.faces, lm.vertex_ids, lm.eyeballs))
    prior = error(RetargetSolver.with_pca_prior(model, turtle.faces, lm.vertex_ids, lm.eyeballs, bounded=False))
    assert prior < 0.3 * plain and prior < 0.001 * diag
    # What retargeting solves: the prior and every weight within the range the captures saw (0 included)
    bounded = RetargetSolver.with_pca_prior(model, turtle.faces, lm.vertex_ids, lm.eyeballs)
    w = bounded.solve(targets, gaps)
    lo, hi = bounded.bounds
    assert (lo <= 0).all() and (hi >= 0).all() and (w >= lo - 1e-9).all() and (w <= hi + 1e-9).all()
    assert error(bounded) < 0.001 * diag


def test_the_bounded_solve_meets_the_box_optimality_conditions():
    """``_solve_linear`` with bounds: the minimiser of 1/2 w^T H w - r^T w in the box (KKT: zero gradient on the free
    weights, pointing out of the box on the clamped ones); inside the box it is the plain solve."""
    from t2bs.face.solve import RetargetSolver

    rng = np.random.default_rng(0)
    a = rng.normal(size=(12, 8))
    h, rhs = a.T @ a + 0.1 * np.eye(8), rng.normal(size=8) * 3.0
    solver = RetargetSolver.__new__(RetargetSolver)
    solver.bounds = np.array([np.full(8, -0.5), np.full(8, 0.5)])
    free = np.linalg.solve(h, rhs)
    assert np.abs(free).max() > 0.5  # the box binds
    w = solver._solve_linear(h, rhs)
    grad = h @ w - rhs
    lo, hi = np.isclose(w, -0.5), np.isclose(w, 0.5)
    assert (lo | hi).any() and (w >= -0.5 - 1e-9).all() and (w <= 0.5 + 1e-9).all()
    assert np.abs(grad[~lo & ~hi]).max() < 1e-8 and (grad[lo] > -1e-8).all() and (grad[hi] < 1e-8).all()
    solver.bounds = np.array([np.full(8, -100.0), np.full(8, 100.0)])
    assert np.array_equal(solver._solve_linear(h, rhs), free)


def test_landmark_errors(tmp_path, turtle):
    from t2bs.geometry.mesh import Mesh
    from t2bs.face.landmarks import detect_landmarks, landmarks_from_override

    plain = Mesh(turtle.vertices, turtle.faces)
    with pytest.raises(UserError, match="no landmarks"):
        detect_landmarks(plain, "auto")
    with pytest.raises(UserError, match="20 vertex ids"):
        landmarks_from_override({"vertex_ids": [1, 2, 3]}, plain)
    lm = landmarks_from_override({"vertex_ids": list(range(20))}, plain)
    assert lm.backend == "override" and lm.positions.shape == (20, 3)


def test_grounding_sam_missing_checkpoint(tmp_path):
    from t2bs.face.grounding_sam import GroundingSamSegmenter

    with pytest.raises(MissingCheckpointError, match="grounding-dino-tiny"):
        GroundingSamSegmenter.from_pretrained(tmp_path / "dino", tmp_path / "sam")


def test_driver_errors(tmp_path):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"this is not a video" * 100)
    with pytest.raises(UserError, match="cannot be decoded"):
        mp.read_driver(bad)
    with pytest.raises(UserError, match="does not exist"):
        mp.read_driver(tmp_path / "missing.mp4")
    lm = np.zeros((5, 468, 3))
    with pytest.raises(UserError, match="no face found"):
        mp.track_landmarks(lm, np.zeros(5, bool), 30.0)


def test_missing_frames_interpolated():
    rng = np.random.default_rng(0)
    base = rng.uniform(100, 200, (468, 3))
    lm = np.repeat(base[None], 6, axis=0)
    lm[3, :, 1] += 4.0  # a different expression in frame 3 (landmarks move, stable points too)
    found = np.array([True, True, False, True, True, True])
    track = mp.track_landmarks(lm, found, 30.0, mp.TrackConfig(smooth_sigma=0.0, neutral_frame=0))
    assert track.report["missing"] == 1 and track.report["missing_runs"] == [[2, 2]]
    assert np.allclose(track.points[2], (track.points[1] + track.points[3]) / 2, atol=1e-3)


@needs_mp
@pytest.mark.slow
def test_cli_end_to_end_and_bad_driver(tmp_path, turtle):
    """Project with the turtle + its model; driver = rendered facecap with blank frames."""
    import imageio.v2 as imageio

    from t2bs.blendshapes.model import save_model
    from t2bs.cli import app
    from t2bs.geometry.io import save_mesh
    from t2bs.eval.bench_retarget import driver_weights, morph_model, render_driver
    from typer.testing import CliRunner

    proj = tmp_path / "proj"
    save_mesh(turtle, proj / "character" / "mesh.glb")
    save_model(morph_model(turtle), proj / "blendshapes" / "model.npz")
    w = driver_weights(24)
    frames = render_driver(w, 192, asset=asset("facecap.glb"))
    frames[5] = 255  # a frame without a face
    video = tmp_path / "drv.mp4"
    imageio.mimwrite(video, list(frames), fps=24, macro_block_size=1)
    runner = CliRunner()
    res = runner.invoke(app, ["landmarks", str(proj), "--show"])
    assert res.exit_code == 0, res.output
    assert (proj / "landmarks" / "overlay.png").exists()
    res = runner.invoke(app, ["retarget", str(proj), "--driver", str(video), "-o", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert "no face in 1 of 24 frames" in res.output
    rows = (tmp_path / "out" / "weights.csv").read_text().splitlines()
    assert len(rows) == 25
    assert (tmp_path / "out" / "animation.glb").stat().st_size > 0 and (
        tmp_path / "out" / "preview.mp4"
    ).stat().st_size > 0
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\x00" * 1000)
    res = runner.invoke(app, ["retarget", str(proj), "--driver", str(bad)])
    assert res.exit_code != 0 and isinstance(res.exception, UserError)
