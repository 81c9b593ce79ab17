"""The HIL parameter tables and their loader (erva_ros/core/hil/settings.py), without ROS."""

import pytest

from erva_ros.core.model.estimator import EstimatorNoise
from erva_ros.core.settings.hil import NOISE_SPECS
from erva_ros.core.hil import settings as hs
from erva_ros.core.model.hardware import GeneratorHardware
from erva_ros.core.settings.hil import HARDWARE_SPECS
from erva_ros.core.model.params import ParamError
from erva_ros.core.settings.specs import Integer, Text

TABLES = {
    'bridge': (hs.BRIDGE_SPECS, hs.BRIDGE_DEFAULTS, hs.load_bridge_section),
    'estimator': (hs.ESTIMATOR_SPECS, hs.ESTIMATOR_DEFAULTS, hs.load_estimator_section),
    'ecu_sim': (hs.ECU_SIM_SPECS, hs.ECU_SIM_DEFAULTS, hs.load_ecu_sim_section),
}


def _one_line(exc_info) -> str:
    text = str(exc_info.value)
    assert '\n' not in text and text, text
    return text


def _write(tmp_path, text, name='hil.yaml'):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize('table', TABLES)
def test_every_default_is_valid_and_has_a_spec(table):
    specs, defaults, _ = TABLES[table]
    assert set(specs) == set(defaults)
    for key, default in defaults.items():
        assert specs[key].check(key, default) == default, key
        assert specs[key].doc, key
        # An integer's default is an int, a string's a str.
        if isinstance(specs[key], Integer):
            assert type(default) is int, key
        if isinstance(specs[key], Text):
            assert isinstance(default, str), key


def test_the_bridge_table_carries_the_hardware_and_the_estimator_the_noise():
    assert set(HARDWARE_SPECS) <= set(hs.BRIDGE_SPECS)
    assert set(NOISE_SPECS) <= set(hs.ESTIMATOR_SPECS)
    assert hs.hardware_of(hs.BRIDGE_DEFAULTS) == GeneratorHardware()
    assert hs.noise_of(hs.ESTIMATOR_DEFAULTS) == EstimatorNoise()


@pytest.mark.parametrize('table', TABLES)
def test_the_shipped_file_loads_within_the_tables(table):
    specs, defaults, load = TABLES[table]
    values = load()                         # config/hil.yaml
    assert set(values) == set(defaults)
    for key, v in values.items():
        assert specs[key].check(key, v) == v
    assert values == load(hs.default_hil_file())


def test_integer_keys_take_whole_numbers_only():
    spec = hs.BRIDGE_SPECS['command_timeout_periods']
    assert spec.check('command_timeout_periods', 4) == 4
    got = spec.check('command_timeout_periods', 4.0)    # YAML 4.0
    assert got == 4 and type(got) is int
    for bad in (3.5, True, '3', None):
        with pytest.raises(ParamError) as exc:
            spec.check('command_timeout_periods', bad, 'x.yaml')
        text = _one_line(exc)
        assert text.startswith("x.yaml: parameter 'command_timeout_periods' must be an "
                               'integer in [1, 1000] periods'), text
    with pytest.raises(ParamError) as exc:
        spec.check('command_timeout_periods', 0)
    assert "'command_timeout_periods' = 0 is out of range" in _one_line(exc)


def test_numbers_are_checked_against_their_range():
    spec = hs.BRIDGE_SPECS['bus_retry_s']
    assert spec.check('bus_retry_s', 1) == 1.0
    for bad in (0.0, 61.0, float('nan'), float('inf')):
        with pytest.raises(ParamError) as exc:
            spec.check('bus_retry_s', bad)
        assert 'out of range; allowed [0.01, 60] s' in _one_line(exc)
    with pytest.raises(ParamError) as exc:
        spec.check('bus_retry_s', 'fast')
    assert "must be a number in [0.01, 60] s, got str 'fast'" in _one_line(exc)


@pytest.mark.parametrize('name', ['ecu_bridge_node', '/ecu_bridge_node', '**/ecu_bridge_node',
                                  '/**/ecu_bridge_node'])
def test_a_section_is_found_as_rcl_finds_it_for_a_node_in_any_namespace(tmp_path, name):
    path = _write(tmp_path, f'"{name}":\n  ros__parameters:\n    bus_retry_s: 2.0\n'
                            '    command_timeout_periods: 5\n')
    values = hs.load_bridge_section(path)
    assert (values['bus_retry_s'], values['command_timeout_periods']) == (2.0, 5)
    assert values['max_delta_counter'] == hs.BRIDGE_DEFAULTS['max_delta_counter']


def test_sections_merge_and_other_nodes_and_the_wildcard_are_not_read(tmp_path):
    path = _write(tmp_path, (
        '/**:\n  ros__parameters:\n    bus_retry_s: 9.0\n    ts: 0.01\n'
        'ecu_bridge_node:\n  ros__parameters:\n    bus_retry_s: 2.0\n    duty_max: 0.9\n'
        '/**/ecu_bridge_node:\n  ros__parameters:\n    bus_retry_s: 3.0\n'
        '/**/ecu_sim:\n  ros__parameters:\n    seed: 7\n'))
    bridge = hs.load_bridge_section(path)
    assert (bridge['bus_retry_s'], bridge['duty_max']) == (3.0, 0.9)
    assert hs.load_ecu_sim_section(path)['seed'] == 7
    assert hs.load_estimator_section(path) == hs.ESTIMATOR_DEFAULTS


@pytest.mark.parametrize('text, message', [
    ('/**/ecu_bridge_node:\n  ros__parameters:\n    duty_max: 1.5\n',
     "hil.yaml: parameter 'duty_max' = 1.5 is out of range"),
    ('/**/ecu_bridge_node:\n  ros__parameters:\n    dbc_file: 3\n',
     "hil.yaml: parameter 'dbc_file' must be a string"),
    ('/**/ecu_bridge_node:\n  ros__parameters:\n    max_delta_counter: 1.5\n',
     "hil.yaml: parameter 'max_delta_counter' must be an integer"),
    ('/**/ecu_bridge_node:\n  bus_retry_s: 2.0\n',
     "section '/**/ecu_bridge_node' must contain a ros__parameters mapping"),
    ('/**/ecu_bridge_node:\n  ros__parameters: [1, 2]\n',
     "section '/**/ecu_bridge_node' must contain a ros__parameters mapping"),
    ('- a\n- b\n', 'expected a mapping of node names to ros__parameters'),
    ('/**/ecu_bridge_node: {ros__parameters: {bus_retry_s: 2.0}\n', 'not valid YAML'),
    ('/**/ecu_bridge_node:\n  ros__parameters:\n    r_internal_ohm: 0.0\n'
     '    r_switch_ohm: 0.0\n', 'r_internal_ohm + r_switch_ohm'),
    # A typo was ignored (the value kept its default); now it is named, with the key meant.
    ('/**/ecu_bridge_node:\n  ros__parameters:\n    dutty_max: 0.9\n',
     "hil.yaml: unknown parameter(s) dutty_max; did you mean 'duty_max'?"),
])
def test_bad_files_give_one_line_naming_the_file(tmp_path, text, message):
    path = _write(tmp_path, text)
    with pytest.raises(ParamError) as exc:
        values = hs.load_bridge_section(path)
        hs.hardware_of(values, path)
    text = _one_line(exc)
    assert message in text and path in text, text


def test_a_missing_file_is_one_line(tmp_path):
    missing = str(tmp_path / 'nope.yaml')
    for load in (hs.load_bridge_section, hs.load_estimator_section, hs.load_ecu_sim_section):
        with pytest.raises(ParamError) as exc:
            load(missing)
        assert _one_line(exc) == f'parameter file {missing!r} does not exist'


def test_noise_errors_name_the_file(tmp_path):
    path = _write(tmp_path, '/**/state_estimator_node:\n  ros__parameters:\n'
                            '    r_speed: 0.0\n')
    with pytest.raises(ParamError) as exc:
        hs.noise_of(hs.load_estimator_section(path), path)
    assert "'r_speed' = 0.0 is out of range" in _one_line(exc)


def test_keys_the_hil_nodes_also_declare_are_not_typos(tmp_path):
    # The nodes declare the physical parameters and some live ones too (a node's own
    # section may set them), and ROS reads use_sim_time.
    path = _write(tmp_path, '/**/state_estimator_node:\n  ros__parameters:\n'
                            '    ts: 0.01\n    realtime_priority: 0\n    c_e0: 9000.0\n'
                            '    use_sim_time: false\n    u_max: 30000.0\n'
                            '/**/ecu_sim:\n  ros__parameters:\n    latch: 0.002\n')
    assert hs.load_estimator_section(path)['u_max'] == 30000.0
    with pytest.raises(ParamError) as exc:
        hs.load_ecu_sim_section(path)
    assert _one_line(exc).endswith("unknown parameter(s) latch; did you mean 'latch_s'?")


def test_erva_ecu_sim_with_a_typo_in_its_file_is_one_line_and_exit_2(tmp_path, erva):
    path = _write(tmp_path, '/**/ecu_sim:\n  ros__parameters:\n    noise_sprung_acc: 0.1\n')
    proc = erva('ecu-sim', '--hil-config', path, '--bus', 'virtual:x', '--duration', '0.1')
    assert proc.returncode == 2 and proc.stdout == ''
    assert proc.stderr.splitlines() == [
        f"erva ecu-sim: error: {path}: unknown parameter(s) noise_sprung_acc; did you mean "
        f"'noise_sprung_accel'?"], proc.stderr
