# observer_ros.outputs.folders: output folders a tool replaces only when it proves it wrote them.
"""
Output folders with an ownership marker.

A tool that writes a folder of results (``observer-eval``) writes a marker file,
``.observer_ros_output.json``, naming the tool and every file it wrote with its size and
modification time. ``--force`` then replaces only such a folder, and only those files,
after checking them all before anything is touched:

- a folder without the marker (whatever else it holds, a ``results.json`` included) is
  refused;
- a file the tool wrote that was since changed (size or time), or replaced by a link, is
  refused;
- files the user added next to the tool's files are kept (never deleted), unless one has
  the name of a file the tool writes, or is a link: then the folder is refused;
- the folder itself being a link is refused (a link is never followed out of the folder).

"""

import errno
import json
import os
from pathlib import Path
import stat

from ..bag.errors import BagToolError

__all__ = ['MARKER', 'TOOL_FILES', 'check_output', 'prepare_output', 'seal_output',
           'mark_output', 'read_marker_text', 'MAX_MARKER_BYTES']

MARKER = '.observer_ros_output.json'

# The names each tool may write in its folder: one of them there that the tool did not
# write (a user's file, a link) would be overwritten or written through, so it is refused.
TOOL_FILES = {
    'observer-eval': ('results.txt', 'results.csv', 'results.json', 'states.png',
                      'error_norm.png', 'residuals.png', 'results_bag'),
    'observer-tune': ('tune.txt', 'tune.json', 'search.csv', 'autocovariance.png',
                      'search.png', '.identified.yaml'),
    'observer-run': tuple(f'{node}.log' for node in (
        'plant_simulator', 'observer_node', 'compensator', 'container', 'recorder')),
}


# a marker lists a folder's files: a few kB; more is not one of ours
MAX_MARKER_BYTES = 1 << 20


def read_marker_text(path):
    """
    Return a marker file's text; ValueError when it is not a regular file or too big.

    Opened without following a link and without blocking (a FIFO named like a marker would
    hold ``--force`` forever), then checked to be a regular file before it is read.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise ValueError('the marker is a link') from None
        raise
    with os.fdopen(fd, 'rb') as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise ValueError('the marker is not a regular file')
        data = f.read(MAX_MARKER_BYTES + 1)
    if len(data) > MAX_MARKER_BYTES:
        raise ValueError(f'the marker has more than {MAX_MARKER_BYTES} bytes')
    return data.decode('utf-8')


def _read_marker(out, tool):
    """Return the marker's dict; raise BagToolError when the folder is not the tool's."""
    marker = out / MARKER
    try:
        data = json.loads(read_marker_text(marker))
        if data.get('tool') != tool or not isinstance(data.get('files'), dict):
            raise ValueError(f'the marker names {data.get("tool")!r}')
    except (OSError, ValueError, AttributeError) as err:
        reason = 'no marker' if not marker.exists() else str(err)
        raise BagToolError(f'{out} exists and is not an {tool} output folder ({reason}: '
                           f'{MARKER}); not touching it even with --force') from None
    return data


def _owned_files(out, tool):
    """
    Return the files of ``out`` the tool wrote and that are unchanged since (relative paths).

    Raises BagToolError, before anything is touched, for a changed or linked file.

    """
    data = _read_marker(out, tool)
    owned = []
    for rel, (size, mtime_ns) in sorted(data['files'].items()):
        path = out / rel
        if '..' in Path(rel).parts or Path(rel).is_absolute():
            raise BagToolError(f'{out}: the marker names {rel!r}, outside the folder; '
                               'not touching it')
        if path.is_symlink():
            raise BagToolError(f'{path} is now a link, not the file {tool} wrote; '
                               'not touching the folder')
        if not path.exists():
            continue
        st = path.stat()
        if not path.is_file() or (st.st_size, st.st_mtime_ns) != (size, mtime_ns):
            raise BagToolError(f'{path} was changed after {tool} wrote it; not touching '
                               'the folder (move it away or choose --out)')
        owned.append(rel)
    ours = {Path(rel).parts[0] for rel in owned}
    for entry in sorted(out.iterdir()):
        if entry.name in ours or entry.name in (MARKER, MARKER + '.tmp'):
            continue
        if entry.is_symlink():
            raise BagToolError(f'{entry} is a link {tool} did not make; refusing to write '
                               'next to it (move it away or choose --out)')
        if entry.name in TOOL_FILES.get(tool, ()):
            raise BagToolError(f'{entry} was not written by {tool} and would be overwritten; '
                               'not touching the folder (move it away or choose --out)')
    return owned


def check_output(out, force, tool):
    """
    Check, touching nothing, that ``out`` may be written (it is new, or ``force`` and ours).

    Parameters
    ----------
    out : path-like
        The output folder.
    force : bool
        Replace an earlier output of the same tool.
    tool : str
        The tool's name (``observer-eval``), as written in the marker.

    Returns
    -------
    list of str
        The files of an earlier output that ``prepare_output`` will delete.

    Raises
    ------
    BagToolError
        The folder exists without ``force``, is a link or not a folder, has no marker of
        ``tool``, or a file the tool wrote there was changed since.

    """
    out = Path(out)
    if out.is_symlink():
        raise BagToolError(f'{out} is a link; refusing to write through it')
    _check_writable(out)
    if not out.exists():
        return []
    if not force:
        raise BagToolError(f'{out} exists; refusing to overwrite it (use --force or '
                           '--out DIR)')
    if not out.is_dir():
        raise BagToolError(f'{out} exists and is not a folder')
    return _owned_files(out, tool)


def _check_writable(out):
    """Refuse, before any work, an output whose folder cannot be written (read-only, ...)."""
    parent = Path(os.path.abspath(out)).parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if os.access(parent, os.W_OK | os.X_OK):
        return
    try:
        readonly = os.statvfs(parent).f_flag & os.ST_RDONLY
    except OSError:
        readonly = False
    why = 'Read-only file system' if readonly else 'Permission denied'
    raise BagToolError(f'{out}: cannot write in {parent}: {why}')


def prepare_output(out, force, tool):
    """
    Make ``out`` ready for a new output: check, delete the earlier output's files, mark it.

    Files the user added are kept. The marker is written (with no files) before anything
    else, so an interrupted run leaves files that a later ``--force`` refuses to delete
    (they are not recorded as the tool's).

    Returns
    -------
    Path

    """
    out = Path(out)
    owned = check_output(out, force, tool)
    for rel in owned:
        (out / rel).unlink()
    # folders the tool made (results_bag/) go when they are empty; a user's file keeps them
    for folder in sorted({(out / rel).parent for rel in owned}, key=lambda p: -len(p.parts)):
        if folder != out:
            try:
                folder.rmdir()
            except OSError:
                pass
    out.mkdir(parents=True, exist_ok=True)
    _write_marker(out, tool, {})
    return out


def seal_output(out, tool, paths):
    """
    Record the files written to ``out`` (a folder among ``paths``: every file in it).

    Parameters
    ----------
    out : path-like
        The output folder made by :func:`prepare_output`.
    tool : str
        The tool's name.
    paths : iterable of path-like
        The files and folders written.

    """
    out = Path(out)
    files = {}
    for path in map(Path, paths):
        found = sorted(p for p in path.rglob('*') if p.is_file()) if path.is_dir() else [path]
        for p in found:
            if p.is_file() and not p.is_symlink():
                st = p.stat()
                files[p.relative_to(out).as_posix()] = [st.st_size, st.st_mtime_ns]
    _write_marker(out, tool, files)


def mark_output(out, tool):
    """Mark an existing folder as ``tool``'s, with no file of its yet (see seal_output)."""
    _write_marker(Path(out), tool, {})


def _write_marker(out, tool, files):
    tmp = out / (MARKER + '.tmp')
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    with os.fdopen(fd, 'w') as f:
        json.dump({'tool': tool, 'files': files}, f, indent=1, sort_keys=True)
        f.write('\n')
    tmp.replace(out / MARKER)
