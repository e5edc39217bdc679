"""Selected inversion: the entries of H^-1 on the pattern of H's sparse factor (Takahashi, Fagan and
Chen 1973; Erisman and Tinney 1975), for the marginal covariances of :meth:`.solve.Solution.marginals`.

With P H P^T = L D L^T (L unit lower triangular), Z = (P H P^T)^-1 satisfies Z = D^-1 L^-1 + (I - L^T) Z,
whose entries on and below the diagonal, column j taken from the last to the first, read

    Z_ij = - sum_{k > j, L_kj != 0} Z_ik L_kj                 (i > j, L_ij != 0)
    Z_jj = 1 / D_j - sum_{k > j, L_kj != 0} L_kj Z_kj

Every Z_ik these sums need lies on the factor's pattern (the filled graph is chordal: two rows of
column j are joined in a later column), so only the factor's entries are ever computed: O(sum_j m_j^2)
for m_j entries in column j, where solving H X = E for the identity columns of n nodes costs a
triangular solve per column (the dense marginals took a quarter of a site1 floor's batch re-solve).
The factor is SuperLU's of P H P^T with diagonal pivots (:class:`.solve._PermutedLU`): P H P^T = L U,
U = D L^T. A pattern that misses an entry a sum needs (SuperLU drops none, but the check is cheap) is
reported, and the caller solves densely instead.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit


@njit(cache=True, nogil=True)
def _find(indices, lo, hi, row):  # pragma: no cover - compiled
    """Position of ``row`` in the sorted indices[lo:hi], -1 when absent (binary search)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        r = indices[mid]
        if r < row:
            lo = mid + 1
        elif r > row:
            hi = mid
        else:
            return mid
    return -1


@njit(cache=True, nogil=True)
def takahashi(indptr, indices, lval, d):  # pragma: no cover - compiled
    """Z on the pattern of L (CSC, rows sorted in each column, the unit diagonal stored first): the
    values in L's data order, and whether every entry the recurrences needed was on the pattern."""
    n = d.size
    z = np.zeros(indices.size)
    for j in range(n - 1, -1, -1):
        lo, hi = indptr[j], indptr[j + 1]
        if hi == lo or indices[lo] != j:
            return z, False
        s = lo + 1  # the entries below the diagonal
        for a in range(s, hi):
            i = indices[a]
            acc = 0.0
            for b in range(s, hi):
                k = indices[b]
                if k >= i:  # Z_ik = Z_ki: stored in column i at row k
                    p = _find(indices, indptr[i], indptr[i + 1], k)
                else:  # stored in column k at row i
                    p = _find(indices, indptr[k], indptr[k + 1], i)
                if p < 0:
                    return z, False
                acc += z[p] * lval[b]
            z[a] = -acc
        acc = 0.0
        for b in range(s, hi):
            acc += lval[b] * z[b]
        z[lo] = 1.0 / d[j] - acc
    return z, True


@njit(cache=True, nogil=True)
def gather(indptr, indices, z, rows, cols):  # pragma: no cover - compiled
    """Z[rows[m], cols[m]] (symmetric: read below the diagonal) and whether each was on the pattern."""
    out = np.zeros(rows.size)
    found = np.zeros(rows.size, np.bool_)
    for m in range(rows.size):
        r, c = rows[m], cols[m]
        if r < c:
            r, c = c, r
        p = _find(indices, indptr[c], indptr[c + 1], r)
        if p >= 0:
            out[m] = z[p]
            found[m] = True
    return out, found


@njit(cache=True, nogil=True)
def _rows_below(rows, lo, hi, j, mark, buf, m):  # pragma: no cover - compiled
    """Append to buf[m:] the rows of rows[lo:hi] below j not yet marked for column j; the new count."""
    for p in range(lo, hi):
        r = rows[p]
        if r > j and mark[r] != j:
            mark[r] = j
            buf[m] = r
            m += 1
    return m


@njit(cache=True, nogil=True)
def symbolic_factor(indptr, indices, n):  # pragma: no cover - compiled
    """The pattern (CSC, the diagonal first, rows sorted) of the Cholesky factor of a symmetric matrix
    of n columns given by its lower pattern (indptr, indices): column j holds the rows of column j below
    the diagonal and those of its children in the elimination tree other than j (the parent of a
    column is its first row below the diagonal). Every pair of rows of a column is then an entry of
    the pattern, which is what :func:`takahashi` needs."""
    head = np.full(n, -1, np.int64)  # the children of each column, as linked lists
    nxt = np.full(n, -1, np.int64)
    mark = np.full(n, -1, np.int64)
    buf = np.empty(n, np.int64)
    cap = 2 * indices.size + n
    out = np.empty(cap, np.int64)
    ptr = np.zeros(n + 1, np.int64)
    pos = 0
    for j in range(n):
        mark[j] = j
        m = _rows_below(indices, indptr[j], indptr[j + 1], j, mark, buf, 0)
        c = head[j]
        while c != -1:
            m = _rows_below(out, ptr[c] + 1, ptr[c + 1], j, mark, buf, m)
            c = nxt[c]
        rows = np.sort(buf[:m])
        if pos + m + 1 > cap:
            cap = 2 * (pos + m + 1)
            grown = np.empty(cap, np.int64)
            grown[:pos] = out[:pos]
            out = grown
        out[pos] = j
        out[pos + 1 : pos + 1 + m] = rows
        pos += m + 1
        ptr[j + 1] = pos
        if m:
            nxt[j] = head[rows[0]]
            head[rows[0]] = j
    return ptr, out[:pos].copy()


@njit(cache=True, nogil=True)
def _place(fptr, fidx, fval, ptr, idx):  # pragma: no cover - compiled
    """The values of a factor (fptr, fidx, fval) on a pattern (ptr, idx) that holds its own (rows sorted
    in both): zeros where the factor has no entry; False when one of its entries is missing."""
    val = np.zeros(idx.size)
    for j in range(ptr.size - 1):
        q = ptr[j]
        for p in range(fptr[j], fptr[j + 1]):
            r = fidx[p]
            while q < ptr[j + 1] and idx[q] < r:
                q += 1
            if q == ptr[j + 1] or idx[q] != r:
                return val, False
            val[q] = fval[p]
    return val, True


def selected_inverse(L, U, pairs: tuple[np.ndarray, np.ndarray] | None = None):
    """(indptr, indices, z, ok) of Z = (L U)^-1 on the factor's pattern for SuperLU's factors of a
    symmetric positive definite matrix in symmetric mode (L unit lower, U = D L^T): module docstring.

    The factor is read from U: L_ij = U_ji / U_jj. SuperLU's exported factors leave out entries that came
    out exactly zero, and not always the same ones in L and in U (an F1 matrix of 6,710 columns: one
    entry of U^T missing from L, which broke the recurrences' pattern); entries only L holds are added
    with L's values. The pattern the recurrences run on is the symbolic factor (:func:`symbolic_factor`)
    of the factor's own pattern with ``pairs`` (rows, cols) added: entries of Z the caller will read
    that the factor need not hold (a node's x-y entry, where no factor couples its x and y)."""
    d = np.asarray(U.diagonal(), dtype=np.float64)
    Ut = U.T.tocsc(copy=True)
    Ut.sort_indices()
    Ut.data = Ut.data / np.repeat(d, np.diff(Ut.indptr))
    L = L.tocsc()
    mask = Ut.copy()
    mask.data[:] = 1.0
    only_l = L - L.multiply(mask)  # L's entries where U^T has none (the others cancel and drop)
    F = (Ut + only_l).tocsc() if only_l.nnz else Ut
    F.sort_indices()
    n = d.size
    A = F.copy()
    A.data = np.ones_like(A.data)  # the pattern only: a sum of ones cannot cancel
    if pairs is not None and len(pairs[0]):
        r, c = np.maximum(pairs[0], pairs[1]), np.minimum(pairs[0], pairs[1])
        A = (A + sp.csc_matrix((np.ones(r.size), (r, c)), shape=(n, n))).tocsc()
        A.sort_indices()
    indptr, indices = symbolic_factor(A.indptr.astype(np.int64), A.indices.astype(np.int64), n)
    lval, placed = _place(F.indptr.astype(np.int64), F.indices.astype(np.int64), np.asarray(F.data, dtype=np.float64), indptr, indices)
    if not placed:
        return indptr, indices, np.zeros(indices.size), False
    z, ok = takahashi(indptr, indices, lval, d)
    return indptr, indices, z, bool(ok)
