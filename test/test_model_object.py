"""One model object, many users: the model is built once by its factory and passed in."""

import ast
import inspect
import os
import re

import pytest

from erva_ros.core.studies.closed_loop import simulate_closed_loop
from erva_ros.core.controllers import make_controller
from erva_ros.core.controllers.clairvoyant import clairvoyant_bound, plant_run
from erva_ros.core.controllers.nmpc import NMPCController
from erva_ros.core.model.estimator import ExtendedKalmanFilter
from erva_ros.core.hil.ecu_sim import EcuSimCore
from erva_ros.core.hil.evaluation import evaluate_estimator
from erva_ros.core.identify.fit import identify
from erva_ros.core.loop.plant_loop import PlantLoop
from erva_ros.core.model.quarter_car import make_model, QuarterCarModel
from erva_ros.core.settings.loop import MODEL_KINDS
from erva_ros.core.model.params import paper_params
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.model.road_estimator import RoadEKF
from erva_ros.core.roadmap.drive import estimate_drive
from erva_ros.core.roadmap.vehicle import simulate_vehicle

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'erva_ros')
FACTORY = os.path.join('core', 'model', 'quarter_car.py')
#: The model's users: each takes the model object (named ``model``, or ``prior_model``),
#: never parameters and a model name.
USERS = (PlantSimulator, ExtendedKalmanFilter, RoadEKF, NMPCController, make_controller,
         simulate_closed_loop, plant_run, clairvoyant_bound, evaluate_estimator, EcuSimCore,
         identify, PlantLoop, estimate_drive, simulate_vehicle)


def _sources():
    for base, _, files in os.walk(ROOT):
        for name in files:
            if name.endswith('.py'):
                path = os.path.join(base, name)
                yield os.path.relpath(path, ROOT), open(path, encoding='utf-8').read()


def test_the_factory_is_the_one_place_a_model_is_chosen_by_name():
    offenders = []
    name = r"""['"](erva|benchmark)['"]"""
    name_test = re.compile(r'(==|!=)\s*' + name + '|' + name + r'\s*(==|!=)')
    for rel, text in _sources():
        if 'get_model' in text:
            offenders.append(f'{rel}: get_model (the factory is make_model)')
        if rel != FACTORY and name_test.search(text):
            offenders.append(f'{rel}: compares a model name')
        tree = ast.parse(text)
        for node in ast.walk(tree):
            # A parameter called ``kind`` defaulting to a model name: a model chosen by string.
            if isinstance(node, ast.arguments) and rel != FACTORY:
                for arg, default in zip(node.args[-len(node.defaults):] if node.defaults
                                        else [], node.defaults):
                    if (arg.arg == 'kind' and isinstance(default, ast.Constant)
                            and default.value in MODEL_KINDS):
                        offenders.append(f'{rel}:{node.args[0].lineno if node.args else 0}: '
                                         f'kind={default.value!r}')
    assert not offenders, offenders


@pytest.mark.parametrize('user', USERS, ids=lambda u: u.__qualname__)
def test_each_user_takes_the_model_object(user):
    params = inspect.signature(user).parameters
    assert 'kind' not in params, user
    models = [p for p in params.values() if p.annotation is QuarterCarModel]
    assert len(models) == 1, (user, list(params))


def test_a_model_is_built_once_per_parameters_and_kind():
    p = paper_params()
    assert make_model(p) is make_model(p, 'erva')                 # shared, not rebuilt
    assert make_model(p, 'benchmark') is not make_model(p)
    other = make_model(p).with_params(p.with_(M_s=300.0))
    assert other.kind == 'erva' and other.params.M_s == 300.0
    with pytest.raises(ValueError, match="model kind 'car' unknown; choose one of erva, "
                                         'benchmark'):
        make_model(p, 'car')
    # It owns its states, their message names and their scales.
    m = make_model(p)
    assert m.state_names == ('z_s', 'zdot_s', 'z_us', 'zdot_us', 'z_d', 'zdot_d')
    assert m.joints == ('z_s', 'z_us', 'z_d') and len(m.x_scale) == m.nx == 6
