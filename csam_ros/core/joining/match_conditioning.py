"""Algorithm 1's state conditioned on Algorithm 2's accepted matches (docs/METHOD.md section
6.1): the posterior shift of the state and its covariance by blocks, and each match's
leave-one-out distance.

Every accepted match ``k`` (feature ``i`` of robot ``a`` is feature ``j`` of robot ``c``) is a
linear measurement ``nu_k + H_k ds = 0`` of the state's step ``ds`` from Algorithm 1's
estimate, with noise ``N_k``; ``H_k = [G_i | -G_j]`` is non-zero on the two robots' rendezvous
poses and base nodes only (:mod:`~csam_ros.core.joining.association`). Two equal forms:

- information form (:class:`SparseConditioning`, what joins use): ``Lambda_post = Lambda +
  sum_k H_k^T N_k^-1 H_k`` on the blocks of Algorithm 1's information ``Lambda`` (one block
  per robot's rendezvous poses, one of the base nodes: :mod:`~csam_ros.core.joining.
  block_cholesky`), a match adding to the blocks of its two robots and of the base nodes;
  ``ds = -Lambda_post^-1 sum_k H_k^T N_k^-1 nu_k``; ``Sigma_post`` by the factor's selected
  inverse, only on the blocks of the factor's pattern. So its cost follows the robots that
  matched and the blocks they touch, not the cube of the state.
- Kalman form (:func:`condition_dense`, the tests' oracle and the path of the dense
  Algorithm 1): ``S = N + H P H^T``, ``Sigma_post = P - (H P)^T S^-1 H P`` on the whole
  state.

Leave-one-out distance of match ``k``: ``e_k^T (N_k - H_k Sigma_post H_k^T)^-1 e_k`` with
``e_k = nu_k + H_k ds`` its posterior residual (the distance to the state conditioned on
every other match).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

from csam_ros.core.joining.state_covariance import FactoredStateCovariance
from csam_ros.core.sam.block_cholesky import BlockFactor, BlockPattern, factor_blocks
from csam_ros.core.sam.normal_equations import SingularProblemError

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class RobotGains(Protocol):
    """One robot's features linearised on the state (``association._GlobalFeatures``)."""

    position: Array  # (F, 2)
    compact: Array  # (F, 2, m): the gain on ``columns``
    noise: Array  # (F, 2, 2)
    columns: IntArray  # (m,) state columns


def stacked_product(stack: Array, matrix: Array) -> Array:
    """``stack @ matrix`` for a stack (..., p, m) and one matrix (m, n) or vector (m,), as one
    BLAS product (NumPy's ``@`` would multiply each matrix of the stack on its own)."""
    flat = stack.reshape(-1, stack.shape[-1]) @ matrix
    return flat.reshape(*stack.shape[:-1], *matrix.shape[1:])


def stacked_congruence(stack: Array, matrix: Array) -> Array:
    """``stack @ matrix @ stack^T`` (K, p, p) for a stack (K, p, m) and one matrix (m, m)."""
    return np.einsum("kim,kjm->kij", stacked_product(stack, matrix), stack)


# a match: robot a, its feature index i, robot c, its feature index j
MatchIndex = tuple[int, int, int, int]


class ConditionedState(Protocol):
    """The state after conditioning on matches."""

    shift: Array  # (d,) posterior minus Algorithm 1's estimate

    def block(self, rows: IntArray, cols: IntArray) -> Array:
        """``Sigma_post[rows, cols]``."""
        ...

    def covers(self, rows: IntArray, cols: IntArray) -> bool:
        """Whether :meth:`block` can answer for these rows and columns."""
        ...


@dataclass
class _PairRows:
    """The matches of one robot pair ``(a, c)``: their positions in the list of matches,
    residuals (K, 2), Jacobians (K, 2, m_a + m_c) on the two robots' state columns ``cols``
    and noise (K, 2, 2)."""

    index: IntArray
    nu: Array
    h: Array
    noise: Array
    cols: IntArray


def _match_rows(glob: dict[int, RobotGains], pairs: Sequence[MatchIndex]) -> list[_PairRows]:
    """The matches ``pairs`` grouped by robot pair (:class:`_PairRows`)."""
    arr = np.asarray(pairs, dtype=np.int64).reshape(-1, 4)
    if not len(arr):
        return []
    keys = arr[:, 0] * (arr[:, 2].max() + 1) + arr[:, 2]
    order = np.argsort(keys, kind="stable")
    cuts = np.flatnonzero(np.diff(keys[order])) + 1
    out = []
    for idx in np.split(order, cuts):
        a, c = int(arr[idx[0], 0]), int(arr[idx[0], 2])
        i, j = arr[idx, 1], arr[idx, 3]
        ga, gc = glob[a], glob[c]
        out.append(
            _PairRows(
                idx,
                ga.position[i] - gc.position[j],
                np.concatenate([ga.compact[i], -gc.compact[j]], axis=2),
                ga.noise[i] + gc.noise[j],
                np.concatenate([ga.columns, gc.columns]),
            )
        )
    return out


# --------------------------------------------------------------------------- information form


class StateInformation:
    """Algorithm 1's information at its estimate, by blocks (from its
    :class:`~csam_ros.core.joining.state_covariance.FactoredStateCovariance`), and where each
    state column lies in them."""

    def __init__(self, covariance: FactoredStateCovariance) -> None:
        if covariance.information is None:
            raise ValueError("the state's covariance holds no information matrix")
        self.covariance = covariance
        self.pattern: BlockPattern = covariance.factor.pattern
        self.data = covariance.information
        n = self.pattern.n
        self.position = np.empty(n, dtype=np.int64)
        self.local = np.empty(n, dtype=np.int64)
        for p, scalars in enumerate(self.pattern.scalars):
            self.position[scalars] = p
            self.local[scalars] = np.arange(len(scalars))
        self._splits: dict[bytes, list[tuple[int, Index, Index]]] = {}

    def block_pairs(self, rows: IntArray, cols: IntArray) -> set[tuple[int, int]]:
        """The blocks ``(p, q)``, ``p >= q``, that hold ``Lambda[rows, cols]``."""
        ps, qs = np.unique(self.position[rows]), np.unique(self.position[cols])
        return {(int(max(p, q)), int(min(p, q))) for p in ps for q in qs}

    def split(self, cols: IntArray) -> list[tuple[int, Index, Index]]:
        """``cols`` by block: each block's position, where its columns are in ``cols`` and
        where in the block (slices where contiguous), kept."""
        key = cols.tobytes()
        out = self._splits.get(key)
        if out is None:
            where = self.position[cols]
            out = []
            for p in np.unique(where):
                sel = np.flatnonzero(where == p)
                out.append((int(p), _as_slice(sel), _as_slice(self.local[cols[sel]])))
            self._splits[key] = out
        return out


Index = slice | IntArray


def _as_slice(index: IntArray) -> Index:
    """A slice where ``index`` is a contiguous ascending range (a view, not a copy)."""
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


class SparseState:
    """The conditioned state: the selected inverse ``Sigma_M`` of a factor of the information
    with the matches ``M``, corrected by ``U C U^T`` for the matches added or removed since
    (``Sigma = Sigma_M + U C U^T``, Woodbury)."""

    def __init__(
        self,
        information: StateInformation,
        shift: Array,
        inverse: dict[tuple[int, int], Array],
        correction: tuple[Array, Array] | None = None,
        blocks: dict[tuple[bytes, bytes], Array] | None = None,
    ) -> None:
        self.information = information
        self.shift = shift
        self._inverse = inverse
        self._correction = correction
        self._blocks = {} if blocks is None else blocks  # shared by uncorrected states

    def covers(self, rows: IntArray, cols: IntArray) -> bool:
        return self.information.block_pairs(rows, cols) <= set(self._inverse)

    def block(self, rows: IntArray, cols: IntArray) -> Array:
        key = (rows.tobytes(), cols.tobytes())
        out = self._blocks.get(key)
        if out is None:
            out = np.empty((len(rows), len(cols)))
            split = self.information.split
            for p, r_sel, lr in split(rows):
                for q, c_sel, lc in split(cols):
                    if p >= q:
                        part = self._inverse[p, q][lr][:, lc]
                    else:
                        part = self._inverse[q, p][lc][:, lr].T
                    if isinstance(r_sel, slice) or isinstance(c_sel, slice):
                        out[r_sel, c_sel] = part
                    else:
                        out[np.ix_(r_sel, c_sel)] = part
            if self._correction is not None:
                u, c = self._correction
                out += u[rows] @ c @ u[cols].T
            self._blocks[key] = out
        return out


def low_rank_rows(factor: BlockFactor) -> float:
    """Rows of matches changed since a factorisation up to which a low-rank (Woodbury)
    correction is cheaper than factoring again: the factor's multiply-adds per nonzero. A
    correction passes over the factor twice per row; a factorisation with its selected inverse
    does about three times its multiply-adds, at a third of the solves' speed per operation.
    Measured: MR.CLAM Dataset 1 (371 rows by this ratio), a factorisation 0.32 s, a correction
    0.74 ms a row; a ring of 64 robots (437 rows), 0.9-1.4 s and 1.5 ms."""
    return factor.flops / factor.nonzeros


class SparseConditioning:
    """The state conditioned on sets of matches in the information form (module docs),
    factored again only when the set changed by more than :func:`low_rank_rows` rows since
    the last factorisation (else corrected by Woodbury's identity) or when the structure grew.
    Each match's ``H_k Sigma_M H_k^T`` and ``U_k = Sigma_M H_k^T`` are kept between calls, so a
    correction costs two solves per match changed since the last call, and the matches'
    products with ``U``, not with the covariance blocks.

    ``couple`` (robot pairs) extends the structure for good: block pairs kept in the factor's
    pattern even where zero, so that :meth:`SparseState.block` covers the pairs' joint
    covariance."""

    def __init__(self, information: StateInformation, glob: dict[int, RobotGains]) -> None:
        self.information = information
        self.glob = glob
        self.structure: set[tuple[int, int]] = set()
        self.factorisations = 0
        self._factored: list[MatchIndex] = []
        self._factor: BlockFactor | None = None  # None: Algorithm 1's own
        self._inverse: dict[tuple[int, int], Array] = {}
        self._explained: dict[MatchIndex, Array] = {}  # H_k Sigma_M H_k^T
        self._columns: dict[MatchIndex, Array] = {}  # U_k = Sigma_M H_k^T (d, 2)
        self._factored_shift = np.zeros(0)  # Sigma_M times the factored matches' vector
        self._uncorrected: SparseState | None = None  # Sigma_M's blocks, kept

    def __call__(
        self, pairs: list[MatchIndex], couple: Sequence[tuple[int, int]] = ()
    ) -> tuple[SparseState, Array]:
        for a, c in couple:
            self.structure |= self.information.block_pairs(
                self.glob[a].columns, self.glob[c].columns
            )
        factored = set(self._factored)
        added = [m for m in pairs if m not in factored]
        kept = set(pairs)
        removed = [m for m in self._factored if m not in kept]
        rows = _match_rows(self.glob, pairs)
        if (
            self._uncorrected is None
            or not self.structure <= set(self._inverse)
            or 2 * (len(added) + len(removed)) > low_rank_rows(self._current_factor)
        ):
            self._factorise(pairs, rows)
            added, removed = [], []
        assert self._uncorrected is not None
        if not (added or removed):
            state = SparseState(
                self.information,
                self._factored_shift,
                self._inverse,
                blocks=self._uncorrected._blocks,
            )
            return state, self._leave_one_out(pairs, rows, state, None)
        changed = added + removed
        nu, flat, noise = stack_sparse(self.glob, changed, self.information.pattern.n)  # H_X
        unknown = [k for k, m in enumerate(changed) if m not in self._columns]
        if unknown:
            unknown_rows = (2 * np.asarray(unknown)[:, None] + np.arange(2)).reshape(-1)
            solved = self._solve(flat[unknown_rows].T.toarray())
            for n_, k in enumerate(unknown):
                self._columns[changed[k]] = solved[:, 2 * n_ : 2 * n_ + 2]
        u = np.concatenate([self._columns[m] for m in changed], axis=1)  # Sigma_M H_X^T
        sign = np.repeat(np.r_[np.ones(len(added)), -np.ones(len(removed))], 2)
        inner = flat @ u + _block_diagonal(noise) * sign[:, None]  # W^-1 + H_X U
        c = -np.linalg.inv(0.5 * (inner + inner.T))
        # Sigma_M times the information vector of ``pairs``: the factored matches' step, less
        # the added matches' terms, plus the removed ones' (Sigma_M H_k^T = U_k)
        weighted = np.linalg.solve(noise, nu[:, :, None]).reshape(-1)  # N_k^-1 nu_k
        own = self._factored_shift - u @ (sign * weighted)
        shift = own + u @ (c @ (flat @ own))
        state = SparseState(self.information, shift, self._inverse, (u, c))
        return state, self._leave_one_out(pairs, rows, state, (u, c))

    def _leave_one_out(
        self,
        pairs: list[MatchIndex],
        rows: list[_PairRows],
        state: SparseState,
        correction: tuple[Array, Array] | None,
    ) -> Array:
        """Each match's leave-one-out distance (module docs): ``H_k Sigma_M H_k^T`` from the
        kept blocks of ``Sigma_M``, plus the correction's ``(H_k U) C (H_k U)^T``."""
        assert self._uncorrected is not None
        loo = np.empty(len(pairs))
        for pair in rows:
            keys = [pairs[k] for k in pair.index]
            missing = [i for i, key in enumerate(keys) if key not in self._explained]
            if missing:
                h = pair.h[missing]
                sigma = self._uncorrected.block(pair.cols, pair.cols)
                explained = stacked_congruence(h, sigma)
                self._explained.update(
                    (keys[i], e) for i, e in zip(missing, explained, strict=True)
                )
            explained = np.stack([self._explained[key] for key in keys])
            if correction is not None:
                u, c = correction
                t = stacked_product(pair.h, u[pair.cols])  # (K, 2, 2X)
                explained = explained + stacked_congruence(t, c)
            resid = pair.nu + stacked_product(pair.h, state.shift[pair.cols])
            v = pair.noise - 0.5 * (explained + explained.swapaxes(1, 2))
            loo[pair.index] = np.einsum(
                "ki,ki->k", resid, np.linalg.solve(v, resid[:, :, None])[:, :, 0]
            )
        return loo

    @property
    def _current_factor(self) -> BlockFactor:
        """The factor of the last factorisation, or Algorithm 1's own."""
        return self._factor or self.information.covariance.factor

    def _solve(self, rhs: Array) -> Array:
        return self._current_factor.solve(rhs)

    def _factorise(self, pairs: list[MatchIndex], rows: list[_PairRows]) -> None:
        """Factor the information with ``pairs`` and the structure; its selected inverse."""
        self._factored = list(pairs)
        self._explained = {}
        self._columns = {}
        own = self.information.covariance
        if not pairs and self.structure <= set(own.selected_inverse()):
            self._factor = None
            self._inverse = own.selected_inverse()
        else:
            pattern = self.information.pattern
            blocks = pattern.blocks(self.information.data)
            for pair in rows:
                h = pair.h.reshape(-1, pair.h.shape[2])
                added = h.T @ np.linalg.solve(pair.noise, pair.h).reshape(h.shape)  # H^T N^-1 H
                _scatter(self.information, blocks, pair.cols, 0.5 * (added + added.T))
            for p, q in self.structure:
                if (p, q) not in blocks:
                    blocks[p, q] = np.zeros((pattern.sizes[p], pattern.sizes[q]))
            factor = factor_blocks(pattern, blocks)
            if factor is None:
                raise SingularProblemError("Algorithm 1's information conditioned on the matches")
            self.factorisations += 1
            self._factor = factor
            self._inverse = factor.selected_inverse()
        self._uncorrected = SparseState(self.information, np.zeros(0), self._inverse)
        self._factored_shift = self._solve(_information_vector(self.information.pattern.n, rows))


def _information_vector(n: int, rows: list[_PairRows]) -> Array:
    """``-sum_k H_k^T N_k^-1 nu_k`` (n,)."""
    rhs = np.zeros(n)
    for pair in rows:
        weighted = np.linalg.solve(pair.noise, pair.nu[:, :, None])[:, :, 0]  # N^-1 nu
        rhs[pair.cols] -= np.einsum("kim,ki->m", pair.h, weighted)
    return rhs


def _block_diagonal(blocks: Array) -> Array:
    """(K, 2, 2) blocks as one (2K, 2K) block-diagonal matrix."""
    k = len(blocks)
    out = np.zeros((2 * k, 2 * k))
    pick = np.arange(k)
    out.reshape(k, 2, k, 2)[pick, :, pick, :] = blocks
    return out


def _scatter(
    information: StateInformation,
    blocks: dict[tuple[int, int], Array],
    cols: IntArray,
    added: Array,
) -> None:
    """Add ``added`` (on state columns ``cols``) into the matrix's blocks."""
    position, local, sizes = information.position, information.local, information.pattern.sizes
    where = position[cols]
    for p in np.unique(where):
        sel_p = np.flatnonzero(where == p)
        for q in np.unique(where[where <= p]):
            sel_q = np.flatnonzero(where == q)
            key = (int(p), int(q))
            target = blocks.get(key)
            if target is None:
                target = blocks[key] = np.zeros((sizes[key[0]], sizes[key[1]]))
            target[np.ix_(local[cols[sel_p]], local[cols[sel_q]])] += added[np.ix_(sel_p, sel_q)]


# --------------------------------------------------------------------------- Kalman form


class DenseState:
    """The conditioned state in the Kalman form: ``Sigma_post = P - (H P)^T S^-1 H P`` formed
    only on the blocks asked for."""

    def __init__(self, shift: Array, prior: Array, hp: Array, gain_t: Array) -> None:
        self.shift = shift  # (d,)
        self.prior = prior  # (d, d) P
        self.hp = hp  # (2K, d) H P
        self.gain_t = gain_t  # (2K, d) S^-1 H P
        self._blocks: dict[tuple[bytes, bytes], Array] = {}

    def covers(self, rows: IntArray, cols: IntArray) -> bool:
        return True

    def block(self, rows: IntArray, cols: IntArray) -> Array:
        """``Sigma_post[rows, cols]`` (symmetrised as the whole matrix would be), kept."""
        key = (rows.tobytes(), cols.tobytes())
        out = self._blocks.get(key)
        if out is None:
            prior = self.prior[np.ix_(rows, cols)] + self.prior[np.ix_(cols, rows)].T
            update = self.hp[:, rows].T @ self.gain_t[:, cols]
            update += self.gain_t[:, rows].T @ self.hp[:, cols]
            out = self._blocks[key] = 0.5 * (prior - update)
        return out

    @property
    def covariance(self) -> Array:
        """The whole ``Sigma_post`` (d, d)."""
        every = np.arange(len(self.prior))
        return self.block(every, every)


def stack_dense(
    glob: dict[int, RobotGains], pairs: Sequence[MatchIndex], dim: int
) -> tuple[Array, Array, Array]:
    """Residuals (K, 2), Jacobians on the whole state (K, 2, dim) and noise (K, 2, 2): the
    dense form of :func:`stack_sparse`."""
    nu, jacobian, noise = stack_sparse(glob, pairs, dim)
    return nu, jacobian.toarray().reshape(len(pairs), 2, dim), noise


def stack_sparse(
    glob: dict[int, RobotGains], pairs: Sequence[MatchIndex], dim: int
) -> tuple[Array, sp.csr_matrix, Array]:
    """Residuals (K, 2), Jacobians on the whole state as one sparse (2K, dim) matrix (each
    match's two rows on its two robots' columns only) and noise (K, 2, 2)."""
    nu = np.empty((len(pairs), 2))
    noise = np.empty((len(pairs), 2, 2))
    none = np.zeros(0, dtype=np.int64)
    rows, cols, values = [none], [none], [np.zeros(0)]  # concatenated: no match, no entry
    for pair in _match_rows(glob, pairs):
        nu[pair.index], noise[pair.index] = pair.nu, pair.noise
        own = (2 * pair.index[:, None] + np.arange(2)).reshape(-1)  # (2k,)
        rows.append(np.repeat(own, len(pair.cols)))
        cols.append(np.tile(pair.cols, len(own)))
        values.append(pair.h.reshape(-1))
    jacobian = sp.csr_matrix(
        (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
        shape=(2 * len(pairs), dim),
    )
    return nu, jacobian, noise


def condition_dense(
    prior_covariance: Array, glob: dict[int, RobotGains], pairs: Sequence[MatchIndex]
) -> tuple[DenseState, Array]:
    """The state conditioned on matches ``pairs`` in the Kalman form (module docs) and their
    leave-one-out distances; ``H Sigma_post H^T = A - A S^-1 A`` with ``A = H P H^T``."""
    d = len(prior_covariance)
    if not pairs:
        none = np.zeros((0, d))
        return DenseState(np.zeros(d), prior_covariance, none, none), np.zeros(0)
    nu, h, noise = stack_dense(glob, pairs, d)
    k = len(pairs)
    rows = h.reshape(2 * k, d)
    hp = rows @ prior_covariance
    a_mat = rows @ hp.T
    innovation = a_mat + _block_diagonal(noise)
    factor = cho_factor(0.5 * (innovation + innovation.T))
    gain_t = cho_solve(factor, hp)
    shift = -gain_t.T @ nu.reshape(-1)
    resid = nu + h @ shift
    explained = a_mat @ cho_solve(factor, a_mat)
    posterior = a_mat - 0.5 * (explained + explained.T)
    pick = np.arange(k)
    v = noise - posterior.reshape(k, 2, k, 2)[pick, :, pick, :]
    loo = np.einsum("ki,ki->k", resid, np.linalg.solve(v, resid[:, :, None])[:, :, 0])
    return DenseState(shift, prior_covariance, hp, gain_t), loo
