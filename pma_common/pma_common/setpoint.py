"""Which gauge pressure may be commanded at all: the rule, and its words, in one place.

Plain Python, no ROS: DeviceControl.setpoint_refusal (the driver's gate) applies it to every
setpoint and sweep step before the device, and `pma set` applies it before it publishes, with
the ceiling read from driver_node's `max_gauge_pressure_pa`; so a pressure the driver refuses
never reaches pma/pressure_setpoint from `pma`, and both say why in the same words.
"""

from __future__ import annotations

import math


def setpoint_refusal(gauge_pa: float, ceiling_pa: float) -> tuple[str, str]:
    """(kind, reason) why `gauge_pa` must not be commanded under `ceiling_pa`; ('', '') when
    it may. `ceiling_pa` is whole Pa (parameters.device_ceiling_pa), or inf for no ceiling."""
    if not math.isfinite(gauge_pa):
        return 'non-finite', f'setpoint {gauge_pa} is not a finite number'
    if gauge_pa < 0:
        return 'negative', f'setpoint {gauge_pa:.0f} Pa is negative (gauge pressure)'
    if gauge_pa > ceiling_pa:
        return 'too high', (f'setpoint {gauge_pa:.0f} Pa is above max_gauge_pressure_pa '
                            f'{ceiling_pa:.0f} Pa')
    return '', ''
