# observer_ros.nodes.runner: how a node process runs, from rclpy.init to a clean exit.
"""
Run the package's nodes in a process: init, build, spin, stop, shut down; the exit status.

:func:`run_nodes` is every node executable's ``main`` (and the container's): ``--help``
and the params files are handled first (:func:`init_ros`), the nodes are built, spun in
one executor (:func:`make_executor`) in short slices (:func:`spin_until`), and stopped
when SIGINT or SIGTERM came (:mod:`observer_ros.nodes.signals`) or a node's work is done
(the simulator at the end of its run). Then, in this order: the executor is shut down,
the nodes are destroyed, the context is shut down; the process exits 0. A file a node
cannot use exits 2 with one ``error:`` line; anything else exits 1 with its traceback.

"""

import os
import sys
import traceback
import warnings

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerOptions

from . import signals
from .command_line import check_command_line, program_name, regular_params_files
from ..core.errors import error_text, ObserverError
from ..ros_names import check_domain_id

__all__ = ['EXECUTOR_ENV', 'EXECUTORS', 'make_executor', 'spin_until', 'exit_status',
           'init_ros', 'run_node', 'run_nodes']

RCLError = _rclpy.RCLError

# Which executor spins the nodes: OBSERVER_ROS_EXECUTOR=events (default) or single_threaded.
EXECUTOR_ENV = 'OBSERVER_ROS_EXECUTOR'
EXECUTORS = ('events', 'single_threaded')


def make_executor(kind=None):
    """
    Return the executor the package's nodes spin in, and its name.

    ``events`` (the default): rclpy's C++ ``EventsExecutor`` (rclpy.experimental, in
    Jazzy since rclpy 7.1.4). It dispatches each ready callback from C++ instead of
    rebuilding a wait set in Python on every spin, which halves the latency and the CPU
    per message of a small node here (benchmarks/README.md, P1 and P2). It ignores callback
    groups; the nodes of this package use one group each. ``single_threaded``: rclpy's
    ``SingleThreadedExecutor``, also used when rclpy has no EventsExecutor.

    Parameters
    ----------
    kind : str, optional
        ``events`` or ``single_threaded``; default ``$OBSERVER_ROS_EXECUTOR``, else
        ``events``.

    """
    kind = kind or os.environ.get(EXECUTOR_ENV) or 'events'
    if kind not in EXECUTORS:
        raise ObserverError(f'{EXECUTOR_ENV}={kind!r}: expected one of {list(EXECUTORS)}')
    if kind == 'events':
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:     # rclpy before 7.1.4
            kind = 'single_threaded'
        else:
            return EventsExecutor(), kind
    from rclpy.executors import SingleThreadedExecutor
    return SingleThreadedExecutor(), kind


def spin_until(executor, stop=None, period=0.1):
    """
    Spin until the context shuts down, a stop signal came, or ``stop()`` is true.

    ``spin_once`` with a timeout rather than ``executor.spin()`` (or ``rclpy.spin``):
    with rclpy 7.1.6 from PyPI, the EventsExecutor's ``spin()`` ran at 100 % CPU without
    running a single callback here; ``spin_once`` works, and returning to Python every
    ``period`` seconds lets the signal handlers run and the loop see what they recorded.

    """
    context = executor.context
    received = signals.RECEIVED
    while context.ok() and not received and not (stop and stop()):
        executor.spin_once(timeout_sec=period)


def exit_status(err, name):
    """
    Report the exception that ended a node process; return the process's exit status.

    0 for a shutdown (the context shut down by someone else); 2 for a file or parameter
    the node cannot use (one ``error:`` line, naming ``name`` when the error does not
    already: no log line besides, so a refusal reads the same as the tools'); 1 for
    anything else (with its traceback).

    """
    if isinstance(err, (KeyboardInterrupt, ExternalShutdownException)):
        return 0
    if isinstance(err, ObserverError):
        text = str(err)
        if name != 'observer_ros' and name not in text:     # which node of a container
            text = f'{name}: {text}'
        print(f'error: {text}', file=sys.stderr)
        return 2
    traceback.print_exception(err)
    return 1


def init_ros(node_class, args=None, **init_options):
    """
    Handle ``--help``, check the params files, then ``rclpy.init``; None when it went on.

    Returns the exit status instead when the process should end now: 0 after ``--help``
    or a stop signal, 2 (one ``error:`` line) for a params file the package's loader or
    ROS's parser refuses. The stop signals are the package's (:mod:`.signals`): rclpy's
    own handlers are not installed.

    Parameters
    ----------
    node_class : type
        The node (its module's docstring is the help's description of its topics).
    args : list of str, optional
        The command line (``sys.argv`` by default), ROS arguments included.
    **init_options
        Passed to ``rclpy.init``.

    """
    signals.install()
    argv = list(sys.argv if args is None else args)
    module = node_class.__module__
    if module == '__main__':    # python -m observer_ros.nodes.<node>
        module = getattr(sys.modules['__main__'].__spec__, 'name', module)
    code = check_command_line(argv[1:], program_name(module.rsplit('.', 1)[-1]), module,
                              sys.modules[node_class.__module__].__doc__)
    if code is not None:    # --help, or a params file the loader refuses
        return code
    if signals.requested():     # stopped while the modules were imported
        signals.ignore()        # the process only exits now
        return 0
    init_options.setdefault('signal_handler_options', SignalHandlerOptions.NO)
    try:
        check_domain_id()       # Fast DDS would exit 1 with only its own log line
        ros_argv = regular_params_files(argv)       # a pipe was read once: rclpy reads a copy
    except (ObserverError, OSError) as err:
        print(f'error: {error_text(err)}', file=sys.stderr)
        return 2
    try:
        rclpy.init(args=args if ros_argv == argv else ros_argv, **init_options)
    except RCLError as err:     # e.g. a params file ROS's parser refuses: one line
        print(f'error: {" ".join(str(err).split())}', file=sys.stderr)
        return 2
    return None


def run_node(node_factory, args=None):
    """
    Run a node as ros2/demos do: init, spin, clean shutdown; exit 2 on an unusable file.

    Parameters
    ----------
    node_factory : callable
        Builds the node (after rclpy.init).
    args : list of str, optional
        Command-line arguments (ROS arguments included).

    """
    return run_nodes([node_factory], args)


def run_nodes(node_factories, args=None, names=None):
    """
    Run nodes in one process and one executor: :func:`run_node` for several.

    The nodes are built in order; a file one of them cannot use stops the process (exit 2,
    one ``error:`` line) before the executor spins. A stop signal ends the process with 0
    (after the node being built, if it came then). A node that sets its ``exit_code`` (the
    simulator when its run is done) ends the process with that code, after its callback
    has returned (an exception raised in a callback would be logged by rclpy as FATAL with
    a traceback).

    Parameters
    ----------
    node_factories : sequence of callable
        Build the nodes (after rclpy.init).
    args : list of str, optional
        Command-line arguments (ROS arguments included).
    names : sequence of str, optional
        The nodes' names for a start-up error (default ``observer_ros``).

    """
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    code = init_ros(node_factories[0], args)
    if code is not None:
        return code
    nodes = []
    executor = None
    code = 0
    try:
        for factory in node_factories:
            if signals.requested():
                break
            nodes.append(factory())
        executor, kind = make_executor()
        for node in nodes:
            executor.add_node(node)
        # asked after every callback: one attribute per node, no generator (a generator
        # here was 2 % of the observer's CPU in P2)
        ending = [node for node in nodes if hasattr(node, 'exit_code')]
        watches = [node.callback_watch for node in nodes if hasattr(node, 'callback_watch')]
        if kind != 'events':
            for watch in watches:
                watch.may_overrun = False

        def stop():
            for node in ending:
                if node.exit_code is not None:
                    return True
            for watch in watches:
                if watch.overrun:
                    return True
            return False
        while True:
            spin_until(executor, stop=stop if ending or watches else None)
            if signals.requested() or not executor.context.ok() or \
                    not any(watch.overrun for watch in watches):
                break
            executor = _leave_events_executor(executor, nodes, watches)
        code = next((node.exit_code for node in ending if node.exit_code is not None), 0)
    except Exception as err:   # noqa: BLE001 - reported by exit_status
        failed = len(nodes) if len(nodes) < len(node_factories) else None
        code = exit_status(err, names[failed] if names and failed is not None else
                           'observer_ros')
    finally:
        if executor is not None:
            executor.shutdown()
        for node in reversed(nodes):    # managed nodes: the shutdown transition
            _finish(node)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
        # from here the process only exits: a signal now must not kill it (the interpreter
        # puts SIGINT and SIGTERM back to their defaults while it finalises)
        signals.ignore()
    return code


def _finish(node):
    """Take a managed node through its shutdown transition (the compensator's safe command)."""
    finish = getattr(node, 'finish', None)
    if finish is None:
        return
    try:
        finish()
    except Exception:   # noqa: BLE001 - the process ends either way; the node says why
        node.get_logger().error(f'shutdown transition failed:\n{traceback.format_exc()}')


def _leave_events_executor(executor, nodes, watches):
    """
    Go on in rclpy's wait-set executor: a flood came (nodes/callback_watch.py).

    Shutting the EventsExecutor down drops the events it queued (one per message received,
    without a bound) at once; the wait-set executor takes what the readers hold, so the
    memory is bounded by their depth.
    """
    from rclpy.executors import SingleThreadedExecutor
    context = executor.context
    executor.shutdown(5.0)
    executor = SingleThreadedExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    for watch in watches:
        watch.overrun = watch.may_overrun = False
    nodes[0].get_logger().error(
        "a flood of messages: the events executor's queue dropped, going on with the wait-set "
        "executor (bounded by the readers' depth)")
    return executor
