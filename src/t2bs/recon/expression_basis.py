"""The expression basis (our addition to VCDGS): a few auto-rig shapes whose per-frame weights the fit learns.

The control points move a blink's lid only through an MLP shared by every point and a skinning that mixes lid and
eyeball, and the photometric gradient of a 1-2 px lid is small next to the head motion's: trained that way, the
lids and lip corners barely move (issue 37; docs/VCDGS_NOTES.md, "The expression basis"). An expression shape of the
character's own auto rig (``t2bs.rig``: built from the static mesh, the face found by part labels or MediaPipe, no
artist shape used) gives the fit a direction for the whole lid at once: its weight per frame is one number that every
lid pixel pulls on, so the images and tracks move it where they cannot move 400 control points. The deformation
networks keep learning on top of it (what the basis gets wrong, and every other motion).

A character whose face is not found gets no basis: one warning line, and the fit runs on its control points alone.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.mesh import Mesh


def expression_basis(
    mesh: Mesh, names: tuple[str, ...] | list[str], landmarks_file: Path | None = None, renderer=None
) -> tuple[np.ndarray | None, dict]:
    """The auto rig's shapes ``names`` (ARKit names) of ``mesh`` (canonical frame; its own morph targets are ignored).

    -> (basis [J, N, 3] float32 offsets from the rest pose, or None; info for metrics.json: the shapes used, those the
    rig could not make and why, where the face came from, or the reason there is no basis). ``landmarks_file``: the
    user's 20 points (``t2bs autorig --landmarks``), else the face is found on a render."""
    names = list(names)
    if not names:
        return None, {"shapes": []}
    from t2bs.rig.stage import rig_canonical

    try:
        rig, seconds = rig_canonical(replace(mesh, morph_targets={}), landmarks_file, renderer=renderer)
    except UserError as exc:
        why = str(exc).split("; give them")[0]  # the landmark hint belongs to `t2bs autorig`, not here
        print(f"warning: no expression basis, VCDGS runs on control points alone: {why}", file=sys.stderr, flush=True)
        return None, {"shapes": [], "error": why}
    have = [n for n in names if n in rig.morph_targets]
    missing = {n: rig.missing.get(n, "not an auto-rig shape") for n in names if n not in rig.morph_targets}
    info = {"shapes": have, "missing": missing, "landmarks": rig.landmarks.source, "seconds": round(seconds, 2)}
    if not have:
        print(
            f"warning: no expression basis, VCDGS runs on control points alone: the auto rig made none of {names}",
            file=sys.stderr,
            flush=True,
        )
        return None, info
    return np.stack([rig.morph_targets[n] for n in have]).astype(np.float32), info


def lid_vertices(basis: np.ndarray, names: list[str], fraction: float) -> np.ndarray:
    """[N] bool: the vertices a blink shape of ``basis`` [J, N, 3] (its shapes ``names``; +y up) moves downwards by
    more than ``fraction`` of that shape's largest vertex motion: the upper lids (none without a blink shape, or with
    ``fraction`` 0). The lower lids, which rise a little, keep their tracks: releasing them too cost the turtle's smile
    (clean, seed 0: 0.504 with the upper lids released, 0.550 with every lid vertex)."""
    out = np.zeros(basis.shape[1], dtype=bool)
    if fraction <= 0:
        return out
    for shape, name in zip(basis, names):
        if name.startswith("eyeBlink"):
            motion = np.linalg.norm(shape, axis=1)
            out |= (motion > fraction * motion.max()) & (shape[:, 1] < 0)
    return out


def release_lid_tracks(tracks, basis: np.ndarray, names: list[str], fraction: float) -> int:
    """Zero the track weights (``recon.tracks.VertexTracks``, in place) of the vertices ``lid_vertices`` picks: the
    optical flow of a closing lid lags it (it carries 0.37 of facecap's blink) and the track term would hold the lid
    back. -> the number of vertices released."""
    import torch

    lids = lid_vertices(basis, names, fraction)
    tracks.weights[:, :, torch.from_numpy(lids)] = 0.0
    return int(lids.sum())


def stretched_faces(vertices: np.ndarray, faces: np.ndarray, basis: np.ndarray, ratio: float) -> np.ndarray:
    """[F] bool: the triangles of ``faces`` [F, 3] whose area some shape of ``basis`` [J, N, 3] (at weight 1) makes
    more than ``ratio`` times their rest area (none with ``ratio`` 0)."""
    from t2bs.geometry.mesh import face_area_normals

    out = np.zeros(len(faces), dtype=bool)
    if ratio <= 0:
        return out
    rest = np.linalg.norm(face_area_normals(vertices, faces), axis=1)
    for shape in basis:
        moved = np.linalg.norm(face_area_normals(vertices + shape, faces), axis=1)
        out |= moved > ratio * np.maximum(rest, 1e-20)
    return out


def shape_support(basis: np.ndarray, fraction: float) -> np.ndarray:
    """[J, N] bool: the vertices each shape of ``basis`` [J, N, 3] moves by more than ``fraction`` of its own largest
    vertex motion (a shape that moves nothing supports no vertex)."""
    size = np.linalg.norm(basis, axis=-1)  # [J, N]
    return size > fraction * size.max(axis=1, keepdims=True)


def face_regions(basis: np.ndarray, names: list[str], support: float = 0.02) -> dict[str, np.ndarray]:
    """Split the vertices by what the basis [J, N, 3] (shapes ``names``) moves -> {"eyes", "mouth", "elsewhere": [N]
    bool}: ``eyes`` those the blinks move, ``mouth`` those the other shapes (jaw, smiles) move; a vertex both move
    counts where it moves more. A shape moves a vertex by more than ``support`` of its largest motion. For the
    diagnostics that say where an expression is lost (benchmarks/expression_regions.py, track_accuracy.py)."""
    size = np.where(shape_support(basis, support), np.linalg.norm(basis, axis=-1), 0.0)  # [J, N]
    blink = np.array([n.startswith("eyeBlink") for n in names])
    zero = np.zeros(basis.shape[1])
    eyes_size = size[blink].max(0) if blink.any() else zero
    mouth_size = size[~blink].max(0) if (~blink).any() else zero
    eyes = (eyes_size > 0) & (eyes_size >= mouth_size)
    mouth = (mouth_size > 0) & (mouth_size > eyes_size)
    return {"eyes": eyes, "mouth": mouth, "elsewhere": ~(eyes | mouth)}
