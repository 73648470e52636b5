"""The connector factor of Algorithm 1 (paper eq. 22-24): rendezvous rows through base nodes,
the poses of the robots' local frames in the reference frame."""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from csam_ros.core.model import rendezvous
from csam_ros.core.sam.factors import (
    POSE,
    Factor,
    VariableKind,
    _as_ids,
    _as_measurements,
    _as_sqrt_information,
)

Array = NDArray[np.float64]

BASE_NODE = VariableKind("base_node", 3, 2)

# central-difference step (m, rad) of the connectors' Jacobians for their second derivatives
CURVATURE_STEP = 1e-6


class Connector(Factor):
    """Rendezvous rows through base nodes: ``e = c(x_o, B_o, t_t, B_t) - z`` (eq. 22-24).

    ``c`` is :func:`csam_ros.core.model.rendezvous.predict`. A base node given as ``None`` is the
    reference robot's identity and is not a variable; otherwise it is a ``BASE_NODE``
    variable. The observed robot is a ``POSE`` variable whose heading does not enter.
    """

    residual_dim = 2

    def __init__(
        self,
        observer_poses: ArrayLike,
        observed_poses: ArrayLike,
        measured: ArrayLike,
        sqrt_information: ArrayLike | None = None,
        *,
        covariance: ArrayLike | None = None,
        observer_bases: ArrayLike | None = None,
        observed_bases: ArrayLike | None = None,
        name: str = "Connector",
    ) -> None:
        obs = _as_ids(observer_poses, name)
        w = _as_sqrt_information(sqrt_information, covariance, len(obs), 2, name)
        columns: list[ArrayLike] = [obs]
        kinds: list[VariableKind] = [POSE]
        if observer_bases is not None:
            columns.append(observer_bases)
            kinds.append(BASE_NODE)
        columns.append(observed_poses)
        kinds.append(POSE)
        if observed_bases is not None:
            columns.append(observed_bases)
            kinds.append(BASE_NODE)
        self.kinds = tuple(kinds)
        self._has_observer_base = observer_bases is not None
        self._has_observed_base = observed_bases is not None
        super().__init__(columns, w, None, name)
        self.measured = _as_measurements(measured, len(obs), 2, name)

    def evaluate(
        self, blocks: Sequence[Array], jacobians: bool = True
    ) -> tuple[Array, list[Array]]:
        it = iter(blocks)
        x_o = next(it)
        b_o = next(it) if self._has_observer_base else np.zeros_like(x_o)
        x_t = next(it)
        b_t = next(it) if self._has_observed_base else np.zeros_like(x_o)
        pred = rendezvous.predict(x_o, b_o, x_t[:, :2], b_t)
        e = pred.position - self.measured
        if not jacobians:
            return e, []
        d_observed = np.zeros((len(e), 2, 3))
        d_observed[:, :, :2] = pred.d_observed_position
        jac = [pred.d_observer_pose]
        if self._has_observer_base:
            jac.append(pred.d_observer_base)
        jac.append(d_observed)
        if self._has_observed_base:
            jac.append(pred.d_observed_base)
        return e, jac

    def curvature(self, blocks: Sequence[Array]) -> Array:
        """``sum_i r_i d^2 r_i / dx^2`` of each row (K, D, D), ``r`` its whitened residual and
        ``x`` its variables side by side (as in :meth:`evaluate`): the part of the Hessian of
        the cost that Gauss-Newton leaves out.

        Central differences of the analytic whitened Jacobians, one vectorised evaluation at
        all rows moved by ``+-CURVATURE_STEP`` along each of their ``D`` columns at once."""
        x = np.concatenate(blocks, axis=1)
        k, width = x.shape
        splits = np.cumsum([b.shape[1] for b in blocks])[:-1]
        r, _, _ = self.whitened(blocks, jacobians=False)
        step = CURVATURE_STEP * np.eye(width)
        moved = np.concatenate(
            [x + step[j] for j in range(width)] + [x - step[j] for j in range(width)]
        )
        tiled = copy.copy(self)  # the same rows, 2 width times
        tiled.measured = np.tile(self.measured, (2 * width, 1))
        tiled.sqrt_information = np.tile(self.sqrt_information, (2 * width, 1, 1))
        a = tiled.whitened(np.split(moved, splits, axis=1))[1]
        assert a is not None
        a = a.reshape(2, width, k, *a.shape[1:])
        out = np.einsum("ki,jkid->kdj", r, a[0] - a[1]) / (2.0 * CURVATURE_STEP)
        return 0.5 * (out + out.transpose(0, 2, 1))
