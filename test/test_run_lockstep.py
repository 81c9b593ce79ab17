"""Lock-step mode: the live nodes over real DDS reproduce `erva sim` for the same scenario.

And with a command delay d > 0 (logical execution time) so does real time: each command
acts at its sample + d in the plant, so when none is late a realtime run, a lock-step run
and `erva sim --actuation-delay d --command-delay d` are one trajectory.
"""

import json
import os

import numpy as np
import pytest
import yaml

from erva_ros.cli import build_parser
from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.commands._closed_loop_options import (load_settings, make_road_from_args,
                                                    preview_model_from_args)
from erva_ros.commands.run import run_config
from erva_ros.core.controllers import make_controller
from erva_ros.core.model.quarter_car import make_model
from erva_ros.session.run.orchestrator import run_session
from erva_ros.core.model.params import load_erva_params

from conftest import REPO

pytestmark = pytest.mark.ros   # every test here starts DDS

# One scenario, spelled the way each command takes it: the real NMPC with preview, the
# paper's twofold weights, a noisy preview and a non-default seed, so the road, the
# preview error, the controller's warm start and the plant must all line up.
SIM = ['sim', '--controller', 'preview', '--alpha', '1,0.01', '--seed', '4', '--duration', '1',
       '--preview-snr', '15']
RUN = ['run', '--controller', 'preview', '--alpha1', '1', '--alpha2', '0.01', '--seed', '4',
       '--duration', '1', '--preview-snr', '15', '--mode', 'lockstep', '--no-record',
       '--command-delay', '0']    # the paper's loop; the shipped d: the test below


def _settings_file(tmp_path):
    """Return the shipped nmpc.yaml with the largest time budget.

    The lock-step NMPC ignores the wall-clock budget (time is simulated); with this file
    a slow solve on a busy machine cannot make `erva sim` fall back either.
    """
    doc = yaml.safe_load(open(os.path.join(REPO, 'config', 'nmpc.yaml')))
    section = next(v for k, v in doc.items() if k.rstrip('/').endswith('nmpc_node'))
    section['ros__parameters']['time_budget_s'] = 10.0
    path = tmp_path / 'nmpc.yaml'
    path.write_text(yaml.safe_dump(doc))
    return str(path)


def _offline(sim_args, delay=0.0):
    """Run the offline closed loop exactly as `erva sim` builds it."""
    params = load_erva_params(sim_args.params)
    settings = load_settings(sim_args, alpha1=sim_args.alpha[0], alpha2=sim_args.alpha[1])
    ctrl = make_controller(settings.controller, make_model(params), settings)
    road = make_road_from_args(sim_args, sim_args.duration, sim_args.seed)
    preview = preview_model_from_args(sim_args, sim_args.seed, settings.ts)
    return simulate_closed_loop(make_model(params), ctrl, road, sim_args.duration, settings.ts,
                                preview_model=preview, actuation_delay_s=delay)


def _same_run(tr, off, mode=''):
    """Check a live run's trajectory against `erva sim`'s: the same computation.

    The nodes get the very floats `erva sim` computes with (states, road samples and
    commands cross DDS as IEEE doubles) and run the same compiled functions, so states,
    commands and accelerations are equal bit for bit on any CPU.  (The NMPC turns a
    last-bit change of an input into ~1e-6 Ns/m of command, so a tolerance here would
    hide a real difference of inputs.)  Two figures are other arithmetic of the same
    values, within a few units in the last place of the signal: the live sample time is
    its stamp in ns times 1e-9 (`erva sim`: k·Ts), and the live power is the generator
    message's effort · velocity (`erva sim`: the model's u·v_gen²).
    """
    eps = np.finfo(float).eps
    np.testing.assert_array_equal(tr['x'], off.x, err_msg=mode)
    np.testing.assert_array_equal(tr['u'], off.u, err_msg=mode)
    np.testing.assert_array_equal(tr['sprung_accel'], off.sprung_accel, err_msg=mode)
    np.testing.assert_allclose(tr['t'], off.t, rtol=0, atol=4 * eps * off.t[-1], err_msg=mode)
    np.testing.assert_allclose(tr['power'], off.power, rtol=0,
                               atol=8 * eps * np.max(np.abs(off.power)), err_msg=mode)


def test_lockstep_run_equals_erva_sim(tmp_path, erva):
    parser = build_parser()
    settings = _settings_file(tmp_path)
    cfg = run_config(parser.parse_args(RUN + ['--nmpc', settings]), record_dir=None)
    cfg.session_dir = str(tmp_path)
    live = run_session(cfg)
    assert live.exit_code == 0, live.summary['errors']
    off = _offline(parser.parse_args(SIM + ['--settings', settings]))

    tr = live.trajectory
    assert tr['x'].shape == off.x.shape == (50, 6)
    _same_run(tr, off)
    np.testing.assert_array_equal(tr['w'], off.w)
    # Nothing was skipped, late or lost on the way.
    plant = live.summary['plant']
    assert plant['u_from_command'] == 50 and plant['lockstep_timeouts'] == 0
    assert live.summary['messages']['dropped_total'] == 0

    # And the metrics equal those `erva sim --json` prints.
    sim = json.loads(erva(*SIM, '--settings', settings, '--json', check=True).stdout)
    m = live.summary['metrics']
    assert abs(m['acc_2norm'] - sim['acc_2norm']) < 1e-9 * sim['acc_2norm']
    assert abs(m['power_w'] - sim['power_w']) < 1e-7 * max(sim['power_w'], 1e-3)


#: The determinism test's d: the shipped one would do; this one leaves a loaded machine
#: (both cores busy) more room, so that no command is late and the test holds anywhere.
LET_DELAY = 0.015


def _live(parser, tmp_path, mode, settings):
    args = [a if a != 'lockstep' else mode for a in RUN] + [
        '--nmpc', settings, '--command-delay', str(LET_DELAY)]
    cfg = run_config(parser.parse_args(args), record_dir=None)
    cfg.session_dir = str(tmp_path / mode)
    return run_session(cfg)


def test_realtime_equals_lockstep_equals_erva_sim_at_a_command_delay(tmp_path):
    parser = build_parser()
    settings = _settings_file(tmp_path)
    off = _offline(parser.parse_args(SIM + ['--settings', settings, '--command-delay',
                                            str(LET_DELAY)]), delay=LET_DELAY)
    late = None
    for mode in ('lockstep', 'realtime'):
        live = _live(parser, tmp_path, mode, settings)
        plant = live.summary['plant']
        if mode == 'realtime' and plant['late_commands']:
            # A command that arrived after t_k + d on an overloaded machine: the late rule
            # acted (test_let checks it), and the claim is for runs without one.
            late = (plant['late_commands'], plant['command_arrival_ms'])
            break
        assert live.exit_code == 0, (mode, live.summary['errors'])
        # Every command acted, at its instant: none late, none replaced by its plan.
        assert plant['late_commands'] == 0, (mode, plant['command_arrival_ms'])
        assert plant['u_from_command'] == 50 and plant['command_delay_ms'] == 15.0
        tr = live.trajectory
        assert tr['x'].shape == off.x.shape == (50, 6)
        # The power at t_k is the damping acting then: the command before, until t_k + d.
        _same_run(tr, off, mode)
    if late:
        pytest.skip(f'realtime leg not compared: {late[0]} commands arrived after t_k + d '
                    f'(arrival {late[1]} ms) on this load; lock-step == erva sim checked')
