"""ament_python package meshfg_ros (colcon build, or pip install into the project venv)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "meshfg_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz") + glob("config/*.json")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ]
    # Bundled recordings are rosbag2 directories (metadata.yaml + MCAP file).
    + [(f"share/{PACKAGE}/{bag}", glob(f"{bag}/*")) for bag in sorted(glob("bags/*/"))],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="meshfg_ros maintainers",
    maintainer_email="maintainers@meshfg.dev",
    description="Factor-graph state estimation of deforming soft tissue meshes.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "meshfg = meshfg_ros.cli:main",
            "simulation_node = meshfg_ros.nodes.simulation_node:main",
            "estimator_node = meshfg_ros.nodes.estimator_node:main",
            "sim_bridge_server = meshfg_ros.nodes.sim_bridge_server:main",
            "meshfg_stack = meshfg_ros.nodes.stack:main",
            "bag_player = meshfg_ros.nodes.bag_player:main",
            "tool_clearance_node = meshfg_ros.nodes.tool_clearance_node:main",
        ],
    },
)
