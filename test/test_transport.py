"""cgags_ros.engine.transport: the shipped Fast DDS profile and when the package turns it on."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from cgags_ros.engine import transport
import pytest

NS = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
KITTI_SCAN_BYTES = 3_989_376  # one of the 16 KITTI scans as PointCloud2, all fields


def test_the_profile_replaces_the_builtin_transports_with_large_ones():
    path = transport.profile_path()
    assert path is not None and path.name == transport.PROFILE_FILE
    root = ET.parse(path).getroot()
    participant = root.find('p:participant', NS)
    assert participant.get('is_default_profile') == 'true'
    assert participant.find('p:rtps/p:useBuiltinTransports', NS).text == 'false'
    used = {e.text for e in participant.findall('p:rtps/p:userTransports/p:transport_id', NS)}
    kinds = {d.find('p:transport_id', NS).text: d for d in
             root.findall('p:transport_descriptors/p:transport_descriptor', NS)}
    assert used == set(kinds)
    shm = [d for d in kinds.values() if d.find('p:type', NS).text == 'SHM']
    udp = [d for d in kinds.values() if d.find('p:type', NS).text == 'UDPv4']
    assert len(shm) == 1 and len(udp) == 1
    # the segment holds several of the largest scans in flight, not one
    assert int(shm[0].find('p:segment_size', NS).text) >= 4 * KITTI_SCAN_BYTES
    for size in ('sendBufferSize', 'receiveBufferSize'):
        assert int(udp[0].find(f'p:{size}', NS).text) >= KITTI_SCAN_BYTES


def test_the_profile_is_set_when_the_user_chose_nothing():
    env = {}
    assert transport.use_large_data_profile(env) == str(transport.profile_path())
    assert env == {transport.PROFILE_VARIABLE: str(transport.profile_path())}


@pytest.mark.parametrize('env, expected, left', [
    ({'FASTRTPS_DEFAULT_PROFILES_FILE': '/mine.xml'}, '/mine.xml',
     {'FASTRTPS_DEFAULT_PROFILES_FILE': '/mine.xml'}),
    ({'FASTRTPS_DEFAULT_PROFILES_FILE': ''}, '', {}),  # empty: Fast DDS's defaults
    ({'FASTDDS_BUILTIN_TRANSPORTS': 'LARGE_DATA'}, '',
     {'FASTDDS_BUILTIN_TRANSPORTS': 'LARGE_DATA'}),
    ({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}, '',
     {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}),
])
def test_the_users_choice_wins(env, expected, left):
    assert transport.use_large_data_profile(env) == expected
    assert env == left


def test_the_users_line_names_the_installed_profile():
    line = transport.user_line()
    assert line == f'export FASTRTPS_DEFAULT_PROFILES_FILE={transport.profile_path()}'
