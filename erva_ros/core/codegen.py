"""C code generation of CasADi Functions on hot paths (the NMPC's solver, the EKF).

``codegen`` settings: ``auto`` compiles when a C compiler is on PATH, ``on`` insists
(one-line error without one), ``off`` keeps CasADi's virtual machine.  A generated
Function is compiled once per machine and cached by the hash of its source, flags and
CPU, so a changed model, parameter set or horizon gets its own library.
"""

import functools
import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings

import casadi as ca
import numpy as np

from erva_ros.core.params import ParamError

#: C compiler flags of ``codegen`` (-O2 measured no faster than -O1, and compiles 6x slower).
CODEGEN_FLAGS = ('-O1', '-shared', '-fPIC')
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


def use_codegen(setting: str) -> bool:
    """Return whether ``codegen`` = setting compiles: 'on', or 'auto' with a C compiler."""
    return setting == 'on' or (setting == 'auto' and c_compiler() is not None)


def compile_functions(fns):
    """Return ``fns`` generated as C, compiled once per machine and loaded (cached by hash).

    Each function's generated source is hashed with the compiler flags, so a changed
    model, parameter set or horizon gets its own library; the first use compiles
    (the functions in parallel, seconds), later processes load the cached objects.
    """
    cache = codegen_cache_dir()
    cc = c_compiler()
    flags = codegen_flags(cc) if cc is not None else CODEGEN_FLAGS
    salt = ' '.join(flags) + (_cpu_id() if flags != CODEGEN_FLAGS else '')
    jobs, libs = [], []
    for fn in fns:
        cg = ca.CodeGenerator(f'{fn.name()}.c', {'with_header': False})
        cg.add(fn)
        source = cg.dump()
        key = hashlib.sha1((source + salt).encode()).hexdigest()[:16]
        lib = os.path.join(cache, f'{fn.name()}_{key}.so')
        libs.append(lib)
        if not os.path.isfile(lib):
            jobs.append((fn.name(), source, lib))
    if jobs:
        if cc is None:
            raise ParamError("parameter 'codegen' = 'on' needs a C compiler (cc or gcc) "
                             "on PATH; set codegen: off")
        os.makedirs(cache, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache) as tmp:
            procs = []
            for i, (name, source, lib) in enumerate(jobs):
                src, out = os.path.join(tmp, f'{i}.c'), os.path.join(tmp, f'{i}.so')
                with open(src, 'w', encoding='utf-8') as fh:
                    fh.write(source)
                procs.append((name, lib, out, subprocess.Popen(
                    [cc, *flags, '-o', out, src, '-lm'],
                    stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)))
            for name, lib, out, proc in procs:
                _, err = proc.communicate()
                if proc.returncode != 0:
                    first = (err.strip().splitlines() or ['unknown error'])[0]
                    raise ParamError(f"parameter 'codegen': compiling {name} failed: {first}"
                                     '; set codegen: off')
                os.replace(out, lib)   # atomic: concurrent processes never load half a file
    return [ca.external(fn.name(), lib) for fn, lib in zip(fns, libs)]


def compile_for(setting: str, fns, what: str):
    """Return ``fns`` compiled as ``codegen`` = setting asks, else unchanged.

    'auto' never fails: without a compiler, or if compiling fails, it warns once and
    keeps CasADi's virtual machine (the same arithmetic); 'on' raises ParamError.
    """
    if not use_codegen(setting):
        return list(fns)
    try:
        return compile_functions(fns)
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
           'use_codegen', 'compile_functions', 'compile_for', 'BufferedCall']
