"""Commander leases: which remote commanders hold the muscle, and which have been lost.

Plain Python, no ROS: driver_node feeds it pma/commander_lease messages and asks it, on a
timer, which leases ran out. A commander that keeps the muscle pressurised from another
host (a length controller holding a target, `pma sweep` waiting on its goal) renews a lease
several times a `timeout_s`; one not renewed for `timeout_s` is lost, and the driver brings
the muscle to its safe state. The driver's own clock times everything (the time a renewal
arrived), so a commander's skewed clock cannot hide a loss.

A lost lease is revoked, not forgotten: if its renewals come back (the link returned, and the
commander never noticed that it lost the muscle), setpoints are refused until they stop, so
a commander that missed the vent cannot re-pressurise the muscle. A revoked lease is forgotten
once it is released, or after REVOKED_KEEP_S without a word (a link down that long has ended
the DDS session, so nothing of that commander's is still queued).
"""

from __future__ import annotations

from dataclasses import dataclass

REVOKED_KEEP_S = 600.0


@dataclass
class Lease:
    commander: str
    lease_id: str
    renewed_at: float         # the driver's monotonic time of the latest renewal [s]
    revoked_at: float = float('inf')   # when it was found lost


class CommanderLeases:
    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self._held: dict[str, Lease] = {}
        self._revoked: dict[str, Lease] = {}
        self.lost_count = 0
        self.late_checks = 0      # checks that judged nobody because they came late
        self._checked_at: float | None = None
        self.last_check_skipped = False   # the latest call came late and judged nobody

    def renew(self, lease_id: str, commander: str, holding: bool, now: float) -> bool:
        """Note a lease message; False when it renews a revoked lease (it is ignored)."""
        revoked = self._revoked.get(lease_id)
        if revoked is not None:
            if holding:
                revoked.renewed_at = now
            else:
                del self._revoked[lease_id]   # it let go: it knows it lost the muscle
            return False
        if holding:
            lease = self._held.get(lease_id)
            if lease is None:
                self._held[lease_id] = Lease(commander, lease_id, now)
            else:
                lease.renewed_at = now
        else:
            self._held.pop(lease_id, None)
        return True

    def expired(self, now: float) -> list[Lease]:
        """The held leases not renewed for timeout_s: revoked now, returned once each.

        Called every tenth of the timeout. A call that comes more than half a timeout after
        the last one finds the checker itself was held up (a starved process): renewals may
        be waiting behind it, so it judges nobody this time, only the next, however late that
        one is: a checker late at every call must still find a silent commander lost."""
        late = self._checked_at is not None and now - self._checked_at > 0.5 * self.timeout_s
        self._checked_at = now
        if late and not self.last_check_skipped:
            self.last_check_skipped = True
            self.late_checks += 1
            return []
        self.last_check_skipped = False
        for lease_id in [key for key, lease in self._revoked.items()
                         if now - lease.renewed_at > REVOKED_KEEP_S]:
            del self._revoked[lease_id]
        lost = [lease for lease in self._held.values()
                if now - lease.renewed_at > self.timeout_s]
        for lease in lost:
            del self._held[lease.lease_id]
            lease.revoked_at = now
            self._revoked[lease.lease_id] = lease
        self.lost_count += len(lost)
        return lost

    def setpoint_refusal(self, now: float) -> str:
        """Why a setpoint must be refused now ('' when it may pass): a revoked lease is still
        being renewed, so its commander goes on as if it held the muscle."""
        for lease in self._revoked.values():
            if lease.renewed_at >= lease.revoked_at and now - lease.renewed_at <= self.timeout_s:
                return (f'{lease.commander} lost the muscle (its lease {lease.lease_id[:8]} ran '
                        f'out for {self.timeout_s:g} s) and still renews it: it must let go '
                        'and start again')
        return ''

    def holders(self) -> list[str]:
        """Who holds a lease now (for /diagnostics)."""
        return sorted({lease.commander for lease in self._held.values()})
