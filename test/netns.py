# Two "hosts" on one machine: network namespaces joined by a veth pair.
"""
Network namespaces that stand for two machines on one Ethernet segment.

Two namespaces joined by a veth pair, 10.200.NET.1/24 and 10.200.NET.2/24, multicast on;
the processes run in them with ``ip netns exec``. Their names carry the test process's
id, so parallel test processes do not share them. Needs root and ``ip``.
"""

import contextlib
import os
import shutil
import subprocess

import pytest

from ros_helpers import DOMAIN_ID

TAG = os.getpid() % 10000
NET = 100 + os.getpid() % 100                # 10.200.NET.0/24
NS_SIM, NS_EST = f'obsros_sim_{TAG}', f'obsros_est_{TAG}'
VETH_SIM, VETH_EST = f'vobs{TAG}a', f'vobs{TAG}b'   # (at most 15 characters)


def ip(*args, check=True):
    """Run ``ip ARGS``; return the completed process."""
    return subprocess.run(['ip', *args], capture_output=True, text=True, check=check)


@contextlib.contextmanager
def two_hosts():
    """Make two namespaces joined by a veth pair; remove them afterwards."""
    if shutil.which('ip') is None:
        pytest.skip('no ip command (iproute2): cannot build network namespaces')
    if os.geteuid() != 0:
        pytest.skip('network namespaces need root')
    made = []
    try:
        for ns in (NS_SIM, NS_EST):
            out = ip('netns', 'add', ns, check=False)
            if out.returncode != 0:
                pytest.skip(f'cannot create a network namespace: {out.stderr.strip()}')
            made.append(ns)
        ip('link', 'add', VETH_SIM, 'type', 'veth', 'peer', 'name', VETH_EST)
        for ns, dev, host in ((NS_SIM, VETH_SIM, 1), (NS_EST, VETH_EST, 2)):
            ip('link', 'set', dev, 'netns', ns)
            ip('-n', ns, 'addr', 'add', f'10.200.{NET}.{host}/24', 'dev', dev)
            ip('-n', ns, 'link', 'set', 'dev', dev, 'multicast', 'on')
            ip('-n', ns, 'link', 'set', dev, 'up')
            ip('-n', ns, 'link', 'set', 'lo', 'up')
        yield {'sim': NS_SIM, 'est': NS_EST}
    finally:
        for ns in made:
            ip('netns', 'del', ns, check=False)      # takes its end of the veth along


def env():
    """Return the environment of a process on a "host": UDP only, this test process's domain."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1',
               FASTDDS_BUILTIN_TRANSPORTS='UDPv4', ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET')
    env.pop('ROS_LOCALHOST_ONLY', None)
    return env
