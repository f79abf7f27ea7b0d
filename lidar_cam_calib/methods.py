"""The method registry: everything the CLI, the replay, setup.py and the
install-layout test need to know about a method, in one entry (ROS-free).

Adding a method is add-only: write its package (calibrator, config), its node
under ``ros/``, its simulator and benchmark, then add one :class:`MethodSpec`
here. Entries name code by ``"module:attribute"`` strings, loaded on use, so
this module imports nothing heavy (setup.py reads it without numpy).
"""
from __future__ import annotations

import dataclasses
import importlib
from typing import Any


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    name: str                 # short name on the command line: lidar-cam-calib calibrate <name> BAG
    summary: str              # one line for --help
    paper: str                # seeds/ file it implements
    node: str                 # "module:Class" of the rclpy node (under lidar_cam_calib.ros)
    executable: str           # console script / ros2 run name == default node name
    calibrator: str           # "module:Class" satisfying core.calibrator.Calibrator
    config: str               # "module:Class" of its config dataclass (cfg_field fields)
    params_file: str          # file under config/
    scenario: str             # default simulator scenario under config/scenarios/
    simulate: str             # "module:function(scenario, out_dir, seed=None, overwrite=False) -> (bag, truth)"
    load_scenario: str        # "module:function(path_or_dict) -> scenario"
    bench: str                # "module:main(argv) -> int"
    demo_bag: str = ""        # bag directory under bags/ (if shipped)
    metrics: tuple = ()       # result metrics the CLI prints: (key, label, unit)

    @property
    def node_module(self) -> str:
        return self.node.split(":")[0]


METHODS: dict[str, MethodSpec] = {
    "lrf": MethodSpec(
        name="lrf",
        summary="2D laser scanner (LaserScan) + depth camera, folded 3-face board (paper 003)",
        paper="003_0df49f7b7d3b39a0.txt",
        node="lidar_cam_calib.ros.lrf_node:LrfCalibNode",
        executable="lrf_calib_node",
        calibrator="lidar_cam_calib.lrf.calibrator:LrfCalibrator",
        config="lidar_cam_calib.lrf.calibrator:LrfConfig",
        params_file="lrf.yaml",
        scenario="lrf_default.yaml",
        simulate="lidar_cam_calib.sim.lrf_bag:write_lrf_bag",
        load_scenario="lidar_cam_calib.sim.scenario:load_scenario",
        bench="lidar_cam_calib.bench.lrf:main",
        demo_bag="lrf_demo",
        metrics=(("point_to_line_mm", "eq. 12 point-to-line error", "mm"),
                 ("plane_rms_mm", "laser points to camera planes RMS", "mm")),
    ),
    "board": MethodSpec(
        name="board",
        summary="3D LiDAR + one or more cameras, checkerboard with a reflective border (paper 000)",
        paper="000_c480f37addc61f7e.txt",
        node="lidar_cam_calib.ros.board_node:BoardCalibNode",
        executable="board_calib_node",
        calibrator="lidar_cam_calib.board.calibrator:BoardCalibrator",
        config="lidar_cam_calib.board.calibrator:BoardConfig",
        params_file="board.yaml",
        scenario="board_default.yaml",
        simulate="lidar_cam_calib.sim.board_bag:write_board_bag",
        load_scenario="lidar_cam_calib.sim.board_world:load_board_scenario",
        bench="lidar_cam_calib.bench.board:main",
        demo_bag="board_demo",
        metrics=(("reprojection_px", "reprojection of the board corners", "px"),
                 ("normalized_plane_error_mm", "normalised plane error (eq. 24-25)", "mm")),
    ),
    "targetless": MethodSpec(
        name="targetless",
        summary="spinning LiDAR + camera on a moving car, no target (paper 001; not yet accurate: see README)",
        paper="001_43f2b4ff66099dbb.txt",
        node="lidar_cam_calib.ros.targetless_node:TargetlessCalibNode",
        executable="targetless_calib_node",
        calibrator="lidar_cam_calib.targetless.calibrator:TargetlessCalibrator",
        config="lidar_cam_calib.targetless.calibrator:TargetlessConfig",
        params_file="targetless.yaml",
        scenario="targetless_default.yaml",
        simulate="lidar_cam_calib.sim.street_bag:write_street_bag",
        load_scenario="lidar_cam_calib.sim.street_world:load_street_scenario",
        bench="lidar_cam_calib.bench.targetless:main",
        metrics=(("sfm_reprojection_px", "SfM re-projection", "px"),
                 ("hausdorff_m", "Hausdorff distance of the registered clouds", "m")),
    ),
}

# Benchmarks that belong to no method.
EXTRA_BENCHES: dict[str, tuple[str, str]] = {
    "decode": ("lidar_cam_calib.io.bench_decode:main", "message conversion speed (PointCloud2, depth Image)"),
    "latency": ("lidar_cam_calib.ros.bench_latency:main", "input callback delay of a live node while it fits"),
}


def load(ref: str) -> Any:
    """Import ``"module:attribute"``."""
    module, _, attr = ref.partition(":")
    obj = importlib.import_module(module)
    return getattr(obj, attr) if attr else obj


def get(name: str) -> MethodSpec:
    try:
        return METHODS[name]
    except KeyError:
        raise KeyError(f"unknown method {name!r}; available: {', '.join(METHODS)}") from None


__all__ = ["EXTRA_BENCHES", "METHODS", "MethodSpec", "get", "load"]
