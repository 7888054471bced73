# observer_ros.ros_names: names and namespaces checked against ROS's rules before anything starts.
"""
Check a namespace, a node name or a topic name as rcl would, and say what is wrong in one line.

rcl refuses a bad name only when a node is made (a namespace with ``é``: "Couldn't parse
remap rule", after the other processes of a run have started). The tools check first, with
rclpy's own validators, and name the offending character and its position.

"""

import os
import re

from .core.errors import ObserverError

# the largest ROS_DOMAIN_ID whose DDS ports (7400 + 250 x id + ...) fit below 65536: Fast DDS
# refuses more ("Calculated port number is too high") and the node then exits 1 with no
# word of ours
MAX_DOMAIN_ID = 232
# a -p name as rcl's lexer reads it: tokens separated by . or /, an optional node: in front
_PARAMETER_NAME = re.compile(r'^(?:[A-Za-z_][A-Za-z0-9_]*:)?[A-Za-z_][A-Za-z0-9_]*'
                             r'(?:[./][A-Za-z_][A-Za-z0-9_]*)*$')

__all__ = ['check_namespace', 'check_topic_name', 'check_parameter_override', 'check_remap',
           'check_ros_arguments', 'check_domain_id', 'MAX_DOMAIN_ID']


def _one_line(err, what, name):
    """Turn rclpy's three-line NameValidationException into one line."""
    text = str(err.args[0] if err.args else err).split('\n', 1)[0]
    text = text.split(': ', 1)[-1].rstrip(':')
    index = None
    lines = str(err.args[0] if err.args else '').split('\n')
    if len(lines) == 3 and '^' in lines[2]:
        index = lines[2].index('^') - 3          # under "  'name'": 2 spaces and a quote
    where = f' (character {index + 1}, {name[index]!r})' if index is not None and \
        0 <= index < len(name) else ''
    return f'{what} {name!r}: {text}{where}'


def check_namespace(namespace, what='--namespace'):
    """
    Return ``namespace`` made absolute (``sub1`` -> ``/sub1``) if ROS accepts it.

    Raises
    ------
    ObserverError
        One line naming the option, the namespace, the rule and the offending character.

    """
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_namespace import validate_namespace
    if namespace is None:
        return None
    full = namespace if namespace.startswith('/') else '/' + namespace
    try:
        validate_namespace(full)
    except NameValidationException as err:
        raise ObserverError(_one_line(err, what, full)) from None
    return full


def check_topic_name(name, what='topic'):
    """
    Return ``name`` if ROS accepts it as a topic name (relative, absolute or private).

    Raises
    ------
    ObserverError
        One line naming ``what``, the name, the rule and the offending character.

    """
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_topic_name import validate_topic_name
    try:
        validate_topic_name(name)
    except NameValidationException as err:
        raise ObserverError(_one_line(err, what, name)) from None
    return name


def check_parameter_override(text, what='-p'):
    """
    Return ``text`` (``name:=value``) if rcl parses it as a ``-p`` parameter override.

    rcl's own parser reads it (``rclpy.utilities.remove_ros_args``, no node made): a name
    rcl refuses (``observer.0x``, ``x-y``) or a value it cannot read (a mapping ``{a: 1}``,
    a list of mixed types) stops a node only once it starts, after the others started.

    Raises
    ------
    ObserverError
        One line naming the option, the override and rcl's reason.

    """
    from rclpy.utilities import remove_ros_args
    name = text.partition(':=')[0]
    if ':=' in text and not _PARAMETER_NAME.match(name):
        raise ObserverError(f'{what} {text!r}: {name!r} is not a parameter name rcl reads '
                            '(parts separated by ".", each a letter or _ followed by letters, '
                            'digits or _)')
    try:
        remove_ros_args(['observer_ros', '--ros-args', '-p', text])
    except Exception as err:   # noqa: BLE001 - rclpy's RCLInvalidROSArgsError
        reason = str(err).split('Error: ', 1)[-1].split(', at /', 1)[0].strip()
        raise ObserverError(f'{what} {text!r}: rcl cannot parse this parameter override '
                            f'({reason})') from None
    return text


def check_remap(rule, what='-r'):
    """
    Return ``rule`` (``FROM:=TO``) if ROS accepts the names it gives a node.

    ``__ns:=`` is checked as a namespace, ``__node:=`` (``__name:=``) as a node name, the
    same with a ``node:`` prefix; other remaps are left to rcl. rcl's own refusal of a bad
    namespace is a lexer's ("Expected lexeme type (1) not found, search ended at index 8").

    Raises
    ------
    ObserverError
        One line naming the option, the name, the rule and the offending character.

    """
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_node_name import validate_node_name
    name, sep, value = rule.partition(':=')
    key = name.rpartition(':')[2]
    if sep and key == '__ns':
        check_namespace(value, f'{what} {name}:=')
    elif sep and key in ('__node', '__name'):
        try:
            validate_node_name(value)
        except NameValidationException as err:
            raise ObserverError(_one_line(err, f'{what} {name}:=', value)) from None
    return rule


def check_ros_arguments(argv):
    """
    Check a node's ``--ros-args``: each ``-p`` override and each ``-r`` remap of a name.

    What rcl would refuse at ``rclpy.init`` with its lexer's words (and log lines) is one
    ``error:`` line naming the argument instead (:func:`check_parameter_override`,
    :func:`check_remap`).

    Raises
    ------
    ObserverError
        The first argument ROS would refuse.

    """
    inside = False
    for i, arg in enumerate(argv):
        if arg == '--ros-args':
            inside = True
        elif arg == '--':
            inside = False
        elif inside and i + 1 < len(argv):
            if arg in ('-p', '--param'):
                check_parameter_override(argv[i + 1], arg)
            elif arg in ('-r', '--remap'):
                check_remap(argv[i + 1], arg)


def check_domain_id(environ=None):
    """
    Refuse a ``ROS_DOMAIN_ID`` the middleware cannot use, before anything starts.

    Unset or empty: the default domain. Otherwise a whole number from 0 to
    :data:`MAX_DOMAIN_ID`.

    Raises
    ------
    ObserverError
        One line naming the variable, its value and the range.

    """
    value = (os.environ if environ is None else environ).get('ROS_DOMAIN_ID', '').strip()
    if not value:
        return
    if not value.isdigit() or int(value) > MAX_DOMAIN_ID:
        raise ObserverError(f'ROS_DOMAIN_ID={value!r}: a DDS domain is a whole number from 0 '
                            f'to {MAX_DOMAIN_ID} (its ports must fit below 65536)')
