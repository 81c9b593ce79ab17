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
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import yaml

from erva_ros.core.settings.specs import ParamError

PACKAGE = 'erva_ros'
#: The source tree's config/ (erva_ros/core/settings/files.py -> <repo>/config).
SOURCE_CONFIG = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                              '..', '..', '..', 'config'))


def _own_prefix() -> List[str]:
    # The prefix this package is installed in (<prefix>/lib/pythonX.Y/site-packages/
    # erva_ros/core/settings/files.py): an install space finds its own config/ unsourced.
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


def load_params_yaml(path: str) -> Dict[str, Any]:
    """Parse a ROS params file into its top-level mapping, or raise a one-line ParamError."""
    if not os.path.isfile(path):
        raise ParamError(f'parameter file {path!r} does not exist')
    try:
        with open(path, encoding='utf-8') as fh:
            doc = yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        at = f' at line {mark.line + 1}' if mark is not None else ''
        raise ParamError(f'{path}: not valid YAML{at}') from None
    except UnicodeDecodeError as exc:
        raise ParamError(f'{path}: not a UTF-8 text file (byte {exc.start}: {exc.reason})'
                         ) from None
    except OSError as exc:
        raise ParamError(f'{path}: cannot be read ({exc.strerror or exc})') from None
    if not isinstance(doc, dict):
        raise ParamError(f'{path}: expected a mapping of node names to ros__parameters')
    return doc


#: Section keys rcl applies to every node.
WILDCARD_SECTIONS = ('/**', '**')


def node_sections(node: str) -> Tuple[str, ...]:
    """Return the section keys rcl applies to ``node`` in any namespace, in merge order.

    ``/**/name`` (and ``**/name``) match the node in any namespace (e.g. /erva/nmpc_node);
    a bare ``name`` or ``/name`` is the node in the root namespace, read here all the same
    (the offline tools have no namespace).
    """
    node = node.lstrip('/')
    return (node, '/' + node, '**/' + node, '/**/' + node)


def read_sections(path: str, nodes: Sequence[str] = (), wildcard: bool = True
                  ) -> List[Tuple[str, Dict[str, Any]]]:
    """Return (key, ros__parameters) of each section of a params file that applies.

    The one reader of params-file sections: the wildcard sections (``/**``, ``**``;
    unless ``wildcard`` is False), then each of ``nodes``' sections
    (:func:`node_sections`), in that order -- later ones override earlier ones when
    merged, as ``--params-file`` does.  A section without a ros__parameters mapping is a
    one-line :class:`ParamError`.
    """
    doc = load_params_yaml(path)
    keys: List[str] = list(WILDCARD_SECTIONS) if wildcard else []
    for node in nodes:
        keys += [k for k in node_sections(node) if k not in keys]
    out = []
    for key in keys:
        sec = doc.get(key)
        if sec is None:
            continue
        if not isinstance(sec, dict) or not isinstance(sec.get('ros__parameters'), dict):
            raise ParamError(f'{path}: section {key!r} must contain a ros__parameters mapping')
        out.append((key, sec['ros__parameters']))
    return out


def read_ros_params(path: str, node_name: Optional[str] = None, wildcard: bool = True,
                    required: bool = True) -> Dict[str, Any]:
    """Merge the ``ros__parameters`` of ``/**`` and ``node_name`` sections of a params file.

    Node-specific values override the wildcard section, as ``--params-file`` does.
    ``wildcard=False`` reads the node's sections only; ``required=False`` returns {}
    where the file has none (else a one-line ParamError).
    """
    sections = read_sections(path, [node_name] if node_name else [], wildcard)
    if required and not sections:
        doc = load_params_yaml(path)
        raise ParamError(
            f'{path}: no ros__parameters for {node_name or "/**"} '
            f'(sections present: {", ".join(map(str, doc)) or "none"})')
    merged: Dict[str, Any] = {}
    for _, params in sections:
        merged.update(params)
    return merged


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
    return read_ros_params(shipped_config(name), node, wildcard=node is None)


def shipped_defaults(name: str, node: Optional[str] = None) -> Dict[str, Any]:
    """Return the defaults a shipped params file gives: its ``/**`` or ``/**/<node>`` section.

    The one home of every default value: ``config/<name>`` as shipped (a copy; read once).
    ``node=None`` reads the wildcard section, else only the node's own sections.
    """
    return dict(_shipped_section(name, node))


def shipped_checked(specs: Mapping[str, Any], name: str, node: Optional[str] = None
                    ) -> Dict[str, Any]:
    """Return the values of ``specs`` in the shipped ``config/<name>`` section, each checked."""
    values = shipped_defaults(name, node)
    return {k: specs[k].check(k, v, f'config/{name}') for k, v in values.items() if k in specs}


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


__all__ = ['load_params_yaml', 'WILDCARD_SECTIONS', 'node_sections', 'read_sections',
           'read_ros_params', 'PACKAGE', 'SOURCE_CONFIG', 'prefixes', 'shipped_config',
           'shipped_defaults', 'shipped_checked', 'share_directory']
