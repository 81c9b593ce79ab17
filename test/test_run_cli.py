"""`erva run` options, errors as one line, and the launch file (which cannot run here)."""

import ast
import importlib.util
import os
import re
import subprocess
import sys

import pytest

from conftest import REPO, ROS_DOMAIN_ID, ros_env

LAUNCH = os.path.join(REPO, 'launch', 'erva.launch.py')


def test_run_help_lists_the_options(erva):
    proc = erva('run', '--help')
    assert proc.returncode == 0
    for opt in ('--controller', '--alpha1', '--alpha2', '--road', '--seed', '--mode',
                '--model', '--duration', '--params', '--record', '--no-record', '--ecu',
                '--realtime-priority', '--json'):
        assert opt in proc.stdout, opt


@pytest.mark.parametrize('args, message', [
    (['--params', '/no/such.yaml'], r"parameter file '/no/such.yaml' does not exist"),
    (['--live', '{bad}'], r'live parameter file'),
    (['--seed', '3', '--live', 'BADLIVE'], r"unknown live parameter\(s\) speeed_mps"),
    (['--road-file', 'BINARY'], r"road_file '.*' is not a UTF-8 text CSV \(byte \d+"),
    (['--road-file', 'LATIN1'], r"road_file '.*' is not a UTF-8 text CSV"),
    (['--road-file', 'NANROW'], r'road_file .*:3: .* is not a finite "time_s, height_m" row'),
    (['--params', 'BINARY'], r'not a UTF-8 text file \(byte \d+'),
    (['--nmpc', 'BINARY'], r'not a UTF-8 text file'),
    (['--live', 'BINARY'], r'not a UTF-8 text file'),
    (['--record', 'FILE/bags'], r'--record .*: cannot write bags there \(Not a directory\)'),
    (['--record', '/proc/x'], r'--record /proc/x/bags: cannot write bags there \('),
    (['--params', 'FOOBAR'], r"erva_paper.yaml: unknown parameter\(s\) foo_bar; known: M_s, "),
    (['--params', 'TYPO'], r"unknown parameter\(s\) M_S; did you mean 'M_s'\?$"),
    (['--nmpc', 'HORIZN'], r"unknown parameter\(s\) horizn; did you mean 'horizon'\?$"),
    (['--road-file', 'DIR'], r"road_file '.*' is a directory, not a CSV file$"),
    (['--road-file', 'HUGE'], r"road_file '.*' is 513 MiB; the limit is 512 MiB \(about 20 "
                              r"million rows\): cut it to the part the run drives$"),
    (['--road-file', 'UNSORTED'], r'road_file .*unsorted.csv:5: time 0.5 s is not after the '
                                  r'row before \(1 s\)'),
    # The loop's timing is the controller's too: a bad one is the live file's, not an
    # "override"'s.
    (['--live', 'BADTS'], r"badts.yaml: parameter 'ts' must be a number in \[0.001, 1\] s, "
                          r"got list \[1\]$"),
    (['--live', 'LATE'], r"late.yaml: parameter 'command_delay_s' = 0.05 must be below "
                         r"ts = 0.02 s$"),
    (['--command-delay', '0.03'], r"^erva run: error: --command-delay \(ts: .*live.yaml\): "
                                  r"parameter 'command_delay_s' = 0.03 must be below ts"),
])
def test_bad_input_is_one_line_and_no_node_starts(erva, tmp_path, args, message):
    bad = tmp_path / 'live.yaml'
    bad.write_text('/**/road_preview_node:\n  ros__parameters:\n    speeed_mps: 3.0\n')
    files = {'BADLIVE': bad, 'BINARY': tmp_path / 'binary.csv',
             'LATIN1': tmp_path / 'latin1.csv', 'NANROW': tmp_path / 'nan.csv',
             'FILE/bags': tmp_path / 'file'}
    files['BINARY'].write_bytes(bytes(range(256)) * 8)
    files['LATIN1'].write_bytes('time_s, höhe_m\n0, 0\n1, 0.01\n'.encode('latin-1'))
    files['NANROW'].write_text('time_s, height_m\n0, 0\n1, nan\n')
    files['FILE/bags'].write_text('a file, not a directory')
    paper = open(os.path.join(REPO, 'config', 'erva_paper.yaml'), encoding='utf-8').read()
    for name, text in (('FOOBAR', paper + '    foo_bar: 1.0\n'),
                       ('TYPO', paper.replace('M_s:', 'M_S:'))):
        files[name] = tmp_path / name / 'erva_paper.yaml'
        files[name].parent.mkdir()
        files[name].write_text(text)
    files['HORIZN'] = tmp_path / 'nmpc.yaml'
    files['HORIZN'].write_text('/**/nmpc_node:\n  ros__parameters:\n    horizn: 5\n')
    files['DIR'] = tmp_path / 'roads'
    files['DIR'].mkdir()
    files['UNSORTED'] = tmp_path / 'unsorted.csv'
    files['UNSORTED'].write_text('time_s, height_m\n0, 0\n# a comment\n1, 0.01\n0.5, 0\n')
    live = open(os.path.join(REPO, 'config', 'live.yaml'), encoding='utf-8').read()
    for name, old, new in (('BADTS', 'ts: 0.02 ', 'ts: [1] '),
                           ('LATE', 'command_delay_s: 0.015', 'command_delay_s: 0.05')):
        files[name] = tmp_path / f'{name.lower()}.yaml'
        files[name].write_text(live.replace(old, new))
    files['HUGE'] = tmp_path / 'huge.csv'
    with open(files['HUGE'], 'wb') as fh:     # sparse: nothing written, 513 MiB long
        fh.truncate(513 * 2 ** 20)
    args = [str(files[a]) if a in files else a for a in args]
    if args[0] == '--record':
        args[1] = os.path.join(args[1], 'bags')
    else:
        args.append('--no-record')
    tmp = tmp_path / 'tmp'      # where erva run keeps a session's params file and logs
    tmp.mkdir()
    # The run's own domain: erva checks the domain before some of these inputs (no node
    # starts either way; the test asserts that).
    proc = erva('run', *args, env={'TMPDIR': str(tmp), 'ROS_DOMAIN_ID': str(ROS_DOMAIN_ID)})
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and re.search(message, lines[0]), proc.stderr
    assert 'started' not in proc.stderr
    assert list(tmp.iterdir()) == []      # a refused run leaves nothing behind


@pytest.mark.parametrize('domain', ['240', 'seven', '500'])
def test_a_bad_ros_domain_is_one_line_and_nothing_is_recorded(erva, tmp_path, domain):
    # Fast DDS would report it as a port error deep in start-up; erva says what it is
    # before a node or a bag exists.  A node started by hand says the same.
    bags, tmp = tmp_path / 'bags', tmp_path / 'tmp'
    tmp.mkdir()
    proc = erva('run', '--duration', 0.2, '--record', bags,
                env={'ROS_DOMAIN_ID': domain, 'TMPDIR': str(tmp)})
    assert proc.returncode == 2
    assert list(tmp.iterdir()) == []      # no erva_run_* directory left behind
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"erva run: error: ROS_DOMAIN_ID='{domain}' is not a ROS domain: an "
                     "integer 0..232 (Fast DDS maps it to UDP ports; 0..101 stay clear of "
                     "Linux's ephemeral ports)"], proc.stderr
    assert not bags.exists() or not any(bags.iterdir())
    node = subprocess.run([sys.executable, '-m', 'erva_ros.nodes.plant_sim_node'],
                          capture_output=True, text=True, timeout=60,
                          env=ros_env({'ROS_DOMAIN_ID': domain}))
    assert node.returncode == 2
    assert node.stderr.strip().splitlines()[-1].startswith(
        f"plant_sim_node: error: ROS_DOMAIN_ID='{domain}' is not a ROS domain"), node.stderr


def test_option_values_are_checked_by_argparse(erva):
    for args in (['--duration', '-1'], ['--alpha1', 'nan'], ['--mode', 'fast'],
                 ['--controller', 'lqr'], ['--seed', 'x'], ['--realtime-priority', '99']):
        proc = erva('run', *args)
        assert proc.returncode == 2 and 'error:' in proc.stderr, args
        assert 'Traceback' not in proc.stderr


def _commands(parser, path=()):
    """Yield (command path, its parser) of every command below ``parser`` (aliases too)."""
    import argparse
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from _commands(sub, (*path, name))


@pytest.mark.parametrize('args, message', [
    (['run', '--duration', '-1'], "argument --duration: '-1' must be a positive, finite number"),
    (['run', '--alpha1', 'abc'], "argument --alpha1: 'abc' is not a number in [0, 1e+06]"),
    (['run', '--seed', '-5'], "argument --seed: '-5' is not an integer in [0, 1e+09]"),
    (['run', '--controller', 'foo'], "argument --controller: invalid choice: 'foo'"),
    (['replay', 'x.mcap', '--rate', '0'], "argument -r/--rate: '0' must be a positive"),
])
def test_a_bad_option_is_one_line_for_every_command(capsys, args, message):
    # The README promises one line; argparse prints its whole usage first (12 lines for
    # `erva run`).  Every command's parser is the CLI's own (cli.Parser).
    from erva_ros import cli
    commands = dict(_commands(cli.build_parser()))
    assert len(commands) > 20 and ('bag', 'info') in commands and ('run',) in commands
    # (a command with a required argument says that first)
    cases = [(args, commands[(args[0],)].prog, message)] + [
        ([*path, '--no-such-option'], p.prog, '') for path, p in commands.items()]
    for argv, prog, text in cases:
        with pytest.raises(SystemExit) as exc:
            cli.main(argv)
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert exc.value.code == 2 and len(lines) == 1, (argv, err)
        assert lines[0].startswith(f'{prog}: error: ') and text in lines[0], (argv, err)
        assert lines[0].endswith(f'("{prog} --help" lists the options)'), (argv, err)


def test_launch_file_parses_and_references_what_exists():
    source = open(LAUNCH, encoding='utf-8').read()
    compile(source, LAUNCH, 'exec')
    spec = importlib.util.spec_from_file_location('erva_launch', LAUNCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)            # no ROS launch needed to import it
    assert callable(mod.generate_launch_description)
    setup = ast.parse(open(os.path.join(REPO, 'setup.py'), encoding='utf-8').read())
    nodes = next(ast.literal_eval(n.value) for n in setup.body
                 if isinstance(n, ast.Assign) and getattr(n.targets[0], 'id', '') == 'NODES')
    assert set(mod.NODES) <= set(nodes)
    for name in mod.NODES:
        assert importlib.util.find_spec(f'erva_ros.nodes.{name}') is not None
    for cfg in mod.CONFIG_FILES:
        assert os.path.isfile(os.path.join(REPO, 'config', cfg)), cfg
    # Every launch argument is a parameter some node declares.
    from erva_ros.core.settings.schemas import SCHEMAS
    declared = {name for node in mod.NODES for name in SCHEMAS[node].specs()}
    for name, default, kind, _ in mod.ARGUMENTS:
        assert name == 'namespace' or name in declared, name
        kind(default)
    section = mod.node_section(os.path.join(REPO, 'config', 'nmpc.yaml'), 'nmpc_node')
    assert section.get('controller') == 'preview' and 'horizon' in section
