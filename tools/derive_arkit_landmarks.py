"""Derive the ARKit-52 landmark-motion table from ICT-FaceKit (MIT) -> src/t2bs/retarget/data/arkit_landmarks.json.

ICT-FaceKit (https://github.com/ICT-VGL/ICT-FaceKit, formerly USC-ICT/ICT-FaceKit; MIT License,
Copyright (c) 2020 USC Institute for Creative Technologies) ships a generic neutral head and one
OBJ per ARKit-style expression on the same topology, plus the 0-based vertex ids of the Multi-PIE
68 landmarks (its README, "Facial Landmarks"). For each expression this script keeps only the
displacement of the 20 retargeting landmarks (68-scheme 36-47: eyes, 60-67: inner lips) and the
neutral positions of those 20, in ICT's units (cm, Y up, the face looking along +Z, the subject's
left at +X, the same convention as t2bs's canonical frame). No mesh is copied.

Naming: ICT's files use ``eyeBlink_L``; Apple's ARKit names are ``eyeBlinkLeft``. ICT splits
browInnerUp and cheekPuff into _L/_R halves (ARKit has one shape each: their sum), and has no
tongueOut (absent from the table). Run:

    python3 tools/derive_arkit_landmarks.py /work/.mirror/ICT-VGL+ICT-FaceKit/repo
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

# ICT README "Facial Landmarks": Multi-PIE 68-point landmark vertex ids (0-based).
ICT_68 = [
    1225,
    1888,
    1052,
    367,
    1719,
    1722,
    2199,
    1447,
    966,
    3661,
    4390,
    3927,
    3924,
    2608,
    3272,
    4088,
    3443,
    268,
    493,
    1914,
    2044,
    1401,
    3615,
    4240,
    4114,
    2734,
    2509,
    978,
    4527,
    4942,
    4857,
    1140,
    2075,
    1147,
    4269,
    3360,
    1507,
    1542,
    1537,
    1528,
    1518,
    1511,
    3742,
    3751,
    3756,
    3721,
    3725,
    3732,
    5708,
    5695,
    2081,
    0,
    4275,
    6200,
    6213,
    6346,
    6461,
    5518,
    5957,
    5841,
    5702,
    5711,
    5533,
    6216,
    6207,
    6470,
    5517,
    5966,
]
USED_68 = list(range(36, 48)) + list(range(60, 68))  # the 20 retargeting landmarks, t2bs order


def apple_name(ict: str) -> str:
    return ict.replace("_L", "Left").replace("_R", "Right")


def read_obj_vertices(repo: Path, name: str) -> np.ndarray:
    """[V, 3] vertices of FaceXModel/<name>.obj from a git directory (bare mirror) or a checkout."""
    rel = f"FaceXModel/{name}.obj"
    if (repo / rel).exists():
        text = (repo / rel).read_text()
    else:
        text = subprocess.run(
            ["git", "--git-dir", str(repo), "show", f"HEAD:{rel}"], check=True, capture_output=True, text=True
        ).stdout
    return np.array([line.split()[1:4] for line in text.splitlines() if line.startswith("v ")], float)


def main(repo: str) -> None:
    from t2bs.face.arkit import ARKIT_NAMES

    root = Path(repo)
    git_dir = root / ".git" if (root / ".git").exists() else root
    commit = subprocess.run(
        ["git", "--git-dir", str(git_dir), "rev-parse", "HEAD"], check=True, capture_output=True, text=True
    ).stdout.strip()
    meta = json.loads(
        subprocess.run(
            ["git", "--git-dir", str(git_dir), "show", "HEAD:FaceXModel/vertex_indices.json"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
    )
    ids = [ICT_68[i] for i in USED_68]
    neutral = read_obj_vertices(git_dir, "generic_neutral_mesh")[ids]  # [20, 3]
    shapes: dict[str, np.ndarray] = {}
    for ict in meta["expressions"]:
        disp = read_obj_vertices(git_dir, ict)[ids] - neutral  # [20, 3]
        name = apple_name(ict)
        for whole in ("browInnerUp", "cheekPuff"):  # ARKit: one shape = both ICT halves
            if name.startswith(whole):
                name = whole
        if name in ARKIT_NAMES:
            shapes[name] = shapes.get(name, 0) + disp
        print(f"{ict:>18} -> {name if name in ARKIT_NAMES else '(not ARKit, skipped)'}", file=sys.stderr)
    table = {
        "source": "ICT-FaceKit, https://github.com/ICT-VGL/ICT-FaceKit (formerly USC-ICT/ICT-FaceKit), commit "
        + commit,
        "licence": "MIT License, Copyright (c) 2020 USC Institute for Creative Technologies",
        "derived_by": "tools/derive_arkit_landmarks.py",
        "units": "cm; X = subject's left, Y up, Z towards the viewer",
        "landmarks_68": USED_68,
        "ict_vertex_ids": ids,
        "neutral": np.round(neutral, 4).tolist(),
        "shapes": {n: np.round(shapes[n], 4).tolist() for n in ARKIT_NAMES if n in shapes},
        "absent": {n: "ICT-FaceKit has no such expression" for n in ARKIT_NAMES if n not in shapes},
    }
    out = Path(__file__).resolve().parents[1] / "src" / "t2bs" / "retarget" / "data" / "arkit_landmarks.json"
    out.write_text(json.dumps(table, separators=(",", ":")) + "\n")
    print(f"wrote {out} ({len(table['shapes'])} shapes, {out.stat().st_size} bytes)", file=sys.stderr)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: derive_arkit_landmarks.py ICT_FACEKIT_REPO (a checkout or a bare git directory)")
    main(sys.argv[1])
