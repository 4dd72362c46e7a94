"""Expression prompts (paper §3.1.1 and appendix "Expression prompts").

The paper animates every character with 20 predefined expression prompts, 13 physically
specific and 7 emotionally expressive, each concatenated with the character prompt and a
camera description, and generates 3 videos per prompt. ``video_prompt`` builds that text;
``load_prompt_list`` reads a user-edited list (one expression per line, or JSON).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

from t2bs.errors import UserError

# Appendix, "Physically specific expressions": concrete actions of facial features.
PHYSICAL_EXPRESSIONS = (
    "talking",
    "screaming",
    "laughing",
    "smiling",
    "smirking",
    "closing the mouth",
    "opening the mouth extremely wide",
    "blinking",
    "teasing the eyes",
    "looking around",
    "waving the ears",
    "tongue sticking out the mouth",
    "shaking the head",
)
# Appendix, "Emotionally expressive states": the character's inner feelings.
EMOTIONAL_EXPRESSIONS = ("sad", "angry", "chilling", "happy", "pensive", "confused", "disappointed")
EXPRESSIONS = PHYSICAL_EXPRESSIONS + EMOTIONAL_EXPRESSIONS  # the paper's 20

CAMERA_SUFFIX = "static camera, the camera is holding still"  # §3.1.1: keeps the camera fixed
PROMPT_TEMPLATE = "{character}, {expression}, " + CAMERA_SUFFIX
SAMPLES_PER_PROMPT = 3  # §4.1: "we generate three sets of multi-view videos" per prompt


@dataclass(frozen=True)
class VideoJob:
    expression: str  # one of the expression prompts (possibly user-defined)
    sample: int  # 0-based sample index; each sample has its own seed
    prompt: str  # the full text given to a video model

    @property
    def video_id(self) -> str:
        """Folder name under DIR/videos/ (docs/ARCHITECTURE.md): "<expression-slug>-s<sample>"."""
        return f"{slug(self.expression)}-s{self.sample}"


def slug(text: str) -> str:
    """'opening the mouth extremely wide' -> 'opening-the-mouth-extremely-wide'."""
    s = re.sub(r"[^a-z0-9]+", "-", text.strip().lower()).strip("-")
    if not s:
        raise UserError(f"expression {text!r} has no letters or digits to name its folder")
    return s


def video_prompt(character: str, expression: str) -> str:
    """The paper's template: "{character prompt}, {expression}, static camera, the camera is holding still"."""
    character = (character or "a 3D character head").strip().rstrip(",.")
    return PROMPT_TEMPLATE.format(character=character, expression=expression.strip())


MAX_PROMPT_CHARS = 300  # longer than any video model's text window (CogVideoX: 226 tokens)


def resolve_expressions(
    spec: str | list[str] | None, known: tuple[str, ...] | list[str] = EXPRESSIONS, allow_custom: bool = False
) -> list[str]:
    """'all' / None -> every known expression; a comma list or list of names/slugs -> those, in order.

    Names match case-insensitively, by full text or by slug ("opening-the-mouth-extremely-wide").
    Unknown names raise a UserError listing the valid ones, unless ``allow_custom`` (a video
    model can be prompted with anything; the offline animator cannot).
    """
    if spec is None or (isinstance(spec, str) and spec.strip().lower() in ("", "all")):
        return list(known)
    items = [s.strip() for s in spec.split(",")] if isinstance(spec, str) else [str(s).strip() for s in spec]
    items = [s for s in items if s]
    if not items:
        raise UserError("no expression prompts given")
    longest = max(items, key=len)
    if len(longest) > MAX_PROMPT_CHARS:  # it names a folder (video id) and goes into a text encoder
        raise UserError(
            f"an expression prompt has {len(longest)} characters; at most {MAX_PROMPT_CHARS} "
            f"(starts {longest[:40]!r})"
        )
    by_key = {}
    for e in known:
        by_key[e.lower()] = e
        by_key[slug(e)] = e
    out, unknown = [], []
    for s in items:
        hit = by_key.get(s.lower()) or by_key.get(slug(s))
        if hit is None:
            if allow_custom:
                hit = s
            else:
                unknown.append(s)
                continue
        if hit not in out:
            out.append(hit)
    if unknown:
        raise UserError(f"unknown expression {', '.join(repr(u) for u in unknown)}; valid: {', '.join(known)}")
    return out


def load_prompt_list(path: str | os.PathLike) -> list[str]:
    """A user-editable list of expressions: a text file (one per line, '#' comments) or JSON
    (a list of strings, or {"expressions": [...]})."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: prompt list not found")
    text = path.read_text()
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise UserError(f"{path}: not valid JSON ({exc})") from None
        if isinstance(data, dict):
            data = data.get("expressions")
        if not isinstance(data, list) or not all(isinstance(x, str) for x in data):
            raise UserError(f'{path}: expected a JSON list of expression strings (or {{"expressions": [...]}})')
        items = [x.strip() for x in data if x.strip()]
    else:
        items = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
        items = [x for x in items if x]
    if not items:
        raise UserError(f"{path}: the prompt list is empty")
    return items


def write_default_prompt_list(path: str | os.PathLike) -> Path:
    """Write the paper's 20 expressions as an editable text file."""
    path = Path(path)
    lines = (
        [
            "# Expression prompts, one per line (paper appendix). Edit freely; '#' starts a comment.",
            "# Physically specific expressions",
        ]
        + list(PHYSICAL_EXPRESSIONS)
        + ["# Emotionally expressive states"]
        + list(EMOTIONAL_EXPRESSIONS)
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def make_jobs(character: str, expressions: list[str], samples: int = SAMPLES_PER_PROMPT) -> list[VideoJob]:
    """One job per (expression, sample), expression-major, as the paper generates them."""
    if samples < 1:
        raise UserError(f"--samples must be at least 1, got {samples}")
    return [VideoJob(e, s, video_prompt(character, e)) for e in expressions for s in range(samples)]
