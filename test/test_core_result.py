import os
import stat

import numpy as np
import pytest

from lidar_cam_calib.core.geometry import inv_T, make_T, R_from_quat, R_from_rpy
from lidar_cam_calib.core.result import (CalibrationResult, CalibrationSet, ResultFileError, check_output_path,
                                         write_atomic)


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


def test_is_better_than_compares_both_sigmas():
    good, worse, better = make_result(1e-3, 1e-3), make_result(1e-2, 1e-2), make_result(5e-4, 5e-4)
    assert good.is_better_than(worse) and not worse.is_better_than(good)
    assert better.is_better_than(good) and good.is_better_than(None)
    assert not make_result(5e-4, 2e-3).is_better_than(good)   # one axis worse is worse


def test_write_atomic_keeps_bak_and_mode_follows_umask(tmp_path):
    path = str(tmp_path / "sub" / "calib.yaml")
    old = os.umask(0o027)
    try:
        write_atomic(path, "a: 1\n")
        write_atomic(path, "a: 2\n")
    finally:
        os.umask(old)
    assert open(path).read() == "a: 2\n" and open(path + ".bak").read() == "a: 1\n"
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o640


@pytest.mark.parametrize("kind", ["dir", "proc", "dev"])
def test_output_path_must_be_a_regular_file(tmp_path, kind):
    target = {"dir": str(tmp_path), "proc": "/proc/self/status", "dev": "/dev/null"}[kind]
    with pytest.raises(ResultFileError):
        check_output_path(target)
    with pytest.raises(ResultFileError):
        write_atomic(target, "x")
    assert os.path.isdir(str(tmp_path)) and not os.path.exists(str(tmp_path) + ".bak")


def test_calibration_set_round_trip_single_and_multi():
    a, b = make_result(1e-3, 1e-3), make_result(2e-3, 1e-3)
    single = CalibrationSet.single(a)
    assert single.to_yaml() == a.to_yaml()
    back = CalibrationSet.from_yaml(single.to_yaml())
    assert back.is_single and back.results[""].sigma() == pytest.approx(a.sigma())
    b.child_frame = "cam_right_optical_frame"
    multi = CalibrationSet("board", {"left": a, "right": b}, extras={"camera_to_camera": {"left->right": np.eye(4)}},
                           refused={"rear": "never saw the board"})
    m2 = CalibrationSet.from_yaml(multi.to_yaml())
    assert set(m2.results) == {"left", "right"} and m2.refused == {"rear": "never saw the board"}
    assert m2.frame_pairs()["right"] == (b.parent_frame, "cam_right_optical_frame")
    assert m2.extras["camera_to_camera"]["left->right"] == np.eye(4).tolist()


def test_unwritable_path_is_a_clear_error_and_keeps_old(tmp_path):
    if os.geteuid() == 0:
        # root ignores permissions: use a path under a regular file instead
        blocker = tmp_path / "file"
        blocker.write_text("x")
        with pytest.raises(ResultFileError, match="is not a directory"):
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
