"""The controller's settings: every key's range, unit, meaning (config/nmpc.yaml's defaults).

The one table of the allowed values of ``nmpc_node`` and of every controller
(core/controllers/settings.py validates with it, nmpc_node declares its descriptors
from it).
"""

from typing import Any, Dict

from erva_ros.core.settings.loop import COMMAND_DELAY_SPEC, TS_SPEC
from erva_ros.core.settings.specs import Choice, Flag, Integer, Number

#: Control laws understood by make_controller (and `erva sim --controller`).
CONTROLLER_NAMES = ('passive', 'skyhook', 'no_preview', 'preview', 'preview_long')
#: Signals that make_controller also builds, for identification: they ignore the state
#: (erva_ros/core/controllers/excite.py), so the studies of control laws leave them out.
EXCITATION_NAMES = ('excite',)
#: Excitation signals of the ``excite`` controller.
EXCITE_SIGNALS = ('prbs', 'chirp')
#: Stage-cost variants of the NMPC (see erva_ros.core.controllers.ocp).
COST_KINDS = ('paper', 'continuous')
#: NMPC solvers: 'sqp' = real-time SQP (one CasADi Function), 'ipopt' = converged reference.
SOLVER_KINDS = ('sqp', 'ipopt')
#: Terminal costs of the continuous NMPC cost (erva_ros/core/controllers/ocp.py passive_tail).
TERMINAL_COSTS = ('passive', 'none')
#: Reduced Hessians of the real-time SQP (erva_ros/core/controllers/sqp.py).
HESSIANS = ('exact', 'gauss_newton')
#: codegen: auto = compile when a C compiler is on PATH (else run the CasADi VM).
CODEGEN_MODES = ('auto', 'on', 'off')
#: How the no-preview NMPC predicts the road: hold the last measured height, or zero.
ROAD_PREDICTIONS = ('hold', 'zero')
#: What follows a failed solve: the previous plan shifted while it lasts, then passive
#: c_e0 (plan), or passive c_e0 at once (passive).  erva_ros/core/controllers/base.py.
FALLBACKS = ('plan', 'passive')

#: Node name whose section of the params file holds the controller settings.
NODE_NAME = 'nmpc_node'

#: Numeric settings: allowed range, unit and meaning (reused for ROS descriptors).
NUMERIC_SPECS: Dict[str, Number] = {
    'horizon': Integer(1, 200, 'steps', 'prediction horizon N (paper: 10)'),
    'ts': TS_SPEC,
    'alpha1': Number(0.0, 1e6, '-', 'comfort weight alpha1 on chassis acceleration (eq. (12))',
                     live=True),
    'alpha2': Number(0.0, 1e6, '-', 'energy weight alpha2 on harvested power (eq. (12))',
                     live=True),
    'u_min': Number(0.0, 1e6, 'Ns/m', 'lower bound of the electrical damping c_e', live=True),
    'u_max': Number(0.0, 1e6, 'Ns/m', 'upper bound of the electrical damping c_e', lo_open=True,
                    live=True),
    'max_iter': Integer(1, 50, 'iterations', 'real-time SQP: most iterations per sample'),
    'sqp_tol': Number(0.0, 1.0, '-', 'real-time SQP: stop when an iteration is predicted to '
                      'gain less than this share of the objective', lo_open=False),
    'ipopt_max_iter': Integer(1, 100000, 'iterations', 'IPOPT iteration limit (reference)'),
    'ipopt_starts': Integer(1, 4, 'starts', 'IPOPT reference: converge from the warm start, '
                            '+ constant c_e0, + first move at u_max, + at u_min; keep the best'),
    'time_budget_s': Number(0.0, 10.0, 's', 'real-time SQP: a solve slower than this is '
                            'counted late (its plan is still used)', live=True),
    'command_delay_s': COMMAND_DELAY_SPEC,
    'collocation_degree': Integer(1, 6, '-', 'Radau collocation points per interval (model)'),
    'long_steps': Integer(0, 200, 'steps', 'preview_long: coarse intervals after the first N'),
    'long_step_s': Number(1e-3, 1.0, 's', 'preview_long: length of a coarse interval'),
    'long_max_iter': Integer(1, 50, 'iterations', 'preview_long: real-time SQP: most '
                             'iterations per sample (an iteration costs 3-4x preview\'s)'),
    'terminal_weight': Number(0.0, 1e6, '-', 'preview_long: weight of the terminal energy cost'),
    'excite_bit_s': Number(1e-3, 10.0, 's', 'excite, prbs: length of one bit (a multiple of '
                           'ts); flat spectrum to about 0.44 / excite_bit_s Hz'),
    'excite_seed': Integer(0, 2 ** 31 - 1, '-', 'excite, prbs: start of the sequence'),
    'excite_f0_hz': Number(0.0, 1e3, 'Hz', 'excite, chirp: start frequency', lo_open=True),
    'excite_f1_hz': Number(0.0, 1e3, 'Hz', 'excite, chirp: end frequency (< 1 / (2 ts))',
                           lo_open=True),
    'excite_sweep_s': Number(0.0, 3600.0, 's', 'excite, chirp: duration of one sweep '
                             '(repeated)', lo_open=True),
}
#: Settings that must be whole numbers.
INTEGER_KEYS = frozenset(k for k, spec in NUMERIC_SPECS.items() if isinstance(spec, Integer))
#: String settings and their allowed values.
CHOICE_SPECS: Dict[str, Choice] = {
    'controller': Choice(CONTROLLER_NAMES + EXCITATION_NAMES,
                         'control law, or excite (an identification signal)'),
    'excite_signal': Choice(EXCITE_SIGNALS, 'excite: the signal driving c_e over '
                            '[u_min, u_max]: prbs (pseudo-random binary) or chirp '
                            '(logarithmic sweep)'),
    'cost': Choice(COST_KINDS,
                   'NMPC stage cost: paper (discrete, eq. (14)) or continuous (eq. (12))'),
    'solver': Choice(SOLVER_KINDS,
                     'NMPC solver: sqp (real-time SQP) or ipopt (converged reference)'),
    'road_prediction': Choice(ROAD_PREDICTIONS,
                              'no_preview road model: hold last height or zero', live=True),
    'fallback': Choice(FALLBACKS, 'after a failed solve: the previous plan shifted while it '
                       'lasts, then the passive c_e0 (plan), or c_e0 at once (passive)',
                       live=True),
    'long_cost': Choice(COST_KINDS, 'stage cost of preview_long (paper or continuous)'),
    'terminal_cost': Choice(TERMINAL_COSTS, 'continuous cost: value of the state at the '
                            'horizon end as if the passive damping took over (passive) or '
                            'none (the paper\'s NMPC)'),
    'hessian': Choice(HESSIANS, 'real-time SQP Hessian: exact (Lagrangian) or gauss_newton '
                                '(comfort Gauss-Newton + exact economic term)'),
    'codegen': Choice(CODEGEN_MODES, 'compile the real-time solver\'s model functions to C '
                                     '(auto: when cc/gcc is on PATH; cached in '
                                     '~/.cache/erva_ros)'),
}
#: On/off settings.
FLAG_SPECS: Dict[str, Flag] = {
    'use_preview': Flag('NMPC preview and preview_long: plan on the road preview (false: the '
                        'road predicted as road_prediction says, as no_preview does)',
                        live=True),
}
#: Every setting's spec (erva_ros.core.settings.specs): the one table of allowed values.
SPECS: Dict[str, Any] = {**NUMERIC_SPECS, **CHOICE_SPECS, **FLAG_SPECS}
