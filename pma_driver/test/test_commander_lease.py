"""CommanderLeases: when a remote commander counts as lost, and what a lost one may still do."""

from __future__ import annotations

import pytest

from pma_driver.commander_lease import REVOKED_KEEP_S, CommanderLeases

pytestmark = pytest.mark.in_process

TIMEOUT_S = 1.0


class Checked(CommanderLeases):
    """Checked as the driver does, every tenth of the timeout, up to each asked time."""

    def __init__(self, timeout_s):
        super().__init__(timeout_s)
        self.clock = 0.0

    def expired(self, now):
        lost = []
        while self.clock + 0.1 * self.timeout_s < now:
            self.clock += 0.1 * self.timeout_s
            lost += super().expired(self.clock)
        self.clock = now
        return lost + super().expired(now)


@pytest.fixture
def leases():
    return Checked(TIMEOUT_S)


def test_a_late_check_judges_nobody_until_the_next():
    """A driver held up for a second must not take a renewal queued behind it for a loss."""
    leases = CommanderLeases(TIMEOUT_S)
    leases.renew('a', 'controller', True, 0.0)
    assert leases.expired(0.1) == []
    assert leases.expired(1.5) == []                       # late: renewals may be queued
    leases.renew('a', 'controller', True, 1.55)            # ... and here they are
    for tenth in range(16, 26):                            # 1.6 ... 2.5 s: renewed at 1.55
        assert leases.expired(tenth / 10) == []
    assert [lease.commander for lease in leases.expired(2.6)] == ['controller']


def test_a_checker_late_at_every_call_still_finds_a_silent_lease_lost():
    """A driver starved for good (its timer 0.6 s apart, past half the timeout each time)
    skips one late check, never two in a row: the silent commander, judged fairly at 0.6 s,
    is skipped at 1.2 s and lost at 1.8 s."""
    leases = CommanderLeases(TIMEOUT_S)
    leases.renew('a', 'controller', True, 0.0)
    found = {}
    for check in range(1, 11):
        for lease in leases.expired(0.6 * check):
            found.setdefault(lease.commander, 0.6 * check)
    assert found == {'controller': pytest.approx(1.8)}


def test_a_starved_checker_keeps_a_lease_renewed_between_its_checks():
    """... and a commander renewing between those late checks is never taken for lost."""
    leases = CommanderLeases(TIMEOUT_S)
    for check in range(1, 21):
        leases.renew('a', 'controller', True, 0.6 * check - 0.05)
        assert leases.expired(0.6 * check) == []
    assert leases.holders() == ['controller']


def test_nothing_is_lost_on_an_idle_rig(leases):
    assert leases.expired(0.0) == [] and leases.expired(1e6) == []
    assert leases.setpoint_refusal(1e6) == '' and leases.holders() == []


def test_a_lease_renewed_in_time_is_never_lost(leases):
    for step in range(100):
        assert leases.renew('a', 'controller', True, step * 0.5)
        assert leases.expired(step * 0.5 + 0.4) == []
    assert leases.holders() == ['controller']


def test_a_silent_lease_is_lost_once_just_after_the_timeout(leases):
    leases.renew('a', 'controller', True, 10.0)
    assert leases.expired(10.0 + TIMEOUT_S) == []          # at the timeout: not yet
    lost = leases.expired(10.0 + TIMEOUT_S + 0.01)
    assert [lease.commander for lease in lost] == ['controller']
    assert leases.expired(20.0) == [] and leases.lost_count == 1
    assert leases.holders() == []


def test_a_released_lease_is_never_lost(leases):
    leases.renew('a', 'pma sweep', True, 0.0)
    leases.renew('a', 'pma sweep', False, 0.5)
    assert leases.expired(100.0) == [] and leases.lost_count == 0


def test_a_lost_commander_that_comes_back_cannot_command_until_it_lets_go(leases):
    """The link returned and the commander never noticed: its renewals are refused, and so
    is every setpoint while they come; its release ends that."""
    leases.renew('a', 'controller', True, 0.0)
    leases.expired(2.0)
    assert leases.setpoint_refusal(2.0) == ''              # lost, silent: nothing to refuse
    assert not leases.renew('a', 'controller', True, 5.0)  # back, still renewing
    refusal = leases.setpoint_refusal(5.1)
    assert 'controller lost the muscle' in refusal and 'must let go' in refusal
    assert leases.holders() == []                          # a revoked lease holds nothing
    assert leases.expired(6.5) == [] and leases.lost_count == 1   # not lost twice
    assert leases.setpoint_refusal(5.0 + TIMEOUT_S + 0.1) == ''   # quiet again
    assert not leases.renew('a', 'controller', True, 8.0)
    assert leases.setpoint_refusal(8.1)
    assert not leases.renew('a', 'controller', False, 8.2)  # it let go
    assert leases.setpoint_refusal(8.3) == ''
    assert leases.renew('b', 'controller', True, 9.0)     # a new hold is a new lease
    assert leases.holders() == ['controller']


def test_a_revoked_lease_is_forgotten_after_a_long_silence(leases):
    leases.renew('a', 'controller', True, 0.0)
    leases.expired(2.0)
    leases.expired(REVOKED_KEEP_S + 1.0)
    assert leases.renew('a', 'controller', True, REVOKED_KEEP_S + 2.0)   # taken as new


def test_two_commanders_are_judged_apart(leases):
    leases.renew('a', 'controller', True, 0.0)
    leases.renew('b', 'pma sweep', True, 0.0)
    leases.renew('b', 'pma sweep', True, 0.9)
    assert [lease.commander for lease in leases.expired(1.5)] == ['controller']
    assert leases.holders() == ['pma sweep']
