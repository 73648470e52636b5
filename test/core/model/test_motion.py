"""Motion model: exactness, omega = 0, Jacobians by finite differences, composition, splits."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from jacobians import numeric_jacobian
from strategies import assert_poses_close, batches, coordinates, poses

from csam_ros.core.model import motion, se2


def integrate(u, T, steps=20000):
    """Pose after driving with constant body velocity u for T (fine Euler, midpoint heading)."""
    h = T / steps
    x = np.zeros(3)
    for _ in range(steps):
        mid = x[2] + 0.5 * u[2] * h
        c, s = np.cos(mid), np.sin(mid)
        x = x + h * np.array([c * u[0] - s * u[1], s * u[0] + c * u[1], u[2]])
    return x


@pytest.mark.parametrize(
    "u", [(1.0, 0.0, 0.8), (0.5, 0.2, -1.7), (0.3, -0.1, 0.0), (0.7, 0.05, 3e-7)]
)
def test_increment_is_exact_for_constant_input(u):
    u = np.array(u)
    np.testing.assert_allclose(motion.increment(u[None], [0.9])[0], integrate(u, 0.9), atol=1e-8)


def test_omega_zero_is_straight_line_with_finite_jacobian():
    U, G = motion.increment_and_jacobian(np.array([[2.0, 0.5, 0.0]]), np.array([0.5]))
    np.testing.assert_allclose(U[0], [1.0, 0.25, 0.0])
    assert np.all(np.isfinite(G))
    # d x / d omega at omega = 0 is -v_lat T^2 / 2, d y / d omega is v T^2 / 2
    np.testing.assert_allclose(G[0, :, 2], [-0.5 * 0.25 * 0.5, 0.5 * 0.25 * 2.0, 0.5])


@pytest.mark.parametrize("omega", [0.0, 1e-9, 1e-5, 0.0099999, 0.0100001, 0.3, -2.5, 6.0])
def test_input_jacobian_matches_finite_differences(omega):
    u = np.array([0.8, -0.15, omega])
    T = 1.0
    _, G = motion.increment_and_jacobian(u[None], [T])
    numeric = numeric_jacobian(lambda v: motion.increment(v, [T]), u[None], angles=[2])
    np.testing.assert_allclose(G, numeric, atol=1e-8)


def test_series_and_exact_branches_agree_at_the_threshold():
    theta = np.array([motion.SERIES_THRESHOLD * (1 - 1e-9), motion.SERIES_THRESHOLD * (1 + 1e-9)])
    _, _, da, db = motion._coefficients(theta)
    assert abs(da[0] - da[1]) < 1e-11
    assert abs(db[0] - db[1]) < 1e-11


def sequential_composition(increments, covariances):
    total = np.zeros(3)
    cov = np.zeros((3, 3))
    for inc, c in zip(increments, covariances, strict=True):
        j1, j2 = se2.compose_jacobians(total, inc)
        cov = j1 @ cov @ j1.T + j2 @ c @ j2.T
        total = se2.compose(total, inc)
    return total, cov


def test_compose_segments_matches_sequential_compounding():
    rng = np.random.default_rng(0)
    inc = rng.normal(scale=[0.3, 0.05, 0.4], size=(40, 3))
    m = rng.normal(size=(40, 3, 3)) * 0.01
    cov = m @ m.transpose(0, 2, 1)
    starts = np.array([0, 7, 8, 25])
    total, total_cov = motion.compose_segments(inc, cov, starts)
    edges = list(starts) + [40]
    for k in range(len(starts)):
        want, want_cov = sequential_composition(
            inc[edges[k] : edges[k + 1]], cov[edges[k] : edges[k + 1]]
        )
        np.testing.assert_allclose(total[k, :2], want[:2], atol=1e-12)
        assert abs(se2.wrap_angle(total[k, 2] - want[2])) < 1e-12
        np.testing.assert_allclose(total_cov[k], want_cov, atol=1e-14)


def make_odometry(rng, count=200, rate=67.0):
    stamps = np.cumsum(rng.uniform(0.8, 1.2, count) / rate)
    inputs = np.column_stack(
        [rng.uniform(0.1, 0.5, count), np.zeros(count), rng.uniform(-0.6, 0.6, count)]
    )
    inputs[50:60, 2] = 0.0
    sigmas = np.tile([0.02, 0.01, 0.05], (count, 1))
    return stamps, inputs, sigmas


def test_odometry_between_sample_stamps_composes_steps():
    rng = np.random.default_rng(1)
    t, u, q = make_odometry(rng)
    keys = t[[0, 10, 11, 60, 199]]
    out = motion.odometry_between(t, u, q, keys)
    U, C = motion.step_covariance(u[1:], np.diff(t), q[1:])
    for k, (i0, i1) in enumerate([(0, 10), (10, 11), (11, 60), (60, 199)]):
        want, want_cov = sequential_composition(U[i0:i1], C[i0:i1])
        np.testing.assert_allclose(out.relative_poses[k, :2], want[:2], atol=1e-12)
        np.testing.assert_allclose(out.covariances[k], want_cov, atol=1e-15)


def test_split_inside_a_sample_is_exact_for_the_mean():
    rng = np.random.default_rng(2)
    t, u, q = make_odometry(rng)
    whole = motion.odometry_between(t, u, q, [t[0], t[120]])
    split_stamps = [t[0], t[30] + 0.3 * (t[31] - t[30]), t[31] + 0.9 * (t[32] - t[31]), t[120]]
    parts = motion.odometry_between(t, u, q, split_stamps)
    total, cov = sequential_composition(parts.relative_poses, parts.covariances)
    np.testing.assert_allclose(total[:2], whole.relative_poses[0, :2], atol=1e-12)
    assert abs(se2.wrap_angle(total[2] - whole.relative_poses[0, 2])) < 1e-12
    # Heading variance is the same exactly; the rest to first order (tiny pieces).
    np.testing.assert_allclose(cov[2, 2], whole.covariances[0][2, 2], rtol=1e-12)
    np.testing.assert_allclose(cov, whole.covariances[0], rtol=2e-3, atol=1e-12)


def test_dead_reckoning_composes_relative_poses():
    rng = np.random.default_rng(3)
    rel = rng.normal(size=(30, 3))
    poses = motion.dead_reckoning(rel, start=[1.0, -2.0, 0.5])
    x = np.array([1.0, -2.0, 0.5])
    for k in range(30):
        x = se2.compose(x, rel[k])
        np.testing.assert_allclose(poses[k + 1, :2], x[:2], atol=1e-12)
        assert abs(se2.wrap_angle(poses[k + 1, 2] - x[2])) < 1e-12


def test_bad_odometry_is_named():
    t = np.array([0.0, 0.1, 0.1, 0.3])
    u = np.ones((4, 3))
    q = np.ones((4, 3))
    with pytest.raises(ValueError, match="odometry sample 2: stamps must increase"):
        motion.odometry_between(t, u, q, [0.0, 0.3])
    t = np.array([0.0, 0.1, 0.2, 0.3])
    u[1, 0] = np.inf
    with pytest.raises(ValueError, match="odometry sample 1: input is not finite"):
        motion.odometry_between(t, u, q, [0.0, 0.3])
    u[1, 0] = 1.0
    with pytest.raises(ValueError, match="key stamp 0.5 lies outside"):
        motion.odometry_between(t, u, q, [0.0, 0.5])
    with pytest.raises(ValueError, match="does not increase"):
        motion.odometry_between(t, u, q, [0.2, 0.1])


def test_odometry_poses_close_a_circle():
    n = 1001
    stamps = np.linspace(0.0, 2 * np.pi, n)  # omega = 1 rad/s for 2 pi seconds
    inputs = np.tile([0.5, 0.0, 1.0], (n, 1))
    poses = motion.odometry_poses(stamps, inputs)
    np.testing.assert_allclose(poses[-1, :2], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses[n // 2, :2], [0.0, 1.0], atol=1e-12)  # radius v / omega


def test_odometry_poses_at_split_a_sample_exactly():
    rng = np.random.default_rng(4)
    stamps = np.cumsum(rng.uniform(0.05, 0.2, size=40))
    inputs = rng.normal(size=(40, 3))
    poses = motion.odometry_poses(stamps, inputs, start=[1.0, 2.0, 0.3])
    at_samples = motion.odometry_poses_at(stamps, inputs, poses, stamps)
    np.testing.assert_allclose(at_samples[:, :2], poses[:, :2], atol=1e-12)
    assert np.all(np.abs(se2.wrap_angle(at_samples[:, 2] - poses[:, 2])) < 1e-12)
    middle = 0.5 * (stamps[9] + stamps[10])
    split = np.insert(stamps, 10, middle)
    refined = motion.odometry_poses(split, np.insert(inputs, 10, inputs[10], axis=0), poses[0])
    at_middle = motion.odometry_poses_at(stamps, inputs, poses, [middle])[0]
    np.testing.assert_allclose(at_middle[:2], refined[10, :2], atol=1e-12)
    assert abs(se2.wrap_angle(at_middle[2] - refined[10, 2])) < 1e-12


# -- properties ------------------------------------------------------------------------------

# turn rates across the series branch (|omega T| < 1e-2), its threshold and fast turns
turn_rates = st.one_of(st.floats(-1e-2, 1e-2), st.floats(-6.0, 6.0))
inputs = st.tuples(st.floats(-2.0, 2.0), st.floats(-1.0, 1.0), turn_rates).map(np.array)
durations = st.floats(0.01, 2.0)


@given(inputs, durations)
def test_input_jacobian_is_the_derivative(u, T):
    _, G = motion.increment_and_jacobian(u[None], [T])
    numeric = numeric_jacobian(lambda v: motion.increment(v, [T]), u[None], angles=[2])
    np.testing.assert_allclose(G, numeric, atol=1e-8)


@given(inputs, durations)
def test_one_increment_in_scalars_is_the_vectorised_increment(u, T):
    one = motion.increment_one(*u.tolist(), T)
    np.testing.assert_allclose(one, motion.increment(u[None], [T])[0], rtol=1e-13, atol=1e-15)


@given(inputs, durations, durations)
def test_constant_input_increments_compose(u, first, second):
    whole = motion.increment(u[None], [first + second])[0]
    parts = motion.increment(np.stack([u, u]), [first, second])
    assert_poses_close(se2.compose(parts[0], parts[1]), whole, atol=1e-9)


@given(inputs, durations, st.tuples(*[st.floats(1e-3, 1.0)] * 3).map(np.array))
def test_step_covariance_is_symmetric_positive_semidefinite(u, T, sigma):
    _, cov = motion.step_covariance(u[None], [T], sigma[None])
    np.testing.assert_allclose(cov[0], cov[0].T, atol=1e-15)
    assert np.linalg.eigvalsh(cov[0]).min() >= -1e-12 * np.abs(cov[0]).max()


@given(batches(poses(), 6))
def test_dead_reckoning_rebuilds_poses_from_their_relative_poses(path):
    rebuilt = motion.dead_reckoning(se2.between(path[:-1], path[1:]), path[0])
    assert_poses_close(rebuilt, path, atol=1e-8)


increments = st.tuples(coordinates(1.0), coordinates(1.0), coordinates(1.0)).map(np.array)


@given(
    batches(increments, 8),
    st.lists(st.integers(1, 7), max_size=4, unique=True).map(sorted),
    st.lists(coordinates(0.1), min_size=8 * 9, max_size=8 * 9),
)
def test_compose_segments_is_sequential_compounding(inc, cuts, noise):
    m = np.reshape(noise, (8, 3, 3))
    cov = m @ m.transpose(0, 2, 1)
    starts = np.array([0, *cuts])
    total, total_cov = motion.compose_segments(inc, cov, starts)
    edges = [*starts, 8]
    for k in range(len(starts)):
        want, want_cov = sequential_composition(
            inc[edges[k] : edges[k + 1]], cov[edges[k] : edges[k + 1]]
        )
        assert_poses_close(total[k], want, atol=1e-12)
        np.testing.assert_allclose(total_cov[k], want_cov, atol=1e-13)


def calibration_log(rng, count=400):
    """Odometry with driving, turning on the spot and standing still, jittered stamps."""
    stamps = np.cumsum(rng.uniform(0.01, 0.03, count))
    inputs = np.column_stack(
        [rng.uniform(-0.1, 0.4, count), rng.normal(0, 0.02, count), rng.normal(0, 0.6, count)]
    )
    inputs[50:90, 0] = 0.0  # on the spot
    inputs[120:140] = 0.0  # standing still
    return stamps, inputs, np.tile([0.03, 0.01, 0.05], (count, 1))


def test_calibrated_odometry_jacobian_against_finite_differences():
    rng = np.random.default_rng(7)
    t, u, q = calibration_log(rng)
    keys = np.sort(rng.uniform(t[0], t[-1], 12))
    keys = np.concatenate([[t[0]], keys, t[[100, 200]], [t[-1]]])
    keys = np.unique(keys)
    c0 = np.array([1.07, 0.64, 0.98])
    odo = motion.calibrated_odometry_between(t, u, q, keys, c0, 0.02)

    def composed(c):
        return np.stack(
            [
                motion.calibrated_odometry_between(t, u, q, keys, ci, 0.02).relative_poses
                for ci in c.reshape(-1, 3)
            ]
        ).reshape(c.shape[:-1] + (len(keys) - 1, 3))

    numeric = numeric_jacobian(lambda c: composed(c).reshape(-1), c0)
    np.testing.assert_allclose(odo.calibration_jacobians.reshape(-1, 3), numeric, atol=1e-7)
    # the inputs scaled by the calibration, then composed as without it
    scaled, _ = motion.calibrated_inputs(u, c0, 0.02)
    plain = motion.odometry_between(t, scaled, q, keys)
    np.testing.assert_allclose(odo.relative_poses, plain.relative_poses, atol=1e-12)
    np.testing.assert_allclose(odo.covariances, plain.covariances, atol=1e-15)


def test_calibration_at_one_is_the_logged_odometry():
    rng = np.random.default_rng(8)
    t, u, q = calibration_log(rng)
    keys = np.linspace(t[0], t[-1], 9)
    plain = motion.odometry_between(t, u, q, keys)
    odo = motion.calibrated_odometry_between(t, u, q, keys, np.ones(3), 0.02)
    np.testing.assert_array_equal(odo.relative_poses, plain.relative_poses)
    np.testing.assert_array_equal(odo.covariances, plain.covariances)
    # the turn of a driving sample scales with k_d, of one on the spot with k_s
    scaled, du_dc = motion.calibrated_inputs(u[[0, 60]], [2.0, 3.0, 5.0], 0.02)
    np.testing.assert_allclose(scaled[:, 2], u[[0, 60], 2] * [3.0, 5.0])
    np.testing.assert_allclose(np.einsum("kij,j->ki", du_dc, [2.0, 3.0, 5.0]), scaled)


# -- odometry as drivers publish it: integrated poses back to inputs -------------------------


@given(inputs, durations)
def test_inputs_from_increments_invert_the_increment(u, T):
    if abs(u[2] * T) >= 3.1:  # a heading difference shows the turn only modulo 2 pi
        u[2] = 3.0 / T
    back = motion.inputs_from_increments(motion.increment(u[None], [T]), [T])[0]
    np.testing.assert_allclose(back, u, atol=1e-9)


def test_twist_integrated_to_poses_comes_back_as_the_twist():
    """twist -> integrate -> poses (as a driver publishes them) -> twist, to 1e-9, across the
    series branch, straight driving and turns up to almost half a turn per sample."""
    rng = np.random.default_rng(11)
    n = 3000
    stamps = 100.0 + np.cumsum(rng.uniform(0.005, 0.5, n))
    dt = np.diff(stamps, prepend=stamps[0] - 0.1)
    twist = np.c_[rng.uniform(-2, 2, n), rng.uniform(-0.5, 0.5, n), rng.uniform(-1, 1, n) * 3 / dt]
    twist[10:20, 2] = 0.0
    twist[20:30, 2] = 1e-9
    twist[30:40, :2] = 0.0
    poses = motion.odometry_poses(stamps, twist, start=(3.0, -2.0, 2.5))
    np.testing.assert_allclose(motion.inputs_from_poses(stamps, poses), twist[1:], atol=1e-9)


def test_default_sigmas_do_not_depend_on_the_sampling_rate():
    """The same motion sampled at 4 Hz and at 100 Hz composes to the same factor covariance
    (the heading's exactly, the position's to first order), growing with the square root
    of the distance and the turn."""
    per_m, per_rad, floor = 0.05, 0.02, 1e-3
    u = np.array([0.8, 0.0, 0.3])
    covariances = []
    for rate in (4.0, 100.0):
        t = np.arange(0.0, 2.0 + 0.5 / rate, 1.0 / rate)
        inputs = np.tile(u, (len(t), 1))
        sigmas = motion.default_input_sigmas(
            inputs, np.full(len(t), 1.0 / rate), per_m, per_rad, floor
        )
        covariances.append(motion.odometry_between(t, inputs, sigmas, [0.0, 2.0]).covariances[0])
    coarse, fine = covariances
    np.testing.assert_allclose(coarse[2, 2], fine[2, 2], rtol=1e-12)
    np.testing.assert_allclose(coarse[2, 2], per_rad**2 * 0.3 * 2.0, rtol=1e-12)
    np.testing.assert_allclose(np.trace(coarse[:2, :2]), np.trace(fine[:2, :2]), rtol=0.05)
    # at rest the floor: floor^2 per second
    at_rest = motion.default_input_sigmas(np.zeros((1, 3)), [0.25], per_m, per_rad, floor)[0]
    np.testing.assert_allclose((at_rest * 0.25) ** 2, floor**2 * 0.25, rtol=1e-12)


@pytest.mark.parametrize(
    ("row", "column", "value", "message"),
    [
        (2, "stamps", np.nan, "odometry sample 2: stamp is not finite"),
        (1, "inputs", np.inf, "odometry sample 1: input is not finite"),
        (3, "sigmas", np.nan, "odometry sample 3: sigma is not finite"),
        (2, "stamps", 0.1, "odometry sample 2: stamps must increase strictly"),
        (1, "sigmas", -0.5, "odometry sample 1: negative sigma"),
    ],
)
def test_check_odometry_names_the_first_bad_sample(row, column, value, message):
    log = {"stamps": np.arange(5) * 0.1, "inputs": np.ones((5, 3)), "sigmas": np.ones((5, 3))}
    for n in (1, 2, 5):  # one sample (online: one per message) and batches pass
        motion.check_odometry(**{k: v[:n] for k, v in log.items()})
    bad = {k: v.copy() for k, v in log.items()}
    if column == "stamps":
        bad[column][row] = value
    else:
        bad[column][row, 1] = value
    with pytest.raises(ValueError, match=message):
        motion.check_odometry(**bad)
