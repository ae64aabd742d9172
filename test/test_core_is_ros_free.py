"""The core, the recording IO and the offline tools never import rclpy or ROS message packages."""
import subprocess
import sys

import pytest

ROS_FREE_MODULES = (
    "meshfg_ros.core.mesh", "meshfg_ros.synthetic.meshing", "meshfg_ros.core.fem", "meshfg_ros.core.simulator",
    "meshfg_ros.synthetic.camera", "meshfg_ros.synthetic.scenarios", "meshfg_ros.evaluation.metrics",
    "meshfg_ros.core.factors", "meshfg_ros.core.factor_graph", "meshfg_ros.core.linear_system",
    "meshfg_ros.core.levenberg_marquardt", "meshfg_ros.core.linear_solvers", "meshfg_ros.core.estimator",
    "meshfg_ros.parameters", "meshfg_ros.io.recording", "meshfg_ros.replay", "meshfg_ros.evaluation",
    "meshfg_ros.evaluation.ablation",
)


@pytest.mark.slow  # a fresh interpreter
def test_core_modules_import_without_ros():
    script = (
        "import sys\n"
        f"for name in {ROS_FREE_MODULES!r}:\n"
        "    __import__(name)\n"
        "ros = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('rclpy', 'rosidl_parser', 'std_msgs', 'sensor_msgs', 'meshfg_msgs', 'geometry_msgs'))\n"
        "print(','.join(ros))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd="/")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == ""
