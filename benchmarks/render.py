"""Mesh renderer speed: ms per 512x512 frame (RGB + depth + normals + mask + face ids).

Usage: python3 benchmarks/render.py [--asset PATH] [--size 512] [--frames 30]
The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

from t2bs.character.render_stage import canonical_character
from t2bs.geometry.camera import orbit_cameras
from t2bs.render.mesh_renderer import MeshRenderer
from t2bs.shared_assets import shared_asset

DEFAULT_ASSET = shared_asset("facecap.glb")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--asset", type=Path, default=DEFAULT_ASSET)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=30)
    args = ap.parse_args()
    mesh, _ = canonical_character(args.asset)
    cams = orbit_cameras(15, args.size)
    with MeshRenderer() as renderer:
        renderer.render(mesh, cams[0])  # warm-up: shader compile, texture upload
        times = []
        for i in range(args.frames):
            t0 = time.perf_counter()
            renderer.render(mesh, cams[i % len(cams)])
            times.append((time.perf_counter() - t0) * 1000)
    print(
        json.dumps(
            {
                "asset": args.asset.name,
                "vertices": mesh.num_vertices,
                "faces": int(mesh.faces.shape[0]),
                "size": args.size,
                "frames": args.frames,
                "ms_per_frame_median": round(statistics.median(times), 2),
                "ms_per_frame_min": round(min(times), 2),
                "load_average_1m": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
