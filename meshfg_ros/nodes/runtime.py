"""The shared `main` of the node executables: --help, the BLAS, init, spin, clean shutdown on
Ctrl-C / SIGINT / SIGTERM, and one-line errors for bad arguments and parameters."""

from __future__ import annotations

import gc
import os
import re
import signal
import threading
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
import yaml
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from meshfg_ros import blas, process_settings
import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.parameters import ParameterError, parameters_help

_HELP_OPTIONS = ("-h", "--help")
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# How long the executor waits for work before it looks at a stop request: the longest a node
# takes to begin stopping after SIGINT / SIGTERM.
SPIN_PERIOD_S = 0.1
_USAGE = ("usage: {program} [-h] [--ros-args [-r FROM:=TO] [-p NAME:=VALUE] [--params-file FILE] "
          "[--log-level LEVEL] ...]")


class ArgumentError(ValueError):
    """A command line rcl cannot parse (e.g. `-p NAME:=[0.0, 1]`, a list of mixed types)."""


def _argument_error(error: Exception) -> ArgumentError:
    # rcl's message ends with the C source locations of the failure: of no use to a user.
    return ArgumentError(re.sub(r", at \S+:\d+", "", " ".join(str(error).split())))


def program_arguments(argv: Sequence[str]) -> list[str]:
    """The command line without its ROS arguments (argv[0] first), or ArgumentError."""
    try:
        return remove_ros_args(list(argv))
    except rclpy_implementation.RCLError as error:
        raise _argument_error(error) from None


def help_requested(argv: Sequence[str]) -> bool:
    """Whether -h or --help is among the program's own arguments (those outside --ros-args)."""
    return any(argument in _HELP_OPTIONS for argument in program_arguments(argv)[1:])


def init_without_signal_handlers(args=None) -> None:
    """rclpy.init, with SIGINT and SIGTERM raising KeyboardInterrupt instead of rclpy's handlers.

    rclpy's handlers invalidate the context at once, so a callback still running fails to
    publish with a traceback; with KeyboardInterrupt the program stops its work, lets the running
    callbacks finish, and only then shuts the context down (run_nodes, which spins an executor,
    turns the signals into a stop request instead). ArgumentError when rcl cannot parse the ROS
    arguments.
    """
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except rclpy_implementation.RCLError as error:
        raise _argument_error(error) from None
    for number in _STOP_SIGNALS:  # SIGINT too: a background job may inherit it ignored
        signal.signal(number, signal.default_int_handler)


def run_nodes(program: str, node_factories: Sequence[Callable[[], Node]], args=None,
              node_names: Sequence[str] | None = None) -> int:
    """Create the nodes, spin them on one single-threaded executor until shutdown; the exit code.

    Single-threaded: rclpy's MultiThreadedExecutor costs ~3x the CPU per message, and the long
    work (the estimator's solves) has its own thread (estimator_node).

    args: command line with --ros-args (None: sys.argv). -h / --help prints the parameters of
    `node_names` (default: the node named like the program) and exits with 0 before ROS starts.
    Invalid arguments or parameters (or MESHFG_BLAS) end the program with exit code 1 and a
    one-line message; Ctrl-C / SIGINT / SIGTERM end it with 0.

    The signals only request the stop, which the loop looks at between callbacks: a
    KeyboardInterrupt raised inside `spin` can land after the executor has made a callback's task
    and before it runs it, and that task's coroutine is then never awaited (a RuntimeWarning at exit).
    """
    argv = sys.argv if args is None else list(args)
    try:
        if help_requested(argv):
            _print_help(program, node_names or (program,))
            return 0
        process_settings.configure()  # before a node loads cvxopt or sets up on its mesh
        init_without_signal_handlers(argv)
    except (blas.BlasSettingError, worker_threads.WorkerThreadsSettingError, ArgumentError) as error:
        print(f"{program}: {error}", file=sys.stderr)
        return 1
    nodes: list[Node] = []
    executor = None
    stop_requested = threading.Event()
    previous_handlers = {number: signal.signal(number, lambda *_: stop_requested.set())
                         for number in _STOP_SIGNALS}
    try:
        for factory in node_factories:
            nodes.append(factory())
        for warning in unmatched_parameter_files(argv, [node.get_fully_qualified_name() for node in nodes]):
            for node in nodes:
                node.get_logger().warning(warning)
                if hasattr(node, "setup_warnings"):  # the nodes with diagnostics: they say it there too
                    node.setup_warnings.append(warning)
        executor = SingleThreadedExecutor()
        for node in nodes:
            executor.add_node(node)
        while not stop_requested.is_set():
            executor.spin_once(timeout_sec=SPIN_PERIOD_S)
    except (KeyboardInterrupt, ExternalShutdownException):  # KeyboardInterrupt: from a node's constructor
        pass
    except (ParameterError, ParameterException) as error:
        print(f"{program}: invalid parameters: {error}", file=sys.stderr)
        return 1
    finally:
        if executor is not None:
            executor.shutdown()  # lets the callbacks that are running or queued finish
        for node in nodes:
            node.destroy_node()
        # A node whose constructor raised (a bad mesh_file) is unreachable but alive (its reference
        # cycles): finalised here while the context is valid, not at interpreter exit after it.
        gc.collect()
        rclpy.try_shutdown()
        for number, handler in previous_handlers.items():
            signal.signal(number, handler)
    return 0


def _print_help(program: str, node_names: Sequence[str]) -> None:
    """The usage and the parameters on stdout; a reader that stops early (`--help | head`) ends it
    quietly: stdout goes to /dev/null, so that the flush at exit raises no BrokenPipeError either
    (the recipe of Python's signal module documentation)."""
    try:
        print(_USAGE.format(program=program), parameters_help(node_names), sep="\n\n", flush=True)
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def unmatched_parameter_files(argv: Sequence[str], node_names: Sequence[str]) -> list[str]:
    """A warning for each --params-file of the ROS arguments none of whose node names matches any
    of `node_names` (fully qualified): rcl applies such a file to no node, silently. Node names
    match as rcl matches them: a leading '/' implied, '*' one token, '**' any number of them, and
    namespaces nested as keys."""
    warnings = []
    for path in _parameter_files(argv):
        try:
            document = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError):
            continue  # rcl has read it already, or stopped the program
        keys = _node_keys(document) if isinstance(document, dict) else []
        if keys and not any(_node_key_matches(key, name) for key in keys for name in node_names):
            warnings.append(f"parameters file {path} sets nothing: its node names ({', '.join(keys)}) match none of "
                            f"this program's nodes ({', '.join(node_names)}); name them so, or use /** for every node")
    return warnings


def _parameter_files(argv: Sequence[str]) -> list[str]:
    """The --params-file arguments within --ros-args ... [--]."""
    files, in_ros_args = [], False
    for argument, following in zip(argv, [*argv[1:], None]):
        if argument == "--ros-args":
            in_ros_args = True
        elif argument == "--":
            in_ros_args = False
        elif in_ros_args and argument == "--params-file" and following is not None:
            files.append(following)
    return files


def _node_keys(document: dict, namespace: str = "") -> list[str]:
    """The node names of a parameters file: keys holding ros__parameters, below namespace keys."""
    keys = []
    for key, value in document.items():
        if not isinstance(value, dict):
            continue
        name = f"{namespace}/{str(key).strip('/')}"
        keys += [name] if "ros__parameters" in value else _node_keys(value, name)
    return keys


def _node_key_matches(key: str, node_name: str) -> bool:
    pattern = "".join(".*" if token == "**" else "[^/]*" if token == "*" else re.escape(token)
                      for token in re.split(r"(\*\*|\*)", key))
    return re.fullmatch(pattern.replace("/.*", "(/.*)?", 1) if key.startswith("/**") else pattern,
                        node_name) is not None


class SolverThread:
    """The thread a node runs its long work in (the estimator's updates), so that the executor
    keeps taking input: it runs `run(*job)` for each job `next_job()` returns (None: nothing
    ready), when woken and every POLL_PERIOD_S (for the scheduler's timeouts). An exception of
    one job is logged and the thread goes on. `stop` waits STOP_WAIT_S for a running job, then
    leaves the (daemon) thread behind."""

    POLL_PERIOD_S = 0.02
    STOP_WAIT_S = 2.0

    def __init__(self, next_job: Callable[[], tuple | None], run: Callable[..., None], logger) -> None:
        self._next_job, self._run, self._logger = next_job, run, logger
        self._wakeup, self.stopping = threading.Event(), False
        self._thread = threading.Thread(target=self._loop, name="meshfg-solver", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Look for a ready job now."""
        self._wakeup.set()

    def stop(self) -> None:
        """Stop taking jobs (`stopping`: a running job publishes nothing more), wait for it a while."""
        self.stopping = True
        self._wakeup.set()
        self._thread.join(self.STOP_WAIT_S)
        if self._thread.is_alive():
            self._logger.warning(f"an update still runs after {self.STOP_WAIT_S:g} s: left behind at shutdown")

    def _loop(self) -> None:
        while not self.stopping:
            self._wakeup.wait(self.POLL_PERIOD_S)
            self._wakeup.clear()
            while not self.stopping and (job := self._next_job()) is not None:
                try:
                    self._run(*job)
                except Exception as error:  # noqa: BLE001 - the thread must outlive any one failure
                    self._logger.error(f"solver thread: {error!r}")
