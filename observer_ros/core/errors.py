# observer_ros.core.errors: the exception classes of the ROS-free core.
"""Exception classes raised by observer_ros, and how a command-line tool reports them."""

import functools
import os
import sys

__all__ = ['ObserverError', 'DimensionError', 'NotObservableError',
           'NotDetectableError', 'NotControllableError', 'DesignError',
           'VehicleFileError', 'ObserverDesignWarning', 'DesignVerificationError',
           'error_text', 'quiet_on_closed_pipe', 'CLOSED_PIPE_STATUS']

# a tool whose reader left (``observer-eval ... | head``) exits as one SIGPIPE ended: 128 + 13
CLOSED_PIPE_STATUS = 141


class ObserverError(Exception):
    """Base class of every error raised by observer_ros."""


class DimensionError(ObserverError, ValueError):
    """A matrix or vector has the wrong shape ("C has 3 columns; expected 2")."""


class NotObservableError(ObserverError, ValueError):
    """The pair (A, C) is not observable where observability is required."""


class NotDetectableError(NotObservableError):
    """The pair (A, C) has an unobservable mode that is not stable."""


class NotControllableError(ObserverError, ValueError):
    """The pair (A, B) is not controllable where controllability is required."""


class DesignError(ObserverError, ValueError):
    """A gain cannot be designed as asked (bad poles, infeasible placement, ...)."""


class VehicleFileError(ObserverError, ValueError):
    """A vehicle parameter file is invalid; the message names the offending field."""


class ObserverDesignWarning(UserWarning):
    """A design went through but is doubtful (inaccurate pole placement, slow observer, ...)."""


class DesignVerificationError(DesignError):
    """A designed or given gain fails verification: an achieved pole is unstable or misplaced."""


def error_text(err):
    """
    Return an exception as one line for an ``error:`` message.

    An OSError says where and why in words (``out/results.txt: Read-only file system``),
    not Python's ``[Errno 30] Read-only file system: 'out/results.txt'``; any other
    exception, its first line.
    """
    if isinstance(err, OSError) and err.strerror:
        where = err.filename if err.filename is not None else ''
        if err.filename2 is not None:
            where = f'{err.filename} -> {err.filename2}'
        return f'{where}: {err.strerror}' if where else err.strerror
    text = str(err).splitlines()[0] if str(err) else type(err).__name__
    return text


def quiet_on_closed_pipe(main):
    """
    Wrap a tool's ``main``: when its output's reader leaves, end without a traceback.

    ``observer-design v.yaml | head`` closes the pipe after ten lines; the next ``print``
    raises BrokenPipeError (and Python's final flush of stdout another). What was written
    (output folders included) stays; the rest of stdout goes to ``/dev/null`` and the tool
    exits :data:`CLOSED_PIPE_STATUS`, as a shell tool ended by SIGPIPE does. A closed pipe
    that ``main`` itself reported (an ``error:`` line) keeps its status.
    """
    @functools.wraps(main)
    def run(*args, **kwargs):
        try:
            status = main(*args, **kwargs)
        except BrokenPipeError:
            status = CLOSED_PIPE_STATUS
        try:
            sys.stdout.flush()
            return status
        except BrokenPipeError:
            status = status or CLOSED_PIPE_STATUS
        except (OSError, ValueError):       # stdout closed or gone: nothing to flush
            return status
        try:        # Python flushes stdout once more at exit: let that go nowhere
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, ValueError, AttributeError):
            pass
        return status
    return run
