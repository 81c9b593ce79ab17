"""The typed spec family (core/settings/specs.py), defaults only in config/, model outputs."""

import argparse
import ast
import os

import numpy as np
import pytest
import rclpy
import yaml

from erva_ros.core.settings.files import shipped_defaults
from erva_ros.core.controllers.settings import ControllerSettings
from erva_ros.core.hil import settings as hs
from erva_ros.core.hil.ecu_sim import SensorNoise
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import ERVAParams, ParamError, Spec
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.settings import schemas as np_
from erva_ros.core.settings.specs import check_all, Choice, Flag, Integer, Number, Text
from erva_ros.ros.parameters import declare_node_parameters, descriptor

from conftest import REPO


def _one_line(info) -> str:
    text = str(info.value)
    assert text and '\n' not in text
    return text


def test_number_checks_range_type_and_openness():
    spec = Number(0.0, 10.0, 'm/rad', 'arm', lo_open=True)
    assert Spec is Number
    assert spec.describe() == '(0, 10] m/rad'
    assert spec.check('l', 3) == 3.0 and type(spec.check('l', 3)) is float
    for bad, needle in ((0.0, "'l' = 0.0 is out of range; allowed (0, 10] m/rad (arm)"),
                        (10.5, "'l' = 10.5 is out of range"),
                        (float('nan'), "'l' = nan is out of range"),
                        (float('inf'), "'l' = inf is out of range"),
                        (True, "'l' must be a number in (0, 10] m/rad, got bool True"),
                        ('3', "'l' must be a number in (0, 10] m/rad, got str '3'")):
        with pytest.raises(ParamError) as info:
            spec.check('l', bad, 'f.yaml')
        text = _one_line(info)
        assert text.startswith('f.yaml: parameter ') and needle in text, text
    assert Number(0.0, 1.0, '-', 'x').describe() == '[0, 1]'     # dimensionless


def test_integer_takes_whole_numbers_and_returns_int():
    spec = Integer(1, 200, 'steps', 'horizon')
    got = spec.check('horizon', 10.0)                # YAML 10.0
    assert got == 10 and type(got) is int
    for bad in (10.5, True, '10', None):
        with pytest.raises(ParamError) as info:
            spec.check('horizon', bad)
        assert "'horizon' must be an integer in [1, 200] steps" in _one_line(info)
    with pytest.raises(ParamError) as info:
        spec.check('horizon', 0)
    assert "'horizon' = 0 is out of range; allowed [1, 200] steps" in _one_line(info)


def test_choice_flag_text():
    choice = Choice(('a', 'b'), 'letters')
    assert choice.check('k', 'b') == 'b'
    for bad in ('c', 1, None):
        with pytest.raises(ParamError) as info:
            choice.check('k', bad)
        assert f"'k' = {bad!r} is not allowed; choose one of a, b (letters)" in _one_line(info)
    assert Flag('f').check('f', False) is False
    with pytest.raises(ParamError, match="'f' must be true or false"):
        Flag('f').check('f', 'false')
    assert Text('t').check('t', '') == ''
    with pytest.raises(ParamError, match="'t' must be a string"):
        Text('t').check('t', 3)


def test_argparse_uses_the_same_check():
    p = argparse.ArgumentParser()
    p.add_argument('--n', **Integer(1, 5, 'steps', 'n').argparse())
    p.add_argument('--x', **Number(0.0, 1.0, 's', 'x').argparse('a time'))
    p.add_argument('--c', **Choice(('a', 'b'), 'c').argparse())
    args = p.parse_args(['--n', '3', '--x', '0.5', '--c', 'a'])
    assert (args.n, args.x, args.c) == (3, 0.5, 'a') and type(args.n) is int
    for argv in (['--n', '0'], ['--n', '2.5'], ['--x', 'nan'], ['--x', '2'], ['--c', 'z']):
        with pytest.raises(SystemExit) as info:
            p.parse_args(argv)
        assert info.value.code == 2, argv
    assert 'a time; [0, 1] s' in p.format_help()


def test_check_all_fills_defaults_and_refuses_unknown_keys():
    specs = {'a': Integer(0, 9, '-', 'a'), 'b': Flag('b')}
    assert check_all(specs, {'a': 2.0}, '', {'a': 1, 'b': True}) == {'a': 2, 'b': True}
    with pytest.raises(ParamError, match=r"src: unknown parameter\(s\) z; known: a, b"):
        check_all(specs, {'z': 1}, 'src')


def test_an_unknown_key_names_the_closest_known_one():
    from erva_ros.core.settings.specs import closest_key, unknown_parameters
    known = ['speed_mps', 'seed', 'road', 'M_s', 'M_us', 'horizon']
    assert closest_key('speeed_mps', known) == 'speed_mps'
    assert closest_key('m_s', known) == 'M_s'                   # another case
    assert closest_key('zzz', known) is None
    assert str(unknown_parameters(['speeed_mps'], known, 'live.yaml', 'live parameter(s)')) == (
        "live.yaml: unknown live parameter(s) speeed_mps; did you mean 'speed_mps'?")
    assert str(unknown_parameters(['horizn', 'rood'], known)) == (
        "unknown parameter(s) horizn, rood; did you mean 'horizon' for 'horizn', 'road' for "
        "'rood'?")


# -- defaults only in config/ ----------------------------------------------------------------

def _yaml(name):
    with open(os.path.join(REPO, 'config', name), encoding='utf-8') as fh:
        return yaml.safe_load(fh)


#: (spec table, config file, section) of every table a node declares from.
TABLES = {
    'live': (np_.LIVE.specs(), 'live.yaml', '/**'),
    'physical': (ERVA_SPECS, 'erva_paper.yaml', '/**'),
    'controller': (np_.CONTROLLER.specs(), 'nmpc.yaml', '/**/nmpc_node'),
    'bridge': (hs.BRIDGE_SPECS, 'hil.yaml', '/**/ecu_bridge_node'),
    'estimator': (hs.ESTIMATOR_SPECS, 'hil.yaml', '/**/state_estimator_node'),
    'ecu_sim': (hs.ECU_SIM_SPECS, 'hil.yaml', '/**/ecu_sim'),
    'recorder': (np_.RECORDER_SPECS, 'session.yaml', '/**/recorder'),
    'foxglove': (np_.FOXGLOVE_SPECS, 'session.yaml', '/**/foxglove_server'),
}


@pytest.mark.parametrize('table', TABLES)
def test_every_parameter_has_its_default_in_config_and_it_is_valid(table):
    specs, name, section = TABLES[table]
    values = _yaml(name)[section]['ros__parameters']
    # The command-line-only keys (rcl lets a node section win over -p) are the exception.
    assert set(specs) - set(hs.COMMAND_LINE_DEFAULTS) == set(values), table
    for key, value in values.items():
        assert specs[key].check(key, value) == value, (table, key)


def test_ts_is_set_in_one_config_file_only():
    files = [f for f in os.listdir(os.path.join(REPO, 'config')) if f.endswith('.yaml')]
    with_ts = [f for f in files if any('ts' in sec.get('ros__parameters', {})
                                       for sec in _yaml(f).values())]
    assert with_ts == ['live.yaml']
    assert ControllerSettings().ts == _yaml('live.yaml')['/**']['ros__parameters']['ts']


def test_each_table_and_its_shipped_section_name_the_same_keys():
    # Group.defaults() keeps the file's keys that have a spec: a key in the file without a
    # spec would be dropped silently, and a spec without a key in the file has no default.
    # (bus and can_log are command-line parameters, hil/settings.py; no file holds them.)
    for group in np_._GROUP_SPECS:
        if group is np_.COMMAND_LINE:
            continue
        in_file = set(shipped_defaults(group.config, group.section))
        in_table = set(group.specs()) - set(hs.COMMAND_LINE_DEFAULTS)
        assert in_file == in_table, (group, sorted(in_file ^ in_table))


def test_a_section_out_of_its_table_is_refused(tmp_path):
    # What Group.defaults() and hil/settings.py do with each value: the table's check.
    bad = dict(hs.ECU_SIM_DEFAULTS, noise_speed=-1.0)
    with pytest.raises(ParamError, match="noise_speed"):
        check_all(hs.ECU_SIM_SPECS, bad, 'config/hil.yaml')
    bridge = dict(hs.BRIDGE_DEFAULTS)
    assert bridge.pop('bus') == hs.COMMAND_LINE_DEFAULTS['bus']
    assert bridge.pop('can_log') == hs.COMMAND_LINE_DEFAULTS['can_log']
    assert shipped_defaults('live.yaml') is not shipped_defaults('live.yaml')   # copies


def test_the_dataclass_defaults_equal_the_shipped_files():
    # The offline tools' dataclasses keep literal defaults; they must say what config/ says.
    nmpc = _yaml('nmpc.yaml')['/**/nmpc_node']['ros__parameters']
    # ts and command_delay_s are the loop's (config/live.yaml); offline d is 0, the paper's.
    offline = ControllerSettings().as_dict()
    assert offline.pop('command_delay_s') == 0.0
    assert {k: v for k, v in offline.items() if k != 'ts'} == nmpc
    assert ERVAParams().as_dict() == _yaml('erva_paper.yaml')['/**']['ros__parameters']
    sim = _yaml('hil.yaml')['/**/ecu_sim']['ros__parameters']
    assert SensorNoise() == SensorNoise(sim['noise_sprung_accel'], sim['noise_deflection'],
                                        sim['noise_speed'], sim['noise_current'],
                                        sim['noise_voltage'], sim['seed'])


def _module_files():
    for top in ('erva_ros', 'launch'):
        for dirpath, _, files in os.walk(os.path.join(REPO, top)):
            for f in files:
                if f.endswith('.py'):
                    yield os.path.join(dirpath, f)


def test_no_default_table_or_declared_default_is_written_in_code():
    offenders = []
    for path in _module_files():
        tree = ast.parse(open(path, encoding='utf-8').read(), path)
        for node in ast.walk(tree):
            # A *DEFAULTS* table given as a literal dict of constants.
            if isinstance(node, (ast.Assign, ast.AnnAssign)) and isinstance(node.value,
                                                                            ast.Dict):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                names = [t.id for t in targets if isinstance(t, ast.Name)]
                literal = any(isinstance(v, ast.Constant) for v in node.value.values)
                if literal and any('DEFAULTS' in n and n != 'COMMAND_LINE_DEFAULTS'
                                   for n in names):
                    offenders.append(f'{path}:{node.lineno} {names}')
            # declare*(node, name, <a literal default>, ...) of ros/parameters.py.
            name = getattr(node, 'func', None) if isinstance(node, ast.Call) else None
            if (isinstance(name, ast.Name) and name.id.startswith('declare')
                    and any(isinstance(a, ast.Constant) for a in node.args[2:])):
                offenders.append(f'{path}:{node.lineno} {name.id}(...) with a literal')
    assert not offenders, offenders


@pytest.fixture
def ros_context():
    ctx = rclpy.Context()
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.mark.ros
def test_nodes_declare_the_config_defaults_with_their_descriptors(ros_context):
    from rclpy.node import Node
    rclpy.init(args=['x'], context=ros_context)
    node = Node('specs_test_node', context=ros_context)
    try:
        values = declare_node_parameters(node, 'nmpc_node')
        assert {k: values[k] for k in ERVA_SPECS} == ERVAParams().as_dict()
        nmpc = _yaml('nmpc.yaml')['/**/nmpc_node']['ros__parameters']
        assert {k: values[k] for k in nmpc} == nmpc
        live = np_.LIVE.defaults()
        assert all(values[k] == live[k] for k in values if k in live)
        desc = node.describe_parameter('horizon')
        assert desc.read_only and desc.additional_constraints == '[1, 200] steps'
        assert (desc.integer_range[0].from_value, desc.integer_range[0].to_value) == (1, 200)
        desc = node.describe_parameter('l')
        assert desc.floating_point_range[0].to_value == 10.0
        assert node.describe_parameter('mode').additional_constraints == \
            'one of realtime, lockstep'
        # live (dynamic) parameters are not read-only; the others say why they are
        live_names = set(np_.SCHEMAS['nmpc_node'].live())
        assert {'alpha1', 'alpha2', 'u_min', 'u_max', 'use_preview', 'fallback',
                'time_budget_s', 'state_timeout_periods'} <= live_names
        for name in values:
            d = node.describe_parameter(name)
            assert d.read_only == (name not in live_names), name
            assert ('read-only while the node runs: ' in d.description) == d.read_only, name
        assert 'needs a new solver' in node.describe_parameter('horizon').description
        assert 'sample grid' in node.describe_parameter('ts').description
    finally:
        node.destroy_node()
    assert descriptor('x', Text('free')).description == \
        f'free; read-only while the node runs: {np_.READ_AT_START}'


@pytest.mark.parametrize('node', sorted(np_.SCHEMAS))
@pytest.mark.ros
def test_each_node_declares_its_schema_with_the_shipped_defaults(ros_context, node):
    from rclpy.node import Node
    rclpy.init(args=['x'], context=ros_context)
    n = Node(node, context=ros_context)
    try:
        values = declare_node_parameters(n, node)
        schema = np_.SCHEMAS[node]
        assert values == schema.defaults()
        builtin = {'use_sim_time', 'start_type_description_service'}
        assert set(values) == set(n.list_parameters([], 0).names) - builtin
        for name, spec, _ in schema.items():
            assert n.describe_parameter(name) == descriptor(name, spec), (node, name)
    finally:
        n.destroy_node()


def test_launch_arguments_session_file_and_cli_come_from_the_schemas(tmp_path):
    spec_files = {name: np_.spec_of(name) for name in np_.LAUNCH_ARGUMENTS}
    import importlib.util
    spec = importlib.util.spec_from_file_location(
        'erva_launch', os.path.join(REPO, 'launch', 'erva.launch.py'))
    launch = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(launch)
    args = {name: (default, kind) for name, default, kind, _ in launch.ARGUMENTS}
    assert set(args) == {'namespace', *np_.LAUNCH_ARGUMENTS}
    defaults = {**np_.LIVE.defaults(), **np_.CONTROLLER.defaults()}
    for name, s in spec_files.items():
        assert args[name] == (str(defaults[name]), getattr(s, 'python_type', str)), name
    # The session file: each value where the nodes that declare it find it.
    doc = np_.session_sections({'seed': 3, 'ts': 0.01, 'alpha1': 2.0, 'M_s': 400.0,
                                'state_timeout_periods': 4})
    assert doc['/**']['ros__parameters'] == {'ts': 0.01, 'M_s': 400.0}
    assert doc['/**/road_preview_node']['ros__parameters'] == {'seed': 3}
    assert doc['/**/nmpc_node']['ros__parameters'] == {
        'alpha1': 2.0, 'state_timeout_periods': 4}
    # The CLI: erva run's options take their choices and checks from the same specs.
    from erva_ros.commands import run as run_cmd
    parser = argparse.ArgumentParser()
    run_cmd.add_arguments(parser)
    actions = {a.dest: a for a in parser._actions}
    assert tuple(actions['controller'].choices) == np_.spec_of('controller').options
    assert tuple(actions['road'].choices) == np_.spec_of('road').options
    assert tuple(actions['mode'].choices) == np_.MODES
    assert tuple(actions['model'].choices) == np_.spec_of('model').options
    with pytest.raises(SystemExit):
        parser.parse_args(['--seed', '-1'])


# -- the model owns its outputs ---------------------------------------------------------------

@pytest.mark.parametrize('kind', ['erva', 'benchmark'])
def test_deflection_and_measurements_come_from_the_model(kind):
    model = make_model(ERVAParams(), kind)
    rng = np.random.default_rng(3)
    x = rng.normal(scale=0.01, size=model.nx)
    u, w = 12000.0, 0.003
    assert float(model.deflection(x)) == x[0] - x[2]
    y = np.asarray(model.measurements(x, u, w)).ravel()
    assert y.shape == (3,)
    assert y[0] == float(model.sprung_accel(x, u, w))
    assert y[1] == x[0] - x[2]
    np.testing.assert_allclose(y[2], float(model.generator_velocity(x)) / ERVAParams().l,
                               rtol=1e-15)
    if kind == 'benchmark':             # the generator moves with the strut
        assert float(model.generator(x, u)[0]) == y[1]
