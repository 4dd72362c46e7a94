"""Automatic face rig (issue 34) on a small synthetic head with eye openings, eyeballs, a lip seam and teeth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from t2bs.errors import UserError
from t2bs.geometry.mesh import Mesh
from t2bs.face.landmarks import EYE_ANGLES, MOUTH_ANGLES
from t2bs.rig.autorig import autorig
from t2bs.rig.face import FaceLandmarks, find_eyeballs, find_face, read_landmarks_file

EYE_X, EYE_Y, EYE_A, EYE_B = 0.17, 0.10, 0.07, 0.035  # eye opening centre (+-x) and half axes
MOUTH_Y, MOUTH_HALF = -0.18, 0.15  # mouth line height and half width
BALL_R = 0.075
TEETH_Y = {"upper": -0.160, "lower": -0.200}


def _boundary(faces: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    return np.unique(u[c == 1])


def synthetic_head(collar: bool = False, slit: bool = True):
    """A sphere head (radius 0.5, facing +Z) with two eye openings, eyeballs behind them, a slit mouth
    (the lip seam; ``slit=False``: a sealed mouth) and an upper and a lower row of teeth (boxes behind the lips).
    Returns (mesh, landmark ids [20], parts {name: vertex ids}, eyeball centres {side: [3]})."""
    import trimesh

    head = trimesh.creation.uv_sphere(radius=0.5, count=[64, 64])
    c = head.triangles_center
    keep = ~((np.abs(c[:, 0]) < MOUTH_HALF) & (np.abs(c[:, 1] - MOUTH_Y) < 0.012) & (c[:, 2] > 0) & slit)
    for sx in (1, -1):
        keep &= ~((((c[:, 0] - sx * EYE_X) / EYE_A) ** 2 + ((c[:, 1] - EYE_Y) / EYE_B) ** 2 < 1) & (c[:, 2] > 0))
    head.update_faces(keep)
    head.remove_unreferenced_vertices()
    parts = [("head", head)]
    centres = {}
    z_surf = np.sqrt(0.25 - EYE_X**2 - EYE_Y**2)
    for side, sx in (("left", 1), ("right", -1)):
        ball = trimesh.creation.icosphere(subdivisions=2, radius=BALL_R)
        centres[side] = np.array([sx * EYE_X, EYE_Y, z_surf - BALL_R + 0.004])
        ball.apply_translation(centres[side])
        parts.append((f"eye_{side}", ball))
    if collar:  # a separate part under the chin (clothes): not in the mouth
        box = trimesh.creation.box(extents=(0.6, 0.08, 0.3))
        box.apply_translation((0, -0.56, 0.1))
        parts.append(("collar", box))
    for name, y in TEETH_Y.items():
        box = trimesh.creation.box(extents=(0.2, 0.025, 0.03))
        box.apply_translation((0, y, np.sqrt(0.25 - y**2) - 0.05))
        parts.append((f"teeth_{name}", box))
    verts, faces, ids = [], [], {}
    n = 0
    for name, m in parts:
        verts.append(np.asarray(m.vertices))
        faces.append(np.asarray(m.faces) + n)
        ids[name] = np.arange(n, n + len(m.vertices))
        n += len(m.vertices)
    mesh = Mesh(np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int32))
    v = mesh.vertices
    rim = np.intersect1d(_boundary(np.asarray(head.faces)), ids["head"])
    lm = []
    for sx in (-1, 1):  # 36-41 the right eye (-X), then 42-47 the left eye (+X)
        for a in np.radians(EYE_ANGLES):
            target = np.array([sx * EYE_X + EYE_A * np.cos(a), EYE_Y + EYE_B * np.sin(a)])
            cand = rim[np.abs(v[rim, 0] - sx * EYE_X) < 0.1]
            lm.append(int(cand[np.argmin(np.linalg.norm(v[cand, :2] - target, axis=1))]))
    for a in MOUTH_ANGLES:
        r = np.radians(a)
        target = np.array([MOUTH_HALF * np.cos(r), MOUTH_Y + 0.01 * np.sin(r)])
        pool = rim if slit else ids["head"]
        cand = pool[np.abs(v[pool, 1] - MOUTH_Y) < 0.05]
        if 0 < a < 180:
            cand = cand[v[cand, 1] > MOUTH_Y]
        elif a < 0:
            cand = cand[v[cand, 1] < MOUTH_Y]
        lm.append(int(cand[np.argmin(np.linalg.norm(v[cand, :2] - target, axis=1))]))
    return mesh, np.asarray(lm), ids, centres


@pytest.fixture(scope="module")
def head():
    mesh, lm, parts, centres = synthetic_head()
    face = FaceLandmarks(lm, "file", {}, find_eyeballs(mesh))
    return mesh, lm, parts, centres, face, autorig(mesh, face)


def test_eyeballs_found_as_mirrored_spheres(head):
    mesh, _, parts, _, face, _ = head
    assert set(face.eyeballs) == {"left", "right"}
    assert np.array_equal(np.sort(face.eyeballs["left"]), parts["eye_left"])  # the +X ball is the character's left
    assert np.array_equal(np.sort(face.eyeballs["right"]), parts["eye_right"])


def test_blink_closes_without_entering_the_eyeball(head):
    mesh, lm, parts, centres, _, rig = head
    v = mesh.vertices.astype(np.float64)
    for side, sl in (("left", slice(6, 12)), ("right", slice(0, 6))):
        d = rig.morph_targets[f"eyeBlink{side.capitalize()}"]
        closed = v + d
        eye = lm[sl]
        # Seen from the front, the opening between the upper and lower lid points closes.
        before = v[eye[[1, 2]], 1] - v[eye[[5, 4]], 1]
        after = closed[eye[[1, 2]], 1] - closed[eye[[5, 4]], 1]
        assert np.all(np.abs(after) < 0.15 * before), (before, after)
        skin = parts["head"]
        dist = np.linalg.norm(closed[skin] - centres[side], axis=1)
        assert dist.min() >= BALL_R * 0.999  # no lid vertex inside the ball
        assert np.abs(d[parts[f"eye_{side}"]]).max() == 0  # the eyeball itself stays
        other = parts["eye_left" if side == "right" else "eye_right"]
        assert np.abs(d[other]).max() == 0


def test_jaw_turns_about_the_hinge_and_lips_part(head):
    mesh, lm, parts, _, _, rig = head
    v = mesh.vertices.astype(np.float64)
    d = rig.morph_targets["jawOpen"].astype(np.float64)
    hinge = np.asarray(rig.info["hinge"])
    head_ids = parts["head"]
    front = head_ids[(np.abs(v[head_ids, 0]) < 0.02) & (v[head_ids, 2] > 0.3)]
    chin = front[np.argmin(np.abs(v[front, 1] - (MOUTH_Y - 0.12)))]
    r0 = np.linalg.norm((v[chin] - hinge)[1:])
    r1 = np.linalg.norm((v[chin] + d[chin] - hinge)[1:])
    assert np.linalg.norm(d[chin]) > 0.02  # the chin moves ...
    assert abs(r1 - r0) < 1e-4 * r0  # ... on a circle about the hinge axis (along X)
    assert abs(d[chin, 0]) < 1e-6 and d[chin, 1] < 0
    lower_lip, upper_lip = lm[18], lm[14]
    assert np.linalg.norm(d[lower_lip]) > 0.02 and np.linalg.norm(d[upper_lip]) < 1e-6
    assert rig.info["mouth_sealed"] is False


def test_lower_teeth_follow_the_jaw_upper_teeth_stay(head):
    mesh, _, parts, _, _, rig = head
    from t2bs.rig.autorig import rotate_about

    v = mesh.vertices.astype(np.float64)
    d = rig.morph_targets["jawOpen"].astype(np.float64)
    low = parts["teeth_lower"]
    turned = rotate_about(
        v[low], np.asarray(rig.info["hinge"]), np.array([1.0, 0, 0]), np.radians(rig.info["jaw_angle_deg"])
    )
    np.testing.assert_allclose(d[low], turned - v[low], atol=2e-4)  # rigidly with the jaw
    assert np.abs(d[parts["teeth_upper"]]).max() == 0


def test_left_is_the_characters_left(head):
    mesh, _, parts, _, _, rig = head
    v = mesh.vertices
    lm = head[1]
    for name, own, mirror in (
        ("eyeBlinkLeft", 7, 1),
        ("mouthSmileLeft", 16, 12),
        ("browOuterUpLeft", None, None),
        ("mouthFrownLeft", 16, 12),
        ("browDownLeft", None, None),
    ):
        for sign, n, a, b in ((1, name, own, mirror), (-1, name.replace("Left", "Right"), mirror, own)):
            mag = np.linalg.norm(rig.morph_targets[n], axis=1)
            assert sign * (mag * v[:, 0]).sum() / mag.sum() > 0.05, n  # its motion sits on its own side
            if a is not None:  # its own landmark moves, the mirrored one stays
                assert mag[lm[a]] > 0.5 * mag.max() and mag[lm[b]] < 0.02 * mag.max(), n
    look = rig.morph_targets["eyeLookOutLeft"][parts["eye_left"]]
    front = parts["eye_left"][np.argmax(v[parts["eye_left"], 2])]
    assert look[list(parts["eye_left"]).index(front), 0] > 0  # the left eye looks out to +X
    assert np.abs(rig.morph_targets["eyeLookOutLeft"][parts["head"]]).max() == 0
    assert rig.morph_targets["mouthSmileLeft"][:, 1].sum() > 0  # the corner goes up
    smile = np.linalg.norm(rig.morph_targets["mouthSmileLeft"] + rig.morph_targets["mouthSmileRight"], axis=1)
    assert smile[[lm[14], lm[18]]].max() < 0.05 * smile[[lm[12], lm[16]]].min()  # the lips' middle stays
    assert "tongueOut" in rig.missing and "mouthClose" in rig.missing


def test_mesh_without_a_face_gets_one_error_line():
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    mesh = Mesh(np.asarray(ball.vertices, np.float32), np.asarray(ball.faces, np.int32))
    with pytest.raises(UserError) as e:
        find_face(mesh, use_mediapipe=False, source_name="ball.glb")
    msg = str(e.value)
    assert "\n" not in msg and "no face found on ball.glb" in msg and "--landmarks" in msg and "36-47" in msg


def test_landmarks_file_formats(tmp_path, head):
    mesh, lm, *_ = head
    p = tmp_path / "lm.json"
    # What `t2bs landmarks` writes: extra keys are ignored; named points are optional.
    p.write_text(
        json.dumps(
            {"version": 1, "backend": "override", "vertex_ids": lm.tolist(), "chin": 5, "named": {"brow_left": 7}}
        )
    )
    ids, named = read_landmarks_file(p, mesh.num_vertices)
    assert ids.tolist() == lm.tolist() and named == {"chin": 5, "brow_left": 7}
    for bad, words in (
        ({"vertex_ids": [1, 2]}, "20 integers"),
        ({"vertex_ids": list(range(19)) + [10**7]}, "must be in"),
        ({"vertex_ids": lm.tolist(), "nose": 3}, None),
        ({"points": []}, 'needs "vertex_ids"'),
    ):
        p.write_text(json.dumps(bad))
        if words is None:  # unknown top-level keys are other tools' data, not an error
            read_landmarks_file(p, mesh.num_vertices)
            continue
        with pytest.raises(UserError, match=words):
            read_landmarks_file(p, mesh.num_vertices)
    swapped = np.concatenate([lm[6:12], lm[0:6], lm[12:]])
    with pytest.raises(UserError, match="left eye"):
        autorig(mesh, FaceLandmarks(swapped, "file"))


def test_autorig_command_keeps_vertex_order_and_animator_plays_it(tmp_path, head):
    from typer.testing import CliRunner

    from t2bs.cli import app
    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.video.animator import animate, morph_drivers, usable_rig

    mesh, lm, *_ = head
    src, out, lmf = tmp_path / "head.glb", tmp_path / "rig.glb", tmp_path / "lm.json"
    save_mesh(mesh, src)
    lmf.write_text(json.dumps({"vertex_ids": lm.tolist()}))
    res = CliRunner().invoke(app, ["autorig", str(src), "-o", str(out), "--landmarks", str(lmf)])
    assert res.exit_code == 0, res.output
    before, after = load_mesh(src), load_mesh(out)
    np.testing.assert_array_equal(before.vertices, after.vertices)  # order and count kept
    assert {"jawOpen", "eyeBlinkLeft", "mouthSmileRight", "browInnerUp"} <= set(after.morph_targets)
    assert not usable_rig(before) and usable_rig(after)
    drivers = morph_drivers(after)
    assert drivers["eyeBlinkLeft"] == [("blink_left", 1.0)] and drivers["mouthSmileRight"] == [("smile_right", 1.0)]
    anim = animate(after, "blinking", seed=0)
    assert "eyeBlinkLeft" in anim.names and anim.weights[:, anim.names.index("eyeBlinkLeft")].max() > 0.5
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["landmarks"]["source"] == "file" and "tongueOut" in summary["missing"]
    assert summary["eye_left"]["lid_meet"] == 0.2  # an eyeball: the human line by default
    # --lid-meet moves where the lids meet: mid-height, the upper lid travels less, the lower more.
    out2 = tmp_path / "rig_mid.glb"
    res = CliRunner().invoke(app, ["autorig", str(src), "-o", str(out2), "--landmarks", str(lmf), "--lid-meet", "0.5"])
    assert res.exit_code == 0, res.output
    assert json.loads(out2.with_suffix(".json").read_text())["eye_left"]["lid_meet"] == 0.5
    d2, d1 = load_mesh(out2).morph_targets["eyeBlinkLeft"], after.morph_targets["eyeBlinkLeft"]
    upper, lower = lm[[7, 8]], lm[[10, 11]]  # left eye: 42-47 -> positions 6-11 (upper 43-44, lower 46-47)
    assert np.abs(d2[upper, 1]).mean() < 0.8 * np.abs(d1[upper, 1]).mean()
    assert np.abs(d2[lower, 1]).mean() > 1.5 * np.abs(d1[lower, 1]).mean()
    res = CliRunner().invoke(app, ["autorig", str(src), "-o", str(tmp_path / "x.glb"), "--lid-meet", "1.5"])
    # A UserError: `t2bs` prints it as one `error:` line and exits 2 (t2bs.cli.main).
    assert "--lid-meet must lie in [0, 1]" in str(res.exception), res.output
    assert type(res.exception).__name__ == "UserError"
    assert not (tmp_path / "x.glb").exists()


def test_landmarks_stage_reuses_the_auto_rigs_landmarks(tmp_path, head):
    """A static character animated through the auto rig has no blink / mouth shapes of its own for the
    motion landmark backend: `t2bs landmarks` (auto) takes the auto rig's 20 points."""
    from t2bs.geometry.io import save_mesh
    from t2bs.project import Project, write_json
    from t2bs.retarget.landmarks_stage import run

    mesh, lm, *_ = head
    project = Project(tmp_path / "proj")
    save_mesh(mesh, project.mesh_path)
    write_json(project.path("character", "autorig.json"), {"landmarks": {"vertex_ids": lm.tolist(), "source": "file"}})
    got = run(project.root).landmarks
    assert got.backend == "autorig" and got.vertex_ids.tolist() == lm.tolist()


def test_picked_landmarks_by_ray_and_saved_for_the_auto_rig(tmp_path, head):
    from t2bs.rig.face import read_landmarks_file
    from t2bs.rig.pick import SLOTS, LandmarkPicks, ray_vertex

    mesh, lm, parts, *_ = head
    v = mesh.vertices.astype(np.float64)
    # A ray from the front camera's side through a landmark vertex hits it (or a vertex of its triangle).
    for k in (0, 7, 14, 18):
        target = v[lm[k]]
        origin = target + np.array([0.0, 0.0, 2.0])
        vid = ray_vertex(v, mesh.faces, origin, target - origin)
        assert np.linalg.norm(v[vid] - target) < 0.03
    assert ray_vertex(v, mesh.faces, [5.0, 5.0, 5.0], [1.0, 0.0, 0.0]) is None  # pointing away: a miss
    picks = LandmarkPicks(mesh.num_vertices)
    for (slot, _), vid in zip(SLOTS, lm):
        assert picks.next_slot() == slot  # the picker walks the 20 in order
        picks.set(slot, int(vid))
    picks.set("chin", int(parts["head"][0]))
    path = picks.save(tmp_path / "landmarks.json")
    ids, named = read_landmarks_file(path, mesh.num_vertices)
    assert ids.tolist() == lm.tolist() and named == {"chin": int(parts["head"][0])}
    # In a project: the picks saved before, else the points the auto rig found, to correct.
    from t2bs.project import write_json

    write_json(
        tmp_path / "proj" / "character" / "autorig.json",
        {"landmarks": {"vertex_ids": lm.tolist(), "named": {"chin": 3}}},
    )
    found = LandmarkPicks.for_project(tmp_path / "proj", mesh.num_vertices)
    assert found.to_dict()["vertex_ids"] == lm.tolist() and found.ids["chin"] == 3
    picks.save(tmp_path / "proj" / "landmarks" / "picked.json")
    assert LandmarkPicks.for_project(tmp_path / "proj", mesh.num_vertices).ids["chin"] == int(parts["head"][0])
    empty = LandmarkPicks(mesh.num_vertices)
    empty.set("36", 1)
    with pytest.raises(UserError, match="not picked yet: 37"):
        empty.save(tmp_path / "x.json")


def test_viewer_click_picks_a_landmark(tmp_path):
    pytest.importorskip("viser")
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from viewer_fixture import build_fixture_project

    from t2bs.viewer.app import ViewerApp

    root = tmp_path / "proj"
    build_fixture_project(root, with_model=False)
    with ViewerApp(root, port=0) as app:
        v = app.neutral.astype(np.float64)
        front = int(np.argmax(v[:, 2]))
        vid = app.pick_ray(v[front] + [0, 0, 3.0], [0, 0, -1.0])  # a click straight at the front-most point
        assert np.linalg.norm(v[vid] - v[front]) < 0.05 and app.picks.ids["36"] == vid
        assert app._pick_slot.value.startswith("37:")  # the picker moved on to the next point
        with pytest.raises(UserError, match="not picked yet"):
            app.save_landmarks()


def test_a_collar_under_the_chin_does_not_follow_the_jaw():
    mesh, lm, parts, _ = synthetic_head(collar=True)
    rig = autorig(mesh, FaceLandmarks(lm, "file", {}, find_eyeballs(mesh)))
    assert np.abs(rig.morph_targets["jawOpen"][parts["collar"]]).max() == 0
    assert np.abs(rig.morph_targets["jawOpen"][parts["teeth_lower"]]).max() > 0.01


def test_video_stage_auto_rigs_a_static_character(tmp_path, head):
    """`t2bs videos` on a character without a face rig builds the auto rig (here from the user's picked
    points, landmarks/picked.json) and animates it: the blinking grid's ground truth closes the lids; the manifest and
    the grid say the motion came from the auto rig."""
    from t2bs.geometry.io import save_mesh
    from t2bs.project import Project, read_json, write_json
    from t2bs.video import stage as videos
    from t2bs.video.grid import load_grid

    mesh, lm, parts, *_ = head
    project = Project(tmp_path / "proj")
    save_mesh(mesh, project.mesh_path)
    write_json(project.path("landmarks", "picked.json"), {"vertex_ids": lm.tolist(), "backend": "picked"})
    videos.run(
        project.root,
        videos.VideosConfig(
            prompts="blinking",
            samples=1,
            defects="clean",
            frames=8,
            size=48,
            views=3,
            seed=0,
            shading="unlit",
            backend="procedural",
            steps=1,
        ),
    )
    stage = read_json(project.path("manifest.json"))["stages"]["videos"]
    assert stage["motion_source"] == "autorig" and stage["autorig"]["landmarks"] == "file"
    assert "eyeBlinkLeft" in stage["autorig"]["shapes"]
    grid = load_grid(project.path("videos", "blinking-s0"))
    assert grid.meta["motion_source"] == "autorig"
    gt = grid.gt_vertices  # [T, N, 3]: head motion + the auto rig's blink
    # The left eye closes in some frame: the distance between its upper and lower lid points (which a
    # rigid head motion keeps) shrinks to a fraction of the open eye's.
    gap = np.linalg.norm(gt[:, lm[8]] - gt[:, lm[10]], axis=-1)  # [T]
    assert gap[0] == pytest.approx(np.linalg.norm(mesh.vertices[lm[8]] - mesh.vertices[lm[10]]), rel=1e-4)
    assert gap.min() < 0.5 * gap[0]
    # The landmarks stage then writes the auto rig's points; a re-run keeps the rig and the videos.
    from t2bs.retarget.landmarks_stage import run
    from t2bs.rig.stage import project_autorig

    assert run(project.root).backend == "autorig"
    done = project.path("character", "autorig", "done.json").read_text()
    project_autorig(project, mesh)
    assert project.path("character", "autorig", "done.json").read_text() == done


def test_cli_on_a_mesh_with_no_face_prints_one_error_line(tmp_path):
    """`t2bs autorig ball.glb`: no labels, MediaPipe finds no face (or is not installed): one `error:` line, exit 2."""
    import subprocess
    import sys
    from pathlib import Path

    import trimesh

    from t2bs.geometry.io import save_mesh

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    save_mesh(Mesh(np.asarray(ball.vertices, np.float32), np.asarray(ball.faces, np.int32)), tmp_path / "ball.glb")
    src = str(Path(__file__).resolve().parents[1] / "src")
    res = subprocess.run(
        [sys.executable, "-m", "t2bs.cli", "autorig", str(tmp_path / "ball.glb"), "-o", str(tmp_path / "o.glb")],
        capture_output=True,
        text=True,
        env={**__import__("os").environ, "PYTHONPATH": src},
        timeout=120,
    )
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: no face found on"), res.stderr
    assert "--landmarks" in lines[0] and not (tmp_path / "o.glb").exists()


def test_report_says_the_motion_came_from_the_auto_rig(tmp_path):
    from t2bs.pipeline import write_report
    from t2bs.project import Project

    project = Project(tmp_path / "proj")
    project.record_stage(
        "videos",
        backend="procedural",
        motion_source="autorig",
        autorig={
            "shapes": ["jawOpen", "eyeBlinkLeft"],
            "landmarks": "mediapipe",
            "mouth": "lip seam: the lips part",
            "missing": {"tongueOut": "no tongue part", "mouthClose": "no lips", "mouthRollLower": "no lips"},
        },
    )
    report = write_report(project, "a head", "quick", {"videos": 1.0})
    text = project.path("report.md").read_text()
    assert report["motion_source"] == "autorig"
    assert "Motion source: the **auto rig**" in text and "2 ARKit shapes from mediapipe landmarks" in text
    assert "- missing mouthClose, mouthRollLower: no lips" in text and "- missing tongueOut: no tongue part" in text


def test_named_jaw_hinge_and_chin_are_used(head):
    mesh, lm, parts, *_ = head
    v = mesh.vertices.astype(np.float64)
    side = parts["head"][np.argmin(np.abs(v[parts["head"]] - [0.45, -0.05, 0.0]).sum(1))]  # a vertex by the ear
    rig = autorig(mesh, FaceLandmarks(lm, "file", {"jaw_hinge": int(side)}, find_eyeballs(mesh)))
    hinge = np.asarray(rig.info["hinge"])
    assert hinge[1] == pytest.approx(v[side, 1], abs=1e-5) and hinge[2] == pytest.approx(v[side, 2], abs=1e-5)
    d = rig.morph_targets["jawOpen"].astype(np.float64)
    chin = lm[18]
    r0, r1 = np.linalg.norm((v[chin] - hinge)[1:]), np.linalg.norm((v[chin] + d[chin] - hinge)[1:])
    assert abs(r1 - r0) < 1e-4 * r0  # the lower lip turns about the user's hinge


def _front_view(mesh):
    from t2bs.geometry.camera import frontal_camera
    from t2bs.render.mesh_renderer import MeshRenderer

    cam = frontal_camera(256)
    r = MeshRenderer()
    try:
        rendered = r.render(mesh, cam, shading="lambert")
        vis = r.vertex_visibility(mesh, cam)
    finally:
        r.release()
    uv, _ = cam.project(mesh.vertices.astype(np.float64))
    return rendered, vis, uv


def test_lip_seam_moves_a_misplaced_mouth_onto_the_mesh_opening():
    """A detector that puts the mouth 40 % of the way up to the eyes and half as wide (what MediaPipe
    does on the turtle): the seam finder puts the 8 inner-lip points on the slit, corner to corner."""
    from t2bs.rig.seam import find_lip_seam

    mesh, lm, parts, _ = synthetic_head()
    rendered, vis, uv = _front_view(mesh)
    vis &= np.isin(np.arange(mesh.num_vertices), parts["head"])  # the skin part, as the MediaPipe lift does
    eyes_px, mouth_px = uv[lm[:12]], uv[lm[12:]].copy()
    centre = mouth_px.mean(0)
    mouth_px = centre + 0.5 * (mouth_px - centre) - [0, 0.4 * (centre[1] - eyes_px[:, 1].mean())]
    seam = find_lip_seam(mesh.vertices, mesh.faces, uv, rendered, vis, eyes_px, mouth_px)
    assert seam is not None
    p = mesh.vertices[seam.ids].astype(np.float64)
    assert np.abs(p[:, 1] - MOUTH_Y).max() < 0.05  # on the mouth line, within two of the sphere's rings (0.025 apart)
    assert p[4, 0] > MOUTH_HALF - 0.04 and p[0, 0] < -(MOUTH_HALF - 0.04)  # 64 on the left (+X), 60 right
    assert (p[[1, 2, 3], 1] > MOUTH_Y).all() and (p[[5, 6, 7], 1] < MOUTH_Y).all()  # upper lip, lower lip
    assert p[1, 0] < p[2, 0] < p[3, 0] and p[7, 0] < p[6, 0] < p[5, 0]  # 61-63 right to left, 65-67 back
    assert np.all(np.isin(seam.ids, parts["head"]))  # on the skin, not on the teeth seen through the slit


def test_sealed_mouth_has_no_lip_seam():
    from t2bs.rig.seam import find_lip_seam

    slit, lm, _, _ = synthetic_head()
    _, _, uv_slit = _front_view(slit)
    mesh, _, parts, _ = synthetic_head(slit=False)
    rendered, vis, uv = _front_view(mesh)
    vis &= np.isin(np.arange(mesh.num_vertices), parts["head"])
    eyes_px, mouth_px = uv_slit[lm[:12]], uv_slit[lm[12:]]  # where the slit head's points are
    assert find_lip_seam(mesh.vertices, mesh.faces, uv, rendered, vis, eyes_px, mouth_px) is None


# ---- flat (painted) eyes: an anime head's eye white painted on the skin, a flat iris disc, a lash card
SKIN_RGB, WHITE_RGB, IRIS_RGB, LASH_RGB = (0.8, 0.4, 0.5), (1.0, 1.0, 1.0), (0.4, 0.1, 0.7), (0.05, 0.05, 0.1)


def _polar_grid(centre, radii, angles, z_of, disc: bool):
    """Vertices [V, 3] and faces of a sheet facing +Z: rings at ``radii`` ([R] half axes (a, b)) x ``angles``, at the
    depth z_of(x, y). ``disc``: the angles go all round and a centre vertex fans the innermost ring; else a strip."""
    n = len(angles)
    verts = [np.asarray(centre, np.float64)] if disc else []
    for a, b in radii:
        verts += list(centre + np.stack([a * np.cos(angles), b * np.sin(angles)], axis=1))
    off, nxt = (1, lambda j: (j + 1) % n) if disc else (0, lambda j: j + 1)
    faces = [(0, 1 + j, 1 + nxt(j)) for j in range(n)] if disc else []
    for k in range(len(radii) - 1):
        for j in range(n if disc else n - 1):
            p, q = off + k * n + j, off + k * n + nxt(j)
            faces += [(p, p + n, q + n), (p, q + n, q)]
    xy = np.asarray(verts)
    return np.concatenate([xy, z_of(xy[:, 0], xy[:, 1])[:, None]], axis=1), np.asarray(faces)


def painted_head(count: int = 128):
    """A sphere head (radius 0.5, facing +Z, no eye holes) with painted eyes: the skin's vertex colour is white
    inside each eye ellipse, a flat iris disc floats just in front of it, a lash card lies along its upper edge;
    a slit mouth. Returns (mesh, landmark ids [20] on the painted outline, parts {name: vertex ids})."""
    import trimesh

    head = trimesh.creation.uv_sphere(radius=0.5, count=[count, count])
    c = head.triangles_center
    head.update_faces(~((np.abs(c[:, 0]) < MOUTH_HALF) & (np.abs(c[:, 1] - MOUTH_Y) < 0.012) & (c[:, 2] > 0)))
    head.remove_unreferenced_vertices()
    hv = np.asarray(head.vertices)
    colours = np.tile(SKIN_RGB, (len(hv), 1))
    on_skin = lambda dz: lambda x, y: np.sqrt(0.25 - x**2 - y**2) + dz  # noqa: E731
    parts = [("head", hv, np.asarray(head.faces), colours)]
    for side, sx in (("left", 1), ("right", -1)):
        ell = ((hv[:, 0] - sx * EYE_X) / EYE_A) ** 2 + ((hv[:, 1] - EYE_Y) / EYE_B) ** 2 < 1
        colours[ell & (hv[:, 2] > 0)] = WHITE_RGB
        centre = np.array([sx * EYE_X - 0.2 * EYE_A * sx, EYE_Y])  # the iris looks a little inwards
        ring = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        v_i, f_i = _polar_grid(centre, [(0.2 * EYE_B * k,) * 2 for k in (1, 2, 3)], ring, on_skin(0.012), True)
        parts.append((f"iris_{side}", v_i, f_i, np.tile(IRIS_RGB, (len(v_i), 1))))
        top = np.radians(np.linspace(12, 168, 20))
        v_l, f_l = _polar_grid(
            np.array([sx * EYE_X, EYE_Y]), [(EYE_A, EYE_B), (1.15 * EYE_A, 1.45 * EYE_B)], top, on_skin(0.006), False
        )
        parts.append((f"lash_{side}", v_l, f_l, np.tile(LASH_RGB, (len(v_l), 1))))
    verts, faces, cols, ids, n = [], [], [], {}, 0
    for name, pv, pf, pc in parts:
        verts.append(pv)
        faces.append(pf + n)
        cols.append(pc)
        ids[name] = np.arange(n, n + len(pv))
        n += len(pv)
    mesh = Mesh(
        np.concatenate(verts).astype(np.float32),
        np.concatenate(faces).astype(np.int32),
        vertex_colors=np.concatenate(cols).astype(np.float32),
    )
    v = mesh.vertices
    skin = ids["head"][v[ids["head"], 2] > 0]
    lm = []
    for sx in (-1, 1):  # 36-41 the right eye (-X), then 42-47 the left eye (+X): skin just outside the white
        out = skin[((v[skin, 0] - sx * EYE_X) / EYE_A) ** 2 + ((v[skin, 1] - EYE_Y) / EYE_B) ** 2 >= 1]
        for a in np.radians(EYE_ANGLES):
            target = np.array([sx * EYE_X + EYE_A * np.cos(a), EYE_Y + EYE_B * np.sin(a)])
            lm.append(int(out[np.argmin(np.linalg.norm(v[out, :2] - target, axis=1))]))
    rim = np.intersect1d(_boundary(np.asarray(head.faces)), ids["head"])
    for a in MOUTH_ANGLES:
        r = np.radians(a)
        target = np.array([MOUTH_HALF * np.cos(r), MOUTH_Y + 0.01 * np.sin(r)])
        cand = rim[np.abs(v[rim, 1] - MOUTH_Y) < 0.05]
        cand = cand[v[cand, 1] > MOUTH_Y] if 0 < a < 180 else cand[v[cand, 1] < MOUTH_Y] if a < 0 else cand
        lm.append(int(cand[np.argmin(np.linalg.norm(v[cand, :2] - target, axis=1))]))
    return mesh, np.asarray(lm), ids


@pytest.fixture(scope="module")
def flat_head():
    mesh, lm, parts = painted_head()
    face = FaceLandmarks(lm, "file", {}, find_eyeballs(mesh))
    return mesh, lm, parts, face, autorig(mesh, face)


def test_flat_eye_squashes_onto_the_meeting_line(flat_head, head):
    """No eyeball behind the lids (a painted eye, a flat iris disc): the lids slide straight down / up in the
    face's plane, the painted opening's upper and lower edge meet on the line 40 % of the way up from the lower
    lid at each place along the eye (equal strain), nothing passes it, and nothing moves outside that eye's lids
    (the lash card and iris go with them)."""
    mesh, lm, parts, face, rig = flat_head
    assert face.eyeballs == {}  # a flat disc is no eyeball
    assert head[5].info["eye_left"]["lids"] == "turn about the eyeball"  # the ball head keeps its turning lids
    assert head[5].info["eye_left"]["lid_meet"] == 0.2  # and its human meeting line
    v = mesh.vertices.astype(np.float64)
    we = 2 * EYE_A
    for side, sl, sx in (("left", slice(6, 12), 1), ("right", slice(0, 6), -1)):
        info = rig.info[f"eye_{side}"]
        assert info["lids"] == "slide (flat eye)" and info["eye_surface"] == "flat", info
        d = rig.morph_targets[f"eyeBlink{side.capitalize()}"].astype(np.float64)
        eye = lm[sl]
        # The eye's frame: across the corner-to-corner axis, in the face's plane (the grid tilts it a little).
        axis = (v[eye[3]] - v[eye[0]]) / np.linalg.norm(v[eye[3]] - v[eye[0]]) * sx
        up = np.array([0, 1.0, 0]) - axis[1] * axis
        up /= np.linalg.norm(up)
        h, h_closed = v @ up, (v + d) @ up
        h_up, h_lo = h[eye[[1, 2]]].mean(), h[eye[[4, 5]]].mean()
        # A flat eye closes on the equal-strain line: each lid travels in proportion to its falloff radius
        # (upper 0.45, lower 0.3 eye widths), so 0.4 of the height up from the lower lid.
        assert info["lid_meet"] == pytest.approx(0.4)
        # The meeting line at each place a along the eye: 0.4 of the way up from the lower lid to the upper, the
        # lids drawn through the six points (the grid tilts the painted eye: its line slopes with it).
        a, a_eye = v @ axis, v[eye] @ axis

        def lid(ids):
            return np.interp(a, a_eye[ids][np.argsort(a_eye[ids])], h[eye[ids]][np.argsort(a_eye[ids])])

        line = lid([0, 5, 4, 3]) + 0.4 * (lid([0, 1, 2, 3]) - lid([0, 5, 4, 3]))
        # The painted opening's upper and lower edge reach that line, and the corners stay. Not exactly: the rig
        # draws its line through the margins, here shortest paths of edges over the skin's polar grid that wander
        # up to a third of the eye's height off the painted edge (the left eye's lower one): 0.17 of the height
        # off (0 on the right eye); the upper edge passes the lower by at most 0.09 of the height.
        eye_h = h_up - h_lo
        assert np.abs(h_closed[eye[[1, 2, 4, 5]]] - line[eye[[1, 2, 4, 5]]]).max() < 0.2 * eye_h, (h_closed[eye], line)
        assert np.abs(d[eye[[0, 3]]]).max() < 1e-7
        lo = np.array([0, 5, 4, 3])[np.argsort(a_eye[[0, 5, 4, 3]])]
        closed_lower = np.interp(a_eye[[1, 2]], a_eye[lo], h_closed[eye[lo]])
        assert np.all(h_closed[eye[[1, 2]]] > closed_lower - 0.1 * eye_h), (h_closed[eye[[1, 2]]], closed_lower)
        assert (h_closed - h)[eye[[1, 2]]].max() < -0.55 * (h_up - h_lo)  # the upper lid travels most of the way
        assert 0.25 * (h_up - h_lo) < (h_closed - h)[eye[[4, 5]]].min() < 0.5 * (h_up - h_lo)  # the lower lid less
        # A slide across the eye: straight down / up in the face's plane, neither sideways nor out of it.
        assert np.abs(d - np.outer(d @ up, up)).max() < 1e-6
        # No vertex goes far past the meeting line (past the six points' line by as much as the margins wander).
        moved = np.linalg.norm(d, axis=1) > 1e-7
        crossed = moved & ((h - line) * (h_closed - line) < 0)
        assert np.all(np.abs(h_closed - line)[crossed] < 0.2 * eye_h)
        # Only this eye's lids move: its own side, within the lid falloff (0.45 eye widths) of the opening.
        assert np.all(sx * v[moved, 0] > 0)
        assert np.all(np.abs(v[moved, 0] - sx * EYE_X) < EYE_A + 0.45 * we)
        assert np.all(np.abs(v[moved, 1] - EYE_Y) < EYE_B + 0.45 * we)
        other = "right" if side == "left" else "left"
        for p in (f"iris_{other}", f"lash_{other}"):
            assert np.abs(d[parts[p]]).max() == 0
        # The lash card goes down with the upper lid, all of it between the corners (its ends past the corners
        # stay with them); the iris squashes with the opening.
        lash = parts[f"lash_{side}"]
        inside = lash[(a[lash] - a_eye[[0, 3]].min() > 0.05 * we) & (a_eye[[0, 3]].max() - a[lash] > 0.05 * we)]
        assert len(inside) > 0.7 * len(lash) and np.all(d[inside] @ up < 0) and np.all(d[lash] @ up <= 0)
        assert (d[lash] @ up).min() < -0.5 * (h_up - line[eye[[1, 2]]].mean())
        assert np.abs(d[parts[f"iris_{side}"]]).max() > 0


def test_eye_surface_decides_turn_or_slide(head, flat_head):
    """The lids turn about a ball only where the skin seen in the opening bulges like one (an eye sculpted into the
    skin: here the ball head's eyeballs taken as skin); a painted eye on the face's curve and a hole slide."""
    from t2bs.rig.autorig import _eye_is_round

    mesh, lm = head[0], head[1]
    v = mesh.vertices.astype(np.float64)
    sculpted = np.ones(len(v), bool)  # the eyeballs as if they were the skin's own bulge
    hole = np.isin(np.arange(len(v)), head[2]["head"])
    flat_v = flat_head[0].vertices.astype(np.float64)
    painted = np.isin(np.arange(len(flat_v)), flat_head[2]["head"])
    for sl in (slice(0, 6), slice(6, 12)):
        pts, flat_pts = v[lm[sl]], flat_v[flat_head[1][sl]]
        we, flat_we = float(np.linalg.norm(pts[0] - pts[3])), float(np.linalg.norm(flat_pts[0] - flat_pts[3]))
        got, info = _eye_is_round(v, sculpted, pts, we, None)
        assert got is True and info["eye_surface_radius_eye_widths"] < 1, info
        assert _eye_is_round(v, hole, pts, we, None)[0] is False  # the rim around a hole: the face's curve
        got, info = _eye_is_round(flat_v, painted, flat_pts, flat_we, None)
        assert got is False and info["eye_surface_radius_eye_widths"] > 2, info  # the head's own curve (3.3)
        # With the iris disc and the lash card counted as eye surface the painted eye would look like a dome.
        assert _eye_is_round(flat_v, np.ones(len(flat_v), bool), flat_pts, flat_we, None)[0] is True


def test_painted_eye_outline_gives_the_lid_points():
    """A flat eye part (the iris disc, or the lash card the detector's eye centre falls on): the opening is the eye
    white painted around it, not the disc's outline; the points go on the skin at the white's edge, under the lash
    card where it hides the skin, upper points on the upper edge, lower on the lower, right eye first."""
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.rig.face import eyes_from_parts

    mesh, _, parts = painted_head()
    v = mesh.vertices.astype(np.float64)
    with MeshRenderer() as r:
        by_iris = eyes_from_parts(mesh, r, {s: parts[f"iris_{s}"] for s in ("left", "right")}, flat=True)
        by_lash = eyes_from_parts(mesh, r, {s: parts[f"lash_{s}"] for s in ("left", "right")}, flat=True)
    for ids in (by_iris, by_lash):
        assert np.all(np.isin(ids, parts["head"]))  # on the skin, not on the lash card or the iris
        for sl, sx in ((slice(0, 6), -1), (slice(6, 12), 1)):
            p = v[ids[sl]]
            e = ((p[:, 0] - sx * EYE_X) / EYE_A) ** 2 + ((p[:, 1] - EYE_Y) / EYE_B) ** 2
            assert np.all((e > 0.8) & (e < 1.6)), e  # on the white's outline (the iris is 0.35 of it)
            assert np.all(p[[1, 2], 1] > EYE_Y + 0.5 * EYE_B) and np.all(p[[4, 5], 1] < EYE_Y - 0.5 * EYE_B)
            assert p[0, 0] < p[1, 0] < p[2, 0] < p[3, 0] and p[0, 0] < p[5, 0] < p[4, 0] < p[3, 0]
    assert np.array_equal(by_iris, by_lash)


@pytest.mark.parametrize("prompt", ["a cartoon fox", "a robot"])
def test_a_lid_shell_turns_as_one_piece_like_the_characters_own_blink(prompt):
    """The procedural characters' lids are shells around the eyeball (their own part): the blink turns the shell
    about the ball, falling off over the whole shell, the lids meeting where a flat eye's do; nothing else moves."""
    from dataclasses import replace

    from t2bs.character.procedural import generate_procedural

    mesh = generate_procedural(prompt, seed=0).mesh
    stripped = replace(mesh, morph_targets={})
    rig = autorig(stripped, find_face(stripped, source_name=prompt))
    assert rig.info["eye_left"]["lid_shell"] is True and rig.info["eye_left"]["lid_meet"] == 0.4
    auto, truth = rig.morph_targets["eyeBlinkLeft"].astype(np.float64), mesh.morph_targets["blink_left"]
    cos = float(auto.ravel() @ truth.ravel() / (np.linalg.norm(auto) * np.linalg.norm(truth)))
    assert cos >= 0.88, cos  # 0.79 (fox) / 0.81 (robot) when the shell's weights fell off over the skin's lid height
    lid = mesh.part_mask("eyelid_left")
    assert np.abs(auto[~lid]).max() == 0  # the skin, the ball and the other eye stay


@pytest.mark.parametrize("prompt", ["a cartoon fox", "a robot"])
def test_a_closed_blink_hides_the_eyeball_into_the_corners(prompt):
    """Seen from the front, eyeBlinkLeft at 1 leaves (almost) nothing of the left eyeball visible: the lid margins
    meet along the whole opening, corners included (a straight meeting line and lid weights halved near the corners
    left open triangles there: 11 of the fox's 257 eyeball pixels, 6 of the robot's 561)."""
    from dataclasses import replace

    from t2bs.character.procedural import generate_procedural
    from t2bs.geometry.camera import frontal_camera
    from t2bs.render.mesh_renderer import render_mesh

    mesh = generate_procedural(prompt, seed=0).mesh
    stripped = replace(mesh, morph_targets={})
    rig = autorig(stripped, find_face(stripped, source_name=prompt))
    eye, cam = mesh.part_names.index("eye_left"), frontal_camera(256)

    def eyeball_pixels(offsets):
        face_id = render_mesh(mesh, cam, vertices=mesh.vertices + offsets).face_id
        return int((mesh.part_ids[mesh.faces[face_id[face_id >= 0], 0]] == eye).sum())

    opened, closed = eyeball_pixels(0 * mesh.vertices), eyeball_pixels(rig.morph_targets["eyeBlinkLeft"])
    assert opened > 200 and closed <= 0.01 * opened, (opened, closed)  # 2 / 257 (fox), 0 / 561 (robot)


def test_meeting_line_ignores_a_margin_that_dips_into_the_opening():
    """The closing line runs 'meet' of the way from the lower margin to the upper at each place, each margin taken
    by its convex hull: a stretch of the upper margin that wanders down into the opening moves nothing."""
    from t2bs.rig.autorig import _meeting_line

    a = np.linspace(-1, 1, 21)
    upper, lower = 1 - a**2, -(1 - a**2)
    dipped = upper.copy()
    dipped[8:12] -= 0.6  # a path of mesh edges cutting through the painted opening
    line = _meeting_line(a, a, dipped, a[::-1], lower[::-1], 0.4)
    np.testing.assert_allclose(line, -0.2 * (1 - a**2), atol=0.025)  # the hull bridges the dip by a chord: 0.024 off
    assert line[10] > -1 + 0.4 * (1 - 0.6 + 1) + 0.1  # through the dip itself, the line would sit at -0.44
    np.testing.assert_allclose(line[[0, -1]], 0.0)  # the corners stay


def test_lids_in_the_skin_are_no_shell(head):
    assert head[-1].info["eye_left"]["lid_shell"] is False and head[-1].info["eye_left"]["lid_meet"] == 0.2


def test_a_head_whose_mouth_is_another_part_is_no_lid_shell(head):
    """Eyes on the head's skin and the mouth points on a part of their own (here: the teeth standing in for lips
    modelled apart): the head is not a shell around the eye, its lids keep the skin's falloff."""
    mesh, lm, parts, _, _, _ = head
    moved = lm.copy()
    teeth = np.concatenate([parts["teeth_upper"], parts["teeth_lower"]])
    v = mesh.vertices
    for i in range(12, 20):  # each mouth point to the nearest tooth vertex
        moved[i] = teeth[np.argmin(np.linalg.norm(v[teeth] - v[lm[i]], axis=1))]
    rig = autorig(mesh, FaceLandmarks(moved, "file", {}, find_eyeballs(mesh)))
    assert rig.info["eye_left"]["lid_shell"] is False and rig.info["eye_left"]["lid_meet"] == 0.2
