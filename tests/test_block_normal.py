"""The block's vectorised normal equations and observation tests against per-observation dense
references (kinreg.estimate.normal, kinreg.estimate.block)."""

import numpy as np
import pytest
from test_block import network

from kinreg.estimate import block
from kinreg.estimate import sparse as ks
from kinreg.estimate.normal import NormalEquations
from kinreg.geometry import Pose
from kinreg.types import ObservationKind, RelativeObservation

BACKENDS = [pytest.param("cholmod", marks=pytest.mark.skipif(not ks.HAVE_CHOLMOD, reason="no scikit-sparse")),
            "scipy"]


def _every_kind(rng):
    """The ring network of test_block with drift velocities on its first trajectory links (DRIFT
    ties and a prior), a station observation and a point observation on two stations."""
    truth, approx, obs = network(rng, n=24)
    obs = list(obs)
    info_v = np.diag(1.0 / np.square([1e-3] * 3 + [1e-4] * 3))
    for i in range(6):  # velocities of the links starting at stations 0..6, tied in sequence
        obs.append(RelativeObservation(ObservationKind.DRIFT, i, i + 1, Pose.identity(), info_v, 6,
                                       decay=np.array([0.9, 0.8, 0.9, 0.7, 0.9, 0.95])))
    obs.append(RelativeObservation(ObservationKind.DRIFT, 0, -1, Pose.identity(), 0.1 * info_v, 6))
    for k, o in enumerate(obs):
        if o.kind is ObservationKind.TRAJECTORY:
            obs[k] = RelativeObservation(o.kind, o.i, o.j, o.Z, o.info, o.rank, dt_s=2.0)
    obs.append(RelativeObservation(ObservationKind.STATION, 9, -1, truth[9].compose(Pose.exp(np.full(6, 1e-3))),
                                   np.diag(1.0 / np.square([2e-3] * 3 + [1e-3] * 3)), 6))
    point = truth[13].apply(np.array([0.3, -0.2, -1.3]))
    info_p = np.zeros((6, 6))
    info_p[:3, :3] = np.eye(3) / 3e-3**2
    obs.append(RelativeObservation(ObservationKind.POINT, 13, 14, Pose(np.array([1.0, 0, 0, 0]), point + 1e-3),
                                   info_p, 3, levers_m=np.array([[0.3, -0.2, -1.3], truth[14].inverse().apply(point)]),
                                   share=0.25))
    return truth, approx, obs


def _dense_normal(cols, J, P, e, n_free):
    """The textbook sum over observations and slot pairs, one 6 x 6 block at a time."""
    N = np.zeros((6 * n_free, 6 * n_free))
    b = np.zeros(6 * n_free)
    for k in range(len(cols)):
        for s in range(cols.shape[1]):
            if cols[k, s] < 0:
                continue
            rs = slice(6 * cols[k, s], 6 * cols[k, s] + 6)
            b[rs] -= J[k, s].T @ P[k] @ e[k]
            for t in range(cols.shape[1]):
                if cols[k, t] >= 0:
                    N[rs, 6 * cols[k, t]:6 * cols[k, t] + 6] += J[k, s].T @ P[k] @ J[k, t]
    return N, b


def _setup(rng, backend, drop=()):
    truth, approx, obs = _every_kind(rng)
    n = len(truth)
    fixed = np.zeros(n, dtype=bool)
    fixed[0] = True
    vnode = block.velocity_nodes(obs, n)
    everything = block._gather(obs, vnode)
    active = np.ones(len(obs), dtype=bool)
    active[list(drop)] = False
    weights = {k.value: 1.0 for k in ObservationKind} | {"planes": 0.7, "trajectory": 0.4}
    a = block._subset(everything, active, weights)
    free_index = block._free_index(fixed, int(np.count_nonzero(vnode >= 0)))
    n_free = int(free_index.max()) + 1
    normal = NormalEquations(n_free, block._columns(everything, free_index), backend=backend)
    velocity = rng.normal(0.0, 1e-4, (int(np.count_nonzero(vnode >= 0)), 6))
    state = (truth.compose(Pose.exp(rng.normal(0.0, 1e-3, (n, 6)))), velocity)
    return obs, a, fixed, free_index, n_free, normal, state


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_assembled_normal_matrix_is_the_dense_sum_over_observations(backend):
    rng = np.random.default_rng(3)
    # Some observations out (as after data snooping): their blocks stay in the pattern, as zeros.
    obs, a, fixed, free_index, n_free, normal, state = _setup(rng, backend, drop=(5, 17, 40))
    e, J = block._linearise(*state, a)
    cols = block._columns(a, free_index)
    assert (cols >= 0).all(axis=1).any()  # observations on three unknown blocks (velocity slots) too
    blocks, b = normal.assemble(normal.select(cols), J, a.P, e)
    N_ref, b_ref = _dense_normal(cols, J, a.P, e, n_free)
    N = normal.pattern.matrix(blocks).toarray()
    scale = np.abs(N_ref).max()
    assert np.abs(N - N_ref).max() <= 1e-13 * scale
    assert np.abs(b - b_ref).max() <= 1e-13 * np.abs(b_ref).max()
    # The factor, undamped and damped, solves the dense system.
    for damping in (0.0, 1e-3):
        M = N_ref + damping * np.diag(np.diag(N_ref))
        x = normal.factorize(blocks, damping).solve(b)
        x_ref = np.linalg.solve(M, b_ref)
        assert np.abs(x - x_ref).max() <= 1e-8 * np.abs(x_ref).max()


def test_a_block_shared_by_two_slots_gets_both_orders():
    """An observation whose two slots are the same unknown block (and fixed or absent slots)."""
    rng = np.random.default_rng(5)
    n_free, k = 7, 40
    cols = rng.integers(-1, n_free, (k, 3))
    cols[:5, 1] = cols[:5, 0] = np.arange(5)
    J = rng.normal(size=(k, 3, 6, 6))
    A = rng.normal(size=(k, 6, 6))
    P = A @ A.transpose(0, 2, 1)
    e = rng.normal(size=(k, 6))
    normal = NormalEquations(n_free, cols)
    blocks, b = normal.assemble(normal.select(cols), J, P, e)
    N_ref, b_ref = _dense_normal(cols, J, P, e, n_free)
    assert np.allclose(normal.pattern.matrix(blocks).toarray(), N_ref, rtol=0, atol=1e-12 * np.abs(N_ref).max())
    assert np.allclose(b, b_ref, rtol=0, atol=1e-12 * np.abs(b_ref).max())


@pytest.mark.parametrize("backend", BACKENDS)
def test_observation_tests_match_a_per_observation_reference(backend):
    """Statistics, redundancies and covariances of the vectorised tests against the cofactor
    Q_ee = P^+ - J Qxx J^T of each observation, from the dense inverse, one observation at a time."""
    rng = np.random.default_rng(11)
    obs, a, fixed, free_index, n_free, normal, state = _setup(rng, backend, drop=(8,))
    e, J = block._linearise(*state, a)
    cols = block._columns(a, free_index)
    blocks, _ = normal.assemble(normal.select(cols), J, a.P, e)
    links = block._Links.of(obs)
    tests, omega, redundancy, Qxx_blocks = block._test_observations(state, a, links, fixed, free_index,
                                                                    normal.factorize(blocks))
    N_ref, _ = _dense_normal(cols, J, a.P, e, n_free)
    Qxx = np.linalg.inv(N_ref)
    n_stations = int(np.count_nonzero(~fixed))
    ref_diag = np.array([Qxx[6 * m:6 * m + 6, 6 * m:6 * m + 6] for m in range(n_stations)])
    assert np.abs(Qxx_blocks - ref_diag).max() <= 1e-9 * np.abs(ref_diag).max()
    position = {int(k): m for m, k in enumerate(tests.index)}
    checked = 0
    for row, k in enumerate(a.idx):
        Jk = np.zeros((6, 6 * n_free))
        Jk01 = np.zeros((6, 6 * n_free))
        for s in range(3):
            if cols[row, s] >= 0:
                Jk[:, 6 * cols[row, s]:6 * cols[row, s] + 6] += J[row, s]
                if s < 2:
                    Jk01[:, 6 * cols[row, s]:6 * cols[row, s] + 6] += J[row, s]
        w, V = np.linalg.eigh(a.P[row])
        det = w > 1e-9 * w[-1]
        if not det.any():
            assert int(k) not in position
            continue
        m = position[int(k)]
        Vd, wd = V[:, det], w[det]
        VJV = Vd.T @ Jk @ Qxx @ Jk.T @ Vd
        z = Vd.T @ e[row]
        Q_zz = np.diag(1.0 / wd) - VJV
        statistic = z @ np.linalg.pinv(Q_zz, rcond=1e-9, hermitian=True) @ z
        r = np.sum(1.0 - wd * np.diag(VJV))
        sw = np.sqrt(wd)
        assert tests.dof[m] == det.sum() and tests.kind[m] == a.kinds[row]
        assert tests.redundancy[m] == pytest.approx(r, rel=1e-8, abs=1e-10)
        assert tests.vtpv[m] == pytest.approx(e[row] @ a.P[row] @ e[row], rel=1e-10)
        assert tests.statistic[m] == pytest.approx(statistic, rel=1e-7)
        assert tests.normalised[m] == pytest.approx(np.sqrt(statistic / det.sum()), rel=1e-7)
        assert tests.min_redundancy[m] == pytest.approx(
            np.linalg.eigvalsh(np.eye(len(wd)) - sw[:, None] * VJV * sw).min(), rel=1e-6, abs=1e-9)
        cov = Jk01 @ Qxx @ Jk01.T
        assert np.abs(tests.cov_adjusted[m] - cov).max() <= 1e-8 * np.abs(cov).max()
        checked += 1
    assert checked == len(tests) > 100
    assert omega == pytest.approx(float(np.sum(tests.vtpv)), rel=1e-12)
    assert redundancy == pytest.approx(float(np.sum(tests.redundancy)), rel=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_identity_slots_and_reused_arrays_change_no_bit(backend):
    """The assembly that skips the products of identity Jacobians, and the residuals and Jacobians
    written into the arrays of an earlier linearisation, give the same bits as without."""
    rng = np.random.default_rng(7)
    obs, a, fixed, free_index, n_free, normal, state = _setup(rng, backend, drop=(3,))
    cols = block._columns(a, free_index)
    unit = block._unit_slots(a)
    assert unit[:, 1].any() and not unit[:, 1].all()  # the point and the drift prior have none
    e, J = block._linearise(*state, a)
    earlier = block._linearise(state[0].compose(Pose.exp(rng.normal(0.0, 1e-2, (len(state[0]), 6)))), state[1], a)
    e2, J2 = block._linearise(*state, a, out=earlier)
    assert e2 is earlier[0] and np.array_equal(e2, e) and np.array_equal(J2, J)
    identity = J[unit[:, 1], 1]
    assert np.array_equal(identity, np.broadcast_to(np.eye(6), identity.shape))
    plain, b_plain = normal.assemble(normal.select(cols), J, a.P, e)
    selection = normal.select(cols, unit)
    for _ in range(2):  # the selection's buffers reused
        blocks, b = normal.assemble(selection, J, a.P, e)
        assert np.array_equal(blocks, plain) and np.array_equal(b, b_plain)


def test_work_in_threads_is_the_work_in_order(monkeypatch):
    monkeypatch.setattr(ks, "_MANY_BLOCKS", 1)
    out = np.zeros(100)

    def work(start):
        out[start:start + 10] = np.sqrt(np.arange(start, start + 10))

    ks.in_threads(work, range(0, 100, 10), n_blocks=10)
    assert np.array_equal(out, np.sqrt(np.arange(100)))

    def failing(start):
        raise ValueError(f"chunk {start}")

    with pytest.raises(ValueError, match="chunk"):
        ks.in_threads(failing, range(0, 100, 10), n_blocks=10)
