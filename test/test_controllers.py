"""Controller settings, the Controller interface, passive and skyhook, and the fallbacks."""

from dataclasses import fields
import os

import numpy as np
import pytest

from erva_ros.core.controllers import (CONTROLLER_NAMES, ControllerSettings,
                                       load_controller_settings, make_controller, STATUSES)
from erva_ros.core.controllers import settings as settings_mod
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params, ParamError

P = paper_params()
M = make_model(P)


def test_controller_names_and_status_values():
    assert CONTROLLER_NAMES == ('passive', 'skyhook', 'no_preview', 'preview', 'preview_long')
    assert STATUSES == ('ok', 'late', 'fallback_plan', 'fallback_passive')


def test_shipped_settings_file_loads_and_spec_tables_cover_every_field():
    s = load_controller_settings()
    assert s == ControllerSettings()       # the file states the defaults
    names = {f.name for f in fields(ControllerSettings)}
    assert names == set(settings_mod.SPECS)
    assert set(settings_mod.SPECS) == (set(settings_mod.NUMERIC_SPECS)
                                       | set(settings_mod.CHOICE_SPECS)
                                       | set(settings_mod.FLAG_SPECS))
    assert set(settings_mod.DEFAULTS) == names
    for key in names:
        assert settings_mod.describe(key)


def test_overrides_win_and_none_is_ignored():
    s = load_controller_settings(overrides={'horizon': 15, 'cost': 'continuous', 'u_max': None})
    assert (s.horizon, s.cost, s.u_max) == (15, 'continuous', 20000.0)


@pytest.mark.parametrize('values,match', [
    ({'horizon': 0}, "'horizon' = 0 is out of range; allowed \\[1, 200\\]"),
    ({'horizon': 2.5}, "'horizon' must be an integer"),
    ({'cost': 'quadratic'}, "'cost' = 'quadratic' is not allowed; choose one of paper"),
    ({'u_min': 30000.0}, "'u_max' = 20000 must exceed u_min = 30000"),
    ({'alpha1': 0.0, 'alpha2': 0.0}, 'both 0'),
    ({'horizn': 3}, r"x.yaml: unknown parameter\(s\) horizn; did you mean 'horizon'\?$"),
    ({'long_steps': 2, 'long_step_s': 0.05}, 'whole multiple of ts'),
    ({'ts': 'fast'}, "'ts' must be a number"),
])
def test_bad_settings_give_one_line_param_errors(values, match):
    with pytest.raises(ParamError, match=match) as err:
        settings_mod.validate_settings(values, source='x.yaml')
    assert '\n' not in str(err.value)


def test_settings_file_errors_name_the_file(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text('nmpc_node:\n  ros__parameters:\n    max_iter: 0\n')
    with pytest.raises(ParamError, match='bad.yaml: parameter .max_iter. = 0'):
        load_controller_settings(str(path))
    path.write_text('/**:\n  ros__parameters:\n    M_s: 250.0\n'
                    'nmpc_node:\n  ros__parameters:\n    horizon: 12\n')
    assert load_controller_settings(str(path)).horizon == 12   # shared file is fine
    assert os.path.basename(settings_mod.default_settings_file()) == 'nmpc.yaml'


@pytest.mark.parametrize('name', CONTROLLER_NAMES)
def test_make_controller_interface(name):
    c = make_controller(name, M, ControllerSettings())
    assert c.name == name
    assert (c.ts, c.u_min, c.u_max) == (0.02, 0.0, 20000.0)
    res = c.compute(np.zeros(6), np.zeros(c.horizon + 1), 0.0)
    assert res.plan.shape == (c.horizon,)
    assert res.plan[0] == res.damping_cmd
    assert res.status in STATUSES and res.solve_time_s >= 0
    assert c.counters['steps'] == 1
    with pytest.raises(ParamError, match='unknown controller'):
        make_controller('lqr', M)


def test_passive_and_skyhook_laws():
    s = ControllerSettings()
    passive = make_controller('passive', M, s)
    assert passive.compute(np.ones(6), np.zeros(11), 0).damping_cmd == P.c_e0
    sky = make_controller('skyhook', M, s)
    # body moving up and away from the wheel: damp hard; moving towards it: soft.
    up_apart = np.array([0, 0.1, 0, 0.0, 0, 0])
    up_closing = np.array([0, 0.1, 0, 0.3, 0, 0])
    assert sky.compute(up_apart, np.zeros(11), 0).damping_cmd == s.u_max
    assert sky.compute(up_closing, np.zeros(11), 0).damping_cmd == s.u_min
    # c_e0 outside a narrow box is clipped into it
    narrow = make_controller('passive', M, s.with_(u_min=12000.0, u_max=15000.0))
    assert narrow.compute(np.zeros(6), np.zeros(11), 0).damping_cmd == 12000.0


def test_non_finite_measurement_falls_back_and_is_counted():
    c = make_controller('skyhook', M, ControllerSettings())
    ok = c.compute(np.array([0, 0.1, 0, 0, 0, 0]), np.zeros(11), 0.0)
    bad = c.compute(np.full(6, np.nan), np.zeros(11), 0.02)
    assert bad.status == 'fallback_plan'
    np.testing.assert_array_equal(bad.plan[:-1], ok.plan[1:])
    for k in range(20):
        last = c.compute(np.zeros(6), np.full(11, np.inf), 0.04 + 0.02 * k)
    assert last.status == 'fallback_passive' and last.damping_cmd == P.c_e0
    assert c.counters['nan_rejections'] == 21
    assert c.counters['fallback_plan'] == 9 and c.counters['fallback_passive'] == 12
    c.reset()
    assert c.counters['nan_rejections'] == 0


def test_short_preview_is_a_programming_error():
    c = make_controller('passive', M, ControllerSettings())
    with pytest.raises(ValueError, match='needs 11 road heights'):
        c.compute(np.zeros(6), np.zeros(3), 0.0)


def test_codegen_setting_accepts_yaml_booleans():
    assert settings_mod.validate_settings({'codegen': True}).codegen == 'on'
    assert settings_mod.validate_settings({'codegen': False}).codegen == 'off'
    with pytest.raises(ParamError, match="'codegen' = 'fast' is not allowed"):
        settings_mod.validate_settings({'codegen': 'fast'})
