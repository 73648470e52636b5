"""Small least-squares problems shared by the tests of the sparse engine."""

import numpy as np

from csam_ros.core.model import se2
from csam_ros.core.sam import factors as f
from csam_ros.core.sam.covariance import factorize_at_estimate
from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.solver import Problem


def dense_inverse_at_estimate(problem: Problem) -> tuple[NormalEquations, np.ndarray]:
    """``problem`` linearised and factored at its values, and the dense inverse of its
    information matrix: the oracle of every covariance the engine computes."""
    system = factorize_at_estimate(problem)
    upper = system.matrix().toarray()
    return system, np.linalg.inv(upper + np.triu(upper, 1).T)


def mixed_problem(seed=0):
    """A small problem with every factor kind (and a robust kernel)."""
    rng = np.random.default_rng(seed)
    p = Problem()
    truth = np.zeros((8, 3))
    for i in range(1, 8):
        truth[i] = se2.compose(truth[i - 1], [1.0, 0.1, 0.3])
    lms = rng.uniform(-2, 6, (4, 2))
    x = p.add_variables(f.POSE, [("x", i) for i in range(8)], truth + rng.normal(0, 0.1, (8, 3)))
    other = p.add_variables(
        f.POSE, ["y0", "y1"], truth[[2, 5]] + [[0.5, 1.0, 0.2], [0.4, 1.1, 0.1]]
    )
    l_ids = p.add_variables(f.POINT, [("l", j) for j in range(4)], lms + rng.normal(0, 0.2, (4, 2)))
    p.add_factor(f.PosePrior(x[:1], truth[:1], np.eye(3) * 100.0))
    z = se2.between(truth[:-1], truth[1:]) + rng.normal(0, 0.01, (7, 3))
    p.add_factor(f.RelativePose(x[:-1], x[1:], z, covariance=np.eye(3) * 1e-3))
    pi, li = np.meshgrid(np.arange(8), np.arange(4), indexing="ij")
    pi, li = pi.ravel(), li.ravel()
    zz = se2.inverse_transform_point(truth[pi], lms[li]) + rng.normal(0, 0.02, (32, 2))
    p.add_factor(
        f.PointObservation(x[pi], l_ids[li], zz, covariance=np.eye(2) * 4e-4, robust=f.Huber())
    )
    p.add_factor(f.PointPrior(l_ids[:1], lms[:1], np.eye(2) * 2.0))
    yt = truth[[2, 5]] + [[0.5, 1.0, 0.2], [0.4, 1.1, 0.1]]
    rel = se2.between(truth[[1, 6, 1]], yt[[0, 1, 1]])[:, :2]
    p.add_factor(
        f.RelativePosition(x[[1, 6, 1]], other[[0, 1, 1]], rel, covariance=np.eye(2) * 1e-2)
    )
    m = rng.normal(size=(5, 5))
    p.add_factor(
        f.LinearPrior(
            [other[0], l_ids[2]],
            [f.POSE, f.POINT],
            np.r_[yt[0], lms[2]],
            np.triu(m) + 4 * np.eye(5),
        )
    )
    p.add_factor(f.PosePrior(other[1:], yt[1:], np.eye(3) * 10.0))
    return p


def chain(n=3):
    """``n`` poses at the origin and no factor yet."""
    p = Problem()
    ids = p.add_variables(f.POSE, [("x", i) for i in range(n)], np.zeros((n, 3)))
    return p, ids
