"""ARKit shapes derived through retargeting vs facecap's own 52 ARKit shapes (issue 38, "Must show").

facecap.glb (a human head with the 52 ARKit morph targets) gets a blendshape model from captures of
its own morph targets (``t2bs.eval.bench_retarget.morph_model``: each shape ramped alone + random mixtures,
so the model spans them all), its 20 landmarks from the motion backend, then every ARKit shape is
derived from the ICT-FaceKit landmark table (``t2bs.face.arkit``) without looking at facecap's
own shapes. For each present shape: cosine between the derived displacement [3N] and facecap's true
one, over the head's vertices; median and worst.

python benchmarks/arkit_facecap.py [--json FILE]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
from t2bs.shared_assets import shared_asset  # noqa: E402

ASSET = shared_asset("facecap.glb")


def run(asset: Path = ASSET) -> dict:
    from t2bs.geometry.io import load_mesh
    from t2bs.geometry.mesh import normalize
    from t2bs.face.arkit import arkit_name, derive_arkit_shapes, summary
    from t2bs.face.solve import observed_range
    from t2bs.eval.bench_retarget import morph_model
    from t2bs.face.landmarks import detect_landmarks

    t0 = time.perf_counter()
    mesh, _ = normalize(load_mesh(asset))
    truth = {arkit_name(n): d.astype(np.float64) for n, d in mesh.morph_targets.items() if arkit_name(n)}
    model = morph_model(mesh)
    lm, _ = detect_landmarks(mesh, "motion", model=model)
    shapes = derive_arkit_shapes(
        model.neutral,
        model.basis,
        model.singular_values,
        mesh.faces,
        lm.vertex_ids,
        lm.eyeballs,
        lm.regions.get("mouth", {}).get("width_world"),
        observed=observed_range(model.capture_weights),
    )
    rows = []
    for name, w in zip(shapes.names, shapes.weights):
        derived = model.offsets(w).reshape(-1)
        true = truth[name].reshape(-1)
        cos = float(derived @ true / max(np.linalg.norm(derived) * np.linalg.norm(true), 1e-30))
        scale = float(derived @ true / max(true @ true, 1e-30))  # least-squares strength vs the true shape
        rows.append(
            {
                "shape": name,
                "cosine": round(cos, 4),
                "strength": round(scale, 3),
                "landmark_cosine": shapes.report[name]["cosine"],
            }
        )
    cosines = np.array([r["cosine"] for r in rows])
    worst = rows[int(cosines.argmin())] if rows else None
    return {
        "asset": asset.name,
        "present": len(shapes.names),
        "of": 52,
        "summary": summary(shapes),
        "cosine_median": round(float(np.median(cosines)), 4) if rows else None,
        "cosine_worst": worst,
        "landmarks_backend": lm.backend,
        "rows": rows,
        "absent": {n: r["why"] for n, r in shapes.report.items() if not r["present"]},
        "seconds": round(time.perf_counter() - t0, 2),
    }


if __name__ == "__main__":
    out = run()
    text = json.dumps(out, indent=2)
    if "--json" in sys.argv:
        Path(sys.argv[sys.argv.index("--json") + 1]).write_text(text + "\n")
    print(text)
