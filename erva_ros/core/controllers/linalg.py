"""Symbolic linear-algebra kernels of the real-time SQP: straight-line SX code.

Each returns CasADi SX expressions (no loops at run time): compiled with the solver
(erva_ros/core/codegen.py), they cost only the arithmetic of the matrices at hand.

* :func:`lu_factor` / :func:`lu_solve`: LU without numerical pivoting that skips
  structural zeros, its pivots in a fill-reducing order chosen from the sparsity
  (:func:`fill_reducing_order`).  The SQP factors each interval's collocation
  Jacobian with it: the order eliminates the kinematic rows (position' = velocity,
  whose pivots are the Radau IIA matrix's constants) first, then the dense 9 x 9
  velocity block, 45 % fewer operations than the natural order and the same
  solution to rounding (test_sqp.py checks it against numpy's pivoted solve).
* :func:`convexify`: V·max(|Λ|, floor)·Vᵀ of a symmetric matrix by a fixed number of
  cyclic Jacobi sweeps, one compiled sweep called ``sweeps`` times.
"""

from functools import lru_cache
from typing import List, NamedTuple, Tuple

import casadi as ca
import numpy as np

#: Sweeps of the Jacobi eigen-decomposition of the reduced Hessian: on the recorded
#: problems |H| to ≤ 5e-13 at 10 x 10 (preview), median 4e-7 at 20 x 20 (preview_long).
#: Fewer at 20 x 20 cost comfort: 3 sweeps, a solve ~5 % faster, J +3.3 ± 1.1 % (docs/nmpc.md).
JACOBI_SWEEPS = 5
#: Eigenvalue floor of the convexified Hessian, relative to its largest |eigenvalue|.
EIG_FLOOR = 1e-6


def _elements(a):
    """Return a dense SX matrix as nested lists of scalars (zeros as the constant 0)."""
    a = ca.densify(a)
    return [[a[i, j] for j in range(a.size2())] for i in range(a.size1())]


def fill_reducing_order(pattern) -> Tuple[int, ...]:
    """Return a pivot order of a square sparsity pattern that keeps its LU sparse.

    Greedy Markowitz on the diagonal: next, the pivot whose row and column have the
    fewest other nonzeros left, fill-in counted as it appears; ties by index, so the
    order is deterministic.  The permutation is symmetric (the pivots stay on the
    diagonal), so structurally nonzero diagonals stay the pivots.
    """
    rows = [set(np.flatnonzero(r)) for r in np.asarray(pattern, dtype=bool)]
    n = len(rows)
    cols = [{i for i in range(n) if j in rows[i]} for j in range(n)]
    left, order = set(range(n)), []
    while left:
        pivot = min((k for k in sorted(left) if k in rows[k]),
                    key=lambda k: (len(rows[k] & left) - 1) * (len(cols[k] & left) - 1))
        order.append(pivot)
        left.remove(pivot)
        below, right = [i for i in cols[pivot] if i in left], [j for j in rows[pivot] if j in left]
        for i in below:
            for j in right:
                if j not in rows[i]:
                    rows[i].add(j)
                    cols[j].add(i)
    return tuple(order)


class SparseLU(NamedTuple):
    """L·U = A[order][:, order] (L unit lower, both in ``m``), from :func:`lu_factor`."""

    order: Tuple[int, ...]
    m: List[list]


def lu_factor(a) -> SparseLU:
    """Factor a square SX matrix in a fill-reducing pivot order, no numerical pivoting."""
    order = fill_reducing_order(np.array(ca.DM(a.sparsity(), 1)))
    m = _elements(a[list(order), list(order)])
    n = len(m)
    for j in range(n):
        for i in range(j + 1, n):
            if m[i][j].is_zero():
                continue
            m[i][j] = m[i][j] / m[j][j]
            for k in range(j + 1, n):
                if not m[j][k].is_zero():
                    m[i][k] = m[i][k] - m[i][j] * m[j][k]
    return SparseLU(order, m)


def lu_solve(lu: SparseLU, b, transpose: bool = False):
    """Solve A·x = b (or Aᵀ·x = b) for the columns of the SX matrix b, from :func:`lu_factor`."""
    m, order = lu.m, list(lu.order)
    n = len(m)
    cols = []
    for c in range(b.size2()):
        x = [b[order[i], c] for i in range(n)]
        if not transpose:      # L y = b, then U x = y
            steps = [(range(n), lambda i, k: m[i][k], False),
                     (range(n - 1, -1, -1), lambda i, k: m[i][k], True)]
        else:                  # Uᵀ y = b, then Lᵀ x = y
            steps = [(range(n), lambda i, k: m[k][i], True),
                     (range(n - 1, -1, -1), lambda i, k: m[k][i], False)]
        for rows, entry, divide in steps:
            done = []
            for i in rows:
                for k in done:
                    e = entry(i, k)
                    if not e.is_zero():
                        x[i] = x[i] - e * x[k]
                if divide:
                    x[i] = x[i] / m[i][i]
                done.append(i)
        out = [None] * n
        for i, o in enumerate(order):
            out[o] = x[i]
        cols.append(ca.vertcat(*out))
    return ca.horzcat(*cols)


def symmetric(m):
    """Return the symmetric matrix of m's upper triangle (SX: the lower one is never computed)."""
    return ca.triu(m) + ca.triu(m, False).T


@lru_cache(maxsize=None)
def _jacobi_sweep(n: int) -> ca.Function:
    """Return one cyclic Jacobi sweep (a, V) -> (a', V'), a the upper triangle by columns.

    One compiled copy called ``sweeps`` times (never inlined), the same arithmetic:
    unrolled, preview_long's 5 sweeps were 1.6 MB of its 5.8 MB iteration library.
    """
    tri, vs = ca.SX.sym('a', n * (n + 1) // 2), ca.SX.sym('v', n, n)
    upper = [(i, j) for j in range(n) for i in range(j + 1)]    # column-major triangle
    a = [[None] * n for _ in range(n)]
    for e, (i, j) in enumerate(upper):
        a[i][j] = a[j][i] = tri[e]
    v = [[vs[i, j] for j in range(n)] for i in range(n)]
    for p in range(n - 1):
        for q in range(p + 1, n):
            apq = a[p][q]
            dlt = a[q][q] - a[p][p]
            sign = 2 * (dlt >= 0) - 1
            t = 2 * apq * sign / (ca.fabs(dlt) + ca.sqrt(dlt ** 2 + 4 * apq ** 2) + 1e-300)
            c = 1 / ca.sqrt(1 + t ** 2)
            s = t * c
            # Jᵀ·A·J with J the rotation in (p, q): the angle zeroes a_pq.
            for k in range(n):
                if k not in (p, q):
                    akp, akq = a[k][p], a[k][q]
                    a[k][p] = a[p][k] = c * akp - s * akq
                    a[k][q] = a[q][k] = s * akp + c * akq
                v[k][p], v[k][q] = c * v[k][p] - s * v[k][q], s * v[k][p] + c * v[k][q]
            a[p][p], a[q][q] = a[p][p] - t * apq, a[q][q] + t * apq
            a[p][q] = a[q][p] = ca.SX(0.0)
    return ca.Function(f'jacobi_sweep_{n}', [tri, vs],
                       [ca.vertcat(*[a[i][j] for i, j in upper]),
                        ca.vertcat(*[ca.horzcat(*row) for row in v])],
                       {'never_inline': True})


def convexify(h, sweeps: int = JACOBI_SWEEPS):
    """Return V·max(|Λ|, floor)·Vᵀ for symmetric h = V·Λ·Vᵀ (SX).

    The eigenvalues are mirrored: along a direction of negative curvature the model
    keeps its magnitude (a modified Cholesky, tried first, inflated the curvature of
    near-singular directions 10-60x and made the SQP creep).  Cyclic Jacobi rotations
    with the smaller angle (|θ| ≤ π/4) converge quadratically; ``sweeps`` fixed, one
    compiled sweep called that many times.  V is a product of rotations, so the result
    is positive definite whatever the sweeps; fewer only leave it further from |h|.  Only
    h's upper triangle is read, and each rotation updates one triangle: a symmetric
    matrix stays symmetric, so the other half would be the same arithmetic again.
    """
    n = h.size1()
    sweep = _jacobi_sweep(n)
    tri = ca.vertcat(*[h[i, j] for j in range(n) for i in range(j + 1)])
    vm = ca.SX.eye(n)
    for _ in range(sweeps):
        tri, vm = sweep(tri, vm)
    lam = ca.vertcat(*[tri[j * (j + 1) // 2 + j] for j in range(n)])
    floor = EIG_FLOOR * ca.fmax(ca.mmax(ca.fabs(lam)), 1e-12)
    return symmetric(ca.mtimes([vm, ca.diag(ca.fmax(ca.fabs(lam), floor)), vm.T]))


__all__ = ['EIG_FLOOR', 'JACOBI_SWEEPS', 'SparseLU', 'convexify', 'fill_reducing_order',
           'lu_factor', 'lu_solve', 'symmetric']
