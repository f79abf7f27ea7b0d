"""The target-less pipeline on one window of the real KITTI sample (skips when the folder is absent).

The window is judged against the official calibration: a published result must be close to it and
carry it inside its covariance; a refused one must name the gate that refused it."""
import os

import pytest
from conftest import SHARED_DATA

from lidar_cam_calib.bench.targetless import kitti_window

KITTI = os.path.join(SHARED_DATA, "kitti_2011_09_26_seq_dev")
needs_kitti = pytest.mark.skipif(not os.path.isdir(KITTI), reason=f"KITTI sample not present at {KITTI}")


@needs_kitti
def test_one_kitti_window_is_right_or_refused_with_its_gate(tmp_path):
    out = kitti_window(KITTI, start=0, solvers=("ours",), overlay=str(tmp_path / "kitti.png"), perturb=2)
    r = out["solvers"]["ours"]
    # whatever the outcome, the overlay shows it (official calibration above, the estimate below)
    assert (tmp_path / "kitti.png").stat().st_size > 10_000
    m = r.get("metrics", {})
    if "edge_paint_inliers" in m:
        # KITTI's reflectance steps meet the image edges about as often as chance: the fit leaves them out
        assert abs(m["edge_paint_inliers"] - m["edge_chance"]) < 0.05 and m["edge_paint_dropped"] == 1, m
        # the edge stage alone, started at the official calibration and near it, stays near it
        pz = out["perturbed_edge_starts"]
        assert pz["from_official"]["rotation_error_deg"] < 0.5 and pz["from_official"]["translation_error_mm"] < 100
        assert pz["levels"][-1]["converged"] >= 1, pz["levels"][-1]
    if not r["accepted"]:
        assert "gate failed" in r["reason"] or "ICP" in r["reason"], r["reason"]
        # the SfM itself works on the real images: the paper's 2 px gate passes
        assert r["metrics"]["sfm_reprojection_px"] < 2.0
        return
    assert r["rotation_error_deg"] < 0.5 and r["translation_error_mm"] < 100.0, r
    assert r["mahalanobis2"] < 22.5  # chi-square, 6 dof, 99.9 %
