# The rules the launch files share: which vehicle file, which remaps, which booleans.
"""observer_ros.launch_support: vehicle names or files, remaps, true/false."""

import os

from observer_ros.core.errors import ObserverError
from observer_ros.launch_support import as_bool, namespace_argument, parse_remaps, vehicle_file
import pytest
from ros_helpers import CONFIG, REPO


def test_vehicle_by_name_or_file():
    assert vehicle_file('submarine', share=REPO) == str(CONFIG / 'submarine.yaml')
    assert vehicle_file(str(CONFIG / 'pitch_imu.yaml')) == str(CONFIG / 'pitch_imu.yaml')
    with pytest.raises(ObserverError, match=r"'sub' is not one of .*'submarine'"):
        vehicle_file('sub', share=REPO)
    with pytest.raises(ObserverError, match='no such file'):
        vehicle_file('/nowhere/robot.yaml')


def test_remaps():
    assert parse_remaps('imu/data:=/robot/imu control/u:=/robot/cmd') == [
        ('imu/data', '/robot/imu'), ('control/u', '/robot/cmd')]
    assert parse_remaps('a:=b,c:=d') == [('a', 'b'), ('c', 'd')]
    assert parse_remaps('') == []
    with pytest.raises(ObserverError, match="'imu/data' is not FROM:=TO"):
        parse_remaps('imu/data')


def test_booleans():
    assert as_bool('True', 'record') is True and as_bool('false', 'record') is False
    with pytest.raises(ObserverError, match="record: 'maybe'"):
        as_bool('maybe', 'record')


def test_names_checked_by_ros_rules_before_any_node_starts():
    assert namespace_argument('') == '' and namespace_argument('sub2') == '/sub2'
    with pytest.raises(ObserverError, match=r"namespace:= '/véhicule_1': namespace must not "
                       r".* \(character 3, 'é'\)"):
        namespace_argument('/véhicule_1')
    with pytest.raises(ObserverError, match=r"remaps: 'imu/da-ta': .* \(character 7, '-'\)"):
        parse_remaps('imu/data:=/robot/imu,control/u:=/robot/cmd imu/da-ta:=x')
    with pytest.raises(ObserverError, match=r"remaps: '/x/2b': topic name token must not "
                       r"start with a number \(character 4, '2'\)"):
        parse_remaps('imu/data:=/x/2b')


def test_a_vehicle_pipe_is_read_once_for_every_node_and_a_folder_is_refused(tmp_path):
    text = (CONFIG / 'submarine.yaml').read_text()
    read, write = os.pipe()         # what vehicle:=<(cat v.yaml) hands the launch
    os.write(write, text.encode())
    os.close(write)
    try:
        copy = vehicle_file(f'/proc/self/fd/{read}')
    finally:
        os.close(read)
    # a regular file every node can read
    assert os.path.isfile(copy) and open(copy).read() == text
    with pytest.raises(ObserverError, match=f'{tmp_path}: a folder, not a parameters file'):
        vehicle_file(f'{tmp_path}/')
