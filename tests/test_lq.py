"""The stage-wise (Riccati) Newton solve against the dense Hessian it replaces."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj import lq
from jtraj._testing import NLP, SolverOptions, init_multipliers, initial_guess
from jtraj.transcription import Transcription, decoupled_hessian, decoupled_hessian_bounds
from jtraj.transcription.hessian import decoupled_pieces

Q0 = jnp.array([0.0, 0.5, 0.5])
Q1 = jnp.array([1.2, -0.4, 0.9])


@pytest.fixture(scope="module")
def point():
    """An AL point of a serial3 problem with an active bound on T (so the global term
    has curvature), random multipliers, and a random set of held variables."""
    robot = jtraj.robots.get("serial3")
    p = jtraj.Problem(robot, Q0, Q1, N=16, weights=jtraj.Weights(time=1, energy=0.1, kinetic=0.2), T_max=1.35)
    tr = Transcription("decoupled")
    lay = tr.layout(p)
    nlp = NLP(problem=p, tr=tr, layout=lay, sd=tr.stage_data(p))
    # (the guess and the multipliers each in one compiled program, not op by op)
    z0 = lay.pack(*eqx.filter_jit(initial_guess)(p, SolverOptions(), tr))
    z = jnp.clip(z0 + 0.5 * (jax.random.uniform(jax.random.PRNGKey(1), z0.shape) - 0.5), lay.z_lo, lay.z_hi)
    mult = jax.tree.map(lambda x: x + 0.3, eqx.filter_jit(init_multipliers)(nlp, z))
    free = jnp.asarray(np.random.default_rng(0).random(z.shape[0]) > 0.25)
    _, g, H = eqx.filter_jit(lambda n, zz, m: n.al_derivatives(zz, m, 7.0))(nlp, z, mult)
    val, model, pieces = eqx.filter_jit(lambda n, zz, m: n.stage_newton_model(zz, m, 7.0))(nlp, z, mult)
    assert float(pieces[3]) > 0  # the bound on T is active: d2 phi / dT2 = mu / T_max^2
    return nlp, z, mult, free, g, H, model, pieces


def test_stage_model_gradient_is_the_condensed_gradient(point):
    nlp, z, mult, free, g, H, model, pieces = point
    np.testing.assert_allclose(model.g, g, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(g))))


def test_riccati_directions_equal_the_dense_solve(point):
    """(H_f + s D_free) d = -g_f with held rows fixed, for shifts on both sides of the
    smallest one that makes H_f positive definite; the positive-definiteness flags agree
    with the dense eigenvalues."""
    nlp, z, mult, free, g, H, model, pieces = point
    Hf = jnp.where(free[:, None] & free[None, :], H, 0.0) + jnp.diag(jnp.where(free, 0.0, 1.0))
    D = jnp.diag(free.astype(H.dtype))
    lam_min = float(jnp.min(jnp.linalg.eigvalsh(Hf)))
    assert lam_min < 0  # an indefinite point: the shifts matter
    shifts = jnp.array([0.5 * -lam_min, 2.0 * -lam_min, 1e-3 + 10 * -lam_min, 1e3])
    d, ok = jax.jit(lq.newton_directions)(model, free, shifts)
    for i, s in enumerate(np.asarray(shifts)):
        pd = bool(jnp.all(jnp.linalg.eigvalsh(Hf + s * D) > 0))
        assert bool(ok[i]) == pd
        if pd:
            dd = -jnp.linalg.solve(Hf + s * D, jnp.where(free, g, 0.0))
            assert float(jnp.max(jnp.abs(d[i] - dd)) / jnp.max(jnp.abs(dd))) < 1e-9
            assert bool(jnp.all(jnp.where(free, True, d[i] == 0.0)))


def test_riccati_under_vmap_equals_one_by_one(point):
    """Under vmap (the solver's batches) each problem gets its own directions."""
    nlp, z, mult, free, g, H, model, pieces = point
    k = 3
    scale = jnp.linspace(0.5, 2.0, k)
    models = jax.tree.map(lambda x: jnp.stack([x * s for s in scale]), model)
    frees = jnp.stack([free, ~free, jnp.ones_like(free)])
    shifts = jnp.stack([jnp.array([1.0, 10.0, 1e3])] * k) * scale[:, None]
    d, ok = jax.jit(jax.vmap(lq.newton_directions))(models, frees, shifts)
    one = jax.jit(lq.newton_directions)
    for i in range(k):
        di, oki = one(jax.tree.map(lambda x: x[i], models), frees[i], shifts[i])
        np.testing.assert_array_equal(ok[i], oki)
        np.testing.assert_allclose(np.nan_to_num(d[i]), np.nan_to_num(di), rtol=1e-12, atol=1e-14)


def test_hessian_bounds_diag_exact_rows_bound(point):
    """diag(H) exactly, and sum over free j of |H_ij| <= bound_i (the Gershgorin shift of
    the stage-wise path is then also always positive definite)."""
    nlp, z, mult, free, g, H, model, pieces = point

    @eqx.filter_jit  # (one program, not op by op; so is the assembly below)
    def bounds(nlp, pieces, free):
        hdiag, rows = nlp.hessian_bounds(pieces)
        return hdiag, rows(free)

    hdiag, rows = bounds(nlp, pieces, free)
    np.testing.assert_allclose(hdiag, jnp.diag(H), rtol=0, atol=1e-11 * float(jnp.max(jnp.abs(H))))
    exact = jnp.abs(H) @ free.astype(H.dtype)
    assert bool(jnp.all(rows >= exact * (1 - 1e-12)))
    excess = jnp.where(free, rows - jnp.abs(hdiag) - hdiag, -1.0)
    Hf = jnp.where(free[:, None] & free[None, :], H, 0.0) + jnp.diag(jnp.where(free, 0.0, 1.0))
    shift = jnp.maximum(0.0, jnp.max(excess)) + 1e-8
    assert float(jnp.min(jnp.linalg.eigvalsh(Hf + shift * jnp.diag(free.astype(H.dtype))))) > 0
    # the assembled Hessian and the bounds share the recursion's derivatives
    W, c, Hk, _ = pieces
    d2 = eqx.filter_jit(lambda lay, *a: decoupled_hessian_bounds(lay, *a)[0])(nlp.layout, W, c, Hk)
    H2 = eqx.filter_jit(decoupled_hessian)(nlp.layout, W, c, Hk)
    np.testing.assert_allclose(jnp.diag(H2), d2, rtol=1e-12, atol=1e-12)


def _dense_row_bounds(layout, W, c, Hk, free):
    """The bound of :func:`decoupled_hessian_bounds` the direct way: the recursion's
    Jacobian J (state rows, dense) and the co-state term C formed, then
    ``(sum_k |J_k|^T |Hk| |J_k| + |C|) 1_free``: an independent reference."""
    N, n = layout.N, layout.m_u
    ns, m = 2 * n, n + 1
    A, sy, Chv, Chh, perm = decoupled_pieces(layout, W, c)
    fy = free[np.argsort(perm)].astype(W.dtype)  # y's order: (v_0, h_0, v_1, ...)
    k, a = np.arange(N)[:, None], np.arange(m)[None, :]
    ctrl = jnp.zeros((N + 1, m, N * m), W.dtype).at[k, a, k * m + a].set(sy[k * m + a])  # selectors of u_k
    J = jnp.concatenate([A, ctrl], axis=1)  # (N+1, nw, ny): |J_k| with the stage's own controls
    r = jnp.einsum("kai,kab,kbj,j->i", jnp.abs(J), jnp.abs(Hk), jnp.abs(J), fy)
    C = jnp.zeros((N, m, N, m), W.dtype).at[:, n, :, :n].set(Chv).reshape(N * m, N * m)
    C = C + C.T + jnp.zeros((N, m, N, m), W.dtype).at[:, n, :, n].set(Chh).reshape(N * m, N * m)
    r = r + jnp.abs(C * jnp.outer(sy, sy)) @ fy
    return r[perm]


def test_hessian_row_bounds_equal_the_dense_form(point):
    """The O(N^2 n) row bounds (prefix and suffix sums over the samples) equal the
    direct product with the dense recursion Jacobian, for several sets of free columns."""
    nlp, z, mult, free, g, H, model, pieces = point
    W, c, Hk, _ = pieces
    _, rows = decoupled_hessian_bounds(nlp.layout, W, c, Hk)
    rng = np.random.default_rng(3)
    for f in [free, ~free, jnp.ones_like(free), jnp.asarray(rng.random(free.shape[0]) > 0.5)]:
        ref = _dense_row_bounds(nlp.layout, W, c, Hk, f)
        np.testing.assert_allclose(jax.jit(rows)(f), ref, rtol=1e-12, atol=1e-14 * float(jnp.max(ref)))


def test_small_cho_solve_against_numpy():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(6, 5, 5))
    A = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(5)
    A[5] = -A[5]  # not positive definite
    Y = rng.normal(size=(6, 5, 3))
    # lanes last
    X, ok = lq.small_cho_solve(jnp.asarray(A.transpose(1, 2, 0)), jnp.asarray(Y.transpose(1, 2, 0)))
    np.testing.assert_array_equal(np.asarray(ok), [True] * 5 + [False])
    np.testing.assert_allclose(np.asarray(X).transpose(2, 0, 1)[:5], np.linalg.solve(A[:5], Y[:5]), rtol=1e-10)
    assert np.all(np.isnan(np.asarray(X)[..., 5]))


@pytest.mark.slow
@pytest.mark.parametrize("N", [20, 40])
def test_riccati_and_dense_solvers_agree_on_solutions(N):
    """The default stage-wise solver and the dense one reach the same verified optima
    within 0.1 % in cost (they take different iterates: the Gershgorin shift is a bound in
    the stage-wise path; on 8 benchmark pairs the costs differed by at most 2.3e-4)."""
    robot = jtraj.robots.get("serial3")
    w = jtraj.Weights(time=1.0, energy=0.1)
    q0 = jnp.array([[0.786, -0.218, 0.119], [0.223, -0.576, 0.816]])  # benchmark pairs
    q1 = jnp.array([[0.031, 0.188, 0.18], [0.238, -0.558, 1.221]])
    a = jtraj.solve_batch(robot, q0, q1, N=N, weights=w, options=SolverOptions(linear_solver="riccati"))
    b = jtraj.solve_batch(robot, q0, q1, N=N, weights=w, options=SolverOptions(linear_solver="dense"))
    assert bool(jnp.all(a.converged)) and bool(jnp.all(b.converged))
    np.testing.assert_allclose(a.cost, b.cost, rtol=1e-3)
    assert float(jnp.max(a.max_violation["overall"])) <= 1e-6


def test_linear_solver_option():
    """"auto" is the stage-wise solve on a CPU (dense on an accelerator); other
    transcriptions are always dense; unknown names are refused."""
    from jtraj._testing import stagewise_directions

    for transcription, ls, expected in [("decoupled", "auto", jax.default_backend() == "cpu"),
                                        ("decoupled", "riccati", True), ("decoupled", "dense", False),
                                        ("coupled", "riccati", False)]:
        assert stagewise_directions(SolverOptions(linear_solver=ls), Transcription(transcription)) == expected
    with pytest.raises(ValueError, match="linear_solver"):
        SolverOptions(linear_solver="qr")
