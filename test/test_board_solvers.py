"""Solvers of the board method on synthetic placements: symmetry, epnp, kabsch, paper, ours, covariance."""
from __future__ import annotations

import numpy as np
import pytest
from test_board_lidar import BOARD, camera_model, default_T_camera_lidar, lidar_sweep, poses_family

from lidar_cam_calib.board.image_corners import ImageCorners, canonical_order, rotate_180
from lidar_cam_calib.board.lidar_board import detect_board
from lidar_cam_calib.board.solvers import (Observation, missing_placements, observability, placement_coverage,
                                           relative_transform, resolve_symmetry, solve_epnp, solve_kabsch,
                                           solve_ours, solve_paper)
from lidar_cam_calib.core.geometry import inv_T, pose_errors, so3_log

CAMS = {"A": camera_model(1280, 960, 1100.0),
        "B": camera_model(1280, 720, 700.0, D=(-0.05, 0.01, 0.0, 0.0, 0.0))}
TRUTH = {"A": default_T_camera_lidar(),
         "B": default_T_camera_lidar(dx=0.12, dy=-0.3, dz=-0.05, rpy_deg=(0.5, 1.0, -12.0))}


def corners_from_truth(cam, T_cb, rng, sigma_px=0.15, flip=False):
    """Image corners by projection + Gaussian noise, in a random (or flipped) grid order."""
    P = BOARD.inner_corners_board() @ T_cb[:3, :3].T + T_cb[:3, 3]
    uv, ok = cam.project(P)
    if not ok.all():
        return None
    uv = uv + rng.normal(0, sigma_px, uv.shape)
    if flip:
        uv = uv[::-1].copy()
    xn = cam.pixels_to_rays(uv)[:, :2]
    uv, xn, T = canonical_order(uv, xn, BOARD)
    return ImageCorners(uv, xn, T, 0.0)


def make_observations(seed, n, sigma_px=0.15, range_sigma_m=0.01, cams=("A", "B")):
    rng = np.random.default_rng(seed)
    obs = []
    for i, T_lb in enumerate(poses_family(rng, n)):
        cl = lidar_sweep(T_lb, rng, sigma_m=range_sigma_m)
        lb = detect_board(np.column_stack([cl["x"], cl["y"], cl["z"]]), cl["intensity"], cl["ring"], BOARD)
        ims = {}
        for c in cams:
            ic = corners_from_truth(CAMS[c], TRUTH[c] @ T_lb, rng, sigma_px, flip=bool(rng.random() < 0.5))
            if ic is not None:
                ims[c] = ic
        if ims:
            obs.append(Observation(float(i), lb, ims))
    return obs


@pytest.fixture(scope="module")
def obs20():
    return make_observations(11, 20)


def _maha(T, Tt, cov):
    d = np.concatenate([so3_log(T[:3, :3] @ Tt[:3, :3].T), T[:3, 3] - Tt[:3, 3]])
    return float(d @ np.linalg.solve(cov, d))


def test_symmetry_resolved_and_all_solvers_close(obs20):
    obs, init, refused = resolve_symmetry(obs20, BOARD)
    assert not refused
    for c in ("A", "B"):
        rot, tr = pose_errors(init[c], TRUTH[c])
        assert rot < 1.0 and tr < 60  # one placement's PnP: a rough start, on the right branch
    ep = solve_epnp(obs, BOARD)
    ka = solve_kabsch(obs, BOARD)
    pa, pts = solve_paper(obs, BOARD, ep)
    ours = solve_ours(obs, BOARD, CAMS, ep)
    for c in ("A", "B"):
        for Ts, lim_deg, lim_mm in ((ep, 0.3, 15), (ka, 0.3, 15), (pa, 0.5, 20), (ours.T, 0.05, 3.0)):
            rot, tr = pose_errors(Ts[c], TRUTH[c])
            assert rot < lim_deg and tr < lim_mm, (c, rot, tr)
        # ours is better than the virtual-corner baselines
        assert pose_errors(ours.T[c], TRUTH[c])[1] < pose_errors(ep[c], TRUTH[c])[1]
    assert len(pts) == len(obs) and pts[0].shape == (54, 3)


def test_ours_covariance_is_consistent_over_seeds():
    m2, sig = [], []
    for seed in (21, 22, 23, 24):
        obs, _init, _ref = resolve_symmetry(make_observations(seed, 10, cams=("A",)), BOARD)
        sol = solve_ours(obs, BOARD, CAMS, solve_epnp(obs, BOARD))
        m2.append(_maha(sol.T["A"], TRUTH["A"], sol.covariance["A"]))
        sig.append(sol.noise["pixel_sigma_px"]["A"])
    # noise re-estimated from the data (truth 0.15 px per axis)
    assert 0.08 < np.median(sig) < 0.25, sig
    # mean Mahalanobis^2 of 6-dof errors ~ 6; loose bounds for 4 samples
    assert 0.5 < np.mean(m2) < 20, m2


def test_wrong_flip_and_inconsistent_camera_are_handled(obs20):
    # one placement's image turned by 180 deg is put back; a camera that never agrees is refused
    bad = [Observation(o.stamp_s, o.lidar, dict(o.images)) for o in obs20]
    bad[0].images["A"] = rotate_180(bad[0].images["A"], BOARD)
    obs, init, refused = resolve_symmetry(bad, BOARD)
    assert "A" in obs[0].images
    assert np.allclose(obs[0].images["A"].uv, obs20[0].images["A"].uv) or \
        np.allclose(obs[0].images["A"].uv, obs20[0].images["A"].uv[::-1])
    rng = np.random.default_rng(3)
    junk = []
    for o in obs20[:6]:
        ic = o.images["A"]
        T_rand = ic.T_camera_board.copy()
        T_rand[:3, 3] += rng.normal(0, 1.0, 3)
        junk.append(Observation(o.stamp_s, o.lidar, {"A": ImageCorners(ic.uv, ic.xn, T_rand, 0.0)}))
    _obs, _init, refused = resolve_symmetry(junk, BOARD)
    assert "A" in refused and "disagree" in refused["A"]
    _obs, _init, refused = resolve_symmetry(obs20[:1], BOARD)
    assert "symmetry" in refused["A"]


def test_camera_to_camera_and_observability(obs20):
    obs, _init, _ref = resolve_symmetry(obs20, BOARD)
    sol = solve_ours(obs, BOARD, CAMS, solve_epnp(obs, BOARD))
    T_ba, cov = relative_transform(sol.T["A"], sol.T["B"], sol.joint_covariance)
    T_true = TRUTH["B"] @ inv_T(TRUTH["A"])
    rot, tr = pose_errors(T_ba, T_true)
    assert rot < 0.05 and tr < 3.0
    assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > 0)
    v = observability(sol.covariance["A"], 0.3, 10.0)
    assert v["verdict"] == "observable"
    weak = observability(sol.covariance["A"] * 1e6, 0.3, 10.0)
    assert weak["verdict"] == "weak"
    # placements only on one side of the image -> advice names the missing side
    one_side = [o for o in obs if "A" in o.images and o.images["A"].uv[:, 0].mean() > 0.5 * CAMS["A"].width]
    adv = missing_placements(placement_coverage(one_side, "A", CAMS["A"]), "A")
    assert any("left" in a for a in adv)
    assert missing_placements({"frames": 0}, "X")[0].startswith("show the board")
