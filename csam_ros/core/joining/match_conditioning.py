"""Algorithm 1's state conditioned on Algorithm 2's accepted matches (docs/METHOD.md section
6.1): the posterior shift of the state and its covariance by blocks, and each match's
leave-one-out distance.

Every accepted match ``k`` (feature ``i`` of robot ``a`` is feature ``j`` of robot ``c``) is a
linear measurement ``nu_k + H_k ds = 0`` of the state's step ``ds`` from Algorithm 1's
estimate, with noise ``N_k``; ``H_k = [G_i | -G_j]`` is non-zero on the two robots' rendezvous
poses and base nodes only (:mod:`~csam_ros.core.joining.association`). Two equal forms:

- information form (:func:`condition_sparse`, what joins use): ``Lambda_post = Lambda +
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
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

from csam_ros.core.joining.block_cholesky import BlockPattern, factor_blocks
from csam_ros.core.joining.state_covariance import FactoredStateCovariance
from csam_ros.core.sam.normal_equations import SingularProblemError

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class RobotGains(Protocol):
    """One robot's features linearised on the state (``association._GlobalFeatures``)."""

    position: Array  # (F, 2)
    compact: Array  # (F, 2, m): the gain on ``columns``
    noise: Array  # (F, 2, 2)
    columns: IntArray  # (m,) state columns


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


def _groups(pairs: Sequence[MatchIndex]) -> dict[tuple[int, int], IntArray]:
    """Positions in ``pairs`` of the matches of each robot pair ``(a, c)``."""
    arr = np.asarray(pairs, dtype=np.int64).reshape(-1, 4)
    keys = arr[:, 0] * (arr[:, 2].max() + 1 if len(arr) else 1) + arr[:, 2]
    out: dict[tuple[int, int], IntArray] = {}
    for key in np.unique(keys):
        idx = np.flatnonzero(keys == key)
        out[int(arr[idx[0], 0]), int(arr[idx[0], 2])] = idx
    return out


def _pair_rows(
    glob: dict[int, RobotGains], a: int, c: int, i: IntArray, j: IntArray
) -> tuple[Array, Array, Array, IntArray]:
    """Residuals (K, 2), Jacobians (K, 2, m_a + m_c) on the two robots' columns, noise
    (K, 2, 2) and those columns, of matches ``(a, i[k], c, j[k])``."""
    ga, gc = glob[a], glob[c]
    nu = ga.position[i] - gc.position[j]
    h = np.concatenate([ga.compact[i], -gc.compact[j]], axis=2)
    return nu, h, ga.noise[i] + gc.noise[j], np.concatenate([ga.columns, gc.columns])


def _leave_one_out(nu: Array, h: Array, noise: Array, shift: Array, posterior: Array) -> Array:
    """Leave-one-out distances (K,) of matches with residuals ``nu``, Jacobians ``h`` on
    columns whose posterior shift is ``shift`` and covariance ``posterior`` (module docs)."""
    resid = nu + h @ shift
    explained = np.einsum("kim,mn,kjn->kij", h, posterior, h, optimize=True)
    v = noise - 0.5 * (explained + explained.swapaxes(1, 2))
    return np.einsum("ki,ki->k", resid, np.linalg.solve(v, resid[:, :, None])[:, :, 0])


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

    def block_pairs(self, rows: IntArray, cols: IntArray) -> set[tuple[int, int]]:
        """The blocks ``(p, q)``, ``p >= q``, that hold ``Lambda[rows, cols]``."""
        ps, qs = np.unique(self.position[rows]), np.unique(self.position[cols])
        return {(int(max(p, q)), int(min(p, q))) for p in ps for q in qs}


class SparseState:
    """The conditioned state from the selected inverse of its information's factor."""

    def __init__(self, information: StateInformation, shift: Array, inverse: dict) -> None:
        self.information = information
        self.shift = shift
        self._inverse = inverse
        self._blocks: dict[tuple[bytes, bytes], Array] = {}

    def covers(self, rows: IntArray, cols: IntArray) -> bool:
        return self.information.block_pairs(rows, cols) <= set(self._inverse)

    def block(self, rows: IntArray, cols: IntArray) -> Array:
        key = (rows.tobytes(), cols.tobytes())
        out = self._blocks.get(key)
        if out is None:
            info = self.information
            out = np.empty((len(rows), len(cols)))
            pr, pc = info.position[rows], info.position[cols]
            for p in np.unique(pr):
                r_sel = np.flatnonzero(pr == p)
                for q in np.unique(pc):
                    c_sel = np.flatnonzero(pc == q)
                    lr, lc = info.local[rows[r_sel]], info.local[cols[c_sel]]
                    if p >= q:
                        part = self._inverse[int(p), int(q)][np.ix_(lr, lc)]
                    else:
                        part = self._inverse[int(q), int(p)][np.ix_(lc, lr)].T
                    out[np.ix_(r_sel, c_sel)] = part
            self._blocks[key] = out
        return out


def condition_sparse(
    information: StateInformation,
    glob: dict[int, RobotGains],
    pairs: Sequence[MatchIndex],
    structure: set[tuple[int, int]] | None = None,
) -> tuple[SparseState, Array]:
    """The state conditioned on matches ``pairs`` in the information form (module docs) and
    their leave-one-out distances. ``structure`` (block pairs ``p >= q``) are kept in the
    factor's pattern even where zero, so that :meth:`SparseState.block` covers them."""
    pattern = information.pattern
    groups = _groups(pairs)
    if not groups and not structure:
        covariance = information.covariance
        inverse = covariance.selected_inverse()
        return SparseState(information, np.zeros(pattern.n), inverse), np.zeros(0)
    blocks = pattern.blocks(information.data)
    rhs = np.zeros(pattern.n)
    rows_of: dict[tuple[int, int], tuple[Array, Array, Array, IntArray]] = {}
    for (a, c), idx in groups.items():
        arr = np.asarray(pairs, dtype=np.int64)[idx]
        nu, h, noise, cols = rows_of[a, c] = _pair_rows(glob, a, c, arr[:, 1], arr[:, 3])
        weighted = np.linalg.solve(noise, h)  # N^-1 H
        flat = h.reshape(-1, h.shape[2])
        added = flat.T @ weighted.reshape(-1, h.shape[2])
        np.add.at(rhs, cols, -np.einsum("kim,ki->m", weighted, nu))
        _scatter(information, blocks, cols, 0.5 * (added + added.T))
    for p, q in structure or ():
        if (p, q) not in blocks:
            blocks[p, q] = np.zeros((pattern.sizes[p], pattern.sizes[q]))
    factor = factor_blocks(pattern, blocks)
    if factor is None:
        raise SingularProblemError("Algorithm 1's information conditioned on the matches")
    shift = factor.solve(rhs)
    state = SparseState(information, shift, factor.selected_inverse())
    loo = np.empty(len(pairs))
    for (a, c), (nu, h, noise, cols) in rows_of.items():
        loo[groups[a, c]] = _leave_one_out(nu, h, noise, shift[cols], state.block(cols, cols))
    return state, loo


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
    """Residuals (K, 2), Jacobians on the whole state (K, 2, dim) and noise (K, 2, 2)."""
    nu = np.empty((len(pairs), 2))
    h = np.zeros((len(pairs), 2, dim))
    noise = np.empty((len(pairs), 2, 2))
    for (a, c), idx in _groups(pairs).items():
        arr = np.asarray(pairs, dtype=np.int64)[idx]
        nu[idx], compact, noise[idx], cols = _pair_rows(glob, a, c, arr[:, 1], arr[:, 3])
        h[np.ix_(idx, [0, 1], cols)] = compact
    return nu, h, noise


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
    innovation = a_mat.copy()
    for m in range(k):
        innovation[2 * m : 2 * m + 2, 2 * m : 2 * m + 2] += noise[m]
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
