"""The rig computer's Fast DDS profile (docs/lab-network.md): sends that never block, shared
memory kept, and the profile the participants take by default. tests/support's rig profile for
tests/test_lab_network.py must say the same about transports."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.in_process

ROOT = Path(__file__).resolve().parents[2]
NS = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}


def transports(path: Path) -> tuple[dict[str, ET.Element], ET.Element]:
    root = ET.parse(path).getroot()
    descriptors = {d.findtext('f:transport_id', namespaces=NS): d
                   for d in root.iterfind('f:transport_descriptors/f:transport_descriptor', NS)}
    participant = root.find('f:participant', NS)
    return descriptors, participant


@pytest.mark.parametrize('path', [ROOT / 'pma_bringup' / 'config' / 'fastdds_rig.xml',
                                  ROOT / 'tests' / 'support' / 'fastdds_rig_nonblocking.xml'])
def test_the_rig_profile_never_blocks_a_send_and_keeps_shared_memory(path):
    descriptors, participant = transports(path)
    assert participant.get('is_default_profile') == 'true'
    used = [t.text for t in participant.iterfind('f:rtps/f:userTransports/f:transport_id', NS)]
    assert participant.findtext('f:rtps/f:useBuiltinTransports', namespaces=NS) == 'false'
    kinds = {descriptors[name].findtext('f:type', namespaces=NS): descriptors[name]
             for name in used}
    assert set(kinds) == {'UDPv4', 'SHM'}
    assert kinds['UDPv4'].findtext('f:non_blocking_send', namespaces=NS) == 'true'
