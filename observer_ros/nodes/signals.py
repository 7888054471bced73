# observer_ros.nodes.signals: SIGINT and SIGTERM ask a node process to stop (no exception).
"""
SIGINT and SIGTERM request a stop; the process stops between two spins of its executor.

A node process handles both signals itself (``rclpy.init`` with
``SignalHandlerOptions.NO``): the handler only records the signal, and the main loop,
which spins the executor in short slices, sees it after the callback in progress has
returned. Then the executor is stopped, the managed nodes go through their shutdown
transition, the nodes are destroyed and the context shut down, in that order, and the
process exits 0. Nothing is raised inside a callback, and the context is never shut down
under a callback that is publishing (rclpy's own handlers do both: a ``KeyboardInterrupt``
in whatever callback runs, and the context shut down from another thread, so that a
``publish`` in progress fails).

A second signal (Ctrl-C signals the whole process group, and ``ros2 launch`` then signals
each node again) is recorded too and changes nothing. The handlers are installed by the
executables' entry points (:mod:`observer_ros.nodes.entry`) before the node's modules are
imported, which takes seconds on a loaded machine (half a minute on a 2-core host at a load
of 30): a signal while those modules are imported ends the process at once with status 0
(:func:`exit_while_importing`; nothing is open yet, no ROS context, no file), and one while
the node is built stops it as above. A tool that starts node processes
(``observer-run``) starts them with both signals blocked until then
(:func:`block_until_installed`), so that not even the interpreter's own start-up is
exposed.

This module imports nothing but the standard library.

"""

import os
import signal
import threading

__all__ = ['STOP_SIGNALS', 'RECEIVED', 'install', 'block_until_installed', 'requested',
           'ignore', 'exit_while_importing']

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: the signals received so far (a list: truthy once one came; cheap to test per spin)
RECEIVED = []

# True while the entry point imports the node's modules: a stop signal then exits at once
_importing = [False]


def _on_signal(signum, frame):
    RECEIVED.append(signum)
    if _importing[0]:
        os._exit(0)     # nothing to stop yet; the imports would take seconds more


def exit_while_importing(on):
    """
    Make a stop signal end the process at once, with status 0, while ``on`` is True.

    For the import of a node's modules only (rclpy, numpy, scipy, python-control), before
    anything that would need closing exists; a signal received before (blocked, or during
    the interpreter's start) exits as soon as :func:`install` takes it.
    """
    _importing[0] = bool(on)
    if on and RECEIVED:
        os._exit(0)


def install():
    """
    Make SIGINT and SIGTERM request a stop (idempotent; the main thread only).

    Signals received before (during the imports) stay requested.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not _on_signal:
            signal.signal(sig, _on_signal)
    # delivered now if they came while blocked (block_until_installed)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


def block_until_installed():
    """
    Block SIGINT and SIGTERM (a ``preexec_fn`` for a node process started by a tool).

    A blocked signal waits, across ``exec``, until :func:`install` unblocks it: one that
    comes while the interpreter starts is then a stop request like any other, instead of
    killing the process (SIGTERM's default) or raising ``KeyboardInterrupt`` in an import.
    """
    signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)


def requested():
    """Return True once SIGINT or SIGTERM was received."""
    return bool(RECEIVED)


def ignore():
    """Ignore SIGINT and SIGTERM from now on (the process is closing; the main thread only)."""
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)
