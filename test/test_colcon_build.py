"""`colcon build` of both packages into an install space, as a user with ROS 2 Jazzy would.

colcon comes from PyPI here, and the ROS prefix is the project venv instead of /opt/ros/jazzy.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV_PREFIX = Path(sys.prefix)
EXECUTABLES = ("simulation_node", "estimator_node", "meshfg_stack", "bag_player", "meshfg")


@pytest.fixture(scope="module")
def install_space(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("colcon")
    env = dict(os.environ, AMENT_PREFIX_PATH=str(VENV_PREFIX), CMAKE_PREFIX_PATH=str(VENV_PREFIX))
    result = subprocess.run(
        [str(VENV_PREFIX / "bin" / "colcon"), "--log-base", str(work / "log"), "build",
         "--base-paths", str(REPO), str(REPO / "meshfg_msgs"),
         "--build-base", str(work / "build"), "--install-base", str(work / "install"),
         "--cmake-args", f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"],
        cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "2 packages finished" in result.stdout
    return work / "install"


def test_executables_installed_where_ros2_run_looks(install_space):
    lib = install_space / "meshfg_ros" / "lib" / "meshfg_ros"
    for name in EXECUTABLES:
        assert (lib / name).is_file() and os.access(lib / name, os.X_OK), name
    share = install_space / "meshfg_ros" / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "meshfg_ros").is_file()
    assert (share / "meshfg_ros" / "package.xml").is_file()


def test_built_messages_import_from_install_space(install_space):
    script = (
        "import meshfg_msgs.msg as m\n"
        "print(m.__file__)\n"
        "mesh = m.TetraMesh(step=3, positions=[1.0, 2.0, 3.0], tetrahedra=[0, 1, 2, 3])\n"
        "status = m.EstimatorStatus(iterations=4, converged=True, message='ok')\n"
        "print(mesh.step, list(mesh.positions), status.iterations, status.converged)\n"
    )
    result = subprocess.run(
        ["bash", "-c", f'source "{install_space}/setup.bash" && "{sys.executable}" -c "$0"', script],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    module_file, values = result.stdout.strip().splitlines()
    assert module_file.startswith(str(install_space / "meshfg_msgs"))
    assert values == "3 [1.0, 2.0, 3.0] 4 True"


@pytest.mark.parametrize("executable", ["simulation_node", "estimator_node", "meshfg_stack", "bag_player"])
def test_installed_executables_start_and_stop_cleanly(install_space, executable, tmp_path):
    """Each executable of the install space runs (sourcing install/setup.bash, as `ros2 run`
    would) and exits 0 on SIGINT without a traceback."""
    import signal
    import time

    lib = install_space / "meshfg_ros" / "lib" / "meshfg_ros"
    arguments = [str(REPO / "bags" / "cao-push"), "--wait-for-subscribers", "60"] if executable == "bag_player" else []
    command = " ".join([f'"{lib / executable}"', *arguments, "--ros-args", "-r", "__ns:=/colcon_check"])
    process = subprocess.Popen(["bash", "-c", f'source "{install_space}/setup.bash" && exec {command}'],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    time.sleep(6.0)
    assert process.poll() is None, process.communicate()[1]
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr
