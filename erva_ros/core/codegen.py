"""C code generation of CasADi Functions on hot paths (the NMPC's solver, the EKF).

``codegen`` settings: ``auto`` compiles when a C compiler is on PATH, ``on`` insists
(one-line error without one), ``off`` keeps CasADi's virtual machine.  A generated
Function is compiled once per machine and cached by the hash of its source, flags and
CPU, so a changed model, parameter set or horizon gets its own library.  Each library
is written atomically under a lock, so a killed compile leaves nothing half-written and
the next run compiles only what is missing; ``erva compile`` (erva_ros.core.warmup)
fills the cache for a whole configuration before any node starts.
"""

from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
import fcntl
import functools
import glob
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from typing import Callable, List, Optional, Sequence, Tuple
import warnings

import casadi as ca
import numpy as np

from erva_ros.core.params import ParamError

#: C compiler flags of ``codegen``.  -O3: the NMPC solver's per-interval kernels run as
#: loops, which the optimiser speeds up (docs/nmpc.md); compiling it takes ~10 s.
CODEGEN_FLAGS = ('-O3', '-shared', '-fPIC')
#: Added when the compiler accepts them: this CPU's instruction set made the NMPC solve
#: 5-8 % faster (docs/nmpc.md); without contraction to fused multiply-adds the results
#: are bit for bit those of CODEGEN_FLAGS.  A library is then keyed to the CPU as well.
NATIVE_FLAGS = ('-march=native', '-ffp-contract=off')


def codegen_cache_dir() -> str:
    """Return the directory of compiled functions (ERVA_CACHE_DIR, else ~/.cache/erva_ros)."""
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.environ.get('ERVA_CACHE_DIR') or os.path.join(base, 'erva_ros')


def c_compiler():
    """Return the C compiler codegen uses ($CC, cc or gcc), or None."""
    return os.environ.get('CC') or shutil.which('cc') or shutil.which('gcc')


@functools.lru_cache(maxsize=None)
def codegen_flags(cc: str):
    """Return the flags ``cc`` compiles with: CODEGEN_FLAGS + NATIVE_FLAGS if it takes them."""
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, 'probe.c')
        with open(src, 'w', encoding='utf-8') as fh:
            fh.write('double f(double x) { return x * x + 1.0; }\n')
        probe = subprocess.run([cc, *CODEGEN_FLAGS, *NATIVE_FLAGS, '-o',
                                os.path.join(tmp, 'probe.so'), src],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return CODEGEN_FLAGS + (NATIVE_FLAGS if probe.returncode == 0 else ())


@functools.lru_cache(maxsize=None)
def _cpu_id() -> str:
    """Return what identifies this CPU's instruction set (model and feature flags)."""
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as fh:
            lines = [ln for ln in fh if ln.startswith(('model name', 'flags', 'Features'))]
        return ''.join(sorted(set(lines)))
    except OSError:
        import platform
        return platform.machine() + platform.processor()


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
    """Return whether ``codegen`` = setting compiles: 'on', or 'auto' with a C compiler."""
    return setting == 'on' or (setting == 'auto' and c_compiler() is not None)


@dataclass(frozen=True)
class CompileJob:
    """One generated function not in the cache yet: its name, C source and library path."""

    name: str
    source: str
    lib: str


def toolchain():
    """Return (cc or None, flags, salt): what a library's key depends on besides its source."""
    cc = c_compiler()
    flags = codegen_flags(cc) if cc is not None else CODEGEN_FLAGS
    salt = ' '.join(flags) + (_cpu_id() if flags != CODEGEN_FLAGS else '')
    return cc, flags, salt


def plan_functions(fns) -> Tuple[List[str], List[CompileJob]]:
    """Return the cached library path of each of ``fns`` and the jobs of those not cached.

    A library is keyed by the hash of its generated source, the compiler flags and (with
    NATIVE_FLAGS) the CPU, so a changed model, parameter set or horizon gets its own.
    """
    cache = codegen_cache_dir()
    _, _, salt = toolchain()
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
    For a planning process only (erva_ros.core.warmup): builders that cache their results
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
    libs, jobs = plan_functions(fns)
    if _collected is not None:
        _collected.libs.extend(libs)
        _collected.jobs.extend(jobs)
        if jobs:
            return list(fns)
    elif jobs:
        note = note or _stderr
        note(f'compiling {what or ", ".join(j.name for j in jobs)} (first run on this '
             f'machine; cached in {codegen_cache_dir()})')
        run_jobs(jobs)
    return [ca.external(fn.name(), lib) for fn, lib in zip(fns, libs)]


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
    cc, flags, _ = toolchain()
    if cc is None:
        raise CompileError("parameter 'codegen' = 'on' needs a C compiler (cc or gcc) on PATH; "
                           'set codegen: off')
    unique = {job.lib: job for job in jobs}
    order = sorted(unique.values(), key=lambda j: -len(j.source))
    if not order:
        return
    os.makedirs(codegen_cache_dir(), exist_ok=True)
    errors: List[str] = []
    workers = max(1, min(workers or _cpus(), len(order)))
    with ThreadPoolExecutor(workers) as pool:
        for err in pool.map(lambda job: _compile_job(job, cc, flags), order):
            if err:
                errors.append(err)
    if errors:
        raise CompileError(f"parameter 'codegen': {errors[0]}; set codegen: off")


#: The cache's subdirectory of lock files, one per library (flock: freed when a holder dies).
LOCKS = '.locks'


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
                proc = subprocess.run([cc, *flags, '-o', tmp, src, *library_flags(job.source),
                                       '-lm'],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                      text=True, errors='replace')
                if proc.returncode == 0:
                    os.replace(tmp, job.lib)   # atomic: no process sees half a library
                    return ''
                why = _compiler_message(cc, proc.returncode, proc.stderr)
                # Killed, or silent (seen under load): once more.  A compiler's error
                # message would only come again.
                if proc.returncode > 0 and proc.stderr.strip():
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

    'auto' never fails: without a compiler, or if compiling fails, it warns once and
    keeps CasADi's virtual machine (the same arithmetic); 'on' raises ParamError.
    """
    if not use_codegen(setting):
        return list(fns)
    try:
        return compile_functions(fns, what)
    except ParamError as exc:
        if setting != 'auto':
            raise
        warnings.warn(f'{exc}; running {what} uncompiled')
        return list(fns)


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


__all__ = ['CODEGEN_FLAGS', 'NATIVE_FLAGS', 'codegen_flags', 'codegen_cache_dir', 'c_compiler',
           'library_flags', 'use_codegen', 'toolchain', 'CompileJob', 'CompileError', 'Plan',
           'plan_functions', 'collecting',
           'compile_functions', 'run_jobs', 'compile_for', 'BufferedCall']
