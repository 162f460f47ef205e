"""The one registry of muscle families: every name parsed in one place, every family listed.

docs/simulated-rig.md, "Muscle families"; docs/development.md, "Where things live".
"""

import pytest

from pma_sim import fake_arduino, registry
from pma_sim.device import DeviceConfig
from pma_sim.families import DriftingMuscle, DriftSpec
from pma_sim.registry import FAMILIES, FAMILY_NAMES, muscle_family, parse_family, parse_muscle_spec
from pma_sim.splits import TUNING, VALIDATION, set_of

pytestmark = pytest.mark.in_process

# One name of every family that builds in well under a second (duhem refits for 30 s; gpi and
# friction for 3 s: test_minor_loops.py builds those).
QUICK = ('narrow', 'wide', 'asymmetric', 'creep', 'creep:wide:0.3:1.5', 'bouc-wen')


def test_the_simulators_own_families_come_first_and_every_family_is_in_one_declared_set():
    assert FAMILY_NAMES == ('narrow', 'wide', 'asymmetric', 'creep')
    assert list(FAMILIES)[:4] == list(FAMILY_NAMES)
    assert {'bouc-wen', 'duhem', 'gpi', 'friction'} <= set(FAMILIES)
    assert set(FAMILY_NAMES) <= TUNING.names()
    # friction chose the 75 kPa correction knot: it tunes, it does not validate
    assert 'friction' in TUNING.names() and 'friction' not in VALIDATION.names()
    assert not TUNING.names() & VALIDATION.names()
    assert all(FAMILIES[name].muscle_set in ('tuning', 'validation') for name in FAMILIES)
    for muscle_set in (TUNING, VALIDATION):
        assert muscle_set.seeds == tuple(range(1, 9))
        for family in muscle_set.families:
            assert set_of(family) is muscle_set
            parse_family(family)   # every declared name is a registered family


@pytest.mark.parametrize('name', QUICK)
def test_every_quick_family_builds_a_relaxed_muscle_by_its_name(name):
    muscle = muscle_family(name)
    assert muscle.length_m == pytest.approx(muscle.rest_length_m)
    assert muscle.update(300e3, 1.0) < muscle.rest_length_m - 0.01   # it contracts


def test_parameters_are_parsed_by_the_family_that_takes_them():
    assert parse_family('gpi')[1] == (1.0,) and parse_family('gpi:2')[1] == (2.0,)
    assert parse_family('friction:0.4')[1] == (0.4,)
    assert parse_family('duhem:30:60')[1] == (30e3, 60e3)
    assert parse_family('creep')[1] == ()
    for bad, why in (('cubic', 'unknown muscle family'), ('wide:2', 'takes no parameters'),
                     ('duhem', 'duhem:RISING:FALLING'), ('gpi:x', 'gpi:BULGE'),
                     ('creep:wide', 'creep:INNER:SHARE:TAU')):
        with pytest.raises(ValueError, match=why):
            parse_family(bad)


def test_drift_is_a_suffix_of_any_family_that_has_the_option():
    assert parse_muscle_spec('gpi:2+drift') == ('gpi:2', DriftSpec())
    assert isinstance(muscle_family('creep:wide:0.3:1.5', DriftSpec()), DriftingMuscle)
    with pytest.raises(ValueError, match='no drift option'):
        parse_muscle_spec('bouc-wen+drift')
    with pytest.raises(ValueError, match='no drift option'):
        DeviceConfig(muscle='bouc-wen+drift')
    assert DeviceConfig(muscle='duhem:30:60+drift').muscle == 'duhem:30:60+drift'  # not built


def test_list_muscles_prints_every_family_one_a_line_with_its_table1_fit(capsys):
    with pytest.raises(SystemExit) as stop:
        fake_arduino.parse_args(['--list-muscles'])
    assert stop.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == registry.describe().splitlines()
    assert [line.split()[0] for line in lines] == [family.syntax for family in FAMILIES.values()]
    assert all('Table 1: ' in line for line in lines)
    assert fake_arduino.parse_args(['--muscle', 'friction:0.5+drift']).muscle == \
        'friction:0.5+drift'
