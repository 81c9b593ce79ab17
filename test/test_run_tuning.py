"""`erva run --set` in lock-step: the live nodes change parameters as `erva sim --set` does.

Three changes through nmpc_node's real SetParameters service at 0.4, 0.6 and 0.8 s (a
weight, the damping box, the preview switch): the commands equal the offline closed loop
with the same changes before the same samples (states to 1e-12, commands to 1e-9, as the
lock-step test without changes); the summary shows the segments from those samples; the
bag holds the /parameter_events, read back by the mcap and rosbags readers, and
`erva report` finds the same segments in it.
"""

import json
import os

import numpy as np
import pytest

from erva_ros.cli import build_parser
from erva_ros.commands._closed_loop_options import (load_settings, make_road_from_args,
                                                    preview_model_from_args)
from erva_ros.commands.run import run_config
from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.controllers import make_controller
from erva_ros.core.controllers.tuning import parse_change, ScheduledTuning
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import load_erva_params
from erva_ros.session.run.orchestrator import run_session

from test_run_lockstep import _settings_file

pytestmark = pytest.mark.ros   # every test here starts DDS

SCENARIO = ['--controller', 'preview', '--seed', '4', '--duration', '1', '--preview-snr', '15']
SIM = ['sim', *SCENARIO, '--alpha', '1,0.01']
RUN = ['run', *SCENARIO, '--alpha1', '1', '--alpha2', '0.01', '--mode', 'lockstep',
       '--command-delay', '0']
CHANGES = ['0.4:alpha1=0.5', '0.6:u_max=15000', '0.8:use_preview=false']
SET = [a for c in CHANGES for a in ('--set', c)]


def _offline(args):
    params = load_erva_params(args.params)
    settings = load_settings(args, alpha1=args.alpha[0], alpha2=args.alpha[1])
    ctrl = make_controller(settings.controller, make_model(params), settings)
    tuner = ScheduledTuning(ctrl, settings, params.c_e0, [parse_change(c) for c in args.set])
    road = make_road_from_args(args, args.duration, args.seed)
    return simulate_closed_loop(make_model(params), ctrl, road,
                                args.duration, settings.ts,
                                preview_model=preview_model_from_args(args, args.seed,
                                                                      settings.ts),
                                before_sample=tuner.before_sample)


@pytest.fixture(scope='module')
def tuned(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('tuned')
    parser = build_parser()
    settings = _settings_file(tmp)
    cfg = run_config(parser.parse_args(RUN + SET + ['--nmpc', settings]),
                     record_dir=str(tmp / 'bags'))
    cfg.session_dir = str(tmp / 'session')
    live = run_session(cfg)
    off = _offline(parser.parse_args(SIM + SET + ['--settings', settings]))
    return live, off, settings


@pytest.mark.slow
def test_lockstep_changes_act_from_their_sample_as_in_erva_sim(tuned):
    live, off, _ = tuned
    assert live.exit_code == 0, live.summary['errors']
    tr = live.trajectory
    assert tr['x'].shape == off.x.shape == (50, 6)
    np.testing.assert_allclose(tr['x'], off.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr['u'], off.u, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(tr['sprung_accel'], off.sprung_accel, rtol=0, atol=1e-9)
    plant = live.summary['plant']
    assert plant['u_from_command'] == 50 and plant['lockstep_timeouts'] == 0
    # Each change was accepted, and acted from its sample: the segments start there.
    tuning = live.summary['tuning']
    assert [r['accepted'] for r in tuning['set']] == [True, True, True]
    segs = tuning['segments']
    assert [(s['from_s'], s['samples']) for s in segs] == [(0.0, 20), (0.4, 10), (0.6, 10),
                                                           (0.8, 10)]
    assert [s['changed'] for s in segs] == [{}, {'alpha1': [1.0, 0.5]},
                                            {'u_max': [20000.0, 15000.0]},
                                            {'use_preview': [True, False]}]
    assert segs[3]['values']['alpha1'] == 0.5 and segs[3]['values']['u_max'] == 15000.0
    assert np.all(tr['u'][30:] <= 15000.0 + 1e-9)      # the box acts from 0.6 s on
    assert segs[0]['acc_rms'] == pytest.approx(np.sqrt(np.mean(off.sprung_accel[:20] ** 2)),
                                               rel=1e-9)
    # No hold timed out: each request came while its sample waited.
    assert tuning['hold_timeouts'] == 0


@pytest.mark.slow
def test_the_bag_holds_the_parameter_events_and_report_finds_the_segments(tuned, erva):
    live, _, _ = tuned
    bag = live.summary['bag']
    # mcap + mcap-ros2-support (not our reader)
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    seen = []
    for name in sorted(f for f in os.listdir(bag) if f.endswith('.mcap')):
        with open(os.path.join(bag, name), 'rb') as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, channel, _, msg in reader.iter_decoded_messages(
                    topics=['/parameter_events']):
                if msg.node == '/erva/nmpc_node' and msg.changed_parameters:
                    seen.append((msg.stamp.sec * 10**9 + msg.stamp.nanosec,
                                 {p.name for p in msg.changed_parameters}))
    stamps = [s for s, _ in seen if s > 0]        # (declarations at start-up: stamp 0)
    changed = [names for s, names in seen if s > 0]
    assert changed == [{'alpha1', 'lockstep_hold_s'}, {'u_max', 'lockstep_hold_s'},
                       {'use_preview', 'lockstep_hold_s'}]
    # accepted while the sample at T waited (node clock: that sample's, or the one before)
    assert all(t - 20_000_000 <= s <= t for s, t in zip(stamps, (4 * 10**8, 6 * 10**8,
                                                                 8 * 10**8)))
    # rosbags (through metadata.yaml)
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    values = []
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == '/parameter_events']
        assert conns and conns[0].msgtype == 'rcl_interfaces/msg/ParameterEvent'
        for conn, _, raw in reader.messages(connections=conns):
            msg = store.deserialize_cdr(raw, conn.msgtype)
            if msg.node == '/erva/nmpc_node':
                values += [(p.name, p.value.double_value, p.value.bool_value)
                           for p in msg.changed_parameters if p.name != 'lockstep_hold_s'
                           and (msg.stamp.sec or msg.stamp.nanosec)]
    assert values == [('alpha1', 0.5, False), ('u_max', 15000.0, False),
                      ('use_preview', 0.0, False)]
    # erva report: the same segments, from the bag alone
    rep = json.loads(erva('report', bag, '--json', check=True).stdout)
    run_segs, bag_segs = live.summary['tuning']['segments'], rep['tuning']['segments']
    assert [(s['from_s'], s['to_s'], s['samples'], s['changed']) for s in bag_segs] == \
        [(s['from_s'], s['to_s'], s['samples'], s['changed']) for s in run_segs]
    for a, b in zip(bag_segs, run_segs):
        assert a['acc_rms'] == pytest.approx(b['acc_rms'], rel=1e-12)
        assert a['power_mean_w'] == pytest.approx(b['power_mean_w'], rel=1e-12)
    assert [e['changed'].get('alpha1') for e in rep['tuning']['parameter_events']] == \
        [0.5, None, None]
    text = erva('report', bag, check=True).stdout
    assert '4 parameter sets' in text and 'alpha1 1 -> 0.5' in text


def test_bad_set_options_are_one_line_before_anything_starts(erva, tmp_path):
    for option, says in (('1:horizon=3', "'horizon' is read-only"),
                         ('1:alpha1=-1', "'alpha1' = -1.0 is out of range"),
                         ('1:u_min=12000', 'c_e0 = 10000 Ns/m'),
                         ('9:alpha1=0.5', 'the scenario ends at 4 s'),
                         ('1:lockstep_hold_s=2', "lockstep_hold_s is the session's own")):
        proc = erva('run', '--set', option, '--record', tmp_path / 'bags')
        assert proc.returncode == 2, (option, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and says in lines[0], (option, proc.stderr)
    assert not (tmp_path / 'bags').exists() or not os.listdir(tmp_path / 'bags')


@pytest.mark.slow
def test_a_realtime_set_goes_through_the_service_and_the_summary_says_from_when(erva):
    proc = erva('run', '--duration', '2', '--no-record', '--set', '1.0:alpha2=0.5', '--json')
    assert proc.returncode == 0, proc.stderr
    tuning = json.loads(proc.stdout)['tuning']
    assert tuning['set'] == [{'t_s': 1.0, 'changes': {'alpha2': 0.5}, 'accepted': True,
                              'reason': ''}]
    first, second = tuning['segments']
    assert second['changed'] == {'alpha2': [0.0, 0.5]}
    # Sent Ts/2 before the sample at 1 s: it acts from there, or (a loaded machine) from
    # a sample later, or earlier if the sample before was solved after it came; the
    # summary says which.  The two segments cover the run.
    assert 0.98 <= second['from_s'] == first['to_s'] < 2.0
    assert first['samples'] + second['samples'] == 100
