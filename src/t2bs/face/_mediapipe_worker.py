"""MediaPipe face-mesh worker, run by the *MediaPipe interpreter* (see face_tracking.py), not by t2bs.

Why a separate process: the only MediaPipe wheels that still ship the face-mesh model
(mediapipe 0.10.21, the legacy ``solutions.face_mesh`` graph with face_landmark.tflite inside)
require numpy < 2, while t2bs runs on numpy 2. scripts/setup.sh installs that wheel into its own
virtual environment and t2bs talks to it through files. This file imports only numpy and
mediapipe, so it runs under any interpreter that has both.

Usage: python _mediapipe_worker.py FRAMES.npy OUT.npz [--static]
  FRAMES.npy: [T, H, W, 3] uint8 RGB.
  OUT.npz: landmarks [T, 468, 3] float32 (x, y normalised to the image, z in the x scale), found [T] bool.
"""

import sys

import numpy as np


def main(argv):
    frames_path, out_path = argv[0], argv[1]
    static = "--static" in argv
    from mediapipe.python.solutions import face_mesh

    frames = np.load(frames_path, mmap_mode="r")  # [T, H, W, 3] uint8
    t = frames.shape[0]
    landmarks = np.zeros((t, 468, 3), np.float32)
    found = np.zeros(t, bool)
    # static_image_mode=False tracks the face between frames (a detector run only when the track is
    # lost), which is the intended use for video and is steadier than detecting every frame.
    with face_mesh.FaceMesh(
        static_image_mode=static,
        max_num_faces=1,
        refine_landmarks="--norefine" not in argv,
        min_detection_confidence=0.5,
        min_tracking_confidence=0.5,
    ) as fm:
        for i in range(t):
            res = fm.process(np.ascontiguousarray(frames[i]))
            if res.multi_face_landmarks:
                lm = res.multi_face_landmarks[0].landmark
                landmarks[i] = np.array([[p.x, p.y, p.z] for p in lm[:468]], np.float32)
                found[i] = True
            if (i + 1) % 10 == 0 or i + 1 == t:
                print(f"progress {i + 1} {t}", flush=True)
    np.savez(out_path, landmarks=landmarks, found=found)


if __name__ == "__main__":
    main(sys.argv[1:])
