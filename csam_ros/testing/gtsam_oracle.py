"""The landmark problems of :mod:`csam_ros.testing.landmark_problem` in GTSAM, an independent
oracle for the tests and the benchmark's speed reference.

``gtsam`` is imported inside the functions only: it is a test and benchmark dependency
(requirements-dev.txt), never one of the running system.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.model import se2, sensor
from csam_ros.core.sam.solver import GAUGE_SIGMA
from csam_ros.testing.landmark_problem import GraphData, LandmarkProblem, as_graph

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

    ``identical=True`` writes exactly this project's errors as ``CustomFactor``, computed with
    GTSAM's own geometry (``Pose2.between``, ``Pose2.transformTo``) and its Jacobians in its
    tangent space, not with this project's factors; ``False`` uses GTSAM's native Pose2 between and
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
            # this project's error, written with GTSAM's geometry and Jacobians
            a = v.atPose2(this.keys()[0])
            b = v.atPose2(this.keys()[1])
            jac_a, jac_b = np.zeros((3, 3), order="F"), np.zeros((3, 3), order="F")
            rel = a.between(b, jac_a, jac_b)
            e = np.array([rel.x() - z[0], rel.y() - z[1], se2.wrap_angle(rel.theta() - z[2])])
            if H is not None:
                # the vector (x, y, theta) of ``rel`` against its tangent: blkdiag(R, 1)
                to_vector = _local_to_global(rel.theta())
                H[0] = to_vector @ jac_a
                H[1] = to_vector @ jac_b
            return e

        return error

    def observation_error(z: Array) -> Any:
        def error(this: Any, v: Any, H: Any) -> Array:
            # R(phi)^T (l - t) - z with GTSAM's Pose2.transformTo and its Jacobians
            pose = v.atPose2(this.keys()[0])
            point = np.asarray(v.atPoint2(this.keys()[1]), dtype=float)
            jac_pose, jac_point = np.zeros((2, 3), order="F"), np.zeros((2, 2), order="F")
            e = pose.transformTo(point, jac_pose, jac_point) - z
            if H is not None:
                H[0] = jac_pose
                H[1] = jac_point
            return e

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


def gauss_newton(
    graph: Any, values: Any, max_iterations: int = 50, relative_tolerance: float = 1e-12
) -> tuple[Any, int]:
    """GTSAM's own linearisation and elimination (COLAMD) in a plain Gauss-Newton loop, until
    the cost decreases by less than ``relative_tolerance``: the estimate and the iterations.

    For graphs of ``CustomFactor``: GTSAM's optimizer classes call them from worker threads,
    which here made one iteration on Victoria Park take 50 s instead of 1 s.
    """
    cost = graph.error(values)
    for iteration in range(1, max_iterations + 1):
        values = values.retract(graph.linearize(values).optimize())
        new_cost = graph.error(values)
        if cost - new_cost <= relative_tolerance * cost:
            return values, iteration
        cost = new_cost
    return values, max_iterations


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
