"""Hot-path helpers: RealtimeSubscription over real DDS, and BufferedCall against fn(*args)."""

import threading
import time

import casadi as ca
import numpy as np
import pytest
import rclpy
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from erva_ros.core.model.codegen import BufferedCall
from erva_ros.ros.rt_subscription import RealtimeSubscription
from erva_ros.ros.qos import control_qos


# -- BufferedCall ------------------------------------------------------------------------
def _function():
    x, m, s = ca.SX.sym('x', 3), ca.SX.sym('m', 2, 3), ca.SX.sym('s')
    outputs = [ca.sin(x) * s, m @ x, ca.dot(x, x) + s, ca.horzcat(x, 2 * x)]
    return ca.Function('f', [x, m, s], outputs)


def test_buffered_call_equals_the_plain_call_bit_for_bit():
    f = _function()
    fast = BufferedCall(f)
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, m, s = rng.normal(size=3), rng.normal(size=(2, 3)), float(rng.normal())
        want = [np.asarray(v) for v in f(x, m, s)]
        got = fast(x, m, s)
        assert got[0].shape == (3,) and got[1].shape == (2,) and isinstance(got[2], float)
        assert got[3].shape == (3, 2)                  # a matrix comes back as one
        assert np.array_equal(got[0], want[0].ravel()) and np.array_equal(got[1],
                                                                          want[1].ravel())
        assert got[2] == want[2].item() and np.array_equal(got[3], want[3])
    col = fast(np.arange(3.0).reshape(3, 1), np.ones((2, 3)), np.array([[2.0]]))
    assert np.array_equal(col[0], fast(np.arange(3.0), np.ones((2, 3)), 2.0)[0])
    out = fast(np.ones(3), np.ones((2, 3)), 1.0)
    again = fast(np.zeros(3), np.zeros((2, 3)), 0.0)
    assert not np.array_equal(out[0], again[0])        # results are copies, not the buffer


def test_buffered_call_reports_failures_and_rejects_misuse():
    x = ca.MX.sym('x')
    checked = ca.Function('checked', [x], [ca.sqrt(x.attachAssert(x >= 0, 'x < 0'))])
    fast = BufferedCall(checked)
    assert fast(4.0)[0] == 2.0
    with pytest.raises(RuntimeError, match='x < 0'):
        fast(-1.0)
    with pytest.raises(TypeError, match='1 arguments, expected 3'):
        BufferedCall(_function())(1.0)
    y = ca.SX.sym('y', 2)
    with pytest.raises(ValueError, match='sparse'):
        BufferedCall(ca.Function('s', [y], [ca.diag(y)]))


# -- RealtimeSubscription ------------------------------------------------------------------
@pytest.fixture
def ros_context():
    ctx = rclpy.Context()
    rclpy.init(args=['x', '--ros-args', '-r', '__ns:=/hot', '-r', 'in:=remapped'],
               context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def _wait_for(cond, timeout=30.0):   # generous: only a failure waits this long
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.01)
    return cond()


@pytest.mark.ros
def test_realtime_subscription_takes_messages_and_idles_between(ros_context):
    owner = Node('owner', context=ros_context)
    talker = Node('talker', context=ros_context, use_global_arguments=False)
    got, events = [], []
    main = threading.get_ident()

    def on_message(data, info):
        assert threading.get_ident() != main
        got.append((deserialize_message(data, JointState), info['received_timestamp']))
        events.append('message')
        sub.idle_at = time.monotonic() + 0.01

    sub = RealtimeSubscription(owner, JointState, 'in', control_qos(), on_message,
                               idle=lambda: events.append('idle'), raw=True)
    assert sub.topic == '/hot/remapped'                # the owner's remapping rules
    sub.start()
    pub = talker.create_publisher(JointState, '/hot/remapped', control_qos())
    try:
        assert _wait_for(lambda: pub.get_subscription_count() == 1)
        assert 'owner_rt' in talker.get_node_names()
        # Each message arms the idle call 10 ms on; the next one goes out once it ran
        # (however late a busy machine runs it), so each message gets exactly one.
        for i in range(5):
            pub.publish(JointState(name=['z_s'], position=[float(i)]))
            assert _wait_for(lambda: events.count('idle') == i + 1), events
        assert [m.position[0] for m, _ in got] == [0.0, 1.0, 2.0, 3.0, 4.0]
        assert all(stamp > 0 for _, stamp in got)
        time.sleep(0.1)                                # not armed again without a message
        assert events == ['message', 'idle'] * 5 and sub.alive
    finally:
        sub.destroy()
        talker.destroy_node()
        owner.destroy_node()
    assert not sub.alive


@pytest.mark.ros
def test_a_failing_callback_stops_the_node_and_is_raised(ros_context):
    owner = Node('owner', context=ros_context)
    talker = Node('talker', context=ros_context, use_global_arguments=False)

    def broken(data, info):
        raise ZeroDivisionError('bad callback')

    sub = RealtimeSubscription(owner, JointState, '/hot/x', control_qos(), broken)
    sub.start()
    pub = talker.create_publisher(JointState, '/hot/x', control_qos())
    try:
        assert _wait_for(lambda: pub.get_subscription_count() == 1)
        pub.publish(JointState())
        assert _wait_for(lambda: not ros_context.ok())   # as a crash in a callback would
        assert _wait_for(lambda: not sub.alive)
        with pytest.raises(ZeroDivisionError, match='bad callback'):
            sub.destroy()
    finally:
        talker.destroy_node()
        owner.destroy_node()
