"""Procedural text -> character: parts, watertightness, rig regions, determinism, backends, CLI."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from t2bs.character.archetypes import ARCHETYPES
from t2bs.character.backends import generate
from t2bs.character.procedural import RIG_REGIONS, generate_procedural
from t2bs.errors import UserError
from t2bs.geometry.mesh import CANONICAL_DIAGONAL

PROMPTS = {
    "fox": "a fox",
    "dog": "a corgi",
    "cat": "a cat",
    "deer": "a deer with antlers",
    "bear": "a bear",
    "rabbit": "a rabbit",
    "shark": "a shark",
    "dinosaur": "an indoraptor",
    "bird": "an owl",
    "frog": "a frog",
    "robot": "a robot",
    "alien": "an alien",
    "bug": "a bug",
    "plant": "a flower creature",
    "human": "a crying head",
    "cartoon": "a blob",
}
ALWAYS = {
    "head",
    "jaw",
    "eye_left",
    "eye_right",
    "eyelid_left",
    "eyelid_right",
    "lip_upper",
    "lip_lower",
    "mouth_interior",
    "teeth",
    "tongue",
}


@pytest.fixture(scope="module")
def characters():
    return {name: generate_procedural(prompt, seed=0) for name, prompt in PROMPTS.items()}


def test_every_archetype_is_covered():
    assert set(PROMPTS) == set(ARCHETYPES)


def _components(faces: np.ndarray, n: int) -> np.ndarray:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


@pytest.mark.parametrize("name", list(PROMPTS))
def test_archetype_parts_are_closed_labelled_and_sized(characters, name):
    result = characters[name]
    mesh = result.mesh
    assert result.info["archetype"] == name
    assert 5000 <= mesh.num_vertices <= 30000
    assert abs(mesh.bbox_diagonal() - CANONICAL_DIAGONAL) < 1e-4
    assert mesh.vertex_colors.shape == (mesh.num_vertices, 3)
    assert ALWAYS <= set(mesh.part_names)
    assert mesh.part_ids.shape == (mesh.num_vertices,)
    labels = _components(mesh.faces, mesh.num_vertices)
    for comp in np.unique(labels[mesh.faces[:, 0]]):
        fmask = labels[mesh.faces[:, 0]] == comp
        vids = np.unique(mesh.faces[fmask])
        assert len(np.unique(mesh.part_ids[vids])) == 1  # a component never mixes parts
        sub = trimesh.Trimesh(mesh.vertices, mesh.faces[fmask], process=False)
        assert sub.is_watertight, f"{name}: a {mesh.part_names[mesh.part_ids[vids[0]]]} component is open"
        assert sub.is_winding_consistent and sub.volume > 0  # outward faces


@pytest.mark.parametrize("name", ["fox", "robot", "human", "shark", "plant", "bug", "deer"])
def test_each_rig_control_moves_only_its_region_and_visibly(characters, name):
    mesh = characters[name].mesh
    diag = mesh.bbox_diagonal()
    expected = {
        "jaw_open",
        "blink_left",
        "blink_right",
        "smile",
        "frown",
        "tongue_out",
        "cheek_puff",
        "look_left",
        "look_right",
        "look_up",
        "look_down",
    }
    assert expected <= set(mesh.morph_names)
    for control, offsets in mesh.morph_targets.items():
        moved = np.linalg.norm(offsets, axis=1)
        allowed = mesh.part_mask(*RIG_REGIONS[control])
        assert moved[~allowed].max(initial=0.0) == 0.0, f"{name}: {control} moves vertices outside its region"
        assert moved.max() > 0.01 * diag, f"{name}: {control} moves only {moved.max() / diag:.4f} of the diagonal"


def test_rig_directions_are_anatomical(characters):
    mesh = characters["fox"].mesh
    jaw = mesh.part_mask("jaw")
    assert mesh.morph_targets["jaw_open"][jaw, 1].mean() < 0  # the jaw drops
    lid = mesh.part_mask("eyelid_left")
    eye = mesh.part_mask("eye_left")
    assert not mesh.morph_targets["blink_left"][mesh.part_mask("eyelid_right")].any()
    # Closed, the left lid covers the front of the left eyeball: its front-most point moves forward.
    closed = mesh.posed({"blink_left": 1.0})
    front = mesh.vertices[eye][np.argmax(mesh.vertices[eye, 2])]
    near = np.linalg.norm(closed[lid] - front, axis=1).min()
    assert near < np.linalg.norm(mesh.vertices[lid] - front, axis=1).min()
    # The character's left is +X: looking left moves the left iris toward +X.
    colors = mesh.vertex_colors[eye]
    iris = colors.sum(1) < 1.0
    assert mesh.morph_targets["look_left"][eye][iris, 0].mean() > 0
    assert mesh.part_mask("eye_left").any() and mesh.vertices[eye, 0].mean() > 0
    assert mesh.morph_targets["smile"][mesh.part_mask("lip_upper"), 1].max() > 0  # corners go up


@pytest.mark.parametrize("name", ["fox", "human", "robot"])
def test_open_mouth_shows_interior_teeth_and_tongue(characters, name):
    from t2bs.geometry.camera import frontal_camera
    from t2bs.render.mesh_renderer import render_mesh

    mesh = characters[name].mesh
    cam = frontal_camera(256)

    def visible_parts(vertices):
        face_id = render_mesh(mesh, cam, vertices=vertices).face_id
        ids = mesh.part_ids[mesh.faces[face_id[face_id >= 0], 0]]
        return {mesh.part_names[i]: int((ids == i).sum()) for i in np.unique(ids)}

    closed = visible_parts(None)
    opened = visible_parts(mesh.posed({"jaw_open": 1.0, "tongue_out": 0.5}))
    assert opened.get("mouth_interior", 0) > 20 + 3 * closed.get("mouth_interior", 0)
    assert opened.get("tongue", 0) > 10
    if name != "robot":  # the robot's teeth bars sit behind its wide lips
        assert opened.get("teeth", 0) > 5
    blink = visible_parts(mesh.posed({"blink_left": 1.0, "blink_right": 1.0}))
    assert blink.get("eye_left", 0) < 0.2 * closed["eye_left"]


def test_deterministic_and_seed_dependent():
    a = generate_procedural("a fox with big ears", seed=3).mesh
    b = generate_procedural("a fox with big ears", seed=3).mesh
    c = generate_procedural("a fox with big ears", seed=4).mesh
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.vertex_colors, b.vertex_colors)
    assert a.vertices.shape != c.vertices.shape or np.abs(a.vertices - c.vertices).max() > 0.02
    assert np.abs(a.vertex_colors.mean(0) - c.vertex_colors.mean(0)).max() > 0.005


def test_prompts_change_the_character():
    fox = generate_procedural("a fox").mesh
    robot = generate_procedural("a robot").mesh
    assert fox.vertices.shape != robot.vertices.shape or np.abs(fox.vertices - robot.vertices).max() > 0.05
    red = generate_procedural("a red robot")
    assert red.mesh.vertex_colors[red.mesh.part_mask("head")].mean(0)[0] > 0.6  # red skin
    big = generate_procedural("a fox with big ears").info["params"]["ear_size"]
    small = generate_procedural("a fox with small ears").info["params"]["ear_size"]
    assert big > small * 1.5
    assert generate_procedural("a bear with horns").mesh.part_mask("horn").any()


def test_unknown_words_and_fallback_give_notices():
    r = generate_procedural("a fox playing zorblax")
    assert r.info["archetype"] == "fox"
    assert any("zorblax" in n and "playing" in n for n in r.notices)
    g = generate_procedural("a mysterious thing")
    assert g.info["archetype"] == "cartoon" and any("generic cartoon head" in n for n in g.notices)


def test_glb_round_trip_keeps_rig_and_parts(tmp_path, characters):
    from t2bs.geometry.io import load_mesh, save_mesh

    mesh = characters["deer"].mesh
    back = load_mesh(save_mesh(mesh, tmp_path / "deer.glb"))
    assert back.morph_names == mesh.morph_names and back.part_names == mesh.part_names
    assert np.allclose(back.vertices, mesh.vertices, atol=1e-6)
    assert np.allclose(back.morph_targets["jaw_open"], mesh.morph_targets["jaw_open"], atol=1e-6)
    assert np.array_equal(back.part_ids, mesh.part_ids)


def test_command_backend(tmp_path):
    script = tmp_path / "make.py"
    script.write_text(
        "import sys, trimesh\n"
        "out, seed = sys.argv[1], int(sys.argv[2])\n"
        "m = trimesh.creation.box(extents=(1, 2, 3 + seed))\n"
        "m.export(out + '/mesh.obj')\n"
    )
    tmpl = f"{sys.executable} {script} {{out}} {{seed}} {{prompt}}"
    r = generate("a box", backend="command", command=tmpl, seed=1)
    assert r.info["backend"] == "command" and abs(r.mesh.bbox_diagonal() - CANONICAL_DIAGONAL) < 1e-4
    ext = r.mesh.vertices.max(0) - r.mesh.vertices.min(0)
    assert ext[2] > ext[1] > ext[0]  # 1 x 2 x 4 box, normalised
    with pytest.raises(UserError, match="exit code 3"):
        generate("x", backend="command", command=f"{sys.executable} -c 'import sys; sys.exit(3)' {{out}}")
    with pytest.raises(UserError, match="wrote no mesh"):
        generate("x", backend="command", command="true {out}")
    with pytest.raises(UserError, match="needs --mesh"):
        generate("x", backend="file")


def test_character_cli_writes_project(tmp_path):
    from typer.testing import CliRunner

    from t2bs.cli import app
    from t2bs.project import Project

    res = CliRunner().invoke(app, ["character", "a corgi with wings", "-o", str(tmp_path), "--size", "64"])
    assert res.exit_code == 0, res.output
    assert "notice:" in res.output and "wings" in res.output
    project = Project(tmp_path)
    mesh = project.load_character()
    assert "jaw_open" in mesh.morph_names and "eyelid_left" in mesh.part_names
    assert (tmp_path / "renders" / "front.png").is_file()
    stage = project.manifest()["stages"]["character"]
    assert stage["backend"] == "procedural" and stage["archetype"] == "dog"
