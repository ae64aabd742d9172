"""`colcon build` of the packages into an install space, as a user with ROS 2 Jazzy would.

colcon comes from PyPI here, and the ROS prefix is the project venv instead of /opt/ros/jazzy.
"""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy

pytestmark = pytest.mark.slow  # a colcon build, then each executable as its own process over DDS

REPO = Path(__file__).resolve().parents[1]
VENV_PREFIX = Path(sys.prefix)
EXECUTABLES = ("simulation_node", "estimator_node", "meshfg_stack", "bag_player", "meshfg", "sim_bridge_server")


@pytest.fixture(scope="module")
def install_space(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("colcon")
    env = dict(os.environ, AMENT_PREFIX_PATH=str(VENV_PREFIX), CMAKE_PREFIX_PATH=str(VENV_PREFIX))
    result = subprocess.run(
        [str(VENV_PREFIX / "bin" / "colcon"), "--log-base", str(work / "log"), "build",
         "--base-paths", str(REPO), str(REPO / "meshfg_msgs"), str(REPO / "sim_bridge"), str(REPO / "tf2_msgs"),
         "--build-base", str(work / "build"), "--install-base", str(work / "install"),
         "--cmake-args", f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"],
        cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "4 packages finished" in result.stdout
    return work / "install"


def test_executables_installed_where_ros2_run_looks(install_space):
    lib = install_space / "meshfg_ros" / "lib" / "meshfg_ros"
    for name in EXECUTABLES:
        assert (lib / name).is_file() and os.access(lib / name, os.X_OK), name
    share = install_space / "meshfg_ros" / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "meshfg_ros").is_file()
    assert (share / "meshfg_ros" / "package.xml").is_file()


def run_in_install_space(install_space, script: str) -> list[str]:
    """The lines a Python `script` prints with the install space sourced (as a ROS user runs it)."""
    result = subprocess.run(
        ["bash", "-c", f'source "{install_space}/setup.bash" && "{sys.executable}" -c "$0"', script],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return result.stdout.strip().splitlines()


def test_built_messages_import_from_install_space(install_space):
    script = (
        "import meshfg_msgs.msg as m\n"
        "print(m.__file__)\n"
        "mesh = m.TetraMesh(step=3, positions=[1.0, 2.0, 3.0], tetrahedra=[0, 1, 2, 3])\n"
        "status = m.EstimatorStatus(iterations=4, converged=True, message='ok')\n"
        "print(mesh.step, list(mesh.positions), status.iterations, status.converged)\n"
    )
    module_file, values = run_in_install_space(install_space, script)
    assert module_file.startswith(str(install_space / "meshfg_msgs"))
    assert values == "3 [1.0, 2.0, 3.0] 4 True"


def test_built_tf2_msgs_import_from_install_space(install_space):
    script = (
        "import tf2_msgs.msg as m, tf2_msgs.srv, tf2_msgs.action\n"
        "print(m.__file__)\n"
        "print(len(m.TFMessage(transforms=[]).transforms), m.TF2Error.EXTRAPOLATION_ERROR)\n"
    )
    module_file, values = run_in_install_space(install_space, script)
    assert module_file.startswith(str(install_space / "tf2_msgs"))
    assert values == "0 3"


@pytest.fixture(scope="module")
def graph():
    """A node of the test process that watches the ROS graph."""
    rclpy.init()
    node = rclpy.create_node("colcon_check_probe")
    yield node
    node.destroy_node()
    rclpy.shutdown()


def wait_for_node_or_exit(graph, process, namespace: str, timeout_s=120.0) -> bool:
    """Spin until a node in `namespace` is in the graph (True), or the process ended or the
    timeout passed (False)."""
    deadline = time.monotonic() + timeout_s
    while process.poll() is None and time.monotonic() < deadline:
        if any(name_space == namespace for _, name_space in graph.get_node_names_and_namespaces()):
            return True
        rclpy.spin_once(graph, timeout_sec=0.05)
    return False


@pytest.mark.parametrize("executable", ["simulation_node", "estimator_node", "meshfg_stack", "bag_player"])
def test_installed_executables_start_and_stop_cleanly(install_space, graph, executable, tmp_path):
    """Each executable of the install space runs (sourcing install/setup.bash, as `ros2 run`
    would), joins the ROS graph, and exits 0 on SIGINT without a traceback. Each gets its own
    namespace, so a node of an earlier case still listed in the graph does not count."""
    namespace = f"/colcon_check_{executable}"
    lib = install_space / "meshfg_ros" / "lib" / "meshfg_ros"
    arguments = [str(REPO / "bags" / "cao-push"), "--wait-for-subscribers", "60"] if executable == "bag_player" else []
    command = " ".join([f'"{lib / executable}"', *arguments, "--ros-args", "-r", f"__ns:={namespace}"])
    process = subprocess.Popen(["bash", "-c", f'source "{install_space}/setup.bash" && exec {command}'],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        if not wait_for_node_or_exit(graph, process, namespace):
            process.kill()
            pytest.fail(f"{executable} never joined the ROS graph:\n{process.communicate(timeout=60)[1][-3000:]}")
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr
