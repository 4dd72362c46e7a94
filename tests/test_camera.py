import numpy as np

from t2bs.geometry.camera import Camera, canonical_view_index, frontal_camera, look_at, orbit_azimuths, orbit_cameras


def test_look_at_is_opencv():
    m = look_at(np.array([0.0, 0.0, 3.0]))
    r = m[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r[2], [0, 0, -1], atol=1e-12)  # z forward, towards the origin
    np.testing.assert_allclose(r[1], [0, -1, 0], atol=1e-12)  # y down
    np.testing.assert_allclose(r[0], [1, 0, 0], atol=1e-12)  # x right


def test_projection_conventions():
    cam = frontal_camera(512)
    uv, z = cam.project(np.array([[0.0, 0, 0], [0.2, 0, 0], [0, 0.2, 0]]))
    np.testing.assert_allclose(uv[0], [256, 256], atol=1e-9)
    assert uv[1, 0] > 256  # +X (the character's left) is image right in the front view
    assert uv[2, 1] < 256  # +Y (up) is image up
    assert np.all(z > 2.0)


def test_orbit_rig_matches_the_paper():
    az = orbit_azimuths()
    assert len(az) == 15 and az[0] == -60 and az[-1] == 60
    cams = orbit_cameras()
    assert canonical_view_index() == 7
    np.testing.assert_allclose(cams[7].world_to_camera, frontal_camera().world_to_camera)
    for cam in cams:
        assert abs(np.linalg.norm(cam.position) - 2.25) < 1e-9
        el = np.degrees(np.arcsin(cam.position[1] / 2.25))
        assert abs(el - 10) < 1e-9
        assert cam.width == cam.height == 512


def test_camera_round_trip_and_resize():
    cam = frontal_camera(512)
    again = Camera.from_dict(cam.to_dict())
    np.testing.assert_allclose(again.K, cam.K)
    small = cam.resized(128, 128)
    p = np.array([[0.1, 0.2, 0.05]])
    np.testing.assert_allclose(small.project(p)[0] * 4, cam.project(p)[0], atol=1e-9)
