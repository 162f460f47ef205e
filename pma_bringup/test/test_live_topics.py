"""foxglove_live's plain helpers: which parameter values it accepts, which topics it forwards."""

import pytest

from pma_bringup.foxglove_live import (
    DEFAULT_TOPICS,
    check_host,
    check_topic_entry,
    matches,
    viewer_urls,
)
from pma_common import names

pytestmark = pytest.mark.in_process


@pytest.mark.parametrize('host', ['127.0.0.1', '0.0.0.0', '::', '::1', 'localhost',
                                  'rig-pc.lab.example.org', '192.168.10.7'])
def test_addresses_and_host_names_are_accepted(host):
    assert check_host(host) == ''


@pytest.mark.parametrize('host', ['', 'bad host', 'http://rig', '-rig', 'rig_pc', '1.2.3.4:80'])
def test_anything_else_is_refused_with_a_reason(host):
    assert repr(host) in check_host(host)


def test_topic_entries_are_names_or_absolute_patterns():
    for entry in (names.STATE, '/diagnostics', '~/status', '/*/pma/state', '/left/pma/*'):
        assert check_topic_entry(entry) == '', entry
    assert 'absolute' in check_topic_entry('*/pma/state')
    assert 'pma state' in check_topic_entry('pma state')
    assert '9pma' in check_topic_entry('9pma')


def test_patterns_match_every_namespace_names_match_exactly():
    names = {'/pma/state'}
    assert matches('/pma/state', names, [])
    assert not matches('/left/pma/state', names, [])
    assert matches('/left/pma/state', names, ['/*/pma/state'])
    assert matches('/lab/left/pma/state', names, ['/*/pma/state'])   # fnmatch: * spans /
    assert not matches('/left/pma/prediction', names, ['/*/pma/state'])


def test_the_default_topics_are_the_recorded_ones_and_the_controllers():
    assert DEFAULT_TOPICS[:2] == ['pma/state', 'pma/pressure']
    assert {'pma/prediction', names.MODEL_PARAMS, '/diagnostics', names.CONTROL_STATE} <= set(
        DEFAULT_TOPICS)
    assert len(DEFAULT_TOPICS) == len(set(DEFAULT_TOPICS))


def test_a_wildcard_address_gives_this_machines_name_and_localhost():
    urls = viewer_urls('0.0.0.0', 8765)
    assert urls[-1] == 'ws://127.0.0.1:8765' and urls[0].endswith(':8765') and len(urls) == 2
    assert viewer_urls('::1', 9000) == ['ws://[::1]:9000']
    assert viewer_urls('127.0.0.1', 8765) == ['ws://127.0.0.1:8765']
