"""Electrical damping c_e ↔ generator load resistance ↔ PWM duty cycle, with hardware limits.

The paper idealises the harvesting circuit as a resistance R(t) and gets the
electrical damping c_e(t) = κ̄²/R(t) (§II.B, after eq. (9)); referred to the
suspension stroke with the ball-screw arm l (eq. (10): κ = κ̄/l) this is

    c_e = κ² / R,          R = R_int + R_load                          (1)

with κ in N/A (= V·s/m), R_int the generator winding resistance and R_load what the
ECU's converter presents.  The ECU realises R_load with a PWM switch that connects
the generator to a low-resistance load R_sw for a fraction D (the duty cycle) of each
PWM period.  With the winding inductance neglected (as the paper does) the current
flows only while the switch is on, so the mean current is D·κv/(R_int + R_sw) and

    c_e = D · c_e,max,     c_e,max = κ² / (R_int + R_sw)               (2)
    R   = (R_int + R_sw) / D = κ² / c_e,   R_load = R − R_int          (3)

D = 0 is the open circuit (c_e = 0, R → ∞).  The duty is limited to
[duty_min, duty_max] (duty_max < 1 leaves an off-time to sample the back-emf), so
the hardware damping range is [duty_min, duty_max]·c_e,max; commands outside it are
clamped.  Measured signals of the ECU (``config/erva_ecu.dbc``):

    generator speed φ̇ = v_gen / l (rad/s),  back-emf V = κ·v_gen (V),
    mean current i = c_e·v_gen / κ (A),      so V·i = c_e·v_gen² = P (paper eq. (12)).

Defaults are illustrative (set them from the generator data sheet): κ = 120 N/A,
R_int = 0.4 Ω, R_sw = 0.2 Ω → c_e,max = 24 kNs/m, duty ∈ [0, 0.95] → c_e ∈
[0, 22.8] kNs/m, which contains the NMPC's default box [0, 20] kNs/m; the paper's
passive c_e0 = 10 kNs/m is D ≈ 0.417 (R ≈ 1.44 Ω).
"""

from dataclasses import asdict, dataclass
import math
from typing import Any, Dict, Mapping, Tuple

from erva_ros.core.settings.files import shipped_checked
from erva_ros.core.settings.hil import HARDWARE_SPECS
from erva_ros.core.settings.specs import ParamError

#: Defaults: the ecu_bridge_node section of the shipped config/hil.yaml (their one home).
DEFAULTS: Dict[str, float] = shipped_checked(HARDWARE_SPECS, 'hil.yaml', 'ecu_bridge_node')


@dataclass(frozen=True)
class GeneratorHardware:
    """Generator + PWM load switch: the c_e ↔ R ↔ duty mapping (module docstring (1)-(3))."""

    kappa_n_per_a: float = DEFAULTS['kappa_n_per_a']
    r_internal_ohm: float = DEFAULTS['r_internal_ohm']
    r_switch_ohm: float = DEFAULTS['r_switch_ohm']
    duty_min: float = DEFAULTS['duty_min']
    duty_max: float = DEFAULTS['duty_max']

    @property
    def c_e_full(self) -> float:
        """Return c_e at 100 % duty, κ²/(R_int + R_sw) in Ns/m (eq. (2))."""
        return self.kappa_n_per_a ** 2 / (self.r_internal_ohm + self.r_switch_ohm)

    @property
    def c_e_range(self) -> Tuple[float, float]:
        """Return the damping the hardware can apply, (c_e,min, c_e,max) in Ns/m."""
        return self.duty_min * self.c_e_full, self.duty_max * self.c_e_full

    def clamp_c_e(self, c_e: float) -> Tuple[float, bool]:
        """Return (c_e clamped to the hardware range, True if it had to be clamped)."""
        lo, hi = self.c_e_range
        v = min(max(c_e, lo), hi)
        return v, v != c_e

    def clamp_duty(self, duty: float) -> Tuple[float, bool]:
        """Return (duty clamped to [duty_min, duty_max], True if it had to be clamped)."""
        v = min(max(duty, self.duty_min), self.duty_max)
        return v, v != duty

    def duty_from_c_e(self, c_e: float) -> float:
        """Return the PWM duty D = c_e / c_e,full for a damping c_e in Ns/m (eq. (2))."""
        return c_e / self.c_e_full

    def c_e_from_duty(self, duty: float) -> float:
        """Return the damping c_e = D·c_e,full (Ns/m) that duty D applies (eq. (2))."""
        return duty * self.c_e_full

    def resistance_from_c_e(self, c_e: float) -> float:
        """Return the total circuit resistance R = κ²/c_e in Ω (inf for c_e = 0, eq. (1))."""
        return math.inf if c_e <= 0 else self.kappa_n_per_a ** 2 / c_e

    def load_resistance_from_c_e(self, c_e: float) -> float:
        """Return the load the converter presents, R_load = κ²/c_e − R_int in Ω (eq. (3))."""
        return self.resistance_from_c_e(c_e) - self.r_internal_ohm

    def current(self, c_e: float, v_gen: float) -> float:
        """Return the mean generator current i = c_e·v_gen/κ (A) at stroke velocity v_gen."""
        return c_e * v_gen / self.kappa_n_per_a

    def back_emf(self, v_gen: float) -> float:
        """Return the back-emf κ·v_gen (V) at generator velocity v_gen (m/s)."""
        return self.kappa_n_per_a * v_gen

    def force_from_current(self, current_a: float) -> float:
        """Return the generator force κ·i (N) on the stroke for a current i (A)."""
        return self.kappa_n_per_a * current_a

    def as_dict(self) -> Dict[str, float]:
        return asdict(self)


def validate_hardware(values: Mapping[str, Any], source: str = '') -> GeneratorHardware:
    """Validate hardware parameters (missing keys take the defaults); one-line errors."""
    out = {}
    for key, spec in HARDWARE_SPECS.items():
        out[key] = spec.check(key, values.get(key, DEFAULTS[key]), source)
    if out['r_internal_ohm'] + out['r_switch_ohm'] <= 0:
        raise ParamError(f'{source + ": " if source else ""}r_internal_ohm + r_switch_ohm '
                         'must be > 0 (the generator circuit needs a resistance)')
    if out['duty_min'] > out['duty_max']:
        raise ParamError(f'{source + ": " if source else ""}duty_min = {out["duty_min"]:g} '
                         f'is above duty_max = {out["duty_max"]:g}')
    return GeneratorHardware(**out)
