"""A family of ``lrf`` scenes drawn from a seed (the benchmark judges on the family, not on one scene).

:func:`draw_scenario` draws, per seed: the depth camera (fx 250-1000 px, 640x480 to 1280x720,
sigma_z = k z^2 with k 0.001-0.005 1/m, 16UC1 millimetres or 32FC1 metres), the board (size,
A/B/D placement, fold depth, apex up / down / sideways), the laser (angular step 0.1-0.5 deg,
range sigma 5-25 mm), the mounting, the stop distances within 1-3 m, the number of stops
(6-20), the time offset between the sensors and the stamp jitter.

:func:`simulate_stops` renders every stop as several frames (the AGV stands still: the geometry
is cast once per stop, every frame gets fresh noise), as a user's robot delivers them.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from lidar_cam_calib.sim.lrf_world import LrfWorld, SimObservation, SimTruth, _counts
from lidar_cam_calib.sim.scenario import Scenario, default_scenario

RESOLUTIONS = ((640, 480), (848, 480), (960, 540), (1280, 720))


@dataclasses.dataclass
class FamilyDraw:
    """What was drawn for one seed (besides the scenario): frames per stop and the true noise."""
    seed: int
    frames_per_stop: int
    depth_k_per_m: float
    laser_sigma_m: float
    apex: str
    scans_per_stop: int = 1


def _fold_angles_deg(a, b, d, c) -> tuple:
    a, b, d, c = (np.asarray(v, float) for v in (a, b, d, c))
    nb = np.array([0.0, 0.0, 1.0])
    n1 = np.cross(b - a, c - a)
    n2 = np.cross(c - a, d - a)
    n1, n2 = n1 / np.linalg.norm(n1), n2 / np.linalg.norm(n2)
    ang = lambda u, v: math.degrees(math.acos(min(1.0, abs(float(u @ v)))))
    return ang(nb, n1), ang(nb, n2), ang(n1, n2)


def _draw_board(rng: np.random.Generator, sc: Scenario) -> str:
    """Board size, A/B/D on the back rectangle, apex C (up, down or sideways); fold angles 25-90 deg."""
    for _ in range(200):
        w, h = rng.uniform(0.8, 1.3), rng.uniform(0.8, 1.3)
        apex = str(rng.choice(["up", "down", "sideways"], p=[0.45, 0.35, 0.2]))
        if apex == "down":  # A near the top, B and D near the bottom edge, apex out near the bottom
            a = [rng.uniform(-0.1, 0.1) * w, h * rng.uniform(0.9, 1.0)]
            yb = h * rng.uniform(0.0, 0.15)
            b = [-w / 2 * rng.uniform(0.8, 1.0), yb]
            d = [w / 2 * rng.uniform(0.8, 1.0), min(max(yb + h * rng.uniform(-0.05, 0.05), 0.0), h)]
            cy = h * rng.uniform(0.0, 0.2)
        else:
            a = [rng.uniform(-0.1, 0.1) * w, h * rng.uniform(0.0, 0.1)]
            yb = h * rng.uniform(0.85, 1.0)
            b = [-w / 2 * rng.uniform(0.8, 1.0), yb]
            d = [w / 2 * rng.uniform(0.8, 1.0), yb + h * rng.uniform(-0.05, 0.0)]
            cy = h * rng.uniform(0.8, 1.0)
        cx = rng.uniform(-0.1, 0.1) * w if apex != "sideways" else rng.choice([-1, 1]) * rng.uniform(0.15, 0.3) * w
        cz = rng.uniform(0.25, 0.7)
        c = [cx, cy, cz]
        ang = _fold_angles_deg([*a, 0], [*b, 0], [*d, 0], c)
        if 25.0 <= min(ang) and max(ang) <= 90.0:
            sc.board.width_m, sc.board.height_m = float(w), float(h)
            sc.board.a_xy_m = [float(v) for v in a]
            sc.board.b_xy_m = [float(v) for v in b]
            sc.board.d_xy_m = [float(v) for v in d]
            sc.board.c_xyz_m = [float(v) for v in c]
            return apex
    raise RuntimeError("could not draw a folded board with fold angles 25-90 deg")


def draw_scenario(seed: int, n_stops: int | None = None) -> tuple[Scenario, FamilyDraw]:
    """One scene of the family; ``n_stops`` fixes the number of stops (else 6-20)."""
    rng = np.random.default_rng(np.random.SeedSequence([20261201, int(seed)]))
    sc = default_scenario()
    sc.name = f"lrf_family_{seed}"
    sc.seed = int(seed)
    # depth camera
    W, H = RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
    fx_max = min(1000.0, 0.5 * W / math.tan(math.radians(26.0)))  # >= 52 deg field of view
    sc.camera.width_px, sc.camera.height_px = W, H
    sc.camera.fx_px = float(rng.uniform(250.0, fx_max))
    k = float(rng.uniform(0.001, 0.005))
    sc.camera.depth_sigma_k = k
    sc.camera.depth_encoding = str(rng.choice(["16UC1", "32FC1"]))
    sc.camera.invalid_value = 0 if sc.camera.depth_encoding == "16UC1" else "nan"
    sc.camera.dropout_fraction = float(rng.uniform(0.0, 0.02))
    sc.camera.render_color = False
    sc.camera.right_camera = False
    # laser
    sc.laser.resolution_deg = float(rng.uniform(0.1, 0.5))
    sc.laser.range_sigma_m = float(rng.uniform(0.005, 0.025))
    sc.laser.fov_deg = float(rng.choice([270.0, 360.0]))
    sc.laser.angle_min_deg = -sc.laser.fov_deg / 2
    # board
    apex = _draw_board(rng, sc)
    # mounting: laser height, camera offset and small misalignments
    lh = float(rng.uniform(0.45, 0.9))
    sc.mount.laser_xyz_m = [0.10, 0.0, lh]
    sc.mount.laser_rpy_deg = [float(v) for v in rng.uniform(-1.5, 1.5, 3)]
    off = rng.uniform([0.03, -0.2, -0.15], [0.25, 0.2, 0.15])
    sc.mount.camera_xyz_m = [0.10 + float(off[0]), float(off[1]), lh + float(off[2])]
    sc.mount.camera_rpy_deg = [float(v) for v in rng.uniform([-3, -6, -5], [3, 6, 5])]
    # stops: the scan crosses the board between 30 % and 70 % of its height
    h = sc.board.height_m
    lo, hi = max(0.0, lh - 0.7 * h), max(0.02, lh - 0.3 * h)
    sc.poses.board_base_height_range_m = [float(lo), float(max(hi, lo + 0.02))]
    # nearest stop: the whole board in the image (vertical field of view), at least 1 m
    fy = sc.camera.fx_px
    half_v = math.atan(0.5 * H / fy)
    need = 0.5 * max(sc.board.width_m, sc.board.height_m) / math.tan(half_v) + 0.6
    d0 = max(float(rng.uniform(1.0, 1.6)), need)
    sc.poses.distance_m = [d0, max(d0 + 0.8, float(rng.uniform(2.2, 3.0)))]
    # AGV heading: keep the board inside the horizontal field of view at the nearest stop
    half_h = math.degrees(math.atan(0.5 * W / fy))
    board_half = math.degrees(math.atan(0.6 * sc.board.width_m / d0))
    yaw_max = float(np.clip(half_h - board_half - abs(sc.mount.camera_rpy_deg[2]) - 6.0, 5.0, 25.0))
    sc.poses.lateral_m = [-0.4, 0.4]
    sc.poses.yaw_deg = [-yaw_max, yaw_max]
    sc.poses.n_poses = int(n_stops) if n_stops is not None else int(rng.integers(6, 21))
    sc.poses.min_pixels_per_face = 200
    sc.poses.min_laser_points_per_face = 6
    sc.poses.max_attempts = 300
    # clocks
    sc.timeline.depth_hz = float(rng.choice([5.0, 10.0, 15.0]))
    sc.timeline.static_s = float(rng.uniform(0.8, 1.6))
    sc.timeline.depth_offset_s = float(rng.uniform(0.0, 0.05))
    sc.timeline.stamp_jitter_s = float(rng.uniform(0.0, 0.005))
    sc.timeline.scan_hz = float(rng.choice([10.0, 15.0, 20.0, 25.0]))
    fps = max(1, min(8, int(sc.timeline.static_s * sc.timeline.depth_hz)))
    sps = max(fps, min(40, int(sc.timeline.static_s * sc.timeline.scan_hz)))
    return sc, FamilyDraw(int(seed), fps, k, sc.laser.range_sigma_m, apex, sps)


@dataclasses.dataclass
class SimStop:
    """The frames of one stop (same AGV / board pose, fresh noise per frame)."""
    frames: list
    T_world_agv: np.ndarray
    T_world_board: np.ndarray
    visibility: dict
    scans: list = dataclasses.field(default_factory=list)  # extra scans of the stop (no depth image)


def simulate_stops(scenario: Scenario, frames_per_stop: int = 1, rng: np.random.Generator | None = None,
                   noise: bool = True, scans_per_stop: int = 0) -> tuple[list, SimTruth, LrfWorld]:
    """Every stop of ``scenario`` as ``frames_per_stop`` frames (SimObservation each) and
    ``scans_per_stop - frames_per_stop`` extra scans (range arrays)."""
    world = LrfWorld(scenario)
    sc = world.scenario
    rng = np.random.default_rng(sc.seed) if rng is None else rng
    for attempt in range(4):
        try:
            poses = world.sample_poses(rng)
            break
        except RuntimeError:
            if attempt == 3:
                raise
            # the drawn stops cannot show the whole board: step back 0.4 m and narrow the heading
            sc.poses.distance_m = [sc.poses.distance_m[0] + 0.4, sc.poses.distance_m[1] + 0.4]
            sc.poses.yaw_deg = [0.7 * sc.poses.yaw_deg[0], 0.7 * sc.poses.yaw_deg[1]]
    tl = sc.timeline
    stops = []
    for i, (T_wa, T_wb) in enumerate(poses):
        r, lab_l = world.cast_scan(T_wa, T_wb)
        z, lab_c = world.cast_depth(T_wa, T_wb)
        vis = {"laser": _counts(lab_l), "camera": _counts(lab_c)}
        t0 = tl.start_s + i * (tl.static_s + tl.drive_s) + 0.2
        frames = []
        for j in range(frames_per_stop):
            jit = rng.uniform(-1.0, 1.0, 2) * tl.stamp_jitter_s
            stamp = t0 + j / max(tl.depth_hz, 1e-3) + jit[0]
            frames.append(SimObservation(
                stamp_s=float(stamp), T_world_agv=T_wa.copy(), T_world_board=T_wb.copy(),
                scan_ranges_m=world.laser.apply_noise(r, rng, noise),
                scan_angle_min_rad=world.laser.angle_min_rad,
                scan_angle_increment_rad=world.laser.angle_increment_rad,
                scan_range_min_m=world.laser.range_min_m, scan_range_max_m=world.laser.range_max_m,
                depth_m=world.depth_cam.apply_noise(z, rng, noise), depth_right_m=None, color_bgr=None,
                camera=world.depth_cam.camera, camera_right=None, visibility=vis))
        extra = [world.laser.apply_noise(r, rng, noise) for _ in range(max(0, scans_per_stop - frames_per_stop))]
        stops.append(SimStop(frames, T_wa, T_wb, vis, extra))
    return stops, world.truth(), world
