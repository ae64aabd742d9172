"""The shared `main` of the node executables: init, spin, clean shutdown on Ctrl-C / SIGINT / SIGTERM."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from meshfg_ros.core.parameters import ParameterError


def init_without_signal_handlers(args=None) -> None:
    """rclpy.init, with SIGINT and SIGTERM raising KeyboardInterrupt instead of rclpy's handlers.

    rclpy's handlers invalidate the context at once, so a callback still running fails to
    publish with a traceback; with KeyboardInterrupt the program stops its executor, lets the
    running callbacks finish, and only then shuts the context down.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    for number in (signal.SIGINT, signal.SIGTERM):  # SIGINT too: a background job may inherit it ignored
        signal.signal(number, signal.default_int_handler)


class _MultiThreadedExecutor(MultiThreadedExecutor):
    """MultiThreadedExecutor whose shutdown first waits for its worker threads.

    rclpy 7.1 (Jazzy) leaves the thread pool running after shutdown, and its
    Executor.shutdown destroys the executor's guard condition without waiting for running
    callbacks (its wait is unreachable); a callback that finishes afterwards then fails on the
    destroyed guard ("exception was never retrieved: cannot use Destroyable"). So the pool is
    drained first (the spin loop has already stopped, nothing new is submitted), then shut down.
    """

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        self._executor.shutdown(wait=True)
        return super().shutdown(timeout_sec)


def run_nodes(program: str, node_factories: Sequence[Callable[[], Node]], threads: int, args=None) -> int:
    """Create the nodes, spin them on one executor (`threads` threads) until shutdown; the exit code.

    args: command line with --ros-args (None: sys.argv). Invalid parameters end the program
    with exit code 1 and a one-line message; Ctrl-C / SIGINT / SIGTERM end it with 0.
    """
    init_without_signal_handlers(args)
    nodes: list[Node] = []
    executor = None
    try:
        for factory in node_factories:
            nodes.append(factory())
        executor = SingleThreadedExecutor() if threads == 1 else _MultiThreadedExecutor(num_threads=threads)
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
