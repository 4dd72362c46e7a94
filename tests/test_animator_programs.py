"""The offline animator's expression programs (video/animator.py ``_program``): which control curves each one adds.

A control added twice in one program is the max of two jittered copies (biased up) and spends one more random draw,
shifting every later draw of that program (timings, blinks, head motion). The invariant: a program adds each control
at most once, except repeated events in time: the blinks of ``_Curves.blinks`` (called at most once, and allowed over
an explicit lid level such as sad's half-closed eyes) and the successive glances of "looking around" (the same
direction may come back later).
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from t2bs.geometry.mesh import Mesh
from t2bs.video import animator
from t2bs.video.animator import AnimationConfig, animate, expression_curves, expression_seed, hold, resolve_expression
from t2bs.video.prompts import EXPRESSIONS

REPEATED_EVENTS = {"looking around": {"look_left", "look_right", "look_up", "look_down"}}


@pytest.fixture
def recorded_adds(monkeypatch):
    """[(control, added by blinks())] of every _Curves.add call, and "<blinks>" for each blinks() call."""
    calls: list[tuple[str, bool]] = []
    add, blinks = animator._Curves.add, animator._Curves.blinks
    inside = []

    def rec_add(self, name, curve, amp=1.0):
        calls.append((name, bool(inside)))
        return add(self, name, curve, amp)

    def rec_blinks(self, *args, **kwargs):
        calls.append(("<blinks>", False))
        inside.append(True)
        try:
            return blinks(self, *args, **kwargs)
        finally:
            inside.pop()

    monkeypatch.setattr(animator._Curves, "add", rec_add)
    monkeypatch.setattr(animator._Curves, "blinks", rec_blinks)
    return calls


@pytest.mark.parametrize("expression", EXPRESSIONS)
def test_each_program_adds_each_control_once(expression, recorded_adds):
    assert resolve_expression(expression) == [expression]  # one program, not a mix
    for seed in range(12):
        for frames in (16, 49):
            recorded_adds.clear()
            expression_curves(expression, frames, seed)
            explicit = Counter(name for name, in_blinks in recorded_adds if not in_blinks)
            twice = {n for n, k in explicit.items() if k > 1} - REPEATED_EVENTS.get(expression, set())
            assert not twice, f"{expression} (seed {seed}, {frames} frames) adds {sorted(twice)} more than once"
            assert {n for n, in_blinks in recorded_adds if in_blinks} <= {"blink_left", "blink_right"}


@pytest.mark.parametrize("frames", [16, 49])
def test_laughing_curves_replayed_from_the_seed(frames):
    """laughing's draws, in program order: side, onset, laugh cycles, then one jitter per added control."""
    seed = 1234
    controls, _, parts = expression_curves("laughing", frames, seed)
    assert parts == ["laughing"]
    rng = np.random.default_rng(seed)
    rng.integers(2)  # side (unused by laughing)
    on = rng.uniform(0.1, 0.2)
    cycles = rng.uniform(3.0, 5.0) if frames >= 24 else rng.uniform(2.0, 3.0)
    jaw, smile_l, smile_r, squint, happy = (rng.uniform(0.85, 1.1) for _ in range(5))
    u = np.linspace(0.0, 1.0, frames)
    h = hold(u, on, on + 0.15, 0.9, 1.2)
    ha = 0.5 + 0.5 * np.sin(2 * np.pi * cycles * u)
    want = {
        "jaw_open": jaw * h * (0.3 + 0.5 * ha),
        "smile_left": smile_l * h,
        "smile_right": smile_r * h,
        "squint": 0.6 * squint * h,
        "happy": happy * h,
    }
    for name, curve in want.items():
        np.testing.assert_allclose(controls[name], np.clip(curve, 0, 1), atol=1e-12, err_msg=name)
    assert set(controls) <= set(want) | {"blink_left", "blink_right"}
    assert controls["happy"].max() == pytest.approx(min(happy * h.max(), 1.0))


def test_laughing_weights_on_a_vrm_rig():
    """On a rig with VRM 1.0 presets, the "happy" morph's weight is the happy curve (gain 1), "aa" the jaw's."""
    rng = np.random.default_rng(0)
    v = rng.normal(size=(60, 3)).astype(np.float32)
    f = np.array([[0, 1, 2], [2, 3, 4]], np.int32)
    morphs = {
        name: rng.normal(0, 0.05, v.shape).astype(np.float32) for name in ("happy", "aa", "blinkLeft", "blinkRight")
    }
    cfg = AnimationConfig(frames=16)
    anim = animate(Mesh(v, f, morph_targets=morphs), "laughing", seed=3, config=cfg)
    controls, _, _ = expression_curves("laughing", cfg.frames, expression_seed(3, "laughing", 0))
    weights = dict(zip(anim.names, anim.weights.T))
    np.testing.assert_allclose(weights["happy"], np.clip(controls["happy"], 0, 1), atol=1e-6)
    np.testing.assert_allclose(weights["aa"], np.clip(controls["jaw_open"], 0, 1), atol=1e-6)
    assert weights["happy"][0] == 0.0 and 0.85 <= weights["happy"].max() <= 1.0  # neutral at frame 0, full laugh
