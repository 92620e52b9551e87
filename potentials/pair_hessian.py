"""The Hessian of a pair potential, kept as one 3x3 block per interacting pair.

A pair energy ``u(|x_i - x_j|)`` contributes a symmetric 3x3 block K to the
Hessian blocks (i, i) and (j, j) and -K to (i, j) and (j, i). A
:class:`PairHessian` stores just K's two eigenvalues and its axis for each
pair (plus the summed diagonal blocks), which is all that Newton-Krylov
solvers need:
:meth:`PairHessian.matvec` applies the Hessian without assembling it, at
about the cost of one force evaluation, and :meth:`PairHessian.tocsr`
assembles the sparse matrix for direct solvers and tests.
:class:`HessianSum` adds several such operators (and plain sparse
matrices), as a force field with several potentials needs. Because the
eigenvalues are at hand, :meth:`PairHessian.projected` gives the positive
semidefinite version that keeps Newton's method well posed on compressed,
stiff pairs.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit, prange
from numpy.typing import NDArray

from md.parallel import chunk_count

#: Fewest pairs per thread worth a chunk of their own.
_MIN_CHUNK_PAIRS = 20000

#: Element (a, b) of a 3x3 block is entry _SYMMETRIC[a, b] of its stored
#: (xx, yy, zz, yz, xz, xy).
_SYMMETRIC = np.array([[0, 5, 4], [5, 1, 3], [4, 3, 2]], dtype=np.int64)


class PairHessian:
    """A (3N, 3N) Hessian given by pair blocks.

    Every pair block of a central pair potential has the form
    K = t I + (r - t) e e^T, with e the unit vector along the pair, t the
    transverse curvature u'(r)/r (twice degenerate) and r the radial one
    u''(r); these three are all that is stored.

    Parameters
    ----------
    n_atoms : int
        N.
    pair_i, pair_j : ndarray of int32 or int64, shape (P,)
        The interacting pairs, i != j.
    transverse, radial : ndarray of float64, shape (P,)
        The eigenvalues of K [energy/length^2].
    unit : ndarray of float64, shape (P, 3)
        e, the unit vector from j to i (either sign will do).
    unique : bool
        Whether each pair is listed at most once (then :meth:`tocsr` need not
        sum duplicates).
    pieces : array_like of int, shape (C, 2), optional
        The [start, stop) runs of the five arrays above that hold the pairs,
        in order, each a chunk of the threaded products; entries between
        runs are ignored (a potential writing each thread's pairs where its
        listed pairs start leaves such gaps). Default: all entries, split
        into one chunk per thread. The attributes ``pair_i`` ... ``unit``
        give just the pairs (P = ``n_pairs``), copied into one run on first
        use if there are gaps.
    """

    def __init__(
        self,
        n_atoms: int,
        pair_i,
        pair_j,
        transverse,
        radial,
        unit,
        unique: bool = True,
        pieces=None,
    ) -> None:
        self.n_atoms = int(n_atoms)
        self.unique = unique
        self.shape = (3 * self.n_atoms, 3 * self.n_atoms)
        stored = (pair_i, pair_j, transverse, radial, unit)
        length = len(pair_i)
        if any(len(a) != length for a in stored):
            raise ValueError("pair_i, pair_j, transverse, radial and unit differ in length")
        if pieces is None:
            # One chunk per thread, each adding into its own buffer, the buffers then
            # summed in chunk order: the same result for a given thread count.
            chunks = chunk_count(length, _MIN_CHUNK_PAIRS)
            bounds = np.arange(chunks + 1) * length // chunks
            pieces = np.column_stack((bounds[:-1], bounds[1:]))
        pieces = np.array(pieces, dtype=np.int64).reshape(-1, 2)
        starts, stops = pieces[:, 0], pieces[:, 1]
        if (
            len(pieces) == 0
            or starts[0] < 0
            or stops[-1] > length
            or np.any(stops < starts)
            or np.any(starts[1:] < stops[:-1])
        ):
            raise ValueError(
                f"pieces must be ordered, non-overlapping [start, stop) runs within the "
                f"{length} stored pairs, got {pieces.tolist()}"
            )
        #: (C, 2) runs [start, stop) of the stored arrays that hold the pairs: one chunk
        #: each of the threaded products (a list's Hessian leaves gaps between them).
        self.pieces = pieces
        self.n_chunks = len(pieces)
        self.n_pairs = int(np.sum(stops - starts))
        self._stored = stored
        self._pairs = None  # the pairs in one run, made on first use
        self._partial_sums = None  # per-thread sums of matvec, allocated at its first call
        self._diagonal_blocks = None  # summed on first use: (N, 6), or (N, 3) for diagonal()
        self._diagonal = None

    def _compact(self) -> tuple:
        """The five arrays of just the pairs (views if they are one run, else copies)."""
        if self._pairs is None:
            starts, stops = self.pieces[:, 0], self.pieces[:, 1]
            if np.all(starts[1:] == stops[:-1]):
                self._pairs = tuple(a[starts[0] : stops[-1]] for a in self._stored)
            else:
                self._pairs = tuple(
                    np.concatenate([a[first:last] for first, last in self.pieces])
                    for a in self._stored
                )
        return self._pairs

    def _piece(self, k: int) -> tuple:
        """The five arrays of piece ``k``, as views."""
        first, last = self.pieces[k]
        return tuple(a[first:last] for a in self._stored)

    @property
    def pair_i(self) -> NDArray[np.integer]:
        """(P,) the first atom of each pair."""
        return self._compact()[0]

    @property
    def pair_j(self) -> NDArray[np.integer]:
        """(P,) the second atom of each pair."""
        return self._compact()[1]

    @property
    def transverse(self) -> NDArray[np.float64]:
        """(P,) t = u'(r)/r of each pair [energy/length^2]."""
        return self._compact()[2]

    @property
    def radial(self) -> NDArray[np.float64]:
        """(P,) u''(r) of each pair [energy/length^2]."""
        return self._compact()[3]

    @property
    def unit(self) -> NDArray[np.float64]:
        """(P, 3) the unit vector of each pair."""
        return self._compact()[4]

    @property
    def diagonal_blocks(self) -> NDArray[np.float64]:
        """The (N, 6) diagonal blocks (xx, yy, zz, yz, xz, xy): each atom's sum of K."""
        if self._diagonal_blocks is None:
            self._diagonal_blocks = self._summed_blocks(6)
        return self._diagonal_blocks

    def _summed_blocks(self, width: int) -> NDArray[np.float64]:
        """Each atom's sum of its pairs' K: the first ``width`` (3 or 6) entries."""
        out = np.zeros((self.n_atoms, width))
        if self.n_chunks == 1:
            _diagonal_blocks(*self._piece(0), out)
        else:
            buffers = np.empty((self.n_chunks, self.n_atoms, width))
            _diagonal_blocks_threaded(*self._stored, self.pieces, buffers, out)
        return out

    @property
    def nnz(self) -> int:
        """Stored entries of the assembled matrix: 9 per diagonal and off-diagonal block."""
        return 9 * (self.n_atoms + 2 * self.n_pairs)

    def min_eigenvalue(self) -> float:
        """Return the smallest eigenvalue of any pair block (0 without pairs) [energy/length^2]."""
        pieces = [self._piece(k) for k in range(self.n_chunks)]
        return min((float(min(p[2].min(), p[3].min())) for p in pieces if len(p[0])), default=0.0)

    def clamped(self, floor) -> PairHessian:
        """Return the Hessian with every pair block's eigenvalues raised to at least ``floor``.

        ``floor`` is a number or a (P,) array [energy/length^2]. With 0 this is
        the projection of projected Newton methods: a sum of positive
        semidefinite blocks.
        """
        return PairHessian(
            self.n_atoms,
            self.pair_i,
            self.pair_j,
            np.maximum(self.transverse, floor),
            np.maximum(self.radial, floor),
            self.unit,
            self.unique,
        )

    def negative_pairs(self) -> NDArray[np.bool_]:
        """Return the (P,) mask of pairs with a negative eigenvalue."""
        return np.minimum(self.transverse, self.radial) < 0.0

    def matvec(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Return H x for a (3N,) vector ``x``.

        The threads' partial sums go into buffers the operator keeps for its
        next product (a Krylov solver applies it several times), so one
        operator must not be applied from two threads at once.
        """
        out = np.zeros(3 * self.n_atoms)
        x = np.ascontiguousarray(x, dtype=np.float64)
        if self.n_chunks == 1:
            _pair_matvec(*self._piece(0), x, out)
        else:
            if self._partial_sums is None:
                self._partial_sums = np.empty((self.n_chunks, 3 * self.n_atoms))
            _pair_matvec_threaded(*self._stored, self.pieces, x, self._partial_sums, out)
        return out

    def diagonal(self) -> NDArray[np.float64]:
        """Return the (3N,) diagonal of H (a Jacobi preconditioner's: only the blocks'
        diagonal entries are summed, unless the blocks are already at hand)."""
        if self._diagonal_blocks is not None:
            return np.ascontiguousarray(self._diagonal_blocks[:, :3]).ravel()
        if self._diagonal is None:
            self._diagonal = self._summed_blocks(3).ravel()
        return self._diagonal.copy()

    def tocsr(self) -> sp.csr_matrix:
        """Return the assembled matrix: CSR with sorted indices, every diagonal block stored."""
        n = self.n_atoms
        counts = np.ones(n, dtype=np.int64)  # the diagonal block
        counts += np.bincount(self.pair_i, minlength=n)
        counts += np.bincount(self.pair_j, minlength=n)
        block_starts = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(counts, out=block_starts[1:])
        nnz = 9 * int(block_starts[-1])
        index_type = np.int32 if nnz < np.iinfo(np.int32).max else np.int64
        indptr = np.empty(3 * n + 1, dtype=index_type)
        indices = np.empty(nnz, dtype=index_type)
        data = np.empty(nnz)
        _pair_blocks_to_csr(
            self.pair_i,
            self.pair_j,
            self.transverse,
            self.radial,
            self.unit,
            self.diagonal_blocks,
            block_starts,
            _SYMMETRIC,
            indptr,
            indices,
            data,
        )
        matrix = sp.csr_matrix((data, indices, indptr), shape=self.shape)
        matrix.has_sorted_indices = True
        if not self.unique:
            matrix.sum_duplicates()
        return matrix


class HessianSum:
    """The sum of Hessian operators (:class:`PairHessian` or sparse matrices) of one system."""

    def __init__(self, terms) -> None:
        self.terms = list(terms)
        self.shape = self.terms[0].shape

    @property
    def nnz(self) -> int:
        """An upper bound on the stored entries of the assembled sum."""
        return sum(term.nnz for term in self.terms)

    def matvec(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Return H x for a (3N,) vector ``x``."""
        out = self.terms[0] @ x if sp.issparse(self.terms[0]) else self.terms[0].matvec(x)
        for term in self.terms[1:]:
            out += term @ x if sp.issparse(term) else term.matvec(x)
        return out

    def diagonal(self) -> NDArray[np.float64]:
        """Return the (3N,) diagonal of H."""
        total = self.terms[0].diagonal()
        for term in self.terms[1:]:
            total = total + term.diagonal()
        return total

    def min_eigenvalue(self) -> float:
        """Return the smallest pair-block eigenvalue of the pair terms (0 without any)."""
        return min(
            (term.min_eigenvalue() for term in self.terms if isinstance(term, PairHessian)),
            default=0.0,
        )

    def definite(self, h2: float, masses: NDArray[np.float64]) -> HessianSum:
        """Return the sum with pair curvatures clamped so that M + h2 H is positive definite.

        Only pairs with a negative eigenvalue change. The mass m_i of atom i
        is shared among its c_i such pairs, a_i = m_i / c_i, and a pair's
        eigenvalues are raised to -(1 - 1e-6) a_i a_j / (h2 (a_i + a_j)), the
        lowest at which the pair with its mass shares stays positive
        semidefinite; the sum is then positive definite. Pairs whose
        curvature is above that bound keep their exact blocks, so where the
        masses dominate this is the exact Hessian. Sparse-matrix terms are
        kept as they are (they may still be indefinite).

        Parameters
        ----------
        h2 : float
            The squared step h^2 of the incremental potential [time^2].
        masses : ndarray, shape (N,)
            Particle masses [mass].
        """
        pairs = [term for term in self.terms if isinstance(term, PairHessian)]
        n = len(masses)
        counts = np.zeros(n)
        for term in pairs:
            negative = term.negative_pairs()
            counts += np.bincount(term.pair_i[negative], minlength=n)
            counts += np.bincount(term.pair_j[negative], minlength=n)
        shares = masses / np.maximum(counts, 1.0)
        out = []
        for term in self.terms:
            if isinstance(term, PairHessian):
                a_i, a_j = shares[term.pair_i], shares[term.pair_j]
                term = term.clamped(-(1.0 - 1e-6) * a_i * a_j / (h2 * (a_i + a_j)))
            out.append(term)
        return HessianSum(out)

    def tocsr(self) -> sp.csr_matrix:
        """Return the assembled sum as a CSR matrix."""
        total = None
        for term in self.terms:
            matrix = sp.csr_matrix(term) if sp.issparse(term) else term.tocsr()
            total = matrix if total is None else total + matrix
        return total


# ------------------------------------------------------------------ kernels
@njit(cache=True)
def _block(t, r, e, out):
    """Write K = t I + (r - t) e e^T as (xx, yy, zz, yz, xz, xy) into ``out`` (6,)."""
    c = r - t
    out[0] = t + c * e[0] * e[0]
    out[1] = t + c * e[1] * e[1]
    out[2] = t + c * e[2] * e[2]
    out[3] = c * e[1] * e[2]
    out[4] = c * e[0] * e[2]
    out[5] = c * e[0] * e[1]


@njit(cache=True)
def _diagonal_blocks(pair_i, pair_j, transverse, radial, unit, diagonal):
    """Add each pair's K to the diagonal blocks (N, 6) of both its atoms, or, for an
    (N, 3) ``diagonal``, just their diagonal entries (xx, yy, zz).

    K = t I + (r - t) e e^T written out in scalars (as ``_block`` does):
    ``_block``'s output row per pair cost as much as the arithmetic.
    """
    if diagonal.shape[1] == 3:
        _diagonal_blocks_loop(pair_i, pair_j, transverse, radial, unit, diagonal, False)
    else:
        _diagonal_blocks_loop(pair_i, pair_j, transverse, radial, unit, diagonal, True)


@njit(cache=True, inline="always")
def _diagonal_blocks_loop(pair_i, pair_j, transverse, radial, unit, diagonal, full):
    """The loop of ``_diagonal_blocks``; ``full``: all six entries (a constant here)."""
    n_pairs = pair_i.shape[0]
    if n_pairs == 0:
        return
    # Atom i's block summed in registers over a run of pairs with the same i (as
    # in ``_pair_matvec``), atom j's added per pair.
    current = pair_i[0]
    s0 = s1 = s2 = s3 = s4 = s5 = 0.0
    for p in range(n_pairs):
        i = pair_i[p]
        if i != current:
            _add_block(diagonal, current, s0, s1, s2, s3, s4, s5, full)
            s0 = s1 = s2 = s3 = s4 = s5 = 0.0
            current = i
        t = transverse[p]
        c = radial[p] - t
        ex = unit[p, 0]
        ey = unit[p, 1]
        ez = unit[p, 2]
        b0 = t + c * ex * ex
        b1 = t + c * ey * ey
        b2 = t + c * ez * ez
        s0 += b0
        s1 += b1
        s2 += b2
        if full:
            b3 = c * ey * ez
            b4 = c * ex * ez
            b5 = c * ex * ey
            s3 += b3
            s4 += b4
            s5 += b5
        else:
            b3 = b4 = b5 = 0.0
        _add_block(diagonal, pair_j[p], b0, b1, b2, b3, b4, b5, full)
    _add_block(diagonal, current, s0, s1, s2, s3, s4, s5, full)


@njit(cache=True, inline="always")
def _add_block(diagonal, atom, b0, b1, b2, b3, b4, b5, full):
    """diagonal[atom] += (b0, ..., b5), or (b0, b1, b2) unless ``full``."""
    diagonal[atom, 0] += b0
    diagonal[atom, 1] += b1
    diagonal[atom, 2] += b2
    if full:
        diagonal[atom, 3] += b3
        diagonal[atom, 4] += b4
        diagonal[atom, 5] += b5


@njit(cache=True, fastmath={"contract"})
def _pair_matvec(pair_i, pair_j, transverse, radial, unit, x, out):
    """Add H x to ``out`` (3N,): K (x_i - x_j) to row i and its negative to row j.

    K d = t d + (r - t) (e . d) e, so no block is formed, and the diagonal
    blocks (the sums of K over each atom's pairs) need not be read: the
    difference form has one product with K per pair where the split form
    (K x_i and K x_j, plus the diagonal blocks) has two. Entries are indexed
    by unsigned integers: a signed index costs a wrap-around test per access.
    """
    n_pairs = pair_i.shape[0]
    if n_pairs == 0:
        return
    # Pairs come in runs with the same i (a slot's partners in a neighbour-list
    # Hessian): row i's terms are summed in registers over the run and written once,
    # instead of a read-modify-write of out[i] per pair that the next pair waits for.
    three = np.uint64(3)
    current = pair_i[0]
    row = three * np.uint64(current)
    xi0, xi1, xi2 = x[row], x[row + 1], x[row + 2]
    s0 = s1 = s2 = 0.0
    for p in range(n_pairs):
        i = pair_i[p]
        if i != current:
            out[row] += s0
            out[row + 1] += s1
            out[row + 2] += s2
            s0 = s1 = s2 = 0.0
            current = i
            row = three * np.uint64(i)
            xi0, xi1, xi2 = x[row], x[row + 1], x[row + 2]
        column = three * np.uint64(pair_j[p])
        d0 = xi0 - x[column]
        d1 = xi1 - x[column + 1]
        d2 = xi2 - x[column + 2]
        t = transverse[p]
        e0, e1, e2 = unit[p, 0], unit[p, 1], unit[p, 2]
        along = (radial[p] - t) * (e0 * d0 + e1 * d1 + e2 * d2)
        k0 = t * d0 + along * e0
        k1 = t * d1 + along * e1
        k2 = t * d2 + along * e2
        s0 += k0
        s1 += k1
        s2 += k2
        out[column] -= k0
        out[column + 1] -= k1
        out[column + 2] -= k2
    out[row] += s0
    out[row + 1] += s1
    out[row + 2] += s2


@njit(cache=True, parallel=True)
def _diagonal_blocks_threaded(pair_i, pair_j, transverse, radial, unit, pieces, buffers, diagonal):
    """``_diagonal_blocks`` on numba's threads: the pairs of piece c (``pieces[c]``, a
    [start, stop) run) into ``buffers[c]`` (C, N, 6), then the buffers summed in chunk
    order into ``diagonal`` (zeroed)."""
    n_chunks = buffers.shape[0]
    n = diagonal.shape[0]
    for c in prange(n_chunks):
        buffers[c, :, :] = 0.0
        first, last = pieces[c, 0], pieces[c, 1]
        _diagonal_blocks(
            pair_i[first:last],
            pair_j[first:last],
            transverse[first:last],
            radial[first:last],
            unit[first:last],
            buffers[c],
        )
    for c in prange(n_chunks):
        for i in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            for k in range(diagonal.shape[1]):
                total = buffers[0, i, k]
                for other in range(1, n_chunks):
                    total += buffers[other, i, k]
                diagonal[i, k] = total


@njit(cache=True, parallel=True)
def _pair_matvec_threaded(pair_i, pair_j, transverse, radial, unit, pieces, x, buffers, out):
    """``_pair_matvec`` on numba's threads: the pairs of piece c (``pieces[c]``) into
    ``buffers[c]`` (C, 3N), then the buffers summed per entry, in chunk order."""
    n_chunks = buffers.shape[0]
    size = x.shape[0]
    for c in prange(n_chunks):
        buffers[c, :] = 0.0
        first, last = pieces[c, 0], pieces[c, 1]
        _pair_matvec(
            pair_i[first:last],
            pair_j[first:last],
            transverse[first:last],
            radial[first:last],
            unit[first:last],
            x,
            buffers[c],
        )
    for c in prange(n_chunks):
        for k in range(c * size // n_chunks, (c + 1) * size // n_chunks):
            total = buffers[0, k]
            for other in range(1, n_chunks):
                total += buffers[other, k]
            out[k] += total


@njit(cache=True)
def _pair_blocks_to_csr(
    pair_i,
    pair_j,
    transverse,
    radial,
    unit,
    diagonal,
    block_starts,
    symmetric,
    indptr,
    indices,
    data,
):
    """Expand pair blocks into CSR arrays, block columns sorted within each row.

    ``block_starts`` (N + 1,) offsets each atom's blocks: its diagonal block
    plus one per pair it belongs to.
    """
    n = diagonal.shape[0]
    n_pairs = pair_i.shape[0]
    blocks = np.empty((n_pairs, 6))
    for p in range(n_pairs):
        _block(transverse[p], radial[p], unit[p], blocks[p])
    n_blocks = block_starts[n]
    block_columns = np.empty(n_blocks, dtype=np.int64)
    block_sources = np.empty(n_blocks, dtype=np.int64)  # pair index, or -1: diagonal
    cursor = np.empty(n, dtype=np.int64)
    for i in range(n):
        block_columns[block_starts[i]] = i
        block_sources[block_starts[i]] = -1
        cursor[i] = block_starts[i] + 1
    for p in range(n_pairs):
        i = pair_i[p]
        j = pair_j[p]
        block_columns[cursor[i]] = j
        block_sources[cursor[i]] = p
        cursor[i] += 1
        block_columns[cursor[j]] = i
        block_sources[cursor[j]] = p
        cursor[j] += 1
    indptr[0] = 0
    for i in range(n):
        first = block_starts[i]
        count = block_starts[i + 1] - first
        order = np.argsort(block_columns[first : first + count])
        for ca in range(3):
            out = 9 * first + 3 * count * ca
            indptr[3 * i + ca + 1] = out + 3 * count
            for q in range(count):
                slot = first + order[q]
                column = 3 * block_columns[slot]
                source = block_sources[slot]
                for cb in range(3):
                    indices[out] = column + cb
                    if source < 0:
                        data[out] = diagonal[i, symmetric[ca, cb]]
                    else:
                        data[out] = -blocks[source, symmetric[ca, cb]]
                    out += 1
