import os
import stat

import numpy as np
import pytest

from lidar_cam_calib.core.geometry import inv_T, make_T, R_from_quat, R_from_rpy
from lidar_cam_calib.core.result import CalibrationResult, ResultFileError, save_if_better, write_atomic


def make_result(sigma_rad=1e-3, sigma_m=1e-3):
    T = make_T(R_from_rpy(0.01, -0.02, 1.5), [0.1, -0.2, 0.3])
    cov = np.diag([sigma_rad**2] * 3 + [sigma_m**2] * 3)
    return CalibrationResult("lrf", "laser", "camera_optical", T, cov,
                             metrics={"point_to_line_mm": np.float64(1.5), "arr": np.arange(3)},
                             observations_used=4, input_topics={"scan": "/scan"}, stamps=[1.0, 2.0],
                             solver="ours")


def test_yaml_roundtrip():
    r = make_result()
    r2 = CalibrationResult.from_yaml(r.to_yaml())
    np.testing.assert_allclose(r2.T_child_parent, r.T_child_parent, atol=1e-15)
    np.testing.assert_allclose(r2.covariance, r.covariance)
    assert r2.metrics["point_to_line_mm"] == 1.5 and r2.metrics["arr"] == [0, 1, 2]
    assert (r2.parent_frame, r2.child_frame, r2.observations_used, r2.solver) == ("laser", "camera_optical", 4, "ours")


def test_tf_meaning_is_child_pose_in_parent():
    """TransformStamped(frame_id=parent, child_frame_id=child) must carry the
    child's pose in the parent: it maps child coordinates into the parent."""
    r = make_result()
    t, q = r.tf_translation_rotation()
    T_parent_child = make_T(R_from_quat(q), t)
    p_child = np.array([0.3, -0.1, 2.0])
    p_parent = T_parent_child[:3, :3] @ p_child + T_parent_child[:3, 3]
    # and the calibration maps the parent point back into the child frame
    np.testing.assert_allclose(r.R @ p_parent + r.t, p_child, atol=1e-12)
    # the child's origin sits at -R^T t in the parent
    np.testing.assert_allclose(t, inv_T(r.T_child_parent)[:3, 3])


def test_sigma_from_covariance():
    r = make_result(np.radians(0.1), 0.002)
    rs, ts = r.sigma()
    assert rs == pytest.approx(0.1) and ts == pytest.approx(2.0)


def test_save_if_better_keeps_better_and_bak(tmp_path):
    path = str(tmp_path / "sub" / "calib.yaml")
    good = make_result(1e-3, 1e-3)
    worse = make_result(1e-2, 1e-2)
    written, _ = save_if_better(good, path)
    assert written and os.path.exists(path)
    written, why = save_if_better(worse, path)
    assert not written and "better" in why
    assert CalibrationResult.load(path).sigma() == pytest.approx(good.sigma())
    better = make_result(5e-4, 5e-4)
    written, _ = save_if_better(better, path)
    assert written and os.path.exists(path + ".bak")
    assert CalibrationResult.load(path + ".bak").sigma() == pytest.approx(good.sigma())
    # force overrides the comparison
    written, _ = save_if_better(worse, path, force=True)
    assert written


def test_unwritable_path_is_a_clear_error_and_keeps_old(tmp_path):
    if os.geteuid() == 0:
        # root ignores permissions: use a path under a regular file instead
        blocker = tmp_path / "file"
        blocker.write_text("x")
        with pytest.raises(ResultFileError, match="cannot write result"):
            write_atomic(str(blocker / "calib.yaml"), "a: 1\n")
        return
    d = tmp_path / "ro"
    d.mkdir()
    (d / "calib.yaml").write_text("old")
    d.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        with pytest.raises(ResultFileError):
            write_atomic(str(d / "calib.yaml"), "new")
        assert (d / "calib.yaml").read_text() == "old"
    finally:
        d.chmod(stat.S_IRWXU)


def test_corrupt_file_is_reported():
    with pytest.raises(ResultFileError):
        CalibrationResult.from_yaml("- just\n- a list\n")
