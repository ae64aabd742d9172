"""The nodes' ROS parameters, from meshfg_ros.parameters: declared with descriptors, checked at
start-up, and the dynamic ones changeable while the node runs.

`declare_parameters(node, node_name, on_change)` is the one call a node makes:
- an override (-p, --params-file) whose name no node of the package knows stops the node with
  ParameterError "unknown parameter X (did you mean Y?)"; rclpy itself would ignore it;
- an integer is taken for a double, also in arrays (-p camera_pose:=[0,0,0,0,0,0,1]), at
  start-up and when set while running;
- every parameter gets a ParameterDescriptor (type, description, range or choices), read-only
  unless the parameter is dynamic and the node passes `on_change`;
- a set of a dynamic parameter while running is validated like the start-up values (type,
  range, the configurations they make) and refused with the reason in its SetParametersResult,
  or applied: the values `declare_parameters` returned are updated, then on_change(changes) is
  called with the validated changes (name -> value).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter as RosParameter

from meshfg_ros.parameters import Parameter, ParameterError, check_parameter_names, load_parameters, node_parameters

__all__ = ["declare_parameters", "parameter_descriptor"]

_ROS_TYPES = {
    "double": ParameterType.PARAMETER_DOUBLE,
    "integer": ParameterType.PARAMETER_INTEGER,
    "string": ParameterType.PARAMETER_STRING,
    "bool": ParameterType.PARAMETER_BOOL,
    "double_array": ParameterType.PARAMETER_DOUBLE_ARRAY,
    "integer_array": ParameterType.PARAMETER_INTEGER_ARRAY,
}


def parameter_descriptor(parameter: Parameter, read_only: bool = True) -> ParameterDescriptor:
    """ROS ParameterDescriptor of a meshfg_ros.parameters.Parameter (type, description, range, choices)."""
    descriptor = ParameterDescriptor(
        name=parameter.name,
        type=_ROS_TYPES[parameter.type],
        description=parameter.description,
        read_only=read_only,
    )
    if parameter.choices is not None:
        descriptor.additional_constraints = f"one of: {', '.join(parameter.choices)}"
    if parameter.length is not None:
        descriptor.additional_constraints = f"exactly {parameter.length} values"
    if parameter.range is not None and parameter.type in ("double", "integer"):
        low, high = parameter.range
        if parameter.type == "double":
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=-sys.float_info.max if low is None else float(low),
                to_value=sys.float_info.max if high is None else float(high),
            )]
        else:
            descriptor.integer_range = [IntegerRange(
                from_value=-(2**63) if low is None else int(low),
                to_value=2**63 - 1 if high is None else int(high),
                step=1,
            )]
    return descriptor


def declare_parameters(node: Node, node_name: str,
                       on_change: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Declare the parameters of `node_name` (meshfg_ros.parameters.NODE_CONFIGURATIONS) on
    `node`; their validated values (ParameterError for unknown names and invalid values).

    on_change: makes the dynamic parameters settable while the node runs (see the module
    docstring); it runs in the executor's thread and must not raise (its changes are validated).
    """
    # rclpy's merged -p and --params-file values for this node: the only place that still holds
    # the names the node does not declare.
    overrides = node._parameter_overrides
    check_parameter_names(overrides, node_name)
    parameters = node_parameters(node_name)
    values = load_parameters({parameter.name: _override_value(overrides[parameter.name], parameter)
                              for parameter in parameters if parameter.name in overrides}, node_name)
    for parameter in parameters:
        _declare(node, parameter, values[parameter.name], read_only=not (parameter.dynamic and on_change is not None))
    if on_change is not None:
        _DynamicParameters(node, node_name, values, on_change)
    return values


def _override_value(override: RosParameter, parameter: Parameter) -> Any:
    """The Python value of an override; rcl reads an empty list (`[]`) as not set."""
    if override.type_ == RosParameter.Type.NOT_SET and parameter.type.endswith("_array"):
        return ()
    return override.value


def _declare(node: Node, parameter: Parameter, value: Any, read_only: bool) -> None:
    descriptor = parameter_descriptor(parameter, read_only)
    if isinstance(value, tuple) and not value:
        # rclpy infers no type from []: declared by type (settable), set to [], then given its descriptor.
        ros_type = RosParameter.Type(descriptor.type)
        node.declare_parameter(parameter.name, ros_type, parameter_descriptor(parameter, read_only=False),
                               ignore_override=True)
        node.set_parameters([RosParameter(parameter.name, ros_type, [])])
        node.set_descriptor(parameter.name, descriptor)
        return
    node.declare_parameter(parameter.name, list(value) if isinstance(value, tuple) else value, descriptor,
                           ignore_override=True)


def _as_declared_type(ros_parameter: RosParameter, parameter: Parameter | None) -> RosParameter:
    """An integer (array) set for a double (array) parameter, as doubles; anything else unchanged."""
    if parameter is None:
        return ros_parameter
    if parameter.type == "double" and ros_parameter.type_ == RosParameter.Type.INTEGER:
        return RosParameter(ros_parameter.name, RosParameter.Type.DOUBLE, float(ros_parameter.value))
    if parameter.type == "double_array" and ros_parameter.type_ == RosParameter.Type.INTEGER_ARRAY:
        return RosParameter(ros_parameter.name, RosParameter.Type.DOUBLE_ARRAY,
                            [float(item) for item in ros_parameter.value])
    return ros_parameter


class _DynamicParameters:
    """Sets of a node's parameters while it runs: integers taken for doubles, the values validated
    as at start-up (rclpy has refused read-only ones and checked types and ranges), then applied."""

    def __init__(self, node: Node, node_name: str, values: dict[str, Any],
                 on_change: Callable[[dict[str, Any]], None]) -> None:
        self._node_name = node_name
        self._by_name = {parameter.name: parameter for parameter in node_parameters(node_name)}
        self._values = values
        self._on_change = on_change
        node.add_pre_set_parameters_callback(self._as_declared_types)
        node.add_on_set_parameters_callback(self._check)
        node.add_post_set_parameters_callback(self._apply)

    def _as_declared_types(self, parameters: list[RosParameter]) -> list[RosParameter]:
        return [_as_declared_type(parameter, self._by_name.get(parameter.name)) for parameter in parameters]

    def _check(self, parameters: list[RosParameter]) -> SetParametersResult:
        try:
            self._validated(parameters)
        except ParameterError as error:
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _apply(self, parameters: list[RosParameter]) -> None:
        changes = self._validated(parameters)
        if changes:
            self._values.update(changes)
            self._on_change(changes)

    def _validated(self, parameters: list[RosParameter]) -> dict[str, Any]:
        """The node's own parameters among `parameters`, validated with the node's other values."""
        changes = {parameter.name: parameter.value for parameter in parameters if parameter.name in self._by_name}
        values = load_parameters({**self._values, **changes}, self._node_name)
        return {name: values[name] for name in changes}
