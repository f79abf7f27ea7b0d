"""A tiny run of the board benchmark (simulator + every solver), skipped if the simulator is absent."""
from __future__ import annotations

import json

import pytest


def test_bench_board_tiny_run(tmp_path):
    pytest.importorskip("lidar_cam_calib.sim.board_world")
    from lidar_cam_calib.bench.board import main
    out = tmp_path / "b.json"
    png = tmp_path / "b.png"
    assert main(["--poses", "5", "--seed", "3", "--half", "--json", str(out), "--plot", str(png)]) == 0
    d = json.loads(out.read_text())
    assert d["method"] == "board" and d["seed"] == 3 and d["poses"] == 5
    assert set(d["solvers"]) == {"epnp", "kabsch_3d3d", "paper", "ours"}
    for s in d["solvers"].values():
        assert {"rotation_error_deg", "translation_error_mm", "runtime_s", "cameras"} <= set(s)
        for cam in s["cameras"].values():
            assert {"rotation_error_deg", "translation_error_mm", "normalized_plane_error_mm", "reprojection_px",
                    "mahalanobis2"} <= set(cam)
    ours = d["solvers"]["ours"]
    assert ours["translation_error_mm"] < 30 and ours["rotation_error_deg"] < 0.5
    assert d["cramer_rao"] and png.stat().st_size > 1000
