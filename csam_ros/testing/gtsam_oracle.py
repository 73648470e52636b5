"""The landmark problems of :mod:`csam_ros.core.landmark_problem` in GTSAM, an independent
oracle for the tests and the benchmark's speed reference.

``gtsam`` is imported inside the functions only: it is a test and benchmark dependency
(requirements-dev.txt), never one of the running system.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core import se2, sensor
from csam_ros.core.factors import PointObservation, RelativePose
from csam_ros.core.landmark_problem import GraphData, LandmarkProblem, as_graph
from csam_ros.core.solver import GAUGE_SIGMA

Array = NDArray[np.float64]


def _local_to_global(phi: float) -> Array:
    """``d(global pose)/d(GTSAM tangent)`` at a pose with heading ``phi``: blkdiag(R, 1)."""
    m = np.eye(3)
    m[:2, :2] = se2.rotation(phi)
    return m


def polar_sigmas(xy: Array, covariance: Array) -> tuple[Array, Array, Array, Array]:
    """Range, bearing and their sigmas of Cartesian observations (first-order projection)."""
    r, b = sensor.cartesian_to_polar(xy)
    radial = np.stack([np.cos(b), np.sin(b)], axis=1)
    tangential = np.stack([-np.sin(b), np.cos(b)], axis=1)
    s_r = np.sqrt(np.einsum("ki,kij,kj->k", radial, covariance, radial))
    s_b = np.sqrt(np.einsum("ki,kij,kj->k", tangential, covariance, tangential)) / r
    return r, b, s_r, s_b


def build_gtsam(source: LandmarkProblem | GraphData, identical: bool) -> tuple[Any, Any]:
    """GTSAM graph and initial values.

    ``identical=True`` writes exactly this project's errors as ``CustomFactor`` (Jacobians
    chained to GTSAM's tangent space); ``False`` uses GTSAM's native Pose2 between and
    bearing-range factors with the covariances mapped to their errors at first order
    (between: ``blkdiag(R(z_phi)^T, 1)``; Cartesian to polar at the measurement).
    """
    import gtsam

    g = as_graph(source)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()

    def pose_key(i: int) -> int:
        return gtsam.symbol("x", i)

    def lm_key(j: int) -> int:
        return gtsam.symbol("l", j)

    for i, p in enumerate(g.initial_poses):
        values.insert(pose_key(i), gtsam.Pose2(*p))
    for j, p in enumerate(g.initial_landmarks):
        values.insert(lm_key(j), np.asarray(p, dtype=float))
    graph.add(
        gtsam.PriorFactorPose2(
            pose_key(0),
            gtsam.Pose2(*g.initial_poses[0]),
            gtsam.noiseModel.Isotropic.Sigma(3, GAUGE_SIGMA),
        )
    )
    edges = zip(g.odometry_first, g.odometry_second, g.odometry, g.odometry_covariance, strict=True)
    if not identical:
        for a, b, z, cov in edges:
            m = np.eye(3)
            m[:2, :2] = se2.rotation(z[2]).T
            graph.add(
                gtsam.BetweenFactorPose2(
                    pose_key(int(a)),
                    pose_key(int(b)),
                    gtsam.Pose2(*z),
                    gtsam.noiseModel.Gaussian.Covariance(m @ cov @ m.T),
                )
            )
        r, bearing, s_r, s_b = polar_sigmas(g.obs_xy, g.obs_covariance)
        for k in range(len(g.obs_pose)):
            graph.add(
                gtsam.BearingRangeFactor2D(
                    pose_key(int(g.obs_pose[k])),
                    lm_key(int(g.obs_landmark[k])),
                    gtsam.Rot2(float(bearing[k])),
                    float(r[k]),
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([s_b[k], s_r[k]])),
                )
            )
        return graph, values

    def between_error(z: Array) -> Any:
        def error(this: Any, v: Any, H: Any) -> Array:
            a = v.atPose2(this.keys()[0])
            b = v.atPose2(this.keys()[1])
            xa = np.array([a.x(), a.y(), a.theta()])
            xb = np.array([b.x(), b.y(), b.theta()])
            f = RelativePose([0], [1], z[None], np.eye(3)[None])
            e, jac = f.evaluate([xa[None], xb[None]])
            if H is not None:
                H[0] = jac[0][0] @ _local_to_global(xa[2])
                H[1] = jac[1][0] @ _local_to_global(xb[2])
            return e[0]

        return error

    def observation_error(z: Array) -> Any:
        def error(this: Any, v: Any, H: Any) -> Array:
            a = v.atPose2(this.keys()[0])
            xa = np.array([a.x(), a.y(), a.theta()])
            lm = np.asarray(v.atPoint2(this.keys()[1]), dtype=float)
            f = PointObservation([0], [1], z[None], np.eye(2)[None])
            e, jac = f.evaluate([xa[None], lm[None]])
            if H is not None:
                H[0] = jac[0][0] @ _local_to_global(xa[2])
                H[1] = jac[1][0]
            return e[0]

        return error

    for a, b, z, cov in edges:
        graph.add(
            gtsam.CustomFactor(
                gtsam.noiseModel.Gaussian.Covariance(cov),
                [pose_key(int(a)), pose_key(int(b))],
                between_error(z),
            )
        )
    for k in range(len(g.obs_pose)):
        graph.add(
            gtsam.CustomFactor(
                gtsam.noiseModel.Gaussian.Covariance(g.obs_covariance[k]),
                [pose_key(int(g.obs_pose[k])), lm_key(int(g.obs_landmark[k]))],
                observation_error(g.obs_xy[k]),
            )
        )
    return graph, values


def gtsam_estimate(source: LandmarkProblem | GraphData, result: Any) -> tuple[Array, Array]:
    """Poses ``(N, 3)`` and landmarks ``(L, 2)`` from GTSAM values."""
    import gtsam

    g = as_graph(source)
    poses = np.array(
        [
            [p.x(), p.y(), p.theta()]
            for p in (result.atPose2(gtsam.symbol("x", i)) for i in range(len(g.initial_poses)))
        ]
    )
    lms = np.array(
        [result.atPoint2(gtsam.symbol("l", j)) for j in range(len(g.initial_landmarks))]
    ).reshape(-1, 2)
    return poses, lms


def gtsam_marginal_covariance(
    source: LandmarkProblem | GraphData, graph: Any, result: Any, keys: list
) -> Array:
    """GTSAM's joint marginal of ``keys`` (("x", i) or ("l", j)) in global parametrisation."""
    import gtsam

    marginals = gtsam.Marginals(graph, result)
    gkeys = [gtsam.symbol(kind, idx) for kind, idx in keys]
    joint = marginals.jointMarginalCovariance(gkeys)
    transforms = []
    dims = []
    for (kind, _), gk in zip(keys, gkeys, strict=True):
        if kind == "x":
            transforms.append(_local_to_global(result.atPose2(gk).theta()))
        else:
            transforms.append(np.eye(2))
        dims.append(joint.at(gk, gk).shape[0])
    edges = np.cumsum([0, *dims])
    m = np.zeros((edges[-1], edges[-1]))
    full = np.zeros((edges[-1], edges[-1]))
    for a, ka in enumerate(gkeys):
        m[edges[a] : edges[a + 1], edges[a] : edges[a + 1]] = transforms[a]
        for b, kb in enumerate(gkeys):
            full[edges[a] : edges[a + 1], edges[b] : edges[b + 1]] = joint.at(ka, kb)
    return m @ full @ m.T
