"""KITTI raw -> MCAP converter (runs on ../shared/data/kitti_2011_09_26_seq_dev when present)."""
import os

import numpy as np
import pytest
import yaml
from conftest import SHARED_DATA

from lidar_cam_calib.core.errors import InputError
from lidar_cam_calib.io import convert
from lidar_cam_calib.io.bag import BagError, bag_topics, read_bag
from lidar_cam_calib.io.kitti import kitti_calibration, kitti_point_time, kitti_to_bag
from lidar_cam_calib.io.msgtypes import RosbagsFactory

KITTI = os.path.join(SHARED_DATA, "kitti_2011_09_26_seq_dev")
needs_kitti = pytest.mark.skipif(not os.path.isdir(KITTI), reason=f"KITTI sample not present at {KITTI}")


@needs_kitti
def test_calibration_matches_kitti_formula():
    T, P2 = kitti_calibration(KITTI)
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0
    # cam2 sits ~6 cm to the left of rectified cam0: the P_rect_02 column moves the translation
    # by inv(K2) @ P2[:, 3] = (0.0598, -0.0004, 0.0027) m against the cam0 extrinsic.
    assert np.allclose(np.linalg.solve(P2[:, :3], P2[:, 3]), [0.059849, -0.000358, 0.002746], atol=2e-6)
    # Velodyne x (forward) is camera z (forward); Velodyne y (left) is camera -x.
    assert R[2, 0] > 0.99 and R[0, 1] < -0.99 and R[1, 2] < -0.99
    # R_rect_00 @ T_velo_to_cam + that column, to 0.1 mm.
    assert np.allclose(T[:3, 3], [0.057052, -0.075467, -0.269387], atol=1e-4)


@needs_kitti
def test_convert_three_frames_and_project(tmp_path):
    bag, truth_p = kitti_to_bag(KITTI, tmp_path, max_frames=3)
    topics = bag_topics(bag)
    assert topics == {"/lidar/points": "sensor_msgs/msg/PointCloud2",
                      "/camera/image_raw": "sensor_msgs/msg/Image",
                      "/camera/camera_info": "sensor_msgs/msg/CameraInfo"}
    truth = yaml.safe_load(truth_p.read_text())
    assert truth["message_counts"] == {t: 3 for t in topics}
    T = np.array(truth["T_camera_lidar"])
    fac = RosbagsFactory()
    recs = list(read_bag(bag))
    clouds = [fac.deserialize(r.raw, r.typename) for r in recs if r.topic == "/lidar/points"]
    images = [fac.deserialize(r.raw, r.typename) for r in recs if r.topic == "/camera/image_raw"]
    infos = [fac.deserialize(r.raw, r.typename) for r in recs if r.topic == "/camera/camera_info"]
    stamps = [r.stamp_ns for r in recs if r.topic == "/lidar/points"]
    assert np.allclose(np.diff(stamps), 1e8)
    cam = convert.camera_info_to_model(infos[0])
    assert (cam.width, cam.height) == (1242, 375) and not cam.is_distorted
    img = convert.image_to_array(images[0])
    assert img.shape == (375, 1242, 3)
    raw = np.fromfile(os.path.join(KITTI, "velodyne_points", "data", "0000000000.bin"), np.float32).reshape(-1, 4)
    arr = convert.pointcloud2_to_arrays(clouds[0])
    assert arr["xyz"].shape[0] == raw.shape[0]
    assert np.allclose(arr["xyz"], raw[:, :3]) and np.allclose(arr["intensity"], raw[:, 3])
    # each point's time about the forward-facing stamp: half a turn (0.05 s) either side
    t = arr["time_s"]
    az = np.degrees(np.arctan2(raw[:, 1], raw[:, 0]))
    assert t.min() >= -0.0501 and t.max() <= 0.0501
    assert np.all(np.abs(t[np.abs(az) < 2]) < 0.0006)
    assert np.all(t[(az > 170) & (az < 178)] < -0.044) and np.all(t[(az < -170) & (az > -178)] > 0.044)
    # Points in front of the car project inside the image with positive depth ...
    pc = arr["xyz"] @ T[:3, :3].T + T[:3, 3]
    uv, ok = cam.project(pc)
    front = arr["xyz"][:, 0] > 5.0
    assert ok.sum() > 15000 and ok[front].mean() > 0.3
    # ... and the official projection P2 @ R_rect @ Tr gives the same pixels as K @ T.
    from lidar_cam_calib.io.kitti import read_kitti_calib
    v2c = read_kitti_calib(os.path.join(KITTI, "calib_velo_to_cam.txt"))
    c2c = read_kitti_calib(os.path.join(KITTI, "calib_cam_to_cam.txt"))
    Tr = np.eye(4)
    Tr[:3, :3], Tr[:3, 3] = v2c["R"].reshape(3, 3), v2c["T"]
    R4 = np.eye(4)
    R4[:3, :3] = c2c["R_rect_00"].reshape(3, 3)
    x = (c2c["P_rect_02"].reshape(3, 4) @ R4 @ Tr @ np.c_[arr["xyz"], np.ones(len(pc))].T).T
    uv_k = x[:, :2] / x[:, 2:]
    assert np.max(np.abs(uv_k[ok] - uv[ok])) < 1e-6
    # The ground below the car lands in the lower image half (v > cy) and is dark-grey road.
    ground = ok & (arr["xyz"][:, 2] < -1.5) & (arr["xyz"][:, 0] < 15)
    assert ground.sum() > 500 and np.median(uv[ground, 1]) > cam.cy
    with pytest.raises(BagError):
        kitti_to_bag(KITTI, tmp_path, max_frames=1)
    kitti_to_bag(KITTI, tmp_path, max_frames=1, overwrite=True)


def test_kitti_point_time_runs_clockwise_about_the_forward_stamp():
    """The HDL-64E faces forward at the stamp and spins clockwise seen from above: the left side is
    measured before the stamp, the right side after, a quarter turn (0.025 s) apart from straight ahead."""
    az = np.radians([0.0, 90.0, -90.0, 179.9, -179.9, 45.0])
    t = kitti_point_time(10 * np.cos(az), 10 * np.sin(az))
    assert t.dtype == np.float32
    assert np.allclose(t, [0.0, -0.025, 0.025, -0.05, 0.05, -0.0125], atol=1e-4)


def test_not_a_kitti_folder(tmp_path):
    with pytest.raises(InputError, match="not found"):
        kitti_to_bag(tmp_path / "nope", tmp_path / "out")
    (tmp_path / "calib_velo_to_cam.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    with pytest.raises(InputError, match="calib_cam_to_cam"):
        kitti_to_bag(tmp_path, tmp_path / "out")


@needs_kitti
def test_kitti_timestamps_are_used(tmp_path):
    """A drive with KITTI's timestamps.txt files gets their stamps (camera and LiDAR separately)."""
    drive = tmp_path / "drive"
    for sub in ("image_02/data", "velodyne_points/data"):
        (drive / sub).mkdir(parents=True)
    for k in range(3):
        for sub, ext in (("image_02/data", "png"), ("velodyne_points/data", "bin")):
            (drive / sub / f"{k:010d}.{ext}").symlink_to(os.path.join(KITTI, sub, f"{k:010d}.{ext}"))
    for name in ("calib_velo_to_cam.txt", "calib_cam_to_cam.txt"):
        (tmp_path / name).symlink_to(os.path.join(KITTI, name))  # one level up, as KITTI raw has them
    (drive / "velodyne_points" / "timestamps.txt").write_text(
        "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.068203167\n2011-09-26 13:02:26.172017916\n")
    (drive / "image_02" / "timestamps.txt").write_text(
        "2011-09-26 13:02:25.951199908\n2011-09-26 13:02:26.054979129\n2011-09-26 13:02:26.158745313\n")
    bag, truth_p = kitti_to_bag(drive, tmp_path / "out")
    truth = yaml.safe_load(truth_p.read_text())
    assert truth["stamps"] == "timestamps.txt"
    t0 = 1317042145.0  # 2011-09-26 13:02:25 UTC
    pc = [r.stamp_ns * 1e-9 - t0 for r in read_bag(bag, ["/lidar/points"])]
    im = [r.stamp_ns * 1e-9 - t0 for r in read_bag(bag, ["/camera/image_raw"])]
    assert np.allclose(pc, [0.964389445, 1.068203167, 1.172017916], atol=1e-6)
    assert np.allclose(im, [0.951199908, 1.054979129, 1.158745313], atol=1e-6)
    (drive / "image_02" / "timestamps.txt").write_text("26.09.2011 13:02\n")
    with pytest.raises(InputError, match="timestamp"):
        kitti_to_bag(drive, tmp_path / "out2")
