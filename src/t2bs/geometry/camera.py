"""Pinhole cameras in one convention (OpenCV: x right, y down, z forward; world->camera 4x4).

World frame of a canonical character: Y up, the character faces +Z (towards a frontal camera),
centred at the origin with bounding-box diagonal CANONICAL_DIAGONAL. The paper's rigs: a
fixed-time orbit of 15 views over azimuth -60..60 deg at 10 deg elevation, distance 2.25, and
the frontal (canonical) view at azimuth 0, which is the orbit's middle view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ORBIT_VIEWS = 15
ORBIT_AZIMUTH_RANGE = (-60.0, 60.0)  # degrees; positive = camera to the character's left (+X)
ORBIT_ELEVATION = 10.0  # degrees above the horizon
ORBIT_DISTANCE = 2.25  # for a bounding-box diagonal of 1.2
ORBIT_FOV_Y = 30.0  # degrees: the head fills most of a square frame at this distance
IMAGE_SIZE = 512

# OpenCV camera axes expressed in OpenGL camera axes (and back): flip y and z.
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    K: np.ndarray  # [3, 3] intrinsics, pixels; principal point at the image centre by default
    world_to_camera: np.ndarray  # [4, 4] OpenCV extrinsics: x_cam = R x_world + t
    width: int  # pixels
    height: int  # pixels
    name: str = ""

    @property
    def position(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        r, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -r.T @ t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> pixel coordinates [N, 2] (x right, y down) and depth [N]."""
        cam = points @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        z = cam[:, 2]
        uv = cam @ self.K.T
        return uv[:, :2] / np.maximum(z[:, None], 1e-9), z

    def resized(self, width: int, height: int) -> "Camera":
        """Same view at another resolution (intrinsics scaled)."""
        s = np.diag([width / self.width, height / self.height, 1.0])
        return Camera(s @ self.K, self.world_to_camera.copy(), width, height, self.name)

    def opengl_view_projection(self, near: float = 0.05, far: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
        """(view [4, 4], projection [4, 4]) for OpenGL clip space, same image (y flipped to GL)."""
        view = CV_TO_GL @ self.world_to_camera
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        w, h = self.width, self.height
        proj = np.array(
            [
                [2 * fx / w, 0.0, 1 - 2 * cx / w, 0.0],
                [0.0, 2 * fy / h, 2 * cy / h - 1, 0.0],
                [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
                [0.0, 0.0, -1.0, 0.0],
            ]
        )
        return view, proj

    def to_dict(self) -> dict:
        return {
            "K": self.K.tolist(),
            "world_to_camera": self.world_to_camera.tolist(),
            "width": self.width,
            "height": self.height,
            "name": self.name,
        }

    @staticmethod
    def from_dict(d: dict) -> "Camera":
        return Camera(
            np.asarray(d["K"], float),
            np.asarray(d["world_to_camera"], float),
            int(d["width"]),
            int(d["height"]),
            d.get("name", ""),
        )


def intrinsics(width: int, height: int, fov_y_deg: float) -> np.ndarray:
    """[3, 3] pinhole intrinsics with square pixels and the principal point at the centre."""
    f = 0.5 * height / np.tan(np.radians(fov_y_deg) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def look_at(
    eye: np.ndarray, target: np.ndarray = np.zeros(3), up: np.ndarray = np.array([0.0, 1.0, 0.0])
) -> np.ndarray:
    """[4, 4] OpenCV world->camera matrix for a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)  # right = (image down = -up) x forward
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: up is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image down
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z])
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def orbit_camera(
    azimuth_deg: float,
    elevation_deg: float = ORBIT_ELEVATION,
    distance: float = ORBIT_DISTANCE,
    size: int = IMAGE_SIZE,
    fov_y_deg: float = ORBIT_FOV_Y,
    name: str = "",
) -> Camera:
    """A camera on a sphere around the origin; azimuth 0 is in front of the character (+Z)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    return Camera(intrinsics(size, size, fov_y_deg), look_at(eye), size, size, name or f"az{azimuth_deg:+.1f}")


def orbit_azimuths(views: int = ORBIT_VIEWS, azimuth_range: tuple[float, float] = ORBIT_AZIMUTH_RANGE) -> np.ndarray:
    """[V] azimuths in degrees, ascending; an odd count puts azimuth 0 in the middle."""
    return np.linspace(azimuth_range[0], azimuth_range[1], views)


def orbit_cameras(
    views: int = ORBIT_VIEWS,
    size: int = IMAGE_SIZE,
    azimuth_range: tuple[float, float] = ORBIT_AZIMUTH_RANGE,
    elevation_deg: float = ORBIT_ELEVATION,
    distance: float = ORBIT_DISTANCE,
    fov_y_deg: float = ORBIT_FOV_Y,
) -> list[Camera]:
    """The paper's fixed-time orbit: ``views`` cameras over ``azimuth_range`` (ascending azimuth)."""
    return [
        orbit_camera(a, elevation_deg, distance, size, fov_y_deg, name=f"view{i:02d}")
        for i, a in enumerate(orbit_azimuths(views, azimuth_range))
    ]


def canonical_view_index(views: int = ORBIT_VIEWS, azimuth_range: tuple[float, float] = ORBIT_AZIMUTH_RANGE) -> int:
    """Index of the orbit view closest to azimuth 0: the paper's canonical view v = 0."""
    return int(np.argmin(np.abs(orbit_azimuths(views, azimuth_range))))


def frontal_camera(
    size: int = IMAGE_SIZE,
    elevation_deg: float = ORBIT_ELEVATION,
    distance: float = ORBIT_DISTANCE,
    fov_y_deg: float = ORBIT_FOV_Y,
) -> Camera:
    """The canonical frontal view (azimuth 0), identical to the orbit's middle view."""
    return orbit_camera(0.0, elevation_deg, distance, size, fov_y_deg, name="front")
