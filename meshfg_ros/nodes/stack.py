"""meshfg_stack: the simulation and estimator nodes in one process (one executor thread, plus
the estimator's solver thread).

Same topics, parameters and --ros-args as the two separate executables, without the DDS hop
between the simulator and the estimator being a process boundary.
"""

from __future__ import annotations

import sys

from meshfg_ros.nodes.estimator_node import EstimatorNode
from meshfg_ros.nodes.runtime import run_nodes
from meshfg_ros.nodes.simulation_node import SimulationNode


def main(args=None) -> int:
    """Console script `meshfg_stack` (accepts --ros-args; e.g. -r __ns:=/meshfg --params-file FILE)."""
    return run_nodes("meshfg_stack", [SimulationNode, EstimatorNode], args=args,
                     node_names=("simulation_node", "estimator_node"))


if __name__ == "__main__":
    sys.exit(main())
