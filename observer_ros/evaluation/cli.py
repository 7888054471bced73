# observer_ros.evaluation.cli: what the offline command-line tools share.
"""
The parts that ``observer-eval``, ``observer-eval-batch`` and ``observer-tune`` share.

A vehicle given as a file or as a loaded vehicle (:func:`resolve_vehicle`), the progress bar
on stderr (:class:`Progress`), the default output folder next to a bag
(:func:`default_out`), SIGTERM ending a tool as Ctrl-C does (:func:`stop_on_sigterm`), the
one ``error:`` line with the exit status (:func:`tool_error`) and the report, warnings and
files of a finished run (:func:`tool_done`).

"""
import os
from pathlib import Path
import signal
import sys
import threading
import time

from ..core.errors import error_text

__all__ = ['IN_MEMORY_HELP', 'resolve_vehicle', 'Progress', 'default_out', 'Terminated',
           'stop_on_sigterm', 'tool_error', 'tool_done']

IN_MEMORY_HELP = ("keep the replays' rows in memory (default: in temporary files in TMPDIR, "
                  'a block at a time, so that a long bag fits in memory)')


def resolve_vehicle(vehicle, overrides=()):
    """
    Return the vehicle to replay, with ``KEY:=VALUE`` overrides applied.

    ``vehicle`` is a vehicle file's path (loaded and checked, the overrides with it) or a
    loaded :class:`~observer_ros.vehicle.Vehicle` (returned as it is without overrides).
    Raises :class:`~observer_ros.core.errors.ObserverError` naming the offending field.

    """
    from ..vehicle import (apply_overrides, load_vehicle, vehicle_from_parameters,
                           vehicle_to_parameters)
    if isinstance(vehicle, (str, os.PathLike)):
        return load_vehicle(vehicle, overrides=list(overrides) or None)
    if not overrides:
        return vehicle
    flat = apply_overrides(vehicle_to_parameters(vehicle), list(overrides))
    return vehicle_from_parameters(flat, source=f'vehicle {vehicle.name}')


class Progress:
    """A one-line text progress bar on stderr: ``progress(label, done, total)``."""

    def __init__(self, enabled, stream=sys.stderr):
        """Write to ``stream`` (stderr) when ``enabled``, else nothing."""
        self.enabled = enabled
        self.stream = stream
        self.label = None
        self.last = 0.0

    def __call__(self, label, done, total):
        """Show ``done`` of ``total`` for ``label`` (at most every 0.2 s, and the last)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if label == self.label and now - self.last < 0.2 and done < total:
            return
        if label != self.label and self.label is not None:
            self.stream.write('\n')
        self.label, self.last = label, now
        if total:
            frac = min(1.0, done / total)
            bar = '#' * int(30 * frac) + '.' * (30 - int(30 * frac))
            text = f'\r{label:<20} [{bar}] {frac * 100:5.1f}% {done}/{total}'
        else:
            text = f'\r{label:<20} {done}'
        self.stream.write(text)
        self.stream.flush()

    def finish(self):
        """End the line of the current label."""
        if self.enabled and self.label is not None:
            self.stream.write('\n')
            self.stream.flush()
            self.label = None


def default_out(bag, suffix='_eval'):
    """
    Return a tool's default output folder: ``<bag><suffix>`` next to the bag directory.

    For a storage file inside a bag directory (one with metadata.yaml) that directory is
    the bag; a bare ``.mcap``/``.db3`` file gets ``<stem><suffix>`` next to it. The folder
    does not depend on the current directory.

    """
    bag = Path(bag)
    if bag.name in ('', '.', '..'):
        bag = bag.resolve()
    if bag.is_file():
        if not (bag.parent / 'metadata.yaml').is_file():
            return bag.with_name(f'{bag.stem or "bag"}{suffix}')
        bag = bag.parent
        if bag.name in ('', '.', '..'):
            bag = bag.resolve()
    return bag.parent / f'{bag.name or "bag"}{suffix}'


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the tool is, so that its clean-up runs (an unfinished stage)."""


def stop_on_sigterm():
    """
    Make SIGTERM end a tool as Ctrl-C does: its ``finally`` blocks run, exit status 143.

    Python's default (die at once) left a tool's unfinished output stage behind.
    """
    def on_sigterm(signum, frame):
        raise Terminated()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, on_sigterm)


def tool_error(progress, err):
    """
    End a command-line tool on ``err``: one ``error:`` line; return the exit status.

    2 for an ObserverError or OSError (its first line), 130 for Ctrl-C, 143 for SIGTERM.

    """
    progress.finish()
    if isinstance(err, Terminated):
        print('error: terminated (SIGTERM)', file=sys.stderr)
        return 143
    if isinstance(err, KeyboardInterrupt):
        print('error: interrupted', file=sys.stderr)
        return 130
    print(f'error: {error_text(err)}', file=sys.stderr)
    return 2


def tool_done(report, warnings, out, files, seconds):
    """
    End a command-line tool's successful run; return the exit status 0.

    Prints ``report`` on stdout, each of ``warnings`` as a ``warning:`` line on stderr, and
    the output folder ``out`` with the names of ``files`` and the run's ``seconds``.

    """
    print(report)
    for text in warnings:
        print(f'warning: {text}', file=sys.stderr)
    print(f'\nwritten to {out}/ ({", ".join(f.name for f in files)}) in {seconds:.1f} s')
    return 0
