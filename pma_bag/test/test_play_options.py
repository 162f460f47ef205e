"""play's options and start point, without a ROS graph."""

from __future__ import annotations

import pytest

from pma_bag import BagError, BagReader, BagWriter
from pma_bag.play import parse_args, playback_start

NS = 1_000_000_000
T0 = 1_700_000_000 * NS


@pytest.mark.parametrize('option, value', [
    ('--rate', 'nan'), ('--rate', 'inf'), ('--rate', '-inf'), ('--rate', '1e300'),
    ('--start-offset', 'nan'), ('--start-offset', 'inf'),
    ('--delay', 'nan'), ('--delay', 'inf'), ('--delay', '1e300'),
    ('--clock', 'nan'), ('--clock', 'inf'), ('--clock', '0'), ('--clock', '1e-300'),
    ('--clock', '1e12'),
])
def test_numbers_the_player_cannot_use_are_refused_at_parsing(option, value, capsys):
    """Regression: `--rate nan` passed `rate <= 0` and the playback thread died in int(nan)
    with a traceback, then `play: done` and exit 0 having played nothing; `inf` likewise."""
    with pytest.raises(SystemExit) as refused:
        parse_args(['bag', f'{option}={value}'])
    assert refused.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith(f'play: error: {option} must be'), error


def test_usable_numbers_pass():
    args = parse_args(['bag', '--rate', '0.5', '--start-offset', '1.5', '--delay', '2',
                       '--clock', '100'])
    assert (args.rate, args.start_offset, args.delay, args.clock) == (0.5, 1.5, 2.0, 100.0)


@pytest.fixture
def bag(tmp_path):
    """/a at 0..9 s, /b at 0..4 s after the first message."""
    path = tmp_path / 'bag'
    with BagWriter(path) as writer:
        for topic in ('/a', '/b'):
            writer.add_topic(topic, 'std_msgs/msg/Empty')
        for second in range(10):
            writer.write('/a', b'\x00\x01\x00\x00', T0 + second * NS)
            if second < 5:
                writer.write('/b', b'\x00\x01\x00\x00', T0 + second * NS)
    with BagReader(path) as reader:
        yield reader


def test_the_start_offset_counts_from_the_first_message(bag):
    assert playback_start(bag, ['/a', '/b'], 0.0) == (T0, 15)
    assert playback_start(bag, ['/a', '/b'], 3.0) == (T0 + 3 * NS, 7 + 2)
    assert playback_start(bag, ['/a'], 9.0) == (T0 + 9 * NS, 1)


def test_an_offset_with_nothing_left_to_play_is_refused(bag):
    """Regression: `--start-offset 1e9` announced `playing 1538 messages` and played none."""
    with pytest.raises(BagError, match=r'--start-offset 1e\+09 s is past the end: the bag '
                                       r'lasts 9\.000 s'):
        playback_start(bag, ['/a', '/b'], 1e9)
    with pytest.raises(BagError, match=r'no message of /b from --start-offset 5 s on'):
        playback_start(bag, ['/b'], 5.0)
