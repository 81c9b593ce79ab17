"""Where erva_ros finds its shipped files and the ROS packages' share directories.

One home for the lookup every tool needs: ``config/<name>`` of the source tree, else of the
installed package (``<prefix>/share/erva_ros/config`` for each prefix of
AMENT_PREFIX_PATH, as colcon installs it, then the Python prefix's, as pip installs the
data files).  The ament index is a directory of marker files, read here directly: the
core ring stays free of ROS imports, and a PyPI install (no ament index) works the same.
"""

import functools
import os
import sys
from typing import Any, Dict, List, Optional

from erva_ros.core.params import ParamError

PACKAGE = 'erva_ros'
#: The source tree's config/ (erva_ros/core/config.py -> <repo>/config).
SOURCE_CONFIG = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                              '..', '..', 'config'))


def _own_prefix() -> List[str]:
    # The prefix this package is installed in (<prefix>/lib/pythonX.Y/site-packages/
    # erva_ros/core/config.py): an install space finds its own config/ unsourced.
    parts = os.path.abspath(__file__).split(os.sep)
    if 'lib' in parts:
        i = len(parts) - 1 - parts[::-1].index('lib')
        return [os.sep.join(parts[:i]) or os.sep]
    return []


def prefixes() -> List[str]:
    """Return the install prefixes to search: AMENT_PREFIX_PATH, sys.prefix, this package's."""
    out = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for extra in [sys.prefix] + _own_prefix():
        if extra not in out:
            out.append(extra)
    return out


def shipped_config(name: str, hint: str = '') -> str:
    """Return the path of the shipped ``config/<name>``; ParamError (one line) if missing."""
    candidates = [os.path.join(SOURCE_CONFIG, name)]
    candidates += [os.path.join(p, 'share', PACKAGE, 'config', name) for p in prefixes()]
    for cand in candidates:
        if os.path.isfile(cand):
            return os.path.normpath(cand)
    raise ParamError(f'cannot find config/{name}' + (f'; {hint}' if hint else ''))


@functools.lru_cache(maxsize=None)
def _shipped_section(name: str, node: Optional[str]) -> Dict[str, Any]:
    from erva_ros.core.params import read_ros_params
    return read_ros_params(shipped_config(name), node, wildcard=node is None)


def shipped_defaults(name: str, node: Optional[str] = None) -> Dict[str, Any]:
    """Return the defaults a shipped params file gives: its ``/**`` or ``/**/<node>`` section.

    The one home of every default value: ``config/<name>`` as shipped (a copy; read once).
    ``node=None`` reads the wildcard section, else only the node's own sections.
    """
    return dict(_shipped_section(name, node))


@functools.lru_cache(maxsize=None)
def share_directory(package: str) -> str:
    """Return ``<prefix>/share/<package>`` of the first prefix that indexes ``package``.

    ParamError if none does (the ament index: share/ament_index/resource_index/packages).
    """
    for prefix in prefixes():
        marker = os.path.join(prefix, 'share', 'ament_index', 'resource_index', 'packages',
                              package)
        share = os.path.join(prefix, 'share', package)
        if os.path.isfile(marker) and os.path.isdir(share):
            return share
    for prefix in prefixes():           # installed without an index entry (pip data files)
        share = os.path.join(prefix, 'share', package)
        if os.path.isdir(share):
            return share
    raise ParamError(f'package {package!r} not found (AMENT_PREFIX_PATH or '
                     f'{sys.prefix}/share)')


__all__ = ['PACKAGE', 'SOURCE_CONFIG', 'prefixes', 'shipped_config', 'shipped_defaults',
           'share_directory']
