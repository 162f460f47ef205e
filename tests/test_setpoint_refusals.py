"""`pma set` refuses what the driver's command gate would refuse by its value, in the driver's
own words, before anything is published (the process tests: tests/test_cli.py). Here, as it
takes both packages: pma_cli does not depend on pma_driver."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pma_cli.commands import DEFAULT_CEILING_PA, check_setpoint
from pma_cli.session import FAILED, CliError
from pma_common.driver_parameters import PARAMETERS, device_ceiling_pa
from pma_driver.command_gate import DeviceControl

pytestmark = pytest.mark.in_process


@given(st.floats() | st.sampled_from([300_000.0, 300_000.4, 300_000.6, -0.0, -1e-9]),
       st.floats(min_value=1000.0, max_value=1_000_000.0))      # the parameter's range
def test_pma_refuses_what_the_driver_refuses_in_the_drivers_words(value, parameter):
    driver = DeviceControl(parameter)       # no link: the parameter is the whole ceiling
    kind, reason = driver.setpoint_refusal(value)
    ceiling = device_ceiling_pa(parameter, None)        # what `pma set` makes of the parameter
    if kind == 'inactive':                  # the value would do; the driver is not running
        check_setpoint(value, ceiling, 'the parameter of /driver_node')
        return
    with pytest.raises(CliError) as error:
        check_setpoint(value, ceiling, 'the parameter of /driver_node')
    assert error.value.code == FAILED
    assert str(error.value).startswith('refused ') and f': {reason}' in str(error.value)
    assert str(error.value).endswith('; nothing was sent')


def test_without_a_driver_the_parameters_default_is_the_ceiling():
    assert DEFAULT_CEILING_PA == PARAMETERS['max_gauge_pressure_pa'][0] == 500_000
    with pytest.raises(CliError, match='refused 501.0 kPa: setpoint 501000 Pa is above '
                       r"max_gauge_pressure_pa 500000 Pa \(the parameter's default"):
        check_setpoint(501_000.0, DEFAULT_CEILING_PA, "the parameter's default")
    check_setpoint(500_000.0, DEFAULT_CEILING_PA)
