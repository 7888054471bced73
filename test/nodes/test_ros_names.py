# Names, namespaces and the DDS domain, checked by ROS's rules before anything starts.
"""One error line naming the offending character or value, never a middleware's log."""

import os
import subprocess
import sys

from observer_ros.core.errors import ObserverError
from observer_ros.ros_names import (check_domain_id, check_namespace,
                                    check_parameter_override, check_ros_arguments,
                                    check_topic_name, MAX_DOMAIN_ID)
import pytest
from ros_helpers import CONFIG, ros_env

SAMPLE = CONFIG.parent / 'bags' / 'samples' / 'submarine'


def test_namespaces_and_topics():
    assert check_namespace('sub1') == '/sub1' and check_namespace(None) is None
    with pytest.raises(ObserverError, match=r"--namespace '/a b': .* \(character 3, ' '\)"):
        check_namespace('/a b')
    assert check_topic_name('~/x') == '~/x' and check_topic_name('/a/b') == '/a/b'
    with pytest.raises(ObserverError, match=r"topic '1x': .*must not start with a number"):
        check_topic_name('1x')


@pytest.mark.parametrize('value, ok', [('', True), ('0', True), (str(MAX_DOMAIN_ID), True),
                                       ('233', False), ('300', False), ('-1', False),
                                       ('abc', False), (' 7 ', True)])
def test_domain_ids(value, ok):
    if ok:
        check_domain_id({'ROS_DOMAIN_ID': value})
    else:
        with pytest.raises(ObserverError, match=f"ROS_DOMAIN_ID='{value.strip()}': a DDS "
                           'domain is a whole number from 0 to 232'):
            check_domain_id({'ROS_DOMAIN_ID': value})


@pytest.mark.ros
@pytest.mark.parametrize('argv', [
    ['observer_ros.nodes.observer_node', '--ros-args', '--params-file',
     str(CONFIG / 'submarine.yaml')],
    ['observer_ros.tools.run_closed_loop', str(CONFIG / 'submarine.yaml'), '--out', '{tmp}'],
    ['observer_ros.bag.play', str(SAMPLE)],
])
def test_a_domain_id_fast_dds_refuses_is_one_line_in_each_entry_point(tmp_path, argv):
    env = dict(ros_env(), ROS_DOMAIN_ID='300')
    argv = [a.format(tmp=tmp_path / 'run') for a in argv]
    done = subprocess.run([sys.executable, '-W', 'ignore', '-m', *argv], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: ROS_DOMAIN_ID='300': a DDS domain is a whole number from 0 to 232 (its ports "
        'must fit below 65536)'], done.stderr
    assert not os.path.exists(tmp_path / 'run')


def test_observer_play_refuses_a_remap_to_a_name_rcl_refuses(capsys):
    from observer_ros.bag.play import main as play_main
    assert play_main([str(SAMPLE), '--remap', '/imu/data:=/imu data']) == 2
    assert "--remap '/imu data': topic name must not contain" in capsys.readouterr().err


@pytest.mark.parametrize('text, reason', [
    ('observer.0x:=1.0', 'is not a parameter name rcl reads'),
    ('observer.x-y:=1.0', 'is not a parameter name rcl reads'),
    ('observer..x:=1.0', 'is not a parameter name rcl reads'),
    ('observer:={poles: [-1.0, -2.0, -3.0]}', 'Unknown YAML event'),
    ('observer.poles:=[a, 1]', 'Sequence should be of same type'),
    ('observer.poles:=[-1.0, -2.0, -3.0]', None), ('vehicle.description:=café', None),
])
def test_parameter_overrides_are_read_by_rcl_before_anything_starts(text, reason):
    if reason is None:
        assert check_parameter_override(text) == text
        return
    with pytest.raises(ObserverError, match=f"^-p '{text[:8]}.*': .*{reason}"):
        check_parameter_override(text)


@pytest.mark.ros
def test_observer_run_refuses_an_override_rcl_cannot_parse_before_any_process(tmp_path,
                                                                              capsys):
    from observer_ros.tools.run_closed_loop import main as run_main
    out = tmp_path / 'runs' / 'dive'
    assert run_main([str(CONFIG / 'submarine.yaml'), '--out', str(out),
                     '-p', 'observer.0x:=1.0']) == 2
    assert capsys.readouterr().err.splitlines() == [
        "error: -p 'observer.0x:=1.0': 'observer.0x' is not a parameter name rcl reads (parts "
        'separated by ".", each a letter or _ followed by letters, digits or _)']
    assert not (tmp_path / 'runs').exists()


def test_a_nodes_ros_arguments_are_checked_by_ros_rules():
    good = ['--ros-args', '--params-file', 'v.yaml', '-p', 'simulator.mode:=realtime',
            '-r', '__ns:=/sub1', '-r', '__node:=observer_2', '-r', 'imu/data:=/robot/imu',
            '--remap', 'observer:__ns:=/sub2', '--log-level', 'debug']
    check_ros_arguments(good)
    check_ros_arguments(['-p', 'x.0y:=1'])          # not a ROS argument: the node's own
    for args, words in [
            (['-r', '__ns:=/véhicule_1'], "-r __ns:= '/véhicule_1': namespace must not "
             "contain characters other than alphanumerics, '_', or '/' (character 3, 'é')"),
            (['--remap', 'observer:__ns:=/a//b'], "--remap observer:__ns:= '/a//b': "
             "namespace must not contain repeated '/' (character 4, '/')"),
            (['-r', '__node:=obs-1'], "-r __node:= 'obs-1': node name must not contain "
             "characters other than alphanumerics or '_' (character 4, '-')"),
            (['--param', 'observer.0x:=1.0'], "--param 'observer.0x:=1.0': 'observer.0x' is "
             'not a parameter name rcl reads')]:
        with pytest.raises(ObserverError) as err:
            check_ros_arguments(['--ros-args', *args])
        assert str(err.value).startswith(words), str(err.value)


@pytest.mark.ros
def test_a_node_refuses_a_namespace_ros_refuses_in_one_line():
    # one line, not rcl's WARN and ERROR log lines ("Couldn't parse remap rule ... Expected
    # lexeme type (1) not found, ..."), which rclpy prints when it parses the name itself
    done = subprocess.run([sys.executable, '-W', 'ignore', '-m',
                           'observer_ros.nodes.observer_node', '--ros-args', '--params-file',
                           str(CONFIG / 'submarine.yaml'), '-r', '__ns:=/véhicule_1'],
                          env=ros_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert (done.stdout + done.stderr).strip().splitlines() == [
        "error: -r __ns:= '/véhicule_1': namespace must not contain characters other than "
        "alphanumerics, '_', or '/' (character 3, 'é')"], done.stderr
