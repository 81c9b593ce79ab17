"""The ERVA quarter car's physical parameters: ranges, units, meaning (paper Table I).

Defaults: config/erva_paper.yaml; the typed values: core/model/params.py (``ERVAParams``).
"""

from typing import Dict

from erva_ros.core.settings.specs import Number

# Physical parameters of the quarter car with ERVA (paper Table I, eq. (10)).
# Ranges are generous physical envelopes; they exist to catch unit and sign
# errors (a mass in tonnes, a negative stiffness), not to restrict design studies.
ERVA_SPECS: Dict[str, Number] = {
    'M_s': Number(1.0, 5000.0, 'kg', 'sprung mass (quarter of the body)'),
    'M_us': Number(1.0, 1000.0, 'kg', 'unsprung mass (wheel, hub, strut)'),
    'k_t': Number(1e3, 1e7, 'N/m', 'tyre vertical stiffness'),
    'k_s': Number(1e2, 1e7, 'N/m', 'suspension spring stiffness'),
    'c': Number(0.0, 1e5, 'Ns/m', 'parasitic viscous damping of the strut'),
    'k_d': Number(0.0, 1e7, 'N/m', 'torsion-spring stiffness, translational (k_d = kbar_d/l^2)'),
    'l': Number(0.0, 10.0, 'm/rad', 'ball-screw effective moment arm (z = l*theta)', lo_open=True),
    'c_e0': Number(0.0, 1e6, 'Ns/m', 'passive electrical damping (c_e = kappa^2/R)'),
    'm_d': Number(0.0, 1e4, 'kg', 'sliding-mass equivalent mass (m r0^2 / l^2)'),
    'm_r': Number(0.0, 1e4, 'kg', 'rotor equivalent mass (J_r / l^2)'),
    'm_b': Number(0.0, 1e4, 'kg', 'ball-screw + housing equivalent mass (J_b / l^2)'),
    'epsilon': Number(0.0, 10.0, '-', 'inertia nonlinearity epsilon = lambda / r0'),
}
