# observer_ros.bag.errors: the one exception class of the bag tools.
"""Exception raised by the bag tools (reader, evaluation, player)."""

from ..core.errors import ObserverError

__all__ = ['BagToolError', 'BagRecoveryError']


class BagToolError(ObserverError):
    """
    A bag cannot be used as asked; the message names the file and the problem.

    Raised for a missing path, a file that is not a bag, an empty or truncated bag,
    missing topics, a topic of the wrong type, or an output folder that exists. The
    command-line tools print it as one line ``error: ...`` and exit with status 2.

    """


class BagRecoveryError(ObserverError):
    """A bag cannot be recovered; the message names the bag and the reason."""
