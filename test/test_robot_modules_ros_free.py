"""The robot-input modules (frames, tool poses, patient meshes, TFMessage conversion) import no ROS:
the nodes wire them, the offline tools use them as they are."""
import subprocess
import sys

import pytest

MODULES = ("meshfg_ros.core.pose_history", "meshfg_ros.core.frames", "meshfg_ros.core.tool_poses",
           "meshfg_ros.core.patient_mesh", "meshfg_ros.io.tf_messages")


@pytest.mark.slow  # a fresh interpreter
def test_robot_modules_import_without_ros():
    script = (
        "import sys\n"
        f"for name in {MODULES!r}:\n"
        "    __import__(name)\n"
        "print(','.join(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('rclpy', 'rosidl_parser', 'std_msgs', 'geometry_msgs', 'tf2_msgs', 'meshfg_msgs'))))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd="/")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == ""
