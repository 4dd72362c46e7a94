"""Prompt -> character parameters: archetype, attributes, colours, and a seeded variation.

Reading is deliberately simple and predictable: words are matched against fixed vocabularies
(archetypes, colours, attribute words, filler words). Words in none of them are ignored and
reported back, so the user sees what the offline generator did not understand.
"""

from __future__ import annotations

import colorsys
import hashlib
import re
from dataclasses import dataclass, field, replace

import numpy as np

from t2bs.character.archetypes import ARCHETYPE_WORDS, CharacterParams, archetype_params

COLORS: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.15, 0.12),
    "orange": (0.93, 0.47, 0.15),
    "yellow": (0.98, 0.85, 0.2),
    "gold": (0.9, 0.72, 0.2),
    "golden": (0.9, 0.72, 0.2),
    "green": (0.3, 0.7, 0.28),
    "lime": (0.6, 0.9, 0.25),
    "teal": (0.15, 0.6, 0.6),
    "cyan": (0.25, 0.8, 0.9),
    "blue": (0.22, 0.42, 0.9),
    "navy": (0.12, 0.18, 0.45),
    "purple": (0.55, 0.3, 0.75),
    "violet": (0.6, 0.35, 0.85),
    "pink": (0.98, 0.6, 0.75),
    "magenta": (0.85, 0.2, 0.65),
    "brown": (0.5, 0.32, 0.18),
    "tan": (0.82, 0.68, 0.5),
    "beige": (0.9, 0.82, 0.68),
    "black": (0.12, 0.12, 0.13),
    "white": (0.96, 0.96, 0.95),
    "grey": (0.55, 0.56, 0.58),
    "gray": (0.55, 0.56, 0.58),
    "silver": (0.75, 0.77, 0.8),
    "metal": (0.68, 0.7, 0.74),
    "metallic": (0.68, 0.7, 0.74),
    "ginger": (0.9, 0.5, 0.2),
    "cream": (0.97, 0.93, 0.8),
}

# Filler words that carry no shape information (never reported as unknown).
STOPWORDS = set(
    """a an the of with and or in on at to for from by is are its it his her their this that very
    cartoon cartoonish character head portrait bust 3d stylized stylised cute adorable lovely
    friendly funny little model render style toon animated chibi creature animal face has having
    looking looks who which wearing pixar disney low poly smooth simple detailed high quality
    one two pair some""".split()
)

SIZE_UP = {"big", "large", "huge", "giant", "enormous", "long", "tall", "wide", "oversized"}
SIZE_DOWN = {"small", "tiny", "little", "short", "mini", "narrow"}
PARTS = {
    "ears": "ear",
    "ear": "ear",
    "eyes": "eye",
    "eye": "eye",
    "snout": "snout",
    "nose": "snout",
    "muzzle": "snout",
    "beak": "snout",
    "mouth": "mouth",
    "jaw": "jaw",
    "teeth": "teeth",
    "horns": "horns",
    "horn": "horns",
    "antlers": "antlers",
    "antler": "antlers",
}
# Attribute words: word -> parameter changes (callables get the current params).
ATTRIBUTES: dict[str, object] = {
    "horned": {"horn": "horns"},
    "antlered": {"horn": "antlers"},
    "spiky": {"horn": "spikes"},
    "spiked": {"horn": "spikes"},
    "spikes": {"horn": "spikes"},
    "round": lambda p: {
        "head_radii": (p.head_radii[0] * 1.12, p.head_radii[1] * 1.05, p.head_radii[2] * 1.05),
        "snout_length": p.snout_length * 0.6,
        "squareness": 2.0,
    },
    "chubby": lambda p: {"head_radii": (p.head_radii[0] * 1.15, p.head_radii[1], p.head_radii[2] * 1.05)},
    "fat": lambda p: {"head_radii": (p.head_radii[0] * 1.15, p.head_radii[1], p.head_radii[2] * 1.05)},
    "thin": lambda p: {"head_radii": (p.head_radii[0] * 0.85, p.head_radii[1] * 1.05, p.head_radii[2])},
    "skinny": lambda p: {"head_radii": (p.head_radii[0] * 0.85, p.head_radii[1] * 1.05, p.head_radii[2])},
    "boxy": {"squareness": 5.0},
    "square": {"squareness": 5.0},
    "striped": {"pattern": "stripes"},
    "stripes": {"pattern": "stripes"},
    "stripy": {"pattern": "stripes"},
    "spotted": {"pattern": "spots"},
    "spots": {"pattern": "spots"},
    "dotted": {"pattern": "spots"},
    "crying": lambda p: {"extras": tuple(dict.fromkeys(p.extras + ("tears",)))},
    "tears": lambda p: {"extras": tuple(dict.fromkeys(p.extras + ("tears",)))},
    "sad": lambda p: {"extras": tuple(dict.fromkeys(p.extras + ("tears",)))},
    "fangs": {"teeth": "fangs"},
    "sharp": {"teeth": "sharp"},
    "toothy": {"teeth": "sharp"},
    "floppy": {"ear": "floppy"},
    "pointy": lambda p: {"ear": "pointy"} if p.ear != "none" else {},
    "hairy": lambda p: {"extras": tuple(dict.fromkeys(p.extras + ("hair",)))},
    "blushing": lambda p: {"extras": tuple(dict.fromkeys(p.extras + ("blush",)))},
    "fluffy": {},
    "furry": {},
    "happy": {},
    "smiling": {},
    "angry": {},
    "grumpy": {},
    "scary": {},
    "baby": lambda p: {"eye_size": p.eye_size * 1.2},
}


@dataclass
class ParsedPrompt:
    params: CharacterParams  # what the generator builds
    archetype: str  # archetype used (the fallback "cartoon" when none matched)
    matched: list[str] = field(default_factory=list)  # words that changed the character
    ignored: list[str] = field(default_factory=list)  # words not understood
    notices: list[str] = field(default_factory=list)  # one line each, shown to the user


def tokenize(prompt: str) -> list[str]:
    return [w for w in re.findall(r"[a-z0-9]+(?:-[a-z0-9]+)?", prompt.lower()) if w]


def prompt_seed(prompt: str, seed: int) -> int:
    """Stable 64-bit seed from (normalised prompt, seed): same pair, same character."""
    key = " ".join(tokenize(prompt)) + f"|{int(seed)}"
    return int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little")


def parse_prompt(prompt: str, seed: int = 0, vary: bool = True) -> ParsedPrompt:
    """Read ``prompt`` into character parameters; ``vary`` applies the seeded variation."""
    words = tokenize(prompt)
    # "crying head" is one of the paper's characters: a human cartoon head with tears.
    joined = " ".join(words)
    if re.search(r"crying\s*head", joined):
        words = [w for w in words if w != "head"]
    archetype, tweaks, matched = None, {}, []
    for w in words:
        key = w if w in ARCHETYPE_WORDS else (w[:-1] if w.endswith("s") and w[:-1] in ARCHETYPE_WORDS else None)
        if key is not None and archetype is None:
            archetype, tweaks = ARCHETYPE_WORDS[key]
            matched.append(w)
    if archetype is None and "crying" in words:
        archetype, tweaks = ARCHETYPE_WORDS["cryinghead"]
    notices = []
    if archetype is None:
        archetype = "cartoon"
        notices.append(
            "no known character type in the prompt: making a generic cartoon head "
            "(known: fox, dog/corgi, cat, deer, bear, rabbit, shark/fish, dinosaur/raptor, "
            "bird/owl, frog, robot, alien, bug, plant/flower, human)"
        )
    params = archetype_params(archetype, **tweaks)

    ignored, colors = [], []
    for i, w in enumerate(words):
        if w in matched or w in ARCHETYPE_WORDS:
            if w not in matched:
                ignored.append(w)  # a second archetype word: the first one wins
            continue
        if w in COLORS:
            colors.append((i, w))
            matched.append(w)
        elif w in ATTRIBUTES:
            change = ATTRIBUTES[w]
            change = change(params) if callable(change) else change
            params = replace(params, **change)
            matched.append(w)
        elif w in PARTS:
            params = _apply_part(params, PARTS[w], words[max(0, i - 3) : i])
            matched.append(w)
        elif w in SIZE_UP or w in SIZE_DOWN:
            if not any(p in PARTS for p in words[i + 1 : i + 4]):
                scale = 1.1 if w in SIZE_UP else 0.9
                params = replace(params, head_radii=tuple(r * scale for r in params.head_radii))
            matched.append(w)
        elif w in STOPWORDS or w.isdigit():
            continue
        else:
            ignored.append(w)
    params = _apply_colors(params, colors, words)
    if ignored:
        notices.append(f"ignored words the procedural generator does not know: {', '.join(dict.fromkeys(ignored))}")
    if vary:
        params = vary_params(params, np.random.default_rng(prompt_seed(prompt, seed)))
    return ParsedPrompt(params, archetype, matched, ignored, notices)


def _apply_part(p: CharacterParams, part: str, before: list[str]) -> CharacterParams:
    up = any(w in SIZE_UP for w in before)
    down = any(w in SIZE_DOWN for w in before)
    s = 1.4 if up else 0.7 if down else 1.0
    if part == "ear":
        if p.ear == "none":
            p = replace(p, ear="pointy", ear_size=0.5, ear_width=0.6, ear_azimuth=40, ear_elevation=48, ear_tilt=20)
        if "long" in before and p.ear in ("pointy", "round"):
            return replace(p, ear_size=p.ear_size * 1.5, ear_width=p.ear_width * 0.75)
        return replace(p, ear_size=p.ear_size * s)
    if part == "eye":
        return replace(p, eye_size=p.eye_size * (1.25 if up else 0.75 if down else 1.0))
    if part == "snout":
        if p.snout_length < 0.1 and up:
            return replace(p, snout_length=0.5)
        return replace(p, snout_length=p.snout_length * s, nose_size=p.nose_size * (1.2 if up else 1.0))
    if part == "mouth":
        return replace(p, mouth_width=p.mouth_width * (1.3 if up else 0.75 if down else 1.0))
    if part == "jaw":
        return replace(p, jaw_size=p.jaw_size * s)
    if part == "teeth":
        return replace(p, teeth="sharp" if "sharp" in before or up else p.teeth)
    if part == "horns":
        return replace(p, horn="horns", horn_size=p.horn_size * s)
    if part == "antlers":
        return replace(p, horn="antlers", horn_size=p.horn_size * s)
    return p


def _apply_colors(p: CharacterParams, colors: list[tuple[int, str]], words: list[str]) -> CharacterParams:
    """First colour -> skin; a colour right before a part noun colours that part; then secondary."""
    rest = []
    for i, name in colors:
        rgb = COLORS[name]
        nxt = next(
            (
                words[j]
                for j in range(i + 1, min(i + 3, len(words)))
                if words[j] in PARTS or words[j] in ("petals", "petal", "hair", "stripes", "spots")
            ),
            None,
        )
        if nxt in ("eyes", "eye"):
            p = replace(p, iris_color=rgb)
        elif nxt in ("petals", "petal"):
            p = replace(p, extra_color=rgb)
        elif nxt == "hair":
            p = replace(p, hair_color=rgb)
        elif nxt in ("stripes", "spots"):
            p = replace(p, pattern_color=rgb)
        elif nxt in ("horns", "horn", "antlers", "antler"):
            p = replace(p, horn_color=rgb)
        elif nxt in ("nose",):
            p = replace(p, nose_color=rgb)
        else:
            rest.append(rgb)
    if rest:
        p = replace(p, base_color=rest[0])
        if p.archetype == "plant":  # a "pink flower" means pink petals
            p = replace(p, extra_color=rest[0], base_color=(0.98, 0.82, 0.25))
    if len(rest) > 1:
        p = replace(p, secondary_color=rest[1], secondary=p.secondary if p.secondary != "none" else "muzzle")
    return p


def _jitter_color(rgb, rng, hue=0.025, val=0.12):
    h, s, v = colorsys.rgb_to_hsv(*rgb)
    h = (h + rng.uniform(-hue, hue)) % 1.0
    s = float(np.clip(s * rng.uniform(0.85, 1.15), 0, 1))
    v = float(np.clip(v * rng.uniform(1 - val, 1 + val * 0.5), 0, 1))
    return tuple(float(c) for c in colorsys.hsv_to_rgb(h, s, v))


def vary_params(p: CharacterParams, rng: np.random.Generator) -> CharacterParams:
    """Seeded variation: proportions and colour shades change visibly, the archetype stays."""
    u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
    return replace(
        p,
        head_radii=(p.head_radii[0] * u(0.88, 1.12), p.head_radii[1] * u(0.9, 1.1), p.head_radii[2] * u(0.92, 1.08)),
        snout_length=p.snout_length * u(0.8, 1.2),
        snout_taper=float(np.clip(p.snout_taper * u(0.8, 1.2), 0, 0.8)),
        mouth_width=p.mouth_width * u(0.88, 1.12),
        eye_size=p.eye_size * u(0.85, 1.15),
        eye_azimuth=p.eye_azimuth + u(-3, 3),
        eye_elevation=p.eye_elevation + u(-3, 3),
        ear_size=p.ear_size * u(0.85, 1.2),
        ear_width=p.ear_width * u(0.88, 1.12),
        ear_tilt=p.ear_tilt + u(-6, 6),
        horn_size=p.horn_size * u(0.85, 1.15),
        base_color=_jitter_color(p.base_color, rng),
        secondary_color=_jitter_color(p.secondary_color, rng, hue=0.01, val=0.05),
        iris_color=_jitter_color(p.iris_color, rng),
        extra_color=_jitter_color(p.extra_color, rng),
        hair_color=_jitter_color(p.hair_color, rng),
        pattern_color=_jitter_color(p.pattern_color, rng),
    )
