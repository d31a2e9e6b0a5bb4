"""The fit's covariance, dense and block by block (`identify.covariance`).

Oracles: NumPy's inverse of `J^T J` for a dense block-arrow `J` assembled from the blocks
(standard errors, correlation), and the dense path's identifiability check for a
combination that is degenerate only after the nuisances are eliminated.
"""

from __future__ import annotations

import numpy as np
import pytest

from identify._fit import covariance

NAMES = ("link1.EI", "joint1.damping", "payload.mass")
LOG_SCALE = (True, True, False)


def _blocks(seed, L=5, n=40, k=3):
    rng = np.random.default_rng(seed)
    P = len(NAMES)
    r = rng.normal(size=(L, n))
    S = rng.normal(size=(L, n, P)) * np.array([1e3, 2.0, 30.0])
    U = rng.normal(size=(L, n, k)) * 10.0
    slots = -np.ones((L, k), int)
    nxt = 0
    for l in range(L):
        k_l = [k, 1, 0, k, 2][l % 5]  # padding, and a log with no nuisances
        slots[l, :k_l] = np.arange(nxt, nxt + k_l)
        nxt += k_l
        U[l, :, k_l:] = rng.normal(size=(n, k - k_l))  # padding columns are ignored, whatever they hold
    used = rng.uniform(size=(L, n)) > 0.15
    return r, S, U, slots, used


def _dense(r, S, U, slots, used):
    L, n, P = S.shape
    n_nuis = slots.max(initial=-1) + 1
    J = np.zeros((L, n, P + n_nuis))
    J[:, :, :P] = S
    for l in range(L):
        for j in np.flatnonzero(slots[l] >= 0):
            J[l, :, P + slots[l, j]] = U[l, :, j]
    m = used.reshape(-1)
    return r.reshape(-1)[m], J.reshape(L * n, -1)[m]


@pytest.mark.parametrize("seed", [0, 1])
def test_blocked_equals_the_inverse_of_the_dense_normal_matrix(seed):
    r, S, U, slots, used = _blocks(seed)
    rd, Jd = _dense(r, S, U, slots, used)
    cov = covariance.blocked(NAMES, LOG_SCALE, r, S, U, slots, used)
    n_res, n_par = Jd.shape
    s2 = float(rd @ rd) / (n_res - n_par)
    ref = s2 * np.linalg.inv(Jd.T @ Jd)
    assert cov.n_residuals == n_res
    assert cov.rss == pytest.approx(float(rd @ rd), rel=1e-12)
    assert cov.residual_variance == pytest.approx(s2, rel=1e-12)
    np.testing.assert_allclose(cov.std_errors, np.sqrt(np.diag(ref)), rtol=1e-9)
    d = np.sqrt(np.diag(ref))[:3]
    np.testing.assert_allclose(cov.correlation, ref[:3, :3] / np.outer(d, d), rtol=1e-9, atol=1e-12)
    assert cov.identifiability == []
    # and the dense path agrees with the same oracle
    dense = covariance.dense(NAMES, LOG_SCALE, rd, Jd)
    np.testing.assert_allclose(dense.std_errors, np.sqrt(np.diag(ref)), rtol=1e-9)
    np.testing.assert_allclose(dense.correlation, cov.correlation, rtol=1e-9, atol=1e-12)


def test_a_combination_degenerate_after_eliminating_the_nuisances_is_reported_by_both():
    r, S, U, slots, used = _blocks(3)
    # damping's column = 2 x EI's plus something each log's nuisances absorb: separable
    # only through the nuisances, i.e. not at all once they are free
    for l in range(S.shape[0]):
        cols = np.flatnonzero(slots[l] >= 0)
        extra = U[l][:, cols] @ (1e-3 * np.linspace(1.0, 2.0, cols.size)) if cols.size else 0.0
        S[l, :, 1] = 2e-3 * S[l, :, 0] + extra
    rd, Jd = _dense(r, S, U, slots, used)
    blocked = covariance.blocked(NAMES, LOG_SCALE, r, S, U, slots, used)
    dense = covariance.dense(NAMES, LOG_SCALE, rd, Jd)
    for cov in (blocked, dense):
        assert len(cov.identifiability) == 1, cov.identifiability
        combo = cov.identifiability[0]["combination"]
        assert "log link1.EI" in combo and "log joint1.damping" in combo and "payload.mass" not in combo
    # the null vector (-2e-3, 1, 0, -c_l per log): EI, damping and every log's nuisances
    # move along it without changing the fit, so they have no standard error; payload.mass
    # is orthogonal to it, and its standard error (an estimable function's: the same for any
    # generalised inverse) agrees between the two paths
    expect = np.ones(dense.std_errors.size, bool)
    expect[2] = False
    np.testing.assert_array_equal(~np.isfinite(dense.std_errors), expect)
    np.testing.assert_array_equal(~np.isfinite(blocked.std_errors), expect)
    assert blocked.std_errors[2] == pytest.approx(dense.std_errors[2], rel=1e-6)
    assert np.isnan(blocked.correlation[0, 2]) and blocked.correlation[2, 2] == pytest.approx(1.0)


def test_a_parameter_on_an_exact_null_direction_has_no_standard_error():
    """A pendulum-like degeneracy: the data see two parameters only through one
    combination (here column 1 = 2 x column 0, in other units), so both are undetermined:
    infinite standard error, no interval. The pseudo-inverse alone would give them a small
    finite one (the spread of their projection on the determined direction). The other
    parameters keep the standard errors of the model with one of the pair fixed (oracle:
    NumPy's inverse of the reduced normal matrix, the same residual variance)."""
    rng = np.random.default_rng(5)
    n = 300
    J = rng.normal(size=(n, 4)) * np.array([1e3, 1.0, 30.0, 0.2])
    J[:, 1] = 2e-3 * J[:, 0]
    r = rng.normal(size=n)
    names = ("link1.com", "link1.inertia", "joint1.damping", "payload.mass")
    cov = covariance.dense(names, (False, True, True, False), r, J)
    assert np.isinf(cov.std_errors[:2]).all()
    s2 = float(r @ r) / (n - 4)
    reduced = J[:, [0, 2, 3]]
    ref = np.sqrt(np.diag(s2 * np.linalg.inv(reduced.T @ reduced)))[1:]
    np.testing.assert_allclose(cov.std_errors[2:], ref, rtol=1e-9)
    assert cov.identifiability and "link1.com" in cov.identifiability[0]["combination"]
    # the same through the blocked path (no nuisances) and the cluster-robust one
    L = 3
    blocks = (r.reshape(L, -1), J.reshape(L, n // L, 4), np.zeros((L, n // L, 0)), np.zeros((L, 0), int))
    used = np.ones((L, n // L), bool)
    b = covariance.blocked(names, (False, True, True, False), *blocks, used)
    np.testing.assert_array_equal(np.isinf(b.std_errors), [True, True, False, False])
    np.testing.assert_allclose(b.std_errors[2:], ref, rtol=1e-9)
    cov, null = covariance.clustered(*blocks, used, null_space=True)
    np.testing.assert_array_equal(null.undetermined(), [True, True, False, False])
    # what the data see, com + 2e-3 inertia (column 1 = 2e-3 column 0), is determined;
    # either alone, or com + inertia, is not; the determined parameters are
    assert null.determines(np.array([1.0, 2e-3, 0.0, 0.0])) and null.determines(np.array([0.0, 0.0, 1.0, 1.0]))
    assert not null.determines(np.array([1.0, 0.0, 0.0, 0.0])) and not null.determines(np.array([1.0, 1.0, 0, 0]))
    assert np.isfinite(cov).all()
    assert covariance.interval_text(-np.inf, np.inf) == "not determined"
    assert covariance.interval_text(0.0, np.inf) == "not determined"
    # a log-space parameter whose interval overflowed, with a finite standard error (review: "not determined"
    # beside SE 0.0341 read as a contradiction)
    assert covariance.interval_text(0.0, np.inf, 0.0341) == "[0, inf)"
    assert covariance.interval_text(0.0, np.inf, np.inf) == "not determined"


def test_no_nuisances_and_no_shared_parameters():
    r, S, U, slots, used = _blocks(4)
    rd, Jd = _dense(r, S, U[:, :, :0], slots[:, :0], used)
    cov = covariance.blocked(NAMES, LOG_SCALE, r, S, U[:, :, :0], slots[:, :0], used)
    s2 = float(rd @ rd) / (Jd.shape[0] - Jd.shape[1])
    np.testing.assert_allclose(cov.std_errors, np.sqrt(np.diag(s2 * np.linalg.inv(Jd.T @ Jd))), rtol=1e-9)
    # nuisances only (every physical parameter fixed)
    rd, Jd = _dense(r, S[:, :, :0], U, slots, used)
    cov = covariance.blocked((), (), r, S[:, :, :0], U, slots, used)
    s2 = float(rd @ rd) / (Jd.shape[0] - Jd.shape[1])
    np.testing.assert_allclose(cov.std_errors, np.sqrt(np.diag(s2 * np.linalg.inv(Jd.T @ Jd))), rtol=1e-9)
    assert cov.correlation.shape == (0, 0)


# ---------------------------------------------------------------------------
# cluster-robust covariance (clusters = logs)
# ---------------------------------------------------------------------------


def _clustered_experiment(rng, L, n, rho, reps):
    """`reps` least-squares fits of a linear model with 2 shared slopes and one offset per
    log, under AR(1) noise of lag-one correlation `rho` within each log (independent
    between logs). Returns the estimates `(reps, 2)`, the cluster-robust and the white-noise
    covariances of each fit."""
    t = np.linspace(0.0, 1.0, n)
    S = np.stack([np.stack([np.sin(2 * np.pi * (t + 0.07 * l)), t * (1 + 0.05 * l)], axis=1) for l in range(L)])
    U = np.ones((L, n, 1))
    slots = np.arange(L)[:, None]
    used = np.ones((L, n), bool)
    beta = np.array([1.0, -0.5])
    Sc = S - S.mean(axis=1, keepdims=True)  # the offsets eliminated exactly
    A = np.einsum("lnp,lnq->pq", Sc, Sc)
    est, robust, white = [], [], []
    for _ in range(reps):
        e = np.empty((L, n))
        e[:, 0] = rng.normal(size=L)
        for k in range(1, n):
            e[:, k] = rho * e[:, k - 1] + np.sqrt(1 - rho**2) * rng.normal(size=L)
        y = S @ beta + rng.normal(size=(L, 1)) + e
        yc = y - y.mean(axis=1, keepdims=True)
        b = np.linalg.solve(A, np.einsum("lnp,ln->p", Sc, yc))
        r = S @ b - y
        r -= r.mean(axis=1, keepdims=True)  # the fitted offsets
        est.append(b)
        robust.append(covariance.clustered(r, S, U, slots, used))
        white.append(covariance.blocked(("a", "b"), (False, False), r, S, U, slots, used).std_errors[:2] ** 2)
    return np.array(est), np.array(robust), np.array(white)


def test_clustered_covariance_matches_the_sampling_distribution_under_correlated_noise():
    """Oracle: the sampling distribution itself. 800 repetitions of a 40-log least-squares
    fit whose noise is strongly correlated along each log (AR(1), rho = 0.95): the mean
    cluster-robust variance matches the estimates' empirical variance (Monte-Carlo error
    ~5 %), its t intervals (39 dof) cover the truth ~95 % of the time, and the white-noise
    variance `s^2 (J^T J)^-1` underestimates it several-fold (why `clustered` exists).
    Measured: mean robust / empirical variance 0.985 and 1.022, coverage 95.4 % and 94.8 %,
    white / empirical 0.062 and 0.047."""
    rng = np.random.default_rng(7)
    est, robust, white = _clustered_experiment(rng, L=40, n=60, rho=0.95, reps=800)
    empirical = est.var(axis=0, ddof=1)
    mean_robust = np.array([robust[:, 0, 0].mean(), robust[:, 1, 1].mean()])
    np.testing.assert_allclose(mean_robust / empirical, 1.0, atol=0.15)
    assert np.all(white.mean(axis=0) < empirical / 4)
    from scipy.stats import t as student_t

    q = student_t.ppf(0.975, 39)
    se = np.sqrt(np.stack([robust[:, 0, 0], robust[:, 1, 1]], axis=1))
    covered = np.abs(est - np.array([1.0, -0.5])) <= q * se
    assert np.all((covered.mean(axis=0) > 0.92) & (covered.mean(axis=0) < 0.98)), covered.mean(axis=0)


def test_clustered_covariance_equals_the_white_one_on_white_noise():
    """With white noise both estimators are consistent: their mean variances agree (and
    match the sampling variance) to Monte-Carlo error."""
    rng = np.random.default_rng(3)
    est, robust, white = _clustered_experiment(rng, L=40, n=60, rho=0.0, reps=400)
    empirical = est.var(axis=0, ddof=1)
    mean_robust = np.array([robust[:, 0, 0].mean(), robust[:, 1, 1].mean()])
    np.testing.assert_allclose(mean_robust / white.mean(axis=0), 1.0, atol=0.1)
    np.testing.assert_allclose(white.mean(axis=0) / empirical, 1.0, atol=0.2)


def test_clustered_covariance_needs_two_logs():
    r, S, U, slots, used = _blocks(0, L=1)
    with pytest.raises(ValueError, match="at least 2 logs"):
        covariance.clustered(r, S, U, slots, used)


@pytest.mark.parametrize(
    ("lo", "hi", "text"),
    [
        (11.99513, 12.00087, "[11.995, 12.001]"),  # a tight interval: its ends differ
        (0.04999918, 0.05000082, "[0.0499992, 0.0500008]"),
        (0.8, 1.4, "[0.8, 1.4]"),  # a wide one keeps the usual 4 digits
        (-3.2e-3, 4.1e-3, "[-0.0032, 0.0041]"),  # across zero
        (2.5, 2.5, "[2.5, 2.5]"),  # a zero width (a parameter the data fix exactly): 4 digits
        (float("nan"), float("nan"), "[nan, nan]"),
        # found on a real log: value / width underflowed to 0 and math.log10 raised
        # "math domain error" after a 5-minute fit; its ends at their 4 digits
        (5e-324, 10.0, "[4.941e-324, 10]"),
        (1e-300, 1e300, "[1e-300, 1e+300]"),  # (and the quotient overflowing)
    ],
)
def test_an_interval_prints_with_the_digits_that_tell_its_ends_apart(lo, hi, text):
    assert covariance.interval_text(lo, hi) == text
    if np.isfinite(lo) and hi > lo:
        a, b = (float(x) for x in text.strip("[]").split(", "))
        assert a < b and abs(a - lo) < (hi - lo) / 10 and abs(b - hi) < (hi - lo) / 10


def test_digits_show_a_change_of_the_spread():
    assert covariance.digits(11.998, 0.00146) == 5  # 11.998, where 4 digits print 12
    assert covariance.digits(1.0, 1e-15) == 12  # capped
    assert covariance.digits(0.0, 1.0) == covariance.digits(1.0, 0.0) == covariance.digits(1.0, np.inf) == 4


def test_a_parameter_the_nuisances_absorb_is_undetermined_in_both_paths():
    """A shared column that each log's nuisances reproduce exactly (an offset fitted per log
    and a parameter that only shifts the output) is not determined. After the projection
    its column is roundoff; scaled by its own (roundoff) norm it would look like a full
    column, and get a large finite error. Scaled by the column before the projection it
    is dropped, as the dense path drops it."""
    r, S, U, slots, used = _blocks(6)
    for l in range(S.shape[0]):
        cols = np.flatnonzero(slots[l] >= 0)
        S[l, :, 2] = U[l][:, cols] @ np.linspace(1.0, 2.0, cols.size) if cols.size else 0.0
    rd, Jd = _dense(r, S, U, slots, used)
    dense = covariance.dense(NAMES, LOG_SCALE, rd, Jd)
    blocked = covariance.blocked(NAMES, LOG_SCALE, r, S, U, slots, used)
    assert np.isinf(dense.std_errors[2]) and np.isinf(blocked.std_errors[2])
    np.testing.assert_allclose(blocked.std_errors[:2], dense.std_errors[:2], rtol=1e-6)
    np.testing.assert_array_equal(np.isinf(blocked.std_errors), np.isinf(dense.std_errors))


def test_blocked_agrees_with_dense_on_absorbed_columns_and_on_nuisances_a_null_direction_misses():
    """Two cases found in review, the dense path as the oracle. (1) Every shared column is
    mostly absorbed by the per-log offsets, one of them exactly: after the projection the
    block's largest singular value is far below its columns' size, and the rank cut must
    be taken against the size (else the absorbed column's roundoff was kept: SE 3e14).
    (2) Zero-mean shared columns with a null direction among them, and a constant offset per
    log: `G = U^+ S` is zero (roundoff), so the offsets do not move along the null
    direction and stay determined (the roundoff, compared with its own size, flagged them)."""
    rng = np.random.default_rng(11)
    L, n = 5, 600
    U = rng.normal(size=(L, n, 1))
    S = np.empty((L, n, 2))
    S[..., 0] = 2.7 * U[..., 0]
    S[..., 1] = U[..., 0] + 1e-4 * rng.normal(size=(L, n))
    r, slots, used = rng.normal(size=(L, n)), np.arange(L)[:, None], np.ones((L, n), bool)
    names = ("a", "b")
    blocked = covariance.blocked(names, (False, False), r, S, U, slots, used)
    dense = covariance.dense(names, (False, False), *_dense(r, S, U, slots, used))
    np.testing.assert_array_equal(np.isinf(blocked.std_errors), np.isinf(dense.std_errors))
    assert np.isinf(blocked.std_errors[0]) and np.isfinite(blocked.std_errors[1])
    np.testing.assert_allclose(blocked.std_errors[1], dense.std_errors[1], rtol=1e-6)

    S = rng.normal(size=(L, n, 3))
    S -= S.mean(axis=1, keepdims=True)
    S[..., 2] = S[..., 0] + 0.3 * S[..., 1]
    U = np.ones((L, n, 1))
    names = ("a", "b", "c")
    blocked = covariance.blocked(names, (False,) * 3, r, S, U, slots, used)
    dense = covariance.dense(names, (False,) * 3, *_dense(r, S, U, slots, used))
    np.testing.assert_array_equal(np.isinf(blocked.std_errors), [True] * 3 + [False] * L)
    np.testing.assert_array_equal(np.isinf(dense.std_errors), [True] * 3 + [False] * L)
    np.testing.assert_allclose(blocked.std_errors[3:], dense.std_errors[3:], rtol=1e-9)
