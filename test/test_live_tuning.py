"""Live tuning of a real nmpc_node over DDS: `erva param`, /parameter_events, Foxglove.

One nmpc_node process and one foxglove_node process in their own namespace, for the
whole module.  Through the node's own rcl_interfaces services (`erva param`, in process
and as a command): a bad value and a read-only parameter are refused with the reason and
change nothing (no /parameter_events message either); a good one is set and announced
once.  Through the Foxglove server, with the WebSocket client of test_foxglove.py: the
parameters capability (get, set, a refusal as an error status, updates of followed
values), the connection graph, and /clock advertised only once it has a publisher.
Pass/fail on values and counts; every wait is for a condition.
"""

import json
import os
import time

import pytest
import rclpy
from rcl_interfaces.msg import ParameterEvent
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from erva_ros.ros import qos as ros_qos

from conftest import run_erva
from live_harness import start_node, stop_node

NS = '/tune'
NMPC = f'{NS}/nmpc_node'


def _wait_line(proc, text, timeout=180.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        log = open(proc.log_path).read()
        if text in log:
            return log
        assert proc.poll() is None, log
        time.sleep(0.1)
    raise AssertionError(f'no {text!r} in {proc.log_path}:\n{open(proc.log_path).read()}')


class Events:
    """An rclpy node that records /parameter_events and can publish /clock."""

    def __init__(self):
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context)
        self.node = Node('tuning_test_events', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.events = []
        self.node.create_subscription(ParameterEvent, '/parameter_events', self.events.append,
                                      ros_qos.control_qos(1000))

    def spin_until(self, done, timeout=60.0, what=''):
        end = time.monotonic() + timeout
        while not done():
            assert time.monotonic() < end, f'timed out waiting for {what}'
            self.executor.spin_once(timeout_sec=0.05)

    def of(self, node, since_ns=0):
        """Return the changes ``node`` announced, stamped from ``since_ns`` on (its clock).

        (A node also announces each parameter as it declares it, at start-up.)
        """
        return [{p.name: p.value for p in e.changed_parameters} for e in self.events
                if e.node == node and e.changed_parameters
                and e.stamp.sec * 10**9 + e.stamp.nanosec >= since_ns]

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope='module')
def nodes(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('live_tuning')
    nmpc = start_node('nmpc_node', NS, str(tmp / 'nmpc.log'), 'realtime_priority:=0')
    fox = start_node('foxglove_node', NS, str(tmp / 'fox.log'), 'port:=0')
    events = Events()
    try:
        _wait_line(nmpc, 'weights (1, 0)')            # configured: its loop core is built
        log = _wait_line(fox, 'serving ws://127.0.0.1:')
        port = int(log.split('serving ws://127.0.0.1:')[1].split()[0])
        # /parameter_events is volatile: wait until this reader matched the node's writer.
        events.spin_until(lambda: any(
            i.node_name == 'nmpc_node' and i.node_namespace == NS
            for i in events.node.get_publishers_info_by_topic('/parameter_events')),
            what='the node\'s /parameter_events writer')
        yield {'nmpc': nmpc, 'fox': fox, 'port': port, 'events': events}
    finally:
        events.close()
        for proc in (fox, nmpc):
            stop_node(proc)


def _tool():
    from erva_ros.ros.param_client import ParameterTool
    return ParameterTool(30.0)


def test_bad_and_read_only_changes_are_refused_with_the_reason_and_change_nothing(nodes):
    since = time.time_ns()        # the node's clock is the wall clock (real time)
    tool = _tool()
    try:
        before = tool.get(NMPC, ['alpha1', 'u_min', 'horizon'])
        assert before == {'alpha1': 1.0, 'u_min': 0.0, 'horizon': 10}
        cases = {'alpha1': ('-1', 'Parameter alpha1 out of range'),
                 'u_min': ('12000', "must keep the passive damping c_e0 = 10000 Ns/m inside"),
                 'horizon': ('20', 'Trying to set a read-only parameter: horizon: read-only '
                                   'while the node runs: the compiled solver is built for it')}
        for name, (text, says) in cases.items():
            reason = tool.set(NMPC, {name: text})
            assert reason is not None and says in reason, (name, reason)
        assert tool.set(NMPC, {'alpha1': '0', 'alpha2': '0'}).endswith(
            "parameters 'alpha1' and 'alpha2' are both 0; the NMPC needs a nonzero weight")
        assert tool.get(NMPC, list(before)) == before            # nothing changed
        # a good change: set, and announced once on /parameter_events
        assert tool.set(NMPC, {'alpha1': '0.5'}) is None
        assert tool.get(NMPC, ['alpha1']) == {'alpha1': 0.5}
    finally:
        tool.close()
    events = nodes['events']
    events.spin_until(lambda: events.of(NMPC, since), what='the change on /parameter_events')
    changes = events.of(NMPC, since)      # the refused ones announced nothing before it
    assert len(changes) == 1 and set(changes[0]) == {'alpha1'}
    assert changes[0]['alpha1'].double_value == 0.5


def test_erva_param_says_why_a_parameter_is_read_only(nodes):
    proc = run_erva('param', 'set', NMPC, 'ts', '0.01', '--timeout', '30')
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout.startswith('Setting parameter failed: Trying to set a read-only '
                                  'parameter: ts: read-only while the node runs: it fixes '
                                  'the sample grid'), proc.stdout
    proc = run_erva('param', 'describe', NMPC, 'u_max', '--timeout', '30', '--json')
    assert proc.returncode == 0, proc.stderr
    (desc,) = json.loads(proc.stdout)
    assert not desc['read_only'] and desc['type'] == 'double'
    assert desc['description'].endswith('live: may change while the node runs, takes effect '
                                        'at its next sample')
    proc = run_erva('param', 'get', NMPC, 'alpha11', '--timeout', '30')
    assert proc.returncode == 2 and "has no parameter 'alpha11'" in proc.stderr


# -- Foxglove --------------------------------------------------------------------------------
pytest.importorskip('foxglove')
from test_foxglove import Viewer  # noqa: E402 (the project's Foxglove client)

pytestmark = pytest.mark.ros   # every test here starts DDS


class ParameterViewer(Viewer):
    """The Foxglove client, keeping the parameter, status and graph messages too."""

    def __init__(self, port):
        super().__init__(port)
        self.ops = []

    def _handle(self, frame):
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg['op'] not in ('serverInfo', 'advertise'):
                self.ops.append(msg)
        super()._handle(frame)

    def send(self, **msg):
        self.ws.send(json.dumps(msg))

    def wait_for(self, match, timeout=60.0):
        end = time.monotonic() + timeout
        while True:
            found = [m for m in self.ops if match(m)]
            if found:
                return found[-1]
            assert time.monotonic() < end, f'no such message; got {self.ops[-5:]}'
            try:
                self._handle(self.ws.recv(timeout=0.2))
            except TimeoutError:
                pass


def _values(msg):
    return {p['name']: p.get('value') for p in msg['parameters']}


def test_foxglove_views_and_sets_parameters_and_follows_the_graph(nodes):
    viewer = ParameterViewer(nodes['port'])
    try:
        viewer.wait_channels([f'{NS}/state'])
        caps = viewer.server_info['capabilities']
        assert 'parameters' in caps and 'connectionGraph' in caps and 'time' not in caps
        assert '/clock' not in viewer.channels       # no publisher of it: not advertised
        name = f'{NMPC}.alpha2'
        n = 0

        def get(names):
            nonlocal n
            n += 1
            viewer.send(op='getParameters', parameterNames=names, id=f'get{n}')
            return _values(viewer.wait_for(lambda m: m.get('id') == f'get{n}'))

        end = time.monotonic() + 60
        while name not in get([name]):          # until the server found the node
            assert time.monotonic() < end
        assert get([name]) == {name: 0.0}
        assert any(k.startswith(f'{NMPC}.') for k in get([]))       # everything
        viewer.send(op='subscribeParameterUpdates', parameterNames=[name])
        viewer.send(op='setParameters', parameters=[{'name': name, 'value': 0.25}], id='set1')
        assert _values(viewer.wait_for(lambda m: m.get('id') == 'set1')) == {name: 0.25}
        # a refusal: the node's reason as an error status, the value as it was
        viewer.send(op='setParameters', id='set2',
                    parameters=[{'name': f'{NMPC}.u_min', 'value': 12000}])
        assert _values(viewer.wait_for(lambda m: m.get('id') == 'set2')) == \
            {f'{NMPC}.u_min': 0.0}
        status = viewer.wait_for(lambda m: m['op'] == 'status' and 'c_e0' in m['message'])
        assert status['level'] == 2 and status['message'].startswith(f'{NMPC}: ')
        viewer.send(op='setParameters', id='set3',
                    parameters=[{'name': f'{NMPC}.horizon', 'value': 20}])
        viewer.wait_for(lambda m: m['op'] == 'status' and 'horizon' in m['message']
                        and 'needs a new solver' in m['message'])
        # a change by another client reaches a client that follows the value
        tool = _tool()
        try:
            assert tool.set(NMPC, {'alpha2': '0.5'}) is None
        finally:
            tool.close()
        viewer.wait_for(lambda m: m['op'] == 'parameterValues' and 'id' not in m
                        and _values(m).get(name) == 0.5)
        # the connection graph, as foxglove_bridge sends it
        viewer.send(op='subscribeConnectionGraph')
        graph = viewer.wait_for(lambda m: m['op'] == 'connectionGraphUpdate' and any(
            t['name'] == f'{NS}/damping_cmd' for t in m['publishedTopics']))
        published = {t['name']: t['publisherIds'] for t in graph['publishedTopics']}
        subscribed = {t['name']: t['subscriberIds'] for t in graph['subscribedTopics']}
        services = {s['name']: s['providerIds'] for s in graph['advertisedServices']}
        assert NMPC in published[f'{NS}/damping_cmd']
        assert NMPC in subscribed[f'{NS}/state']
        assert services[f'{NMPC}/set_parameters'] == [NMPC]
        # /clock: advertised once it has a publisher (lock-step's plant; here this test)
        events = nodes['events']
        pub = events.node.create_publisher(Clock, '/clock', 10)
        try:
            end = time.monotonic() + 60
            while '/clock' not in viewer.channels:
                assert time.monotonic() < end, 'the server did not advertise /clock'
                try:
                    viewer._handle(viewer.ws.recv(timeout=0.2))
                except TimeoutError:
                    pass
                events.executor.spin_once(timeout_sec=0.0)
        finally:
            events.node.destroy_publisher(pub)
    finally:
        viewer.close()
    assert os.path.exists(nodes['fox'].log_path)
