"""lrf on a scene of the simulator family (a board, camera, laser and clock it
was not tuned to) through the real node: bag written, replayed over DDS,
stops accepted automatically, the extrinsic recovered."""
import re

import pytest
import yaml

pytest.importorskip("rclpy")

from live_node import run_cli


@pytest.mark.parametrize("seed", [202])
def test_family_scene_through_the_node(tmp_path, seed):
    from lidar_cam_calib.sim.lrf_bag import write_lrf_bag
    from lidar_cam_calib.sim.lrf_family import draw_scenario

    sc, _ = draw_scenario(seed, n_stops=4)
    bag, truth = write_lrf_bag(sc, str(tmp_path), seed=seed)
    b = sc.board
    params = {"board_width_m": float(b.width_m), "board_height_m": float(b.height_m),
              "board_a_xy_m": [float(v) for v in b.a_xy_m], "board_b_xy_m": [float(v) for v in b.b_xy_m],
              "board_d_xy_m": [float(v) for v in b.d_xy_m], "board_c_xyz_m": [float(v) for v in b.c_xyz_m],
              # the AGV's stops of this scene are shorter than the 1 s default
              "static_time_s": 0.5}
    pf = tmp_path / "params.yaml"
    pf.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    r = run_cli(["calibrate", "lrf", str(bag), "--params", str(pf), "--truth", str(truth),
                 "--output", str(tmp_path / "r.yaml")], 84)
    assert r.returncode == 0, r.stdout + r.stderr
    m = re.search(r"observations: (\d+)", r.stdout)
    assert m and int(m.group(1)) >= 3, r.stdout
    er, et = (float(x) for x in re.search(r"rotation ([0-9.]+) deg, translation ([0-9.]+) mm", r.stdout).groups())
    assert er < 1.0 and et < 25.0, r.stdout   # 4 stops; the 2-stop goal is 1 deg / 15 mm (median)
