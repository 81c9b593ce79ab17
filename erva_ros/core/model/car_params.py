"""The whole car's parameters: a published body and four ERVA corners (docs/car.md).

A ROS 2 parameter file (``config/car.yaml``) gives the body -- mass, pitch and roll inertia,
where the axles and wheels are -- and the unsprung mass of each axle, as a published
full-car set states them; each corner's ERVA device (spring, tyre, absorber) comes from the
quarter car's file (``config/erva_paper.yaml``, the paper's Table I), so Table I has one
home.  A corner may differ from it: a mapping ``fl:``, ``fr:``, ``rl:`` or ``rr:`` (or a
dotted key ``rl.k_s``) sets that corner's own values::

    /**:
      ros__parameters:
        M: 965.0
        ...
        rr:
          k_s: 50000.0

Validation happens once, at load: a bad value is a one-line :class:`ParamError` naming the
key and its allowed range, as for the quarter car (erva_ros/core/model/params.py).
"""

from dataclasses import dataclass, replace
from typing import Any, Dict, Optional, Tuple

from erva_ros.core.settings.files import shipped_config
from erva_ros.core.model.params import ERVAParams, load_erva_params, read_ros_params, ROS_BUILTINS
from erva_ros.core.settings.erva import ERVA_SPECS
from erva_ros.core.settings.specs import check_all, Number, ParamError, unknown_parameters

#: The corners in the order of every per-corner vector (u, w, outputs): front left, front
#: right, rear left, rear right.
CORNERS = ('FL', 'FR', 'RL', 'RR')

#: The body and the axles (a published full-car set; ISO 8855 axes: x forward, y left).
BODY_SPECS: Dict[str, Number] = {
    'M': Number(1.0, 1e4, 'kg', 'body (sprung) mass'),
    'I_theta': Number(0.0, 1e5, 'kg m^2', 'pitch inertia of the body about its centre of '
                      'gravity', lo_open=True),
    'I_phi': Number(0.0, 1e5, 'kg m^2', 'roll inertia of the body about its centre of '
                    'gravity', lo_open=True),
    'l_f': Number(0.0, 10.0, 'm', 'centre of gravity to the front axle', lo_open=True),
    'l_r': Number(0.0, 10.0, 'm', 'centre of gravity to the rear axle', lo_open=True),
    't_f': Number(0.0, 5.0, 'm', 'front track width', lo_open=True),
    't_r': Number(0.0, 5.0, 'm', 'rear track width', lo_open=True),
    'M_u_f': Number(2.0, 2000.0, 'kg', 'unsprung mass of the front axle (both wheels)'),
    'M_u_r': Number(2.0, 2000.0, 'kg', 'unsprung mass of the rear axle (both wheels)'),
}

#: What a corner section may set: the ERVA device and tyre (Table I's keys) and the wheel's
#: own unsprung mass.  M_s is not one: the body is the car's.
CORNER_KEYS = ('M_us', 'k_t', 'k_s', 'c', 'k_d', 'l', 'c_e0', 'm_d', 'm_r', 'm_b', 'epsilon')


@dataclass(frozen=True)
class CarParams:
    """The whole car, SI units: the body (ISO 8855 axes) and its four corners.

    ``corners`` are the FL, FR, RL, RR quarter cars: each one's device, tyre and unsprung
    mass, and as M_s the corner's static share of the body's mass (what a quarter-car model
    of that corner uses).  The car model takes the body from M, I_theta and I_phi and never
    reads a corner's M_s.
    """

    M: float
    I_theta: float
    I_phi: float
    l_f: float
    l_r: float
    t_f: float
    t_r: float
    corners: Tuple[ERVAParams, ERVAParams, ERVAParams, ERVAParams]

    def positions(self) -> Tuple[Tuple[float, float], ...]:
        """Return (x_i, y_i) of each corner's strut from the centre of gravity (m), FL..RR."""
        return ((self.l_f, self.t_f / 2), (self.l_f, -self.t_f / 2),
                (-self.l_r, self.t_r / 2), (-self.l_r, -self.t_r / 2))

    def static_share(self, i: int) -> float:
        """Return the body mass corner ``i`` carries at rest (kg).

        M·l_r/(2L) at the front, M·l_f/(2L) at the rear, L = l_f + l_r.
        """
        far = self.l_r if i < 2 else self.l_f
        return self.M * far / (2 * (self.l_f + self.l_r))


def _corner_values(values: Dict[str, Any], source: str) -> Dict[str, Dict[str, Any]]:
    """Split per-corner values (``fl: {...}`` or ``fl.k_s``) from the body's."""
    out: Dict[str, Dict[str, Any]] = {c: {} for c in CORNERS}
    for key, value in values.items():
        head, _, tail = str(key).partition('.')
        corner = head.upper()
        if corner not in CORNERS or head != head.lower():
            continue
        if tail:
            out[corner][tail] = value
        elif isinstance(value, dict):
            out[corner].update(value)
        else:
            where = f'{source}: ' if source else ''
            raise ParamError(f'{where}parameter {key!r} must be a mapping of corner '
                             f'parameters ({", ".join(CORNER_KEYS)}), got {value!r}')
    for corner, given in out.items():
        unknown = set(map(str, given)) - set(CORNER_KEYS)
        if unknown:
            raise unknown_parameters(unknown, CORNER_KEYS, source,
                                     f'parameter(s) of corner {corner.lower()}:')
    return out


def validate_car(values: Dict[str, Any], device: ERVAParams, source: str = '') -> CarParams:
    """Validate a car's values; every body key is required, corners default to ``device``."""
    where = f'{source}: ' if source else ''
    corners = {c.lower() for c in CORNERS}
    unknown = {k for k in map(str, values) if k.partition('.')[0] not in corners}
    unknown -= set(BODY_SPECS) | set(ROS_BUILTINS)
    if unknown:
        raise unknown_parameters(unknown, [*BODY_SPECS, *corners], source)
    missing = [key for key in BODY_SPECS if key not in values]
    if missing:
        spec = BODY_SPECS[missing[0]]
        raise ParamError(f'{where}missing parameter {missing[0]!r} (expected '
                         f'{spec.describe()}, {spec.doc})')
    body = check_all(BODY_SPECS, {key: values[key] for key in BODY_SPECS}, source)
    own = _corner_values(values, source)
    built = []
    for i, corner in enumerate(CORNERS):
        merged = dict(device.as_dict(), M_us=body['M_u_f' if i < 2 else 'M_u_r'] / 2)
        for key, value in own[corner].items():
            merged[key] = ERVA_SPECS[key].check(f'{corner.lower()}.{key}', value, source)
        built.append(ERVAParams(**merged))
    car = CarParams(body['M'], body['I_theta'], body['I_phi'], body['l_f'], body['l_r'],
                    body['t_f'], body['t_r'], tuple(built))
    shares = tuple(replace(c, M_s=car.static_share(i)) for i, c in enumerate(built))
    return replace(car, corners=shares)


def default_car_file() -> str:
    """Path of the shipped car file (source tree or installed share directory)."""
    return shipped_config('car.yaml', 'pass the car file')


def load_car_params(path: Optional[str] = None, erva_path: Optional[str] = None,
                    node_name: Optional[str] = None) -> CarParams:
    """Load and validate the car; a one-line ParamError if anything is bad.

    The body from ``path`` (default config/car.yaml), each corner's device from
    ``erva_path`` (default config/erva_paper.yaml, the paper's Table I).
    """
    path = path or default_car_file()
    device = load_erva_params(erva_path, node_name)
    return validate_car(read_ros_params(path, node_name), device, source=path)


__all__ = ['CORNERS', 'BODY_SPECS', 'CORNER_KEYS', 'CarParams', 'validate_car',
           'default_car_file', 'load_car_params']
