"""Parameters: stored defaults are real fits, params files round-trip, bad input is named."""

import os
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from pma_model import units
from pma_model.branches import HillBranch, SigmoidBranch, fit_branch
from pma_model.correction import CORRECTION_KNOTS_PA
from pma_model.memory import HysteresisModel
from pma_model.params import (
    MAX_PARAMS_FILE_BYTES,
    ModelParams,
    ParamsError,
    default_params,
    paper_table1,
)

pytestmark = pytest.mark.in_process

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'model_node.yaml'
SHARED_TABLE = Path(__file__).resolve().parents[2].parent / 'shared' / 'data' / \
    'paper_table1.csv'


@pytest.fixture(scope='module')
def defaults():
    return default_params()


def test_increasing_sigmoid_default_is_the_papers_fit(defaults):
    branch = defaults.increasing.sigmoid
    assert branch.a == 0.19073
    assert branch.b_per_pa == pytest.approx(units.per_kpa_to_per_pa(0.011333), rel=1e-12)
    assert branch.c == 6.214
    assert branch.l0_m == pytest.approx(units.cm_to_m(30.06), rel=1e-12)


def test_decreasing_sigmoid_default_is_a_least_squares_fit(defaults):
    table = paper_table1()
    refit = fit_branch(SigmoidBranch(units.cm_to_m(30.06), 0.15, 2e-5, 6.214),
                       table.pressure_pa, table.decreasing_length_m, fixed=('l0_m', 'c'))
    stored = defaults.decreasing.sigmoid
    assert stored.a == pytest.approx(refit.a, rel=1e-6)
    assert stored.b_per_pa == pytest.approx(refit.b_per_pa, rel=1e-6)
    assert (stored.l0_m, stored.c) == (refit.l0_m, refit.c)
    assert stored.a == pytest.approx(0.1879, abs=1e-4)
    assert units.per_pa_to_per_kpa(stored.b_per_pa) == pytest.approx(0.01305, abs=1e-5)


@pytest.mark.parametrize('direction', ['increasing', 'decreasing'])
def test_hill_defaults_are_least_squares_fits(defaults, direction):
    table = paper_table1()
    refit = fit_branch(HillBranch(0.30, 0.05, 150_000.0, 3.0), table.pressure_pa,
                       getattr(table, f'{direction}_length_m'))
    stored = getattr(defaults, direction).hill
    assert stored.vector() == pytest.approx(refit.vector(), rel=2e-6)


def test_packaged_table_is_the_shared_table():
    if not SHARED_TABLE.exists():
        pytest.skip('../shared is not present here')
    table = paper_table1()
    shared = np.genfromtxt(SHARED_TABLE, delimiter=',', names=True)
    assert np.array_equal(units.pa_to_kpa(table.pressure_pa), shared['pressure_kpa'])
    assert np.allclose(units.m_to_cm(table.decreasing_length_m),
                       shared['length_decreasing_cm'], rtol=0, atol=1e-12)


def test_config_file_carries_the_defaults_with_a_comment_on_every_parameter(defaults):
    assert ModelParams.load_yaml(CONFIG) == defaults
    lines = CONFIG.read_text().splitlines()
    leaf = re.compile(r'^\s+(\w+): (?!$)')
    for index, line in enumerate(lines):
        if leaf.match(line):
            assert lines[index - 1].strip().startswith('#'), f'no comment above: {line}'


def test_yaml_round_trip_in_the_ros_params_file_format(defaults, tmp_path):
    params = replace(defaults, branch_form='hill', memory='switch', deadband_pa=15_000.0)
    path = tmp_path / 'model.yaml'
    params.save_yaml(path)
    text = path.read_text()
    document = yaml.safe_load(text)
    assert list(document) == ['/**'] and list(document['/**']) == ['ros__parameters']
    section = document['/**']['ros__parameters']
    assert section['increasing']['sigmoid']['a'] == defaults.increasing.sigmoid.a
    assert section['adaptation']['enabled'] is False
    # Every number is written as a float, with a decimal point (ROS types it from the text).
    for value in re.findall(r':\s+([-+]?[0-9][0-9.eE+-]*)\s*$', text, flags=re.MULTILINE):
        assert '.' in value, value
    assert ModelParams.load_yaml(path) == params
    named = params.to_yaml(node_name='model_node')
    assert ModelParams.from_yaml(named) == params


def test_flat_ros_parameters_round_trip(defaults):
    flat = defaults.to_ros_parameters()
    assert flat['increasing.sigmoid.a'] == 0.19073
    assert flat['decreasing.hill.k_pa'] == defaults.decreasing.hill.k_pa
    assert flat['adaptation.enabled'] is False
    assert all(isinstance(v, float) for k, v in flat.items()
               if k not in ('branch_form', 'memory', 'adaptation.enabled',
                            'identification.enabled', 'identification.branch_correction_m',
                            'identification.branch_difference_m', 'identification.creep_gains',
                            'identification.play_rule_correction_m',
                            'identification.play_rule_difference_m',
                            'identification.play_rule_creep_gains'))
    assert flat['identification.branch_correction_m'] == [0.0] * len(CORRECTION_KNOTS_PA)
    assert flat['identification.branch_difference_m'] == [0.0] * len(CORRECTION_KNOTS_PA)
    assert len(flat) == 4 + 6 + 13 + 16
    assert ModelParams.from_ros_parameters(flat) == defaults
    changed = ModelParams.from_ros_parameters({'deadband_pa': 5000, 'memory': 'switch'})
    assert changed.deadband_pa == 5000.0 and isinstance(changed.deadband_pa, float)
    assert changed.memory == 'switch' and changed.increasing == defaults.increasing


@pytest.mark.parametrize(('values', 'named'), [
    ({'increasing.sigmoid.a': 1.5}, 'increasing.sigmoid.a must be in'),
    ({'decreasing.hill.n': -1.0}, 'decreasing.hill.n must be'),
    ({'decreasing.hill.k_pa': 170.5}, r'decreasing.hill.k_pa .*not kPa'),
    ({'increasing.sigmoid.b_per_pa': 0.011333}, r'b_per_pa .*per Pa, not per kPa'),
    ({'increasing.hill.l0_m': 30.18}, r'l0_m .*metres, not cm'),
    ({'max_gauge_pressure_pa': 500.0}, r'max_gauge_pressure_pa .*Pa, not kPa'),
    ({'deadband_pa': 400_000.0}, 'deadband_pa must be'),
    ({'deadband_pa': 'big'}, 'deadband_pa must be a number'),
    ({'deadband_pa': True}, 'deadband_pa must be a number'),
    ({'deadband_pa': float('nan')}, 'deadband_pa must be finite'),
    ({'adaptation.enabled': 'yes'}, 'adaptation.enabled must be true or false'),
    ({'adaptation.time_constant_s': 0.2}, 'adaptation.time_constant_s must be'),
    ({'identification.play_share_rising': 2.0}, 'identification.play_share_rising must be'),
    ({'memory': 'preisach'}, 'memory must be one of'),
    ({'branch_form': 'cubic'}, 'branch_form must be one of'),
    ({'increasing.sigmoid.q': 1.0}, r"unknown parameter\(s\) \['increasing.sigmoid.q'\]"),
])
def test_validation_names_the_bad_field(values, named):
    with pytest.raises(ParamsError, match=named):
        ModelParams.from_ros_parameters(values)


def test_a_correction_of_another_length_is_refused(tmp_path):
    # Only today's knots are read (no file written before the 75 kPa knot is kept).
    section = {'identification': {'branch_correction_m': [0.0] * (len(CORRECTION_KNOTS_PA) - 1)}}
    path = tmp_path / 'other_knots.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': section}}))
    with pytest.raises(ParamsError, match='branch_correction_m must have 12 values'):
        ModelParams.load_yaml(path)


def test_bad_files_are_refused_with_the_path(tmp_path):
    with pytest.raises(ParamsError, match='cannot read'):
        ModelParams.load_yaml(tmp_path / 'missing.yaml')
    broken = tmp_path / 'broken.yaml'
    broken.write_text('/**:\n  ros__parameters: [1, 2\n')
    with pytest.raises(ParamsError, match=r'broken\.yaml: not valid YAML'):
        ModelParams.load_yaml(broken)
    wrong = tmp_path / 'wrong.yaml'
    wrong.write_text('branch_form: hill\n')
    with pytest.raises(ParamsError, match='ros__parameters'):
        ModelParams.load_yaml(wrong)


def test_a_non_utf8_byte_is_refused_with_its_offset(defaults, tmp_path):
    # Even in a comment: the whole file must be text before YAML sees it.
    latin1 = tmp_path / 'latin1.yaml'
    latin1.write_bytes(defaults.to_yaml().encode() + b'# caf\xe9\n')
    offset = len(defaults.to_yaml().encode()) + 5
    with pytest.raises(ParamsError, match=rf'latin1\.yaml is not UTF-8 text: byte 0xe9 at '
                                          rf'offset {offset} \(line \d+\)'):
        ModelParams.load_yaml(latin1)


@pytest.mark.timeout(10)
def test_files_that_never_end_or_block_are_refused_at_once(tmp_path):
    # /dev/zero would be read until memory runs out, a FIFO without a writer blocks a
    # plain open() forever (and model_node has one executor thread): neither is a file.
    fifo = tmp_path / 'params.fifo'
    os.mkfifo(fifo)
    for path, kind in (('/dev/zero', 'a character device'), (fifo, 'a FIFO'),
                       (tmp_path, 'a directory')):
        with pytest.raises(ParamsError, match=f'is {kind}, not a regular file'):
            ModelParams.load_yaml(path)


def test_a_file_larger_than_any_params_file_is_refused(defaults, tmp_path):
    big = tmp_path / 'big.yaml'
    big.write_text(defaults.to_yaml() + '#' * MAX_PARAMS_FILE_BYTES + '\n')
    with pytest.raises(ParamsError, match=f'more than the {MAX_PARAMS_FILE_BYTES}'):
        ModelParams.load_yaml(big)
    # A params file of ordinary size, with comments, still loads.
    fine = tmp_path / 'fine.yaml'
    fine.write_text('# refit output\n' + defaults.to_yaml())
    assert ModelParams.load_yaml(fine) == defaults


def test_build_model_and_online_model_use_the_selected_form(defaults):
    hill = replace(defaults, branch_form='hill', memory='switch', deadband_pa=5_000.0,
                   max_gauge_pressure_pa=400_000.0)
    model = hill.build_model()
    assert isinstance(model, HysteresisModel)
    assert model.increasing == defaults.increasing.hill
    assert model.decreasing == defaults.decreasing.hill
    assert (model.memory, model.deadband_pa, model.max_gauge_pressure_pa) == (
        'switch', 5_000.0, 400_000.0)
    online = hill.build_online()
    assert online.model.increasing == defaults.increasing.hill
    assert (online.memory, online.deadband_pa) == ('switch', 5_000.0)
    swapped = defaults.with_branches(HillBranch(0.3, 0.06, 2e5, 2.0),
                                     HillBranch(0.3, 0.06, 1.8e5, 2.0))
    assert swapped.increasing.hill.k_pa == 2e5 and swapped.increasing.sigmoid == \
        defaults.increasing.sigmoid
    with pytest.raises(ParamsError, match='same form'):
        defaults.with_branches(HillBranch(0.3, 0.06, 2e5, 2.0), defaults.decreasing.sigmoid)


def test_table_1_stroke_is_rest_to_the_shortest_length():
    """30.06 cm at rest, 24.20 cm at 500 kPa (the rising branch's 30.063 cm at 50 kPa is
    above rest, not part of the stroke)."""
    assert units.m_to_cm(paper_table1().stroke_m) == pytest.approx(5.86, abs=1e-9)
