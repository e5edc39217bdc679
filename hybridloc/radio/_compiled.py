"""The Sorensen kNN search's sums of minima, compiled with Numba (:func:`.locate.sorensen_neighbours`).

For one query q (a row of represented readings) and the column-compressed references R, the sum over
the columns q holds of min(R[r, c], q[c]) for every reference r. The reference form took the query's
columns of R (scipy's column selection), replaced the entries by their minimum with the query's value
in R's dtype, widened them to float64 and multiplied by a vector of ones: scipy's ``csc_matvec`` adds
``entry * 1.0`` into each row's sum column by column in ascending column order, entries in stored
order, from zero. The loop below adds the same float64 terms in the same order, so the sums are the
same to the bit (a test holds them to a plain scatter-add of the minima); it skips the two sparse
matrices built per query, which were most of a search's time (a SLAM batch re-solve of a site1 floor
runs hundreds of thousands of these).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def sums_of_minima(indptr, indices, data, q, n):  # pragma: no cover - compiled
    """(n,) float64: sum over c with q[c] > 0 of min(data[r, c], q[c]) per row r of the CSC matrix
    (indptr, indices, data) with n rows; data and q of one dtype, the minimum taken in it."""
    out = np.zeros(n)
    for c in range(q.size):
        qc = q[c]
        if qc > 0:
            for ii in range(indptr[c], indptr[c + 1]):
                v = data[ii]
                out[indices[ii]] += v if v < qc else qc
    return out
