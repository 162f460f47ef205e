"""Bursts of service requests at a node under test, from tests/helpers/service_burst.py.

The client is a process of its own (a test's probe spins in a thread and would time itself);
it warms every service up, then sends each burst when told: `BurstClient.burst(*services)`
sends `count` requests to each of `services` at once, interleaved, and returns what the
helper printed for each (sent, answered, succeeded, latency_ms).
"""

from __future__ import annotations

import json
from pathlib import Path

HELPER = Path(__file__).resolve().parents[1] / 'helpers' / 'service_burst.py'
COUNT = 300


class BurstClient:
    def __init__(self, procs, go_dir: Path, services: list[str], count: int = COUNT,
                 timeout: float = 20.0):
        self.go_dir = go_dir
        self.timeout = timeout
        self.rounds = 0
        go_dir.mkdir(parents=True, exist_ok=True)
        self.proc = procs.python(HELPER, '--count', str(count), '--go-dir', str(go_dir),
                                 '--services', ','.join(services), '--timeout', str(timeout),
                                 name='service_burst')
        self.proc.wait_for_line('ready', timeout=40)

    def burst(self, *services: str) -> dict[str, dict]:
        """{service: the helper's result} of one round: `count` requests to each of them."""
        number, self.rounds = self.rounds, self.rounds + 1
        go = self.go_dir / f'.go-{number}'
        go.write_text(','.join(services))
        go.rename(self.go_dir / f'go-{number}')      # seen whole
        return {service: json.loads(self.proc.wait_for_line(
                    f'"round": {number}, "service": "{service}"', timeout=self.timeout + 30))
                for service in services}

    def close(self) -> None:
        (self.go_dir / 'stop').touch()


def answered(results: dict[str, dict]) -> dict[str, int]:
    return {service: result['answered'] for service, result in results.items()}
