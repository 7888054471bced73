# observer_ros.params_file: reading a ROS 2 parameters file as ROS's own parser does.
"""
Read ROS 2 parameters files (``/**:`` then ``ros__parameters:``) into flat dicts.

What ROS's parameter parser accepts and nothing more: no anchors or aliases, no duplicate
keys, ``1e-3`` a float. Limits are checked before anything is built: what the path is
(a regular file, or a pipe read without blocking for at most :data:`STREAM_TIMEOUT` s;
never a folder or a device), the file's size (:data:`MAX_FILE_BYTES`, from its size on
disk, before it is read) and each array's length (:data:`MAX_ARRAY_LENGTH`, while it is
read). Every refusal is one :class:`VehicleFileError` naming the file and the limit. No
ROS imports.

"""

import atexit
import os
import re
import select
import stat
import tempfile
import time

import yaml

from .core.errors import VehicleFileError

__all__ = ['MAX_FILE_BYTES', 'MAX_ARRAY_LENGTH', 'MAX_NESTING', 'STREAM_TIMEOUT', 'read_text',
           'regular_file', 'check_parameters_file', 'yaml_load', 'flatten_parameters',
           'load_parameters']

# A vehicle file is a few kB (the largest here, aircraft_lateral.yaml, under 6 kB): 256 KiB
# is 40 times that, and is read in about a second on a loaded 2-core machine
MAX_FILE_BYTES = 1 << 18
# Entries of one array: the A matrix of a 100-state model
MAX_ARRAY_LENGTH = 10000
# s: a pipe (a FIFO, process substitution) must give its whole text within this time
STREAM_TIMEOUT = 5.0
# levels of mappings, sequences and values a parameters file may nest (a vehicle file: 7)
MAX_NESTING = 32


def _kind(mode):
    """Name what a non-regular file is: ``a folder``, ``a character device``, ..."""
    for test, name in ((stat.S_ISDIR, 'a folder'), (stat.S_ISCHR, 'a character device'),
                       (stat.S_ISBLK, 'a block device'), (stat.S_ISSOCK, 'a socket')):
        if test(mode):
            return name
    return 'not a regular file'


def read_text(path):
    """
    Return a parameters file's text, refusing it before reading when it cannot be one.

    What the path is, is checked (``os.stat``) before it is opened: a regular file is read
    when it is at most :data:`MAX_FILE_BYTES`; a pipe (``<(cat v.yaml)``, ``cat v.yaml |
    ... /dev/stdin``, a FIFO made by ``mkfifo``) is read without blocking, for at most
    :data:`STREAM_TIMEOUT` s, and what it gave is kept for the process (a pipe is read
    once: :func:`regular_file` gives a copy to a program that reads it again, such as
    rclpy); a folder, a device (a terminal as ``/dev/stdin``, ``/dev/zero``) or a socket is
    refused unopened.

    Raises
    ------
    VehicleFileError
        Missing or unreadable file, not a regular file or a pipe, over
        :data:`MAX_FILE_BYTES`, a pipe without a writer or whose writer does not finish
        within :data:`STREAM_TIMEOUT` s, or not UTF-8.

    """
    where = str(path)
    try:
        st = os.stat(path)
    except OSError as err:
        raise VehicleFileError(f'{where}: cannot read: {err.strerror or err}') from None
    if stat.S_ISFIFO(st.st_mode):
        key = (st.st_dev, st.st_ino)
        if key not in _STREAMS:
            _STREAMS[key] = _read_stream(path, where)
        data = _STREAMS[key]
    elif not stat.S_ISREG(st.st_mode):
        raise VehicleFileError(f'{where}: {_kind(st.st_mode)}, not a parameters file (a '
                               'regular file, or a pipe with a writer)')
    else:
        if st.st_size > MAX_FILE_BYTES:
            raise VehicleFileError(f'{where}: {st.st_size} bytes; a parameters file may have '
                                   f'at most {MAX_FILE_BYTES} (MAX_FILE_BYTES)')
        try:
            # O_NONBLOCK: if the path was swapped for a FIFO since the stat, opening it
            # does not wait for a writer (a regular file ignores the flag)
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
            with os.fdopen(fd, 'rb') as stream:
                if not stat.S_ISREG(os.fstat(stream.fileno()).st_mode):
                    raise VehicleFileError(f'{where}: changed while being opened; not read')
                data = stream.read(MAX_FILE_BYTES + 1)
        except OSError as err:
            raise VehicleFileError(f'{where}: cannot read: {err.strerror or err}') from None
    if len(data) > MAX_FILE_BYTES:      # grew since stat
        raise VehicleFileError(f'{where}: more than {MAX_FILE_BYTES} bytes (MAX_FILE_BYTES)')
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError as err:
        line = data[:err.start].count(b'\n') + 1
        raise VehicleFileError(f'{where}: not UTF-8 text (byte 0x{data[err.start]:02x} at '
                               f'offset {err.start}, line {line})') from None


# what each pipe read by this process gave, by (device, inode): a pipe is read once
_STREAMS = {}


def _read_stream(path, where):
    """Read a pipe without blocking: at most STREAM_TIMEOUT s and MAX_FILE_BYTES + 1 bytes."""
    deadline = time.monotonic() + STREAM_TIMEOUT
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)     # a FIFO: no wait for a writer
    except OSError as err:
        raise VehicleFileError(f'{where}: cannot read: {err.strerror or err}') from None
    chunks, size = [], 0
    try:
        poller = select.poll()
        poller.register(fd, select.POLLIN)
        while size <= MAX_FILE_BYTES:
            left = deadline - time.monotonic()
            # a FIFO that never had a writer is not ready (Linux): it times out here
            if left <= 0 or not poller.poll(left * 1000.0):
                what = ('no writer gave it any text' if not size else
                        f'its writer did not finish ({size} bytes so far)')
                raise VehicleFileError(
                    f'{where}: a pipe, and {what} within {STREAM_TIMEOUT:g} s '
                    '(STREAM_TIMEOUT); give a regular file, or a pipe with a writer')
            try:
                chunk = os.read(fd, 1 << 16)
            except BlockingIOError:
                continue
            if not chunk:
                break                       # the writer closed it: the whole text
            chunks.append(chunk)
            size += len(chunk)
    except OSError as err:
        raise VehicleFileError(f'{where}: cannot read: {err.strerror or err}') from None
    finally:
        os.close(fd)
    return b''.join(chunks)


def regular_file(path):
    """
    Return a path a program can open and read again: ``path``, or a copy of a pipe's text.

    A regular file is returned as it is. A pipe (``<(cat v.yaml)``) gives its text once:
    it is read (:func:`read_text`) and written to a temporary file, deleted when the
    process exits, whose path is returned (for rclpy's ``--params-file``, or for the
    nodes ``observer-run`` starts).

    Raises
    ------
    VehicleFileError
        As :func:`read_text`.

    """
    text = read_text(path)
    try:
        if stat.S_ISREG(os.stat(path).st_mode):
            return path
    except OSError:
        pass
    fd, copy = tempfile.mkstemp(prefix='observer_ros_', suffix='.yaml')
    with os.fdopen(fd, 'w', encoding='utf-8') as f:
        f.write(text)
    atexit.register(_remove, copy)
    return copy


def _remove(path):
    try:
        os.unlink(path)
    except OSError:
        pass


def check_parameters_file(path):
    """
    Check a parameters file the way the loader reads it; raise VehicleFileError if unusable.

    What a node does with each ``--params-file`` before rclpy reads it: the same limits and
    the same refusals as the offline tools, as quickly.

    """
    yaml_load(read_text(path), str(path))


_FLOAT_RE = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                            |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                            |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                            |[-+]?\.(?:inf|Inf|INF)
                            |\.(?:nan|NaN|NAN))$""", re.X)


try:    # libyaml's parser (C) under the Python composer below: 4x faster than pure Python
    from yaml._yaml import CParser as _Parser
except ImportError:     # PyYAML built without libyaml
    from yaml.parser import Parser as _Parser
    from yaml.reader import Reader as _Reader
    from yaml.scanner import Scanner as _Scanner
else:
    _Reader = _Scanner = None


class _Loader(yaml.composer.Composer, _Parser, yaml.constructor.SafeConstructor,
              yaml.resolver.Resolver):
    """
    A safe loader that reads a parameters file as ROS's parser does.

    1e-3 is a float (as in ROS); duplicate keys, anchors and aliases are refused (ROS's
    parser refuses aliases; an alias bomb would otherwise expand to gigabytes), and so is a
    sequence longer than :data:`MAX_ARRAY_LENGTH` (counted while it is read, before any
    value is built).

    """

    def __init__(self, stream):
        if _Reader is None:
            _Parser.__init__(self, stream)
        else:
            _Reader.__init__(self, stream)
            _Scanner.__init__(self)
            _Parser.__init__(self)
        yaml.composer.Composer.__init__(self)
        yaml.constructor.SafeConstructor.__init__(self)
        yaml.resolver.Resolver.__init__(self)

    def compose_node(self, parent, index):
        """Refuse anchors, aliases, over-long arrays and deep nesting as soon as they are read."""
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent) or getattr(event, 'anchor', None):
            raise yaml.composer.ComposerError(
                None, None, "anchors and aliases (&name, *name) are not allowed: ROS's "
                'parameter parser refuses them', event.start_mark)
        if isinstance(parent, yaml.SequenceNode) and index >= MAX_ARRAY_LENGTH:
            raise yaml.composer.ComposerError(
                None, None, f'an array of more than {MAX_ARRAY_LENGTH} entries '
                '(MAX_ARRAY_LENGTH)', parent.start_mark)
        # each level is a Python call (composing, building, flattening): {a: {a: ...}} 30000
        # deep was a RecursionError traceback
        self._depth = getattr(self, '_depth', 0) + 1
        try:
            if self._depth > MAX_NESTING:
                raise yaml.composer.ComposerError(
                    None, None, f'nested more than {MAX_NESTING} levels deep (MAX_NESTING)',
                    event.start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


_Loader.yaml_implicit_resolvers = {
    key: [(tag, regexp) for tag, regexp in resolvers if tag != 'tag:yaml.org,2002:float']
    for key, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver('tag:yaml.org,2002:float', _FLOAT_RE,
                              list('-+0123456789.'))
# ROS's parser (rcl_yaml_param_parser) also reads a bare y, Y, n or N as a boolean
# (PyYAML keeps them strings): `input_units: [N]` is [false] to a node.
ROS_BOOL_RE = re.compile(r'^(?:y|Y|n|N)$')
_Loader.add_implicit_resolver('tag:yaml.org,2002:bool', ROS_BOOL_RE, list('yYnN'))
_Loader.bool_values = dict(yaml.constructor.SafeConstructor.bool_values, y=True, n=False)


def _construct_mapping(loader, node, deep=False):
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    'while reading a mapping', node.start_mark,
                    f'duplicate key {key!r} (first at line {seen[key] + 1})',
                    key_node.start_mark)
            seen[key] = key_node.start_mark.line
        except TypeError:   # unhashable key: SafeLoader reports it
            pass
    return yaml.constructor.SafeConstructor.construct_mapping(loader, node, deep=deep)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def yaml_load(text, where):
    """Parse YAML as ROS's parser does (no aliases, no duplicate keys); errors name where."""
    try:
        return yaml.load(text, Loader=_Loader)   # noqa: S506 - a SafeLoader subclass
    except yaml.MarkedYAMLError as err:     # one line: the problem and where it is
        mark = err.problem_mark or err.context_mark
        at = f' (line {mark.line + 1}, column {mark.column + 1})' if mark else ''
        what = ' '.join(str(err.problem or err.context).split())
        raise VehicleFileError(f'{where}: not valid YAML: {what}{at}') from None
    except yaml.YAMLError as err:
        raise VehicleFileError(f'{where}: not valid YAML: {" ".join(str(err).split())}') \
            from None


def flatten_parameters(tree, prefix='', where='parameters'):
    """
    Flatten nested dicts to dotted parameter names.

    Parameters
    ----------
    tree : dict
        For example ``{'model': {'A': [...]}}``.
    prefix : str
        Prepended to every name (with a dot).
    where : str
        Used in error messages.

    Returns
    -------
    flat : dict
        ``{'model.A': [...]}``; values other than dicts are kept as they are.

    """
    flat = {}
    for key, value in tree.items():
        if not isinstance(key, str) or not key:
            raise VehicleFileError(f'{where}: key {key!r} under {prefix or "the top"} is not '
                                   'a parameter name')
        name = f'{prefix}.{key}' if prefix else key
        if isinstance(value, dict):
            if not value:
                raise VehicleFileError(f'{where}: {name} is an empty mapping')
            flat.update(flatten_parameters(value, name, where))
        else:
            flat[name] = value
    return flat


def _node_key_regex(key):
    """Regex matching fully qualified node names for a parameters-file node key."""
    key = key if key.startswith('/') else '/' + key
    parts = []
    for token in key.strip('/').split('/'):
        if token == '**':
            parts.append('(?:/[^/]+)*')
        else:
            parts.append('/' + '[^/]+'.join(re.escape(t) for t in token.split('*')))
    return re.compile(''.join(parts) + '$')


def load_parameters(path, node_name=None):
    """
    Read a ROS 2 parameters file into a flat dict of dotted names.

    Parameters
    ----------
    path : str or path-like
        The file (``/**:`` then ``ros__parameters:``).
    node_name : str, optional
        A node name (``observer``) or fully qualified name (``/sub1/observer``). The
        sections that apply to it are merged in the order ``/**`` and other wildcard
        keys first, then keys naming the node, each in file order. Without a node name
        only ``/**`` is read.

    Returns
    -------
    flat : dict
        Dotted parameter name to value.

    """
    where = str(path)
    doc = yaml_load(read_text(path), where)
    if not isinstance(doc, dict) or not doc:
        raise VehicleFileError(f"{where}: not a ROS 2 parameters file (expected '/**:' "
                               "then 'ros__parameters:')")
    fq = None
    if node_name:
        fq = node_name if node_name.startswith('/') else '/' + node_name
    wildcard, exact = [], []
    for key, section in doc.items():
        if not isinstance(key, str):
            raise VehicleFileError(f'{where}: top-level key {key!r} is not a node name')
        if not isinstance(section, dict) or set(section) != {'ros__parameters'}:
            raise VehicleFileError(
                f"{where}: section {key!r} must hold exactly one key, 'ros__parameters'")
        if not isinstance(section['ros__parameters'], dict):
            raise VehicleFileError(f'{where}: {key}.ros__parameters is not a mapping')
        if fq is None:
            if key.strip('/') == '**':
                wildcard.append(section['ros__parameters'])
        elif _node_key_regex(key).match(fq):
            (wildcard if '*' in key else exact).append(section['ros__parameters'])
    if not wildcard and not exact:
        what = f'node {fq}' if fq else "'/**'"
        raise VehicleFileError(f'{where}: no section applies to {what}; sections are '
                               f'{list(doc)}')
    flat = {}
    for params in wildcard + exact:
        flat.update(flatten_parameters(params, where=where))
    return flat
