# observer_ros.tools.interrupt: Ctrl-C (or SIGTERM) in a tool that runs node processes.
"""
SIGINT and SIGTERM stop a tool that runs node processes (``observer-run``) cleanly.

:func:`handling` makes the first SIGINT or SIGTERM raise :class:`RunInterrupted` in the main
thread, except inside :func:`deferred` sections (starting a process and recording it,
stopping every process): there it is raised when the section ends, so that no process is
started without being recorded, and every one is stopped. Later signals are ignored (a
terminal's Ctrl-C signals the whole process group; a node stops on its own signal).

"""

import contextlib
import signal
import threading

__all__ = ['RunInterrupted', 'handling', 'deferred']

_state = {'depth': 0, 'signal': None, 'raised': False}


class RunInterrupted(Exception):
    """SIGINT or SIGTERM stopped the tool; ``exit_codes`` are its processes' statuses."""

    def __init__(self, signum):
        self.signal_name = signal.Signals(signum).name
        self.exit_codes = {}
        super().__init__(f'interrupted by {self.signal_name}')


def _raise():
    _state['raised'] = True
    raise RunInterrupted(_state['signal'])


def _on_signal(signum, frame):
    if _state['signal'] is not None:
        return      # one interruption is enough
    _state['signal'] = signum
    if not _state['depth']:
        _raise()


@contextlib.contextmanager
def handling():
    """
    While the block runs, the first SIGINT or SIGTERM raises RunInterrupted.

    The handlers in place before are put back when the block ends (the main thread only;
    elsewhere the block runs without them).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _state.update(depth=0, signal=None, raised=False)
    old = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def deferred():
    """Hold a signal back while the block runs; raise it (once) when the block ends."""
    _state['depth'] += 1
    try:
        yield
    finally:
        _state['depth'] -= 1
    if not _state['depth'] and _state['signal'] is not None and not _state['raised']:
        _raise()
