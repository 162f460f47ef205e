"""`pma`'s argument parsing: a negative quantity is a value, an option stays an option."""

import pytest
from pma_cli.main import parser


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
