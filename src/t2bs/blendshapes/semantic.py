"""Named shapes on top of the orthogonal basis (beyond the paper: animators work with named shapes).

For each expression prompt, the frame of its captures that moves furthest from the neutral mesh
(the peak of the expression) is projected onto the PCA basis and kept as a shape named after the
prompt: "opening the mouth extremely wide" -> jaw_open, "blinking" -> blink, "tongue sticking out
the mouth" -> tongue_out. Expressed in the basis, a named shape is a fixed weight vector, so it
mixes with the PCA sliders and stays inside what the captures support (no per-video noise
outside the model's span).
"""

from __future__ import annotations

import re

import numpy as np

from t2bs.blendshapes.model import BlendshapeModel
from t2bs.geometry.mesh import bbox_diagonal

# Prompt words -> shape name; first match wins (more specific phrases first). The paper's 20
# prompts (appendix) are all covered; anything else keeps its own slug.
PROMPT_NAMES: list[tuple[str, str]] = [
    (r"tongue", "tongue_out"),
    (r"(blink|clos\w*).*left eye|left eye.*(blink|clos)|wink\w* left", "blink_left"),
    (r"(blink|clos\w*).*right eye|right eye.*(blink|clos)|wink\w* right", "blink_right"),
    (r"blink", "blink"),
    (r"teas\w* the eyes|squint", "eye_squint"),
    (r"mouth extremely wide|open\w* the mouth|jaw", "jaw_open"),
    (r"clos\w* the mouth", "mouth_close"),
    (r"scream", "scream"),
    (r"laugh", "laugh"),
    (r"smirk", "smirk"),
    (r"smil", "smile"),
    (r"talk", "talk"),
    (r"look\w* around|look\w*", "look_around"),
    (r"ear", "ear_wave"),
    (r"shak\w* the head|head", "head_shake"),
    (r"sad", "sad"),
    (r"angry|anger", "angry"),
    (r"chill", "chill"),
    (r"happy", "happy"),
    (r"pensive", "pensive"),
    (r"confus", "confused"),
    (r"disappoint", "disappointed"),
    (r"frown", "frown"),
    (r"brow", "brow_up"),
    (r"cheek", "cheek_puff"),
]

_SAMPLE = re.compile(r"-s\d+$")


def prompt_of(video_id: str) -> str:
    """The expression part of a video id "<expression-slug>-s<sample>" ("blinking-s0" -> "blinking")."""
    return _SAMPLE.sub("", video_id)


def shape_name(expression: str) -> str:
    """A morph target name for an expression prompt or slug."""
    text = expression.replace("-", " ").replace("_", " ").lower()
    for pattern, name in PROMPT_NAMES:
        if re.search(pattern, text):
            return name
    slug = re.sub(r"[^a-z0-9]+", "_", text).strip("_")
    return slug or "expression"


def semantic_shapes(
    model: BlendshapeModel, captures: dict[str, np.ndarray], expressions: dict[str, str] | None = None
) -> tuple[list[str], np.ndarray, list[str]]:
    """Named shapes: (names [S], weights [S, K] in the basis, sources ["video_id:frame"]).

    ``captures``: video_id -> [T, N, 3]; ``expressions``: video_id -> prompt text (default: from the
    id). Captures of the same prompt (samples) share one name; the peak over all of them is kept.
    Two prompts mapping to the same name are numbered (smile, smile_2). A prompt whose peak moves no vertex by
    model.VISIBLE_FRACTION of the diagonal gets no shape (with the head motion taken out of the captures, as the
    blendshapes stage does, "shaking the head" is such a prompt).
    """
    from t2bs.blendshapes.model import VISIBLE_FRACTION

    expressions = expressions or {}
    neutral = model.neutral.astype(np.float64)
    best: dict[str, tuple[float, str, int]] = {}  # prompt -> (peak displacement, video id, frame)
    for vid in sorted(captures):
        prompt = expressions.get(vid) or prompt_of(vid)
        frames = np.asarray(captures[vid], np.float64)
        disp = np.linalg.norm(frames - neutral, axis=-1).mean(-1)  # [T] mean vertex displacement
        t = int(disp.argmax())
        if prompt not in best or disp[t] > best[prompt][0]:
            best[prompt] = (float(disp[t]), vid, t)
    names, weights, sources, used = [], [], [], set(model.names)
    diag = bbox_diagonal(neutral)
    for prompt in sorted(best):
        _, vid, t = best[prompt]
        if np.linalg.norm(np.asarray(captures[vid][t], np.float64) - neutral, axis=-1).max() < VISIBLE_FRACTION * diag:
            continue
        name = base = shape_name(prompt)
        i = 2
        while name in used:
            name, i = f"{base}_{i}", i + 1
        used.add(name)
        names.append(name)
        weights.append(model.project(np.asarray(captures[vid][t])))
        sources.append(f"{vid}:{t}")
    w = np.asarray(weights, np.float32).reshape(len(names), model.num_components)
    return names, w, sources
