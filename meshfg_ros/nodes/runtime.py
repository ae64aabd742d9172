"""The shared `main` of the node executables: the BLAS, init, spin, clean shutdown on Ctrl-C / SIGINT / SIGTERM."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from meshfg_ros import blas
from meshfg_ros.parameters import ParameterError


def init_without_signal_handlers(args=None) -> None:
    """rclpy.init, with SIGINT and SIGTERM raising KeyboardInterrupt instead of rclpy's handlers.

    rclpy's handlers invalidate the context at once, so a callback still running fails to
    publish with a traceback; with KeyboardInterrupt the program stops its executor, lets the
    running callbacks finish, and only then shuts the context down.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    for number in (signal.SIGINT, signal.SIGTERM):  # SIGINT too: a background job may inherit it ignored
        signal.signal(number, signal.default_int_handler)


def run_nodes(program: str, node_factories: Sequence[Callable[[], Node]], args=None) -> int:
    """Create the nodes, spin them on one single-threaded executor until shutdown; the exit code.

    Single-threaded: rclpy's MultiThreadedExecutor costs ~3x the CPU per message, and the long
    work (the estimator's solves) has its own thread (estimator_node).

    args: command line with --ros-args (None: sys.argv). Invalid parameters (or MESHFG_BLAS) end
    the program with exit code 1 and a one-line message; Ctrl-C / SIGINT / SIGTERM end it with 0.
    """
    try:
        blas.configure()  # before a node loads cvxopt: CHOLMOD binds to the BLAS chosen for this CPU
    except blas.BlasSettingError as error:
        print(f"{program}: {error}", file=sys.stderr)
        return 1
    init_without_signal_handlers(args)
    nodes: list[Node] = []
    executor = None
    try:
        for factory in node_factories:
            nodes.append(factory())
        executor = SingleThreadedExecutor()
        for node in nodes:
            executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParameterError, ParameterException) as error:
        print(f"{program}: invalid parameters: {error}", file=sys.stderr)
        return 1
    finally:
        if executor is not None:
            executor.shutdown()  # lets the callbacks that are running or queued finish
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
