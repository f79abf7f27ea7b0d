import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from lidar_cam_calib.core.camera import CameraModel  # noqa: E402 - after the cv2 skip

MODELS = [
    ("plumb_bob", [-0.2, 0.05, 0.001, -0.002, 0.01]),
    ("rational_polynomial", [-0.2, 0.05, 0.001, -0.002, 0.01, 0.1, 0.02, 0.003]),
    ("equidistant", [0.1, -0.02, 0.003, -0.001]),
    ("none", []),
]


@pytest.mark.parametrize("model,D", MODELS)
def test_projection_matches_opencv_and_inverts(model, D):
    cam = CameraModel.from_K(640, 480, 500, 505, 320, 240, D=D, distortion_model=model)
    p = np.random.default_rng(0).uniform([-1, -0.7, 2], [1, 0.7, 4], (200, 3))
    uv, ok = cam.project(p)
    if model == "equidistant":
        ref, _ = cv2.fisheye.projectPoints(p[None], np.zeros(3), np.zeros(3), cam.K, np.array(D, float))
    elif model == "none":
        ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, np.zeros(5))
    else:
        ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, np.array(D, float))
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    rays = cam.pixels_to_rays(uv)
    np.testing.assert_allclose(rays[:, :2], p[:, :2] / p[:, 2:], atol=1e-9)


def test_depth_to_points_drops_invalid_and_checks_size():
    cam = CameraModel.from_K(8, 6, 10, 10, 3.5, 2.5)
    depth = np.full((6, 8), 2.0, np.float32)
    depth[0, 0] = 0
    depth[1, 1] = np.nan
    depth[2, 2] = np.inf
    pts, idx = cam.depth_to_points(depth)
    assert pts.shape == (45, 3)
    assert 0 not in idx and 9 not in idx and 18 not in idx
    np.testing.assert_allclose(pts[:, 2], 2.0)
    with pytest.raises(ValueError, match="CameraInfo says 8x6"):
        cam.depth_to_points(np.ones((5, 8), np.float32))


def test_uncalibrated_camera_rejected():
    with pytest.raises(ValueError, match="calibrated"):
        CameraModel(640, 480, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="distortion_model"):
        CameraModel.from_K(640, 480, 500, 500, 320, 240, distortion_model="fisheye62")


def test_behind_camera_is_invalid():
    cam = CameraModel.from_K(640, 480, 500, 500, 320, 240)
    _, ok = cam.project(np.array([[0, 0, -1.0], [0, 0, 1.0], [10, 0, 1.0]]))
    assert ok.tolist() == [False, True, False]


@pytest.mark.parametrize("model,D", MODELS[:3])
def test_wide_angle_pixels_invert_exactly(model, D):
    """A wide lens (f = 250 px on 640x480: up to ~58 deg off axis at the corners) inverts to
    1e-6 px everywhere: a fixed-point undistortion was left pixels off there on a fisheye, which
    biased every corner far from the centre."""
    cam = CameraModel.from_K(640, 480, 250, 250, 320, 240, D=D, distortion_model=model)
    u, v = np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25))
    uv = np.column_stack([u.ravel(), v.ravel()])
    rays = cam.pixels_to_rays(uv)
    uv2, _ = cam.project(rays)
    assert np.abs(uv2 - uv).max() < 1e-6
    # and the rays are those of points projected there (the projection matches OpenCV's above)
    p = np.random.default_rng(1).uniform([-1.6, -1.2, 1.0], [1.6, 1.2, 1.0], (300, 3))
    uvp, ok = cam.project(p)
    np.testing.assert_allclose(cam.pixels_to_rays(uvp[ok])[:, :2], p[ok, :2], atol=1e-9)
