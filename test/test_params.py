"""Parameter files: the paper's values load; bad files fail with one line naming the key."""

import pytest
import yaml

from erva_ros.core.model.params import load_erva_params, PAPER_VALUES, ParamError


def write(tmp_path, body):
    path = tmp_path / 'p.yaml'
    path.write_text(body if isinstance(body, str) else yaml.safe_dump(body))
    return str(path)


def paper_doc(**override):
    values = dict(PAPER_VALUES, **override)
    return {'/**': {'ros__parameters': values}}


def test_shipped_file_is_the_paper_table():
    p = load_erva_params()
    assert p.as_dict() == PAPER_VALUES
    assert p.m_x == pytest.approx(21.31 + 14.42 + 129.78)


def test_node_section_overrides_wildcard(tmp_path):
    doc = paper_doc()
    doc['plant_sim_node'] = {'ros__parameters': {'M_s': 300.0}}
    assert load_erva_params(write(tmp_path, doc), 'plant_sim_node').M_s == 300.0
    assert load_erva_params(write(tmp_path, doc)).M_s == 250.0


@pytest.mark.parametrize('key,value,needle', [
    ('M_s', -250.0, "'M_s' = -250.0 is out of range; allowed [1, 5000] kg"),
    ('l', 0.0, "'l' = 0.0 is out of range; allowed (0, 10] m/rad"),
    ('k_t', 'stiff', "'k_t' must be a number in [1000, 1e+07] N/m, got str 'stiff'"),
    ('epsilon', True, "'epsilon' must be a number"),
    ('c_e0', float('nan'), "'c_e0' = nan is out of range"),
])
def test_bad_values_name_key_value_and_range(tmp_path, key, value, needle):
    with pytest.raises(ParamError) as exc:
        load_erva_params(write(tmp_path, paper_doc(**{key: value})))
    msg = str(exc.value)
    assert needle in msg
    assert '\n' not in msg


def test_missing_key(tmp_path):
    doc = paper_doc()
    del doc['/**']['ros__parameters']['m_d']
    with pytest.raises(ParamError, match=r"missing parameter 'm_d' \(expected \[0, 10000\] kg"):
        load_erva_params(write(tmp_path, doc))


@pytest.mark.parametrize('body,needle', [
    ('a: [1, 2\n', 'not valid YAML at line'),
    ('- 1\n- 2\n', 'expected a mapping'),
    ('other_node:\n  ros__parameters: {M_s: 1.0}\n', 'no ros__parameters for /**'),
    ('/**:\n  params: {}\n', "section '/**' must contain a ros__parameters mapping"),
])
def test_malformed_files(tmp_path, body, needle):
    with pytest.raises(ParamError, match=needle.replace('*', r'\*').replace('[', r'\[')):
        load_erva_params(write(tmp_path, body))


def test_cli_reports_bad_file_in_one_line(tmp_path, erva):
    path = write(tmp_path, paper_doc(M_us=0.0))
    proc = erva('fr', '--params', path, '--json')
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "'M_us' = 0.0 is out of range; allowed [1, 1000] kg" in lines[0]
    assert 'Traceback' not in proc.stderr
