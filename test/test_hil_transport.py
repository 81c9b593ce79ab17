"""Bus selection and the loopback-only UDP CAN link between processes."""

import socket
import subprocess
import sys
import textwrap
import time

import can
import pytest

from erva_ros.session.hil.hil_processes import hil_process_specs
from erva_ros.core.hil.transport import (free_udp_ports, LoopbackUdpBus, open_bus, parse_spec,
                                         reverse_udp_spec)


def test_spec_parsing_gives_one_line_errors():
    assert parse_spec('socketcan:can0') == ('socketcan', 'can0')
    assert parse_spec('udp:4000:4001') == ('udp', '4000:4001')
    assert reverse_udp_spec('udp:4000:4001') == 'udp:4001:4000'
    for bad, msg in (('can0', 'expected socketcan:IFACE'), ('udp_multicast:x', 'expected'),
                     ('udp:4000', 'LOCAL_PORT:PEER_PORT'), ('udp:4000:4000', 'must differ'),
                     ('udp:0:4001', 'out of range')):
        with pytest.raises(ValueError, match=msg):
            parse_spec(bad)


def test_loopback_only():
    with pytest.raises(ValueError, match='not a loopback address'):
        LoopbackUdpBus('4000:4001', host='192.0.2.1')


def test_frames_cross_processes_with_kernel_timestamps():
    a, b = free_udp_ports(2)
    bus = open_bus(f'udp:{a}:{b}')
    child = textwrap.dedent(f"""
        import time, can
        from erva_ros.core.hil.transport import open_bus
        bus = open_bus('udp:{b}:{a}')
        msg = bus.recv(10.0)
        bus.send(can.Message(arbitration_id=msg.arbitration_id + 1, data=msg.data[::-1],
                             is_extended_id=False))
        bus.shutdown()
        """)
    proc = subprocess.Popen([sys.executable, '-c', child])
    try:
        deadline = time.monotonic() + 20
        reply = None
        t_first = time.time()
        while reply is None and time.monotonic() < deadline:
            bus.send(can.Message(arbitration_id=0x123, data=b'\x01\x02\x03',
                                 is_extended_id=False))
            reply = bus.recv(0.2)
        assert reply is not None
        assert (reply.arbitration_id, bytes(reply.data)) == (0x124, b'\x03\x02\x01')
        # An epoch time between the first frame out and the reply read.
        assert t_first <= reply.timestamp <= time.time()
    finally:
        proc.wait(20)
        bus.shutdown()
    assert proc.returncode == 0


def test_datagrams_from_others_are_ignored_and_counted():
    a, b = free_udp_ports(2)
    bus = open_bus(f'udp:{a}:{b}')
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        stranger.sendto(b'EC\x01\x00\x00\x00\x01\x00\x00', ('127.0.0.1', a))  # not the peer
        peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        peer.bind(('127.0.0.1', b))
        peer.sendto(b'garbage', ('127.0.0.1', a))
        t_before = time.time()
        peer.sendto(b'EC\x01\x00\x00\x00\x01\x00\x02\xab\xcd', ('127.0.0.1', a))
        t_after = time.time()                 # loopback: queued during sendto
        time.sleep(0.1)                       # read well after arrival
        msg = bus.recv(1.0)
        assert msg.arbitration_id == 0x100 and bytes(msg.data) == b'\xab\xcd'
        assert t_before <= msg.timestamp <= t_after    # the kernel's arrival time
        assert bus.foreign_datagrams == 2
        peer.close()
    finally:
        stranger.close()
        bus.shutdown()
    with pytest.raises(can.CanOperationError):
        bus.send(can.Message(arbitration_id=1, data=b'', is_extended_id=False))


def test_hil_process_specs(tmp_path):
    specs = hil_process_specs('params.yaml', '/car1', 12.0, hil_file='hil.yaml',
                              env={'ROS_DOMAIN_ID': '42', 'PATH': '/usr/bin'})
    assert [s.name for s in specs] == ['ecu_sim', 'ecu_bridge_node', 'state_estimator_node']
    ecu, bridge, est = specs
    bus_ecu = ecu.argv[ecu.argv.index('--bus') + 1]
    bus_bridge = next(a for a in bridge.argv if a.startswith('bus:=')).split('=', 1)[1]
    assert reverse_udp_spec(bus_ecu) == bus_bridge
    assert ecu.argv[ecu.argv.index('--duration') + 1] == '12.0'
    for s in specs:
        assert s.env['ROS_DOMAIN_ID'] == '42'
        assert s.env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    for s in (bridge, est):
        assert '__ns:=/car1' in s.argv and s.argv.count('--params-file') == 2
