"""targetless: SfM, densification, metric scale on a ray-cast textured corridor (forward driving)."""
import numpy as np
import pytest

from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.core.errors import CalibError
from lidar_cam_calib.core.geometry import R_BODY_OPTICAL, inv_T, make_T, transform_points
from lidar_cam_calib.targetless.dynamic import metric_scale
from lidar_cam_calib.targetless.sfm import SfmConfig, apply_scale, densify, depth_sigma, run_sfm

W, H, F = 320, 240, 260.0
WALL_Y = 5.0


def _texture(seed):
    import cv2
    rng = np.random.default_rng(seed)
    t = np.zeros((512, 512), np.float32)
    for s in (2, 5, 11):
        n = cv2.resize(rng.random((512 // s + 1, 512 // s + 1)).astype(np.float32), (512, 512),
                       interpolation=cv2.INTER_CUBIC)
        t += n / s ** 0.5
    t = (t - t.min()) / (t.max() - t.min())
    return (40 + 180 * t).astype(np.float32)


def render(T_world_cam, tex):
    """Ground z=0 and walls y=+-WALL_Y seen by a pinhole camera (optical frame)."""
    import cv2
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - W / 2) / F, (v - H / 2) / F, np.ones_like(u)], -1) @ T_world_cam[:3, :3].T
    c = T_world_cam[:3, 3]
    t = np.full(u.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(d[..., 2] < -1e-6, -c[2] / d[..., 2], np.inf)
        tl = np.where(d[..., 1] > 1e-6, (WALL_Y - c[1]) / d[..., 1], np.inf)
        tr = np.where(d[..., 1] < -1e-6, (-WALL_Y - c[1]) / d[..., 1], np.inf)
    t = np.minimum(np.minimum(tg, tl), tr)
    p = c + d * np.where(np.isfinite(t), t, 0)[..., None]
    on_ground = tg <= np.minimum(tl, tr)
    su = np.where(on_ground, p[..., 0], p[..., 0])
    sv = np.where(on_ground, p[..., 1], p[..., 2] + 20 * np.sign(p[..., 1]))
    mx = np.mod(su * 20.0, 512).astype(np.float32)
    my = np.mod(sv * 20.0, 512).astype(np.float32)
    img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    img[~np.isfinite(t)] = 200
    return np.clip(img, 0, 255).astype(np.uint8)


def drive(n=8, step=0.6, seed=0):
    tex = _texture(seed)
    poses, ims = [], []
    for k in range(n):
        pos = np.array([k * step, 0.3 * np.sin(0.4 * k), 1.5])
        T = make_T(R_BODY_OPTICAL, pos)  # optical frame looking along +x
        poses.append(T)
        ims.append(render(T, tex))
    return poses, ims


@pytest.fixture(scope="module")
def corridor():
    poses, ims = drive()
    cam = CameraModel.from_K(W, H, F, F, W / 2, H / 2)
    res = run_sfm(ims, cam)
    return poses, ims, cam, res


def test_sfm_poses_and_reprojection(corridor):
    poses, ims, cam, res = corridor
    assert res.reprojection_px < 1.0
    assert res.t1_reprojection_px < 2.0
    # centres in the reference camera frame, up to scale
    true_c = np.array([transform_points(inv_T(poses[0]), T[:3, 3][None])[0] for T in poses])
    s, rel = metric_scale(res.centres(), true_c)
    assert rel < 0.05
    err = np.linalg.norm(res.centres() * s - true_c, axis=1)
    assert err.max() < 0.05


def test_sfm_does_not_depend_on_what_the_process_ran_before(corridor):
    """OpenCV's RANSAC draws from one process-wide generator; the SfM seeds it, so the same window gives
    the same reconstruction after other OpenCV work (in the bench, seed 106 moved from 10 to 32 mm)."""
    import cv2
    poses, ims, cam, res = corridor
    cv2.randu(np.zeros((100, 100), np.float32), 0, 1)  # advance the generator
    again = run_sfm(ims, cam)
    assert np.array_equal(again.centres(), res.centres())
    assert again.reprojection_px == res.reprojection_px


def test_dense_points_lie_on_the_surfaces(corridor):
    poses, ims, cam, res = corridor
    true_c = np.array([transform_points(inv_T(poses[0]), T[:3, 3][None])[0] for T in poses])
    s, _ = metric_scale(res.centres(), true_c)
    m = apply_scale(res, s)
    X, col = densify(ims, cam, m, cfg=SfmConfig(dense_step_px=4), refs=[0, 4])
    assert X.shape[0] > 2000 and col.shape == (X.shape[0], 3)
    sig = depth_sigma(X, m.centres(), F, max(m.reprojection_px, 0.2))
    Xw = transform_points(poses[0], X[sig < 0.1])
    assert Xw.shape[0] > 500
    dist = np.minimum(np.abs(Xw[:, 2]), np.abs(np.abs(Xw[:, 1]) - WALL_Y))
    assert np.median(dist) < 0.05


def test_static_camera_is_refused():
    tex = _texture(1)
    T = make_T(R_BODY_OPTICAL, np.array([0.0, 0.0, 1.5]))
    ims = [render(T, tex)] * 4
    cam = CameraModel.from_K(W, H, F, F, W / 2, H / 2)
    with pytest.raises(CalibError, match="barely moved|no two frames|not overlap|did not move"):
        run_sfm(ims, cam)


def test_triangulate_tracks_recovers_points_from_exact_rays():
    """Multi-view midpoint triangulation: exact observations give the points back (to 1e-6 relative: the
    rays of a forward drive are nearly parallel at 40 m, and the normal equations carry a 1e-12 ridge),
    with ~0 re-projection error and the widest angle between the rays; a track seen by one view only stays
    finite (its normal equations are singular) and is never better than its rays allow."""
    from lidar_cam_calib.core.geometry import make_T, so3_exp
    from lidar_cam_calib.targetless.sfm import _project, triangulate_tracks
    rng = np.random.default_rng(11)
    K = np.array([[900.0, 0, 640], [0, 900.0, 480], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-5, 5, 300), rng.uniform(-2, 2, 300), rng.uniform(8, 40, 300)])
    poses = [make_T(so3_exp(rng.normal(0, 0.02, 3)), np.array([0.1 * k, 0.0, -1.5 * k])) for k in range(6)]
    obs = np.stack([_project(K, T, X)[0] for T in poses], axis=1)
    use = rng.random((300, 6)) < 0.7
    use[:, 0] = True
    use[0] = False
    use[0, 2] = True  # track 0: one view
    Xt, err, ang = triangulate_tracks(K, poses, obs, use)
    multi = use.sum(1) >= 2
    rel = np.linalg.norm(Xt[multi] - X[multi], axis=1) / np.linalg.norm(X[multi], axis=1)
    assert np.max(rel) < 1e-5 and np.median(rel) < 1e-8
    assert np.max(err[multi]) < 1e-3
    assert np.all(np.isfinite(Xt[0]))
    assert ang[0] == 0.0 and np.all(ang[multi] > 0)
    Xn, e2, a2 = triangulate_tracks(K, poses, obs, use, checks=False)
    assert e2 is None and a2 is None and np.array_equal(Xn, Xt)
