"""Expression prompts and the offline animator against the real assets' morph targets."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import asset
from t2bs.errors import UserError
from t2bs.video.animator import AnimationConfig, animate, apply_head_motion, morph_drivers, resolve_expression
from t2bs.video.prompts import (
    EMOTIONAL_EXPRESSIONS,
    EXPRESSIONS,
    PHYSICAL_EXPRESSIONS,
    load_prompt_list,
    make_jobs,
    resolve_expressions,
    video_prompt,
    write_default_prompt_list,
)


@pytest.fixture(scope="module")
def characters():
    from t2bs.character.render_stage import canonical_character

    return {n: canonical_character(asset(f"{n}.glb"))[0] for n in ("turtle", "facecap", "vipe_hero_head")}


def test_paper_prompts():
    assert len(PHYSICAL_EXPRESSIONS) == 13 and len(EMOTIONAL_EXPRESSIONS) == 7 and len(set(EXPRESSIONS)) == 20
    assert (
        video_prompt("a cartoon turtle", "blinking")
        == "a cartoon turtle, blinking, static camera, the camera is holding still"
    )
    jobs = make_jobs("a fox", ["blinking", "opening the mouth extremely wide"], samples=3)
    assert len(jobs) == 6 and jobs[5].video_id == "opening-the-mouth-extremely-wide-s2"
    assert resolve_expressions("all") == list(EXPRESSIONS)
    assert resolve_expressions("Blinking, tongue-sticking-out-the-mouth") == [
        "blinking",
        "tongue sticking out the mouth",
    ]
    with pytest.raises(UserError, match="unknown expression 'dancing'; valid: talking, screaming"):
        resolve_expressions("blinking,dancing")


def test_prompt_list_files(tmp_path):
    path = write_default_prompt_list(tmp_path / "prompts.txt")
    assert load_prompt_list(path) == list(EXPRESSIONS)
    (tmp_path / "p.json").write_text('{"expressions": ["winking", "sad"]}')
    assert load_prompt_list(tmp_path / "p.json") == ["winking", "sad"]
    assert resolve_expression("winking slowly") == ["teasing the eyes"]  # custom words -> built-ins
    with pytest.raises(UserError, match="cannot animate 'dancing'"):
        resolve_expression("dancing")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(UserError, match="empty"):
        load_prompt_list(tmp_path / "empty.txt")


@pytest.mark.parametrize("name", ["turtle", "facecap"])
def test_every_prompt_moves_the_geometry(characters, name):
    mesh = characters[name]
    diag = mesh.bbox_diagonal()
    for e in EXPRESSIONS:
        a = animate(mesh, e, seed=0, config=AnimationConfig(frames=16))
        assert a.vertices.shape == (16, mesh.num_vertices, 3)
        assert np.abs(a.vertices[0] - mesh.vertices).max() < 1e-6, "frame 0 is the neutral asset"
        total = np.linalg.norm(a.vertices - mesh.vertices[None], axis=-1).max() / diag
        nonrigid = np.linalg.norm(a.morphed - mesh.vertices[None], axis=-1).max() / diag
        assert total > 0.01 and nonrigid > 0.01, (e, total, nonrigid)
        # the rigid part is a rotation: it keeps the distance between any two vertices
        i, j = 0, mesh.num_vertices - 1
        d_morph = np.linalg.norm(a.morphed[:, i] - a.morphed[:, j], axis=-1)
        d_full = np.linalg.norm(a.vertices[:, i] - a.vertices[:, j], axis=-1)
        assert np.allclose(d_morph, d_full, atol=1e-5)


def test_vrm_morph_families_and_mixing(characters):
    m = characters["vipe_hero_head"]
    talk = animate(m, "talking", seed=3, config=AnimationConfig(frames=32))
    assert {"a", "blink_l", "blink_r"} <= set(talk.names)  # a blink while talking
    laugh = animate(characters["facecap"], "laughing", seed=0)
    assert {"jawOpen", "mouthSmile_L", "mouthSmile_R"} <= set(laugh.names)
    turtle = animate(characters["turtle"], "opening the mouth extremely wide", seed=0)
    assert "mouthOpen" in turtle.names and turtle.weights[:, turtle.names.index("mouthOpen")].max() > 0.8


def test_left_right_follow_the_geometry(characters):
    # The turtle's eyeBrowLeft* moves its -X brow: the animator must treat it as the right brow.
    d = morph_drivers(characters["turtle"])
    assert d["eyeBrowRightUp"][0][0] == "brow_up_left" and d["eyeLeftClose"][0][0] == "blink_left"
    for name in ("facecap", "vipe_hero_head", "turtle"):
        m = characters[name]
        left = [n for n, drv in morph_drivers(m).items() if drv[0][0] == "blink_left"][0]
        off = np.linalg.norm(m.morph_targets[left], axis=1)
        assert (off * m.vertices[:, 0]).sum() / off.sum() > 0, f"{name}: blink_left must close the +X eye"


def test_blink_reaches_full_closure_on_a_frame(characters):
    a = animate(characters["facecap"], "blinking", seed=5, config=AnimationConfig(frames=16))
    w = a.weights[:, a.names.index("eyeBlink_L")]
    assert w.max() > 0.8 and w[0] == 0


def test_seed_determinism_and_variation(characters):
    m = characters["facecap"]
    a = animate(m, "talking", seed=1)
    b = animate(m, "talking", seed=1)
    c = animate(m, "talking", seed=2)
    s1 = animate(m, "talking", seed=1, sample=1)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.weights, b.weights)
    assert not np.allclose(a.vertices, c.vertices) and not np.allclose(a.vertices, s1.vertices)


def test_head_motion_axes():
    v = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]], np.float32)[None]  # nose (+Z), top (+Y)
    yaw = apply_head_motion(v, np.array([[90.0, 0, 0]]), np.zeros(3))
    assert np.allclose(yaw[0, 0], [1, 0, 0], atol=1e-6)  # positive yaw turns the face to its left (+X)
    nod = apply_head_motion(v, np.array([[0, 90.0, 0]]), np.zeros(3))
    assert np.allclose(nod[0, 0], [0, -1, 0], atol=1e-6)  # positive pitch nods the face down


def test_smoothstep_is_the_hermite_ramp_rising_or_falling():
    from t2bs.geometry.curves import smoothstep

    x = np.array([-1.0, 0.2, 0.35, 0.5, 1.0])
    assert smoothstep(0.2, 0.5, x).tolist() == pytest.approx([0.0, 0.0, 0.5, 1.0, 1.0])
    assert smoothstep(0.5, 0.2, x).tolist() == pytest.approx([1.0, 1.0, 0.5, 0.0, 0.0])  # edges swapped: falling
    eps = 1e-4  # flat where it starts and stops: no crease in a weight built from it
    assert smoothstep(0.0, 1.0, eps) < 1e-7 and 1.0 - smoothstep(0.0, 1.0, 1.0 - eps) < 1e-7
