"""`pma`'s argument parsing: a negative quantity is a value, an option stays an option."""

import pytest
from rcl_interfaces.msg import ParameterType

from pma_cli.commands import typed_value
from pma_cli.main import main, parser
from pma_cli.session import CliError


def parsed(*argv: str):
    return parser().parse_args(list(argv))


@pytest.mark.parametrize(('argv', 'field', 'si'), [
    (('set', '-5kPa'), 'pressure', -5000.0),
    (('set', '-5'), 'pressure', -5.0),
    (('length', '-0.5cm'), 'length', -0.005),
    (('length', '-.5cm'), 'length', -0.005),
    (('move', '-2mm'), 'length', -0.002),
])
def test_a_negative_quantity_with_a_unit_is_a_value_for_the_node_to_judge(argv, field, si):
    # argparse alone took `-5kPa` for an unknown option and said the pressure was missing.
    assert getattr(parsed(*argv), field) == pytest.approx(si)


def test_options_are_still_options_beside_a_negative_value():
    args = parsed('set', '-n', 'left', '--timeout', '2s', '-5kPa')
    assert (args.namespace, args.timeout, args.pressure) == ('left', 2.0, -5000.0)


@pytest.mark.parametrize('argv', [('set', '--bogus', '200kPa'), ('set', '-x5kPa'),
                                  ('set', '-5parsecs')])
def test_what_is_neither_is_refused_with_usage_status(argv, capsys):
    with pytest.raises(SystemExit) as ended:
        parsed(*argv)
    assert ended.value.code == 2
    assert 'error:' in capsys.readouterr().err


def refusal(capsys, *argv: str) -> str:
    """argparse's one error line for argv (exit 2, no traceback)."""
    with pytest.raises(SystemExit) as ended:
        parsed(*argv)
    assert ended.value.code == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if 'error:' in line]
    assert len(errors) == 1
    return errors[0]


@pytest.mark.parametrize('value', ['-inf', '-nan', '-Infinity', '-NaN'])
def test_minus_inf_and_nan_are_values_the_quantity_parser_refuses(value, capsys):
    # argparse took `-inf` for an option (pressure "required") and `-nan` for `-n an`.
    assert f"{value!r} is not a pressure" in refusal(capsys, 'set', value)


def test_a_namespace_starting_with_an_stays_the_short_option():
    assert parsed('status', '-nanimal').namespace == 'animal'


@pytest.mark.parametrize(('flag', 'value'), [
    ('--cycles', '-1'), ('--cycles', '0'), ('--cycles', '4294967298'),
    ('--cycles', '5000000000'), ('--forc-count', '-2'), ('--forc-count', '4294967297'),
    ('--cycles', '2.5'),
])
def test_counts_outside_their_message_field_are_refused_not_wrapped(flag, value, capsys):
    # Sweep.Goal's cycles and forc_count are uint32: -1 raised inside rclpy, 2**32 + 2 became 2.
    line = refusal(capsys, 'sweep', '--max', '200kPa', '--step', '100kPa', flag, value)
    assert flag in line and repr(value) in line


def test_the_largest_count_the_field_holds_is_taken():
    args = parsed('sweep', '--cycles', '4294967295', '--forc-count', '4294967295')
    assert (args.cycles, args.forc_count) == (4294967295, 4294967295)


def test_watch_count_is_zero_or_more(capsys):
    assert parsed('watch').count == 0                  # until Ctrl-C
    assert "'-3' is out of range" in refusal(capsys, 'watch', '--count', '-3')
    assert 'at least 0 Hz' in refusal(capsys, 'watch', '--max-rate', '-1')
    assert parsed('watch', '--max-rate', '5Hz').max_rate == 5.0


@pytest.mark.parametrize('verb', ['length', 'move'])
def test_a_length_that_overflows_in_cm_is_refused_like_inf(verb, capsys):
    assert 'not a finite length' in refusal(capsys, verb, '1e308')


@pytest.mark.parametrize('value', ['-1', '0', '0s', '-5ms'])
def test_a_timeout_must_be_more_than_zero(value, capsys):
    assert 'must be more than 0 s' in refusal(capsys, 'length', '27cm', '--timeout', value)


@pytest.mark.parametrize(('value', 'words'), [
    ('bad name!', "must not contain characters other than alphanumerics, '_', or '/'"),
    ('1abc', 'must not have a token that starts with a number'),
    ('a//b', "must not contain repeated '/'"),
])
def test_a_namespace_rcl_would_refuse_is_a_usage_error(value, words, capsys):
    line = refusal(capsys, 'status', '--namespace', value)
    assert f'{value!r} is not a ROS namespace: {words}' in line


@pytest.mark.parametrize('value', ['/', '', 'left', '/left/', ' right '])
def test_namespaces_as_people_type_them_are_taken(value):
    assert parsed('status', '--namespace', value).namespace == value


def test_an_output_that_names_a_directory_is_refused(tmp_path, capsys):
    # Path() drops the trailing slash: `missing/` used to become a file named `missing`.
    assert 'is a directory' in refusal(capsys, 'export', 'bag', '--csv', f'{tmp_path}/new/')
    assert 'is a directory' in refusal(capsys, 'export', 'bag', '--csv', str(tmp_path))
    assert 'is a directory' in refusal(capsys, 'calibrate', '-o', f'{tmp_path}/')
    assert parsed('export', 'bag', '--csv', f'{tmp_path}/out.csv').csv == tmp_path / 'out.csv'
    assert str(parsed('export', 'bag', '--csv', '-').csv) == '-'


def test_export_into_a_missing_directory_is_refused_before_the_bag_is_read(tmp_path, capsys):
    # Checked when it runs, not by the parser: a documented line may make the directory first.
    assert main(['export', str(tmp_path / 'no_bag'), '--csv', f'{tmp_path}/new/out.csv']) == 2
    assert capsys.readouterr().err == (f'pma export: there is no directory {tmp_path}/new to '
                                       'write out.csv in\n')
    assert not (tmp_path / 'new').exists()


@pytest.mark.parametrize(('value', 'words'), [
    ('bad node!', "must not contain characters other than alphanumerics or '_'"),
    ('1x', 'must not start with a number'), ('driver_node/', 'must not be empty'),
    ('/1abc/driver_node', "'/1abc/driver_node' is not a ROS node name: must not have a token"),
])
def test_a_node_name_rcl_would_refuse_is_a_usage_error(value, words, capsys):
    assert words in refusal(capsys, 'param', 'get', value, 'x')


@pytest.mark.parametrize('value', ['driver_node', 'left/driver_node', '/left/driver_node'])
def test_node_names_relative_or_absolute_are_taken(value):
    assert parsed('param', 'list', value).node == value


@pytest.mark.parametrize(('text', 'kind', 'words'), [
    ('99999999999999999999', ParameterType.PARAMETER_INTEGER, 'out of range'),
    ('-9223372036854775809', ParameterType.PARAMETER_INTEGER, 'out of range'),
    ('1.5', ParameterType.PARAMETER_INTEGER, 'not a whole number'),
    ('[1, 99999999999999999999]', ParameterType.PARAMETER_INTEGER_ARRAY, 'outside'),
])
def test_an_integer_parameter_value_must_fit_int64(text, kind, words):
    # rclpy raised a SystemError from inside the service call for 2**64.
    with pytest.raises(CliError, match=words) as error:
        typed_value('qos_depth', text, kind)
    assert error.value.code == 2


@pytest.mark.parametrize(('text', 'kind'), [
    ('٢٠', ParameterType.PARAMETER_DOUBLE),            # float() took it: 20.0
    ('２0', ParameterType.PARAMETER_INTEGER),          # int() took it: 20
])
def test_a_numeric_parameter_value_takes_ascii_digits_only(text, kind):
    with pytest.raises(CliError, match='is not an ASCII digit: use ASCII digits 0-9') as error:
        typed_value('sample_rate_hz', text, kind)
    assert error.value.code == 2


def test_the_largest_int64_is_a_parameter_value():
    assert typed_value('qos_depth', '9223372036854775807',
                       ParameterType.PARAMETER_INTEGER) == 2 ** 63 - 1


@pytest.mark.parametrize(('argv', 'note'), [
    (('move', '27'), 'did you mean 27cm?'),
    (('length', '27'), 'did you mean 27cm?'),
    (('set', '200'), 'did you mean 200kPa?'),
])
def test_a_plain_number_like_a_unit_left_out_is_taken_as_si_with_a_note(argv, note, capsys):
    # `pma move 27` said only `moving to 2700.00 cm`, then that it was not reachable.
    args = parsed(*argv)
    assert getattr(args, 'length', None) == 27.0 or args.pressure == 200.0
    err = capsys.readouterr().err
    assert f'pma: note: {argv[1]} is read as' in err and note in err, err


def test_a_plain_number_that_fits_gets_no_note(capsys):
    parsed('move', '0.27')
    parsed('set', '200000')
    assert capsys.readouterr().err == ''


# -- issue 46 ------------------------------------------------------------------------------

@pytest.mark.parametrize(('argv', 'field', 'si'), [
    (('set', '2', 'bar'), 'pressure', 200_000.0),           # bar is a pressure unit: 200 kPa
    (('set', '150', 'kPa', '--wait'), 'pressure', 150_000.0),
    (('move', '27', 'cm'), 'length', 0.27),
    (('sweep', '--max', '500', 'kPa', '--step', '100', 'kPa'), 'max_pa', 500_000.0),
    (('sweep', '--profile', 'ramp', '--max', '3', 'bar', '--rate', '50', 'kPa/s'),
     'rate_pa_s', 50_000.0),
])
def test_a_unit_typed_apart_from_its_number_is_taken_with_it_and_no_note(argv, field, si,
                                                                         capsys):
    # `pma set 2 bar` took 2 Pa, suggested `2kPa` and refused `bar` as an extra argument.
    assert getattr(parsed(*argv), field) == pytest.approx(si)
    assert capsys.readouterr().err == ''


def test_a_unit_of_another_kind_typed_apart_is_refused_naming_the_units_taken(capsys):
    line = refusal(capsys, 'move', '2', 'bar')
    assert "'bar' is not a unit of length but of pressure (units of length: cm, m, mm" in line
    assert 'did you mean' not in line


def test_run_passes_its_arguments_on_untouched():
    args = parsed('run', 'pma_sim', 'fake_arduino', '--delay', '5', 's')
    assert args.args == ['--delay', '5', 's']


@pytest.mark.parametrize(('argv', 'note'), [
    (('sweep', '--max', '500', '--step', '100kPa'), 'did you mean --max 500kPa?'),
    (('sweep', '--max', '500kPa', '--step', '50'), 'did you mean --step 50kPa?'),
    (('sweep', '--profile', 'ramp', '--max', '300kPa', '--rate', '50'),
     'did you mean --rate 50kPa/s?'),
    (('sweep', '--max', '500kPa', '--step', '100kPa', '--reversals', '300,150kPa'),
     'did you mean --reversals 300kPa?'),
    (('sweep', '--profile', 'sine', '--amplitude', '100', '--offset', '200kPa',
      '--frequency', '0.1Hz'), 'did you mean --amplitude 100kPa?'),
    (('set', '200kPa', '--tolerance', '5'), 'did you mean --tolerance 5kPa?'),
    (('move', '27cm', '--tolerance', '2'), 'did you mean --tolerance 2cm?'),
    (('calibrate', '--check-pressure', '300'), 'did you mean --check-pressure 300kPa?'),
])
def test_a_flags_plain_number_like_a_unit_left_out_gets_the_note_cli_md_promises(argv, note,
                                                                                capsys):
    parsed(*argv)
    err = capsys.readouterr().err
    assert err.startswith('pma: note: ') and note in err, err


def test_a_flags_plain_number_in_si_gets_no_note(capsys):
    parsed('sweep', '--max', '500000', '--step', '100000', '--hold', '5', '--rate', '5e4')
    assert capsys.readouterr().err == ''


@pytest.mark.parametrize(('argv', 'unit'), [(('length', '300mm'), 'mm'), (('move', '27cm'), 'cm'),
                                            (('length', '0.3m'), 'm'), (('move', '0.27'), 'cm')])
def test_a_length_keeps_the_unit_it_was_typed_in(argv, unit):
    from pma_cli import quantities as q
    assert q.length_unit(parsed(*argv).length) == unit
