import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

# No DDS traffic may leave loopback, whatever the caller's environment.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_LOCALHOST_ONLY", None)

DEMO_BAG = os.path.join(ROOT, "bags", "lrf_demo")
SHARED_DATA = os.path.join(ROOT, "..", "shared", "data")


@pytest.fixture
def demo_bag():
    if not os.path.isdir(DEMO_BAG):
        pytest.fail(f"demo bag missing: {DEMO_BAG} (regenerate: lidar-cam-calib simulate lrf "
                    "--scenario config/scenarios/lrf_demo.yaml --out bags/lrf_demo)")
    return DEMO_BAG


_domain = [150 + os.getpid() % 40]


@pytest.fixture
def domain_id():
    """A ROS_DOMAIN_ID unique to this test in this run."""
    _domain[0] += 1
    return _domain[0]
