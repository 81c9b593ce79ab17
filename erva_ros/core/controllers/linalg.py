"""Symbolic linear-algebra kernels of the real-time SQP: straight-line SX code.

Each returns CasADi SX expressions (no loops at run time): compiled with the solver
(erva_ros/core/model/codegen.py), they cost only the arithmetic of the matrices at hand.

* :func:`lu_factor` / :func:`lu_solve`: LU without numerical pivoting that skips
  structural zeros, its pivots in a fill-reducing order chosen from the sparsity
  (:func:`fill_reducing_order`).  The SQP factors each interval's collocation
  Jacobian with it: the order eliminates the kinematic rows (position' = velocity,
  whose pivots are the Radau IIA matrix's constants) first, then the dense 9 x 9
  velocity block, 45 % fewer operations than the natural order and the same
  solution to rounding (test_sqp.py checks it against numpy's pivoted solve).
* :func:`convexify`: V·max(Λ, floor)·Vᵀ of a symmetric matrix by a fixed number of
  parallel Jacobi sweeps, one compiled round called as a loop.
"""

from functools import lru_cache
from typing import List, NamedTuple, Tuple

import casadi as ca
import numpy as np

#: Sweeps of the Jacobi eigen-decomposition of the reduced Hessian: on recorded problems
#: the result is the exact one to ≤ 1.3e-10 at 10 x 10 (preview; median 1.5e-15), to a
#: median 6e-9 (max 1.7e-4) at 20 x 20 (preview_long); 4 sweeps: median 2e-5 there.
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


def _round_robin(n: int) -> Tuple[int, ...]:
    """Return the move between rounds of the circle method on n (even) positions.

    Pairs are the positions (0, 1), (2, 3), ...; after each round the player at new
    position j comes from old position σ[j].  n − 1 rounds pair every two players once
    and bring everyone back.
    """
    m = n // 2
    arr = list(range(n))
    top, bot = arr[0::2], arr[1::2]
    ring = top[1:] + bot[::-1]
    ring = ring[-1:] + ring[:-1]
    new = [None] * n
    new[0::2] = [top[0]] + ring[:m - 1]
    new[1::2] = ring[m - 1:][::-1]
    return tuple(arr.index(x) for x in new)


@lru_cache(maxsize=None)
def _jacobi_round(n: int) -> ca.Function:
    """Return one round of parallel Jacobi [A; V] -> [A'; V'] on an n x n (n even) matrix.

    n/2 disjoint rotations at once, on the pairs (2k, 2k + 1), each with the smaller
    angle that zeroes its a_pq (as in cyclic Jacobi), then the round-robin move
    (:func:`_round_robin`): n − 1 rounds are one sweep over all pairs.  Compiled once
    and called as a loop (``fold``), where the cyclic sweep unrolled at n = 20 was
    48k lines of C.
    """
    m = n // 2
    av = ca.SX.sym('av', 2 * n, n)
    a_in, v_in = av[:n, :], av[n:, :]
    a = [[a_in[min(i, j), max(i, j)] for j in range(n)] for i in range(n)]   # upper half read
    rot = []
    for k in range(m):
        p, q = 2 * k, 2 * k + 1
        apq, dlt = a[p][q], a[q][q] - a[p][p]
        sign = 2 * (dlt >= 0) - 1
        t = 2 * apq * sign / (ca.fabs(dlt) + ca.sqrt(dlt ** 2 + 4 * apq ** 2) + 1e-300)
        c = 1 / ca.sqrt(1 + t ** 2)
        rot.append((c, t * c, t))
    out = [[None] * n for _ in range(n)]
    for k in range(m):
        c, s, t = rot[k]
        p, q = 2 * k, 2 * k + 1
        out[p][p], out[q][q] = a[p][p] - t * a[p][q], a[q][q] + t * a[p][q]
        out[p][q] = out[q][p] = ca.SX(0.0)
        for ll in range(k + 1, m):          # the block of pairs k, l: R_kᵀ·B·R_l
            cl, sl, _ = rot[ll]
            r, w = 2 * ll, 2 * ll + 1
            b_pr, b_pw = cl * a[p][r] - sl * a[p][w], sl * a[p][r] + cl * a[p][w]
            b_qr, b_qw = cl * a[q][r] - sl * a[q][w], sl * a[q][r] + cl * a[q][w]
            out[p][r] = out[r][p] = c * b_pr - s * b_qr
            out[q][r] = out[r][q] = s * b_pr + c * b_qr
            out[p][w] = out[w][p] = c * b_pw - s * b_qw
            out[q][w] = out[w][q] = s * b_pw + c * b_qw
    v = [[v_in[i, j] for j in range(n)] for i in range(n)]
    for k in range(m):
        c, s, _ = rot[k]
        p, q = 2 * k, 2 * k + 1
        for i in range(n):
            v[i][p], v[i][q] = c * v[i][p] - s * v[i][q], s * v[i][p] + c * v[i][q]
    sigma = _round_robin(n)
    a_next = ca.vertcat(*[ca.horzcat(*[out[sigma[i]][sigma[j]] for j in range(n)])
                          for i in range(n)])
    v_next = ca.vertcat(*[ca.horzcat(*[v[i][sigma[j]] for j in range(n)]) for i in range(n)])
    return ca.Function(f'jacobi_round_{n}', [av], [ca.vertcat(a_next, v_next)],
                       {'never_inline': True})


def convexify(h, sweeps: int = JACOBI_SWEEPS):
    """Return V·max(Λ, floor)·Vᵀ for symmetric h = V·Λ·Vᵀ (MX).

    Negative (and tiny) eigenvalues are raised to the floor: along a direction of
    negative curvature the QP step goes as far as the box lets it and the line search
    judges it.  On the recorded problems this took fewer iterations to lower costs
    than mirroring them, |λ|, which keeps the curvature's size and so shortens the step
    where the cost keeps falling (docs/nmpc.md); a modified Cholesky, tried before,
    inflated the curvature of near-singular directions 10-60x.  Parallel (round-robin)
    Jacobi rotations with the smaller angle (|θ| ≤ π/4) converge quadratically like
    cyclic ones; ``sweeps`` fixed, each n − 1 rounds of n/2 rotations, one compiled
    round called as a loop.  V is a product of rotations, so the result is positive
    definite whatever the sweeps; fewer only leave it further from the exact result.
    Only h's upper
    triangle is read.  An odd n is padded with a zero row and column, which no rotation
    touches (its a_pq are 0).
    """
    n = h.size1()
    n2 = n + n % 2
    a = ca.MX.zeros(n2, n2)
    a[:n, :n] = h
    rounds = _jacobi_round(n2).fold(sweeps * (n2 - 1))
    av = rounds(ca.vertcat(a, ca.DM.eye(n2)))
    a, vm = av[:n2, :], av[n2:, :]
    lam = ca.diag(a)[:n]
    vm = vm[:n, :n]
    floor = EIG_FLOOR * ca.fmax(ca.mmax(ca.fabs(lam)), 1e-12)
    out = ca.mtimes(vm * ca.repmat(ca.fmax(lam, floor).T, n, 1), vm.T)
    return ca.triu(out) + ca.triu(out, False).T         # exactly symmetric


__all__ = ['EIG_FLOOR', 'JACOBI_SWEEPS', 'SparseLU', 'convexify', 'fill_reducing_order',
           'lu_factor', 'lu_solve', 'symmetric']
