"""The tissue model and the tool: the settings the simulator and the estimator share.

The simulator predicts with them; the estimator's physics prior takes the tissue model's
stiffness (Young's modulus, Poisson's ratio), and its tool gate the tool (its mode and radius).
SimulatorConfig and EstimatorConfig both inherit `TissueAndTool`, so each of these settings is
one field, with one default and one description: one parameter of both nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

from meshfg_ros.core.settings import setting

__all__ = ["TOOL_MODES", "TissueAndTool"]

TOOL_MODES = ("sphere", "grasp")


@dataclass(frozen=True)
class TissueAndTool:
    """The tissue model (linear-elastic moduli, SI units) and the tool that drives it. The
    configurations that inherit it check its fields with their own (core/settings.py)."""

    # Soft tissue is of the order of kPa.
    youngs_modulus: float = setting(3.0e3, "Young's modulus of the tissue model in pascals.", range=(1.0, 1e9))
    poisson_ratio: float = setting(0.45, "Poisson's ratio of the tissue model.", range=(0.001, 0.499))
    tool_radius: float = setting(5.0e-3, "Radius of the tool sphere in metres (sphere mode).", range=(1e-6, 1.0))
    tool_mode: str = setting(
        "sphere", "How the tool drives the tissue: 'sphere' pushes it with a rigid sphere, 'grasp' moves "
        "grasped_vertices rigidly with the tool.", choices=TOOL_MODES)
