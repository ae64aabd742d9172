"""The layering of the package: the core is the estimator only and knows nothing of ROS; the
offline tools never import rclpy; the live nodes never load the synthetic-scene generator."""
import pkgutil
import subprocess
import sys

import pytest

import meshfg_ros.core

CORE_MODULES = tuple(sorted(info.name for info in pkgutil.walk_packages(meshfg_ros.core.__path__, prefix="meshfg_ros.core.")))
OFFLINE_MODULES = (
    "meshfg_ros.parameters", "meshfg_ros.io.recording", "meshfg_ros.replay", "meshfg_ros.synthetic.scenarios",
    "meshfg_ros.synthetic.recordings", "meshfg_ros.evaluation.evaluate", "meshfg_ros.evaluation.ablation",
    "meshfg_ros.evaluation.accuracy", "meshfg_ros.benchmarks.baselines", "meshfg_ros.io.tf_messages",
)
ROS_PACKAGES = ("rclpy", "rosidl_parser", "std_msgs", "sensor_msgs", "meshfg_msgs", "geometry_msgs", "tf2_msgs")


def _loaded_after_import(modules: tuple[str, ...]) -> set[str]:
    """The modules a fresh interpreter has loaded after importing `modules`."""
    script = (
        "import sys\n"
        f"for name in {modules!r}:\n"
        "    __import__(name)\n"
        "print('\\n'.join(sorted(sys.modules)))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd="/")
    assert result.returncode == 0, result.stderr
    return set(result.stdout.split())


def test_the_core_has_the_estimator_modules():
    assert {"meshfg_ros.core.estimation.estimator", "meshfg_ros.core.scheduler", "meshfg_ros.core.estimation.factors",
            "meshfg_ros.core.solvers.levenberg_marquardt"} <= set(CORE_MODULES)


@pytest.mark.slow  # a fresh interpreter
def test_the_core_imports_only_itself_and_no_ros():
    loaded = _loaded_after_import(CORE_MODULES)
    ours = {name for name in loaded if name.startswith("meshfg_ros.")}
    assert ours <= set(CORE_MODULES) | {"meshfg_ros.core"}, sorted(ours - set(CORE_MODULES))
    assert not {name for name in loaded if name.split(".")[0] in ROS_PACKAGES}


@pytest.mark.slow  # a fresh interpreter
def test_offline_tools_import_without_ros():
    loaded = _loaded_after_import(OFFLINE_MODULES)
    assert not {name for name in loaded if name.split(".")[0] in ROS_PACKAGES}


@pytest.mark.slow  # a fresh interpreter
def test_the_live_nodes_do_not_load_the_synthetic_scenes_or_the_evaluation():
    loaded = _loaded_after_import(("meshfg_ros.nodes.estimator_node", "meshfg_ros.nodes.simulation_node"))
    unwanted = {name for name in loaded
                if name.split(".")[:2] in (["meshfg_ros", "synthetic"], ["meshfg_ros", "evaluation"],
                                           ["meshfg_ros", "benchmarks"])}
    assert not unwanted, sorted(unwanted)
    assert "rclpy" in loaded


@pytest.mark.slow  # a fresh interpreter
def test_nodes_and_offline_tools_do_not_import_scipy_stats():
    """scipy.stats takes about half a second to import, in every process that starts a node or
    a command; the chi-squared quantile comes from scipy.special instead (covariance.py)."""
    loaded = _loaded_after_import(("meshfg_ros.nodes.estimator_node", "meshfg_ros.nodes.simulation_node",
                                   "meshfg_ros.nodes.stack", "meshfg_ros.cli", *OFFLINE_MODULES))
    assert not {name for name in loaded if name.startswith("scipy.stats")}
