# observer_ros.bag.bag_topics: a vehicle's topics found in a bag, namespace included.
"""
Find a vehicle's topics in a bag.

The vehicle file names its topics relative to the vehicle's namespace (``imu/gyro``);
the bag holds absolute names (``/imu/gyro``, ``/sub1/imu/gyro``). The namespace is given
or detected: the one under which every sensor topic of the vehicle is in the bag.

"""

from dataclasses import dataclass
from typing import Dict, Optional

from .cdr_decode import JOINT_STATE
from .errors import BagToolError

__all__ = ['VEHICLE_TOPICS', 'normalize_namespace', 'TopicMap', 'resolve_topics']

# The vector topics of the nodes (relative names, JointState named by the vector's names).
VEHICLE_TOPICS = {
    'truth': 'state/true',
    'estimate': 'state/estimate',
    'command': 'control/u',
    'residual': 'observer/residual',
}


def normalize_namespace(namespace):
    """
    Return a namespace as ``''`` (root) or ``'/a/b'``.

    Parameters
    ----------
    namespace : str or None
        ``None``, ``''``, ``'/'``, ``'sub1'``, ``'/sub1/'`` ...

    Returns
    -------
    ns : str
        ``''`` for the root namespace, else a name with one leading and no trailing ``/``.

    """
    if namespace is None:
        return ''
    parts = [p for p in str(namespace).strip().split('/') if p]
    return '/' + '/'.join(parts) if parts else ''


def _join(namespace, topic):
    """Absolute name of a (relative or absolute) topic in a namespace."""
    if topic.startswith('/'):
        return topic
    return f'{namespace}/{topic.lstrip("~/")}'


@dataclass
class TopicMap:
    """The absolute topic names of a vehicle in a bag."""

    namespace: str
    sensors: Dict[str, str]                     # sensor name -> topic
    truth: Optional[str] = None                 # present in the bag, else None
    estimate: Optional[str] = None
    command: Optional[str] = None
    residual: Optional[str] = None


def resolve_topics(info, vehicle, namespace=None):
    """
    Find a vehicle's topics in a bag.

    Parameters
    ----------
    info : BagInfo
        The bag's topics and counts, from :func:`bag_info`.
    vehicle : Vehicle
        Its sensors say which topics to find.
    namespace : str, optional
        The vehicle's namespace (``/sub1``); detected when None: the one namespace under
        which every sensor topic of the vehicle is in the bag.

    Returns
    -------
    topics : TopicMap
        Sensor topics are in the bag and have messages; the vector topics are None
        when the bag does not have them.

    Raises
    ------
    BagToolError
        The bag is empty, a sensor topic is missing or has no messages ("bag has no
        messages on /sub1/imu/gyro (sensor 'gyro' of vehicle submarine); topics in the
        bag: ..."), several namespaces match, or a topic has the wrong type.

    """
    where = info.path
    if info.message_count == 0:
        raise BagToolError(f'{where}: the bag is empty (no messages); topics in the '
                           f'bag: {info.describe_topics()}')
    sensors = list(vehicle.sensors)
    if namespace is not None:
        ns = normalize_namespace(namespace)
    else:
        ns = _detect_namespace(info, vehicle)
    names = {s.name: _join(ns, s.topic) for s in sensors}
    for s in sensors:
        topic = names[s.name]
        msgtype, count = info.topics.get(topic, (None, 0))
        if msgtype is None or count == 0:
            hint = '' if namespace is not None or msgtype is not None else \
                ' (pass --namespace if the vehicle ran in a namespace)'
            raise BagToolError(
                f'{where}: bag has no messages on {topic} (sensor {s.name!r} of vehicle '
                f'{vehicle.name}); topics in the bag: {info.describe_topics()}{hint}')
        if msgtype != s.msg_type:
            raise BagToolError(
                f'{where}: topic {topic} is {msgtype} in the bag; sensor {s.name!r} of '
                f'vehicle {vehicle.name} expects {s.msg_type}')
    topics = TopicMap(namespace=ns, sensors=names)
    for key, rel in VEHICLE_TOPICS.items():
        topic = _join(ns, rel)
        msgtype, count = info.topics.get(topic, (None, 0))
        if msgtype is None or count == 0:
            continue
        if msgtype != JOINT_STATE:
            info.warnings.append(f'{topic} is {msgtype}, not {JOINT_STATE}; ignored')
            continue
        setattr(topics, key, topic)
    return topics


def _detect_namespace(info, vehicle):
    """Return the one namespace under which all the vehicle's sensor topics are."""
    rels = [s.topic for s in vehicle.sensors]
    relative = [r for r in rels if not r.startswith('/')]
    if not relative:
        return ''
    candidates = {}
    for rel in relative:
        tail = '/' + rel.lstrip('~/')
        for topic in info.topics:
            if topic == tail or topic.endswith(tail):
                ns = topic[:len(topic) - len(tail)]
                candidates.setdefault(ns, set()).add(rel)
    full = sorted(ns for ns, found in candidates.items() if len(found) == len(set(relative)))
    if len(full) == 1:
        return full[0]
    if len(full) > 1:
        shown = ', '.join(repr(ns or '/') for ns in full)
        raise BagToolError(
            f'{info.path}: the sensor topics of vehicle {vehicle.name} are in the bag under '
            f'several namespaces ({shown}); choose one with --namespace')
    if candidates:   # the namespace that has most of them: its missing topic is the error
        return max(sorted(candidates), key=lambda ns: len(candidates[ns]))
    # no sensor topic at all: the namespace of the vehicle's other topics, if one
    others = set()
    for rel in VEHICLE_TOPICS.values():
        for topic in info.topics:
            if topic.endswith('/' + rel):
                others.add(topic[:len(topic) - len(rel) - 1])
    return others.pop() if len(others) == 1 else ''
