"""The package installs the way colcon (ament_python) lays it out."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_colcon_style_install_layout(tmp_path):
    pytest.importorskip("setuptools")
    prefix = tmp_path / "install"
    build = tmp_path / "build"
    # What colcon's ament_python build does, without colcon.
    build.mkdir()
    cmd = [sys.executable, "setup.py", "-q", "egg_info", "--egg-base", str(build),
           "build", "--build-base", str(build), "install", "--prefix", str(prefix),
           "--record", str(tmp_path / "record.txt"), "--single-version-externally-managed"]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    share = prefix / "share" / "lidar_cam_calib"
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "lidar_cam_calib").is_file()
    assert (share / "package.xml").is_file()
    assert (share / "config" / "lrf.yaml").is_file()
    from lidar_cam_calib import methods

    for spec in methods.METHODS.values():   # every registered method: its node and its files
        node = prefix / "lib" / "lidar_cam_calib" / spec.executable
        assert node.is_file() and os.access(node, os.X_OK), spec.executable
        assert (share / "config" / spec.params_file).is_file(), spec.params_file
        assert (share / "config" / "scenarios" / spec.scenario).is_file(), spec.scenario
    assert (prefix / "lib" / "lidar_cam_calib" / "lidar-cam-calib").is_file()
    bag_files = list((share / "bags").rglob("*.mcap"))
    assert bag_files, "demo bag not installed under share/lidar_cam_calib/bags"
    assert list((share / "config" / "scenarios").glob("*.yaml"))
    # No build artefacts of ours left in the source tree.
    assert not os.path.isdir(os.path.join(ROOT, "build", "lib"))


def test_package_xml_declares_run_dependencies():
    import xml.etree.ElementTree as ET

    root = ET.parse(os.path.join(ROOT, "package.xml")).getroot()
    deps = {e.text for e in root if e.tag in ("exec_depend", "depend")}
    for key in ("rclpy", "rcl_interfaces", "sensor_msgs", "geometry_msgs", "std_msgs", "std_srvs", "tf2_msgs",
                "python3-numpy", "python3-scipy", "python3-opencv", "python3-yaml"):
        assert key in deps, key
    for unused in ("visualization_msgs", "tf2_ros"):
        assert unused not in deps, unused
    assert root.find("export/build_type").text == "ament_python"


def test_core_imports_without_rclpy():
    """Everything but lidar_cam_calib.ros must import with rclpy unavailable."""
    code = (
        "import sys, importlib, pkgutil\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('rclpy', 'sensor_msgs', 'geometry_msgs', 'std_msgs', 'std_srvs'):\n"
        "            raise ImportError('blocked ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import lidar_cam_calib\n"
        "for m in pkgutil.walk_packages(lidar_cam_calib.__path__, 'lidar_cam_calib.'):\n"
        "    if not m.name.startswith('lidar_cam_calib.ros.') or m.name == 'lidar_cam_calib.ros.env':\n"
        "        importlib.import_module(m.name)\n"
        "print('ok')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]


def test_registry_entries_resolve():
    """Every string in the method registry names code and files that exist."""
    import importlib.util

    from lidar_cam_calib import methods

    for spec in methods.METHODS.values():
        for ref in (spec.calibrator, spec.config, spec.simulate, spec.load_scenario, spec.bench):
            module, _, attr = ref.partition(":")
            assert importlib.util.find_spec(module) is not None, ref
            assert hasattr(methods.load(module), attr), ref
        assert importlib.util.find_spec(spec.node_module) is not None, spec.node
        assert os.path.isfile(os.path.join(ROOT, "config", spec.params_file))
        assert os.path.isfile(os.path.join(ROOT, "config", "scenarios", spec.scenario))
        cfg = methods.load(spec.config)()
        from lidar_cam_calib.core.calibrator import Calibrator, validate_config

        validate_config(cfg)
        assert isinstance(methods.load(spec.calibrator)(cfg), Calibrator)


def test_every_cli_subcommand_has_its_own_help():
    from lidar_cam_calib import methods

    def run(*args):
        return subprocess.run([sys.executable, "-m", "lidar_cam_calib.cli", *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)

    top = run("--help")
    assert top.returncode == 0 and "exit codes:" in top.stdout
    cal = run("calibrate", "--help")
    assert cal.returncode == 0 and "--truth" in cal.stdout and "exit codes:" in cal.stdout
    assert "--seed" in run("simulate", "--help").stdout
    benches = run("bench", "--help")
    assert benches.returncode == 0 and all(n in benches.stdout for n in methods.METHODS)
    for name in list(methods.METHODS) + list(methods.EXTRA_BENCHES):
        r = run("bench", name, "--help")
        assert r.returncode == 0 and f"bench {name}" in r.stdout, (name, r.stdout, r.stderr)
