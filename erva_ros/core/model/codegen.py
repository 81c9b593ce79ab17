"""C code generation of CasADi Functions on hot paths (the NMPC's solver, the EKF).

``codegen`` settings: ``auto`` compiles when a C compiler is on PATH, ``on`` insists
(one-line error without one), ``off`` keeps CasADi's virtual machine.  A generated
Function is compiled once per target and cached by the hash of its source and flags, so
a changed model, parameter set or horizon gets its own library.  Each library is written
atomically under a lock, so a killed compile leaves nothing half-written and the next
run compiles only what is missing; ``erva compile`` (erva_ros.core.loop.warmup) fills the
cache for a whole configuration before any node starts.

The target (ERVA_CODEGEN_TARGET, GCC's ``-march``) is ``native`` by default: this CPU,
keyed by its model and feature flags, so a cache copied to another CPU never loads it.
A named target (``x86-64-v3``) builds for another machine, e.g. a vehicle PC; the cache
records which CPU features its code may use (:class:`TargetRecord`), and a library is
loaded only on a CPU that has them all.
"""

from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
import fcntl
import functools
import glob
import hashlib
import json
import os
import platform
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from typing import Any, Callable, Dict, FrozenSet, List, Optional, Sequence, Set, Tuple
import warnings

import casadi as ca
import numpy as np

from erva_ros.core.model.params import ParamError

#: C compiler flags of ``codegen``.  -O3: the NMPC solver's per-interval kernels run as
#: loops, which the optimiser speeds up (docs/nmpc.md); compiling it takes ~10 s.
CODEGEN_FLAGS = ('-O3', '-shared', '-fPIC')
#: The environment variable that names the CPU the compiled functions are built for, as
#: GCC's ``-march`` takes it: ``native`` (the default: this CPU), ``x86-64-v2``,
#: ``x86-64-v3``, ``x86-64-v4`` (the x86-64 psABI levels), or a CPU (``znver3``, ...).
TARGET_ENV = 'ERVA_CODEGEN_TARGET'
NATIVE = 'native'
#: GCC's ``-march`` names: lower case letters, digits, '-', '.' and '_'.
_TARGET_NAME = re.compile(r'[a-z0-9][a-z0-9._-]*')
#: Where the cache keeps one record per target it holds (:class:`TargetRecord`).
TARGET_RECORDS = 'cpu'


def codegen_cache_dir() -> str:
    """Return the directory of compiled functions (ERVA_CACHE_DIR, else ~/.cache/erva_ros)."""
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.environ.get('ERVA_CACHE_DIR') or os.path.join(base, 'erva_ros')


def c_compiler():
    """Return the C compiler codegen uses ($CC, cc or gcc), or None."""
    return os.environ.get('CC') or shutil.which('cc') or shutil.which('gcc')


class TargetError(ParamError):
    """The target of the compiled functions is unknown, or this CPU cannot run its code."""


def codegen_target() -> str:
    """Return the target the compiled functions are built for (ERVA_CODEGEN_TARGET, native)."""
    target = os.environ.get(TARGET_ENV, '').strip() or NATIVE
    if not _TARGET_NAME.fullmatch(target):
        raise TargetError(f'{TARGET_ENV}={target!r}: not a -march name (e.g. native, '
                          f'x86-64-v2, x86-64-v3, znver3)')
    return target


def target_flags(target: str) -> Tuple[str, ...]:
    """Return the flags added for ``target``: its instruction set, and no fused multiply-adds.

    Without contraction to FMAs every target computes the same IEEE operations in the
    same order: the results are bit for bit those of CODEGEN_FLAGS (tested), only the
    speed differs (docs/nmpc.md).
    """
    return (f'-march={target}', '-ffp-contract=off')


@functools.lru_cache(maxsize=None)
def _accepts(cc: str, target: str) -> str:
    """Return '' if ``cc`` compiles for ``target``, else its first error line."""
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, 'probe.c')
        with open(src, 'w', encoding='utf-8') as fh:
            fh.write('double f(double x) { return x * x + 1.0; }\n')
        probe = subprocess.run([cc, *CODEGEN_FLAGS, *target_flags(target), '-o',
                                os.path.join(tmp, 'probe.so'), src],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               errors='replace')
    if probe.returncode == 0:
        return ''
    return _compiler_message(cc, probe.returncode, probe.stderr)


@functools.lru_cache(maxsize=None)
def _cpu_id() -> str:
    """Return what identifies this CPU's instruction set (model and feature flags)."""
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as fh:
            lines = [ln for ln in fh if ln.startswith(('model name', 'flags', 'Features'))]
        return ''.join(sorted(set(lines)))
    except OSError:
        return platform.machine() + platform.processor()


@functools.lru_cache(maxsize=None)
def cpu_features() -> FrozenSet[str]:
    """Return this CPU's feature flags as /proc/cpuinfo names them (``avx2``, ``fma``, ...)."""
    out: Set[str] = set()
    for line in _cpu_id().splitlines():
        key, _, value = line.partition(':')
        if key.strip() in ('flags', 'Features'):
            out.update(value.split())
    return frozenset(out)


#: The compiler's macros of instruction-set extensions (``cc -march=T -dM -E``) and the
#: /proc/cpuinfo flag of each: what code built for a target may use.  Extensions the
#: generated arithmetic cannot use (RDRND, SGX, ...) are left out.
ISA_FLAGS = {
    '__SSE__': 'sse', '__SSE2__': 'sse2', '__SSE3__': 'pni', '__SSSE3__': 'ssse3',
    '__SSE4_1__': 'sse4_1', '__SSE4_2__': 'sse4_2', '__SSE4A__': 'sse4a',
    '__POPCNT__': 'popcnt', '__LZCNT__': 'abm', '__BMI__': 'bmi1', '__BMI2__': 'bmi2',
    '__MOVBE__': 'movbe', '__F16C__': 'f16c', '__FMA__': 'fma', '__FMA4__': 'fma4',
    '__XOP__': 'xop', '__AVX__': 'avx', '__AVX2__': 'avx2', '__AVXVNNI__': 'avx_vnni',
    '__AVX512F__': 'avx512f', '__AVX512CD__': 'avx512cd', '__AVX512BW__': 'avx512bw',
    '__AVX512DQ__': 'avx512dq', '__AVX512VL__': 'avx512vl', '__AVX512ER__': 'avx512er',
    '__AVX512PF__': 'avx512pf', '__AVX512IFMA__': 'avx512ifma',
    '__AVX512VBMI__': 'avx512vbmi', '__AVX512VBMI2__': 'avx512_vbmi2',
    '__AVX512VNNI__': 'avx512_vnni', '__AVX512BITALG__': 'avx512_bitalg',
    '__AVX512VPOPCNTDQ__': 'avx512_vpopcntdq', '__AVX512BF16__': 'avx512_bf16',
    '__AVX512FP16__': 'avx512_fp16', '__AVX512VP2INTERSECT__': 'avx512_vp2intersect',
    '__ADX__': 'adx', '__AES__': 'aes', '__PCLMUL__': 'pclmulqdq', '__SHA__': 'sha_ni',
    '__VAES__': 'vaes', '__VPCLMULQDQ__': 'vpclmulqdq', '__GFNI__': 'gfni',
}


def _target_isa(cc: str, target: str) -> FrozenSet[str]:
    """Return the cpuinfo flags code that ``cc`` builds for ``target`` may use."""
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, 'probe.c')       # the macros the compiler predefines
        with open(src, 'w', encoding='utf-8') as fh:
            fh.write('\n')
        proc = subprocess.run([cc, *target_flags(target), '-dM', '-E', src],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    macros = {ln.split()[1] for ln in proc.stdout.splitlines() if ln.startswith('#define ')}
    return frozenset(flag for macro, flag in ISA_FLAGS.items() if macro in macros)


@dataclass(frozen=True)
class TargetRecord:
    """What the cache knows of one target: its flags, key salt and required CPU features.

    Written when the first library for the target is compiled (``<cache>/cpu/<tag>.json``),
    so that a machine without a compiler (a vehicle PC given a cache built elsewhere)
    knows which CPU can load its libraries.
    """

    target: str                 # as asked: native, x86-64-v3, ...
    tag: str                    # the cache's name: the target, native-<CPU hash>, or default
    flags: Tuple[str, ...]
    requires: FrozenSet[str]    # cpuinfo flags the code may use
    cpu: str = ''               # native: the CPU's model name

    @property
    def salt(self) -> str:
        """Return what a library's key depends on besides its source."""
        native = self.tag.startswith(NATIVE + '-')
        return ' '.join(self.flags) + (_cpu_id() if native else '')

    def missing_here(self) -> List[str]:
        """Return the features this CPU lacks to run the target's code (empty: it runs)."""
        return sorted(self.requires - cpu_features())

    def as_dict(self) -> Dict[str, Any]:
        """Return the record as plain values (its file, and --json)."""
        return {'target': self.target, 'tag': self.tag, 'flags': list(self.flags),
                'requires': sorted(self.requires), 'cpu': self.cpu}


def _cpu_model() -> str:
    for line in _cpu_id().splitlines():
        if line.startswith('model name'):
            return line.partition(':')[2].strip()
    return platform.machine()


def native_tag_suffix() -> str:
    """Return the short hash of this CPU's id that names its ``native`` target's cache."""
    return hashlib.sha1(_cpu_id().encode()).hexdigest()[:8]


def _tag(target: str, flags: Sequence[str]) -> str:
    if target != NATIVE:
        return target
    if '-march=native' not in flags:
        return 'default'           # the compiler takes no -march: its own default
    return f'{NATIVE}-{native_tag_suffix()}'


def _record_path(tag: str) -> str:
    return os.path.join(codegen_cache_dir(), TARGET_RECORDS, f'{tag}.json')


def read_record(tag: str) -> Optional[TargetRecord]:
    """Return the cache's record of the target ``tag``, or None."""
    try:
        with open(_record_path(tag), encoding='utf-8') as fh:
            d = json.load(fh)
        return TargetRecord(d['target'], d['tag'], tuple(d['flags']),
                            frozenset(d['requires']), d.get('cpu', ''))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def cached_records() -> List[TargetRecord]:
    """Return the records of every target the cache holds libraries for."""
    folder = os.path.join(codegen_cache_dir(), TARGET_RECORDS)
    names = sorted(glob.glob(os.path.join(glob.escape(folder), '*.json')))
    return [r for r in (read_record(os.path.basename(n)[:-5]) for n in names) if r is not None]


def ensure_record(record: TargetRecord) -> None:
    """Write ``record`` into the cache unless it is there already."""
    if read_record(record.tag) == record:
        return
    path = _record_path(record.tag)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f'{path}.{os.getpid()}.{threading.get_ident()}.tmp'
    with open(tmp, 'w', encoding='utf-8') as fh:
        json.dump(record.as_dict(), fh, indent=1)
    os.replace(tmp, path)


@dataclass(frozen=True)
class Toolchain:
    """The compiler (or None) and the target record the libraries are keyed and loaded by."""

    cc: Optional[str]
    record: TargetRecord

    @property
    def flags(self) -> Tuple[str, ...]:
        """Return the compiler flags of the target's libraries."""
        return self.record.flags

    @property
    def salt(self) -> str:
        """Return what a library's key depends on besides its source."""
        return self.record.salt


@functools.lru_cache(maxsize=None)
def _toolchain(cc: Optional[str], target: str, cache: str) -> Toolchain:
    if cc is not None:
        why = _accepts(cc, target)
        if why and target != NATIVE:
            raise TargetError(f'{TARGET_ENV}={target}: {os.path.basename(cc)} cannot build '
                              f'for it: {why}')
        flags = CODEGEN_FLAGS + (target_flags(target) if not why else ('-ffp-contract=off',))
        tag = _tag(target, flags)
        record = read_record(tag)
        if record is None or record.flags != flags:
            march = target_flags(target) if not why else ()
            requires = _target_isa(cc, target) if march else frozenset()
            record = TargetRecord(target, tag, flags, requires,
                                  _cpu_model() if tag.startswith(NATIVE + '-') else '')
        return Toolchain(cc, record)
    # No compiler: what the cache holds for the target (built here earlier, or elsewhere).
    flags = CODEGEN_FLAGS + target_flags(target)
    tag = _tag(target, flags)
    record = read_record(tag)
    if record is None:
        raise TargetError(f'{TARGET_ENV}={target}: no C compiler (cc or gcc) on PATH and no '
                          f'libraries built for {target} in {cache} (build them with `erva '
                          f'compile --target {target}` on a machine with one, and copy the '
                          f'cache here)')
    return Toolchain(None, record)


def toolchain(target: Optional[str] = None) -> Toolchain:
    """Return the toolchain of ``target`` (default: :func:`codegen_target`)."""
    return _toolchain(c_compiler(), target or codegen_target(), codegen_cache_dir())


def check_runs_here(tc: Toolchain) -> None:
    """Raise TargetError (one line) unless this CPU can run the code of ``tc``'s target."""
    missing = tc.record.missing_here()
    if missing:
        raise TargetError(
            f'{TARGET_ENV}={tc.record.target}: this CPU cannot run code built for it (it has '
            f'no {", ".join(missing)}); run on a CPU that has them, or choose a target this '
            f'one runs (native, x86-64-v2, ...)')


def library_flags(source: str):
    """Return the compiler flags of the solver libraries that generated ``source`` calls.

    CasADi's ``daqp`` QP (the NMPC's box QP) generates calls into DAQP, whose headers
    and static library ship in the casadi wheel: compile against those.
    """
    if '#include <daqp/api.h>' not in source:
        return []
    base = os.path.dirname(ca.__file__)
    return ['-I', os.path.join(base, 'include'), os.path.join(base, 'libdaqpstat.a')]


def use_codegen(setting: str) -> bool:
    """Return whether ``codegen`` = setting compiles (or loads compiled libraries).

    'on'; 'auto' with a C compiler, or with libraries built for the target in the cache
    (copied from another machine).
    """
    if setting == 'on':
        return True
    if setting != 'auto':
        return False
    if c_compiler() is not None:
        return True
    try:
        toolchain()               # without a compiler: only if the cache has the target
        return True
    except TargetError:
        return False


@dataclass(frozen=True)
class CompileJob:
    """One generated function not in the cache yet: its name, C source and library path."""

    name: str
    source: str
    lib: str


def plan_functions(fns) -> Tuple[List[str], List[CompileJob]]:
    """Return the cached library path of each of ``fns`` and the jobs of those not cached.

    A library is keyed by the hash of its generated source, the compiler flags (the
    target's ``-march`` among them) and, for ``native``, the CPU, so a changed model,
    parameter set, horizon or target gets its own, and a library built for another CPU
    is never found.
    """
    cache = codegen_cache_dir()
    salt = toolchain().salt
    libs, jobs = [], []
    for fn in fns:
        cg = ca.CodeGenerator(f'{fn.name()}.c', {'with_header': False})
        cg.add(fn)
        source = cg.dump()
        key = hashlib.sha1((source + salt).encode()).hexdigest()[:16]
        lib = os.path.join(cache, f'{fn.name()}_{key}.so')
        libs.append(lib)
        if not os.path.isfile(lib):
            jobs.append(CompileJob(fn.name(), source, lib))
    return libs, jobs


@dataclass
class Plan:
    """What the functions built under :func:`collecting` load: every library, and the missing."""

    libs: List[str]
    jobs: List[CompileJob]


#: While :func:`collecting` is active: the plan compile_functions adds to.
_collected: Optional[Plan] = None


@contextmanager
def collecting():
    """Record what :func:`compile_functions` would load and compile, without compiling.

    Inside, a function not in the cache is returned as it is (CasADi's virtual machine);
    the :class:`Plan` this yields gets every library and the jobs of the missing ones.
    For a planning process only (erva_ros.core.loop.warmup): builders that cache their results
    (``functools.lru_cache``) would keep the uncompiled functions, and a second build of
    the same configuration in that process would not call this module at all.
    """
    global _collected
    outer, _collected = _collected, Plan([], [])
    try:
        yield _collected
    finally:
        _collected = outer


def compile_functions(fns, what: str = '', note: Optional[Callable[[str], None]] = None):
    """Return ``fns`` generated as C, compiled once per machine and loaded (cached by hash).

    The first use compiles the missing ones in parallel (:func:`run_jobs`: atomic, safe
    against other processes compiling the same function, a failure retried once), saying
    so through ``note`` (default: a line on stderr); later processes load the libraries.
    """
    return _compile_functions(fns, what, note)[0]


def _compile_functions(fns, what: str = '', note: Optional[Callable[[str], None]] = None):
    """Return (the compiled ``fns``, their libraries): :func:`compile_functions`."""
    libs, jobs = plan_functions(fns)
    if _collected is None:
        check_runs_here(toolchain())
    if _collected is not None:
        _collected.libs.extend(libs)
        _collected.jobs.extend(jobs)
        if jobs:
            return list(fns), libs
    elif jobs:
        note = note or _stderr
        note(f'compiling {what or ", ".join(j.name for j in jobs)} (first run on this '
             f'machine; cached in {codegen_cache_dir()})')
        run_jobs(jobs)
    return [ca.external(fn.name(), lib) for fn, lib in zip(fns, libs)], libs


#: Where the cache keeps what each build produced (:func:`load_or_build`).
BUILDS = 'builds'


@functools.lru_cache(maxsize=None)
def code_fingerprint() -> str:
    """Return a hash of the core ring's source: a changed model or solver builds anew."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))     # erva_ros/core
    h = hashlib.sha1()
    for base, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(files):
            if name.endswith('.py'):
                path = os.path.join(base, name)
                h.update(os.path.relpath(path, root).encode())
                with open(path, 'rb') as fh:
                    h.update(fh.read())
    return h.hexdigest()


def load_or_build(setting: str, key: str, build: Callable[[], Sequence[ca.Function]],
                  what: str) -> List[ca.Function]:
    """Return ``build()``'s functions compiled as ``codegen`` = setting asks (compile_for).

    Building a solver symbolically and generating its C only to find its library by the
    source's hash costs most of a node's start-up (the NMPC: 1.2 of 1.7 s).  So a build
    is recorded under ``key`` -- what the caller builds from (its parameters), with the
    core ring's source (:func:`code_fingerprint`), CasADi's version and the target's
    flags -- and a later process with the same key loads the libraries without building.
    Not while :func:`collecting` (erva compile plans by building).
    """
    if not use_codegen(setting) or _collected is not None:
        return compile_for(setting, build(), what)
    tc = toolchain()
    digest = hashlib.sha1('|'.join((key, tc.salt, ca.__version__, code_fingerprint())).encode())
    path = os.path.join(codegen_cache_dir(), BUILDS, f'{digest.hexdigest()[:20]}.json')
    try:
        with open(path, encoding='utf-8') as fh:
            built = json.load(fh)
        libs = [os.path.join(codegen_cache_dir(), lib) for _, lib in built]
        if all(os.path.isfile(lib) for lib in libs):
            check_runs_here(tc)
            return [ca.external(name, lib) for (name, _), lib in zip(built, libs)]
    except (OSError, ValueError, TypeError):
        pass                          # not built before (or unreadable): build it
    fns = list(build())
    compiled, libs = _compile_for(setting, fns, what)
    if libs is None:
        return compiled
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f'{path}.{os.getpid()}.{threading.get_ident()}.tmp'
    with open(tmp, 'w', encoding='utf-8') as fh:
        json.dump([[fn.name(), os.path.basename(lib)] for fn, lib in zip(fns, libs)], fh)
    os.replace(tmp, path)
    return compiled


def _stderr(line: str) -> None:
    print(f'erva: {line}', file=sys.stderr, flush=True)


class CompileError(ParamError):
    """A generated function did not compile (the compiler's own message, one line)."""


def run_jobs(jobs: Sequence[CompileJob], workers: Optional[int] = None) -> None:
    """Compile ``jobs`` into the cache, at most ``workers`` at a time (default: the CPUs).

    Largest first.  Each library is written under a lock (in ``.locks/``, released by
    the kernel if its holder dies) to a temporary file and renamed into place, so a
    killed compile leaves no half-written library and another process compiling the
    same function waits and then loads it.  A compiler killed by a signal or failing
    without a message (seen under load) is run once more.  Every job is tried; then the
    first failure is raised as :class:`CompileError` with the compiler's own message.
    """
    tc = toolchain()
    cc, flags = tc.cc, tc.flags
    if cc is None:
        raise CompileError("parameter 'codegen' = 'on' needs a C compiler (cc or gcc) on PATH; "
                           'set codegen: off')
    unique = {job.lib: job for job in jobs}
    order = sorted(unique.values(), key=lambda j: -len(j.source))
    if not order:
        return
    os.makedirs(codegen_cache_dir(), exist_ok=True)
    ensure_record(tc.record)          # which CPU may load what is compiled now
    errors: List[str] = []
    workers = max(1, min(workers or _cpus(), len(order)))
    pool = ThreadPoolExecutor(workers)
    try:
        for err in pool.map(lambda job: _compile_job(job, cc, flags), order):
            if err:
                errors.append(err)
    except KeyboardInterrupt:
        stop_compilers()
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown()
    if errors:
        raise CompileError(f"parameter 'codegen': {errors[0]}; set codegen: off")


#: The cache's subdirectory of lock files, one per library (flock: freed when a holder dies).
LOCKS = '.locks'
#: The compilers running in this process, and whether Ctrl-C stopped compiling for good.
_RUNNING: Set[subprocess.Popen] = set()
_RUNNING_LOCK = threading.Lock()
_STOPPED = threading.Event()


def stop_compilers() -> None:
    """Ctrl-C: start no compiler in this process again, and end the running ones.

    Each compiler runs in a process group of its own (:func:`run_stoppable`), ended here
    as a whole: gcc's driver and the cc1 it started.  (A terminal's SIGINT ended the
    driver but not a cc1 started just after it, which then compiled on, a minute and
    more under load, holding the driver's stderr open.)
    """
    _STOPPED.set()
    with _RUNNING_LOCK:
        for proc in _RUNNING:
            _end_group(proc)


def stopped() -> bool:
    """Return True once Ctrl-C stopped compiling in this process (:func:`stop_compilers`)."""
    return _STOPPED.is_set()


def _end_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except (ProcessLookupError, PermissionError):
        pass                        # already gone


def run_stoppable(argv: List[str], env: Optional[Dict[str, str]] = None) -> Tuple[int, str]:
    """Run a compiler or a planner in a session of its own; return (status, stderr).

    Ended as a whole by :func:`stop_compilers`, never by the terminal's Ctrl-C (a child
    that got it while still starting printed a traceback).
    """
    if _STOPPED.is_set():
        return -signal.SIGINT, ''
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, errors='replace', start_new_session=True, env=env)
    with _RUNNING_LOCK:
        _RUNNING.add(proc)
    if _STOPPED.is_set():           # stopped between the check and the registration
        _end_group(proc)
    try:
        _, err = proc.communicate()
    finally:
        with _RUNNING_LOCK:
            _RUNNING.discard(proc)
    return proc.returncode, err


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _compile_job(job: CompileJob, cc: str, flags) -> str:
    """Compile one job into its library (see :func:`run_jobs`); return '' or the error."""
    locks = os.path.join(os.path.dirname(job.lib), LOCKS)
    os.makedirs(locks, exist_ok=True)
    with open(os.path.join(locks, os.path.basename(job.lib)), 'a', encoding='utf-8') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)      # another process may be compiling it
        if os.path.isfile(job.lib):
            return ''
        for stale in glob.glob(glob.escape(job.lib) + '.*.tmp*'):
            _remove(stale)                     # left by a compile that was killed
        tmp = f'{job.lib}.{os.getpid()}.{threading.get_ident()}.tmp'
        src = tmp + '.c'
        try:
            with open(src, 'w', encoding='utf-8') as fh:
                fh.write(job.source)
            for attempt in (1, 2):
                status, stderr = run_stoppable([cc, *flags, '-o', tmp, src,
                                                *library_flags(job.source), '-lm'])
                if status == 0:
                    os.replace(tmp, job.lib)   # atomic: no process sees half a library
                    return ''
                why = _compiler_message(cc, status, stderr)
                # Killed, or silent (seen under load): once more.  A compiler's error
                # message would only come again, and Ctrl-C means stop.
                if (status > 0 and stderr.strip()) or _STOPPED.is_set():
                    break
            return f'compiling {job.name} failed{" twice" if attempt == 2 else ""}: {why}'
        finally:
            _remove(tmp)
            _remove(src)


def _compiler_message(cc: str, status: int, stderr: str) -> str:
    """Return the compiler's own reason for a failure, in one line."""
    if status < 0:
        try:
            name = signal.Signals(-status).name
        except ValueError:
            name = f'signal {-status}'
        return f'{os.path.basename(cc)} was killed by {name} (out of memory, or stopped?)'
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if 'error' in ln.lower()] or lines
    if not errors:
        return f'{os.path.basename(cc)} exited with status {status} and no message'
    return errors[0]


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def compile_for(setting: str, fns, what: str):
    """Return ``fns`` compiled as ``codegen`` = setting asks, else unchanged.

    'auto' does not fail for want of a compiler: without one, or if compiling fails, it
    warns once and keeps CasADi's virtual machine (the same arithmetic); 'on' raises
    ParamError.  A target this CPU cannot run is an error either way (TargetError):
    running uncompiled, several times slower, would hide it.
    """
    return _compile_for(setting, fns, what)[0]


def _compile_for(setting: str, fns, what: str):
    """Return (``fns`` as :func:`compile_for` gives them, their libraries or None)."""
    if not use_codegen(setting):
        return list(fns), None
    try:
        return _compile_functions(fns, what)
    except TargetError:
        raise
    except ParamError as exc:
        if setting != 'auto':
            raise
        warnings.warn(f'{exc}; running {what} uncompiled')
        return list(fns), None


class BufferedCall:
    """Call a CasADi Function through preallocated numpy buffers (``Function.buffer``).

    ``fn(*args)`` converts every argument to a DM and every result back: measured on
    the compiled EKF cycle (10 inputs), 0.19 ms per call around 0.012 ms of arithmetic.
    Here the inputs are copied into fixed float64 arrays the Function reads directly
    and the outputs are read from fixed arrays it writes: same results, bit for bit
    (tested).  Inputs and outputs must be dense; matrices are column-major, as CasADi
    stores them.  Not thread-safe: one instance per thread.

    ``__call__`` returns numpy copies shaped as the Function's outputs (vectors 1-D,
    scalars float); a failed evaluation (CasADi's return flag) raises RuntimeError,
    as ``fn(*args)`` would.
    """

    def __init__(self, fn: ca.Function):
        for i in range(fn.n_in()):
            if not fn.sparsity_in(i).is_dense():
                raise ValueError(f'{fn.name()}: input {fn.name_in(i)} is sparse')
        for i in range(fn.n_out()):
            if not fn.sparsity_out(i).is_dense():
                raise ValueError(f'{fn.name()}: output {fn.name_out(i)} is sparse')
        self.fn = fn
        self._buf, self._eval = fn.buffer()
        self._in = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self._out = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        for i, a in enumerate(self._in):
            self._buf.set_arg(i, memoryview(a))
        for i, a in enumerate(self._out):
            self._buf.set_res(i, memoryview(a))
        self._matrix_in = [fn.size2_in(i) != 1 for i in range(fn.n_in())]
        self._shape_out = []
        for i in range(fn.n_out()):
            rows, cols = fn.size_out(i)
            self._shape_out.append(None if rows * cols == 1 else
                                   (rows,) if cols == 1 else (rows, cols))

    def __call__(self, *args):
        if len(args) != len(self._in):
            raise TypeError(f'{self.fn.name()}: {len(args)} arguments, '
                            f'expected {len(self._in)}')
        for dst, matrix, a in zip(self._in, self._matrix_in, args):
            if matrix:
                dst[:] = np.asarray(a, dtype=float).ravel(order='F')
            else:
                try:
                    dst[:] = a
                except ValueError:       # a column (n, 1) or row (1, n) vector
                    dst[:] = np.ravel(a)
        self._eval()
        if self._buf.ret() != 0:
            raise RuntimeError(f'{self.fn.name()}: evaluation failed')
        out = []
        for res, shape in zip(self._out, self._shape_out):
            if shape is None:
                out.append(float(res[0]))
            elif len(shape) == 1:
                out.append(res.copy())
            else:
                out.append(res.reshape(shape[::-1]).T.copy())
        return out


__all__ = ['CODEGEN_FLAGS', 'TARGET_ENV', 'NATIVE', 'codegen_cache_dir', 'c_compiler',
           'TargetError', 'codegen_target', 'target_flags', 'cpu_features', 'ISA_FLAGS',
           'TargetRecord', 'native_tag_suffix', 'read_record', 'ensure_record', 'cached_records',
           'Toolchain', 'toolchain',
           'check_runs_here', 'code_fingerprint', 'load_or_build', 'library_flags',
           'stop_compilers',
           'use_codegen', 'CompileJob', 'CompileError', 'Plan',
           'plan_functions', 'collecting',
           'compile_functions', 'run_jobs', 'compile_for', 'BufferedCall']
