"""diffusers backend: a tiny random-weight Shap-E pipeline built from configs, saved, loaded, run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from t2bs.errors import MissingCheckpointError

pytest.importorskip("diffusers")
pytest.importorskip("transformers")


def _byte_vocab() -> dict[str, int]:
    """A CLIP byte-level vocabulary without merges: every byte is a token (no download needed)."""
    printable = list(range(ord("!"), ord("~") + 1)) + list(range(0xA1, 0xAD)) + list(range(0xAE, 0x100))
    codes, extra = printable[:], 0
    for b in range(256):
        if b not in printable:
            codes.append(256 + extra)
            extra += 1
    chars = [chr(c) for c in codes]
    vocab = {c: i for i, c in enumerate(chars)}
    vocab.update({c + "</w>": i + len(chars) for i, c in enumerate(chars)})
    vocab["<|startoftext|>"] = len(vocab)
    vocab["<|endoftext|>"] = len(vocab)
    return vocab


def build_tiny_shap_e(folder: Path, seed: int = 0, grid_size: int = 24) -> Path:
    """Tiny prior / CLIP text encoder / renderer (sizes as in diffusers' own fast tests), saved to ``folder``.

    Random weights give a random SDF; the renderer's SDF output bias is calibrated on the latent
    that ``seed`` produces so that its zero level set (the mesh) is not empty, and the marching
    cubes tables (weights of a real checkpoint) are filled in.
    """
    import torch
    from diffusers import HeunDiscreteScheduler, PriorTransformer, ShapEPipeline
    from diffusers.pipelines.shap_e import ShapERenderer
    from diffusers.pipelines.shap_e.renderer import volume_query_points
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection, CLIPTokenizer

    torch.manual_seed(0)
    vocab = _byte_vocab()
    tokenizer = CLIPTokenizer(vocab=vocab, merges=[], model_max_length=77)
    eos = vocab["<|endoftext|>"]
    text_encoder = CLIPTextModelWithProjection(
        CLIPTextConfig(
            bos_token_id=vocab["<|startoftext|>"],
            eos_token_id=eos,
            pad_token_id=eos,
            hidden_size=32,
            projection_dim=32,
            intermediate_size=37,
            num_attention_heads=4,
            num_hidden_layers=2,
            vocab_size=len(vocab),
        )
    )
    prior = PriorTransformer(
        num_attention_heads=2,
        attention_head_dim=16,
        embedding_dim=32,
        num_embeddings=32,
        embedding_proj_dim=32,
        time_embed_dim=128,
        num_layers=1,
        clip_embed_dim=64,
        additional_embeddings=0,
        time_embed_act_fn="gelu",
        norm_in_type="layer",
        encoder_hid_proj_type=None,
        added_emb_type=None,
    )
    renderer = ShapERenderer(
        param_shapes=((8, 93), (8, 8), (8, 8), (8, 8)), d_latent=32, d_hidden=8, n_output=12, background=(0.1, 0.1, 0.1)
    )
    scheduler = HeunDiscreteScheduler(
        beta_schedule="exp",
        num_train_timesteps=1024,
        prediction_type="sample",
        use_karras_sigmas=True,
        clip_sample=True,
        clip_sample_range=1.0,
    )
    cases, masks = marching_cubes_tables()
    renderer.mesh_decoder.cases.copy_(cases)
    renderer.mesh_decoder.masks.copy_(masks)
    pipe = ShapEPipeline(
        prior=prior, text_encoder=text_encoder, tokenizer=tokenizer, scheduler=scheduler, shap_e_renderer=renderer
    )
    pipe.set_progress_bar_config(disable=True)
    with torch.no_grad():
        latents = pipe(
            "a fox", num_inference_steps=1, generator=torch.Generator().manual_seed(seed), output_type="latent"
        ).images
        projected = renderer.params_proj(latents[0][None])
        for name, param in renderer.mlp.state_dict().items():
            if f"nerstf.{name}" in projected:
                param.copy_(projected[f"nerstf.{name}"].squeeze(0))
        points = volume_query_points(renderer.volume, grid_size)[None].float()
        sdf = renderer.mlp(
            position=points, direction=None, ts=None, nerf_level="fine", rendering_mode="stf"
        ).signed_distance
        logits = torch.atanh(sdf.clamp(-0.999, 0.999))
        renderer.mlp.mlp[-1].bias[0] -= logits.median()
    pipe.save_pretrained(str(folder))
    return folder


def _edge_corners() -> list[tuple[int, int]]:
    """Corner pairs of the 12 cube edges in diffusers' MeshDecoder order (corner = x + 2y + 4z)."""
    edges = []
    for k in range(4):  # x edges at (y, z) = (k & 1, k >> 1)
        edges.append(((k & 1) * 2 + (k >> 1) * 4, 1 + (k & 1) * 2 + (k >> 1) * 4))
    for k in range(4):  # y edges at (x, z)
        edges.append(((k & 1) + (k >> 1) * 4, (k & 1) + 2 + (k >> 1) * 4))
    for k in range(4):  # z edges at (x, y)
        edges.append(((k & 1) + (k >> 1) * 2, (k & 1) + (k >> 1) * 2 + 4))
    return edges


def marching_cubes_tables():
    """(cases [256, 5, 3] long, masks [256, 5] bool) for MeshDecoder, built from first principles.

    Real Shap-E checkpoints ship these tables as buffers; a model built from a config has zeros.
    Per case: the sign-change edges on each cube face are joined into segments (an ambiguous
    face separates its inside corners), the segments into loops, each loop is fanned into
    triangles oriented away from the inside corners.
    """
    import torch

    edges = _edge_corners()
    pos = lambda c: np.array([c & 1, (c >> 1) & 1, (c >> 2) & 1], float)  # noqa: E731
    faces = []  # each cube face: its 4 corners in cyclic order
    for axis in range(3):
        for side in (0, 1):
            corners = [c for c in range(8) if (c >> axis) & 1 == side]
            centre = np.mean([pos(c) for c in corners], 0)
            others = [a for a in range(3) if a != axis]
            corners.sort(key=lambda c: np.arctan2(*(pos(c) - centre)[others]))
            faces.append(corners)
    cases = torch.zeros(256, 5, 3, dtype=torch.long)
    masks = torch.zeros(256, 5, dtype=torch.bool)
    for case in range(256):
        inside = [(case >> c) & 1 for c in range(8)]
        links: dict[int, list[int]] = {}
        for quad in faces:
            cut = [
                edges.index(tuple(sorted((quad[i], quad[(i + 1) % 4]))))
                for i in range(4)
                if inside[quad[i]] != inside[quad[(i + 1) % 4]]
            ]
            if len(cut) == 2:
                pairs = [cut]
            elif len(cut) == 4:  # ambiguous face: cut off each inside corner on its own
                first_in = inside[quad[0]] == 1
                pairs = [[cut[0], cut[3]], [cut[1], cut[2]]] if first_in else [[cut[0], cut[1]], [cut[2], cut[3]]]
            else:
                pairs = []
            for a, b in pairs:
                links.setdefault(a, []).append(b)
                links.setdefault(b, []).append(a)
        tris, seen = [], set()
        for start in links:
            if start in seen:
                continue
            loop, prev, cur = [start], None, start
            seen.add(start)
            while True:
                nxt = [e for e in links[cur] if e != prev and (e not in seen or e == start)]
                if not nxt or nxt[0] == start:
                    break
                prev, cur = cur, nxt[0]
                loop.append(cur)
                seen.add(cur)
            inner = np.mean([pos(c) for c in range(8) if inside[c]] or [np.full(3, 0.5)], 0)
            for i in range(1, len(loop) - 1):
                tri = [loop[0], loop[i], loop[i + 1]]
                mid = [np.mean([pos(c) for c in edges[e]], 0) for e in tri]
                normal = np.cross(mid[1] - mid[0], mid[2] - mid[0])
                if normal @ (np.mean(mid, 0) - inner) < 0:
                    tri = [tri[0], tri[2], tri[1]]
                tris.append(tri)
        for i, tri in enumerate(tris[:5]):
            cases[case, i] = torch.tensor(tri)
            masks[case, i] = True
    return cases, masks


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    return build_tiny_shap_e(tmp_path_factory.mktemp("shap-e") / "ckpt")


def test_tiny_shap_e_pipeline_loads_and_makes_a_canonical_mesh(tiny_checkpoint):
    from t2bs.character.backends import generate
    from t2bs.geometry.mesh import CANONICAL_DIAGONAL

    assert json.loads((tiny_checkpoint / "model_index.json").read_text())["_class_name"] == "ShapEPipeline"
    result = generate(
        "a fox", backend="diffusers", seed=0, checkpoint=tiny_checkpoint, steps=1, grid_size=24, device="cpu"
    )
    mesh = result.mesh
    assert result.info["backend"] == "diffusers" and result.info["model"] == "ShapEPipeline"
    assert mesh.num_vertices > 10 and len(mesh.faces) > 10
    assert mesh.vertex_colors is not None and mesh.vertex_colors.shape == (mesh.num_vertices, 3)
    assert abs(mesh.bbox_diagonal() - CANONICAL_DIAGONAL) < 1e-4
    assert np.allclose((mesh.vertices.min(0) + mesh.vertices.max(0)) / 2, 0, atol=1e-5)
    again = generate(
        "a fox", backend="diffusers", seed=0, checkpoint=tiny_checkpoint, steps=1, grid_size=24, device="cpu"
    )
    assert np.array_equal(again.mesh.vertices, mesh.vertices)  # deterministic for a seed


def test_missing_checkpoint_is_one_line_naming_what_and_where(tmp_path):
    from t2bs.character.backends import generate

    where = tmp_path / "nowhere" / "shap-e"
    with pytest.raises(MissingCheckpointError) as err:
        generate("a fox", backend="diffusers", checkpoint=where)
    msg = str(err.value)
    assert "\n" not in msg and "openai/shap-e" in msg and str(where) in msg
