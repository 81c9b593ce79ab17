"""ament linters as tests (flake8 at 99 columns, pep257), as ros2/examples packages do."""

import os

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PATHS = [os.path.join(REPO, p) for p in ('erva_ros', 'test', 'launch', 'setup.py')]


def _existing():
    return [p for p in PATHS if os.path.exists(p)]


@pytest.mark.linter
def test_flake8():
    main_with_errors = pytest.importorskip('ament_flake8.main').main_with_errors
    rc, errors = main_with_errors(argv=_existing())
    assert rc == 0, f'Found {len(errors)} code style errors / warnings:\n' + '\n'.join(errors)


@pytest.mark.linter
def test_pep257():
    # ament convention, except that a multi-line docstring's summary sits on its first
    # line (D212 checked, D213 not) -- the PEP 257 examples' layout.
    main = pytest.importorskip('ament_pep257.main').main
    argv = ['--ignore', 'D100', 'D101', 'D102', 'D103', 'D104', 'D105', 'D106', 'D107',
            'D203', 'D213', 'D404', '--'] + _existing()
    assert main(argv=argv) == 0, 'Found docstring style errors (see output above)'
