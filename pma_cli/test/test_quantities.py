"""Quantities typed the way people say them become SI, and SI prints the way people read it."""

import math
import re
import unicodedata

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pma_cli import quantities as q

pytestmark = pytest.mark.in_process


@pytest.mark.parametrize(('text', 'kind', 'si'), [
    ('200kPa', 'pressure', 200_000.0), ('200 kPa', 'pressure', 200_000.0),
    ('200KPA', 'pressure', 200_000.0), ('0.2MPa', 'pressure', 200_000.0),
    ('2bar', 'pressure', 200_000.0), ('150mbar', 'pressure', 15_000.0),
    ('1psi', 'pressure', 6894.757293168361), ('200000', 'pressure', 200_000.0),
    ('2e5', 'pressure', 200_000.0), ('.5bar', 'pressure', 50_000.0),
    ('26.5cm', 'length', 0.265), ('265mm', 'length', 0.265), ('0.265m', 'length', 0.265),
    ('0.265', 'length', 0.265), ('5s', 'time', 5.0), ('500ms', 'time', 0.5),
    ('2min', 'time', 120.0), ('1h', 'time', 3600.0), ('-3kPa', 'pressure', -3000.0),
    ('0.5Hz', 'frequency', 0.5), ('0.1', 'frequency', 0.1),
])
def test_parse_gives_si(text, kind, si):
    assert math.isclose(q.parse(text, kind), si, rel_tol=1e-12)


@pytest.mark.parametrize(('text', 'kind', 'words'), [
    ('200', 'length', None),                  # plain = SI: valid (200 m), checked elsewhere
    ('200kpa5', 'pressure', 'not a pressure'),
    ('26.5cm', 'pressure', "'cm' is not a unit of pressure"),
    ('5kPa', 'time', "'kPa' is not a unit of time"),
    ('', 'length', 'not a length'),
    ('1e999', 'pressure', 'not a finite'),
    ('1e308', 'length', 'not a finite length in cm'),    # finite in m, inf where it is shown
    ('1e308', 'time', 'not a finite time in ms'),
    ('kPa', 'pressure', 'not a pressure'),
])
def test_parse_refuses_with_a_reason(text, kind, words):
    if words is None:
        assert q.parse(text, kind) == 200.0
        return
    with pytest.raises(q.QuantityError, match=words):
        q.parse(text, kind)


def test_the_refusal_names_the_known_units():
    with pytest.raises(q.QuantityError) as error:
        q.parse('3atm', 'pressure')
    assert 'kPa' in str(error.value) and 'psi' in str(error.value) and 'Pa' in str(error.value)


@pytest.mark.parametrize(('text', 'si'), [
    ('50kPa/s', 50_000.0), ('50 kPa / s', 50_000.0), ('3bar/min', 5000.0),
    ('1kPa/ms', 1e6), ('2000', 2000.0),
])
def test_rates_are_si_per_second(text, si):
    assert math.isclose(q.parse_rate(text), si, rel_tol=1e-12)


@pytest.mark.parametrize(('text', 'words'), [
    ('50kPa', r'not a rate: give it per time \(50kPa/s\)'),   # kPa meant per second?
    ('50kPa/fortnight', "'fortnight' is not a unit of time"),
    ('5cm/s', "'cm' is not a unit of pressure"),
])
def test_a_rate_without_a_time_or_with_a_wrong_unit_is_refused(text, words):
    with pytest.raises(q.QuantityError, match=words):
        q.parse_rate(text)


def test_lists_split_on_commas_and_spaces():
    assert q.parse_list('300kPa,150kPa', 'pressure') == [300_000.0, 150_000.0]
    assert q.parse_list(' 3bar  1.5bar ', 'pressure') == [300_000.0, 150_000.0]
    with pytest.raises(q.QuantityError):
        q.parse_list(' , ', 'pressure')


@given(st.floats(min_value=0.0, max_value=1e7, allow_nan=False))
def test_kpa_round_trip(pressure_pa):
    shown = q.kpa(pressure_pa, digits=6).replace(' ', '')
    assert math.isclose(q.parse(shown, 'pressure'), pressure_pa, abs_tol=1e-3)


@given(st.floats(min_value=0.0, max_value=10.0, allow_nan=False))
def test_cm_round_trip(length_m):
    shown = q.cm(length_m, digits=6).replace(' ', '')
    assert math.isclose(q.parse(shown, 'length'), length_m, abs_tol=1e-8)


def test_missing_values_print_as_a_dash():
    assert q.kpa(math.nan) == '-' and q.cm(math.nan) == '-' and q.seconds(math.inf) == '-'


def test_durations_read_naturally():
    assert q.seconds(4.25) == '4.2 s'
    assert q.seconds(42) == '42 s'
    assert q.seconds(125) == '2 min 05 s'
    assert q.seconds(3720) == '1 h 02 min'


@pytest.mark.parametrize(('name', 'kind'), [
    ('max_gauge_pressure_pa', 'pressure'), ('calibration.length_offset_m', 'length'),
    ('sweep.step_timeout_s', 'time'), ('calibration.tare_offset_pa', 'pressure'),
    ('calibration.speed_of_sound_m_s', None), ('max_pressure_rate_pa_s', None),
    ('ki_per_s', None), ('fb_kp_pa_per_m', None), ('heartbeat_timeout_ms', None),
    ('sample_rate_hz', None), ('port', None), ('params_file', None),
])
def test_parameter_names_say_their_unit(name, kind):
    assert q.unit_of_name(name) == kind


def test_a_minimum_bounds_what_pma_uses_itself():
    assert q.parse('5s', 'time', minimum=0.0, strict=True) == 5.0
    assert q.parse('0', 'frequency', minimum=0.0) == 0.0
    with pytest.raises(q.QuantityError, match="'-1': the time must be more than 0 s"):
        q.parse('-1', 'time', minimum=0.0, strict=True)
    with pytest.raises(q.QuantityError, match='at least 0 Hz'):
        q.parse('-1Hz', 'frequency', minimum=0.0)


def test_a_rate_that_overflows_is_refused():
    with pytest.raises(q.QuantityError, match='not a finite rate'):
        q.parse_rate('1e305kPa/ms')


@pytest.mark.parametrize(('text', 'words'), [
    ('-1', "'-1' is out of range: give a whole number from 1 to 4294967295"),
    ('4294967296', 'out of range'), ('2.5', 'not a whole number'), ('ten', 'not a whole'),
])
def test_counts_are_whole_and_in_range(text, words):
    assert q.parse_count(' 7 ', 1, 2**32 - 1) == 7
    with pytest.raises(q.QuantityError, match=words):
        q.parse_count(text, 1, 2**32 - 1)


@pytest.mark.parametrize(('seconds', 'shown'), [
    (0.15, '0.15 s'), (0.001, '0.001 s'), (12.0, '12 s'), (42.5, '42.5 s'), (125.0, '2 min 05 s'),
    (90.5, '90.5 s'),
])
def test_a_time_parameter_is_shown_with_its_digits(seconds, shown):
    # fb_filter_time_constant_s = 0.15 was listed as "(0.1 s)".
    assert q.human(seconds, 'time') == shown


@pytest.mark.parametrize(('text', 'kind', 'note'), [
    ('27', 'length', '27 is read as 27 m (a plain number is SI): did you mean 27cm?'),
    ('200', 'pressure', '200 is read as 200 Pa (a plain number is SI): did you mean 200kPa?'),
    ('0.27', 'length', ''), ('27cm', 'length', ''), ('200000', 'pressure', ''),
    ('0', 'pressure', ''), ('2bar', 'pressure', ''), ('5', 'time', ''),
])
def test_a_plain_number_that_reads_like_a_unit_left_out_gets_a_note(text, kind, note):
    assert q.unit_slip(text, kind) == note


# -- ASCII only: float(), int() and a regex's \d take every script's decimal digits ----------

@pytest.mark.parametrize(('text', 'kind', 'character'), [
    ('٣٠٠', 'pressure', "'٣' (ARABIC-INDIC DIGIT THREE)"),         # was 300 Pa
    ('２００kPa', 'pressure', "'２' (FULLWIDTH DIGIT TWO)"),           # was 200 kPa
    ('26.٥cm', 'length', "'٥' (ARABIC-INDIC DIGIT FIVE)"),
    ('५s', 'time', "'५' (DEVANAGARI DIGIT FIVE)"),
    ('0.𝟏Hz', 'frequency', "'𝟏' (MATHEMATICAL BOLD DIGIT ONE)"),
])
def test_digits_of_other_scripts_are_refused_by_name(text, kind, character):
    with pytest.raises(q.QuantityError) as error:
        q.parse(text, kind)
    assert str(error.value) == (f'{text!r}: {character} is not an ASCII digit: use ASCII '
                                'digits 0-9')


@pytest.mark.parametrize(('text', 'character'), [
    ('26.5\u00a0cm', "'\\xa0' (NO-BREAK SPACE)"),          # \s took it
    ('２00kPa', "'２' (FULLWIDTH DIGIT TWO)"),
    ('200\u3000kPa', "'\\u3000' (IDEOGRAPHIC SPACE)"),
])
def test_any_character_outside_ascii_is_named(text, character):
    with pytest.raises(q.QuantityError, match=re.escape(character)):
        q.parse(text, 'length' if 'cm' in text else 'pressure')


def test_counts_rates_and_lists_take_ascii_digits_only():
    with pytest.raises(q.QuantityError, match=r"'٣' .* use ASCII digits 0-9"):
        q.parse_count('٣', 1)                                     # int() took it: 3
    with pytest.raises(q.QuantityError, match=r"'５' .* use ASCII digits 0-9"):
        q.parse_rate('５0kPa/s')
    with pytest.raises(q.QuantityError, match=r"'１' .* use ASCII digits 0-9"):
        q.parse_list('300kPa,１50kPa', 'pressure')


def other_script(number: int, digit: str) -> str:
    """`number` written in the digits of `digit`'s script (Unicode keeps each script's ten
    decimal digits in a row, 0 first)."""
    zero = ord(digit) - unicodedata.decimal(digit)
    return ''.join(chr(zero + int(d)) for d in str(number))


@given(st.integers(min_value=0, max_value=10**9),
       st.characters(categories=['Nd']).filter(lambda c: not c.isascii()))
def test_a_number_in_any_other_scripts_digits_is_never_read(number, digit):
    text = other_script(number, digit)
    for parse in (lambda: q.parse(text, 'pressure'), lambda: q.parse(f'{text}kPa', 'pressure'),
                  lambda: q.parse(f'1.{text}cm', 'length'), lambda: q.parse_count(text),
                  lambda: q.parse_rate(f'{text}kPa/s'),
                  lambda: q.parse_list(f'1kPa,{text}kPa', 'pressure')):
        with pytest.raises(q.QuantityError, match='is not an ASCII digit: use ASCII digits 0-9'):
            parse()


# -- issue 46: units typed apart, a unit of another kind, what is printed back -------------

@pytest.mark.parametrize(('argv', 'joined'), [
    (['set', '2', 'bar'], ['set', '2 bar']),
    (['sweep', '--max', '500', 'kPa', '--rate', '50', 'kPa/s'],
     ['sweep', '--max', '500 kPa', '--rate', '50 kPa/s']),
    (['move', '-2', 'mm'], ['move', '-2 mm']),
    (['set', '2', 'foo'], ['set', '2', 'foo']),             # not a unit: left for argparse
    (['set', '2bar'], ['set', '2bar']),
    (['param', 'get', 'driver_node', 'x'], ['param', 'get', 'driver_node', 'x']),
])
def test_a_unit_typed_apart_from_its_number_is_joined_to_it(argv, joined):
    assert q.join_spaced_units(argv) == joined


@pytest.mark.parametrize(('text', 'kind', 'words'), [
    ('2 bar', 'length', "'bar' is not a unit of length but of pressure (units of length: "
                        'cm, m, mm; a plain number is m)'),
    ('27cm', 'pressure', "'cm' is not a unit of pressure but of length (units of pressure: "),
    ('5kPa', 'time', "'kPa' is not a unit of time but of pressure"),
    ('3atm', 'pressure', "'atm' is not a unit of pressure (units of pressure: "),
])
def test_a_unit_of_another_kind_is_named_as_such_with_the_units_taken(text, kind, words):
    with pytest.raises(q.QuantityError) as error:
        q.parse(text, kind)
    assert words in str(error.value)
    assert 'did you mean' not in str(error.value)


def test_a_spaced_unit_is_no_unit_slip_and_bar_is_a_pressure():
    assert q.parse('2 bar', 'pressure') == 200_000.0
    assert q.unit_slip('2 bar', 'pressure') == ''          # never "did you mean 2kPa?"


@pytest.mark.parametrize(('text', 'kind', 'where', 'note'), [
    ('500', 'pressure', {'flag': '--max'},
     '--max 500 is read as 500 Pa (a plain number is SI): did you mean --max 500kPa?'),
    ('50', 'pressure', {'flag': '--rate', 'per': '/s'},
     '--rate 50 is read as 50 Pa/s (a plain number is SI): did you mean --rate 50kPa/s?'),
    ('500kPa', 'pressure', {'flag': '--max'}, ''),
])
def test_a_flags_plain_number_that_reads_like_a_unit_left_out_gets_a_note(text, kind, where,
                                                                          note):
    assert q.unit_slip(text, kind, **where) == note


@pytest.mark.parametrize(('text', 'unit'), [('300mm', 'mm'), ('27cm', 'cm'), ('0.27m', 'm'),
                                            ('0.27', 'cm'), ('2 MM', 'mm')])
def test_lengths_are_printed_back_in_the_unit_they_were_typed_in(text, unit):
    given = q.parse_given(text, 'length')
    assert q.length_unit(given) == unit
    assert q.length(float(given), unit).endswith(f' {unit}')


def test_lengths_print_to_a_tenth_of_a_millimetre_in_every_unit():
    assert [q.length(0.27, u) for u in ('cm', 'mm', 'm')] == ['27.00 cm', '270.0 mm', '0.2700 m']
    assert q.length_range(0.2445, 0.3004, 'mm') == '244.5 .. 300.4 mm'
    assert q.length(math.nan, 'mm') == '-'


@pytest.mark.parametrize(('message', 'unit', 'shown'), [
    ('holding 0.2750 m', 'cm', 'holding 27.50 cm'),
    ('target 0.4000 m is not reachable: reachable [0.2454, 0.3008] m with 0..500000 Pa', 'cm',
     'target 40.00 cm is not reachable: reachable 24.54 .. 30.08 cm with 0.0 .. 500.0 kPa'),
    ('target 0.4000 m is not reachable: reachable [0.2454, 0.3008] m with 0..500000 Pa', 'mm',
     'target 400.0 mm is not reachable: reachable 245.4 .. 300.8 mm with 0.0 .. 500.0 kPa'),
    ('hold ended: released: another node commanded 60000 Pa on pma/pressure_setpoint', 'cm',
     'hold ended: released: another node commanded 60.0 kPa on pma/pressure_setpoint'),
    # Left alone: rates, millimetres, seconds, names with a unit in them.
    ('ramp_rate_pa_s must be > 0 Pa/s', 'cm', 'ramp_rate_pa_s must be > 0 Pa/s'),
    ('settled within 2.0 mm for 1 s after 0.83 s; holding', 'cm',
     'settled within 2.0 mm for 1 s after 0.83 s; holding'),
])
def test_a_nodes_si_message_is_shown_in_one_unit_style(message, unit, shown):
    assert q.in_units(message, unit) == shown
    assert ' m ' not in f'{q.in_units(message, unit)} ' or unit == 'm'
