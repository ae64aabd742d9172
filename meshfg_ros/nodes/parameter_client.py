"""`meshfg param get|set`: read or change a running node's parameters without the `ros2` command
(the venv's ROS 2 wheels have rclpy but no ros2cli), through the node's get_parameters and
set_parameters services, as `ros2 param get|set` does.

A request is sent again every RESEND_S without an answer, until the timeout: Fast DDS drops a
response when the client's response reader was not matched yet (ros2/rmw_fastrtps#390), and
both requests are idempotent.
"""

from __future__ import annotations

import os
import time
from typing import Any

import rclpy
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.parameter import Parameter, parameter_value_to_python

RESEND_S = 2.0


class ParameterClientError(RuntimeError):
    """No such node or parameter, no answer, or a set the node refused (with its reason)."""


def get_parameters(node_name: str, names: list[str], timeout_s: float = 10.0) -> dict[str, Any]:
    """name -> value of `names` on the running node `node_name` (fully qualified, e.g. /meshfg/estimator_node)."""
    response = _call(node_name, GetParameters, GetParameters.Request(names=names), timeout_s)
    values = {name: parameter_value_to_python(value) for name, value in zip(names, response.values)}
    unset = [name for name, value in zip(names, response.values) if value.type == 0]  # PARAMETER_NOT_SET
    if unset:
        raise ParameterClientError(f"{node_name} has no parameter {', '.join(unset)}")
    return values


def set_parameter(node_name: str, name: str, value: Any, timeout_s: float = 10.0) -> None:
    """Set `name` to `value` on the running node; ParameterClientError with the node's reason if refused."""
    try:
        message = Parameter(name, value=value).to_parameter_msg()
    except (TypeError, ValueError) as error:
        raise ParameterClientError(f"{name}: a value of this type cannot be a parameter: {value!r} ({error})") from None
    response = _call(node_name, SetParameters, SetParameters.Request(parameters=[message]), timeout_s)
    result = response.results[0]
    if not result.successful:
        raise ParameterClientError(f"{node_name} refused {name} = {value!r}: {result.reason}")


def _call(node_name: str, service_type, request, timeout_s: float):
    service = f"{node_name.rstrip('/')}/{'get' if service_type is GetParameters else 'set'}_parameters"
    rclpy.init(args=[])
    node = rclpy.create_node(f"meshfg_param_{os.getpid()}")
    try:
        client = node.create_client(service_type, service)
        deadline = time.monotonic() + timeout_s
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise ParameterClientError(f"no node {node_name} answers on {service} (is it running, in this "
                                       "ROS_DOMAIN_ID, with that namespace?)")
        while time.monotonic() < deadline:
            future = client.call_async(request)
            resend_at = min(deadline, time.monotonic() + RESEND_S)
            while not future.done() and time.monotonic() < resend_at:
                rclpy.spin_once(node, timeout_sec=0.05)
            if future.done():
                return future.result()
            client.remove_pending_request(future)
        raise ParameterClientError(f"{service} did not answer in {timeout_s:g} s")
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
