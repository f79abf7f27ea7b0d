"""Edge-based translation refinement (lidar_cam_calib.targetless.edges) on a synthetic scene:
boards in front of a wall, seen by a ring LiDAR and rendered by ray casting into a pinhole image."""
import numpy as np

from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.core.geometry import R_BODY_OPTICAL, make_T, pose_errors, so3_exp
from lidar_cam_calib.targetless.edges import (EdgeConfig, EdgeView, edge_kind_inliers, intensity_steps, lidar_edges,
                                             refine_pose, refine_translation, without_paint)

# boards x = const (LiDAR frame: x forward, y left, z up): (x, y0, y1, z0, z1, brightness)
BOARDS = [(6.0, 2.5, 3.0, -1.5, 2.0, 0.9), (9.0, -4.0, -3.4, -1.5, 2.5, 0.8), (12.0, 3.5, 5.0, -1.0, 1.0, 0.95),
          (8.0, -2.5, -2.3, -1.5, 3.0, 0.85), (15.0, -6.0, -5.0, -1.5, 2.0, 0.9), (7.0, 4.0, 4.3, -1.5, 2.5, 0.9)]
WALL_X = 30.0


def _cast(o: np.ndarray, d: np.ndarray, boards=BOARDS) -> tuple[np.ndarray, np.ndarray]:
    """Range along unit rays ``d`` from ``o`` (LiDAR frame) and the brightness hit."""
    t = np.full(d.shape[0], np.inf)
    b = np.full(d.shape[0], 0.3)
    with np.errstate(divide="ignore", invalid="ignore"):
        tw = (WALL_X - o[0]) / d[:, 0]
        hit = tw > 0
        t[hit], b[hit] = tw[hit], 0.3 + 0.1 * (np.floor(((o[1] + tw * d[:, 1]) * 2)[hit]) % 2)
        for x, y0, y1, z0, z1, br in boards:
            tb = (x - o[0]) / d[:, 0]
            p = o + tb[:, None] * d
            m = (tb > 0) & (tb < t) & (p[:, 1] >= y0) & (p[:, 1] <= y1) & (p[:, 2] >= z0) & (p[:, 2] <= z1)
            t[m], b[m] = tb[m], br
    return t, b


def _scene(boards=BOARDS, ahead_m: float = 0.0):
    """Camera, image, LiDAR points (LiDAR frame) and the true extrinsic, with the car ``ahead_m``
    forward of the first position."""
    o = np.array([ahead_m, 0.0, 0.0])
    cam = CameraModel.from_K(480, 320, 300.0, 300.0, 240.0, 160.0)
    R = R_BODY_OPTICAL.T  # camera <- LiDAR
    X = make_T(R, -R @ np.array([0.3, 0.1, -0.2]))  # camera 30 cm ahead, 10 cm left, 20 cm below the LiDAR
    # image: ray cast from the camera centre
    u, v = np.meshgrid(np.arange(cam.width) + 0.0, np.arange(cam.height) + 0.0)
    rays_c = np.stack([(u - 240.0) / 300.0, (v - 160.0) / 300.0, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays_l = rays_c @ R  # R^T applied to each ray
    rays_l /= np.linalg.norm(rays_l, axis=1, keepdims=True)
    _, br = _cast(o + np.array([0.3, 0.1, -0.2]), rays_l, boards)
    img = np.clip(br.reshape(cam.height, cam.width) * 255, 0, 255).astype(np.uint8)
    # LiDAR: 32 rings, 0.2 deg azimuth steps over the front half
    el = np.radians(np.linspace(-15.0, 15.0, 32))
    az = np.radians(np.arange(-80.0, 80.0, 0.2))
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    t, _ = _cast(o, d, boards)
    ok = np.isfinite(t)
    pts = d[ok] * t[ok, None]
    return cam, img, pts, X


def test_lidar_edges_finds_the_board_silhouettes():
    _, _, pts, _ = _scene()
    E, kind = lidar_edges(pts, pts, None, EdgeConfig())
    assert E.shape[0] > 100 and np.all(kind == 0)
    # every silhouette point lies on a board side, on the near surface
    on_side = np.zeros(E.shape[0], bool)
    for x, y0, y1, _z0, _z1, _b in BOARDS:
        on_side |= (np.abs(E[:, 0] - x) < 0.05) & ((np.abs(E[:, 1] - y0) < 0.1) | (np.abs(E[:, 1] - y1) < 0.1))
    assert on_side.mean() > 0.95


def test_refine_translation_recovers_an_offset_along_the_driving_direction():
    cam, img, pts, X = _scene()
    d = X[:3, :3] @ np.array([1.0, 0.0, 0.0])  # driving direction (LiDAR x) in the camera frame
    static = np.ones(pts.shape[0], bool)
    for off in (-0.15, 0.12):
        Xe = X.copy()
        Xe[:3, 3] += off * d
        r = refine_translation([img, img], cam, pts, pts, None, static, Xe, [np.eye(4), np.eye(4)], d,
                               EdgeConfig(min_points=50))
        assert r is not None
        assert abs(r.delta @ d + off) < 0.02, (off, r.delta)
        assert r.cost < r.cost0


def test_refine_translation_full_keeps_the_truth():
    cam, img, pts, X = _scene()
    d = X[:3, :3] @ np.array([1.0, 0.0, 0.0])
    r = refine_translation([img], cam, pts, pts, None, np.ones(pts.shape[0], bool), X, [np.eye(4)], d,
                           EdgeConfig(min_points=50), full=True)
    assert r is not None and np.linalg.norm(r.delta) < 0.02


def test_refine_translation_needs_edges():
    cam, img, pts, X = _scene(boards=[])
    d = X[:3, :3] @ np.array([1.0, 0.0, 0.0])
    assert refine_translation([img], cam, pts, pts, None, np.ones(pts.shape[0], bool), X, [np.eye(4)], d) is None



def _views(offsets=(0.0, 1.0, 2.0)):
    out = []
    for a in offsets:
        cam, img, pts, X = _scene(ahead_m=a)
        out.append(EdgeView(img, pts, pts, None, np.ones(pts.shape[0], bool), np.eye(4)))
    return cam, X, out


def test_refine_pose_recovers_yaw_and_lateral_offset_and_says_what_it_cannot_see():
    """Ring LiDARs see vertical silhouettes: the yaw and the sideways translation are measured, the
    height is not. The result must recover the first and report the second as uncertain."""
    cam, X, views = _views()
    up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    lateral = X[:3, :3] @ np.array([0.0, 1.0, 0.0])
    Xe = X.copy()
    dR = so3_exp(np.radians(0.6) * up)
    Xe[:3, :3] = dR @ X[:3, :3]
    Xe[:3, 3] = dR @ X[:3, 3] + 0.08 * lateral
    r = refine_pose(views, cam, Xe, EdgeConfig(min_points=50), up=up, tilt_prior_deg=0.1)
    assert r is not None and r.n_views == 3
    rot_deg, _ = pose_errors(r.T, X)
    assert rot_deg < 0.1, rot_deg
    assert abs((r.T[:3, 3] - X[:3, 3]) @ lateral) < 0.01
    assert r.inliers > r.inliers0 and r.cost < r.cost0
    sd_lateral = np.sqrt(lateral @ r.cov[3:, 3:] @ lateral)
    sd_up = np.sqrt(up @ r.cov[3:, 3:] @ up)
    assert sd_up > 1.5 * sd_lateral, (sd_up, sd_lateral)


def test_paint_edges_unlike_the_image_meet_it_at_chance_and_can_be_left_out():
    """An intensity pattern the camera does not see (a real LiDAR's reflectance steps) makes paint edges
    that meet the image edges no more often than chance, while the silhouettes meet them; without the
    paint the silhouettes alone recover the extrinsic."""
    cfg = EdgeConfig(min_points=50, max_range_m=40.0)  # the wall is 30 m away
    views = []
    for a in (0.0, 1.0, 2.0):
        cam, img, pts, X = _scene(ahead_m=a)
        az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
        unseen = 0.2 + 0.6 * (np.floor(az / 1.3) % 2)   # 1.3 deg stripes of reflectance, not in the image
        views.append(EdgeView(img, pts, pts, unseen, np.ones(pts.shape[0], bool), np.eye(4)))
    ki = edge_kind_inliers(views, cam, X, cfg)
    assert 0.0 < ki["chance"] < 0.2, ki
    assert ki["n_paint"] > 1000 and ki["n_silhouette"] > 300, ki
    assert ki["silhouette"] > 0.8, ki
    assert abs(ki["paint"] - ki["chance"]) < 0.1, ki
    # a fit from 5 cm sideways: the paint pulls it away; without it, back to the truth
    sil = without_paint(views, cfg)
    assert all(np.all(v.kinds == 0) and v.edges.shape[0] > 0 for v in sil)
    assert sum(v.edges.shape[0] for v in sil) < sum(v.edges.shape[0] for v in views)
    assert all(v.image is w.image for v, w in zip(sil, views))
    assert edge_kind_inliers(sil, cam, X, cfg)["n_paint"] == 0
    up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    lateral = X[:3, :3] @ np.array([0.0, 1.0, 0.0])
    Xe = X.copy()
    Xe[:3, 3] += 0.05 * lateral
    pulled = refine_pose(views, cam, Xe, cfg, up=up, tilt_prior_deg=0.1)
    assert abs((pulled.T[:3, 3] - X[:3, 3]) @ lateral) > 0.1    # the paint drags the fit away
    r = refine_pose(sil, cam, Xe, cfg, up=up, tilt_prior_deg=0.1)
    assert r is not None and abs((r.T[:3, 3] - X[:3, 3]) @ lateral) < 0.015 and r.inliers > 0.85


def _textured_line(rng, texture: float, n: int = 3000, period: int = 150, width: int = 6):
    """A scan line of asphalt (0.1) with paint stripes (0.5, ``width`` returns, every ``period``) and a bright
    sign at the end (the sweep's 95th percentile), each return times exp(N(0, texture^2) - texture^2 / 2);
    the indices of the pairs that are true steps."""
    base = np.full(n, 0.1)
    steps = []
    for st in range(period, n - 200, period):
        base[st:st + width] = 0.5
        steps += [st - 1, st + width - 1]
    base[-150:] = 1.0
    inten = base * np.exp(rng.normal(-0.5 * texture ** 2, texture, n))
    cont = np.ones(n - 1, bool)
    cont[n - 151] = False  # the sign is another surface
    return inten, cont, np.array(steps)


def test_paint_steps_on_a_textured_surface_from_windowed_means():
    """Asphalt with paint stripes under a LiDAR texture of 25 % per return (what a camera pixel averages
    away; KITTI's road shows about 30 %): the neighbour difference alone (window 1) marks a step at more
    than one return in fifty; the windowed test finds nine in ten stripe sides and marks almost nothing
    else, since the texture it is judged against is measured on the line itself. Without texture both find
    every side and nothing else."""
    rng = np.random.default_rng(11)

    def score(inten, cont, steps, cfg):
        det = np.flatnonzero(intensity_steps(inten, cont, cfg))
        near = np.abs(det[:, None] - steps[None, :]).min(axis=1) <= 1
        found = np.abs(steps[:, None] - det[None, :]).min(axis=1) <= 1
        return found.mean(), int((~near).sum())

    plain = EdgeConfig(intensity_window=1, intensity_z=0.0)
    win = EdgeConfig()
    assert win.intensity_window == 5 and win.intensity_z == 3.0
    inten, cont, steps = _textured_line(rng, 0.0)
    assert score(inten, cont, steps, plain) == (1.0, 0)
    assert score(inten, cont, steps, win) == (1.0, 0)
    inten, cont, steps = _textured_line(rng, 0.25)
    found1, false1 = score(inten, cont, steps, plain)
    found5, false5 = score(inten, cont, steps, win)
    assert false1 > 0.02 * inten.size, false1
    assert found5 > 0.9 and false5 <= 5, (found5, false5)
    # no pair on a continuous surface, no step
    assert not intensity_steps(inten, np.zeros(inten.size - 1, bool), win).any()


def test_paint_edges_only_on_the_road_when_the_ground_is_given():
    """A ring LiDAR over a road with paint stripes and a wall with reflectance stripes: with the ground
    points given, the intensity edges are the road's alone; without, the wall's too. The silhouettes do
    not depend on it. ``ground_distance`` finds the road's plane (no plane: every point infinitely far)."""
    from lidar_cam_calib.targetless.calibrator import ground_distance
    el = np.radians(np.linspace(-25.0, 2.0, 24))
    az = np.radians(np.arange(-60.0, 60.0, 0.2))
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    ring = np.repeat(np.arange(el.size), az.size)
    with np.errstate(divide="ignore"):
        t_ground = np.where(d[:, 2] < 0, -1.8 / d[:, 2], np.inf)   # road 1.8 m below the LiDAR
        t_wall = 10.0 / d[:, 0]                                      # wall 10 m ahead
    t = np.minimum(t_ground, t_wall)
    pts = d * t[:, None]
    on_ground = t_ground <= t_wall
    stripes = np.floor(pts[:, 1] / 0.8) % 2 == 0          # 0.8 m stripes across the scan lines
    inten = np.where(on_ground, np.where(stripes, 0.6, 0.1), np.where(stripes, 0.3, 0.7))
    cfg = EdgeConfig(max_range_m=30.0)
    road = ground_distance(pts) <= 0.2
    assert road[on_ground].all() and not road[pts[:, 2] > -1.55].any()
    assert np.all(np.isinf(ground_distance(pts[~on_ground])))     # no ground plane: no road
    e_all, k_all = lidar_edges(pts, pts, inten, cfg, ring=ring)
    e_road, k_road = lidar_edges(pts, pts, inten, cfg, ring=ring, ground=road)
    paint_all, paint_road = e_all[k_all == 1], e_road[k_road == 1]
    assert (paint_all[:, 2] > -1.0).sum() > 100 and (paint_all[:, 2] < -1.7).sum() > 100
    assert paint_road.shape[0] > 100 and np.all(paint_road[:, 2] < -1.55)  # (the wall's foot is within 0.2 m)
    assert np.array_equal(e_all[k_all == 0], e_road[k_road == 0])


def test_refine_pose_stays_at_the_truth_and_needs_edges():
    cam, X, views = _views()
    r = refine_pose(views, cam, X, EdgeConfig(min_points=50), up=X[:3, :3] @ np.array([0.0, 0.0, 1.0]),
                    tilt_prior_deg=0.1)
    rot_deg, t_mm = pose_errors(r.T, X)
    assert rot_deg < 0.05 and abs((r.T[:3, 3] - X[:3, 3]) @ (X[:3, :3] @ np.array([0.0, 1.0, 0.0]))) < 0.005
    cam, img, pts, X = _scene(boards=[])
    empty = [EdgeView(img, pts, pts, None, np.ones(pts.shape[0], bool), np.eye(4))] * 2
    assert refine_pose(empty, cam, X) is None


def test_coarse_candidates_are_ranked_by_their_edges():
    """The bird's-eye correlation of a street with repeating objects has peaks metres apart; the
    candidate whose LiDAR edges meet the image edges after a short yaw-and-translation fit is the true
    one, and the ratio of the inlier fractions says how distinct it is."""
    from lidar_cam_calib.targetless.calibrator import _rank_candidates, _rank_fit
    cam, X, views = _views()
    ahead, lateral = X[:3, :3] @ np.array([1.0, 0.0, 0.0]), X[:3, :3] @ np.array([0.0, 1.0, 0.0])
    cands = []
    for shift in (2.0 * lateral - 1.5 * ahead, 0.15 * ahead + 0.1 * lateral, -2.5 * lateral):
        Xc = X.copy()
        Xc[:3, 3] = X[:3, 3] + shift
        cands.append(Xc)
    link = make_T(np.eye(3), np.array([1.0, 0.0, 0.0]))
    fits = [_rank_fit(views, cam, Xc, np.eye(4), link, EdgeConfig(min_points=50)) for Xc in cands]
    best, ratio = _rank_candidates(fits)
    assert best == 1 and ratio > 1.3, (best, ratio, [f.inliers if f else None for f in fits])
    rot_deg, _ = pose_errors(fits[1].T, X)
    assert rot_deg < 0.1 and np.linalg.norm(fits[1].T[:3, 3] - X[:3, 3]) < 0.05
    # no candidate with edges: no choice, no ratio
    best, ratio = _rank_candidates([None, None])
    assert best is None and np.isnan(ratio)


def test_yaw_about_edges_turns_about_the_edges_median_point():
    """The restart move turns the extrinsic about the up axis through the median LiDAR edge point: that
    point keeps its camera position while the rotation changes by the asked yaw."""
    from lidar_cam_calib.targetless.edges import prepare_view, yaw_about_edges
    from lidar_cam_calib.core.geometry import transform_points
    cam, X, views = _views()
    cfg = EdgeConfig(min_points=50)
    for v in views:
        prepare_view(v, cfg)
    up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    Xr = yaw_about_edges(views, X, up, 0.8)
    rot_deg, _ = pose_errors(Xr, X)
    assert abs(rot_deg - 0.8) < 1e-6
    q = np.median(np.concatenate([transform_points(X, v.edges) for v in views]), axis=0)
    p_lidar = transform_points(np.linalg.inv(X), q[None])[0]
    assert np.linalg.norm(transform_points(Xr, p_lidar[None])[0] - q) < 1e-9
    # the pivot is not the camera centre: the translation changes with the yaw
    assert np.linalg.norm(Xr[:3, 3] - X[:3, 3]) > 0.01


def test_edge_restarts_leave_a_side_minimum_along_the_yaw_valley():
    """A fit left 0.8 deg along the yaw-lateral valley is replaced by the restart that reaches the truth
    (more inliers); a fit at the truth is kept."""
    import dataclasses
    from lidar_cam_calib.targetless.calibrator import TargetlessConfig, _edge_restarts
    from lidar_cam_calib.targetless.edges import prepare_view, yaw_about_edges
    cam, X, views = _views()
    cfg = TargetlessConfig()
    cfg = dataclasses.replace(cfg, edges=dataclasses.replace(cfg.edges, min_points=50))
    for v in views:
        prepare_view(v, cfg.edges)
    up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    link = make_T(np.eye(3), np.array([1.0, 0.0, 0.0]))
    Xbad = yaw_about_edges(views, X, up, 0.8)
    at = refine_pose(views, cam, Xbad, cfg.edges, up=up, tilt_prior_deg=0.3)
    stuck = dataclasses.replace(at, T=Xbad, inliers=at.inliers0)  # as if the fit had stopped there
    best, taken = _edge_restarts(views, cam, stuck, np.eye(4), link, cfg, Xbad)
    assert taken != 0.0 and best.inliers >= stuck.inliers + 0.01
    rot_deg, _ = pose_errors(best.T, X)
    assert rot_deg < 0.1 and np.linalg.norm(best.T[:3, 3] - X[:3, 3]) < 0.02, (rot_deg, best.T[:3, 3] - X[:3, 3])
    good = refine_pose(views, cam, X, cfg.edges, up=up, tilt_prior_deg=0.3)
    kept, taken = _edge_restarts(views, cam, good, np.eye(4), link, cfg, X)
    assert taken == 0.0 and kept is good


def test_tilt_prior_stays_at_its_centre_when_the_start_moves():
    """A start tilted 0.6 deg about a horizontal axis: with the prior about the start (the default) a tight
    tilt prior holds the tilt there; with the prior about the ground planes' estimate (here the truth),
    the fit comes back to it. Restarts from a fit's own result pass the clouds' estimate as the centre,
    so the tilt cannot creep by one prior width per restart."""
    import dataclasses
    from lidar_cam_calib.core.geometry import so3_exp
    from lidar_cam_calib.targetless.edges import EdgeConfig
    cam, X, views = _views()
    ecfg = dataclasses.replace(EdgeConfig(), min_points=50)
    up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    side = np.cross(up, X[:3, :3] @ np.array([1.0, 0.0, 0.0]))
    Xt = X.copy()
    Xt[:3, :3] = so3_exp(np.radians(0.6) * side / np.linalg.norm(side)) @ X[:3, :3]
    held = refine_pose(views, cam, Xt, ecfg, up=up, tilt_prior_deg=0.02)
    back = refine_pose(views, cam, Xt, ecfg, up=up, tilt_prior_deg=0.02, prior_centre=X)
    r_held, _ = pose_errors(held.T, X)
    r_back, _ = pose_errors(back.T, X)
    assert r_held > 0.4 and r_back < 0.1, (r_held, r_back)


def test_cov_upper_is_at_least_both():
    from lidar_cam_calib.targetless.calibrator import cov_upper
    rng = np.random.default_rng(0)
    M = rng.normal(size=(6, 6))
    A = M @ M.T + 0.1 * np.eye(6)
    B = np.diag([10.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    C = cov_upper(A, B)
    assert np.min(np.linalg.eigvalsh(C - A)) > -1e-9 and np.min(np.linalg.eigvalsh(C - B)) > -1e-9
    assert np.allclose(cov_upper(A, 0.5 * A), A)  # a smaller spread leaves it alone


def test_jackknife_sees_images_that_disagree():
    """Five images; two of them with their pose 10 cm off sideways (two basins of the edge objective).
    Refitted without each image in turn, the lateral spread is several times what the linearised
    covariance says, and the covariance taken (cov_upper) is at least that spread. With five consistent
    images the jackknife stays within the linearised covariance and changes nothing."""
    import dataclasses
    from lidar_cam_calib.targetless.calibrator import TargetlessConfig, _jackknife_cov, cov_upper
    cfg = TargetlessConfig()
    cfg = dataclasses.replace(cfg, edges=dataclasses.replace(cfg.edges, min_points=50))
    for bad in (0.0, 0.1):
        cam, X, views = _views((0.0, 0.5, 1.0, 1.5, 2.0))
        lateral = X[:3, :3] @ np.array([0.0, 1.0, 0.0])
        for i in (1, 3):
            views[i].T_sweep_img = make_T(np.eye(3), np.array([0.0, bad, 0.0]))
        up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
        pe = refine_pose(views, cam, X, cfg.edges, up=up, tilt_prior_deg=0.3, prior_centre=X)
        cj, n = _jackknife_cov(views, cam, pe, (None, up), cfg, X)
        assert n == 5
        c = cov_upper(pe.cov, cj)
        sd_lin, sd_jk = (np.sqrt(lateral @ m[3:, 3:] @ lateral) for m in (pe.cov, cj))
        assert lateral @ c[3:, 3:] @ lateral >= sd_jk ** 2 - 1e-12
        if bad == 0.0:
            assert sd_jk < sd_lin, (sd_jk, sd_lin)
        else:
            assert sd_jk > 2 * sd_lin, (sd_jk, sd_lin)


def test_height_prior_at_a_pivot_lets_the_tilt_carry_the_camera_height():
    """The ground planes fix the height where the registered road is, not at the camera: with the height
    prior held at a pivot 10 m ahead, the camera's own height is uncertain by about the prior's 3 cm
    together with the tilt prior's 0.3 deg times 10 m (5 cm), and the height at the pivot by about 3 cm;
    held at the camera (no pivot), the other way round. The vertical silhouettes here see little of
    either."""
    cam, X, views = _views()
    up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    p0 = np.array([0.0, 0.0, 10.0])  # camera frame: 10 m ahead
    a_cam = np.concatenate([np.zeros(3), up])
    a_piv = np.concatenate([np.cross(p0, up), up])  # the pivot's height change per left perturbation
    sd = {}
    for name, piv in (("camera", None), ("pivot", p0)):
        r = refine_pose(views, cam, X, EdgeConfig(min_points=50), up=up, tilt_prior_deg=0.3, height_prior_m=0.03,
                        prior_centre=X, height_pivot=piv)
        sd[name] = (np.sqrt(a_cam @ r.cov @ a_cam), np.sqrt(a_piv @ r.cov @ a_piv))
    assert 0.02 < sd["camera"][0] < 0.032 and sd["camera"][1] > 1.5 * sd["camera"][0], sd
    assert 0.02 < sd["pivot"][1] < 0.032 and sd["pivot"][0] > 1.5 * sd["pivot"][1], sd


def test_edge_basins_tilt_starts_find_a_basin_turned_about_the_pivot():
    """A result turned 0.45 deg about the camera's horizontal axis through a pivot 10 m ahead (its height
    there unchanged, the camera's 8 cm off), meeting the edges as well as the truth: the two tilt starts
    (+-1.5 tilt priors about the pivot) reach the truth's basin, and the covariance spans the turn."""
    import dataclasses
    from lidar_cam_calib.targetless.calibrator import TargetlessConfig, _drive_axes, _edge_basins, _edge_fit
    from lidar_cam_calib.targetless.edges import prepare_view
    cam, X, views = _views()
    cfg = TargetlessConfig()
    cfg = dataclasses.replace(cfg, edges=dataclasses.replace(cfg.edges, min_points=50),
                              ours_edge_basin_along_m=0.0, ours_edge_basin_side_m=0.0)
    for v in views:
        prepare_view(v, cfg.edges)
    link = make_T(np.eye(3), np.array([1.0, 0.0, 0.0]))
    p0 = np.array([0.0, 0.0, 10.0])
    good = _edge_fit(views, cam, X, _drive_axes(X, np.eye(4), link), cfg, X, p0)
    up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    h = np.cross(up, [0.0, 0.0, 1.0])
    h /= np.linalg.norm(h)
    w = np.radians(1.5 * cfg.ours_edge_tilt_prior_deg) * h
    R = so3_exp(w)
    Xt = make_T(R @ X[:3, :3], R @ X[:3, 3] + p0 - R @ p0)
    twin = dataclasses.replace(good, T=Xt)
    best, S, n, starts = _edge_basins(views, cam, twin, np.eye(4), link, cfg, X, p0)
    assert starts == 2 and best is twin and n >= 2
    assert h @ S[:3, :3] @ h > 0.8 * (w @ w) / n, (np.degrees(np.sqrt(h @ S[:3, :3] @ h)), n)


def test_block_jackknife_sees_an_object_every_image_gets_wrong():
    """One board's LiDAR edges 5 cm off sideways in all five images (an object's error, which every image
    repeats): the fit turns towards it, the leave-one-image-out refits all agree with it, and leaving out
    the band of image columns that holds the board moves the fit back: the block jackknife's yaw spread
    is more than twice the image jackknife's and the Mahalanobis^2 of the error falls. With the board in
    place the block spread stays a fraction of the fit's own covariance. Weighed by leverage (the board's
    band carries much of the yaw, so its refit counts for less) the block spread is 0.30 deg where the plain
    one is 0.37: still well beyond the image jackknife's 0.14."""
    import dataclasses
    from lidar_cam_calib.targetless.calibrator import (TargetlessConfig, _block_jackknife_cov, _delta, _edge_fit,
                                                       _jackknife_cov, cov_upper)
    from lidar_cam_calib.targetless.edges import prepare_view
    for lev, shift in ((False, 0.0), (False, 0.05), (True, 0.0), (True, 0.05)):
        cfg = TargetlessConfig(ours_edge_jackknife_leverage=lev)
        cfg = dataclasses.replace(cfg, edges=dataclasses.replace(cfg.edges, min_points=50))
        cam, X, views = _views((0.0, 0.5, 1.0, 1.5, 2.0))
        for v in views:
            prepare_view(v, cfg.edges)
            board = (v.edges[:, 1] > 2.3) & (v.edges[:, 1] < 3.2)  # the board at y 2.5-3.0 m
            v.edges = v.edges.copy()
            v.edges[board, 1] += shift
        up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
        pe = _edge_fit(views, cam, X, (None, up), cfg, X)
        cj, n = _jackknife_cov(views, cam, pe, (None, up), cfg, X)
        cb, nb = _block_jackknife_cov(views, cam, pe, (None, up), cfg, X)
        assert n == 5 and nb == cfg.ours_edge_block_jackknife
        sd = {k: np.degrees(np.sqrt(up @ c[:3, :3] @ up)) for k, c in (("fit", pe.cov), ("image", cj), ("block", cb))}
        if shift == 0.0:
            assert sd["block"] < 0.3 * sd["fit"], sd
        else:
            e = _delta(pe.T, X)
            assert abs(np.degrees(e[:3] @ up)) > 0.3, e  # the board pulled the yaw
            assert sd["block"] > (1.7 if lev else 2) * sd["image"], sd
            if not lev:
                c_img = cov_upper(pe.cov, cj)
                assert e @ np.linalg.solve(cov_upper(c_img, cb), e) < 0.9 * e @ np.linalg.solve(c_img, e)


def test_edge_basins_widen_the_covariance_towards_an_equally_good_basin():
    """The basin starts (clouds' estimate moved along the drive and sideways) come back to within 2 cm
    of the truth on a well-posed scene: the spread they give stays below 2.5 cm. A result 8 cm off
    sideways that meets the edges as well as the truth (a second basin) is kept, but the covariance it
    gets spans the truth; one that meets them clearly worse is replaced by the start's fit at the truth."""
    import dataclasses
    from lidar_cam_calib.targetless.calibrator import TargetlessConfig, _drive_axes, _edge_basins, _edge_fit
    from lidar_cam_calib.targetless.edges import prepare_view
    cam, X, views = _views()
    cfg = TargetlessConfig()
    cfg = dataclasses.replace(cfg, edges=dataclasses.replace(cfg.edges, min_points=50))
    for v in views:
        prepare_view(v, cfg.edges)
    link = make_T(np.eye(3), np.array([1.0, 0.0, 0.0]))
    good = _edge_fit(views, cam, X, _drive_axes(X, np.eye(4), link), cfg, X)
    best, S, n, starts = _edge_basins(views, cam, good, np.eye(4), link, cfg, X)
    assert starts == 8 and n >= 4 and np.linalg.norm(best.T[:3, 3] - X[:3, 3]) < 0.02
    assert np.sqrt(np.linalg.eigvalsh(S[3:, 3:]).max()) < 0.025
    good = best
    lateral = X[:3, :3] @ np.array([0.0, 1.0, 0.0])
    Xoff = X.copy()
    Xoff[:3, 3] += 0.08 * lateral
    twin = dataclasses.replace(good, T=Xoff)  # as good as the truth, 8 cm away
    best, S2, n2, _ = _edge_basins(views, cam, twin, np.eye(4), link, cfg, X)
    assert best is twin and n2 >= 2
    assert lateral @ S2[3:, 3:] @ lateral > max(0.8 * 0.08 ** 2 / n2, 4 * lateral @ S[3:, 3:] @ lateral)
    worse = dataclasses.replace(good, T=Xoff, inliers=good.inliers - 0.05)
    best, _, _, _ = _edge_basins(views, cam, worse, np.eye(4), link, cfg, X)
    assert best is not worse and np.linalg.norm(best.T[:3, 3] - X[:3, 3]) < 0.02


def test_azimuth_step_from_one_sweep_of_each_preset():
    """The LiDAR's column step, which sets the share of edge points the edge gate asks for, from the points
    alone: every preset (Ouster's staggered beams included), with a third of the returns missing, the cloud
    stored column by column or ring by ring (as KITTI's files are); NaN when there is nothing to measure."""
    from lidar_cam_calib.sim.lidar import PRESETS
    from lidar_cam_calib.targetless.edges import azimuth_step_rad
    rng = np.random.default_rng(4)
    for name, pr in PRESETS.items():
        d, ring, _, _ = pr.ray_directions()
        p = d * rng.uniform(2.0, 40.0, d.shape[0])[:, None]
        keep = rng.random(d.shape[0]) > 0.33
        for order in (np.arange(d.shape[0]), np.argsort(ring, kind="stable")):
            q = p[order][keep[order]]
            assert abs(np.degrees(azimuth_step_rad(q)) - pr.azimuth_step_deg) < 0.02 * pr.azimuth_step_deg, name
    assert np.isnan(azimuth_step_rad(np.zeros((50, 3))))
    assert np.isnan(azimuth_step_rad(rng.normal(size=(20, 3))))
    assert np.isnan(azimuth_step_rad(np.full((500, 3), np.nan)))


def _head_scene(offset_m: float = 0.12):
    """The boards seen by a 32-ring LiDAR whose lasers sit alternately ``offset_m`` above and below the
    sensor origin, as in a real HDL-64 head: seen from the origin, one laser's elevation then spreads with
    range (over a degree at 6 m), wider than the ring spacing. Points stored ring by ring, as KITTI's files
    are; returns the points and each point's ring."""
    el = np.radians(np.linspace(-15.0, 15.0, 32))
    az = np.radians(np.arange(-80.0, 80.0, 0.2))
    pts, ring = [], []
    for r, e in enumerate(el):
        o = np.array([0.0, 0.0, offset_m if r % 2 else -offset_m])
        d = np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.full(az.size, np.sin(e))], axis=1)
        t, _ = _cast(o, d)
        ok = np.isfinite(t)
        pts.append(o + d[ok] * t[ok, None])
        ring.append(np.full(int(ok.sum()), r))
    return np.concatenate(pts), np.concatenate(ring)


def _on_board_side(E: np.ndarray) -> np.ndarray:
    on_side = np.zeros(E.shape[0], bool)
    for x, y0, y1, _z0, _z1, _b in BOARDS:
        on_side |= (np.abs(E[:, 0] - x) < 0.05) & ((np.abs(E[:, 1] - y0) < 0.1) | (np.abs(E[:, 1] - y1) < 0.1))
    return on_side


def test_rings_of_a_real_head_from_the_storage_order_or_the_ring_field():
    """A real head's lasers are not at the origin, so the elevation angles do not cluster into rings: the
    rings come from the driver's ring field, else from the storage order (ring by ring). Either way the
    silhouettes lie on the board sides. Clustered elevations alone mix the lasers: here they lose
    silhouettes; on KITTI they paired points of different lasers, and 10-18 % of the silhouettes lay within
    1.5 px of an image edge at the official calibration (chance level), against 32-40 % with the rings
    from the storage order."""
    from lidar_cam_calib.targetless.edges import ring_sequence
    pts, ring = _head_scene()
    order, lab = ring_sequence(pts)
    assert np.array_equal(order, np.arange(pts.shape[0]))        # stored ring by ring: storage neighbours
    assert np.array_equal(lab, ring)
    E, kind = lidar_edges(pts, pts, None, EdgeConfig())
    assert E.shape[0] > 100 and _on_board_side(E).mean() > 0.95
    # the same cloud shuffled, with the driver's ring field
    perm = np.random.default_rng(1).permutation(pts.shape[0])
    E2, _ = lidar_edges(pts[perm], pts[perm], None, EdgeConfig(), ring=ring[perm] + 7)
    assert abs(E2.shape[0] - E.shape[0]) <= 0.02 * E.shape[0] and _on_board_side(E2).mean() > 0.95
    # shuffled with no ring field, the rings come from clustered elevations, which mix lasers near the
    # boards: neighbours of one laser are missed and a third of the silhouettes with them
    E3, _ = lidar_edges(pts[perm], pts[perm], None, EdgeConfig())
    assert E3.shape[0] < 0.8 * E.shape[0]


def test_ring_spacing_of_each_preset_and_of_a_real_head():
    """Rings seen and their median spacing, which the refusal's advice reads (a 16-beam LiDAR's rings are
    2 deg apart): every preset stored column by column (elevations clustered), ring by ring (storage
    order), or shuffled with its ring field; a head with its lasers off the origin; NaN with nothing to
    measure."""
    from lidar_cam_calib.sim.lidar import PRESETS
    from lidar_cam_calib.targetless.edges import ring_spacing_deg
    rng = np.random.default_rng(5)
    for name, pr in PRESETS.items():
        d, ring, _, _ = pr.ray_directions()
        p = d * rng.uniform(2.0, 40.0, d.shape[0])[:, None]
        keep = rng.random(d.shape[0]) > 0.33
        want = float(np.median(np.diff(np.sort(pr.ring_elevations_deg()))))
        perm = rng.permutation(d.shape[0])
        for order, r in ((np.arange(d.shape[0]), None), (np.argsort(ring, kind="stable"), None), (perm, ring)):
            n, s = ring_spacing_deg(p[order][keep[order]], None if r is None else r[order][keep[order]])
            assert abs(n - pr.n_rings) <= 1 and abs(s - want) < 0.02, (name, n, s)
    pts, _ = _head_scene()
    n, s = ring_spacing_deg(pts)
    # 0.97 deg apart; seen from the origin the lasers' parallax moves each ring's median by up to 0.4 deg
    assert n == 32 and 0.5 < s < 1.5
    assert ring_spacing_deg(np.zeros((50, 3)))[0] == 0
    assert np.isnan(ring_spacing_deg(np.full((500, 3), np.nan))[1])


def test_foliage_jumps_are_not_silhouettes_but_a_thin_pole_is():
    """A tree crown lets a third of the rays through to the wall behind and scatters the others half a
    metre deep: its depth jumps come every few points along a ring and meet no edge in the image. The
    clutter count leaves them out and keeps both sides of a 12 cm pole (4-5 returns wide at 8 m)."""
    rng = np.random.default_rng(3)
    pole = (8.0, -1.06, -0.94, -1.5, 3.0, 0.5)
    el = np.radians(np.linspace(-15.0, 15.0, 32))
    az = np.radians(np.arange(-80.0, 80.0, 0.2))
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    t, _ = _cast(np.zeros(3), d, [pole])
    # crown: a sphere of 1.5 m radius 10 m ahead, 3 m to the left
    c, r = np.array([10.0, 3.0, 1.0]), 1.5
    b = d @ c
    disc = b * b - (c @ c - r * r)
    t_in = b - np.sqrt(np.maximum(disc, 0.0))
    crown = (disc > 0) & (t_in < t) & (rng.random(d.shape[0]) > 0.35)
    t[crown] = t_in[crown] + rng.uniform(0.0, 0.5, int(crown.sum()))
    ok = np.isfinite(t)
    pts = d[ok] * t[ok, None]
    ring = np.repeat(np.arange(32), az.size)[ok]

    def split(cfg):
        Ed, kind = lidar_edges(pts, pts, None, cfg, ring=ring)
        Ed = Ed[kind == 0]
        in_crown = np.linalg.norm(Ed - c, axis=1) < r + 0.6
        on_pole = (np.abs(Ed[:, 0] - 8.0) < 0.1) & (np.abs(np.abs(Ed[:, 1] + 1.0) - 0.06) < 0.06)
        return int(in_crown.sum()), int(on_pole.sum())

    crown_off, pole_off = split(EdgeConfig(clutter_window=0))
    crown_on, pole_on = split(EdgeConfig())
    rings_on_pole = int(np.sum((el > np.arctan2(-1.5, 8.0)) & (el < np.arctan2(3.0, 8.0))))  # rings that see it
    assert crown_off > 100, crown_off  # without the count the crown brings more silhouettes than the pole
    assert crown_on < 0.25 * crown_off, (crown_on, crown_off)
    assert pole_on == pole_off and pole_on >= 2 * rings_on_pole - 4, (pole_on, pole_off, rings_on_pole)


def test_dispersion_scale_leaves_out_an_image_that_sees_no_edge():
    """An image whose edge points all lie on the truncated plateau of its distance field brings a zero
    information matrix; the dispersion scale leaves it out instead of failing on a singular solve (slow
    seed 5108 stopped the benchmark that way)."""
    from lidar_cam_calib.targetless.edges import _scale
    rng = np.random.default_rng(0)
    Hs, gs = [], []
    for _ in range(3):
        A = rng.normal(size=(50, 6))
        Hs.append(A.T @ A)
        gs.append(rng.normal(size=6))
    ref = _scale(Hs, gs, 0.0, 6)
    assert np.isfinite(ref) and ref > 0
    assert _scale(Hs + [np.zeros((6, 6))], gs + [np.zeros(6)], 0.0, 6) == ref
    assert _scale([np.zeros((6, 6))], [np.zeros(6)], 0.25, 6) == 0.25  # nothing seen: the naive variance


def test_kind_check_sees_one_kind_of_edge_part_from_the_other():
    """The silhouettes on every other scan line are labelled as the second kind (paint: a kind the scene
    does not have, but the check only needs two independent sets of edges). Where both sets are placed
    right, their separate fits agree within their covariances. With one set moved 10 cm sideways in every
    sweep (a placement bias all images share, which the leave-one-image-out spread cannot see), they part
    beyond them, and the widened covariance spans each set's fit about the result."""
    import dataclasses
    from lidar_cam_calib.targetless.calibrator import TargetlessConfig, _delta, _edge_fit, _kind_fits, kind_widened
    from lidar_cam_calib.targetless.edges import prepare_view
    cfg = TargetlessConfig()
    cfg = dataclasses.replace(cfg, edges=dataclasses.replace(cfg.edges, min_points=50))
    chi2 = {}
    for shift in (0.0, 0.1):
        cam, X, views = _views()
        for v in views:
            prepare_view(v, cfg.edges)
            el = np.degrees(np.arctan2(v.edges[:, 2], np.hypot(v.edges[:, 0], v.edges[:, 1])))
            v.kinds = np.round((el + 15.0) * 31.0 / 30.0).astype(int) % 2   # the scene's 32 rings, -15..15 deg
            v.edges[v.kinds == 0] += np.array([0.0, shift, 0.0])
        assert all((v.kinds == 0).sum() > 100 and (v.kinds == 1).sum() > 100 for v in views)
        up = X[:3, :3] @ np.array([0.0, 0.0, 1.0])
        pe = _edge_fit(views, cam, X, (None, up), cfg, X)
        fits, m = _kind_fits(views, cam, pe, (None, up), cfg, X)
        assert fits is not None
        chi2[shift] = m["edge_kind_chi2"]
        C = kind_widened(pe.cov, pe.T, [f.T for f in fits])
        assert np.min(np.linalg.eigvalsh(C - pe.cov)) > -1e-12
        for f in fits:
            d = _delta(f.T, pe.T)
            assert d @ np.linalg.solve(C, d) <= 1.0 + 1e-6
    assert chi2[0.0] < 3.0 and chi2[0.1] > 3 * 16.8, chi2
    # one kind without edges: no check
    for v in views:
        v.kinds[:] = 0
    assert _kind_fits(views, cam, pe, (None, up), cfg, X) == (None, {})


def test_bilinear_sampling_of_one_and_of_several_images():
    """_sample is exact on a linear field inside the image and clamps outside it; _sample_split samples each
    image at its own run of points (runs may be empty) with the same values as _sample image by image."""
    from lidar_cam_calib.targetless.edges import _sample, _sample_split
    h, w = 40, 60
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    imgs = [np.stack([k + 2 * xx + 3 * yy, k - xx], axis=2).astype(np.float32) for k in range(3)]
    rng = np.random.default_rng(3)
    uv = np.column_stack([rng.uniform(0, w - 1.01, 50), rng.uniform(0, h - 1.01, 50)])
    got = _sample(imgs[1], uv)
    assert got.shape == (50, 2)
    assert np.allclose(got[:, 0], 1 + 2 * uv[:, 0] + 3 * uv[:, 1], atol=1e-4)
    assert np.allclose(got[:, 1], 1 - uv[:, 0], atol=1e-4)
    # outside the image: the border's value
    out = _sample(imgs[0][:, :, 0], np.array([[-5.0, 10.0], [w + 7.0, -3.0]]))
    assert np.allclose(out, [0 + 3 * 10.0, 2 * (w - 1.001)], atol=1e-3)
    cuts = np.array([20, 20])  # the second image gets no point
    split = _sample_split(imgs, uv, cuts)
    per = np.concatenate([_sample(f, p) for f, p in zip(imgs, np.split(uv, cuts))])
    assert np.array_equal(split, per)
    assert np.allclose(split[:20, 0] - 0, 2 * uv[:20, 0] + 3 * uv[:20, 1], atol=1e-4)
    assert np.allclose(split[20:, 0] - 2, 2 * uv[20:, 0] + 3 * uv[20:, 1], atol=1e-4)


def _ls_fits(A: np.ndarray, y: np.ndarray, groups: np.ndarray):
    """A linear least-squares translation problem (rows A, data y) solved on all rows (as an edge-fit
    result: the rotation fixed, identity information) and without each group in turn: (full fit, the
    refits' offsets from it (g, 6), each group's information (g, 6, 6))."""
    from lidar_cam_calib.targetless.edges import PoseEdgeResult

    def solve(rows):
        return np.linalg.solve(A[rows].T @ A[rows], A[rows].T @ y[rows])
    H = np.eye(6)
    H[3:, 3:] = A.T @ A
    t = solve(np.ones(len(y), bool))
    full = PoseEdgeResult(T=make_T(np.eye(3), t), xi=np.zeros(6), cov=np.linalg.inv(H), cost0=0.0, cost=0.0,
                          inliers0=1.0, inliers=1.0, n_points=len(y), n_views=1, dispersion=1.0, info=H)
    xs, Hg = [], []
    for b in np.unique(groups):
        xs.append(np.concatenate([np.zeros(3), solve(groups != b) - t]))
        Hb = np.zeros((6, 6))
        Hb[3:, 3:] = A[groups == b].T @ A[groups == b]
        Hg.append(Hb)
    return full, np.array(xs), np.array(Hg)


def test_leverage_jackknife_matches_the_true_covariance_when_one_group_carries_a_direction():
    """Six groups of equal size; one of them holds nearly all the information along x (the one band of image
    columns whose edges pin the translation along the street). Over many noise draws the plain jackknife's
    x variance comes out many times the true one (without that group the refit is barely posed along x);
    the leverage-weighted one (pure CR2, ours_edge_jackknife_min_rest 0) comes out near the truth, and
    near the plain one's along y and z, which every group measures alike. With the default cutoff the
    x offset of the group that holds x is left out (the jackknife cannot measure x; the fit's own
    covariance does): no blow-up, y and z unchanged. With groups of equal weight all three agree."""
    from lidar_cam_calib.targetless.calibrator import TargetlessConfig, _leave_out_cov
    rng = np.random.default_rng(3)
    g, n = 6, 40
    groups = np.repeat(np.arange(g), n)
    A = np.zeros((g * n, 3))
    A[:, 1:] = rng.normal(size=(g * n, 2))
    A[:, 0] = 0.05 * rng.normal(size=g * n)
    A[:n, 0] = rng.normal(size=n) * 3.0            # group 0 sees x
    true = np.linalg.inv(A.T @ A)                   # unit noise
    cfgs = {"cr2": TargetlessConfig(ours_edge_jackknife_min_rest=0.0), "cut": TargetlessConfig()}
    sums = {k: np.zeros((6, 6)) for k in ("plain", "cr2", "cut")}
    draws = 300
    for _ in range(draws):
        y = A @ np.array([0.1, -0.2, 0.3]) + rng.normal(size=g * n)
        full, xs, Hg = _ls_fits(A, y, groups)
        sums["plain"] += _leave_out_cov(full, xs, None, cfgs["cut"])
        for k in ("cr2", "cut"):
            sums[k] += _leave_out_cov(full, xs, Hg, cfgs[k])
    v = {k: np.diag(c[3:, 3:]) / draws / np.diag(true) for k, c in sums.items()}
    assert v["plain"][0] > 20, v
    assert 0.6 < v["cr2"][0] < 1.6, v
    assert v["cut"][0] < 1.0, v
    for k in ("plain", "cr2", "cut"):
        assert np.all((v[k][1:] > 0.6) & (v[k][1:] < 1.6)), (k, v)
    # equal groups (every group the same rows): the three agree
    A_eq = np.tile(A[:n], (g, 1))
    y = A_eq @ np.array([0.1, -0.2, 0.3]) + rng.normal(size=g * n)
    full, xs, Hg = _ls_fits(A_eq, y, groups)
    ref = _leave_out_cov(full, xs, None, cfgs["cut"])
    for k in ("cr2", "cut"):
        assert np.allclose(_leave_out_cov(full, xs, Hg, cfgs[k]), ref, rtol=1e-6, atol=1e-12)
