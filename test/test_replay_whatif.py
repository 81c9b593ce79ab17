"""What-if replays and re-evaluation: a recorded session drives fresh controllers."""

import json
import os

import numpy as np
import pytest

from erva_ros.core.model.quarter_car import make_model
from erva_ros.session.bag.offline_bag import run_and_record
from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.bag.reader import open_bag
from erva_ros.session.bag.reevaluate import reevaluate
from erva_ros.session.bag.bag_report import load_session
from erva_ros.core.controllers import load_controller_settings, make_controller
from erva_ros.core.model.params import load_erva_params
from erva_ros.core.road.profiles import make_road


@pytest.fixture(scope='module')
def passive_session(tmp_path_factory):
    params = load_erva_params(None)
    bag = str(tmp_path_factory.mktemp('whatif') / 'passive')
    model = make_model(params)
    result, _ = run_and_record(bag, model, make_controller('passive', model),
                               make_road('paper', 2.0, seed=5), 2.0,
                               session={'scenario': 'paper', 'controller': 'passive'})
    return bag, result


def test_the_recorded_road_with_the_same_controller_reproduces_the_session(
        erva, passive_session, tmp_path):
    bag, result = passive_session
    out = json.loads(erva('replay', bag, '--drive-plant', '--controller', 'passive',
                          '--record-dir', tmp_path, '--json', check=True).stdout)
    for key in ('acc_2norm', 'acc_rms', 'power_w'):
        assert out['recorded'][key] == pytest.approx(result.metrics[key], rel=1e-12), key
    # The what-if ends at the last recorded road sample, one period early; up to there
    # it is the original run: the plant only sees the road at the control samples,
    # which the bag holds exactly.
    assert out['what_if']['duration_s'] == pytest.approx(2.0 - 0.02)
    params = load_erva_params(None)
    model = make_model(params)
    short = simulate_closed_loop(model, make_controller('passive', model),
                                 make_road('paper', 2.0, seed=5), 2.0 - 0.02)
    for key in ('acc_2norm', 'acc_rms', 'power_w'):
        assert out['what_if'][key] == pytest.approx(short.metrics[key], rel=1e-9), key


def test_what_if_with_another_controller_is_a_new_session(erva, passive_session, tmp_path):
    bag, result = passive_session
    proc = erva('replay', bag, '--drive-plant', '--controller', 'skyhook',
                '--record-dir', tmp_path, check=True)
    assert 'what-if (skyhook)' in proc.stdout and 'recorded (passive)' in proc.stdout
    [new] = [os.path.join(tmp_path, d) for d in os.listdir(tmp_path)]
    assert os.path.basename(new).endswith('_whatif-skyhook')
    new_bag = open_bag(new)
    assert new_bag.complete and new_bag.session['controller'] == 'skyhook'
    assert new_bag.session['based_on'] == bag
    assert new_bag.session['source'].startswith('offline closed loop')
    old, fresh = load_session(open_bag(bag)), load_session(new_bag)
    assert fresh.road.n == old.road.n - 1      # ends at the last recorded road sample
    np.testing.assert_allclose(fresh.road.values[:, 1], old.road.values[:-1, 1], atol=1e-15)
    assert not np.allclose(fresh.cmd.values[:, 0], old.cmd.values[:-1, 0])  # other commands
    report = json.loads(erva('report', new, '--json', check=True).stdout)
    assert report['comfort']['acc_2norm'] != pytest.approx(result.metrics['acc_2norm'])


def test_what_if_options_are_checked(erva, passive_session, tmp_path):
    bag, _ = passive_session
    for args in (['--controller', 'skyhook'],                       # needs --drive-plant
                 ['--drive-plant', '--loop'],
                 ['--drive-plant', '--controller', 'nonsense']):
        proc = erva('replay', bag, *args, '--record-dir', tmp_path)
        assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, args


def test_recorded_states_and_previews_reproduce_the_nmpc_commands(tmp_path):
    """Determinism: a fresh NMPC fed the session's inputs gives its recorded commands."""
    params = load_erva_params(None)
    # No wall-clock budget: an over-budget fallback would depend on the machine's load.
    settings = load_controller_settings(None, {'controller': 'preview',
                                               'time_budget_s': 10.0})
    bag = str(tmp_path / 'nmpc')
    steps = 12
    model = make_model(params)
    run_and_record(bag, model, make_controller('preview', model, settings),
                   make_road('paper', steps * settings.ts, seed=2), steps * settings.ts)
    data = load_session(open_bag(bag))
    again = reevaluate(data, make_controller('preview', make_model(params), settings))
    assert len(again.recorded) == steps and set(again.statuses) == {'ok'}
    # The same inputs (the bag's doubles) to the same compiled solver: bit for bit.
    assert again.max_abs_difference() == 0.0
    # The check can fail: other weights give other commands.
    other = reevaluate(data, make_controller('preview', make_model(params),
                                             settings.with_(alpha1=1.0, alpha2=1.0)),
                       max_commands=4)
    assert other.max_abs_difference() > 1.0
