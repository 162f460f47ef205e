"""ROS domain IDs for tests: each pytest-xdist worker has its own range, so two never share one."""

from __future__ import annotations

import os
import random


def worker_domains() -> range:
    """Domain IDs 1-101, split between pytest-xdist workers so that two never share one.

    PMA_TEST_DOMAINS=FIRST-LAST gives a session a range of its own instead (split the same
    way between its workers), for two sessions run side by side (`make test`'s in-process
    part, tools/test.sh).
    """
    first, last = 1, 101
    if 'PMA_TEST_DOMAINS' in os.environ:
        first, last = (int(end) for end in os.environ['PMA_TEST_DOMAINS'].split('-'))
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')          # 'gw0', 'gw1', ...
    count = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
    if not worker.startswith('gw') or count <= 1:
        return range(first, last + 1)
    size = (last - first + 1) // count
    start = first + int(worker[2:]) * size
    return range(start, start + size)


def another_domain() -> int:
    """A domain of this worker other than the current one: a graph of its own."""
    current = os.environ.get('ROS_DOMAIN_ID')
    return random.SystemRandom().choice(
        [domain for domain in worker_domains() if str(domain) != current])
