"""A small method on the real node base, for testing the base itself through
real rclpy and DDS: each std_msgs/String input is a JSON frame
``{"stamp": s, "cams": {name: [x, y, z]}, "fit_s": seconds}``; a fit takes
``fit_s`` seconds and calibrates every camera seen to the mean translation
of its frames. Run: ``python probe_node.py --ros-args ...``."""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from lidar_cam_calib.core.calibrator import Verdict, cfg_field
from lidar_cam_calib.core.errors import NotReadyError
from lidar_cam_calib.core.geometry import make_T
from lidar_cam_calib.core.result import CalibrationResult, CalibrationSet
from lidar_cam_calib.ros.node_base import CalibNodeBase, run_node


@dataclasses.dataclass
class ProbeConfig:
    min_frames: int = cfg_field(2, "Frames needed before the first fit.", range=(1, 100))
    sigma_m: float = cfg_field(0.01, "Reported 1-sigma of each translation axis, divided by sqrt(frames).",
                               range=(0.0, 1.0), exclusive_min=True)


class ProbeCalibrator:
    def __init__(self, cfg: ProbeConfig):
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        self.frames = []

    def add(self, frame: dict) -> Verdict:
        self.frames.append(frame)
        return Verdict(True, f"frame {len(self.frames)} accepted")

    def ready(self) -> bool:
        return len(self.frames) >= self.cfg.min_frames

    def fit(self) -> CalibrationSet:
        if not self.ready():
            raise NotReadyError("not enough frames")
        time.sleep(float(self.frames[-1].get("fit_s", 0.0)))
        res = {}
        for name in sorted({n for f in self.frames for n in f["cams"]}):
            t = np.mean([f["cams"][name] for f in self.frames if name in f["cams"]], axis=0)
            n = sum(name in f["cams"] for f in self.frames)
            cov = np.diag([1e-6] * 3 + [self.cfg.sigma_m ** 2 / n] * 3)
            res[name] = CalibrationResult("probe", "lidar", f"{name}_optical_frame", make_T(np.eye(3), t), cov,
                                          observations_used=n)
        return CalibrationSet("probe", res)

    def status(self) -> dict:
        return {"frames": len(self.frames), "needed": self.cfg.min_frames}


class ProbeNode(CalibNodeBase):
    method_name = "probe"
    config_cls = ProbeConfig

    def __init__(self) -> None:
        super().__init__("probe_calib_node")
        from std_msgs.msg import String

        self.add_input("frames", String, "frame_topic", "/probe/frames", "JSON frames.", self._on_frame)
        self.announce_ready()

    def make_calibrator(self, cfg: ProbeConfig) -> ProbeCalibrator:
        return ProbeCalibrator(cfg)

    def _on_frame(self, msg) -> None:
        frame = json.loads(msg.data)
        self.check_stamp("frames", float(frame["stamp"]), msg.data.encode())
        self.submit_frame(frame, float(frame["stamp"]), auto=True, wait=False)


if __name__ == "__main__":
    sys.exit(run_node(ProbeNode, sys.argv))
