"""refit --memory-check identifies the memory offline and --params-out carries what it learned.

The recorded path: minor loops made by the default (Table 1) branches with a known play
share per direction and a known branch correction, plus sensor-sized noise, sampled like
the driver at 50 Hz. The identify rule, run online along it as model_node would, must win
and learn the shares; the params file must hold them, and model_node's parameters must load.
"""

import itertools

import numpy as np
import yaml
from test_refit import PAPER_TABLE, run_refit
from test_samples import write_sample_log

from pma_model.identification import CorrectedBranch, correction_caps, monotone_correction
from pma_model.memory import HysteresisModel
from pma_model.params import ModelParams, default_params

SHARES = (0.85, 0.15)


def test_memory_check_identifies_the_shares_and_params_out_writes_them(procs, tmp_path):
    branches = default_params().branches()
    caps = np.minimum(*(correction_caps(branch) for branch in branches))
    correction = monotone_correction(
        [0.002 * np.sin(np.pi * k / 10) for k in range(11)], caps)
    truth = HysteresisModel(*(CorrectedBranch(b, correction) for b in branches),
                            memory='identify', play_shares=SHARES)
    rng = np.random.default_rng(8)
    turns = [0.0]
    for k in range(40):
        turns.append(rng.uniform(turns[-1], 500e3) if k % 2 == 0 else rng.uniform(0, turns[-1]))
    turns.append(0.0)
    pressure = np.concatenate([np.linspace(a, b, max(2, round(abs(b - a) / 4e3)))[1:]
                               for a, b in itertools.pairwise(turns)])
    length = truth.predict(pressure) + rng.normal(0.0, 5e-4, pressure.size)
    path = write_sample_log(tmp_path / 'minor.csv', np.arange(pressure.size) / 50.0, pressure,
                            length)
    code, output = run_refit(procs, PAPER_TABLE, '--no-holdout', '--memory-check', path,
                             '--json', tmp_path / 'r.json', '--params-out', tmp_path / 'p.yaml',
                             '--model', 'sigmoid_fixed_c')
    assert code == 0, output
    check = yaml.safe_load((tmp_path / 'r.json').read_text())['memory_check']
    assert check['best_memory']['sigmoid_fixed_c'] == 'identify'
    learned = check['identified']['sigmoid_fixed_c']
    assert abs(learned['play_share_rising'] - SHARES[0]) < 0.15
    assert abs(learned['play_share_falling'] - SHARES[1]) < 0.15
    assert 'sigmoid_fixed_c/identify learned: play share rising' in output
    written = yaml.safe_load((tmp_path / 'p.yaml').read_text())['/**']['ros__parameters']
    assert written['memory'] == 'identify'
    assert written['identification']['play_share_rising'] == learned['play_share_rising']
    assert written['identification']['branch_correction_m'] == learned['branch_correction_m']
    assert written['identification']['branch_difference_m'] == learned['branch_difference_m']
    assert 'adaptation' not in written          # the node's own settings stay its own
    loaded = ModelParams.load_yaml(tmp_path / 'p.yaml')
    assert loaded.identification.play_shares == (learned['play_share_rising'],
                                                  learned['play_share_falling'])
