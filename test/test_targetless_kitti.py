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
        pz = out["perturbed_edge_starts"]
        # at the official calibration the road's paint edges (windowed intensity steps on the ground plane)
        # meet the image edges well above chance, as often as the silhouettes (each neighbour step anywhere,
        # KITTI's texture, cars and hedges, met them at chance: 16.6 % against 15.9 %)
        ki = pz["edge_kinds_at_official"]
        assert ki["n_paint"] >= 100 and ki["paint"] > ki["chance"] + 0.1, ki
        assert ki["paint"] > 0.8 * ki["silhouette"], ki
        # the edge stage alone, started at the official calibration and near it, stays near it
        assert pz["from_official"]["rotation_error_deg"] < 0.5 and pz["from_official"]["translation_error_mm"] < 100
        assert pz["levels"][-1]["converged"] >= 1, pz["levels"][-1]
    if not r["accepted"]:
        assert "gate failed" in r["reason"] or "ICP" in r["reason"], r["reason"]
        # the SfM itself works on the real images: the paper's 2 px gate passes
        assert r["metrics"]["sfm_reprojection_px"] < 2.0
        return
    assert r["rotation_error_deg"] < 0.5 and r["translation_error_mm"] < 100.0, r
    assert r["mahalanobis2"] < 22.5  # chi-square, 6 dof, 99.9 %
