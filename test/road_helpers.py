"""Drives for the road-map tests: simulated offline, written as HIL session bags.

The bags have the layout of an `erva run --ecu virtual` recording where the map reads
it: ``/erva/ecu/measurements`` (the bridge's JointState, encoded by erva_ros.core.contract) and
``/erva/road/height`` (PointStamped, rclpy's serialisation), stamped on the Ts grid, and
the session record with the live parameters (road, seed, speed, ts).
"""

import json
import subprocess
import sys

import numpy as np

from erva_ros.core import topics as contract
from erva_ros.core.bag.writer import BagWriter
from erva_ros.core.controllers import ControllerSettings, make_controller
from erva_ros.core.hil import topics as hil_topics
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.params import paper_params
from erva_ros.core.roadmap.vehicle import OdometryError, Route, simulate_vehicle
from erva_ros.core.road.profiles import make_road

from conftest import REPO, ros_env

P = paper_params()
M = make_model(P)
TS = 0.02
T0_NS = 1_800_000_000 * 10 ** 9


def route(seed=0, speed=20.0, seconds=12.0):
    """Return the paper road of ``seed`` as a route."""
    return Route.of(make_road('paper', seconds, seed=seed, speed_mps=speed))


def drive(rt, sensor_seed, seconds=5.0, speed=20.0, odometry=OdometryError(), start_m=0.0):
    """Return one passive drive along route ``rt`` (VehicleRun)."""
    passive = make_controller('passive', M, ControllerSettings())
    return simulate_vehicle(M, passive, rt.drive(speed, start_m), seconds, start_m=start_m,
                            sensor_seed=sensor_seed, odometry=odometry)


def write_bag(path, run, road_seed=0, speed=20.0, drop=()):
    """Write ``run`` as a HIL session bag at ``path``; cycles in ``drop`` are left out."""
    from erva_ros.core.contract import encode_road_height, JointStateEncoder

    live = {'road': 'paper', 'seed': road_seed, 'speed_mps': speed, 'ts': TS, 'road_file': '',
            'road_class': 'C'}
    meas = f'{contract.NAMESPACE}/{hil_topics.ECU_MEASUREMENTS}'
    height = f'{contract.NAMESPACE}/{contract.ROAD_HEIGHT}'
    enc = JointStateEncoder(hil_topics.MEASUREMENT_NAMES)
    with BagWriter(path, session={'parameters': json.dumps({'live': live})}) as w:
        w.add_topic(meas, 'sensor_msgs/msg/JointState')
        w.add_topic(height, 'geometry_msgs/msg/PointStamped')
        for k in range(run.t.size):
            stamp = T0_NS + k * int(TS * 1e9)
            w.write(height, encode_road_height(stamp, run.s_odo[k], run.w[k]), stamp)
            if k in drop:
                continue
            y = run.y[k]
            w.write(meas, enc.encode(stamp + 600_000, [run.u_now[k], run.u_mean[k], y[0], y[1],
                                                       y[2], y[3]]), stamp + 700_000)
    return path


def nodes(location):
    """Return the map's nodes table as an array (i, info, info_height, drives)."""
    from erva_ros.core.roadmap.store import RoadMap
    with RoadMap.open(location) as m:
        return np.array(m.db.execute('SELECT * FROM nodes ORDER BY i'), dtype=float)


def table(location, name):
    """Return every row of a map's table ``name``, ordered by its key, as tuples."""
    from erva_ros.core.roadmap.store import RoadMap
    key = {'meta': 'key', 'nodes': 'i', 'drives': 'id'}[name]
    with RoadMap.open(location) as m:
        return [tuple(r) for r in m.db.execute(f'SELECT * FROM {name} ORDER BY {key}')]


def map_build(bags, out):
    """Run ``erva map build BAGS --out OUT`` as a user does; it must succeed."""
    r = subprocess.run([sys.executable, '-m', 'erva_ros.cli', 'map', 'build', *bags, '--out',
                        out], capture_output=True, text=True, env=ros_env(), cwd=REPO)
    assert r.returncode == 0, r.stderr
