"""The solver's derivatives of the augmented Lagrangian against independent references:
central differences of the autodiff gradient, and one forward-over-reverse pass over
each stage. (Apart from test_solver.py so that the two test workers share the load.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj

Q0 = np.array([1.077, -0.096, 0.619])
Q1 = np.array([1.2, -0.049, 0.9])


@pytest.mark.parametrize("name, transcription", [
    ("serial3_vertical", "decoupled"),
    pytest.param("serial3", "coupled", marks=pytest.mark.slow),  # ~36 s: forward dynamics in the loop
    pytest.param("serial3", "spline", marks=pytest.mark.slow),
    pytest.param("serial3", "collocation", marks=pytest.mark.slow),
])
def test_structured_hessian_matches_differences_of_the_gradient(name, transcription):
    """The solver's stage-structured Hessian (stage Hessians + co-state term of the
    recursion) against central differences of the autodiff gradient of the AL value
    (a full jax.hessian would take minutes to compile here)."""
    import jax

    from jtraj._testing import NLP, init_multipliers
    from jtraj.transcription import Transcription

    robot = jtraj.robots.get(name)
    p = jtraj.Problem(robot, Q0, Q1, N=8, weights=jtraj.Weights(time=1, energy=0.1, kinetic=0.2))
    tr = Transcription(transcription)
    lay = tr.layout(p)
    nlp = NLP(problem=p, tr=tr, layout=lay, sd=tr.stage_data(p))
    # a random point around the default guess (unbounded variables, like the spline's
    # knots, get a spread of 1 in their scaled units)
    from jtraj.solver import SolverOptions, initial_guess

    import equinox as eqx

    # (the point, the multipliers and the value each in one compiled program, not op by op)
    z0 = lay.pack(*eqx.filter_jit(initial_guess)(p, SolverOptions(), tr))
    spread = jnp.minimum(lay.z_hi - lay.z_lo, 2.0)
    z = jnp.clip(z0 + spread * (jax.random.uniform(jax.random.PRNGKey(0), z0.shape) - 0.5), lay.z_lo, lay.z_hi)
    mult = jax.tree.map(lambda x: x + 0.3, eqx.filter_jit(init_multipliers)(nlp, z))
    val, g, H = eqx.filter_jit(lambda n, zz, m: n.al_derivatives(zz, m, 7.0))(nlp, z, mult)
    grad_jit = eqx.filter_jit(lambda n, zz, m: jax.grad(n.al_value)(zz, m, 7.0))

    def grad(zz, m, mu):
        return np.asarray(grad_jit(nlp, zz, m))

    al_value = eqx.filter_jit(lambda n, zz, m: n.al_value(zz, m, 7.0))
    assert float(val) == pytest.approx(float(al_value(nlp, z, mult)), rel=1e-12)
    np.testing.assert_allclose(g, grad(z, mult, 7.0), rtol=1e-11, atol=1e-11)
    eps = 1e-5
    E = np.eye(z.shape[0]) * eps
    H_fd = np.stack([(grad(z + e, mult, 7.0) - grad(z - e, mult, 7.0)) / (2 * eps) for e in E], axis=1)
    # central differences: O(eps^2) truncation, O(1e-16/eps) rounding; the PHR kinks are
    # avoided by the random point (no constraint within eps of its switch)
    assert np.max(np.abs(H - H_fd)) / np.max(np.abs(H_fd)) < 1e-7
    np.testing.assert_allclose(H, H.T, atol=1e-12 * float(np.max(np.abs(H))))
    if transcription == "decoupled":
        # the closed-form assembly of the decoupled recursion against jacfwd through it
        generic = NLP(problem=p, tr=tr, layout=lay, sd=nlp.sd, generic_hessian=True)
        _, g2, H2 = eqx.filter_jit(lambda n, zz, m: n.al_derivatives(zz, m, 7.0))(generic, z, mult)
        np.testing.assert_allclose(g, g2, rtol=0, atol=1e-12 * float(np.max(np.abs(g2))))
        np.testing.assert_allclose(H, H2, rtol=0, atol=1e-12 * float(np.max(np.abs(H2))))


@pytest.mark.parametrize("name, transcription", [
    pytest.param("serial3_vertical", "decoupled", marks=pytest.mark.slow),
    # a minute or more each to compile on a 2-core machine beside another test worker
    pytest.param("ibm7535", "decoupled", marks=pytest.mark.slow),
    pytest.param("pkm2", "decoupled", marks=pytest.mark.slow),
    pytest.param("wmr", "decoupled", marks=pytest.mark.slow),
    pytest.param("serial3", "decoupled", marks=pytest.mark.slow),
    pytest.param("parallel3", "decoupled", marks=pytest.mark.slow),  # ~45 s to compile
    pytest.param("serial3", "spline", marks=pytest.mark.slow),
])
def test_split_stage_derivatives_match_one_pass(name, transcription):
    """The stage derivatives by the chain rule through the efforts (what the solver uses
    where the control slot is the acceleration; it relies on the inverse dynamics being
    affine in the acceleration) against one forward-over-reverse pass over the whole
    stage (``generic_hessian``), at a random point with every cost term, a via point, an
    active T_max, random multipliers and the kink curvature on rows within 0.5 of their
    PHR switch: agreement to rounding (1e-11 relative). Gravity in the default suite;
    actuators (ibm7535), closed chains (pkm2, parallel3) and a mobile base (wmr) with
    ``-m slow``."""
    import equinox as eqx

    from jtraj.gradcheck import default_weights, random_point
    from jtraj._testing import NLP, init_multipliers
    from jtraj.transcription import Transcription

    rng = np.random.default_rng(3)
    tr = Transcription(transcription)
    problem, v, h, _, mu, _ = random_point(jtraj.robots.get(name), rng, N=4, weights=default_weights())
    lay = tr.layout(problem)
    split = NLP(problem=problem, tr=tr, layout=lay, sd=tr.stage_data(problem))
    plain = NLP(problem=problem, tr=tr, layout=lay, sd=split.sd, generic_hessian=True)
    z = lay.pack(tr.initial_controls(problem, v, h), h)
    mult = jax.tree.map(lambda x: x + jnp.asarray(rng.uniform(0, 2, x.shape)),
                        eqx.filter_jit(init_multipliers)(split, z))
    derivs = eqx.filter_jit(lambda n, zz, m: n.stage_derivatives(n.W(zz), m, mu, jnp.asarray(0.5)))
    for got, want, what in zip(derivs(split, z, mult), derivs(plain, z, mult), ("value", "gradient", "Hessian")):
        assert np.all(np.isfinite(np.asarray(got))), what
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-11 * float(np.max(np.abs(want))), err_msg=what)
