"""Compile, before anything starts, every function a configuration's processes will load.

A node builds its core from its parameters (the NMPC, the plant, the EKF, the simulated
ECU's plant) and loads the compiled C of its CasADi functions from the cache
(:mod:`erva_ros.core.model.codegen`).  On an empty cache it would compile them itself, for up
to a minute, while the other nodes' start-up timeouts run out.  Here each such core is a
:class:`Target`, built as its process builds it; :func:`warm`:

1. skips a target whose libraries are all there (a manifest per target, keyed by its
   parameters, the core's source code, the compiler flags and CasADi's version: a warm
   cache costs milliseconds, and no process starts);
2. builds the others in parallel processes, one fresh process per target, to learn which
   functions they load and which are missing (:func:`erva_ros.core.model.codegen.collecting`);
3. compiles the missing ones, all targets together, largest first, as many at a time as
   there are CPUs (:func:`erva_ros.core.model.codegen.run_jobs`: atomic, locked, retried once),
   with one progress line per target ("compiling the NMPC (preview, erva model) (first
   run on this machine, ~14 s)").

:func:`shipped_targets` are the shipped configurations (``erva compile``);
:func:`session_targets` are the cores of one `erva run` session, from the same values
its params file gives the nodes.
"""

from concurrent.futures import as_completed, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
import hashlib
import os
import pickle
import sys
import tempfile
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Set, Tuple, Union

import casadi as ca

import erva_ros
from erva_ros.core.controllers import make_controller
from erva_ros.core.hil.settings import load_ecu_sim_section, load_estimator_section
from erva_ros.core.model import codegen
from erva_ros.core.controllers.settings import ControllerSettings, load_controller_settings
from erva_ros.core.model.estimator import ExtendedKalmanFilter
from erva_ros.core.model.plant import PlantSimulator
from erva_ros.core.model.quarter_car import make_model
from erva_ros.core.model.road_estimator import RoadEKF
from erva_ros.core.settings.loop import MODEL_KINDS
from erva_ros.core.model.params import ERVAParams, load_erva_params, ParamError, validate_erva

#: Controllers built on the real-time SQP: the only controllers with compiled functions.
NMPC_CONTROLLERS = ('no_preview', 'preview', 'preview_long')
#: The models of the shipped configurations: every one.
MODELS = MODEL_KINDS
#: The command delay (a share of Ts) the "with a command delay" NMPCs are built with: any
#: d > 0 gives the same functions.
DELAYED_S = 0.25
#: Where the per-target manifests live in the cache directory.
MANIFESTS = 'targets'


@dataclass(frozen=True)
class Target:
    """One core a process builds from its parameters: what it compiles depends on them.

    ``role``: ``nmpc`` (nmpc_node, `erva sim`, `erva bench`: make_controller with
    ``settings``), ``plant`` (plant_sim_node: PlantSimulator at ``ts``), ``ekf``
    (state_estimator_node: the EKF at ``ts``, stable up to ``u_max``), ``road_ekf``
    (state_estimator_node estimating the road, `--preview map:`: the road EKF, likewise)
    or ``ecu_plant`` (`erva ecu-sim`: the plant at the ECU period ``ts`` with its
    ``latch_s`` profile).
    """

    role: str
    params: ERVAParams
    model: str = 'erva'
    ts: float = 0.02
    settings: Optional[ControllerSettings] = None
    u_max: float = 0.0
    latch_s: float = 0.0

    @property
    def codegen(self) -> str:
        """Return the ``codegen`` setting the process builds this core with."""
        return self.settings.codegen if self.role == 'nmpc' else 'auto'

    @property
    def label(self) -> str:
        """Return what the progress line calls it, e.g. ``the NMPC (preview, erva model)``."""
        if self.role == 'nmpc':
            s = self.settings
            delay = ', with a command delay' if s.command_delay_s else ''
            return f'the NMPC ({s.controller}, {self.model} model{delay})'
        if self.role == 'ekf':
            return f'the EKF ({self.model} model)'
        if self.role == 'road_ekf':
            return f'the road EKF ({self.model} model)'
        if self.role == 'ecu_plant':
            return f"the simulated ECU's plant ({self.model} model)"
        return f'the plant ({self.model} model)'

    @property
    def compiles(self) -> bool:
        """Return whether building it may compile anything (a solver or model to C)."""
        if self.role == 'nmpc' and (self.settings.controller not in NMPC_CONTROLLERS
                                    or self.settings.solver != 'sqp'):
            return False
        return codegen.use_codegen(self.codegen)

    def build(self) -> Any:
        """Build the core as its process does (compiling or loading its functions)."""
        model = make_model(self.params, self.model)
        if self.role == 'nmpc':
            return make_controller(self.settings.controller, model, self.settings)
        if self.role == 'ekf':
            return ExtendedKalmanFilter(model, self.ts, u_max=self.u_max)
        if self.role == 'road_ekf':
            # Its functions depend on the road model's kind, not on its noise levels: the
            # node's random walk (core/loop/road_loop.py) is RoadEKF's default.
            return RoadEKF(model, self.ts, u_max=self.u_max)
        plant = PlantSimulator(model, self.ts)
        if self.role == 'ecu_plant':    # as EcuSimCore: one period of latch_s pieces
            n = int(round(self.ts / self.latch_s))
            plant.integrate_profile([self.params.c_e0] * n, [0.0] * (n + 1))
        return plant


def nmpc_target(params: ERVAParams, settings: ControllerSettings, model: str = 'erva'
                ) -> Target:
    """Return the NMPC of ``settings`` (its ``controller``) on ``model``."""
    return Target('nmpc', params, model, settings.ts, settings)


def session_targets(erva: Union[ERVAParams, Mapping[str, float]], settings: ControllerSettings,
                    live: Mapping[str, Any], ecu: str = 'none', hil_file: Optional[str] = None,
                    road_estimated: bool = False) -> List[Target]:
    """Return the cores of an `erva run` session: what its nodes will build and load.

    ``erva``, ``settings`` and ``live`` are the session's effective values (those of the
    params file the nodes read); ``ecu`` 'virtual' replaces plant_sim_node by the
    simulated ECU and the estimator (their settings from ``hil_file``, default
    config/hil.yaml), whose filter is the road EKF when ``road_estimated`` (a map's
    preview).
    """
    params = erva if isinstance(erva, ERVAParams) else validate_erva(dict(erva), 'session')
    model, ts = live['model'], float(live['ts'])
    out = [nmpc_target(params, settings, model)]
    if ecu == 'none':
        out.append(Target('plant', params, model, ts))
    else:
        out.append(Target('road_ekf' if road_estimated else 'ekf', params, model, ts,
                          u_max=load_estimator_section(hil_file)['u_max']))
        out.append(Target('ecu_plant', params, model, ts,
                          latch_s=load_ecu_sim_section(hil_file)['latch_s']))
    return out


def shipped_targets(params_file: Optional[str] = None, nmpc_file: Optional[str] = None,
                    hil_file: Optional[str] = None, models: Sequence[str] = MODELS
                    ) -> List[Target]:
    """Return every core the shipped configurations build (``erva compile``).

    On each model the NMPCs (preview_long, preview, no_preview) of config/nmpc.yaml, without
    and with a command delay (config/live.yaml's ``command_delay_s``: any d > 0 loads the
    same functions, d is a parameter of the OCP), and the plant; the EKF and the simulated
    ECU's plant of the HIL loop (config/hil.yaml), and the road EKF of a map's preview.
    Other files may replace the shipped ones.
    """
    params = load_erva_params(params_file)
    base = load_controller_settings(nmpc_file)
    out: List[Target] = []
    for model in models:
        for delay in (0.0, DELAYED_S * base.ts):
            for name in ('preview_long', 'preview', 'no_preview'):   # the largest first
                settings = load_controller_settings(
                    nmpc_file, {'controller': name, 'command_delay_s': delay})
                out.append(nmpc_target(params, settings, model))
        out.append(Target('plant', params, model, base.ts))
    # The HIL loop (config/hil.yaml calibrates the ERVA's generator): estimator and ECU.
    out += session_targets(params, base, {'model': 'erva', 'ts': base.ts}, 'virtual',
                           hil_file)[1:]
    out += session_targets(params, base, {'model': 'erva', 'ts': base.ts}, 'virtual',
                           hil_file, road_estimated=True)[1:2]
    return out


@dataclass
class TargetResult:
    """What :func:`warm` did for one target."""

    label: str
    status: str          # cached | compiled | missing (--check) | failed | uncompiled
    functions: int = 0   # compiled functions the target loads
    missing: int = 0     # of them, not in the cache before
    error: str = ''

    def as_dict(self) -> Dict[str, Any]:
        """Return the result as plain values (for --json)."""
        return {'target': self.label, 'status': self.status, 'functions': self.functions,
                'missing': self.missing, 'error': self.error}


@dataclass
class WarmResult:
    """What :func:`warm` did: per target, the functions compiled, the time and the cache."""

    targets: List[TargetResult]
    compiled: int
    seconds: float
    cache_dir: str
    compiler: Optional[str]
    errors: List[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """Return True if nothing failed (and, for a check, nothing is missing)."""
        return all(t.status in ('cached', 'compiled', 'uncompiled') for t in self.targets)

    def as_dict(self) -> Dict[str, Any]:
        """Return the result as plain values (for --json)."""
        return {'ok': self.ok, 'compiled': self.compiled, 'seconds': round(self.seconds, 2),
                'cache_dir': self.cache_dir, 'compiler': self.compiler,
                'targets': [t.as_dict() for t in self.targets]}


#: Settings that are values of the NMPC's compiled functions (OCP parameters) or of the
#: Python loop around them, not part of their code: a sweep of them is one target.  Only
#: whether a command delay is modelled changes the OCP, not its value.  (Were one of them
#: ever compiled in, a node would still find its library missing and compile it.)
NOT_COMPILED_IN = ('alpha1', 'alpha2', 'max_iter', 'long_max_iter', 'sqp_tol', 'time_budget_s',
                   'ipopt_max_iter', 'ipopt_starts', 'road_prediction', 'use_preview',
                   'fallback')


def _target_key(target: Target, salt: str) -> str:
    """Return the key of a target's manifest (see the module doc)."""
    if target.settings is not None:
        defaults = ControllerSettings()
        # no_preview is the preview's OCP with a held road as its parameter: one solver.
        controller = 'preview' if target.settings.controller == 'no_preview' else \
            target.settings.controller
        target = replace(target, settings=replace(
            target.settings, controller=controller,
            command_delay_s=float(target.settings.command_delay_s > 0),
            **{k: getattr(defaults, k) for k in NOT_COMPILED_IN}))
    text = f'{target!r}|{salt}|{ca.__version__}|{codegen.code_fingerprint()}'
    return hashlib.sha1(text.encode()).hexdigest()[:20]


def _manifest(cache: str, key: str) -> str:
    return os.path.join(cache, MANIFESTS, f'{key}.txt')


def _cached_libs(cache: str, key: str) -> Optional[List[str]]:
    """Return the libraries a target's manifest lists if they are all there, else None."""
    try:
        with open(_manifest(cache, key), encoding='utf-8') as fh:
            libs = [os.path.join(cache, line.strip()) for line in fh if line.strip()]
    except OSError:
        return None
    return libs if all(os.path.isfile(lib) for lib in libs) else None


def _write_manifest(cache: str, key: str, libs: Sequence[str]) -> None:
    path = _manifest(cache, key)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f'{path}.{os.getpid()}.tmp'
    with open(tmp, 'w', encoding='utf-8') as fh:
        fh.write(''.join(os.path.basename(lib) + '\n' for lib in libs))
    os.replace(tmp, path)


def plan_target(target: Target) -> codegen.Plan:
    """Build ``target`` without compiling (in a fresh process): what it loads and misses."""
    with codegen.collecting() as plan:
        target.build()
    return plan


def warm(targets: Sequence[Target], log: Optional[Callable[[str], None]] = None,
         workers: Optional[int] = None, check: bool = False) -> WarmResult:
    """Compile every function ``targets`` load that is not cached (see the module doc).

    ``log`` gets one line per target that compiles and one at the end (none when all is
    cached); ``workers`` processes plan and compile at a time (default: the CPUs);
    ``check`` only reports what is missing.  A failed compile does not raise: its target
    says ``failed`` with the compiler's message (its process would then compile again,
    or with ``codegen: auto`` run the function in CasADi's virtual machine).
    """
    say = log or (lambda line: None)
    t0 = time.monotonic()
    cache = codegen.codegen_cache_dir()
    tc = codegen.toolchain()
    cc, salt = tc.cc, tc.salt
    workers = max(1, workers or codegen._cpus())
    results: List[Optional[TargetResult]] = [None] * len(targets)
    keys: Dict[int, str] = {}
    todo: List[int] = []
    for i, target in enumerate(targets):
        if not target.compiles:
            results[i] = TargetResult(target.label, 'uncompiled')
            continue
        keys[i] = _target_key(target, salt)
        libs = _cached_libs(cache, keys[i])
        if libs is not None:
            results[i] = TargetResult(target.label, 'cached', len(libs))
        else:
            todo.append(i)
    compiled: Set[str] = set()
    errors: Dict[str, str] = {}
    if todo:
        first: Dict[str, int] = {}         # one plan per key (no_preview is preview's)
        for i in todo:
            first.setdefault(keys[i], i)
        planned = list(first.values())
        plans, compiled, errors = _plan_and_compile([targets[i] for i in planned], workers,
                                                    None if check else say)
        plan_of = {keys[i]: plan for i, plan in zip(planned, plans)}
        for i in todo:
            plan = plan_of[keys[i]]
            libs = sorted(set(plan.libs))
            missing = {j.lib for j in plan.jobs}
            failed = sorted({errors[lib] for lib in missing if lib in errors})
            status = ('failed' if failed else 'missing' if check and missing
                      else 'compiled' if missing else 'cached')
            results[i] = TargetResult(targets[i].label, status, len(libs), len(missing),
                                      failed[0] if failed else '')
            if status in ('compiled', 'cached'):
                _write_manifest(cache, keys[i], libs)
    if not check and any(r.status in ('cached', 'compiled') for r in results):
        codegen.ensure_record(tc.record)       # also for a cache an older erva filled
    seconds = time.monotonic() - t0
    if compiled:
        say(f'compiled {len(compiled)} function(s) in {seconds:.0f} s (cached in {cache})')
    return WarmResult(list(results), len(compiled), seconds, cache, cc,
                      sorted(set(errors.values())))


@dataclass
class CachedTarget:
    """What the cache holds for one codegen target (``erva compile --check``)."""

    record: codegen.TargetRecord
    parts: int                   # of the given configuration's parts that compile
    cached: Optional[int]        # of them, complete in the cache (None: another CPU's native)
    selected: bool               # the target runs use here (ERVA_CODEGEN_TARGET)

    @property
    def missing_here(self) -> List[str]:
        """Return the CPU features this machine lacks to run the target's code."""
        return self.record.missing_here()

    def as_dict(self) -> Dict[str, Any]:
        """Return the status as plain values (for --json)."""
        return {'target': self.record.target, 'tag': self.record.tag, 'cpu': self.record.cpu,
                'parts': self.parts, 'cached': self.cached, 'selected': self.selected,
                'runs_here': not self.missing_here, 'missing_features': self.missing_here}


def cached_targets(targets: Sequence[Target]) -> List[CachedTarget]:
    """Return, per codegen target in the cache, how many of ``targets`` it holds complete.

    From the manifests alone (milliseconds): a part whose manifest is missing counts as
    not cached.  A ``native`` target of another CPU cannot be keyed here (its key holds
    that CPU): its count is None.
    """
    cache = codegen.codegen_cache_dir()
    try:
        own = codegen.toolchain().record
    except codegen.TargetError:
        own = None
    here = f'{codegen.NATIVE}-{codegen.native_tag_suffix()}'
    parts = [t for t in targets if t.compiles]
    records = {r.tag: r for r in codegen.cached_records()}
    if own is not None:
        records.setdefault(own.tag, own)
    selected = own.tag if own is not None else ''
    out = []
    for record in sorted(records.values(), key=lambda r: r.tag):
        if record.tag.startswith(codegen.NATIVE + '-') and record.tag != here:
            count = None
        else:
            count = sum(_cached_libs(cache, _target_key(t, record.salt)) is not None
                        for t in parts)
        out.append(CachedTarget(record, len(parts), count, record.tag == selected))
    return out


def ensure_compiled(targets: Sequence[Target], log: Optional[Callable[[str], None]] = None
                    ) -> WarmResult:
    """Compile what ``targets`` load before their processes start or anything is timed.

    :func:`warm`, then a failure is one line through ``log`` where the target's
    ``codegen`` is ``auto`` (it runs uncompiled) and a one-line :class:`ParamError`
    where it is ``on``.  A codegen target this CPU cannot run is a
    :class:`~erva_ros.core.model.codegen.TargetError` first.
    """
    if any(t.compiles for t in targets):
        codegen.check_runs_here(codegen.toolchain())   # before compiling for nothing
    result = warm(targets, log)
    for target, res in zip(targets, result.targets):
        if res.status != 'failed':
            continue
        if target.codegen == 'on':
            raise ParamError(f'{target.label}: {res.error}')
        if log is not None:
            log(f'{target.label}: {res.error} (codegen: auto runs it uncompiled)')
    return result


def _plan_in_process(target: Target) -> codegen.Plan:
    """Return the plan of ``target`` from a fresh planning process (core/loop/plan_worker.py)."""
    with tempfile.TemporaryDirectory(prefix='erva_plan_') as tmp:
        source, destination = os.path.join(tmp, 'target'), os.path.join(tmp, 'plan')
        with open(source, 'wb') as fh:
            pickle.dump(target, fh, protocol=pickle.HIGHEST_PROTOCOL)
        package = os.path.dirname(os.path.dirname(os.path.abspath(erva_ros.__file__)))
        env = dict(os.environ)
        env['PYTHONPATH'] = os.pathsep.join(p for p in (package, env.get('PYTHONPATH')) if p)
        status, stderr = codegen.run_stoppable(
            [sys.executable, '-m', 'erva_ros.core.loop.plan_worker', source, destination], env)
        if status < 0 and codegen.stopped():
            raise KeyboardInterrupt
        if status != 0:
            lines = [ln for ln in stderr.splitlines() if ln.strip()]
            raise ParamError(f'planning {target.label} failed (status {status}): '
                             f'{lines[-1] if lines else "no message"}')
        with open(destination, 'rb') as fh:
            return pickle.load(fh)


def _plan_and_compile(targets: Sequence[Target], workers: int,
                      say: Optional[Callable[[str], None]]
                      ) -> Tuple[List[codegen.Plan], Set[str], Dict[str, str]]:
    """Plan each target in a fresh process; compile what is missing as plans come in.

    Returns the plans (in ``targets``' order), the libraries compiled and lib -> error.
    ``say`` None: plan only (a check).
    """
    plans: List[Optional[codegen.Plan]] = [None] * len(targets)
    submitted: Set[str] = set()
    compiled: Set[str] = set()
    errors: Dict[str, str] = {}

    def one(job: codegen.CompileJob) -> None:
        try:
            codegen.run_jobs([job], workers=1)
            compiled.add(job.lib)
        except ParamError as exc:
            errors[job.lib] = str(exc)

    threads = ThreadPoolExecutor(workers)
    planners = ThreadPoolExecutor(min(workers, len(targets)) or 1)
    try:
        futures = {planners.submit(_plan_in_process, t): i for i, t in enumerate(targets)}
        for done in as_completed(futures):
            i, plan = futures[done], done.result()
            plans[i] = plan
            new = sorted({j.lib: j for j in plan.jobs if j.lib not in submitted}.values(),
                         key=lambda j: -len(j.source))
            if say is None or not new:
                continue
            say(f'compiling {targets[i].label} (first run on this machine'
                f'{_expected(targets[i])})')
            submitted.update(j.lib for j in new)
            for job in new:
                threads.submit(one, job)
        threads.shutdown()     # in the try: Ctrl-C comes here once every plan is in
    except KeyboardInterrupt:
        # Ctrl-C: the planners and the compilers are ended (sessions of their own: the
        # terminal's SIGINT reaches only this process), no other starts (a queued one
        # would run at the interpreter's exit); what finished is in the cache.
        codegen.stop_compilers()
        planners.shutdown(wait=True, cancel_futures=True)
        threads.shutdown(wait=True, cancel_futures=True)
        raise
    finally:
        planners.shutdown(wait=False, cancel_futures=True)
    return plans, compiled, errors


#: Compiler time (CPU s, one core) of each NMPC's functions without a command delay (with
#: one: ~15 % more), measured on this project's machine (gcc 12, -O3 -march=native;
#: 2026-12-07, load 9-15, docs/tests.md): the progress line's rough figure.
REFERENCE_CPU_S = {('erva', 'preview'): 14, ('erva', 'preview_long'): 21,
                   ('benchmark', 'preview'): 7, ('benchmark', 'preview_long'): 12}


def _expected(target: Target) -> str:
    """Return ', ~N s' for an NMPC of the shipped horizon measured here, else ''."""
    s = target.settings
    if target.role != 'nmpc' or s.horizon != ControllerSettings.horizon:
        return ''
    name = 'preview' if s.controller == 'no_preview' else s.controller
    seconds = REFERENCE_CPU_S.get((target.model, name))
    return f', ~{seconds} s' if seconds else ''


__all__ = ['NMPC_CONTROLLERS', 'MODELS', 'Target', 'nmpc_target', 'session_targets',
           'shipped_targets', 'TargetResult', 'WarmResult', 'warm', 'CachedTarget',
           'cached_targets', 'ensure_compiled']
