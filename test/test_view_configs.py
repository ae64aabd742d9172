"""config/meshfg.rviz and config/foxglove_layout.json: they parse, show the package's topics (in
namespace /meshfg) with QoS the nodes' publishers match, and the README names them."""
import json
from pathlib import Path

import yaml
from rclpy.qos import QoSCompatibility, QoSProfile, ReliabilityPolicy, qos_check_compatible, qos_profile_sensor_data

from meshfg_msgs.msg import EstimatorStatus
from meshfg_ros.nodes.ros_conversions import STREAM_QOS

REPOSITORY = Path(__file__).resolve().parents[1]
NAMESPACE = "/meshfg"
# What a viewer may show, and the QoS the topic is published with: markers and status by the
# estimator node, clouds and tool poses as a camera (sensor data) and a robot driver (reliable) send them.
PUBLISHED = {f"{NAMESPACE}/markers": STREAM_QOS, f"{NAMESPACE}/status": STREAM_QOS,
             f"{NAMESPACE}/points": qos_profile_sensor_data, f"{NAMESPACE}/tool_pose": STREAM_QOS,
             "/diagnostics": STREAM_QOS}
RELIABILITY = {"Reliable": ReliabilityPolicy.RELIABLE, "Best Effort": ReliabilityPolicy.BEST_EFFORT}


def test_the_rviz_config_subscribes_the_package_topics_with_matching_qos():
    config = yaml.safe_load((REPOSITORY / "config" / "meshfg.rviz").read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == "world"
    displays = {display["Class"]: display for display in manager["Displays"]}
    assert {"rviz_default_plugins/MarkerArray", "rviz_default_plugins/PointCloud2", "rviz_default_plugins/Pose",
            "rviz_default_plugins/TF"} <= set(displays)
    topics = [display["Topic"] for display in displays.values() if "Topic" in display]
    assert {topic["Value"] for topic in topics} == {f"{NAMESPACE}/markers", f"{NAMESPACE}/points",
                                                    f"{NAMESPACE}/tool_pose"}
    for topic in topics:
        subscription = QoSProfile(depth=topic["Depth"], reliability=RELIABILITY[topic["Reliability Policy"]])
        # WARNING: a policy left at the system default, which rmw resolves to a matching one
        assert qos_check_compatible(PUBLISHED[topic["Value"]], subscription)[0] != QoSCompatibility.ERROR, topic


def test_the_foxglove_layout_shows_the_package_topics_and_status_fields():
    layout = json.loads((REPOSITORY / "config" / "foxglove_layout.json").read_text())
    panels = layout["configById"]
    assert set(panels) == {"3D!meshfg", "DiagnosticSummary!meshfg", "Plot!meshfg", "RawMessages!meshfg"}

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)  # every panel placed, none missing
    assert panels["3D!meshfg"]["followTf"] == "world"
    assert set(panels["3D!meshfg"]["topics"]) <= set(PUBLISHED)
    assert panels["DiagnosticSummary!meshfg"]["topicToRender"] == "/diagnostics"
    status_fields = EstimatorStatus.get_fields_and_field_types()
    for path in [entry["value"] for entry in panels["Plot!meshfg"]["paths"]] + [panels["RawMessages!meshfg"]["topicPath"]]:
        topic, _, field = path.partition(".")
        assert topic == f"{NAMESPACE}/status" and (not field or field in status_fields), path


def test_the_readme_names_both():
    readme = (REPOSITORY / "README.md").read_text()
    assert "config/meshfg.rviz" in readme and "config/foxglove_layout.json" in readme
