# observer_ros.outputs.staging: a tool's output written aside, then put in place whole.
"""
Outputs that are either the previous ones or a complete new set, whatever interrupts a tool.

A tool writes its folder of results into a stage beside it (``.<name>.<tool>-<pid>-<n>.new``,
same file system), seals it (the ownership marker of :mod:`.outputs`), then puts it in
place with the signals that end a tool (SIGINT, SIGTERM, SIGHUP) held back:

- no earlier output: the stage is renamed to the folder (one ``rename``);
- an earlier output of the same tool (``--force``): the files the user added to it are
  hard-linked into the stage (their bytes are not copied; a folder of the user's is moved
  after), the stage and the folder are exchanged in one ``renameat2(RENAME_EXCHANGE)``
  (where the file system lacks it: two renames, the old folder first set aside as
  ``.<name>.<tool>-<pid>-<n>.old``), and the old files are deleted.

An interrupted tool (Ctrl-C, SIGTERM, a crash) leaves the folder as it was; its stage is
removed on the way out, or, after a SIGKILL, by the next run of the tool for the same
folder (a stage whose process is gone). A file in such a stage that has no other name (a
user's file moved there in the instant before a SIGKILL) is never deleted: it is left,
and named.

:func:`write_new_file` does the same for one file that must never be overwritten (the
tuned vehicle file, ``<bag>_slow_poles.yaml``): written under a temporary name, then
linked to its name, which fails if the name exists.

"""

import contextlib
import ctypes
import json
import os
from pathlib import Path
import secrets
import signal

from .folders import check_output, MARKER, read_marker_text, seal_output
from ..bag.errors import BagToolError

__all__ = ['StagedOutput', 'write_new_file', 'STAGE_MARKER']

STAGE_MARKER = '.observer_ros_stage.json'
_SIGNALS = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a, b):
    """Swap two paths atomically (Linux renameat2); False when the system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                          ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (22, 38, 95):     # EINVAL, ENOSYS, EOPNOTSUPP: not on this file system
        return False
    raise OSError(err, os.strerror(err), str(a))


@contextlib.contextmanager
def _signals_held():
    """Hold back SIGINT, SIGTERM and SIGHUP (delivered when the block ends)."""
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    except (AttributeError, ValueError, OSError):     # not the main interpreter, or no POSIX
        old = None
    try:
        yield
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _stages(out, tool):
    """Return the stages (and set-aside old folders) of ``tool`` for ``out``."""
    prefix = f'.{out.name}.{tool}-'
    try:
        entries = list(out.parent.iterdir())
    except OSError:
        return []
    return [p for p in entries if p.name.startswith(prefix) and
            p.name.endswith(('.new', '.old')) and p.is_dir() and not p.is_symlink()]


def _read_json(path, key, default):
    try:
        value = json.loads(read_marker_text(path)).get(key, default)
    except (OSError, ValueError, AttributeError):
        return None
    return value


def _remove_tree(path):
    """
    Delete a stage (or a set-aside old output): never a user's file that has no other name.

    The tool's files: the markers, the files its output marker lists, and, in a stage,
    every file but the users' it links in at the end (named in the stage marker). A user's
    file whose only name is here is kept; returns the paths kept.
    """
    listed = _read_json(path / MARKER, 'files', {}) or {}
    users = _read_json(path / STAGE_MARKER, 'users', [])
    kept = []
    for root, dirs, files in os.walk(path, topdown=False):
        for name in files:
            p = Path(root) / name
            rel = p.relative_to(path).as_posix()
            if rel in (STAGE_MARKER, MARKER, MARKER + '.tmp'):
                continue                    # last: they say what the rest is
            ours = rel in listed or (users is not None and rel not in users)
            if ours or os.lstat(p).st_nlink > 1:
                p.unlink()
            else:
                kept.append(p)
        for name in dirs:
            try:
                (Path(root) / name).rmdir()
            except OSError:
                pass
    if not kept:
        for name in (STAGE_MARKER, MARKER, MARKER + '.tmp'):
            (path / name).unlink(missing_ok=True)
        try:
            path.rmdir()
        except OSError:
            pass
    return kept


def _clean_stale(out, tool):
    """Remove the stages a killed run of ``tool`` left for ``out``; restore a set-aside old."""
    for stage in _stages(out, tool):
        try:
            pid = int(stage.name[len(f'.{out.name}.{tool}-'):].split('-')[0])
        except ValueError:
            continue
        if pid == os.getpid() or _alive(pid):
            continue
        if stage.name.endswith('.old') and not out.exists():
            stage.rename(out)       # killed between the two renames: the old output back
            continue
        kept = _remove_tree(stage)
        if kept:
            raise BagToolError(f'{stage} (left by an interrupted {tool}) holds '
                               f'{", ".join(str(p) for p in kept)}, which exists nowhere '
                               'else; move it back, then run again')


class StagedOutput:
    """
    A folder of results written beside ``out`` and put in its place whole.

    Use as a context manager; write into :attr:`path`, then call :meth:`commit` with the
    files written. Leaving the block without committing (an exception, Ctrl-C) removes
    the stage and leaves ``out`` as it was.

    Parameters
    ----------
    out : path-like
        The output folder.
    force : bool
        Replace an earlier output of ``tool`` (checked as :func:`.outputs.check_output`).
    tool : str
        The tool's name (``observer-eval``).

    """

    def __init__(self, out, force, tool):
        self.out = Path(os.path.abspath(out))     # '.' has no name to stage beside
        self.force = force
        self.tool = tool
        self.path = None

    def __enter__(self):
        """Check the folder, clear stale stages, make the stage."""
        if self.out.parent.is_dir():
            _clean_stale(self.out, self.tool)       # first: it may restore the old output
        check_output(self.out, self.force, self.tool)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self._name = f'.{self.out.name}.{self.tool}-{os.getpid()}-{secrets.token_hex(4)}'
        self.path = self.out.parent / f'{self._name}.new'
        if self.path.exists():
            _remove_tree(self.path)
        try:
            self.path.mkdir()
            self._write_stage_marker([])
        except BaseException:
            # Ctrl-C or SIGTERM here: __exit__ does not run for an __enter__ that raised
            if self.path.exists():
                _remove_tree(self.path)
            raise
        return self

    def __exit__(self, *exc):
        """Remove the stage unless it was committed."""
        if self.path is not None and self.path.exists():
            _remove_tree(self.path)

    def _write_stage_marker(self, users):
        (self.path / STAGE_MARKER).write_text(json.dumps(
            {'tool': self.tool, 'pid': os.getpid(), 'out': self.out.name, 'users': users}))

    def commit(self, paths):
        """
        Seal the stage with ``paths`` (the files written, in the stage) and put it in place.

        Returns the paths as they are in ``out``.
        """
        stage, out = self.path, self.out
        seal_output(stage, self.tool, paths)
        (stage / STAGE_MARKER).unlink()
        moved = [out / Path(p).relative_to(stage) for p in paths]
        with _signals_held():
            if not out.exists() and not out.is_symlink():
                stage.rename(out)
                self.path = None
                return moved
            # again, as the user asked: another run may have written it meanwhile
            owned = set(check_output(out, self.force, self.tool))
            files, folders = _users_entries(out, owned)
            self._write_stage_marker(files)
            for rel in files + folders:
                (stage / rel).parent.mkdir(parents=True, exist_ok=True)
            for rel in files:
                try:
                    os.link(out / rel, stage / rel, follow_symlinks=False)
                except FileExistsError:
                    raise BagToolError(f'{out / rel} was not written by {self.tool} and '
                                       'would be replaced; nothing changed (move it away '
                                       'or choose --out)') from None
            old = out.parent / f'{self._name}.old'
            if _exchange(stage, out):
                old = stage
            else:
                out.rename(old)
                stage.rename(out)
            self.path = None
            for rel in folders:
                (old / rel).rename(out / rel)
            (out / STAGE_MARKER).unlink(missing_ok=True)
            kept = _remove_tree(old)
        if kept:
            raise BagToolError(f'{old} holds {", ".join(map(str, kept))} (not written by '
                               f'{self.tool}); move it back into {out}')
        return moved


def _users_entries(out, owned):
    """
    Return the user's files and folders in an output folder (relative paths).

    Files: every file (or link) the marker does not list as the tool's, at any depth.
    Folders: those holding no file of the tool's, taken whole.
    """
    files, folders = [], []
    for root, dirs, names in os.walk(out):
        rel_root = Path(root).relative_to(out)
        for name in list(dirs):
            rel = (rel_root / name).as_posix()
            if (Path(root) / name).is_symlink():
                files.append(rel)
                dirs.remove(name)
            elif not any(o.startswith(rel + '/') for o in owned):
                folders.append(rel)
                dirs.remove(name)
        for name in names:
            rel = (rel_root / name).as_posix()
            if rel in owned or rel in (MARKER, MARKER + '.tmp', STAGE_MARKER):
                continue
            files.append(rel)
    return files, folders


def write_new_file(path, text):
    """
    Write ``text`` to a new file ``path`` whole, never over an existing one.

    Written to a temporary name beside it, then linked to ``path`` (which fails if it
    exists): a reader never sees a partial file, and an interrupted write leaves none.

    Raises
    ------
    FileExistsError
        ``path`` exists.

    """
    path = Path(path)
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    tmp.unlink(missing_ok=True)
    try:
        with open(tmp, 'x') as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.link(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
