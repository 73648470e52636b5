"""Base-node initialisation and Algorithm 1: closed-form cases without noise, observability
checks (pending), chains through non-reference robots, the sparse Newton path against the
generic Gauss-Newton path and the dense Newton oracle (Algorithm 1 alone and whole joins of
simulated runs), and agreement of Algorithm 1 (rendezvous parts only) with the full joint
solve."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from csam_ros.core.joining.alignment import (
    AlignmentOptions,
    RendezvousPart,
    align,
    initial_pair_base,
    joined,
)
from csam_ros.core.joining.config import CsamConfig
from csam_ros.core.joining.join import join_maps
from csam_ros.core.joining.pipeline import build_robot_maps, run_csam
from csam_ros.core.model import se2, sensor
from csam_ros.core.model.rendezvous import RendezvousSet
from csam_ros.datasets.formations import CSAM_SECTION, many_robot_scenario
from csam_ros.datasets.scenario import load_scenario
from csam_ros.datasets.simulation import simulate

CONFIG = Path(__file__).resolve().parents[3] / "config"


def _straight(start, heading, step, n):
    """World poses along a straight line."""
    t = np.arange(n) * step
    return np.column_stack(
        [start[0] + t * np.cos(heading), start[1] + t * np.sin(heading), np.full(n, heading)]
    )


def _measurements(world, pairs, robots) -> RendezvousSet:
    """Exact (noise-free) measurements ``(observer, observed, pose index)`` at equal stamps."""
    obs = np.array([p[0] for p in pairs])
    tgt = np.array([p[1] for p in pairs])
    idx = np.array([p[2] for p in pairs])
    rel = np.array([se2.inverse_transform_point(world[o][i], world[t][i, :2]) for o, t, i in pairs])
    r = np.hypot(rel[:, 0], rel[:, 1])
    b = np.arctan2(rel[:, 1], rel[:, 0])
    z, cov = sensor.polar_to_cartesian(r, b, 0.01, 0.012)
    return RendezvousSet(robots, obs, tgt, idx * 1.0, idx, idx, z, cov, b)


def _parts(world, sigma=0.01):
    """Local poses (first pose = origin) of every robot as rendezvous parts of all poses."""
    parts, local = [], {}
    for r, w in enumerate(world):
        poses = se2.between(w[0], w)
        local[r] = poses
        parts.append(RendezvousPart(np.arange(len(w)), poses, np.eye(3 * len(w)) / sigma))
    return parts, local


def _true_base(world, r):
    return se2.between(world[0][0], world[r][0])


@pytest.fixture
def two_robots():
    a = _straight((0.0, 0.0), 0.3, 0.5, 8)
    c = _straight((4.0, 3.0), 0.3 + np.pi - 0.2, 0.5, 8)
    return [a, c]


def test_mutual_initialisation_is_exact(two_robots) -> None:
    pairs = [(0, 1, 2), (1, 0, 2)]
    meas = _measurements(two_robots, pairs, ["p", "q"])
    _, local = _parts(two_robots)
    init = initial_pair_base(meas, 0, 1, local)
    assert init.method == "mutual"
    np.testing.assert_allclose(init.base, _true_base(two_robots, 1), atol=1e-9)


def test_registration_initialisation_is_exact(two_robots) -> None:
    pairs = [(0, 1, i) for i in (1, 3, 5, 7)] + [(1, 0, 6)]
    meas = _measurements(two_robots, pairs, ["p", "q"])
    _, local = _parts(two_robots)
    init = initial_pair_base(meas, 0, 1, local)
    assert init.method == "registration"
    np.testing.assert_allclose(init.base, _true_base(two_robots, 1), atol=1e-9)
    assert 0 < init.heading_sigma < 0.05


def test_one_measurement_is_pending(two_robots) -> None:
    meas = _measurements(two_robots, [(0, 1, 3)], ["p", "q"])
    parts, local = _parts(two_robots)
    init = initial_pair_base(meas, 0, 1, local)
    assert init.base is None and "one rendezvous measurement" in init.reason
    result = align(parts, meas)
    assert result.status[1].startswith("pending: ") and "unobservable" in result.status[1]
    assert np.all(np.isnan(result.base_nodes[1]))
    assert result.aligned(0) and not result.aligned(1)
    assert joined("reference") and joined("aligned") and not joined(result.status[1])


def test_positions_not_spread_are_pending(two_robots) -> None:
    still = np.repeat(two_robots[1][:1], 8, axis=0)  # q does not move; only p observes
    world = [two_robots[0], still]
    meas = _measurements(world, [(0, 1, i) for i in range(0, 8, 2)], ["p", "q"])
    parts, local = _parts(world)
    init = initial_pair_base(meas, 0, 1, local)
    assert init.base is None and "undetermined" in init.reason
    assert align(parts, meas).status[1].startswith("pending: ")


def test_chain_through_non_reference_robots_is_exact() -> None:
    world = [
        _straight((0.0, 0.0), 0.0, 0.5, 10),
        _straight((6.0, 2.0), np.pi, 0.5, 10),
        _straight((1.0, 4.5), 0.4, 0.5, 10),
        _straight((30.0, 30.0), 1.0, 0.5, 10),  # never meets anyone
    ]
    pairs = [(0, 1, i) for i in (1, 4, 8)] + [(1, 2, i) for i in (0, 5)] + [(2, 1, 9)]
    meas = _measurements(world, pairs, ["r1", "r2", "r3", "r4"])
    parts, _ = _parts(world)
    parts[3] = None
    result = align(parts, meas)
    assert result.status[:3] == ["reference", "aligned", "aligned"]
    assert result.status[3] == "pending: no rendezvous with any robot"
    assert result.parents == {1: 0, 2: 1}
    for r in (1, 2):
        np.testing.assert_allclose(result.base_nodes[r], _true_base(world, r), atol=1e-8)
        assert np.all(np.linalg.eigvalsh(result.base_covariance(r)) > 0)
    # the refined rendezvous poses of exact data stay where they were
    np.testing.assert_allclose(result.rendezvous_shift[2], 0.0, atol=1e-8)


def test_refinement_moves_a_rough_start_to_the_optimum(two_robots) -> None:
    pairs = [(0, 1, i) for i in range(8)] + [(1, 0, i) for i in range(0, 8, 3)]
    meas = _measurements(two_robots, pairs, ["p", "q"])
    rng = np.random.default_rng(0)
    meas.position += rng.normal(0, 0.01, meas.position.shape)
    parts, _ = _parts(two_robots)
    result = align(parts, meas)
    assert result.iterations >= 1
    truth = _true_base(two_robots, 1)
    err = result.base_nodes[1] - truth
    err[2] = se2.wrap_angle(err[2])
    assert err @ np.linalg.solve(result.base_covariance(1), err) < 16.3  # chi2(3) 99.9 %


def test_a_start_at_the_optimum_ends_there(two_robots) -> None:
    """Started at its own solution (base node and rendezvous poses), Algorithm 1 stops at
    once, at the same solution; a start of the wrong shape is an error."""
    pairs = [(0, 1, i) for i in range(8)] + [(1, 0, i) for i in range(0, 8, 3)]
    meas = _measurements(two_robots, pairs, ["p", "q"])
    meas.position += np.random.default_rng(1).normal(0, 0.01, meas.position.shape)
    parts, _ = _parts(two_robots)
    cold = align(parts, meas)
    assert cold.iterations > 1
    poses = [cold.rendezvous_poses[r] for r in range(2)]
    warm = align(parts, meas, start=cold.base_nodes, rendezvous_start=poses)
    assert warm.iterations == 1
    np.testing.assert_allclose(warm.base_nodes, cold.base_nodes, atol=1e-9)
    for r in range(2):
        np.testing.assert_allclose(warm.rendezvous_poses[r], poses[r], atol=1e-9)
    np.testing.assert_allclose(warm.covariance, cold.covariance, rtol=1e-6, atol=1e-12)
    with pytest.raises(ValueError, match="rendezvous start of 'q'"):
        align(parts, meas, rendezvous_start=[poses[0], poses[1][1:]])


@pytest.mark.parametrize("scenario", ["map_joining", "chain"])
def test_algorithm1_agrees_with_the_joint_solve(scenario: str) -> None:
    """From the rendezvous parts alone, Algorithm 1 finds the joint solution's base nodes
    (without association) up to the local maps' linearisation."""
    result = run_csam(simulate(load_scenario(scenario), 1), CsamConfig(associate=False))
    for robot in list(result.robots.values())[1:]:
        assert robot.alignment == "aligned"
        sigma = np.sqrt(np.diag(robot.base_node_cov))
        diff = robot.alignment_base_node - robot.base_node
        diff[2] = se2.wrap_angle(diff[2])
        assert np.all(np.abs(diff) < 0.05 * sigma)
        np.testing.assert_allclose(
            np.sqrt(np.diag(robot.alignment_base_node_cov)), sigma, rtol=0.05
        )


def test_rendezvous_far_from_the_frame_origin_is_still_observable() -> None:
    """500 m between q's first pose and the meeting: translation and heading of b_pq are
    nearly collinear, the heading itself is well determined."""
    p = _straight((0.0, 0.0), 0.0, 0.5, 1000)
    q = _straight((505.0, 3.0), np.pi, 0.5, 1000)
    meeting = [i for i in range(1000) if abs(p[i, 0] - q[i, 0]) < 2.5]
    pairs = [(0, 1, i) for i in meeting] + [(1, 0, i) for i in meeting[::2]]
    world = [p, q]
    meas = _measurements(world, pairs, ["p", "q"])
    local = {r: se2.between(w[0], w) for r, w in enumerate(world)}
    init = initial_pair_base(meas, 0, 1, local)
    assert init.base is not None, init.reason
    np.testing.assert_allclose(init.base, _true_base(world, 1), atol=1e-6)
    assert init.heading_sigma < np.deg2rad(1.0)


def _drifting_parts(world, rng, sigma_step=0.02, sigma_start=(0.3, 0.3, 0.1)):
    """Local estimates with odometry-like noise and their dense prior: information of
    consecutive differences (sigma_step) plus a weak prior on the first pose, so that a rigid
    rotation of all poses is weakly determined (as in real local maps)."""
    parts = []
    for w in world:
        local = se2.between(w[0], w)
        n = len(local)
        local = local + rng.normal(0, sigma_step, local.shape).cumsum(axis=0)
        diff = np.zeros((3 * n, 3 * n))
        diff[:3, :3] = np.diag(1.0 / np.asarray(sigma_start))
        for k in range(1, n):
            diff[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = np.eye(3) / sigma_step
            diff[3 * k : 3 * k + 3, 3 * k - 3 : 3 * k] = -np.eye(3) / sigma_step
        upper = np.linalg.cholesky(diff.T @ diff).T
        parts.append(RendezvousPart(np.arange(n), local, upper))
    return parts


@pytest.fixture
def three_drifting_robots():
    rng = np.random.default_rng(11)
    world = [
        _straight((0.0, 0.0), 0.0, 0.4, 12),
        _straight((6.0, 2.0), np.pi - 0.1, 0.4, 12),
        _straight((1.0, 5.0), -0.5, 0.4, 12),
    ]
    pairs = [(0, 1, i) for i in range(0, 12, 2)] + [(1, 0, i) for i in range(1, 12, 3)]
    pairs += [(1, 2, i) for i in range(0, 12, 3)] + [(2, 0, i) for i in range(0, 12, 4)]
    meas = _measurements(world, pairs, ["a", "b", "c"])
    meas.position += rng.normal(0, 0.05, meas.position.shape)  # large residuals
    return _drifting_parts(world, rng), meas


def test_newton_matches_gauss_newton_and_the_dense_oracle(three_drifting_robots) -> None:
    """The sparse Newton path reaches Gauss-Newton's minimum (run to convergence), at least as
    low and in no more iterations, and is the dense Newton oracle to rounding, covariance
    included."""
    parts, meas = three_drifting_robots
    newton = align(parts, meas, AlignmentOptions(method="newton", max_iterations=500))
    generic = align(parts, meas, AlignmentOptions(method="gauss-newton", max_iterations=500))
    oracle = align(parts, meas, AlignmentOptions(method="dense-newton", max_iterations=500))
    assert newton.status == generic.status == ["reference", "aligned", "aligned"]
    np.testing.assert_allclose(newton.base_nodes, generic.base_nodes, atol=1e-6)
    for r, poses in generic.rendezvous_poses.items():
        np.testing.assert_allclose(newton.rendezvous_poses[r], poses, atol=1e-6)
    assert newton.state_keys == generic.state_keys == oracle.state_keys
    scale = np.sqrt(np.outer(np.diag(generic.covariance), np.diag(generic.covariance)))
    np.testing.assert_allclose(newton.covariance / scale, generic.covariance / scale, atol=1e-5)
    assert newton.final_cost <= generic.final_cost + 1e-9
    assert 1 <= newton.iterations <= generic.iterations
    # the same steps: they part only at the numerical minimum (a step within rounding may be
    # taken by one and rejected by the other)
    assert abs(newton.final_cost - oracle.final_cost) <= 1e-12 * oracle.final_cost
    np.testing.assert_allclose(newton.base_nodes, oracle.base_nodes, atol=1e-10)
    np.testing.assert_allclose(newton.covariance / scale, oracle.covariance / scale, atol=1e-9)
    for r in range(3):
        cols = newton.base_columns(r)
        if cols is not None:
            np.testing.assert_allclose(
                newton.base_covariance(r) / scale[np.ix_(cols, cols)],
                oracle.base_covariance(r) / scale[np.ix_(cols, cols)],
                atol=1e-9,
            )
    np.testing.assert_array_equal(newton.base_covariance(0), np.zeros((3, 3)))
    rho, base = newton.rho_columns(1), newton.base_columns(2)
    np.testing.assert_allclose(
        newton.covariance_block(rho, base) / scale[np.ix_(rho, base)],
        oracle.covariance[np.ix_(rho, base)] / scale[np.ix_(rho, base)],
        atol=1e-9,
    )
    auto = align(parts, meas, AlignmentOptions(max_iterations=500))
    np.testing.assert_array_equal(auto.base_nodes, newton.base_nodes)


def test_unknown_alignment_method_is_an_error(two_robots) -> None:
    meas = _measurements(two_robots, [(0, 1, i) for i in range(8)], ["p", "q"])
    parts, _ = _parts(two_robots)
    with pytest.raises(ValueError, match="method"):
        align(parts, meas, AlignmentOptions(method="bfgs"))


@pytest.mark.parametrize(
    "scenario", ["map_joining", "sensor_extension", "chain", "five_robots", "ring16"]
)
def test_joined_result_equals_the_dense_oracles(scenario: str) -> None:
    """The whole join (base nodes, poses, features, covariances, associations) is the one the
    dense Newton oracle gives, to 1e-6."""
    if scenario.startswith("ring"):
        log = simulate(many_robot_scenario(int(scenario[4:]), "ring"))
        config = CsamConfig.from_dict(CSAM_SECTION, "ring")
    else:
        log = simulate(load_scenario(scenario))
        config = CsamConfig.from_file(CONFIG / f"{scenario}.yaml")
    built = build_robot_maps(log, config)
    sparse = join_maps(built.maps, built.rendezvous_logs, config).to_dict()
    dense = replace(config, alignment_method="dense-newton")
    oracle = join_maps(built.maps, built.rendezvous_logs, dense).to_dict()
    assert sparse["statistics"]["algorithm1_iterations"] >= 1
    _assert_same(sparse, oracle, "")


def _assert_same(a: object, b: object, where: str) -> None:
    """Equal structure, numbers within 1e-6 (timings aside)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), where
        for key in a:
            if key != "timing_s":
                _assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert abs(a - b) <= 1e-6, (where, a, b)
    else:
        assert a == b, (where, a, b)


def test_joint_problem_by_blocks_equals_it_by_qdldl(monkeypatch) -> None:
    """The joint solve and its marginals factored by robot blocks (where they are cheaper than
    qdldl: many robots observing each other at every sample) give the join qdldl gives."""
    import csam_ros.core.sam.normal_equations as normal_equations

    log = simulate(many_robot_scenario(8, "ring", rendezvous_every=1))
    config = CsamConfig.from_dict(CSAM_SECTION, "ring")
    built = build_robot_maps(log, config)
    choose = normal_equations.NormalEquations._choose_blocks
    switched: list[bool] = []

    def spy(self: normal_equations.NormalEquations) -> None:
        choose(self)
        switched.append(self.block_pattern is not None)

    monkeypatch.setattr(normal_equations.NormalEquations, "_choose_blocks", spy)
    joined = {}
    for ratio in (0.0, 1e9):
        monkeypatch.setattr(normal_equations, "BLOCK_FLOPS_RATIO", ratio)
        joined[ratio] = join_maps(built.maps, built.rendezvous_logs, config).to_dict()
    assert switched == [False, True]  # the joint problem's only: the local maps have no blocks
    _assert_same(joined[1e9], joined[0.0], "")
