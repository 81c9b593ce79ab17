"""Which of the sessions that start on one namespace runs: the rules, without DDS.

The sessions themselves, over DDS: test_run_sessions.py.
"""

import time

from erva_ros.session.run.bringup import node_stages, Timeline
from erva_ros.session.run.session_file import new_session_id
from erva_ros.session.run.start_gate import Contest, extra_nodes

A, B = '0000000000a00001', '0000000000a00002'     # A started first


def _pair(force_b=False):
    a = Contest(A, '/erva', nodes=['nmpc_node', 'recorder'], clock=lambda: 1)
    b = Contest(B, '/erva', force=force_b, nodes=['nmpc_node'], clock=lambda: 2)
    a.hear(b.claim())
    b.hear(a.claim())
    return a, b


def test_the_session_that_started_first_runs_and_the_other_stands_down():
    a, b = _pair()
    assert not a.beats(B) and b.beats(A)
    assert a.winners({}) == [] and b.winners({}) == [
        f'session {A} (pid {a.own.pid}) /erva/nmpc_node /erva/recorder']
    # Its own claim is not heard as another's; nodes seen by their statuses are named.
    a.hear(a.claim())
    assert set(a.heard) == {B}
    assert b.winners({'plant_sim_node': A}) == [f'/erva/plant_sim_node (session {A})']
    # The one that ran knows who stood down for it, by claim or by status.
    assert a.yielded() == [B] and a.yielded({'recorder: bag recorder': 'ffff'}) == [B, 'ffff']
    assert b.yielded() == []


def test_a_session_bringing_up_or_forced_never_yields_and_always_wins():
    a, b = _pair()
    b.commit()                      # B committed before it heard A (discovery was slow)
    a.hear(b.claim())
    assert a.beats(B) and a.yielded() == []
    assert not b.beats(A)           # committed: it no longer yields
    a, b = _pair(force_b=True)
    assert a.beats(B) and not b.beats(A) and b.winners({'nmpc_node': A}) == []
    # Nodes outside any session (started by hand: id '') win over a session.
    alone = Contest(A, '/erva')
    assert alone.beats('') and alone.winners({'nmpc_node': ''}) == [
        '/erva/nmpc_node (session none)']


def test_session_ids_sort_by_start_and_other_nodes_are_counted_beyond_the_own():
    ids = []
    for _ in range(3):          # a millisecond apart: their order is the start's
        ids.append(new_session_id())
        time.sleep(0.002)
    assert all(len(i) == 16 and int(i, 16) >= 0 for i in ids) and ids == sorted(ids)
    graph = [('nmpc_node', '/erva'), ('nmpc_node', '/erva'), ('recorder', '/erva'),
             ('erva_run_monitor', '/erva'), ('erva_run_monitor', '/erva'),
             ('ecu_bridge_node', '/erva'), ('nmpc_node', '/b'), ('talker', '/erva')]
    assert extra_nodes(graph, '/erva', ['nmpc_node', 'recorder']) == [
        '/erva/ecu_bridge_node', '/erva/nmpc_node']


def test_the_stage_table_counts_from_the_command_and_each_node_from_its_spawn():
    t = Timeline(t0=0.0)
    t.stages.update({'options parsed': 0.4, 'running': 1.9})
    t.spawned['nmpc_node'] = 0.5

    class Report:
        startup = {'imported': 0.6, 'initialised': 0.65, 'constructed': 0.8,
                   'configured': 1.2, 'activated': 1.25}
    nodes = node_stages(t.spawned, {'nmpc_node': Report()})
    assert nodes == {'nmpc_node': {'started': 0.5, 'imported': 1.1, 'initialised': 1.15,
                                   'constructed': 1.3, 'configured': 1.7, 'activated': 1.75}}
    lines = t.lines(nodes)
    assert lines[1:3] == ['    0.400  (+ 0.400)  options parsed',
                          '    1.900  (+ 1.500)  running']
    assert lines[3].startswith('  nmpc_node: started at 0.500, python + imports +0.600')
