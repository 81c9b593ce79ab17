"""``erva ecu-sim``: a simulated generator ECU with the quarter car behind it, on a CAN bus."""

import math
import signal
import sys

from erva_ros.commands._common import (add_json_option, add_params_option, live_type,
                                       positive_float, print_json, realtime_priority)
from erva_ros.core import topics
from erva_ros.core.errors import CLIError
from erva_ros.core.settings.loop import MODEL_KINDS

COMMAND = 'ecu-sim'
HELP = 'simulated generator ECU on a CAN bus: applies damping frames to the plant, sends sensors'
DESCRIPTION = """\
Plays the vehicle side of the HIL loop (erva_ros/core/hil/ecu_sim.py) with a real ECU's
timing: at every sample instant it samples the sensors and sends the chassis,
generator and status frames of config/erva_ecu.dbc at once; the quarter car
(erva_ros.core.model.plant.PlantSimulator) is integrated ahead, with the ERVA_CMD frames
(E2E-checked, duty clamped to the hardware range) applied at their cycle's instant
t_k + d (the loop's command delay d, --command-delay; a frame received after it is
late: counted, never applied), or with d = 0 latched within latch_s of their arrival;
the passive c_e0 at once on a safe frame and after command_timeout_periods without a
valid command (the bridge's rule).

Bus (--bus): socketcan:IFACE, udp:LOCAL_PORT:PEER_PORT (loopback only, the peer is
ecu_bridge_node with the ports swapped) or virtual:NAME (same process only, useless
here).  Example, with the bridge on udp:47001:47002:

  erva ecu-sim --bus udp:47002:47001 --road paper --duration 10

Roads: a road of erva_ros.core.road.profiles started with the ECU (paper, sine, bump, iso8608,
--seed), flat, ros (the heights of /erva/road/height as they arrive: each cycle
waits for its sample) or session (the road of the --params file, an `erva run`
session file, placed on the sample grid of /erva/road/height and known ahead, so
the ECU never waits for the road; every received height is checked against it).
With ros or session the ECU's cycles fall on the road's sample grid; --ros
publishes the ground truth (sprung_accel, generator, ecu_sim/state and
/diagnostics) like plant_sim_node; `erva run --ecu virtual` starts it with
--road session.  Stops after --duration, or on Ctrl-C / SIGTERM, and prints a
summary (with --json: counters, comfort, and the ECU's latencies)."""

ROADS = ('session', 'ros', 'flat', 'paper', 'sine', 'bump', 'iso8608')
GRID_ROADS = ('session', 'ros')
REJECTS = ('wrong_length', 'bad_crc', 'repeated', 'skipped', 'bad_counter')


def add_arguments(parser):
    parser.add_argument('--bus', required=True, metavar='SPEC',
                        help='CAN bus: socketcan:IFACE | udp:LOCAL_PORT:PEER_PORT | '
                             'virtual:NAME')
    add_params_option(parser)
    parser.add_argument('--hil-config', metavar='FILE', default=None,
                        help='HIL params file (default: the shipped config/hil.yaml); the '
                             'ecu_bridge_node section gives the hardware and timeout, the '
                             'ecu_sim section the sensor noise')
    parser.add_argument('--model', choices=MODEL_KINDS, default=MODEL_KINDS[0],
                        help='plant model (default erva, paper eq. (11))')
    parser.add_argument('--ts', type=positive_float, default=0.02, metavar='S',
                        help='ECU cycle Ts (s, default 0.02)')
    parser.add_argument('--road', choices=ROADS, default='paper',
                        help='road at the tyre: session (the --params session file\'s road on '
                             'the grid of /erva/road/height), ros (/erva/road/height as it '
                             'arrives), flat, or a road of core/road/profiles.py started with the '
                             'ECU (default paper)')
    parser.add_argument('--seed', type=live_type('seed'), default=0,
                        help='road seed (default 0)')
    parser.add_argument('--duration', type=float, default=0.0, metavar='S',
                        help='stop after S seconds (default 0: until Ctrl-C / SIGTERM)')
    parser.add_argument('--ros', action='store_true',
                        help='publish the ground truth and /diagnostics on ROS 2 '
                             '(implied by --road ros and --road session)')
    parser.add_argument('--namespace', default=topics.NAMESPACE, metavar='NS',
                        help=f'ROS namespace of the topics (default {topics.NAMESPACE})')
    parser.add_argument('--wait-road', type=positive_float, default=15.0, metavar='S',
                        help='with --road ros: wait at most S s for the first road height')
    parser.add_argument('--realtime-priority', type=realtime_priority,
                        default=0, metavar='P',
                        help='SCHED_FIFO priority of the ECU loop once it runs, 0 = normal '
                             'scheduling (default; needs CAP_SYS_NICE, else a warning)')
    parser.add_argument('--command-delay', type=live_type('command_delay_s'), default=None,
                        metavar='S',
                        help='command delay d: a command frame for cycle k acts at t_k + d '
                             '(s, < Ts; 0 = at its arrival; default: the --params session '
                             'file\'s command_delay_s, else config/live.yaml\'s)')
    parser.add_argument('--noise-free', action='store_true',
                        help='sensors without noise (the DBC quantisation remains)')
    add_json_option(parser)


def _road_function(args):
    """Return w(t) (m) at epoch time t for a road (core/road/profiles.py) started at first call."""
    from erva_ros.core.road.profiles import make_road, RoadError
    if args.road == 'flat':
        return lambda t: 0.0
    try:
        profile = make_road(args.road, max(args.duration, 1.0), ts=args.ts, seed=args.seed)
    except RoadError as exc:
        raise CLIError(str(exc)) from None
    start = []

    def road(t):
        if not start:
            start.append(t)
        return profile.height(t - start[0])
    return road


def _session_road(path, ts):
    """Return the :class:`KnownRoad` of a session params file (its road_preview_node section).

    The same ``build_road`` as road_preview_node, from the same values, so the heights
    agree to the bit (checked against every received sample).
    """
    from erva_ros.core.hil.road_buffer import KnownRoad
    from erva_ros.core.settings.schemas import LIVE
    from erva_ros.core.loop.scenario import build_road
    from erva_ros.core.model.params import ParamError, read_ros_params
    from erva_ros.core.settings.specs import check_all
    if path is None:
        raise CLIError('--road session needs --params FILE (the session params file of '
                       '`erva run`)')
    try:
        values = read_ros_params(path, 'road_preview_node', required=False)
        specs = LIVE.specs()
        cfg = check_all(specs, {k: v for k, v in values.items() if k in specs}, path,
                        LIVE.defaults())
        if abs(float(cfg['ts']) - ts) > 1e-12:
            raise CLIError(f'{path}: ts = {cfg["ts"]} s differs from --ts {ts:g} s')
        road = build_road(cfg)
    except ParamError as exc:
        raise CLIError(str(exc)) from None
    return KnownRoad(road.height, road.speed_mps, ts)


def _check_args(args) -> None:
    """Refuse bad options with one line (CLIError), before anything starts."""
    from erva_ros.core.hil.transport import parse_spec
    if not (math.isfinite(args.duration) and args.duration >= 0):
        raise CLIError(f'--duration must be >= 0, got {args.duration}')
    try:
        parse_spec(args.bus)
    except ValueError as exc:
        raise CLIError(str(exc)) from None


def _build_core(args, road, delay_s: float):
    """Return the EcuSimCore of the options (hardware and noise from the HIL file)."""
    from erva_ros.core.hil.codec import EcuCodec
    from erva_ros.core.hil.ecu_sim import EcuSimConfig, EcuSimCore, SensorNoise
    from erva_ros.core.hil.settings import hardware_of, load_bridge_section, load_ecu_sim_section
    from erva_ros.core.hil.transport import open_bus
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import load_erva_params

    from erva_ros.core.settings.schemas import SCHEMAS
    # --params may be an `erva run` session file: /** holds the nodes' shared parameters.
    params = load_erva_params(args.params,
                              others={k for s in SCHEMAS.values() for k in s.specs()})
    bridge = load_bridge_section(args.hil_config)
    sim = load_ecu_sim_section(args.hil_config)
    noise = SensorNoise.none() if args.noise_free else SensorNoise(
        sim['noise_sprung_accel'], sim['noise_deflection'], sim['noise_speed'],
        sim['noise_current'], sim['noise_voltage'], sim['seed'])
    try:
        cfg = EcuSimConfig(period_s=args.ts, latch_s=sim['latch_s'],
                           command_timeout_s=bridge['command_timeout_periods'] * args.ts,
                           c_e_safe=params.c_e0, max_delta_counter=bridge['max_delta_counter'],
                           command_delay_s=delay_s)
        return EcuSimCore(make_model(params, args.model), hardware_of(bridge),
                          EcuCodec(bridge['dbc_file'] or None), lambda: open_bus(args.bus), road,
                          cfg, noise)
    except (ValueError, FileNotFoundError) as exc:
        raise CLIError(str(exc)) from None


def _run(args, core, ros, stop) -> list:
    """Run the ECU loop until --duration or a stop; return its samples (cycle 0 first)."""
    from erva_ros.core.hil.codec import cycle_of
    from erva_ros.core.hil.ecu_sim import run_realtime
    samples = []
    on_cycle = samples.append if ros is None else (
        lambda s: (samples.append(s), ros.publish(core, s)))
    if ros is None:
        print(f'erva ecu-sim: {args.bus}, Ts = {args.ts:g} s, road {args.road}, '
              f'd = {core.cfg.command_delay_s:g} s', file=sys.stderr, flush=True)
    should_stop = lambda: bool(stop)        # noqa: E731
    if args.road in GRID_ROADS:             # cycles on the road's grid
        t0_ns = ros.start_time_ns(args.ts)
        run_realtime(core, args.duration, on_cycle, should_stop, wait=ros.spin_for,
                     t0=t0_ns * 1e-9, cycle0=cycle_of(t0_ns, core.ts_ns),
                     ahead=args.road == 'session', until_road=ros.wait_road_sample)
    else:
        run_realtime(core, args.duration, on_cycle, should_stop,
                     wait=None if ros is None else ros.spin_for)
    if ros is not None:
        ros.publish_final(core)
    core.close()
    return samples


def _realtime(args, ros) -> None:
    """Switch to SCHED_FIFO once set up (as the nodes do, erva_ros/ros/realtime.py).

    Before waiting for the road: the ECU's first sample goes out when the first road
    height arrives, which a busy machine would otherwise delay by milliseconds.
    """
    from erva_ros.ros.realtime import set_fifo_priority
    scheduling = set_fifo_priority(
        args.realtime_priority, lambda m: print(f'erva ecu-sim: warning: {m}',
                                                file=sys.stderr))
    if ros is not None:
        ros.scheduling = scheduling


def _summary(args, core, samples) -> dict:
    """Return the run's counters, comfort and power, and the ECU's latencies."""
    from erva_ros.core.metrics import comfort_power, percentiles_ms
    n = len(samples) - 1
    result = core.summary()
    result['bus'] = args.bus
    result['bus_error'] = core.bus_error
    if n > 0:
        result.update(comfort_power([s.sprung_accel for s in samples[1:]],
                                    samples[-1].harvested_j, n * args.ts))
    result['duration_s'] = n * args.ts
    result['mode_changes'] = core.mode_changes()
    t0 = core.t0 or 0.0
    lags = {'sample_to_can': percentiles_ms([s.sent_at - t0 - s.t for s in samples
                                             if s.sent_at is not None]),
            'sample_to_applied': percentiles_ms([s.command_latched - t0 - s.t + args.ts
                                                 for s in samples
                                                 if s.command_latched is not None]),
            # t_k -> its command frame received, and the actuation instant's lateness
            'sample_to_command': core.arrival.summary(),
            'actuation': core.actuation.summary()}
    # None, not NaN, where nothing was measured (no command came): valid JSON.
    result['latency_ms'] = {k: {key: (v if math.isfinite(v) else None)
                                for key, v in lag.items()}
                            for k, lag in lags.items()}
    result['command_delay_s'] = core.cfg.command_delay_s
    p999 = core.arrival.quantile(0.999)
    result['arrival_p999_ms'] = p999 * 1e3 if math.isfinite(p999) else None
    return result


def _print(args, result) -> None:
    n = int(round(result['duration_s'] / args.ts))
    rejects = ', '.join(f'{k} {result["rx_" + k]}' for k in REJECTS)
    print(f'ecu-sim: {n} cycles ({result["duration_s"]:.2f} s) on {args.bus}')
    print(f'  commands applied {result["commands_applied"]}, rejected: {rejects}; '
          f'duty out of range {result["duty_out_of_range"]}, timeouts '
          f'{result["command_timeouts"]}, overruns {result["overruns"]}')
    if result['command_delay_s'] > 0:
        act, arr = result['latency_ms']['actuation'], result['latency_ms']['sample_to_command']
        print(f'  commands act at t_k + d = {result["command_delay_s"] * 1e3:g} ms: late '
              f'{result["late_commands"]}; sample -> command p50 / p99 / max '
              f'{_ms(arr)}; actuation - (t_k + d) {_ms(act)}')
    if n > 0:
        print(f'  chassis acceleration RMS {result["acc_rms"]:.4g} m/s^2, harvested power '
              f'{result["power_w"]:.4g} W')
    if result['bus_error']:
        print(f'  bus: {result["bus_error"]}')


def _ms(stats) -> str:
    if not stats.get('samples'):
        return 'n/a'
    return f'{stats["p50"]:.3f} / {stats["p99"]:.3f} / {stats["max"]:.3f} ms'


def _session_value(path, key: str):
    """Return live parameter ``key`` of the session's params file, else its default."""
    from erva_ros.core.settings.schemas import LIVE
    from erva_ros.core.model.params import ParamError, read_ros_params
    value = LIVE.defaults()[key]
    if path:
        try:
            value = read_ros_params(path, 'ecu_sim').get(key, value)
            value = LIVE.specs()[key].check(key, value, path)
        except ParamError as exc:
            raise CLIError(str(exc)) from None
    return value


def main(args) -> int:
    from erva_ros.core.hil.settings import hardware_of, load_bridge_section

    _check_args(args)
    # One d for the loop: the session's (erva run), unless given here.
    delay = (args.command_delay if args.command_delay is not None
             else _session_value(args.params, 'command_delay_s'))
    if not delay < args.ts:
        raise CLIError(f'command delay d = {delay:g} s must be below Ts = {args.ts:g} s')
    use_ros = args.ros or args.road in GRID_ROADS
    known = _session_road(args.params, args.ts) if args.road == 'session' else None
    stop = []
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in handlers:
        signal.signal(s, lambda signum, frame: stop.append(signum))
    ros = None
    try:
        if use_ros:
            from erva_ros.ros.ecu_sim_ros import EcuSimRos
            ros = EcuSimRos(args.namespace, hardware_of(load_bridge_section(args.hil_config)),
                            known_road=known, ts=args.ts,
                            publisher_history_s=_session_value(args.params,
                                                               'publisher_history_s'),
                            session_id=_session_value(args.params, 'session_id'))
        core = _build_core(args, _road_function(args) if ros is None or args.road not in
                           GRID_ROADS else ros.road_height, delay)
        _realtime(args, ros)
        # Built before the wait (the plant's CasADi set-up takes longer than a period), so
        # the ECU starts on the road's first sample; the bus opens after it (no backlog).
        if args.road in GRID_ROADS and not ros.wait_for_road(args.wait_road, lambda: bool(stop)):
            if stop:
                return 130
            raise CLIError(f'no road height on {args.namespace}/road/height within '
                           f'{args.wait_road:g} s (is road_preview_node running?)')
        if not core.open():                 # later losses are retried; a wrong bus is not
            raise CLIError(f'{args.bus}: {core.bus_error}')
        samples = _run(args, core, ros, stop)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        if ros is not None:
            ros.shutdown()
    result = _summary(args, core, samples)
    if args.json:
        print_json(result)
    else:
        _print(args, result)
    return 0
