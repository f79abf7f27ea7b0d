"""TargetlessCalibrator: LiDAR + camera extrinsic from a drive, no target, no initial guess (ROS-free).

Paper 001 (Nagy & Benedek 2020) as implemented here, per calibration window:

1. Frame selection: an image is kept when the median sparse optical flow to
   the last kept image is at least ``min_motion_px`` (paper: 10 px), until
   ``n_frames`` (paper: 8) are kept. Sweeps are buffered for the same span.
2. SfM (:mod:`.sfm`): SIFT, matching, incremental reconstruction with bundle
   adjustment, tracks, ``T1`` by EPnP on 45 points, the re-projection gate,
   densification by multi-view flow-track triangulation.
3. Metric scale and ego-motion (:mod:`.dynamic`): scan-to-scan ICP odometry;
   the SfM scale is the ratio of travelled distances; the reference sweep is
   de-skewed with the odometry velocity (per-point time, or the azimuth when
   the driver publishes no time); moving objects are removed by motion
   consistency between sweeps; an optional image mask removes them in the SfM.
4. Both clouds levelled on their ground planes (LiDAR: +z up; camera: -y up),
   objects (:mod:`.objects`), 4D Hough vote over yaw and translation, ICP
   (:mod:`.align`), final ``solvePnP`` (LM) from LiDAR points pushed through
   the chain (:mod:`.pnp`).
5. Gates: SfM re-projection below ``max_sfm_reprojection_px`` (paper 2 px) and
   the registered clouds' (partial) Hausdorff distance below ``max_hausdorff_m``
   (paper 5 cm); a failed gate raises :class:`CalibError` naming it.

Solvers (``solver``): ``oba`` (object alignment only), ``oba_icp``, ``paper``
(+ PnP from object centroids, voxel-majority shapes, z extent in the
compatibility test), ``ours``:

* its own SfM (``ours_sfm``): SIFT over all frame pairs, the widest initial
  pair, ratio 0.7, sub-pixel KLT corner tracks added, and a Schur-complement
  Levenberg-Marquardt bundle adjustment (scipy's LSMR trust region stalls in
  the bas-relief valley of forward motion: 0.2-0.4 deg pose errors, hence
  metre-level depth errors at 15 m; the exact step reaches 0.03-0.1 deg);
* rotation without a guess from Wahba's problem on the two ground normals and
  the camera trajectory against the LiDAR odometry (lever arm iterated);
* translation by a layered bird's-eye cross-correlation (then a
  translation-only point-to-plane ICP with the precise near camera points as
  the source, moving LiDAR points left out);
* the extrinsic refined on the images (:mod:`.edges` ``refine_pose``, default): every image against
  the LiDAR edges of its own nearest sweep, six degrees of freedom with ground-plane priors on the
  tilt and the height, a dispersion-scaled covariance, and gates on the edge fit; restarted along
  the valley where a yaw and a lateral shift trade off (``_edge_restarts``);
* (``ours_edge_mode='translation'``, the earlier step) the translation refined on the images: the LiDAR silhouettes
  and intensity steps of the reference sweep, projected into the first images
  of the window (each with its odometry pose), put on the Canny edges (1-D
  search along the driving direction, then a small 3-D step); kept when the
  improvement is significant and the images agree, its spread then replaces
  the along-the-street prior in the covariance;
* a second gate on the above-ground partial Hausdorff distance, the
  covariance from the Wahba weights and the ICP information plus an
  along-the-street and an isotropic term; PnP on every registered point.
The curve-based non-rigid refinement (:mod:`.curve`) is not wired in here.

Clock: the camera stamp minus ``time_offset_s`` is the exposure on the LiDAR
clock. Under constant velocity an unknown offset is indistinguishable from a
translation along the driving direction, so it cannot be estimated from one
window; its prior ``time_offset_sigma_s`` times the speed enters the
covariance along the motion direction.
"""
from __future__ import annotations

import dataclasses
import math
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial import cKDTree

from ..core.calibrator import Verdict, cfg_field
from ..core.errors import CalibError, NotReadyError
from ..core.fusion import fuse_estimates
from ..core.geometry import inv_T, make_T, skew, so3_exp, so3_log, spin_time_s, transform_points
from ..core.result import CalibrationResult
from ..core.threads import one_blas_thread
from .align import (AlignConfig, HoughResult, estimate_normals, hough_align, icp_translation,
                    layered_bev_translation, wahba,
                    icp_point_to_plane)
from .edges import (EdgeConfig, EdgeView, azimuth_step_rad, edge_group_information, edge_kind_inliers, of_kind,
                    prepare_view, refine_pose, refine_translation, ring_spacing_deg, without_paint, yaw_about_edges)
from .dynamic import (dynamic_objects, interpolate_pose, lidar_odometry, metric_scale, moving_clusters, point_motion,
                      voxel_down)
from .frame import CameraFrame, LidarSweep
from .objects import ObjectConfig, extract_objects, ground_normal_scatter_deg, ground_plane, level_rotation
from .pnp import _ideal_project, final_pnp
from .sfm import SfmConfig, apply_scale, densify, depth_sigma, run_sfm

SOLVERS = ("oba", "oba_icp", "paper", "ours")


@dataclasses.dataclass
class TargetlessConfig:
    """The four ``*_topic`` fields are declared by the node itself (``add_input``),
    hence ``param=False`` here; they document the names and defaults."""
    lidar_topic: str = cfg_field("/points", "PointCloud2 of the spinning LiDAR", read_only=True, param=False)
    image_topic: str = cfg_field("/camera/image_raw", "camera image (mono8/bgr8/rgb8)", read_only=True, param=False)
    camera_info_topic: str = cfg_field("/camera/camera_info", "CameraInfo of the image", read_only=True, param=False)
    mask_topic: str = cfg_field("", "optional mono8 mask of moving objects (non-zero = dynamic); empty: none",
                                read_only=True, param=False)
    solver: str = cfg_field("ours", "pipeline variant", choices=SOLVERS)
    n_frames: int = cfg_field(8, "images per SfM window (paper: 8)", range=(3, 30))
    min_motion_px: float = cfg_field(10.0, "global image motion (75th percentile of sparse flow) between kept "
                                           "frames (paper: 10 px at 1288 px width)",
                                     range=(0.0, 500.0))
    max_sfm_reprojection_px: float = cfg_field(2.0, "gate: SfM mean re-projection error (paper: 2 px)",
                                               range=(0.1, 50.0))
    max_hausdorff_m: float = cfg_field(0.05, "gate: partial Hausdorff distance of the registered clouds "
                                             "(paper: 5 cm)", range=(0.005, 5.0))
    ours_max_hausdorff_m: float = cfg_field(
        0.08, "ours (edge pose refinement): the paper's gate, evaluated through the refined extrinsic with the "
              "camera cloud's scale free (ours_hausdorff_scale_free; the camera cloud is less precise at speed: "
              "7-9 cm at the true extrinsic on simulated drives at 15-20 m/s; the edges, not the clouds, fix the "
              "result)", range=(0.005, 5.0))
    ours_hausdorff_scale_free: bool = cfg_field(
        True, "ours (edge pose refinement): both Hausdorff gates take the best distance over the camera cloud's "
              "metric scale within +-ours_hausdorff_scale_range about the first camera (the odometry scale "
              "was measured up to 1.7 % off at speed, which alone moves the clouds' distance at the true "
              "extrinsic from 5 to 10 cm)")
    ours_hausdorff_scale_range: float = cfg_field(
        0.03, "ours: half-width of that scale search (relative), in steps of 0.25 %", range=(0.0, 0.2))
    ours_max_hausdorff_above_ground_m: float = cfg_field(
        0.12, "ours, second gate: the same distance over the registered LiDAR points above the ground only "
              "(the ground alone matches whatever slides along a street)", range=(0.005, 5.0))
    ours_min_bev_peak_ratio: float = cfg_field(1.15, "ours, gate: the bird's-eye translation peak over the best "
                                                     "score farther than 1 m from it", range=(1.0, 100.0))
    hausdorff_quantile: float = cfg_field(0.5, "quantile of LiDAR-to-camera-cloud point-to-surface distances "
                                               "used as the partial Hausdorff distance", range=(0.1, 1.0))
    dynamic_dist_m: float = cfg_field(0.3, "an object whose points moved more than this between compensated "
                                           "sweeps is dynamic", range=(0.02, 5.0))
    ground_static_m: float = cfg_field(
        0.15, "points within this of their sweep's ground plane are static whatever the motion test says: a "
              "sparse head's rings cross the road up to a metre apart, so compensated sweeps do not meet point to "
              "point there (simulated VLP-32: 17 % of the road passed the 0.3 m test, HDL-64: 87 %), and without "
              "the road the ICP matched the camera's road to kerbs and car sills, 0.4 m too low, and the paint "
              "edges were lost", range=(0.0, 2.0))
    dynamic_sweep_gap: int = cfg_field(3, "compare the reference sweep with sweeps this many apart",
                                       range=(1, 20))
    dynamic_cluster_speed_mps: float = cfg_field(
        0.5, "edge views: an above-ground cluster off the facades (pillars seen from above, at most 8 m across) "
             "that the neighbouring sweeps put this fast or faster is moving, and its silhouettes are left out "
             "(dynamic.moving_clusters). People walk at 0.7-1.6 m/s and pass the point test (dynamic_dist_m); "
             "their silhouettes, measured at another time than the image, held slow 5100 window 0 113 mm off "
             "(with this test 27 mm). 0: off", range=(0.0, 50.0))
    dynamic_cluster_max_move_m: float = cfg_field(
        3.0, "... compared with the sweeps dynamic_sweep_gap apart, or fewer when the car moved more than this "
             "between them (none when it did even one sweep apart): seen from places farther apart, a static "
             "object's footprint changes and matches elsewhere (simulated at 20 m/s three sweeps apart: 5 % of "
             "the static points above the ground flagged)", range=(0.0, 100.0))
    time_offset_s: float = cfg_field(0.0, "known camera clock minus LiDAR clock", range=(-5.0, 5.0))
    time_offset_sigma_s: float = cfg_field(0.01, "1-sigma prior of the unknown part of the clock offset "
                                                 "(enters the covariance times the speed)", range=(0.0, 1.0))
    sweep_spin: int = cfg_field(-1, "spin direction when the driver publishes no per-point time "
                                    "(-1 clockwise from above: Velodyne, Ouster)", choices=(-1, 1))
    sweep_start_azimuth_deg: float = cfg_field(180.0, "azimuth where a sweep starts (no per-point time)",
                                               range=(-360.0, 360.0))
    sweep_period_s: float = cfg_field(0.1, "sweep period when no per-point time is published", range=(0.01, 1.0))
    sweep_stamp_fraction: float = cfg_field(0.0, "share of the sweep measured before its stamp when no per-point "
                                                 "time is published: 0 stamped at its start, 0.5 halfway (KITTI: "
                                                 "the head faces forward at the stamp), 1 at its end",
                                            range=(0.0, 1.0))
    deskew: bool = cfg_field(True, "de-skew the reference sweep with the odometry velocity")
    odometry_deskew_refit: bool = cfg_field(
        True, "with deskew: the LiDAR odometry is fitted again on the sweeps de-skewed with its first estimate "
              "(a moving LiDAR bends each raw sweep, and scan-to-scan ICP on bent sweeps is biased: stop 39, "
              "fast 6208 at 18.2 m/s, the window's travel 0.5 % short and its links 0.04-0.08 deg off, the "
              "extrinsic 1.06 / 2.12 px and 0.166 deg off; refitted once, 0.41 / 0.64 px and 0.093 deg, as "
              "with the true trajectory; costs one more odometry, about 2 s)")
    odometry_refit_warm: bool = cfg_field(
        True, "the odometry refit starts each link from the first estimate's link alone (the de-skew moves "
              "links by centimetres), without the other starts and the neighbours' passes, at the short "
              "correspondence radius (stop 40, four simulated windows: the same links within 0.3 mm and "
              "0.0005 deg, the refit 25-55 % faster)")
    fuse_windows: int = cfg_field(10, "the published result fuses the most recent accepted windows of the "
                                      "collection, weighted by their covariances (1: each window alone)",
                                  range=(1, 1000))
    fuse_outlier_p: float = cfg_field(0.001, "with 3 or more windows, one that disagrees with the fusion of the "
                                             "others beyond this chi-square tail (6 dof) is left out",
                                      range=(1e-9, 0.5))
    fuse_edge_floor_shared: float = cfg_field(
        0.0, "the share of the edge fit's floors (ours_edge_floor_deg / _m) that the windows of a drive have in "
             "common when they are fused (the clock's part along the drive is always common): 0, each window's "
             "floor is its own (its own street, edges and SfM), so fusing windows shrinks it; 1, none shrinks "
             "(measured offline on 80 simulated drives at 1288 px, 40 published: Mahalanobis^2 of the published "
             "results median 2.1, mean 3.9 with 1; 3.9, 5.8 with 0). A camera model that is wrong in the same "
             "way in every window is not in the floor either way", range=(0.0, 1.0))
    fuse_window_correlation: float = cfg_field(
        0.0, "the share of each window's own error variance (its covariance beyond the shared clock and floor "
             "parts) that the windows of a drive have in common: the fusion shrinks only the rest. At speed the "
             "windows of a drive can repeat their error (stop 39, fast 6400: four drives whose windows were "
             "each 1-2 px off with an honest covariance were published with Mahalanobis^2 8.7-26.5 when fused "
             "as independent). Over stop 39's 60 fresh drives (40 published, the fusion redone exactly from "
             "the stored windows) the published Mahalanobis^2 is median 6.2, mean 6.8 with 0 (2 above 16, 6 "
             "above chi-square's 90 %); 3.7, 4.7 with 0.25; 4.0, 4.0 with 0.5 (none above 16): 0 is the "
             "honest one over the family, a higher value trades a too-wide covariance for a thinner tail",
        range=(0.0, 0.95))
    fuse_min_windows: int = cfg_field(2, "a result is published once this many accepted windows agree (two "
                                         "independent windows within their covariances; 1: every accepted "
                                         "window at once)", range=(1, 100))
    fuse_provisional: bool = cfg_field(
        True, "a window that passed every gate but the distinct-peak one (its translation search found other "
              "places along the street nearly as good) is kept as provisional: it is never published on its "
              "own, but it counts towards fuse_min_windows where it agrees with an accepted window (the "
              "other window's street chose the same place independently)")
    max_point_sigma_m: float = cfg_field(0.15, "camera-cloud points with a larger predicted triangulation "
                                              "error are dropped", range=(0.005, 10.0))
    ours_max_point_sigma_m: float = cfg_field(0.05, "ours: the same limit for the translation ICP (the "
                                                    "predicted sigma is optimistic beyond ~10 m: keep only "
                                                    "the best points there)",
                                              range=(0.005, 10.0))
    ours_centre_sigma_m: float = cfg_field(0.01, "ours: 1-sigma of the SfM camera centres (Wahba weights)",
                                           range=(1e-4, 1.0))
    ours_trajectory_yaw_only: bool = cfg_field(
        True, "ours: the trajectory (SfM camera centres against the LiDAR odometry) sets the yaw alone, the "
              "ground normals the tilt: each trajectory step enters Wahba's problem projected onto its cloud's "
              "ground plane. A sparse LiDAR's scan-to-scan odometry can climb or sink by a degree along a "
              "street (simulated VLP-32: +0.2 deg where the car went -0.9 deg), and the trajectory, weighted as "
              "precise as the SfM centres, then tilted the extrinsic 0.7 deg")
    ours_along_motion_sigma_m: float = cfg_field(0.1, "ours: 1-sigma of the translation along the driving "
                                                       "direction from the camera cloud's depth bias (measured "
                                                       "on the simulated family at 644 px width)",
                                                 range=(0.0, 5.0))
    ours_icp_range_m: float = cfg_field(15.0, "ours: camera-cloud points farther than this from the first camera "
                                              "are left out of the translation ICP", range=(2.0, 100.0))
    ours_icp_stride: int = cfg_field(
        2, "ours: the translation ICP pairs every stride-th camera-cloud point (the densification's flows from "
           "several frames cover each surface several times over; its information is counted for all)",
        range=(1, 16))
    ours_translation_floor_m: float = cfg_field(0.05, "ours: isotropic 1-sigma added to the translation (the "
                                                      "ICP information is over-confident across the street)",
                                                range=(0.0, 5.0))
    ours_ground_sigma_deg: float = cfg_field(0.1, "ours: 1-sigma of a ground normal (Wahba weight)",
                                             range=(0.001, 10.0))
    ours_coarse_candidates: int = cfg_field(12, "ours: bird's-eye translation peaks (1 m apart) ranked by the image "
                                                "edges (1: the highest peak, as before)", range=(1, 50))
    ours_coarse_min_score: float = cfg_field(0.3, "ours: a candidate peak's correlation at least this fraction of "
                                                  "the highest", range=(0.0, 1.0))
    ours_min_coarse_edge_ratio: float = cfg_field(1.15, "ours, gate: the chosen candidate's edge inlier fraction "
                                                       "this many times the best elsewhere's (or a distinct "
                                                       "bird's-eye peak)",
                                                  range=(1.0, 10.0))
    ours_coarse_tie_keeps_bev: bool = cfg_field(
        True, "ours: when the image edges prefer another candidate over the highest bird's-eye peak by less "
              "than ours_min_coarse_edge_ratio and that peak stands out (ours_min_bev_peak_ratio), the highest "
              "peak is kept (if its edges meet well enough) rather than the edges' marginal choice (stop 40: in "
              "347 stored windows the edges chose another candidate by less than 1.15x 6 times, each time "
              "21-678 px off)")
    ours_coarse_agree_m: float = cfg_field(1.0, "ours, gate: when the bird's-eye peak stands out (above "
                                                "ours_min_bev_peak_ratio), the candidate the image edges chose "
                                                "must end within this of it (the candidates' spacing: a fit "
                                                "from the next peak may end between the two)",
                                           range=(0.05, 50.0))
    coarse_radius_m: float = cfg_field(2.5, "ours: the largest horizontal distance between camera and LiDAR on "
                                            "the vehicle (m): the translation search radius about the position "
                                            "of a zero lever arm (the motion between sweep and image taken out)",
                                       range=(0.3, 30.0))
    dense_refs: int = cfg_field(4, "frames the densification starts flow tracks from", range=(1, 30))
    covariance_inflation: float = cfg_field(3.0, "factor on the ICP covariance for correlated residuals",
                                            range=(1.0, 1000.0))
    ours_edge_refine: bool = cfg_field(True, "ours: refine the translation along the driving direction by "
                                             "putting the LiDAR edges on the image edges")
    ours_edge_mode: str = cfg_field("pose", "ours: what the image edges refine: all six degrees of freedom, each "
                                            "image against its own nearest sweep ('pose'), or the translation "
                                            "from the reference sweep only ('translation')",
                                    choices=("pose", "translation"))
    ours_edge_tilt_prior_deg: float = cfg_field(0.3, "ours, pose mode: 1-sigma prior of the tilt from the two "
                                                      "ground planes (the edges see pitch and roll weakly: "
                                                      "LiDAR scan lines give mostly vertical silhouettes; the "
                                                      "camera cloud's ground normal was measured 0.02-0.6 deg "
                                                      "off on the simulated family); with "
                                                      "ours_tilt_prior_measured, only where the road is too "
                                                      "thin to measure it",
                                                range=(0.0, 10.0))
    ours_tilt_prior_measured: bool = cfg_field(True, "ours, pose mode: the tilt prior's 1-sigma measured per "
                                                     "window, the rms scatter of the camera cloud's road "
                                                     "normals in 4 blocks near to far (at least "
                                                     "ours_edge_tilt_prior_min_deg; ours_edge_tilt_prior_deg "
                                                     "when the road has too few points or this is off)")
    ours_edge_tilt_prior_min_deg: float = cfg_field(0.1, "ours, pose mode: the measured tilt prior is at "
                                                          "least this", range=(0.0, 10.0))
    ours_edge_height_prior_m: float = cfg_field(0.03, "ours, pose mode: 1-sigma prior of the height along the up "
                                                      "axis from the registered ground planes (vertical "
                                                      "silhouettes do not see it)", range=(0.0, 10.0))
    ours_height_prior_at_pivot: bool = cfg_field(
        True, "ours, pose mode: the height prior (ours_edge_height_prior_m) holds where the registered clouds fix "
              "the height (the overlap's centroid weighted by its horizontal surfaces, metric "
              "edge_height_pivot_m its distance), not at the camera: a tilt within its prior then moves the "
              "camera's height by the tilt times that lever arm (False: at the camera, as before stop 38)")
    ours_paint_min_lift: float = cfg_field(0.25, "ours, pose mode: after the first edge fit, the paint (LiDAR "
                                                 "intensity) edges must meet the image edges at least this far "
                                                 "from chance towards the silhouettes' share, or the fit is "
                                                 "redone on the silhouettes alone (a real LiDAR's reflectance "
                                                 "steps need not be the image's edges: KITTI's meet them no "
                                                 "more often than chance, 0.10 of the way, and pull the fit "
                                                 "1.7 deg off; simulated paint that is only misaligned, 0.4-0.5 "
                                                 "of the way, holds the camera's height and pitch and must "
                                                 "stay); 0: always keep them", range=(0.0, 1.0))
    ours_paint_min_points: int = cfg_field(
        50, "ours, pose mode: fewer visible paint edge points than this (all images; the edge fit's own minimum "
            "for one image) and the fit is redone on the silhouettes alone: a handful of road-paint points, the "
            "only edges that see the camera's pitch and height, is counted by the fit's information as if each "
            "were independent, and one misplaced point then moves the pitch while the covariance claims it is "
            "known (simulated, 16 points over 8 images: 0.9 deg off, 1.2 px predicted, 12 px true; 149 points "
            "held it within 0.11 deg)", range=(0, 100000))
    ours_edge_restart_yaw_deg: float = cfg_field(0.4, "ours, pose mode: the edge fit restarts from its result "
                                                       "turned by this yaw and twice it, each way, about the "
                                                       "edges' median point (0: no restarts)",
                                                 range=(0.0, 5.0))
    ours_edge_restart_min_gain: float = cfg_field(0.01, "ours, pose mode: a restart replaces the fit only when its "
                                                        "inlier fraction is higher by at least this",
                                                  range=(0.0, 1.0))
    ours_edge_jackknife: bool = cfg_field(True, "ours, pose mode: the covariance is at least the leave-one-image-out "
                                                "(jackknife) spread of the edge fit, refitted without each image "
                                                "in turn (it sees a flat or two-basin objective that the "
                                                "linearised per-image dispersion does not)")
    ours_edge_block_jackknife: int = cfg_field(
        6, "ours, pose mode: the covariance is also at least the jackknife spread of the edge fit refitted "
           "without each of this many bands of image columns in turn (the images share their objects, so an "
           "object's error is in every image; fewer than 3: off)", range=(0, 32))
    ours_edge_jackknife_local: bool = cfg_field(
        True, "ours, pose mode: the jackknifes' refits start from the fit without the edge fit's 1-D search "
              "along the street (a local re-optimisation, as a jackknife assumes; the basin starts look for "
              "other minima along the street); False: each refit searches again")
    ours_edge_jackknife_leverage: bool = cfg_field(
        True, "ours, pose mode: both jackknifes weigh each refit's offset by its left-out group's share of the "
              "fit's information (the group's own information at the fit): a group that carries most of the "
              "information along some direction (the one band of columns that pins the translation along the "
              "street) then counts for what it measures, not for how ill-posed the fit is without it (the CR2 "
              "weighting, see _leave_out_cov); False: the plain jackknife, which assumes groups of equal weight")
    ours_edge_jackknife_min_rest: float = cfg_field(
        0.2, "ours, pose mode, with ours_edge_jackknife_leverage: a refit's offset along a direction where the "
             "groups left in hold less than this share of the fit's information is left out (there the refit "
             "is a barely posed fit, not a perturbed one; the fit's own covariance stays); 0: pure CR2",
        range=(0.0, 1.0))
    ours_edge_basin_along_m: float = cfg_field(
        0.15, "ours, pose mode: the edge fit is also started from the clouds' estimate shifted by -2, -1, 1, 2 "
              "times this along the driving direction (and by ours_edge_basin_side_m sideways); the fits whose "
              "inliers come within ours_edge_basin_margin of the best widen the covariance to their spread "
              "(0: no such starts)", range=(0.0, 2.0))
    ours_edge_basin_side_m: float = cfg_field(0.1, "ours, pose mode: the sideways shift of those starts (each way)",
                                              range=(0.0, 2.0))
    ours_edge_basin_tilt_sigmas: float = cfg_field(
        1.5, "ours, pose mode: two more such starts turned about the camera's horizontal axis (through the "
             "height pivot) by this many tilt priors each way (0: none)", range=(0.0, 10.0))
    ours_edge_kind_check: bool = cfg_field(True, "ours, pose mode: the edge fit is also run on the silhouettes "
                                                 "alone and on the road paint alone (each from the result, the "
                                                 "same priors), to see whether the two kinds agree")
    ours_edge_kind_chi2: float = cfg_field(
        1e6, "ours, pose mode: when the two kinds disagree by more than this chi-square (6 DoF, against the sum "
             "of their covariances) the covariance is widened (ours_edge_kind_widen). 1e6: never, the default: "
             "each kind alone is weak along some direction and its covariance too small there, so on 20 "
             "simulated drives (stop 33) the chi-square exceeded 16.8 in 14 of 26 windows that had both fits, "
             "mostly good ones, and widening at 16.8 refused good windows (90 -> 80 % succeed or are rightly "
             "refused) and made the windows' Mahalanobis^2 median 1.9 (too wide); the case that prompted it "
             "(slow 5100: silhouettes 175 mm off, paint 17 mm, both 113 mm) was people walking, now removed "
             "(dynamic_cluster_speed_mps). The chi-square stays in the metrics (edge_kind_chi2)", range=(0.0, 1e6))
    ours_edge_kind_widen: str = cfg_field(
        "paint", "ours, pose mode: when the two kinds disagree, the covariance is widened to at least the paint "
                 "fit's offset from the result ('paint': the result's error if the silhouettes are the biased "
                 "kind; the paint alone was nearer the truth than the silhouettes alone in 18 of 26 simulated "
                 "windows) or to both fits' offsets ('both': on the same drives at 16.8 it refused 12 windows, "
                 "most of them good)", choices=("paint", "both"))
    ours_edge_basin_margin: float = cfg_field(
        0.03, "ours, pose mode: a start's fit whose inlier fraction is within this of the best is a basin as good "
              "as the result: the covariance is at least the spread of such fits about the result (measured: "
              "on windows within the goals the starts return within ~1 cm; on windows 5-20 px off they stop "
              "5-10 cm apart with inliers 0.01-0.03 apart)", range=(0.0, 1.0))
    ours_min_edge_inliers: float = cfg_field(0.5, "ours, pose mode, gate: fewest LiDAR edge points within 1.5 px "
                                                  "of an image edge after the refinement (a fraction), for a "
                                                  "LiDAR whose column step the camera sees as at most "
                                                  "ours_edge_inliers_step_px", range=(0.0, 1.0))
    ours_edge_inliers_step_px: float = cfg_field(
        3.5, "ours, pose mode: a LiDAR edge lies anywhere within one column step of where it is measured, so "
             "for a column step wider than this (in pixels: the step measured from the sweep times fx) the "
             "share of edge points within 1.5 px of an image edge needed (ours_min_edge_inliers, and the "
             "coarse ranking's) falls as this / step; the 1.5 px tolerance itself stays (measured at 1288 px: "
             "an HDL-64's 0.17 deg is 2.2-3.7 px and its correct fits met 61-89 % of the edges; an Ouster "
             "1024-column's 0.35 deg is 4.5-7.3 px and its fits within 1 px met 40-49 %)",
        range=(0.1, 100.0))
    ours_max_prior_conflict: float = cfg_field(
        16.3, "ours, pose mode, gate: the largest squared, prior-normalised move of the edge fit's tilt and "
              "height away from where the ground planes put them (ours_edge_tilt_prior_deg, "
              "ours_edge_height_prior_m; 3 degrees of freedom, 16.3 is chi-square's 0.1 %: the edges may "
              "rightly correct a prior by 3-4 sigma, 1 % refused a good window): beyond it the ground "
              "planes and the image edges disagree and neither can be trusted", range=(0.0, 1e6))
    ours_min_edge_views: int = cfg_field(4, "ours, pose mode, gate: fewest images whose LiDAR edges are seen",
                                         range=(2, 30))
    ours_edge_floor_deg: float = cfg_field(
        0.035, "ours, pose mode: 1-sigma per axis added to the rotation for what all images share (LiDAR edge "
               "placement, camera model), at the focal length ours_edge_floor_fx_px (stop 39 halved it from "
               "0.07: the block jackknife measures what the images' objects share; with the 0.07 floor the "
               "Mahalanobis^2 median of the published results was 2.4 / 3.8 over 10 + 10 fresh drives, "
               "4.6 / 5.6 re-fused offline with half and 4.9 / 8.7 over 10 + 10 more run with it; without any "
               "floor the fused results' is 12-15: what the windows of a drive share is real, and a user's "
               "camera model is not the simulator's)",
        range=(0.0, 10.0))
    ours_edge_floor_m: float = cfg_field(0.0075, "ours, pose mode: the same for the translation (0.015 before "
                                                 "stop 39)", range=(0.0, 1.0))
    ours_edge_floor_fx_px: float = cfg_field(
        460.0, "ours, pose mode: the focal length (px) at which the two floors hold; they scale with the pixel's "
               "angle, this / fx (measured: the edge fit's drift from the truth halves from 644 to 1288 px wide "
               "images; 460 px is the median focal length of the 644 px wide family the floors were set on)",
        range=(1.0, 1e5))
    ours_edge_images: int = cfg_field(8, "ours: images of the window the edge refinement uses", range=(1, 30))
    ours_edge_view_rotation_sfm: bool = cfg_field(
        True, "ours: each edge view's LiDAR rotation between its sweep's stamp and the image's exposure comes "
              "from the SfM's camera rotations (interpolated to when the LiDAR faced the camera, turned into "
              "the LiDAR frame by the extrinsic's rotation found so far, then to the stamp by the de-skew's own "
              "rotation: sfm_view_rotations) rather than from the LiDAR odometry's links. On a "
              "16-beam LiDAR at 70 km/h the links' pitch erred 0.05-0.11 deg on average (0.1-0.2 rms) even "
              "between sweeps de-skewed with the true motion, the SfM's relative rotations 0.01-0.03 deg; "
              "the images' pitch error became the extrinsic's (simulated fast 7004: the edge fit from the "
              "truth went to 0.155 deg in pitch, 0.06 with the SfM's rotations). The translation stays the "
              "odometry's")
    ours_edge_full: bool = cfg_field(True, "ours: after the 1-D search along the driving direction, a small 3-D "
                                           "translation refinement")
    ours_edge_min_t: float = cfg_field(3.0, "ours: the edge refinement is kept when it lowers the edge score "
                                            "significantly (paired t statistic over the edge points)",
                                       range=(0.0, 100.0))
    ours_edge_max_spread_m: float = cfg_field(0.03, "ours: ... and the standard error of the per-image optima "
                                                    "along the driving direction is below this",
                                              range=(0.001, 1.0))
    ours_edge_sigma_floor_m: float = cfg_field(0.03, "ours: 1-sigma floor of the edge-refined translation along "
                                                     "the driving direction", range=(0.0, 1.0))
    ours_require_edge: bool = cfg_field(True, "ours, gate: refuse a window whose translation along the driving "
                                              "direction the image edges do not confirm (clouds alone leave it "
                                              "about ours_along_motion_sigma_m uncertain on a street)")
    ours_max_predicted_px: float = cfg_field(
        2.5, "ours, gate: the mean projection error in x or y that the result's own covariance predicts over "
             "the LiDAR points in view: half the 5 px a published result must never exceed, since an honest "
             "covariance still leaves the error twice its prediction now and then (stop 29, offline on the "
             "stored windows of 124 drives: at 5 px, 6 windows were accepted worse than 5 px, 4 of them "
             "predicted at 3.5-4.9 px; at 2.5, 2, predicted at 1.4-1.5 px, which no such gate can catch; "
             "the share of drives that succeed or are rightly refused the same)", range=(0.1, 100.0))
    sparse_ring_spacing_deg: float = cfg_field(
        1.0, "advice: when a window is refused and the LiDAR's rings are farther apart than this (median, "
             "measured from a sweep: 2 deg on a 16-beam LiDAR, 0.33-0.53 deg on a VLP-32C, HDL-64 or OS1-64), "
             "the refusal says that the target-less gates pass less often with so sparse a LiDAR and "
             "points to the board method", range=(0.1, 10.0))
    seed: int = cfg_field(0, "random seed of the RANSAC steps", range=(0, 2**31 - 1))
    objects: ObjectConfig = dataclasses.field(default_factory=lambda: ObjectConfig(radius_m=30.0))
    align: AlignConfig = dataclasses.field(default_factory=AlignConfig)
    sfm: SfmConfig = dataclasses.field(default_factory=SfmConfig)
    edges: EdgeConfig = dataclasses.field(default_factory=EdgeConfig)
    ours_sfm: SfmConfig = dataclasses.field(default_factory=lambda: SfmConfig(
        match_window=7, init_parallax_cap_px=1000.0, ratio=0.7, klt_tracks=1500, ba_solver="schur"))


@dataclasses.dataclass
class WindowDiagnostics:
    """What one fit measured (bench and tests read it)."""
    T_oba: np.ndarray | None = None
    T_icp: np.ndarray | None = None
    T_final: np.ndarray | None = None
    T_pre_edge: np.ndarray | None = None
    edge_pose: object = None
    coarse_candidates: list = dataclasses.field(default_factory=list)  # ours: [(T, edge fit)], BEV order
    # ours: the edge views the fit used (silhouettes only when the paint was left out) and its (driving
    # direction, up) in the camera frame
    edge_views: list = dataclasses.field(default_factory=list)
    edge_views_with_paint: list = dataclasses.field(default_factory=list)  # the same before any paint was dropped
    edge_axes: tuple | None = None
    # ours: the edge fit on the silhouettes alone and on the paint alone, and the covariance widened to them
    edge_kind_T: list | None = None
    edge_kind_cov: np.ndarray | None = None
    # the gate's registered overlap: LiDAR points (reference sweep, de-skewed), the levelled camera cloud, its
    # KD-tree, normals and per-point depth sigma, the levelling Ls and T_sweep_img (for distances at any T)
    registered: dict = dataclasses.field(default_factory=dict)
    timings_s: dict = dataclasses.field(default_factory=dict)
    metrics: dict = dataclasses.field(default_factory=dict)
    # the part of the covariance every window of the drive shares (floors, clock): fusing windows keeps it
    shared_cov: np.ndarray | None = None


def _median_flow_px(a: np.ndarray, b: np.ndarray) -> float:
    import cv2
    ga = a if a.ndim == 2 else cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    gb = b if b.ndim == 2 else cv2.cvtColor(b, cv2.COLOR_BGR2GRAY)
    pts = cv2.goodFeaturesToTrack(ga, 400, 0.01, 8)
    if pts is None or len(pts) < 10:
        return 0.0
    nxt, st, _ = cv2.calcOpticalFlowPyrLK(ga, gb, pts, None, winSize=(21, 21), maxLevel=4)
    ok = st.ravel() == 1
    if ok.sum() < 10:
        return math.inf  # lost track: large motion
    return float(np.percentile(np.linalg.norm((nxt - pts).reshape(-1, 2)[ok], axis=1), 75))


def sweep_odometry(sweeps: list, cfg: TargetlessConfig) -> tuple[np.ndarray, list]:
    """(poses ``T_first_k``, links) of consecutive ``sweeps`` by scan-to-scan ICP (:func:`lidar_odometry`);
    with ``deskew`` and ``odometry_deskew_refit``, fitted again on the sweeps de-skewed with the first
    estimate's links: the raw sweeps of a moving LiDAR are bent by the motion during the sweep, and ICP
    between bent sweeps comes out short and turned (``test_odometry_refit_on_deskewed_sweeps``)."""
    poses, links = lidar_odometry([s.points for s in sweeps])
    if cfg.deskew and cfg.odometry_deskew_refit:  # (lidar_odometry needs 2 sweeps: there is a link)
        poses, links = lidar_odometry([deskew_sweep(s, links[j - 1].T if j > 0 else links[0].T, cfg)
                                       for j, s in enumerate(sweeps)],
                                      init_links=[r.T for r in links] if cfg.odometry_refit_warm else None)
    return poses, links


def sweep_times(sweep: LidarSweep, cfg: TargetlessConfig) -> np.ndarray:
    """Each point's time after the sweep's stamp (s): the driver's, else from its azimuth."""
    if sweep.time_s is not None:
        return sweep.time_s
    p = sweep.points
    return spin_time_s(p[:, 0], p[:, 1], cfg.sweep_period_s, cfg.sweep_spin, cfg.sweep_start_azimuth_deg,
                       cfg.sweep_stamp_fraction)


def deskew_sweep(sweep: LidarSweep, T_prev_cur: np.ndarray, cfg: TargetlessConfig) -> np.ndarray:
    """Points of ``sweep`` in the LiDAR frame at its stamp, with the constant
    velocity of the odometry link ``T_prev_cur`` (previous sweep <- this one)."""
    p = sweep.points
    t = sweep_times(sweep, cfg)
    xi_r = so3_log(T_prev_cur[:3, :3]) / cfg.sweep_period_s
    xi_t = T_prev_cur[:3, 3] / cfg.sweep_period_s
    out = np.empty_like(p)
    # group by time (72 bins are plenty: <= 1.4 ms apart)
    bins = np.clip((t / cfg.sweep_period_s * 72).astype(int), -72, 143)
    order = np.argsort(bins, kind="stable")  # each bin's points in their own order, found once
    cuts = np.flatnonzero(np.diff(bins[order])) + 1
    for m in np.split(order, cuts):
        tb = float(np.mean(t[m]))
        R = so3_exp(xi_r * tb)
        out[m] = p[m] @ R.T + xi_t * tb
    return out


class AmbiguousWindow(CalibError):
    """A window that passed every gate but the distinct-peak one: refused on its own, its estimate
    (``T``, ``cov``, ``metrics``; the shared part is in the window's diagnostics) kept as provisional
    (``fuse_provisional``)."""

    def __init__(self, message: str, T: np.ndarray, cov: np.ndarray, metrics: dict):
        super().__init__(message)
        self.T, self.cov, self.metrics = T, cov, metrics


def fuse_accepted(windows: list, cfg: TargetlessConfig) -> tuple:
    """(fused estimate, the windows it was made from, whether it may be published) for the kept
    ``windows`` (dicts with ``T``, ``cov``, ``shared``, and ``provisional`` True for a window kept by
    ``fuse_provisional``): the most recent ``cfg.fuse_windows`` fused, published once ``cfg.fuse_min_windows``
    of them agree and at least one of those is accepted, not provisional (the node's rule; the bench
    re-fuses stored windows with it). Provisional windows are left out when ``cfg.fuse_provisional`` is off."""
    kept = windows if cfg.fuse_provisional else [w for w in windows if not w.get("provisional")]
    recent = kept[-cfg.fuse_windows:]
    if not recent:
        return None, recent, False
    rho = cfg.fuse_window_correlation
    # each window's shared part: the clock and floor part it carries, plus rho of the rest of its covariance
    shared = [np.asarray(w["shared"]) + rho * (np.asarray(w["cov"]) - np.asarray(w["shared"])) for w in recent]
    fused = fuse_estimates([np.asarray(w["T"]) for w in recent], [np.asarray(w["cov"]) for w in recent],
                           shared=np.mean(shared, axis=0), outlier_p=cfg.fuse_outlier_p)
    firm = any(not recent[i].get("provisional") for i in fused.used)
    return fused, recent, len(fused.used) >= cfg.fuse_min_windows and fused.agree and firm


class TargetlessCalibrator:
    """Collects sweeps and images (``add``), calibrates one window (``fit``) and publishes the fusion of
    the accepted windows of the collection (``fuse_windows``); ``next_window`` starts the next window,
    ``reset`` the next collection."""

    def __init__(self, cfg: TargetlessConfig | None = None):
        self.cfg = cfg or TargetlessConfig()
        self.last_diagnostics = WindowDiagnostics()
        self.last_window_images: list = []
        self.reset()

    def reset(self) -> None:
        """A new collection: the images, the sweeps and the accepted windows are dropped."""
        self.sweeps: list[LidarSweep] = []
        self.windows: list[dict] = []   # accepted and provisional windows: T, cov, shared, stamps, metrics, provisional
        self.n_windows_tried = 0
        self.lidar_rings: tuple[int, float] | None = None  # (rings seen, median spacing deg), first fit
        self.last_fused = None
        self.next_window()
        self.n_seen_images = 0

    def next_window(self) -> None:
        """The next window of the same collection: its images start again; the sweeps still needed and
        the accepted windows are kept."""
        self.images: list[CameraFrame] = []
        self.last_reason = ""
        self._trim_sweeps()

    # -- collection -----------------------------------------------------------
    def add(self, frame) -> Verdict:
        if isinstance(frame, LidarSweep):
            if self.sweeps and frame.stamp_s <= self.sweeps[-1].stamp_s:
                v = Verdict(False, f"sweep stamp {frame.stamp_s:.3f} not after the last one")
            elif frame.points.shape[0] < 1000:
                v = Verdict(False, f"sweep has only {frame.points.shape[0]} valid points")
            else:
                self.sweeps.append(frame)
                self._trim_sweeps()
                v = Verdict(True, f"sweep {len(self.sweeps)} buffered")
        elif isinstance(frame, CameraFrame):
            self.n_seen_images += 1
            if len(self.images) >= self.cfg.n_frames:
                v = Verdict(False, "window full: call fit() or reset()")
            elif not self.images:
                self.images.append(frame)
                v = Verdict(True, "first image of the window")
            else:
                mv = _median_flow_px(self.images[-1].image, frame.image)
                if mv < self.cfg.min_motion_px:
                    v = Verdict(False, f"image moved {mv:.1f} px < {self.cfg.min_motion_px:.0f} px since the last "
                                       "kept frame (car too slow)")
                else:
                    self.images.append(frame)
                    v = Verdict(True, f"image {len(self.images)}/{self.cfg.n_frames} kept ({mv:.0f} px motion)")
        else:
            v = Verdict(False, f"unknown frame type {type(frame).__name__}")
        self.last_reason = v.reason
        return v

    def _trim_sweeps(self) -> None:
        if self.images:
            t0 = self._lidar_time(self.images[0]) - 0.5
            while len(self.sweeps) > 2 and self.sweeps[1].stamp_s < t0:
                self.sweeps.pop(0)
        else:
            del self.sweeps[:-8]

    def _lidar_time(self, img: CameraFrame) -> float:
        return img.stamp_s - self.cfg.time_offset_s

    def ready(self) -> bool:
        if len(self.images) < self.cfg.n_frames or len(self.sweeps) < 2:
            return False
        return self.sweeps[-1].stamp_s + self.cfg.sweep_period_s >= self._lidar_time(self.images[-1])

    def sparse_lidar_advice(self) -> str:
        """What a refusal adds when the LiDAR's rings are sparse (``sparse_ring_spacing_deg``); '' else."""
        n, sp = self.lidar_rings or (0, float("nan"))
        if not (sp > self.cfg.sparse_ring_spacing_deg):
            return ""
        return (f". This LiDAR's {n} rings are {sp:.1f} deg apart: with rings this sparse the target-less "
                "gates pass less often (fewer edges and a thinner cloud on the street's objects); if its "
                "windows keep being refused, calibrate it on a checkerboard with board_calib_node instead")

    def status(self) -> dict:
        advice = ""
        if len(self.images) < self.cfg.n_frames:
            advice = "keep driving through a street with poles, trunks or signs"
        elif not self.ready():
            advice = "waiting for LiDAR sweeps covering the kept images"
        return {"frames_collected": len(self.images), "frames_needed": self.cfg.n_frames,
                "sweeps_buffered": len(self.sweeps), "images_seen": self.n_seen_images,
                "windows_tried": self.n_windows_tried,
                "windows_accepted": self.n_accepted(),
                "windows_provisional": len(self.windows) - self.n_accepted(),
                "last_reason": self.last_reason, "advice": advice, "ready": self.ready()}

    def n_accepted(self) -> int:
        """The kept windows that passed every gate (the others are provisional)."""
        return sum(1 for w in self.windows if not w["provisional"])

    # -- fit ------------------------------------------------------------------
    def _refuse(self, e: CalibError) -> None:
        """Raise the window's refusal ``e`` with what the collection keeps and the sparse-LiDAR advice added."""
        n_acc = self.n_accepted()
        kept = f" (window {self.n_windows_tried}; {n_acc} accepted before, kept)" if n_acc else ""
        extra = kept + self.sparse_lidar_advice()
        if extra:
            raise CalibError(f"{e}{extra}") from e
        raise e

    def fit(self) -> CalibrationResult:
        if not self.ready():
            raise NotReadyError(f"targetless: {len(self.images)}/{self.cfg.n_frames} images kept and "
                                f"{len(self.sweeps)} sweeps; keep driving")
        diag = WindowDiagnostics()
        self.last_diagnostics = diag
        self.last_window_images = list(self.images)
        self.n_windows_tried += 1
        if self.lidar_rings is None or not np.isfinite(self.lidar_rings[1]):
            self.lidar_rings = ring_spacing_deg(self.sweeps[-1].points, self.sweeps[-1].ring)
        provisional = None
        try:
            T, cov, metrics = calibrate_window(self.images, self.sweeps, self.cfg, diag)
        except AmbiguousWindow as e:
            if not self.cfg.fuse_provisional:
                self._refuse(e)
            provisional = e
            T, cov, metrics = e.T, e.cov, e.metrics
        except CalibError as e:
            self._refuse(e)
        shared = diag.shared_cov if diag.shared_cov is not None else np.zeros((6, 6))
        self.windows.append({"T": T, "cov": cov, "shared": shared, "stamps": [f.stamp_s for f in self.images],
                             "index": self.n_windows_tried, "metrics": metrics,
                             "provisional": provisional is not None})
        fused, recent, publish = fuse_accepted(self.windows, self.cfg)
        used = [recent[i] for i in fused.used]
        n_acc = self.n_accepted()
        sw = np.degrees(np.sqrt(np.max(np.diag(cov)[:3]))), 1000 * np.sqrt(np.max(np.diag(cov)[3:]))
        metrics = {**metrics, "window_sigma_rotation_deg": float(sw[0]), "window_sigma_translation_mm": float(sw[1]),
                   "windows_accepted": n_acc, "windows_provisional": len(self.windows) - n_acc,
                   "windows_tried": self.n_windows_tried, "window_provisional": int(provisional is not None),
                   "windows_fused": len(used), "windows_fused_provisional": sum(1 for w in used if w["provisional"]),
                   "windows_left_out": len(fused.dropped),
                   "fusion_chi2": fused.chi2, "fusion_dof": fused.dof, "fusion_birge": fused.birge}
        diag.metrics = metrics
        notes = ["Nagy & Benedek 2020 pipeline (SfM, objects, 4D Hough, ICP, PnP); curve refinement not "
                 "implemented"]
        if len(used) > 1:
            notes.append(f"fusion of {len(used)} windows (of {self.n_windows_tried} tried): "
                         + ", ".join(str(w["index"]) + (" (provisional)" if w["provisional"] else "") for w in used)
                         + (f"; scatter chi2 {fused.chi2:.1f} / {fused.dof} dof, covariance x {fused.birge:.2f}"
                            if fused.birge > 1 else ""))
        for i, c2 in fused.dropped:
            notes.append(f"window {recent[i]['index']} left out: it disagrees with the others (chi2 {c2:.1f}, "
                         f"6 dof, beyond the {100 * (1 - self.cfg.fuse_outlier_p):.1f} % quantile)")
        self.last_fused = fused
        if not publish and provisional is not None:
            raise CalibError(f"{provisional} (window {self.n_windows_tried}; kept as provisional: it counts "
                             "once it agrees with an accepted window)" + self.sparse_lidar_advice())
        if not publish:
            if not fused.agree:
                why = (f"the {len(used)} windows disagree (chi2 {fused.chi2:.1f}, 6 dof, beyond the "
                       f"{100 * (1 - self.cfg.fuse_outlier_p):.1f} % quantile): neither is trusted until a third "
                       "decides")
            elif len(used) < self.cfg.fuse_min_windows:
                why = f"{len(used)} of {self.cfg.fuse_min_windows} agreeing windows needed before a result is published"
            else:
                why = "the windows that agree are all provisional (no distinct peak), this one left out"
            raise CalibError(f"window {self.n_windows_tried} accepted ({sw[0]:.2f} deg, {sw[1]:.0f} mm 1-sigma), "
                             f"but {why}; keep driving")
        img0 = self.images[0]
        return CalibrationResult(
            method="targetless", parent_frame=self.sweeps[0].frame_id, child_frame=img0.frame_id,
            T_child_parent=fused.T, covariance=fused.cov, metrics=metrics,
            observations_used=sum(len(w["stamps"]) for w in used),
            stamps=[t for w in used for t in w["stamps"]], solver=self.cfg.solver, notes=notes)


def _neighbours(sweeps: list, use: list, poses: list, j: int, gap: int) -> tuple[list, list]:
    """The sweeps ``gap`` before and after sweep ``j`` of the window (raw points) and their poses
    relative to it (odometry), for the motion-consistency test."""
    others, T_others = [], []
    for dj in (-gap, gap):
        i = j + dj
        if 0 <= i < len(use):
            others.append(sweeps[use[i]].points)
            T_others.append(inv_T(poses[j]) @ poses[i])
    return others, T_others


def _registered_distances(regl: np.ndarray, tree, cs: np.ndarray, nrm: np.ndarray, quantile: float):
    """Point-to-plane distances of registered LiDAR points (levelled camera-cloud frame) to the camera
    cloud ``cs``: the overlap mask and, with at least 50 points on the cloud, the partial Hausdorff
    distances overall and above the ground (None otherwise)."""
    d, nn = tree.query(regl, k=1, distance_upper_bound=0.5, workers=-1)
    ok = np.isfinite(d)
    if ok.sum() < 50:
        return ok, None
    dist = np.abs(np.einsum("ij,ij->i", regl[ok] - cs[nn[ok]], nrm[nn[ok]]))
    above = regl[ok][:, 2] > 0.3
    return ok, {"hausdorff_m": float(np.quantile(dist, quantile)),
                "hausdorff_above_ground_m": float(np.quantile(dist[above], quantile)) if above.sum() >= 20
                else float("nan"),
                "overlap_above_ground_points": int(above.sum()), "overlap_points": int(ok.sum())}


def _height_pivot(regl: np.ndarray, q_cam: np.ndarray, tree, nrm: np.ndarray,
                  max_points: int = 5000) -> np.ndarray | None:
    """Where the registered clouds fix the camera's height (camera frame): the centroid of the registered
    overlap's points ``q_cam`` (the same points levelled, ``regl``), each weighted by the squared vertical
    part of the camera cloud's normal where it lands (a point-to-plane fit pins the height where the
    horizontal surfaces are: mostly the road ahead). A tilt error of the levelling turns about this point,
    so the camera's own height is off by the tilt times the lever arm (measured on a VLP-32 window: 0.6 deg
    of tilt left the camera 156 mm low, while 10-18 m ahead, where the registered road is, the height was
    32-46 mm off). None with fewer than 50 points or no horizontal surface."""
    if regl.shape[0] < 50:
        return None
    idx = np.linspace(0, regl.shape[0] - 1, min(max_points, regl.shape[0])).astype(int)
    d, nn = tree.query(regl[idx], k=1, distance_upper_bound=0.5, workers=-1)
    ok = np.isfinite(d)
    if ok.sum() < 50:
        return None
    w = nrm[nn[ok], 2] ** 2
    if not float(w.sum()) > 1e-9:
        return None
    return (q_cam[idx][ok] * w[:, None]).sum(axis=0) / float(w.sum())


def _drive_axes(X: np.ndarray, Ll: np.ndarray, T_link: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(driving direction, LiDAR ground normal) in the camera frame of the extrinsic ``X``."""
    d = T_link[:3, 3] / max(np.linalg.norm(T_link[:3, 3]), 1e-9)
    return X[:3, :3] @ d, X[:3, :3] @ Ll[2, :3]


def _rank_fit(views: list, cam, X: np.ndarray, Ll: np.ndarray, T_link: np.ndarray, ecfg: EdgeConfig,
              max_rot_deg: float = 1.5, max_shift_m: float = 1.0):
    """A coarse candidate's edge fit: yaw about the LiDAR's up axis and the translation of ``X``
    (the tilt comes from the ground planes), with the 1-D search along the driving direction. None when
    too few edges are seen; a fit that left the candidate (more than ``max_rot_deg`` / ``max_shift_m``)
    found some other alignment of the edges, not this candidate's: it counts with no inliers."""
    d, up = _drive_axes(X, Ll, T_link)
    f = refine_pose(views, cam, X, ecfg, direction=d, up=up, tilt_prior_deg=0.0)
    if f is not None and (np.degrees(np.linalg.norm(f.xi[:3])) > max_rot_deg or
                          np.linalg.norm(f.xi[3:]) > max_shift_m):
        return dataclasses.replace(f, T=X.copy(), inliers=0.0)
    return f


def _edge_fit(views: list, cam, X: np.ndarray, axes: tuple, cfg: TargetlessConfig, centre: np.ndarray,
              pivot: np.ndarray | None = None):
    """The 6-DoF edge fit from ``X`` with the ground-plane priors on the tilt and the height about
    ``centre`` (the clouds' estimate, whatever the start); ``axes``: (driving direction, up) in the camera
    frame (``_drive_axes``); ``pivot``: where the height prior holds (camera frame of ``centre``; None: at
    the camera, see :func:`_height_pivot`)."""
    d, up = axes
    return refine_pose(views, cam, X, cfg.edges, direction=d, up=up, tilt_prior_deg=cfg.ours_edge_tilt_prior_deg,
                       height_prior_m=cfg.ours_edge_height_prior_m, prior_centre=centre, height_pivot=pivot)


def _edge_restarts(views: list, cam, pe, Ll: np.ndarray, T_link: np.ndarray, cfg: TargetlessConfig,
                   centre: np.ndarray, pivot: np.ndarray | None = None):
    """(fit, the restart's yaw in deg, 0 for none): the 6-DoF edge fit ``pe`` restarted from its result
    turned by -2, -1, 1, 2 times ``ours_edge_restart_yaw_deg`` about the edges' median point. Along that
    valley a yaw and a lateral shift trade off and a single start can stop in a side minimum; a restart
    replaces the fit only when its inlier fraction is ``ours_edge_restart_min_gain`` higher. The tilt and
    height priors stay about ``centre`` (the clouds' estimate)."""
    axes = _drive_axes(pe.T, Ll, T_link)
    best, taken = pe, 0.0
    for k in (-2, -1, 1, 2):
        a = k * cfg.ours_edge_restart_yaw_deg
        r = _edge_fit(views, cam, yaw_about_edges(views, pe.T, axes[1], a), axes, cfg, centre, pivot)
        if r is not None and r.inliers >= best.inliers + cfg.ours_edge_restart_min_gain:
            best, taken = r, a
    return best, taken


def _jackknife_cov(views: list, cam, pe, axes: tuple, cfg: TargetlessConfig, centre: np.ndarray,
                   pivot: np.ndarray | None = None):
    """(6x6 jackknife covariance of the edge fit ``pe`` in its left-perturbation convention, number of
    refits) from the fit refitted without each view in turn (from ``pe.T``, the same priors); None when
    fewer than 4 refits have edges."""
    axes = _leave_out_axes(axes, cfg)
    fits = [_edge_fit(views[:i] + views[i + 1:], cam, pe.T, axes, cfg, centre, pivot) for i in range(len(views))]
    keep = [i for i, r in enumerate(fits) if r is not None]
    if len(keep) < 4:
        return None, len(keep)
    Hg = edge_group_information(views, cam, pe.T, cfg.edges) if cfg.ours_edge_jackknife_leverage else None
    return _leave_out_cov(pe, np.array([_delta(fits[i].T, pe.T) for i in keep]),
                          None if Hg is None else Hg[keep], cfg), len(keep)


def _leave_out_axes(axes: tuple, cfg: TargetlessConfig) -> tuple:
    """The axes a leave-out refit gets: with ``ours_edge_jackknife_local`` no driving direction, so that
    the refit is the local re-optimisation from the fit that a jackknife assumes. The edge fit's 1-D
    search along the street (+-``edges.search_m``, on the coarse field) is a global move: without a band of
    columns that held 8 % of slow 5706 w1's edges it chose another place 494 mm along the street, where
    the refit then settled, though the bands left held 78 % of the fit's information along the street
    and its 0.35 px result was right (the block jackknife widened it 407x); the basin starts
    (:func:`_edge_basins`) are what looks for another minimum along the street."""
    return (None, axes[1]) if cfg.ours_edge_jackknife_local else axes


def _leave_out_cov(pe, xs: np.ndarray, Hg: np.ndarray | None, cfg: TargetlessConfig) -> np.ndarray:
    """The delete-a-group jackknife covariance of the edge fit ``pe`` from its leave-one-group-out refits'
    offsets ``xs`` (g, 6) from it: (g-1)/g sum (x - mean)(x - mean)^T.

    That holds for groups of equal weight. A group that carries most of the information along some
    direction leaves the refit barely posed there, and its offset blows up: the bands of image columns are
    far from equal (slow 5706 w1 at its fit: one band of 8 % of the edges holds 55 % of the information
    along the street, the two outer bands of 40 % each none of it), and fast 5809 w0 and w1 carry a bias every image
    repeats, so there the block jackknife is what widens the covariance.

    With ``Hg`` (g, 6, 6), each group's information at ``pe`` (:func:`edge_group_information`), each offset
    is first weighed by its group's share of the information, in the full fit's whitened coordinates
    z = H^1/2 x (H = ``pe.info``): z' = (I - M_b)^1/2 z, M_b = H^-1/2 H_b H^-1/2, and the sum is not scaled
    by (g-1)/g: the parameter-space form of the bias-reduced cluster-robust (CR2) estimator. For equal
    groups M_b = I/g and the two agree; on a linear problem with one group holding nearly all of a
    direction's information the plain estimate is 290x the true variance there, this one 0.8x
    (test_targetless_edges). Along the directions where the other groups hold less than
    ``ours_edge_jackknife_min_rest`` of the information the offset is left out altogether: there the refit
    is not a perturbed fit but a different, barely posed one, and the jackknife cannot say more than the
    fit's own information, which stays in the covariance. On the stored windows: fast 5809 w1 (1.1 / 1.6
    px) Mahalanobis^2 1.9 -> 3.1 (block widening 3.8x -> 2.9x), fast 5809 w0 (0.7 / 1.5 px) refused for a
    predicted 2.6 px -> accepted at 10.5, slow 5706 w0 (1.8 / 1.1 px) still refused."""
    g = len(xs)
    if Hg is None or pe.info is None:
        d = xs - xs.mean(axis=0)
        return (g - 1) / g * d.T @ d
    w, V = np.linalg.eigh(0.5 * (pe.info + pe.info.T))
    pos = w > 1e-12 * max(float(w.max()), 1e-300)
    S = (V[:, pos] / np.sqrt(w[pos])) @ V[:, pos].T        # H^-1/2 (on the observed directions)
    Si = (V[:, pos] * np.sqrt(w[pos])) @ V[:, pos].T       # H^1/2
    out = []
    for Hb, x in zip(Hg, xs):
        M = S @ Hb @ S
        mw, mv = np.linalg.eigh(0.5 * (M + M.T))
        rest = np.clip(1.0 - mw, 0.0, 1.0)
        f = np.where(rest >= cfg.ours_edge_jackknife_min_rest, np.sqrt(rest), 0.0)
        out.append(S @ (mv * f) @ mv.T @ Si @ x)
    d = np.array(out) - np.mean(out, axis=0)
    return d.T @ d


def _block_jackknife_cov(views: list, cam, pe, axes: tuple, cfg: TargetlessConfig, centre: np.ndarray,
                         pivot: np.ndarray | None = None):
    """(6x6 jackknife covariance, number of refits): the edge fit ``pe`` refitted without each of
    ``ours_edge_block_jackknife`` bands of image columns in turn (the edges of every image that fall in
    the band at ``pe.T`` left out; from ``pe.T``, the same priors). The images of a window see the same
    few poles and paint stripes, so what one of them gets wrong (a post's silhouette, a stripe's step)
    every image repeats: the leave-one-image-out jackknife cannot see it, leaving out the part of the
    scene that carries it can (fast 5809 w1: 0.32 deg of pitch with all 8 image refits within 0.02 deg
    of it; without the outer bands, 0.13 and 0.21 deg back). None with fewer than 3 refits."""
    nb = int(cfg.ours_edge_block_jackknife)
    axes = _leave_out_axes(axes, cfg)
    bands = []
    for v in views:
        prepare_view(v, cfg.edges)
        uv, _ = cam.project(transform_points(pe.T @ inv_T(v.T_sweep_img), v.edges))
        bands.append(np.clip(np.floor(uv[:, 0] / cam.width * nb), 0, nb - 1).astype(int))
    fits = []
    for b in range(nb):
        sub = [dataclasses.replace(v, edges=v.edges[k != b], kinds=v.kinds[k != b]) for v, k in zip(views, bands)]
        r = _edge_fit(sub, cam, pe.T, axes, cfg, centre, pivot)
        if r is not None:
            fits.append((b, r))
    if len(fits) < 3:
        return None, len(fits)
    Hg = edge_group_information(views, cam, pe.T, cfg.edges, nb) if cfg.ours_edge_jackknife_leverage else None
    return _leave_out_cov(pe, np.array([_delta(r.T, pe.T) for _, r in fits]),
                          None if Hg is None else Hg[[b for b, _ in fits]], cfg), len(fits)


def _delta(T: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """(rotation vector, translation) of ``T`` about ``T_ref``, left perturbation (the covariances' convention)."""
    R = T[:3, :3] @ T_ref[:3, :3].T
    return np.concatenate([so3_log(R), T[:3, 3] - R @ T_ref[:3, 3]])


def _edge_basins(views: list, cam, pe, Ll: np.ndarray, T_link: np.ndarray, cfg: TargetlessConfig,
                 centre: np.ndarray, pivot: np.ndarray | None = None):
    """(fit, spread 6x6 or None, number of fits within the margin, starts run): the 6-DoF edge fit also
    started from the clouds' estimate ``centre`` shifted along the driving direction (-2, -1, 1, 2 times
    ``ours_edge_basin_along_m``) and sideways (+-``ours_edge_basin_side_m``). The edge objective is rough:
    where the images do not pin the extrinsic, each start stops in its own minimum, with inlier fractions
    a few hundredths apart and poses 5-10 cm apart; where they do, the starts come back to within about
    1 cm. A start's fit replaces ``pe`` only when its inliers are ``ours_edge_restart_min_gain`` higher;
    the spread returned is the mean of d d^T over the fits (the result's own included, d = 0) whose
    inliers come within ``ours_edge_basin_margin`` of the result's: a second moment about the result, so
    that a basin as good as the result widens the covariance towards it.

    Two more starts tilt the result ``pe`` up and down (about the camera's horizontal axis, through
    ``pivot``, by +-``ours_edge_basin_tilt_sigmas`` times the tilt prior): the vertical silhouettes barely
    see that tilt, the camera's height moves with it, and the fit can have a second minimum there (a
    VLP-32 window stopped 0.6 deg and 18 cm off, its covariance saying 0.06 deg, in a basin whose inliers
    were 0.717 where the truth's were 0.700)."""
    d, up = _drive_axes(centre, Ll, T_link)
    side = np.cross(up, d)
    side /= max(np.linalg.norm(side), 1e-9)
    a, b = cfg.ours_edge_basin_along_m, cfg.ours_edge_basin_side_m
    starts = [(centre, np.zeros(3), k * a * d) for k in (-2, -1, 1, 2)] if a > 0 else []
    starts += [(centre, np.zeros(3), s * b * side) for s in (-1, 1)] if b > 0 else []
    u = up / max(np.linalg.norm(up), 1e-12)
    h = np.cross(u, [0.0, 0.0, 1.0])  # the camera's horizontal axis (image rows move with a turn about it)
    if cfg.ours_edge_basin_tilt_sigmas > 0 and np.linalg.norm(h) > 0.3:
        h /= np.linalg.norm(h)
        # the pivot moved with the fit (it is a point of the scene: where the clouds' estimate put it)
        p0 = np.zeros(3) if pivot is None else \
            transform_points(pe.T @ inv_T(centre), np.asarray(pivot, float)[None])[0]
        for s in (-1, 1):
            w = h * s * math.radians(cfg.ours_edge_basin_tilt_sigmas * cfg.ours_edge_tilt_prior_deg)
            starts.append((pe.T, w, p0 - so3_exp(w) @ p0))  # turned about the pivot, which stays put
    fits = []
    for base, w, sh in starts:
        R = so3_exp(w)
        X = base.copy()
        X[:3, :3] = R @ base[:3, :3]
        X[:3, 3] = R @ base[:3, 3] + sh
        r = _edge_fit(views, cam, X, (d, up), cfg, centre, pivot)
        if r is not None:
            fits.append(r)
    best = pe
    for r in fits:
        if r.inliers >= best.inliers + cfg.ours_edge_restart_min_gain:
            best = r
    near = [r for r in fits + [pe] if r.inliers >= best.inliers - cfg.ours_edge_basin_margin]
    if best is not pe:
        near = [r for r in near if r is not best] + [best]
    D = np.array([_delta(r.T, best.T) for r in near])
    return best, (D.T @ D / len(near) if len(near) > 1 else None), len(near), len(starts)


def _camera_sector_time(v, R_cl: np.ndarray, half_deg: float = 20.0) -> float:
    """When (s after the sweep's stamp) the LiDAR scanned the camera's side: the median time of the view's
    returns within ``half_deg`` of the camera's optical axis in azimuth (0 when unknown)."""
    if v.time_s is None or v.time_s.shape[0] != v.raw.shape[0] or v.raw.shape[0] == 0:
        return 0.0
    a = np.asarray(R_cl, float).T @ np.array([0.0, 0.0, 1.0])
    if math.hypot(a[0], a[1]) < 0.2:  # a camera looking up or down: no sector
        return 0.0
    az = np.arctan2(v.raw[:, 1], v.raw[:, 0]) - math.atan2(a[1], a[0])
    near = np.abs(np.angle(np.exp(1j * az))) <= math.radians(half_deg)
    return float(np.median(v.time_s[near])) if near.any() else 0.0


def sfm_view_rotations(views: list, sfm_poses: np.ndarray, exposures: np.ndarray, R_cl: np.ndarray) -> tuple:
    """(views, the largest change in deg): each view's ``T_sweep_img`` (LiDAR at its sweep's stamp <- LiDAR
    at its image's exposure) with the rotation taken from the SfM. The camera's rotation is interpolated
    (geodesically, extrapolated past the ends) between the two nearest exposures to the time the LiDAR
    scanned the camera's side (``_camera_sector_time`` after the sweep's stamp), taken relative to its rotation
    at the view's exposure and turned into the LiDAR frame by ``R_cl`` (camera <- LiDAR); the de-skew's own
    rotation over that time (``deskew_rate``, the odometry link's) then brings it to the stamp, so that the
    points the camera sees, de-skewed with the odometry's rate, are undone to when they were measured
    before the SfM takes them to the exposure. The translation is kept. ``sfm_poses``: (N,4,4)
    T_cam_k_world, ``exposures``: (N,) the images' exposure times on the LiDAR clock, in the same order. A
    view without its sweep's stamp or image index, or with non-finite SfM poses around it, is kept as it
    is."""
    t = np.asarray(exposures, float)
    n = t.size
    if n < 2 or len(sfm_poses) != n:
        return views, 0.0
    C = [np.asarray(P, float)[:3, :3].T for P in sfm_poses]  # camera k -> SfM world
    R_cl = np.asarray(R_cl, float)
    out, moved = [], 0.0
    for v in views:
        k = v.image_index
        if v.sweep_stamp_s is None or not 0 <= k < n:
            out.append(v)
            continue
        tau = _camera_sector_time(v, R_cl) if v.deskew_rate is not None else 0.0
        ts = v.sweep_stamp_s + tau
        i = int(np.clip(np.searchsorted(t, ts) - 1, 0, n - 2))
        span = t[i + 1] - t[i]
        if not (span > 0 and np.all(np.isfinite(C[i])) and np.all(np.isfinite(C[i + 1])) and
                np.all(np.isfinite(C[k]))):
            out.append(v)
            continue
        a = (ts - t[i]) / span
        C_s = C[i] @ so3_exp(a * so3_log(C[i].T @ C[i + 1]))
        T = np.array(v.T_sweep_img, float)
        R = R_cl.T @ C_s.T @ C[k] @ R_cl
        if tau != 0.0:
            R = so3_exp(np.asarray(v.deskew_rate, float) * tau) @ R
        moved = max(moved, float(np.degrees(np.linalg.norm(so3_log(R @ T[:3, :3].T)))))
        T[:3, :3] = R
        out.append(dataclasses.replace(v, T_sweep_img=T))
    return out, moved


def _kind_fits(views: list, cam, pe, axes: tuple, cfg: TargetlessConfig, centre: np.ndarray,
               pivot: np.ndarray | None = None) -> tuple:
    """(the two fits, or None, metrics): the edge fit ``pe`` refitted (from ``pe.T``, the same priors) on the
    silhouettes alone and on the road paint alone. The two kinds are independent measurements with their
    own failure modes (a silhouette sits where the laser's footprint left an object, paint where the
    reflectance steps on the road), so beyond their covariances they must agree: ``edge_kind_chi2`` is
    their difference's chi-square (6 DoF) against the sum of their covariances. None when either kind has
    too few edges to fit."""
    fits = [_edge_fit(of_kind(views, cfg.edges, k), cam, pe.T, axes, cfg, centre, pivot) for k in (0, 1)]
    if fits[0] is None or fits[1] is None:
        return None, {}
    d = _delta(fits[0].T, fits[1].T)
    try:
        chi2 = float(d @ np.linalg.solve(fits[0].cov + fits[1].cov, d))
    except np.linalg.LinAlgError:
        return None, {}
    return fits, {"edge_kind_chi2": chi2, "edge_kind_apart_deg": float(np.degrees(np.linalg.norm(d[:3]))),
                  "edge_kind_apart_mm": float(1000 * np.linalg.norm(d[3:]))}


def kind_widened(cov: np.ndarray, T: np.ndarray, kind_T: list) -> np.ndarray:
    """The covariance ``cov`` of the result ``T`` widened to at least each given per-kind fit's offset from
    it (:func:`cov_upper` of the sum of their d d^T). The result weighs both kinds: if one kind is biased
    and the other right, the result is off by the right kind's offset from it (the joint optimum is the
    information-weighted mean, so that offset is H^-1 H_biased times the bias)."""
    D = np.array([_delta(Tk, T) for Tk in kind_T])
    return cov_upper(cov, D.T @ D)


def _prior_move(T: np.ndarray, centre: np.ndarray, up: np.ndarray, cfg: TargetlessConfig,
                pivot: np.ndarray | None = None) -> dict:
    """How far the edge fit ``T`` moved the tilt and the height (at ``pivot``, camera frame of ``centre``;
    None: at the camera) from the ground planes' ``centre`` (the
    clouds' estimate, where the priors sit), in the priors' own perturbation (left, camera frame), and that
    move squared in units of the priors (``edge_prior_conflict``: chi-square with 3 degrees of freedom when
    the priors are honest and the edges see tilt and height better than the priors)."""
    u = up / max(np.linalg.norm(up), 1e-12)
    R = T[:3, :3] @ centre[:3, :3].T
    w = so3_log(R)
    tilt = float(np.linalg.norm(w - (w @ u) * u))
    p0 = np.zeros(3) if pivot is None else np.asarray(pivot, float)
    height = float(u @ (R @ p0 + T[:3, 3] - R @ centre[:3, 3] - p0))
    z2 = (tilt / math.radians(max(cfg.ours_edge_tilt_prior_deg, 1e-9))) ** 2 + \
        (height / max(cfg.ours_edge_height_prior_m, 1e-9)) ** 2
    return {"edge_prior_tilt_move_deg": math.degrees(tilt), "edge_prior_height_move_m": height,
            "edge_prior_conflict": float(z2)}


def cov_upper(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The covariance that is at least ``A`` and at least ``B`` along every direction: ``A`` stretched along
    the directions where ``B`` is larger (eigenvalues of ``B`` whitened by ``A`` clamped at >= 1)."""
    L = np.linalg.cholesky(A)
    Li = np.linalg.inv(L)
    w, V = np.linalg.eigh(Li @ B @ Li.T)
    return L @ (V * np.maximum(w, 1.0)) @ V.T @ L.T


def _widen(pe, B: np.ndarray, metrics: dict, key: str):
    """The edge fit ``pe`` with its covariance widened to at least ``B`` (:func:`cov_upper`); ``metrics[key]``:
    by how much (the largest sigma ratio). Unchanged when the covariance is singular."""
    try:
        c_up = cov_upper(pe.cov, B)
        metrics[key] = float(np.sqrt(max(np.linalg.eigvals(np.linalg.solve(pe.cov, c_up)).real.max(), 1.0)))
        return dataclasses.replace(pe, cov=c_up)
    except np.linalg.LinAlgError:
        return pe


def edge_inliers_needed(cfg: TargetlessConfig, step_px: float) -> float:
    """The share of LiDAR edge points within 1.5 px of an image edge that the edge gate and the coarse
    ranking ask for, given the LiDAR's column step as the camera sees it (px; NaN: unknown):
    ``ours_min_edge_inliers`` up to a step of ``ours_edge_inliers_step_px``, falling as that / step beyond
    (an edge point lies anywhere within a step of the true edge, so the share of correct points within a
    fixed tolerance falls as the step widens)."""
    if np.isfinite(step_px) and step_px > cfg.ours_edge_inliers_step_px:
        return cfg.ours_min_edge_inliers * cfg.ours_edge_inliers_step_px / step_px
    return cfg.ours_min_edge_inliers


def _rank_candidates(fits: list, same_m: float = 0.5) -> tuple[int | None, float]:
    """(index of the fit whose edges meet best, its inlier fraction over the best of the fits that
    ended elsewhere (> ``same_m`` apart; inf when none did)); (None, nan) when no fit has edges."""
    ok = [i for i, f in enumerate(fits) if f is not None]
    if not ok:
        return None, float("nan")
    b = max(ok, key=lambda i: fits[i].inliers)
    return b, _rank_ratio(fits, b, same_m)


def _coarse_choice(fits: list, bev_ratio: float, min_inliers: float, cfg: TargetlessConfig) -> tuple:
    """(the coarse candidate kept, or None for the highest bird's-eye peak; its edge inlier ratio over the
    best elsewhere) from the candidates' edge fits ``fits`` (the highest peak's first) and the bird's-eye
    peak ratio. The edges' choice (:func:`_rank_candidates`), unless they meet poorly everywhere; with
    ``ours_coarse_tie_keeps_bev``, the highest peak when the edges prefer another over it by less than
    ``ours_min_coarse_edge_ratio`` and the bird's-eye peak stands out (a tie in the edges is no vote
    against the clouds: which candidate wins a tie turns on bits)."""
    best_i, ratio_e = _rank_candidates(fits)
    if best_i is not None and fits[best_i].inliers < min_inliers:
        # the edges meet poorly wherever the candidates put them: keep the highest peak
        return None, float("nan")
    if (cfg.ours_coarse_tie_keeps_bev and best_i not in (None, 0) and bev_ratio >= cfg.ours_min_bev_peak_ratio
            and fits[0] is not None and fits[0].inliers >= min_inliers
            and fits[best_i].inliers < cfg.ours_min_coarse_edge_ratio * fits[0].inliers):
        return 0, _rank_ratio(fits, 0)
    return best_i, ratio_e


def _rank_ratio(fits: list, b: int, same_m: float = 0.5) -> float:
    """Fit ``b``'s inlier fraction over the best of the fits that ended more than ``same_m`` from it
    (inf when none did)."""
    others = [f.inliers for f in fits
              if f is not None and np.linalg.norm(f.T[:3, 3] - fits[b].T[:3, 3]) > same_m]
    return fits[b].inliers / max(max(others), 0.01) if others else float("inf")


def ground_distance(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """(N,) each point's distance to the sweep's ground plane (LiDAR z up within 25 deg; m), inf for every
    point when it has none."""
    try:
        n, d = ground_plane(points, np.random.default_rng(seed), np.array([0.0, 0.0, 1.0]))
    except CalibError:
        return np.full(points.shape[0], np.inf)
    return np.abs(points @ n + d)


def _level(points: np.ndarray, up: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    n, d = ground_plane(points, rng, up)
    L = make_T(level_rotation(n), np.zeros(3))
    L[2, 3] = d  # n.p + d = 0 on the ground -> z = n.p + d
    return L


def calibrate_window(images: list, sweeps: list, cfg: TargetlessConfig,
                     diag: WindowDiagnostics | None = None, cache: dict | None = None
                     ) -> tuple[np.ndarray, np.ndarray, dict]:
    """(T_camera_lidar, covariance 6x6, metrics) from one window of kept images
    and the sweeps around them. Raises :class:`CalibError` (gate or failure).
    ``cache``: a dict shared between calls on the same window (the bench runs
    several solvers on one SfM and one odometry). BLAS runs on one thread meanwhile
    (:func:`~lidar_cam_calib.core.threads.one_blas_thread`: its spinning threads
    would take the core the LiDAR side and OpenCV work on)."""
    with one_blas_thread():
        return _calibrate_window(images, sweeps, cfg, diag, cache)


def _calibrate_window(images: list, sweeps: list, cfg: TargetlessConfig, diag: WindowDiagnostics | None,
                      cache: dict | None) -> tuple[np.ndarray, np.ndarray, dict]:
    cache = {} if cache is None else cache
    diag = diag or WindowDiagnostics()
    solver = cfg.solver
    ours = solver == "ours"
    rng = np.random.default_rng(cfg.seed)
    tm = diag.timings_s
    t0 = time.perf_counter()
    cam = images[0].camera
    ims = [f.image for f in images]
    masks = [f.mask for f in images] if any(f.mask is not None for f in images) else None
    # -- the LiDAR side (odometry, de-skew, the moving points, the edge views) does not need the SfM: it runs
    # in a second thread while the SfM runs (OpenCV, the kd-tree queries and numpy's array work release the
    # GIL; OpenCV's stages of the SfM use both cores much of the time, so the two sides share the cores rather
    # than fill an idle one: stop 36 measured 0.1-1.5 s a window, with BLAS's spinning threads, which
    # calibrate_window now turns off, still taking a core). The same results: no random state is shared (the
    # SfM's FLANN draws from OpenCV's RNG, which is per thread)
    def lidar_side() -> dict:
        # -- LiDAR odometry
        t1 = time.perf_counter()
        t_img = np.array([f.stamp_s - cfg.time_offset_s for f in images])
        stamps = np.array([s.stamp_s for s in sweeps])
        lo = max(0, int(np.searchsorted(stamps, t_img[0])) - 1 - cfg.dynamic_sweep_gap)
        hi = min(len(sweeps), int(np.searchsorted(stamps, t_img[-1])) + 1)
        use = list(range(lo, hi))
        if len(use) < 2:
            raise CalibError("not enough LiDAR sweeps around the kept images")
        if "odometry" not in cache:
            cache["odometry"] = sweep_odometry([sweeps[i] for i in use], cfg)
        poses, links = cache["odometry"]
        stamps_u = stamps[use]
        P_img = np.array([interpolate_pose(stamps_u, poses, t) for t in t_img])
        tm["odometry"] = time.perf_counter() - t1
        # reference sweep: nearest to the first image; de-skewed to its stamp
        jr = int(np.argmin(np.abs(stamps_u - t_img[0])))
        ref_sweep = sweeps[use[jr]]
        def link_of(j):  # the odometry link that ends at sweep j (the first one for sweep 0)
            return links[j - 1] if j > 0 else links[0]
        link = link_of(jr)
        lid = deskew_sweep(ref_sweep, link.T, cfg) if cfg.deskew else ref_sweep.points
        # LiDAR pose at the reference exposure, relative to the reference sweep stamp
        T_sweep_img = inv_T(poses[jr]) @ P_img[0]
        ja = max(jr, 1)
        speed = float(np.linalg.norm(link.T[:3, 3]) / max(stamps_u[ja] - stamps_u[ja - 1], 1e-3))
        # -- dynamic objects (motion consistency with sweeps gap apart)
        others, T_others = _neighbours(sweeps, use, poses, jr, cfg.dynamic_sweep_gap)
        # per point: how far it moved between the compensated sweeps (objects and the edge views use it)
        motion = point_motion(ref_sweep.points, others, T_others) if others else np.zeros(lid.shape[0])
        # -- edge views (ours): each image with the sweep nearest its exposure, de-skewed, its moving points
        # marked; they rank the coarse translations and refine the extrinsic
        views = []
        min_inliers = cfg.ours_min_edge_inliers
        metrics_step = {}
        t_views = time.perf_counter()
        if ours and cfg.ours_edge_refine and cfg.ours_edge_mode == "pose":
            # an edge point is measured up to one column step from the true edge: with a step wider than the
            # one the inlier share was set on, fewer correct points are within 1.5 px; ask for that many less
            step = azimuth_step_rad(ref_sweep.points)
            step_px = float(cam.K[0, 0]) * step
            min_inliers = edge_inliers_needed(cfg, step_px)
            metrics_step = {"lidar_azimuth_step_deg": math.degrees(step), "edge_step_px": step_px,
                            "edge_inliers_needed": min_inliers}
            static_cache: dict = {jr: (lid, motion <= cfg.dynamic_dist_m)}  # sweep -> (de-skewed, static)
            ground_cache: dict = {}  # sweep -> each point's distance to its ground plane
            walk_cache: dict = {}    # sweep -> points on clusters that moved (moving_clusters)

            deskew_cache: dict = {}  # sweep -> de-skewed points (each sweep de-skewed once)

            def _deskewed(j: int) -> np.ndarray:
                if j in static_cache:
                    return static_cache[j][0]
                if j not in deskew_cache:
                    sj = sweeps[use[j]]
                    deskew_cache[j] = deskew_sweep(sj, link_of(j).T, cfg) if cfg.deskew else sj.points
                return deskew_cache[j]

            def _ground_of(j: int) -> np.ndarray:
                if j not in ground_cache:
                    ground_cache[j] = ground_distance(sweeps[use[j]].points, j)
                return ground_cache[j]
            # the points' times and the de-skew's rate are only read by sfm_view_rotations (a sweep without
            # per-point times would have them computed from every point's azimuth for nothing)
            sector = cfg.deskew and cfg.ours_edge_view_rotation_sfm
            for k in range(min(cfg.ours_edge_images, len(images))):
                jk = int(np.argmin(np.abs(stamps_u - t_img[k])))
                sw = sweeps[use[jk]]
                if jk not in static_cache:
                    pk = _deskewed(jk)  # (a sweep the walker test de-skewed as a neighbour is not de-skewed again)
                    oth, T_oth = _neighbours(sweeps, use, poses, jk, cfg.dynamic_sweep_gap)
                    st = point_motion(sw.points, oth, T_oth) <= cfg.dynamic_dist_m if oth \
                        else np.ones(sw.points.shape[0], bool)
                    static_cache[jk] = (pk, st)
                pk, st = static_cache[jk]
                gd = _ground_of(jk)
                if cfg.dynamic_cluster_speed_mps > 0:
                    if jk not in walk_cache:  # people walking: whole clusters that moved (the point test misses them)
                        walk_cache[jk] = np.zeros(sw.points.shape[0], bool)
                        for gap in range(cfg.dynamic_sweep_gap, 0, -1):  # the widest gap the car's move allows
                            nb = [jk + dj for dj in (-gap, gap) if 0 <= jk + dj < len(use)]
                            T_nb = [inv_T(poses[jk]) @ poses[i] for i in nb]
                            if nb and max(np.linalg.norm(T[:3, 3]) for T in T_nb) <= cfg.dynamic_cluster_max_move_m:
                                break
                        else:
                            nb = []
                        if nb:
                            walk_cache[jk] = moving_clusters(
                                pk, gd > cfg.ground_static_m, [_deskewed(i) for i in nb],
                                [_ground_of(i) > cfg.ground_static_m for i in nb], T_nb,
                                [float(stamps_u[i] - stamps_u[jk]) for i in nb],
                                speed_mps=cfg.dynamic_cluster_speed_mps, max_range_m=cfg.edges.max_range_m + 5.0)
                    st = st & ~walk_cache[jk]
                views.append(EdgeView(ims[k], sw.points, pk, sw.intensity, st | (gd <= cfg.ground_static_m),
                                      inv_T(poses[jk]) @ P_img[k], ring=sw.ring,
                                      ground=gd <= cfg.edges.paint_ground_m if cfg.edges.paint_ground_m > 0 else None,
                                      sweep_stamp_s=float(stamps_u[jk]), image_index=k,
                                      time_s=sweep_times(sw, cfg) if sector else None,
                                      deskew_rate=so3_log(link_of(jk).T[:3, :3]) / cfg.sweep_period_s
                                      if sector else None))
        for v in views:  # each view's LiDAR edges and image edge-distance map (computed once, on first use)
            prepare_view(v, cfg.edges)
        tm["edge_views"] = time.perf_counter() - t_views
        return {"poses": poses, "P_img": P_img, "jr": jr, "ref_sweep": ref_sweep, "link": link, "lid": lid,
                "T_sweep_img": T_sweep_img, "speed": speed, "others": others, "motion": motion, "views": views,
                "min_inliers": min_inliers, "metrics_step": metrics_step}
    with ThreadPoolExecutor(max_workers=1) as pool:  # (leaving the block waits for the thread)
        side = pool.submit(lidar_side)
        # -- SfM
        # ours: SIFT on every frame pair, widest initial pair, stricter ratio test, plus sub-pixel KLT tracks
        # (forward motion leaves the translation direction weakly determined: the bas-relief ambiguity; more
        # and longer precise tracks narrow it)
        sfm_cfg = cfg.ours_sfm if ours else cfg.sfm
        key = "sfm_ours" if ours else "sfm"
        if key not in cache:
            sfm0 = run_sfm(ims, cam, masks, ref=0, cfg=sfm_cfg)
            step = max(1, len(ims) // cfg.dense_refs)
            refs = list(range(0, len(ims), step))[:cfg.dense_refs]
            dense0 = densify(ims, cam, sfm0, masks, sfm_cfg, refs=refs)[0] \
                if sfm0.reprojection_px <= cfg.max_sfm_reprojection_px else None
            cache[key] = (sfm0, dense0)
        t_sfm = time.perf_counter()
    tm["sfm"] = t_sfm - t0
    tm["lidar_wait"] = time.perf_counter() - t_sfm  # (after the SfM, until the LiDAR side was done)
    sfm, dense = cache[key]
    if sfm.reprojection_px > cfg.max_sfm_reprojection_px:
        raise CalibError(f"gate failed: SfM re-projection error {sfm.reprojection_px:.2f} px > "
                         f"{cfg.max_sfm_reprojection_px:.2f} px; calibration rejected (try another stretch)")
    L = side.result()  # (raises what the LiDAR side raised)
    poses, P_img, jr, ref_sweep, link, lid = L["poses"], L["P_img"], L["jr"], L["ref_sweep"], L["link"], L["lid"]
    T_sweep_img, speed, others, motion, views = L["T_sweep_img"], L["speed"], L["others"], L["motion"], L["views"]
    min_inliers, metrics_step = L["min_inliers"], L["metrics_step"]
    # -- metric scale: the SfM camera centres against the LiDAR odometry at the exposures
    scale, scale_rel = metric_scale(sfm.centres(), P_img[:, :3, 3])
    sfm = apply_scale(sfm, scale)
    dense = dense * scale
    t2 = time.perf_counter()
    # -- camera cloud: only points whose triangulation is precise (forward motion: far points ahead have
    # tiny parallax and metre-level depth errors); sigma from the SfM's own re-projection error
    cloud_all = np.concatenate([dense, sfm.points])
    sig = depth_sigma(cloud_all, sfm.centres(), float(cam.K[0, 0]), max(sfm.reprojection_px, 0.2))
    max_sig = cfg.max_point_sigma_m
    keep_s = sig <= max_sig
    cloud_s = cloud_all[keep_s]
    sig_s = sig[keep_s]
    if cloud_s.shape[0] < 500:
        raise CalibError(f"only {cloud_s.shape[0]} camera-cloud points are triangulated to better than "
                         f"{max_sig * 100:.0f} cm: the camera barely moved sideways to the scene "
                         "(drive past objects, not towards them)")
    n_rings, ring_deg = ring_spacing_deg(ref_sweep.points, ref_sweep.ring)
    metrics_pre = {"camera_cloud_points": int(cloud_s.shape[0]), "lidar_rings": n_rings,
                   "lidar_ring_spacing_deg": ring_deg, **metrics_step}
    # -- level both clouds
    Ls = _level(cloud_s, np.array([0.0, -1.0, 0.0]), rng)
    Ll = _level(lid, np.array([0.0, 0.0, 1.0]), rng)
    cs = transform_points(Ls, cloud_s)
    cl = transform_points(Ll, lid)
    # how well the camera cloud's road fixes the tilt, measured on this window: the edge fit's tilt prior
    # (the edges see the tilt weakly, and a fixed 0.3 deg let them pull it 0.5 deg off where the road
    # was within 0.03 deg; on KITTI the road is 3 deg off and its blocks scatter 1-1.5 deg)
    scatter = ground_normal_scatter_deg(cs)
    if ours and cfg.ours_tilt_prior_measured and np.isfinite(scatter):
        cfg = dataclasses.replace(cfg, ours_edge_tilt_prior_deg=float(
            np.clip(scatter, cfg.ours_edge_tilt_prior_min_deg, 10.0)))
    metrics_pre.update({"ground_normal_scatter_deg": scatter, "edge_tilt_prior_deg": cfg.ours_edge_tilt_prior_deg})
    ocfg = dataclasses.replace(cfg.objects, shape_mode="object" if ours else "voxel")
    acfg = dataclasses.replace(cfg.align, verify=ours or cfg.align.verify and solver != "paper",
                               use_z_ratio=False if ours else cfg.align.use_z_ratio)
    A = extract_objects(cs, dataclasses.replace(ocfg, min_voxel_points=max(2, ocfg.min_voxel_points)))
    B = extract_objects(cl, ocfg)
    n_dyn = 0
    if others and solver != "oba":
        dyn = dynamic_objects(B.point_labels, motion, len(B), cfg.dynamic_dist_m)
        n_dyn = int(dyn.sum())
        B = B.subset(~dyn)
    tm["objects"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    metrics = {"sfm_reprojection_px": sfm.reprojection_px, "sfm_t1_reprojection_px": sfm.t1_reprojection_px,
               "sfm_points": int(sfm.points.shape[0]), "dense_points": int(dense.shape[0]),
               "scale_m_per_unit": sfm.unit_m, "scale_rel_sigma": scale_rel, "objects_camera": len(A),
               "objects_lidar": len(B), "objects_dynamic_removed": n_dyn, "speed_mps": speed, **metrics_pre}
    near = np.linalg.norm(cl[:, :2], axis=1) < cfg.objects.radius_m + 10.0
    static_pts = np.ones(cl.shape[0], bool)
    if ours and others:
        # ours: every point that moved between the compensated sweeps leaves the ICP too (not only whole
        # objects): the camera saw the moving cars elsewhere
        # (the road does not move, whatever the nearest-neighbour test says of a sparse head's rings)
        static_pts = (motion <= cfg.dynamic_dist_m) | (np.abs(cl[:, 2]) <= cfg.ground_static_m)
        near &= static_pts
    src = voxel_down(cl[near], 0.1)
    tree = cKDTree(cs)
    nrm, _ = estimate_normals(cs, tree)
    icp = None
    coarse_fit = None  # ours: the chosen coarse candidate's edge fit, when the edges chose it
    if ours:
        # rotation (no guess): Wahba's problem on the two ground normals and the camera trajectory.
        # Camera centre k in the camera-0 frame: c_k = R (q_k + (A_k - I) o), with (A_k, q_k) the LiDAR
        # motion from exposure 0 to k (odometry), o the camera centre in the LiDAR frame (lever arm,
        # from the translation found below; two rounds)
        c = sfm.centres()
        Q = [inv_T(P_img[0]) @ P for P in P_img]
        n_cam, n_lid = Ls[2, :3], Ll[2, :3]
        T_S_L0 = T_sweep_img  # LiDAR at the sweep stamp <- LiDAR at exposure 0
        o = np.zeros(3)
        sig_c = max(cfg.ours_centre_sigma_m, 1e-4)
        t_lev = None
        # only the camera points close to the camera: their depth bias is smallest
        near_c = (np.linalg.norm(cloud_s - c[0], axis=1) <= cfg.ours_icp_range_m) & \
            (sig_s <= cfg.ours_max_point_sigma_m)
        if near_c.sum() < 2000:  # too few precise points: use the whole camera cloud
            near_c = np.ones(cloud_s.shape[0], bool)
        c_tr = c[1:] - np.outer(c[1:] @ n_cam, n_cam) if cfg.ours_trajectory_yaw_only else c[1:]
        for _ in range(3):
            v = np.array([Qk[:3, 3] + (Qk[:3, :3] - np.eye(3)) @ o for Qk in Q[1:]])
            if cfg.ours_trajectory_yaw_only:
                v = v - np.outer(v @ n_lid, n_lid)
            a = np.concatenate([n_cam[None], c_tr])
            b = np.concatenate([n_lid[None], v])
            lv = np.linalg.norm(v, axis=1)
            w = np.concatenate([[1.0 / math.radians(cfg.ours_ground_sigma_deg) ** 2], (lv / sig_c) ** 2])
            R_cl = wahba(a, b, w)
            # levelled: cam_lev = R_lev lid_lev + t_lev
            R_lev = Ls[:3, :3] @ R_cl @ inv_T(T_S_L0)[:3, :3] @ Ll[:3, :3].T
            if t_lev is None:
                # translation: layered bird's-eye cross-correlation of everything above the ground
                # (R_lev lid ~ cam + t'  <=>  t_lev = -t')
                # a zero lever arm puts the LiDAR origin at exposure 0 on the camera centre
                # (cam_lev = R_lev lid_lev + t_lev): the search is about there, as far as the sensors can be apart
                t_zero = Ls[:3, 3] - R_lev @ (Ll @ T_S_L0)[:3, 3]
                t_bev, hit, ratio, peaks = layered_bev_translation(
                    (cl[~B.ground]) @ R_lev.T, cs[~A.ground], 0.0, radius_m=cfg.coarse_radius_m,
                    n_peaks=cfg.ours_coarse_candidates if views else 1, centre=-t_zero)
                t_lev = -t_bev
                metrics.update({"bev_peak_ratio": ratio, "bev_hit_fraction": hit})
                peaks = [p for p in peaks if p[1] >= cfg.ours_coarse_min_score]
                if len(peaks) > 1:
                    # the street repeats itself along its axis (trees, lights, facades at a spacing): fit
                    # each candidate's LiDAR edges to the image edges (yaw and translation, from the
                    # extrinsic it implies) and keep the one whose edges meet best
                    Xc = [inv_T(Ls) @ make_T(R_lev, -tp) @ Ll @ T_S_L0 for tp, _ in peaks]
                    fits = [_rank_fit(views, cam, X_, Ll, link.T, cfg.edges) for X_ in Xc]
                    best_i, ratio_e = _coarse_choice(fits, ratio, min_inliers, cfg)
                    if best_i is not None:
                        t_lev = -peaks[best_i][0]
                        coarse_fit = fits[best_i]
                        # where the edges' choice ended against the highest bird's-eye peak: two distinct
                        # votes that put the camera apart along the street contradict each other
                        metrics.update({"coarse_candidates": len(peaks), "coarse_rank": best_i,
                                        "coarse_edge_inliers": fits[best_i].inliers, "coarse_edge_ratio": ratio_e,
                                        "coarse_bev_disagreement_m": float(np.linalg.norm(
                                            fits[best_i].T[:3, 3] - Xc[0][:3, 3]))})
                    diag.coarse_candidates = list(zip(Xc, fits))
                T_oba_lev = make_T(R_lev, t_lev)
            # translation-only point-to-plane ICP, camera cloud as the source (the rotation is better
            # determined by the ground and the trajectory than by ICP on a street, which is nearly
            # degenerate along its axis)
            icp = icp_translation(cs[near_c][::cfg.ours_icp_stride], nrm[near_c][::cfg.ours_icp_stride],
                                  src @ R_lev.T, t_lev, acfg, info_scale=cfg.ours_icp_stride)
            t_lev = icp.T[:3, 3]
            T_c0_L0 = inv_T(Ls) @ make_T(R_lev, t_lev) @ Ll @ T_S_L0
            o = -T_c0_L0[:3, :3].T @ T_c0_L0[:3, 3]
        metrics["motion_yaw_deg"] = math.degrees(math.atan2(R_lev[1, 0], R_lev[0, 0]))
        # the ICP may slide along a street with few cross-street surfaces: keep the bird's-eye translation
        # when its above-ground fit is better
        lid_in = cl[np.linalg.norm(cl[:, :2], axis=1) < cfg.objects.radius_m]
        lid_in = lid_in[lid_in[:, 2] > 0.3]

        def above_fit(Tl):
            q = transform_points(Tl, lid_in)
            d, nn = tree.query(q, k=1, distance_upper_bound=0.5, workers=-1)
            okq = np.isfinite(d)
            if okq.sum() < 20:
                return np.inf
            return float(np.median(np.abs(np.einsum("ij,ij->i", q[okq] - cs[nn[okq]], nrm[nn[okq]]))))
        T_icp_lev, T_bev_lev = make_T(R_lev, t_lev), make_T(R_lev, T_oba_lev[:3, 3])
        f_icp, f_bev = above_fit(T_icp_lev), above_fit(T_bev_lev)
        metrics.update({"above_fit_icp_m": f_icp, "above_fit_bev_m": f_bev})
        icp = dataclasses.replace(icp, T=T_icp_lev if f_icp <= f_bev else T_bev_lev)
    else:
        h: HoughResult = hough_align(A, B, acfg)
        T_oba_lev = h.T
        metrics.update({"objects_matched": h.n_matches, "hough_votes": h.votes})
    diag.T_oba = inv_T(Ls) @ T_oba_lev @ Ll @ T_sweep_img
    # -- ICP
    T_lev = icp.T if icp is not None else T_oba_lev
    if solver != "oba" and not ours:
        icp = icp_point_to_plane(src, cs, T_oba_lev, acfg, dst_tree=tree, dst_normals=nrm)
        T_lev = icp.T
    scale_icp = icp.scale if icp is not None else 1.0
    T_chain = inv_T(Ls) @ T_lev @ Ll
    # ICP geometry in camera coordinates: q_cam = Ls^-1 (s (T_lev Ll p)); pixels invariant to s about the
    # camera centre only if Ls keeps the camera at the origin (rotation + z shift): undo the shift
    Ls_inv = inv_T(Ls)

    def chain(p):
        q = transform_points(T_lev @ Ll, p) * scale_icp
        return transform_points(Ls_inv, q)

    diag.T_icp = T_chain @ T_sweep_img
    tm["align"] = time.perf_counter() - t3
    # -- gates: partial Hausdorff distance on the registered overlap
    in_r = np.linalg.norm(cl[:, :2], axis=1) < cfg.objects.radius_m
    ok, dist_m = _registered_distances(transform_points(Ls, chain(lid[in_r])), tree, cs, nrm, cfg.hausdorff_quantile)
    if dist_m is None:
        raise CalibError(f"gate failed: only {int(ok.sum())} LiDAR points lie on the camera cloud after "
                         "registration; calibration rejected")
    metrics.update(dist_m)
    diag.registered = {"points": lid[in_r], "static": static_pts[in_r], "tree": tree, "cloud": cs, "normals": nrm,
                       "sigma": sig_s, "Ls": Ls, "T_sweep_img": T_sweep_img}
    # -- final PnP (the paper: object centroids through the chain; ours: every overlapping point)
    t4 = time.perf_counter()
    if solver in ("paper", "ours"):
        if solver == "paper":
            pl = inv_T(Ll) @ np.concatenate([B.centroids.T, np.ones((1, len(B)))])
            pts = pl[:3].T
        else:
            pts = lid[in_r][ok]
            if pts.shape[0] > 3000:
                pts = pts[rng.choice(pts.shape[0], 3000, replace=False)]
        qc = chain(pts)
        uv, z = _ideal_project(cam.K, np.eye(4), qc)
        vis = (z > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if vis.sum() >= 6:
            T_pnp, res_px = final_pnp(pts[vis], uv[vis], cam, T_chain)
            metrics["pnp_points"] = int(vis.sum())
            metrics["pnp_residual_px"] = float(np.sqrt(np.mean(res_px ** 2)))
            T_final_sweep = T_pnp
        else:
            metrics["pnp_points"] = int(vis.sum())
            T_final_sweep = T_chain
    else:
        T_final_sweep = T_chain
    T_final = T_final_sweep @ T_sweep_img
    # driving direction in the camera frame (LiDAR x motion mapped into the camera)
    vdir = T_final[:3, :3] @ (link.T[:3, 3] / max(np.linalg.norm(link.T[:3, 3]), 1e-9))
    edge = pe = kind_fits = None
    diag.T_pre_edge = T_final
    if views and ours and cfg.ours_edge_view_rotation_sfm:
        views, metrics["edge_view_sfm_rotation_deg"] = sfm_view_rotations(
            views, sfm.poses, np.array([f.stamp_s - cfg.time_offset_s for f in images]), T_final[:3, :3])
    if views:
        t5 = time.perf_counter()
        # the tilt and height priors (ground planes) stay about the clouds' estimate for every start, the
        # height's where the registration fixed it
        axes_centre = _drive_axes(T_final, Ll, link.T)
        pivot = None
        if cfg.ours_height_prior_at_pivot:
            reg_in = lid[in_r][ok]
            pivot = _height_pivot(transform_points(Ls @ T_final @ inv_T(T_sweep_img), reg_in),
                                  transform_points(T_final @ inv_T(T_sweep_img), reg_in), tree, nrm)
        if pivot is not None:
            metrics["edge_height_pivot_m"] = float(np.linalg.norm(pivot))

        def first_fit(views_):
            """The edge fit from the clouds' estimate; when the edges chose the coarse translation, their
            own fit from it is a second start (the clouds' ICP may have slid away from it along the
            street)."""
            metrics.pop("edge_from_coarse_fit", None)
            f = _edge_fit(views_, cam, T_final, axes_centre, cfg, T_final, pivot)
            if coarse_fit is not None:
                f2 = _edge_fit(views_, cam, coarse_fit.T, _drive_axes(coarse_fit.T, Ll, link.T), cfg, T_final,
                               pivot)
                if f2 is not None and (f is None or f2.inliers > f.inliers):
                    f = f2
                    metrics["edge_from_coarse_fit"] = 1
            return f

        pe = first_fit(views)
        tm["edge_first_fit"] = time.perf_counter() - t5
        diag.edge_views_with_paint = views
        if pe is not None and cfg.ours_paint_min_lift > 0:
            # paint edges that meet the image no better than chance only pull the fit, and a handful of them
            # claims a pitch the fit cannot know: redo it without them
            ki = edge_kind_inliers(views, cam, pe.T, cfg.edges)
            metrics.update({"edge_silhouette_inliers": ki["silhouette"], "edge_paint_inliers": ki["paint"],
                            "edge_paint_points": ki["n_paint"], "edge_chance": ki["chance"]})
            need = ki["chance"] + cfg.ours_paint_min_lift * (ki["silhouette"] - ki["chance"])
            drop = ki["n_paint"] > 0 and ki["n_silhouette"] >= cfg.edges.min_points and \
                (not (ki["paint"] >= need) or ki["n_paint"] < cfg.ours_paint_min_points)
            metrics["edge_paint_dropped"] = int(drop)
            if drop:
                views = without_paint(views, cfg.edges)
                pe = first_fit(views)
        diag.edge_views, diag.edge_axes = views, axes_centre
        t6 = time.perf_counter()
        if pe is not None and cfg.ours_edge_restart_yaw_deg > 0:
            pe, metrics["edge_restart_yaw_deg"] = _edge_restarts(views, cam, pe, Ll, link.T, cfg, T_final, pivot)
        tm["edge_restarts"], t6 = time.perf_counter() - t6, time.perf_counter()
        spread = None
        if pe is not None and (cfg.ours_edge_basin_along_m > 0 or cfg.ours_edge_basin_side_m > 0 or
                               cfg.ours_edge_basin_tilt_sigmas > 0):
            pe1 = pe
            pe, spread, metrics["edge_basin_fits"], metrics["edge_basin_starts"] = _edge_basins(
                views, cam, pe, Ll, link.T, cfg, T_final, pivot)
            metrics["edge_basin_moved"] = int(pe is not pe1)
        tm["edge_basins"], t6 = time.perf_counter() - t6, time.perf_counter()
        if pe is not None and cfg.ours_edge_jackknife:
            cj, n_jk = _jackknife_cov(views, cam, pe, _drive_axes(pe.T, Ll, link.T), cfg, T_final, pivot)
            metrics["edge_jackknife_refits"] = n_jk
            if cj is not None:
                pe = _widen(pe, cj, metrics, "edge_jackknife_inflation")
        if pe is not None and cfg.ours_edge_block_jackknife >= 3:
            cb, n_b = _block_jackknife_cov(views, cam, pe, _drive_axes(pe.T, Ll, link.T), cfg, T_final, pivot)
            metrics["edge_block_refits"] = n_b
            if cb is not None:
                pe = _widen(pe, cb, metrics, "edge_block_inflation")
        if pe is not None and spread is not None:
            pe = _widen(pe, spread, metrics, "edge_basin_inflation")
        tm["edge_jackknife"], t6 = time.perf_counter() - t6, time.perf_counter()
        if pe is not None and cfg.ours_edge_kind_check:
            kind_fits, kind_m = _kind_fits(views, cam, pe, _drive_axes(pe.T, Ll, link.T), cfg, T_final, pivot)
            metrics.update(kind_m)
        tm["edge_kind"] = time.perf_counter() - t6
        diag.edge_pose = pe
        tm["edges"] = time.perf_counter() - t5
        if pe is not None:
            metrics.update({"edge_points": pe.n_points, "edge_views": pe.n_views, "edge_cost0_px": pe.cost0,
                            "edge_cost_px": pe.cost, "edge_inliers0": pe.inliers0, "edge_inliers": pe.inliers,
                            "edge_dispersion": pe.dispersion,
                            # how far the edges moved the extrinsic from the clouds' estimate (the fit may
                            # have started elsewhere: the coarse candidate's fit, a restart)
                            "edge_delta_rot_deg": float(np.degrees(np.linalg.norm(
                                so3_log(pe.T[:3, :3] @ T_final[:3, :3].T)))),
                            "edge_delta_norm_m": float(np.linalg.norm(pe.T[:3, 3] - T_final[:3, 3]))})
            metrics.update(_prior_move(pe.T, T_final, axes_centre[1], cfg, pivot))
            T_final = pe.T
            # the registered clouds' distances again, now through the refined extrinsic
            metrics["hausdorff_before_edges_m"] = metrics.get("hausdorff_m", float("nan"))
            metrics["hausdorff_above_ground_before_edges_m"] = metrics.get("hausdorff_above_ground_m", float("nan"))
            _, dist_e = _registered_distances(transform_points(Ls @ T_final @ inv_T(T_sweep_img), lid[in_r]),
                                              tree, cs, nrm, cfg.hausdorff_quantile)
            if dist_e is not None:
                metrics["hausdorff_m"] = dist_e["hausdorff_m"]
                metrics["hausdorff_above_ground_m"] = dist_e["hausdorff_above_ground_m"]
            # the same with the camera cloud's metric scale free about the first camera (the odometry
            # scale is off by up to ~1.5 % at speed): the best over +-ours_hausdorff_scale_range
            q_cam = transform_points(T_final @ inv_T(T_sweep_img), lid[in_r])
            best_sf = (np.inf, 1.0, np.nan)
            sr = cfg.ours_hausdorff_scale_range
            # only points within 0.5 m of the camera cloud at some scale can count: |s q - c| <= 0.5 implies
            # |q - c| <= 0.5 + |s - 1| |q| (the same distances, from far fewer queries)
            rq = np.linalg.norm(q_cam, axis=1)
            d1, _ = tree.query(transform_points(Ls, q_cam), k=1, workers=-1,
                               distance_upper_bound=0.5 + sr * float(rq.max(initial=0)))
            q_near = q_cam[d1 <= 0.5 + sr * rq]
            for sc in np.linspace(1.0 - sr, 1.0 + sr, 2 * int(round(sr / 0.0025)) + 1):  # 0.25 % steps
                _, dsf = _registered_distances(transform_points(Ls, q_near * sc), tree, cs, nrm, cfg.hausdorff_quantile)
                if dsf is not None and dsf["hausdorff_m"] < best_sf[0]:
                    best_sf = (dsf["hausdorff_m"], float(sc), dsf["hausdorff_above_ground_m"])
            metrics.update({"hausdorff_scale_free_m": best_sf[0], "hausdorff_scale_free_above_ground_m": best_sf[2],
                            "hausdorff_best_scale": best_sf[1]})
    if ours and cfg.ours_edge_refine and cfg.ours_edge_mode == "translation":
        t5 = time.perf_counter()
        T_si = [inv_T(poses[jr]) @ P for P in P_img[:cfg.ours_edge_images]]
        edge = refine_translation(ims[:cfg.ours_edge_images], cam, ref_sweep.points, lid, ref_sweep.intensity,
                                  static_pts, T_final, T_si, vdir, cfg.edges, full=cfg.ours_edge_full,
                                  ring=ref_sweep.ring)
        tm["edges"] = time.perf_counter() - t5
        applied = False
        if edge is not None:
            gain = (edge.cost0 - edge.cost) / max(edge.cost0, 1e-9)
            # keep it only when it clearly improves the score and the images agree
            applied = edge.tstat >= cfg.ours_edge_min_t and edge.sigma_m <= cfg.ours_edge_max_spread_m
            metrics.update({"edge_points": edge.n_points, "edge_cost0_px": edge.cost0, "edge_cost_px": edge.cost,
                            "edge_gain": gain, "edge_t": edge.tstat, "edge_delta_along_m": float(edge.delta @ vdir),
                            "edge_delta_norm_m": float(np.linalg.norm(edge.delta)), "edge_sigma_m": edge.sigma_m})
            if applied:
                T_final = T_final.copy()
                T_final[:3, 3] += edge.delta
        metrics["edge_applied"] = int(applied)
        if not applied:
            edge = None
    diag.T_final = T_final
    tm["pnp"] = time.perf_counter() - t4
    tm["total"] = time.perf_counter() - t0
    metrics["runtime_s"] = tm["total"]
    # where the time went (s): the stages, the edge views (de-skew, motion tests) and the edge fit's parts
    metrics.update({f"time_{k}_s": float(v) for k, v in tm.items() if k != "total"})
    # -- covariance: ICP information (levelled camera-cloud space) mapped to the camera frame,
    # inflated for correlated residuals, plus the scale and the clock priors
    cov = np.zeros((6, 6))
    pose_edge = ours and cfg.ours_edge_refine and cfg.ours_edge_mode == "pose"
    if pe is not None:
        # the edge fit's own covariance (dispersion-scaled, with the tilt prior), a floor for what the
        # images share (the LiDAR edge placement, the camera model), and the clock along the drive
        cov = pe.cov.copy()
        floor = np.zeros((6, 6))
        px = cfg.ours_edge_floor_fx_px / cam.fx     # the floors scale with the pixel's angle
        floor[:3, :3] = np.eye(3) * math.radians(cfg.ours_edge_floor_deg * px) ** 2
        floor[3:, 3:] = np.eye(3) * (cfg.ours_edge_floor_m * px) ** 2
        clock = np.zeros((6, 6))
        clock[3:, 3:] = np.outer(vdir, vdir) * (speed * cfg.time_offset_sigma_s) ** 2
        cov += floor + clock
        # what every window of the drive shares, which fusing windows cannot shrink
        diag.shared_cov = clock + cfg.fuse_edge_floor_shared * floor
    elif icp is not None:
        sig2 = icp.residual_sigma_m ** 2
        try:
            if ours:
                # rotation from Wahba (ground normals: tilt; trajectory chord: yaw), translation from the
                # translation-only ICP information
                C_lev = np.zeros((6, 6))
                chord = max(float(np.linalg.norm(sfm.centres()[-1] - sfm.centres()[0])), 0.1)
                s_tilt = math.radians(cfg.ours_ground_sigma_deg)
                C_lev[:3, :3] = np.diag([s_tilt ** 2, s_tilt ** 2, (cfg.ours_centre_sigma_m / chord) ** 2])
                C_lev[3:, 3:] = np.linalg.inv(icp.H[:3, :3]) * sig2 * cfg.covariance_inflation
            else:
                C_lev = np.linalg.inv(icp.H[:6, :6]) * sig2 * cfg.covariance_inflation
        except np.linalg.LinAlgError:
            C_lev = np.eye(6)
        Rs, ts = Ls[:3, :3], Ls[:3, 3]
        A_ = np.zeros((6, 6))
        A_[:3, :3] = Rs.T
        A_[3:, :3] = -skew(T_chain[:3, 3] + Rs.T @ ts) @ Rs.T
        A_[3:, 3:] = Rs.T
        cov += A_ @ C_lev @ A_.T
    else:
        cov[:3, :3] += np.eye(3) * math.radians(cfg.align.yaw_step_deg) ** 2
        cov[3:, 3:] += np.eye(3) * (cfg.align.trans_step_m / 2) ** 2
    if pe is None:
        # scale: a relative error e moves the registered translation by about e * |t|
        tcam = T_final[:3, 3]
        cov[3:, 3:] += np.outer(tcam, tcam) * scale_rel ** 2 + np.eye(3) * (scale_rel * 0.5) ** 2 * 0.01
        # clock: translation along the driving direction (the same offset in every window)
        diag.shared_cov = np.zeros((6, 6))
        diag.shared_cov[3:, 3:] = np.outer(vdir, vdir) * (speed * cfg.time_offset_sigma_s) ** 2
        cov[3:, 3:] += diag.shared_cov[3:, 3:]
    if ours and pe is None:
        # the camera cloud's depth ahead (what fixes the translation along a street) carries a bias
        # correlated through the SfM poses that the ICP information does not see
        # (after the edge refinement: its per-image spread plus a floor for what the spread does not see, the
        # coupling with the rotation error above all)
        s_along = math.hypot(edge.sigma_m, cfg.ours_edge_sigma_floor_m) if edge is not None \
            else cfg.ours_along_motion_sigma_m
        cov[3:, 3:] += np.outer(vdir, vdir) * s_along ** 2 + np.eye(3) * cfg.ours_translation_floor_m ** 2
    metrics["icp_rms_m"] = float(icp.rms_m) if icp is not None else float("nan")
    metrics["icp_scale"] = float(scale_icp)
    if pe is not None and kind_fits is not None:
        # where silhouettes and paint disagree, the covariance is at least the paint fit's offset from the
        # result (or both fits'); computed always, so that the benchmark can judge the rule offline
        kind_T = [f.T for f in kind_fits]
        kind_cov = kind_widened(cov, T_final, kind_T if cfg.ours_edge_kind_widen == "both" else kind_T[1:])
        diag.edge_kind_T, diag.edge_kind_cov = kind_T, kind_cov
        pred_kind = predicted_projection_px(cam, T_final, kind_cov, ref_sweep.points)
        metrics["predicted_x_px_kind"], metrics["predicted_y_px_kind"] = pred_kind
        metrics["edge_kind_widened"] = int(metrics["edge_kind_chi2"] > cfg.ours_edge_kind_chi2)
        if metrics["edge_kind_widened"]:
            cov = kind_cov
    pred = pred_kind if metrics.get("edge_kind_widened") else predicted_projection_px(cam, T_final, cov,
                                                                                       ref_sweep.points)
    metrics["predicted_x_px"], metrics["predicted_y_px"] = pred
    diag.metrics = metrics
    haus = metrics["hausdorff_m"]
    ha = metrics["hausdorff_above_ground_m"]
    free = pe is not None and cfg.ours_hausdorff_scale_free and "hausdorff_scale_free_m" in metrics
    if free:
        haus, ha = metrics["hausdorff_scale_free_m"], metrics["hausdorff_scale_free_above_ground_m"]
    how = f" (camera-cloud scale free: best at {metrics['hausdorff_best_scale']:.4f})" if free else ""
    max_h = cfg.ours_max_hausdorff_m if pe is not None else cfg.max_hausdorff_m
    if not (haus <= max_h) and solver != "oba":
        raise CalibError(f"gate failed: Hausdorff distance {haus * 100:.1f} cm between the registered clouds{how} > "
                         f"{max_h * 100:.1f} cm: the camera's and the LiDAR's clouds do not agree in shape "
                         "(moving traffic, or a registration that slid along the street); calibration rejected "
                         "(drive past parked cars, poles, trunks and facades close to the road, away from "
                         "traffic)")
    ambiguous = translation_ambiguity(cfg, metrics) if ours else ""
    try:
        _later_gates(cfg, metrics, ours, pose_edge, pe, edge, min_inliers, metrics_step, pred, ha, how)
    except CalibError:
        if ambiguous:  # the first gate that failed is the one named
            raise CalibError(ambiguous) from None
        raise
    diag.metrics = metrics
    if ambiguous:
        raise AmbiguousWindow(ambiguous, T_final, cov, metrics)
    return T_final, cov, metrics


def translation_ambiguity(cfg: TargetlessConfig, metrics: dict) -> str:
    """Why the translation along the street is not settled ("" when it is), from the coarse search's
    figures in ``metrics``. Settled: the candidate the image edges chose meets them clearly better than
    anywhere else, or (the highest peak kept) the bird's-eye peak stands out; and when the bird's-eye peak
    stands out, the edges' choice ends within ``ours_coarse_agree_m`` of it (two distinct votes for places
    metres apart mean one of them matched a repeated structure)."""
    edge_distinct = metrics.get("coarse_edge_ratio", 0.0) >= cfg.ours_min_coarse_edge_ratio
    bev_stands_out = metrics.get("bev_peak_ratio", np.inf) >= cfg.ours_min_bev_peak_ratio
    apart = metrics.get("coarse_bev_disagreement_m", 0.0)
    if bev_stands_out and apart > cfg.ours_coarse_agree_m:
        return (f"gate failed: the image edges and the clouds disagree along the street (the bird's-eye peak "
                f"stands out by {metrics['bev_peak_ratio']:.2f}, but the edges meet best {apart:.2f} m from it, "
                f"{metrics.get('coarse_edge_ratio', float('nan')):.2f} times better than elsewhere): one of them "
                "matched a repeated structure (foliage, a facade's windows); calibration rejected (drive past "
                "poles, trunks and signs close to the road)")
    if edge_distinct or (bev_stands_out and metrics.get("coarse_rank", 0) == 0):
        return ""
    er = f", image-edge inliers chosen / best elsewhere {metrics['coarse_edge_ratio']:.2f} < " \
         f"{cfg.ours_min_coarse_edge_ratio:.2f}" if "coarse_edge_ratio" in metrics else ""
    return (f"gate failed: the translation search has no distinct peak (best / best elsewhere "
            f"{metrics['bev_peak_ratio']:.2f} < {cfg.ours_min_bev_peak_ratio:.2f}{er}): the street "
            "looks the same along its axis; calibration rejected (drive past poles, trunks, signs)")


def _later_gates(cfg: TargetlessConfig, metrics: dict, ours: bool, pose_edge: bool, pe, edge, min_inliers: float,
                 metrics_step: dict, pred: tuple, ha: float, how: str) -> None:
    """The gates after the distinct-peak one (raise :class:`CalibError` with the first that fails)."""
    if ours and not (ha <= cfg.ours_max_hausdorff_above_ground_m):
        raise CalibError(f"gate failed: Hausdorff distance above the ground {ha * 100:.1f} cm{how} > "
                         f"{cfg.ours_max_hausdorff_above_ground_m * 100:.1f} cm (the poles, trunks and facades "
                         "do not meet; the registration slid along the street); calibration rejected")
    if ours and pose_edge and cfg.ours_require_edge and pe is None:
        raise CalibError("gate failed: too few LiDAR edges (silhouettes of poles, trunks, cars; road paint) are "
                         f"seen in the images (at least {cfg.edges.min_points} over 2 or more images needed) to "
                         "refine the extrinsic on them; calibration rejected (drive past poles, trunks, parked "
                         "cars and road paint close to the camera)")
    if ours and pe is not None and (pe.n_views < cfg.ours_min_edge_views or pe.inliers < min_inliers):
        step_note = f" for a column step of {metrics_step['edge_step_px']:.1f} px" \
            if min_inliers < cfg.ours_min_edge_inliers else ""
        raise CalibError(f"gate failed: the LiDAR edges do not meet the image edges well enough "
                         f"({pe.inliers * 100:.0f} % within 1.5 px, >= {min_inliers * 100:.0f} % "
                         f"needed{step_note}, over {pe.n_views} images, >= {cfg.ours_min_edge_views} needed); "
                         "calibration rejected (drive past poles, trunks, parked cars and road paint close to "
                         "the camera)")
    if ours and not pose_edge and cfg.ours_edge_refine and cfg.ours_require_edge and edge is None:
        why = "no usable edges" if "edge_t" not in metrics else (
            f"gain t = {metrics['edge_t']:.1f} (>= {cfg.ours_edge_min_t:.1f} needed), per-image spread "
            f"{metrics['edge_sigma_m'] * 100:.1f} cm (<= {cfg.ours_edge_max_spread_m * 100:.1f} cm needed)")
        raise CalibError("gate failed: the image edges do not confirm the translation along the driving "
                         f"direction ({why}); without them a street leaves it uncertain by about "
                         f"{cfg.ours_along_motion_sigma_m * 100:.0f} cm; calibration rejected (drive past "
                         "poles, trunks, parked cars and road paint close to the camera)")
    if ours and not (max(pred) <= cfg.ours_max_predicted_px):
        raise CalibError(f"gate failed: the result is not certain enough (its covariance predicts a mean "
                         f"projection error of {pred[0]:.1f} / {pred[1]:.1f} px in x / y > "
                         f"{cfg.ours_max_predicted_px:.1f} px); calibration rejected (drive past more poles, "
                         "trunks and facades close to the road, or a longer stretch)")
    if ours and pe is not None and not (metrics["edge_prior_conflict"] <= cfg.ours_max_prior_conflict):
        raise CalibError(f"gate failed: the image edges pull the camera's tilt "
                         f"{metrics['edge_prior_tilt_move_deg']:.2f} deg and its height "
                         f"{metrics['edge_prior_height_move_m'] * 100:+.1f} cm away from where the ground planes "
                         f"put them (squared, in units of the priors' {cfg.ours_edge_tilt_prior_deg:.2f} deg / "
                         f"{cfg.ours_edge_height_prior_m * 100:.1f} cm: {metrics['edge_prior_conflict']:.1f} > "
                         f"{cfg.ours_max_prior_conflict:.1f}): the ground planes and the image edges disagree; "
                         "calibration rejected (drive a stretch where the road ahead is open and flat)")


def predicted_projection_px(cam, T: np.ndarray, cov: np.ndarray, points: np.ndarray,
                            max_points: int = 2000, samples: int = 64) -> tuple[float, float]:
    """Mean absolute projection error in x and y over the LiDAR points in view that the covariance
    ``cov`` of ``T`` predicts: the benchmark's own figure (x_error_px / y_error_px), averaged over
    ``samples`` extrinsics drawn from N(T, cov) and projected through the camera's distortion model,
    each taken as the truth in turn. ``cov`` is over (rotation vector, translation) of ``T`` perturbed on
    the left (camera frame). Drawn, not linearised: the mean is carried by the points a few metres from
    the camera near the image border, whose error grows faster than linearly with a translation error
    of several centimetres (a linearised figure predicted 1.1 px for a simulated window 20 px off)."""
    P = np.asarray(points, float)[:, :3]
    q0 = transform_points(T, P)
    uv0, _ = cam.project(q0)
    # in front of T's camera and not far outside its image (a sample's view is tested per draw)
    keep = (q0[:, 2] > 0.1) & np.all(np.isfinite(uv0), axis=1) & \
        (uv0[:, 0] > -0.5 * cam.width) & (uv0[:, 0] < 1.5 * cam.width) & \
        (uv0[:, 1] > -0.5 * cam.height) & (uv0[:, 1] < 1.5 * cam.height)
    P, uv0 = P[keep], uv0[keep]
    if P.shape[0] == 0:
        return float("inf"), float("inf")
    if P.shape[0] > max_points:
        idx = np.linspace(0, P.shape[0] - 1, max_points).astype(int)
        P, uv0 = P[idx], uv0[idx]
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    L = V * np.sqrt(np.maximum(w, 0.0))
    rng = np.random.default_rng(0)
    ex, ey = [], []
    for _ in range(samples):
        e = L @ rng.normal(size=6)
        Ts = make_T(so3_exp(e[:3]) @ T[:3, :3], T[:3, 3] + e[3:])
        uv, ok = cam.project(transform_points(Ts, P))
        if not np.any(ok):
            continue
        d = np.abs(uv[ok] - uv0[ok])
        ex.append(d[:, 0].mean())
        ey.append(d[:, 1].mean())
    if not ex:
        return float("inf"), float("inf")
    return float(np.mean(ex)), float(np.mean(ey))


__all__ = ["SOLVERS", "TargetlessCalibrator", "TargetlessConfig", "WindowDiagnostics", "calibrate_window",
           "deskew_sweep", "predicted_projection_px"]
