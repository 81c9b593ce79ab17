"""Typed, validated ERVA parameters (paper Table I) loaded from a ROS 2 parameter file.

The parameter file is an ordinary ROS 2 ``--params-file`` YAML::

    /**:
      ros__parameters:
        M_s: 250.0
        ...

Every node reads its own section (or ``/**``) so the same file configures the
plant simulator, the NMPC and the offline tools.  Validation happens once, at
load, and a bad value raises :class:`ParamError` whose message is one line naming
the key, the value and the allowed range.
"""

from dataclasses import dataclass, fields, replace
from typing import Any, Collection, Dict, Optional

# The params-file readers live in config; named here too, where their callers find them.
from erva_ros.core.settings.files import (load_params_yaml, node_sections,  # noqa: F401
                                          read_ros_params, read_sections, shipped_config,
                                          WILDCARD_SECTIONS)
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.settings.specs import Number, ParamError, unknown_parameters


#: The one numeric spec (``Spec`` is its historical name): see :mod:`erva_ros.core.settings.specs`.
Spec = Number


# Values printed in paper Table I.
PAPER_VALUES: Dict[str, float] = {
    'M_s': 250.0, 'M_us': 35.0, 'k_t': 150e3, 'k_s': 55e3,
    'c': 70.71, 'k_d': 24.09e3, 'l': 0.16, 'c_e0': 10e3,
    'm_d': 129.78, 'm_r': 14.42, 'm_b': 21.31, 'epsilon': 0.1,
}


@dataclass(frozen=True)
class ERVAParams:
    """Physical parameters of the ERVA quarter car, SI units (paper Table I)."""

    M_s: float = PAPER_VALUES['M_s']
    M_us: float = PAPER_VALUES['M_us']
    k_t: float = PAPER_VALUES['k_t']
    k_s: float = PAPER_VALUES['k_s']
    c: float = PAPER_VALUES['c']
    k_d: float = PAPER_VALUES['k_d']
    l: float = PAPER_VALUES['l']  # noqa: E741 -- the paper's symbol
    c_e0: float = PAPER_VALUES['c_e0']
    m_d: float = PAPER_VALUES['m_d']
    m_r: float = PAPER_VALUES['m_r']
    m_b: float = PAPER_VALUES['m_b']
    epsilon: float = PAPER_VALUES['epsilon']

    @property
    def m_x(self) -> float:
        """Lumped inertia of the linear benchmark, m_x = m_b + m_r + m_d (paper §III.B)."""
        return self.m_b + self.m_r + self.m_d

    def with_(self, **kw: float) -> 'ERVAParams':
        """Return a validated copy with some values replaced."""
        return validate_erva(dict(self.as_dict(), **kw), source='override')

    def as_dict(self) -> Dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def validate_erva(values: Dict[str, Any], source: str = '') -> ERVAParams:
    """Validate a mapping of physical parameters; every key of ERVA_SPECS is required."""
    where = f'{source}: ' if source else ''
    out = {}
    for key, spec in ERVA_SPECS.items():
        if key not in values:
            raise ParamError(
                f'{where}missing parameter {key!r} (expected {spec.describe()}, {spec.doc})')
        out[key] = spec.check(key, values[key], source)
    return ERVAParams(**out)


def default_params_file() -> str:
    """Path of the shipped paper parameter file (source tree or installed share dir)."""
    return shipped_config('erva_paper.yaml', 'pass --params FILE')


#: Keys ROS itself reads from a params file's sections: never an erva parameter, never a typo.
ROS_BUILTINS = ('use_sim_time', 'qos_overrides', 'start_type_description_service')


def load_erva_params(path: Optional[str] = None, node_name: Optional[str] = None,
                     others: Collection[str] = ()) -> ERVAParams:
    """Load and validate the physical ERVA parameters from a ROS params file.

    A key that is neither a physical parameter, nor one of ``others`` (what else a shared
    file may hold, e.g. the live parameters of an `erva run` session file), nor ROS's
    own (:data:`ROS_BUILTINS`) is a one-line ParamError naming the closest known key:
    it was silently ignored before, so a misspelt parameter kept its default.
    """
    path = path or default_params_file()
    values = read_ros_params(path, node_name)
    unknown = set(values) - set(ERVA_SPECS) - set(others) - set(ROS_BUILTINS)
    if unknown:
        raise unknown_parameters(unknown, [*ERVA_SPECS, *others], path)
    return validate_erva(values, source=path)


def load_section(path: Optional[str], node_name: Optional[str] = None) -> Dict[str, Any]:
    """Raw merged ``ros__parameters`` for ``node_name`` from ``path`` (default paper file)."""
    return read_ros_params(path or default_params_file(), node_name)


def paper_params() -> ERVAParams:
    """Return the paper's Table I values."""
    return ERVAParams()


__all__ = ['ParamError', 'Spec', 'ERVA_SPECS', 'PAPER_VALUES', 'ERVAParams',
           'validate_erva', 'WILDCARD_SECTIONS', 'node_sections', 'read_sections',
           'read_ros_params', 'ROS_BUILTINS', 'load_erva_params', 'load_section',
           'default_params_file', 'paper_params', 'replace']
