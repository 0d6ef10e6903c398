"""The ALD solver against independent references.

* every trajectory reported converged is re-simulated from its own (v, h) by the
  NumPy + Pinocchio verifier of ``jtraj_peers/verify.py`` (no jtraj code);
* its cost is compared with CasADi + IPOPT on the same transcription (<= 0.5 %);
* bad input is rejected before tracing, per-sample status codes in batches.

All solves share N = 10 and the default options so that the suite compiles the solver
once for single problems and once for batches.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj import Status
from jtraj import _testing as S
from jtraj.solver import SolverOptions


N = 10
W = jtraj.Weights(time=1.0, energy=0.1)
Q0 = np.array([1.077, -0.096, 0.619])
Q1 = np.array([1.2, -0.049, 0.9])  # feasible with N = 10 (T <= 1 s); IPOPT converges too
# every AL run is cut short, then restarted (the interior-point method, which "auto" takes
# here, solves these problems in 11-13 iterations and never restarts)
RESTART = SolverOptions(method="al", max_iter=12, restart_iter=300)


@pytest.fixture(scope="module")
def robot():
    return jtraj.robots.get("serial3")


@pytest.fixture(scope="module")
def single(robot):
    problem = jtraj.Problem(robot, Q0, Q1, N=N, weights=W)
    return problem, jtraj.solve(problem)


@pytest.fixture(scope="module")
def single_al(robot):
    """``single`` by the AL loop (``method="al"``; the default "auto" takes the
    interior-point method there), for the tests of the loop's own behaviour."""
    problem = jtraj.Problem(robot, Q0, Q1, N=N, weights=W)
    return problem, jtraj.solve(problem, options=SolverOptions(method="al"))


@pytest.fixture(scope="module")
def batch(robot):
    rng = np.random.default_rng(3)
    q0 = rng.uniform(-1.2, 1.2, (4, 3))
    q1 = q0 + rng.uniform(-0.25, 0.25, (4, 3))
    q1[3] = np.nan  # one bad sample must not poison the others
    # and one that jtraj.Problem refuses (the move needs 2 s, N h_max = 1 s)
    q0, q1 = np.vstack([q0, q0[2]]), np.vstack([q1, q0[2] + 3.0])
    # the default path on a CPU: the interior-point method's lanes (4 for the three valid
    # problems), the last ones on 2 (single solves, 2 lanes refilled and the one-shot batch
    # check it below; test_dataset.py's real-solver chunk of 8 pairs runs the same programs
    # and 16 lanes)
    return q0, q1, jtraj.solve_batch(robot, q0, q1, N=N, weights=W)


def test_single_solve_converges_and_verifies_independently(single):
    V = pytest.importorskip("jtraj_peers.verify")
    problem, sol = single
    assert sol.converged, sol.status_message
    assert sol.status_message.startswith("converged")
    assert sol.q.shape == (N + 1, 3) and sol.v.shape == (N, 3) and sol.h.shape == (N,)
    chk = V.verify(Q0, Q1, np.asarray(sol.v), np.asarray(sol.h), tol=1e-6)
    assert chk["ok"], chk["max_rel_violation"]
    assert chk["goal_error"] <= 1e-6
    assert chk["cost"] == pytest.approx(float(sol.cost), rel=1e-9)
    np.testing.assert_allclose(chk["tau"], np.asarray(sol.tau), atol=1e-8)
    assert float(sol.T) == pytest.approx(float(jnp.sum(sol.h)))
    terms = {k: float(v) for k, v in sol.cost_terms.items()}
    assert sum(terms.values()) == pytest.approx(float(sol.cost))
    assert terms["time"] == pytest.approx(float(sol.T))


#: four pairs of serial3 with its first joint slowed to 0.02 rad/s (accelerations to
#: 3 rad/s^2, periods to 0.2 s) that stall as "likely infeasible" at N = 10 when the
#: accelerations are scaled by qdd_max alone
SLOW_PAIRS = [([-0.04189740371833195, -0.6805221707258429, 0.46915430281842907],
               [-0.06730877358313905, -0.41431909078937523, 0.18741381562507542]),
              ([0.7834221408903144, 0.17032587978181613, -0.057380669636337256],
               [0.7564954981994023, -0.05915971390204133, 0.29287041872667086]),
              ([0.6995366749323075, -0.2121453347353297, -0.040632152975450087],
               [0.667354811522114, 0.1410901365520827, -0.8210120445420219]),
              ([-0.26142738781116015, -0.8302104556690639, -0.6129448370689712],
               [-0.23642150195447714, -0.9666245083477961, -0.27189653696720284])]


def test_a_slow_joint_is_scaled_by_its_velocity_bound(robot):
    """A joint whose velocity bound is small against its acceleration bound has its
    accelerations scaled by ``2 qd_max / h_max`` (``Decoupled.control_box``; the box is
    still ``|v| <= qdd_max``), and the pairs that stall with the accelerations scaled by
    qdd_max converge, verified independently (NumPy recursion, Pinocchio's RNEA)."""
    V = pytest.importorskip("jtraj_peers.verify")
    from jtraj.transcription.methods import Decoupled

    qd_max = np.array([0.02, 2.0, 2.0])
    slow = jtraj.robots.with_params(robot, qd_max=qd_max, h_max=0.2)
    lim = slow.limits
    scale, lo, hi = Decoupled().control_box(jtraj.Problem(slow, *SLOW_PAIRS[0], N=N, weights=W))
    expected = np.minimum(np.asarray(lim.qdd_max), 2 * qd_max / 0.2)
    np.testing.assert_allclose(np.asarray(scale), expected, rtol=1e-15)
    assert expected[0] < float(lim.qdd_max[0]) and np.all(expected[1:] == np.asarray(lim.qdd_max)[1:])
    np.testing.assert_allclose(np.asarray(hi) * np.asarray(scale), np.asarray(lim.qdd_max), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(lo), -np.asarray(hi))
    for a, b in SLOW_PAIRS:
        sol = jtraj.solve(jtraj.Problem(slow, a, b, N=N, weights=W))
        assert sol.converged and int(sol.iterations) <= 100, (sol.status_message, int(sol.iterations))
        chk = V.verify(a, b, np.asarray(sol.v), np.asarray(sol.h), qd_max=qd_max, h_max=0.2, tol=1e-6)
        assert chk["ok"], chk["max_rel_violation"]
        assert chk["cost"] == pytest.approx(float(sol.cost), rel=1e-9)


def test_mirrored_pair_has_the_mirrored_optimum(robot, single):
    # serial3's inverse dynamics are odd and its limits symmetric: the reflection q -> -q
    # maps its optimal trajectories onto optimal ones (what jtraj train's mirror
    # augmentation relies on, see jtraj.mappings.mirror_symmetry)
    _, sol = single
    mir = jtraj.solve(jtraj.Problem(robot, -Q0, -Q1, N=N, weights=W))
    assert mir.converged, mir.status_message
    np.testing.assert_allclose(np.asarray(mir.q), -np.asarray(sol.q), atol=1e-8)
    np.testing.assert_allclose(np.asarray(mir.tau), -np.asarray(sol.tau), atol=1e-6)
    np.testing.assert_allclose(np.asarray(mir.h), np.asarray(sol.h), atol=1e-10)
    assert float(mir.cost) == pytest.approx(float(sol.cost), rel=1e-9)


def test_cost_matches_ipopt(single):
    P = pytest.importorskip("jtraj_peers.ipopt_peer")
    _, sol = single
    ref = P.solve_pair(Q0, Q1, N=N)
    assert ref["success"]
    # goal of the issue: at most IPOPT's cost + 0.5 %
    assert float(sol.cost) <= ref["cost"] * 1.005
    assert float(sol.cost) >= ref["cost"] * 0.99  # same problem: no spurious "better" optimum


@pytest.mark.slow
def test_warm_start_from_solution_is_immediate(single, single_al):
    problem, sol = single
    certified = single_al[1]
    warm = jtraj.solve(problem, init=(certified.v, certified.h))
    assert warm.converged
    # an optimum the least-squares certificate accepts (the AL loop's) meets both
    # tolerances: finished before the first iteration (the AL loop's warm start)
    assert int(warm.iterations) == 0
    assert float(warm.cost) == pytest.approx(float(certified.cost), rel=1e-6)
    # the interior-point optimum stops before the barrier parameter's last fall
    # (SolverOptions.ip_dual_tol): rows active with multipliers near 1e-3 still sit about
    # 1e-3 from their bounds, which the least-squares certificate counts as inactive
    # (measured 0.016 against 3e-4), so a warm start from it runs, in fewer iterations
    again = jtraj.solve(problem, init=(sol.v, sol.h))
    assert again.converged and int(again.iterations) < int(sol.iterations)
    assert float(again.cost) == pytest.approx(float(sol.cost), rel=1e-4)
    # a nearby point that does not (accelerations off by 1 %) takes iterations
    near = jtraj.solve(problem, init=(sol.v * 0.99, sol.h))
    assert near.converged and 0 < int(near.iterations) < int(sol.iterations)
    assert float(near.cost) == pytest.approx(float(sol.cost), rel=1e-4)
    # primal-only warm start: cold multipliers and penalty, same compiled solver
    primal = jtraj.solve(problem, init=(sol.v, sol.h), warm="primal")
    assert primal.converged
    assert float(primal.cost) == pytest.approx(float(sol.cost), rel=1e-4)
    with pytest.raises(ValueError, match="warm"):
        jtraj.solve(problem, init=(sol.v, sol.h), warm="dual")


def test_batch_statuses_and_no_false_convergence(robot, batch):
    V = pytest.importorskip("jtraj_peers.verify")
    q0, q1, sol = batch
    assert sol.q.shape == (5, N + 1, 3) and sol.status.shape == (5,)
    status = np.asarray(sol.status)
    assert status[3] == Status.INVALID_INPUT and not bool(sol.converged[3])
    # infeasible on its face: flagged without an iteration, like a non-finite sample
    with pytest.raises(ValueError, match="N = 10 is too small"):
        jtraj.Problem(robot, q0[4], q1[4], N=N)
    assert status[4] == Status.INVALID_INPUT and int(sol.iterations[4]) == 0
    assert np.all(np.isfinite(np.asarray(sol.q)))  # never a NaN trajectory
    for i in range(3):
        if bool(sol.converged[i]):
            chk = V.verify(q0[i], q1[i], np.asarray(sol.v[i]), np.asarray(sol.h[i]), tol=1e-6)
            assert chk["ok"], (i, chk["max_rel_violation"], chk["goal_error"])
    assert np.sum(np.asarray(sol.converged[:3])) >= 2


def test_problem_needing_more_time_than_n_h_max_stops_as_likely_infeasible(robot):
    """0.7 rad on every joint is within reach kinematically in N h_max = 1 s (bang-bang:
    0.97 s) but not under serial3's torque limits: the violation stalls while the penalty
    grows, and the solver stops early instead of running out its iterations."""
    q0 = np.array([0.0, 0.3, -0.3])
    problem = jtraj.Problem(robot, q0, q0 + 0.7, N=N, weights=W)
    sol = jtraj.solve(problem)
    assert int(sol.status) == Status.LIKELY_INFEASIBLE, sol.status_message
    assert "likely infeasible" in sol.status_message and not bool(sol.converged)
    assert float(sol.max_violation["overall"]) > 1e-3
    assert int(sol.iterations) < SolverOptions().max_iter


@pytest.mark.slow
def test_stalled_subproblems_end_early_and_infeasibility_is_still_detected(robot):
    """The infeasible problem above, with the stall exit of ``SolverOptions.stall_window``
    active from the first iteration (``stall_after=0``) and checked every 5 Newton
    iterations: its subproblems, whose AL hardly moves while the violation stays frozen,
    end before ``max_inner`` and the run stops as likely infeasible in fewer iterations
    than with the exit off; the violation it reports is the same minimum it reaches
    either way (to 1e-3 relative)."""
    q0 = np.array([0.0, 0.3, -0.3])
    problem = jtraj.Problem(robot, q0, q0 + 0.7, N=N, weights=W)
    off = jtraj.solve(problem, options=SolverOptions(stall_window=0, method="al"))
    on = jtraj.solve(problem, options=SolverOptions(stall_window=5, stall_after=0, method="al"))
    for sol in (off, on):
        assert int(sol.status) == Status.LIKELY_INFEASIBLE, sol.status_message
    assert int(on.iterations) < 0.8 * int(off.iterations), (int(on.iterations), int(off.iterations))
    np.testing.assert_allclose(float(on.max_violation["overall"]), float(off.max_violation["overall"]), rtol=1e-3)
    with pytest.raises(ValueError, match="stall_window"):
        SolverOptions(stall_window=-1)
    with pytest.raises(ValueError, match="stall_ratio"):
        SolverOptions(stall_ratio=float("nan"))


@pytest.mark.slow
def test_a_penalty_stuck_at_its_cap_also_stops_as_likely_infeasible(robot):
    """The same infeasible problem with the penalty capped at 4x its start: it can never
    grow 16x, so only the second rule of ``SolverOptions.detect_infeasible`` (violation
    hardly shrinking with the penalty at its cap) can stop it early; without detection
    the run goes on to the outer-iteration limit, its violation frozen."""
    q0 = np.array([0.0, 0.3, -0.3])
    problem = jtraj.Problem(robot, q0, q0 + 0.7, N=N, weights=W)
    capped = SolverOptions(penalty_max=40.0, restart_iter=0, method="al")
    sol = jtraj.solve(problem, options=capped)
    assert int(sol.status) == Status.LIKELY_INFEASIBLE, sol.status_message
    assert int(sol.outer_iterations) < capped.max_outer // 2
    off = jtraj.solve(problem, options=SolverOptions(penalty_max=40.0, restart_iter=0, detect_infeasible=False,
                                                     method="al"))
    assert int(off.status) == Status.MAX_ITERATIONS and int(off.outer_iterations) == capped.max_outer


def test_batch_matches_single(robot, batch):
    q0, q1, sol = batch
    one = jtraj.solve(jtraj.Problem(robot, q0[0], q1[0], N=N, weights=W))
    assert int(one.status) == int(sol.status[0])
    np.testing.assert_allclose(np.asarray(one.h), np.asarray(sol.h[0]), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("kwargs, match", [
    (dict(N=1), "N must be"),
    (dict(q_goal=[0.1, 0.2]), "q_goal"),
    (dict(q_start=[np.nan, 0.0, 0.0]), "q_start"),
    (dict(T_max=0.05), "T_max"),
    (dict(T_max=-1.0), "T_max"),
    (dict(N=2, q_goal=[2.0, 0.0, 0.0]), "N = 2 is too small"),
    (dict(qd_start=[5.0, 0.0, 0.0]), "qd_start"),
    (dict(via_points=[jtraj.ViaPoint(np.array([1.0, 1.0]), tol=0.0)]), r"via_points\[0\]\.tol"),
    (dict(via_points=[[1.0, 1.0, 1.0]]), r"via_points\[0\] must have shape \(2,\)"),
])
def test_bad_problem_input(robot, kwargs, match):
    args = dict(q_start=Q0, q_goal=Q1, N=N, weights=W)
    args.update(kwargs)
    q_start, q_goal = args.pop("q_start"), args.pop("q_goal")
    with pytest.raises(ValueError, match=match):
        jtraj.Problem(robot, q_start, q_goal, **args)


@pytest.mark.parametrize("name, q_start, q_goal, match", [
    ("serial3", Q0, Q1, None),
    ("serial3", Q0, Q0 + 3.0, "N = 10 is too small"),
    ("parallel3", [0.1, 0.1], [0.2, -0.1], None),
    ("parallel3", [0.1, 0.1], [0.5, 0.5], "q_goal .* path constraints"),  # a leg nearly stretched
    ("parallel3", [0.1, 0.1], [0.6, 0.0], "q_goal .* joint limits"),
    ("pkm2", [0.0, -1.2], [0.3, -1.0], None),
    ("pkm2", [0.0, -1.2], [0.0, -1.8], "q_goal .* joint limits"),
])
def test_face_check_traced_agrees_with_the_problem_check(name, q_start, q_goal, match):
    """A batch flags as INVALID_INPUT exactly the problems a single Problem refuses:
    the traced check (under jit) and the eager ValueError agree."""
    robot = jtraj.robots.get(name)
    unchecked = jtraj.Problem(robot, q_start, q_goal, N=N, validate=False)
    flagged = bool(jax.jit(lambda p: p.infeasible_on_its_face())(unchecked))
    assert flagged == (match is not None)
    if match is None:
        jtraj.Problem(robot, q_start, q_goal, N=N)
    else:
        with pytest.raises(ValueError, match=match):
            jtraj.Problem(robot, q_start, q_goal, N=N)


def _tip(q):
    """serial3's tip by its closed form (lengths 1.0, 0.8, 0.45 m; no jtraj code)."""
    phi = np.cumsum(q)
    return np.array([1.0, 0.8, 0.45]) @ np.stack([np.cos(phi), np.sin(phi)], axis=1)


VIA_TOL = 1e-3  # one via point, at sample round(N / 2)


@pytest.fixture(scope="module")
def via(robot, single):
    """The single problem with one via point 1 cm (10 tol) off the free optimum's tip at
    sample N / 2: the passage must bind."""
    target = _tip(np.asarray(single[1].q[N // 2])) + np.array([0.01, 0.0])
    problem = jtraj.Problem(robot, Q0, Q1, N=N, weights=W, via_points=[jtraj.ViaPoint(target, tol=VIA_TOL)])
    return problem, jtraj.solve(problem), target


def test_via_point_is_passed_within_its_own_tolerance(single, via):
    V = pytest.importorskip("jtraj_peers.verify")
    free = single[1]
    problem, sol, target = via
    tol, k = VIA_TOL, N // 2
    assert problem.via_samples() == (k,)
    assert sol.converged, sol.status_message
    q, _ = V.simulate(Q0, np.asarray(sol.v), np.asarray(sol.h))
    dist = np.linalg.norm(_tip(q[k]) - target)
    # converged promises the Euclidean distance within tol + verify_tol (1e-6); the box
    # the solver imposes is inscribed in that ball, so the passage lies between
    # tol / sqrt(2) and tol, and binds (the free optimum is 10 tol away)
    assert tol / np.sqrt(2) * (1 - 1e-3) <= dist <= tol + 1e-6
    assert float(sol.max_violation["via"]) == pytest.approx(max(dist - tol, 0.0), abs=1e-12)
    assert float(sol.cost) > float(free.cost)
    chk = V.verify(Q0, Q1, np.asarray(sol.v), np.asarray(sol.h), tol=1e-6)
    assert chk["ok"], chk["max_rel_violation"]


def test_bad_batch_input(robot):
    with pytest.raises(ValueError, match="q_start"):
        jtraj.solve_batch(robot, np.zeros((2, 2)), np.zeros((2, 2)), N=N)
    with pytest.raises(ValueError, match="q_goal"):
        jtraj.solve_batch(robot, np.zeros((2, 3)), np.zeros((3, 3)), N=N)
    with pytest.raises(ValueError, match="robot"):
        jtraj.solve_batch("serial3", np.zeros((2, 3)), np.zeros((2, 3)), N=N)
    for slots in (0, True, "many"):
        with pytest.raises(ValueError, match="slots"):
            jtraj.solve_batch(robot, np.zeros((2, 3)), np.ones((2, 3)), N=N, slots=slots)
    with pytest.raises(ValueError, match="transcription"):
        jtraj.solve(jtraj.Problem(robot, Q0, Q1, N=N), transcription="magic")
    with pytest.raises(ValueError, match="init"):
        jtraj.solve(jtraj.Problem(robot, Q0, Q1, N=N), init=(np.zeros((N, 2)), np.ones(N) * 0.05))


def test_weights_validation():
    assert jtraj.Weights.parse("time=1,energy=0.5").energy == 0.5
    with pytest.raises(ValueError, match="weights"):
        jtraj.Weights.parse("speed=1")
    with pytest.raises(ValueError):
        jtraj.Weights(time=-1.0)
    with pytest.raises(ValueError, match="singularity"):
        jtraj.Weights(singularity=float("nan"))


def test_weights_are_values_and_their_terms_are_static(robot):
    """A compiled solver serves any weight values: problems that differ only in their
    weights share their static part (what ``eqx.filter_jit`` caches on), however the
    values are given. A concrete zero drops the kinetic or singularity term from the structure (its
    derivatives are never computed), a traced weight keeps it, and the dropped term
    really is absent from the cost while a kept one counts."""
    import equinox as eqx

    def structure(w):  # what eqx.filter_jit keys its cache on: the non-array part
        static = eqx.partition(jtraj.Problem(robot, Q0, Q1, N=N, weights=w), eqx.is_array)[1]
        leaves, treedef = jax.tree.flatten(static)
        return treedef, [repr(x) for x in leaves]

    base = structure(jtraj.Weights(time=1.0, energy=0.1))
    assert structure(jtraj.Weights(time=2.0, energy=0.3)) == base
    assert structure(jtraj.Weights(time=np.float32(1.0), energy=jnp.asarray(0.2), kinetic=jnp.asarray(0.0))) == base
    on = jtraj.Weights(time=1.0, energy=0.1, singularity=0.01)
    assert on.has_singularity and not on.has_kinetic and structure(on) != base
    assert jtraj.Weights(kinetic=0.0, Q=np.eye(3)).has_kinetic
    assert jax.jit(lambda s: jnp.asarray(jtraj.Weights(singularity=s).has_singularity))(0.0)
    # the terms' values: a kept term counts, a dropped one is zero
    from jtraj.transcription import Transcription

    tr = Transcription("decoupled")

    def terms(w):
        p = jtraj.Problem(robot, Q0, Q1, N=N, weights=w)
        lay = tr.layout(p)
        u, h = jtraj.solver.initial_guess(p, SolverOptions(), tr)
        W = tr.stage_vectors(p, lay, lay.pack(u, h))
        return eqx.filter_jit(jax.vmap(lambda wk, sk: tr.stage_cost_terms(p, wk, sk)))(W, tr.stage_data(p))

    assert float(jnp.sum(terms(on)["singularity"])) > 0
    assert float(jnp.sum(terms(jtraj.Weights(time=1.0, energy=0.1))["singularity"])) == 0.0


def test_inner_tolerance_schedules():
    """The subproblem tolerance follows the violation (default) or shrinks tenfold per
    outer iteration (inner_tol_ratio=0), never below tol_optimality nor above 1e-2."""
    from jtraj._testing import next_inner_tol

    follow, geometric = SolverOptions(), SolverOptions(inner_tol_ratio=0.0)
    assert follow.inner_tol_ratio == 0.01 and follow.tol_optimality == 3e-4
    for viol, want in [(5.0, 1e-2), (5e-2, 5e-4), (3e-3, 3e-4)]:
        assert float(next_inner_tol(follow, 1e-3, viol)) == pytest.approx(want, rel=1e-12)
    assert float(next_inner_tol(geometric, 1e-2, 5e-2)) == pytest.approx(1e-3, rel=1e-12)
    assert float(next_inner_tol(geometric, 2e-3, 5e-2)) == pytest.approx(3e-4, rel=1e-12)
    with pytest.raises(ValueError, match="inner_tol_ratio"):
        SolverOptions(inner_tol_ratio=-1.0)
    for kw in (dict(tol_optimality=0.0), dict(tol_feasibility=float("nan")), dict(verify_tol=-1e-6),
               dict(penalty_max=float("inf")), dict(penalty_growth=1.0), dict(feasibility_ratio=1.5)):
        with pytest.raises(ValueError, match=next(iter(kw))):
            SolverOptions(**kw)


def test_held_variables_need_the_gradient_to_beat_their_curvature():
    """Projected Newton holds a variable at a bound only if it is within eps of it, the
    gradient pushes outwards, and the diagonal Newton step -g / hdiag reaches the bound
    (always where the curvature is not positive)."""
    from jtraj._testing import held_bounds

    lo, hi, eps = jnp.zeros(7), jnp.ones(7), 1e-3
    z = jnp.array([0.0, 6e-4, 6e-4, 6e-4, 6e-4, 0.5, 1 - 6e-4])
    g = jnp.array([1e-6, 7e-4, 7e-4, 7e-4, -7e-4, 1.0, -7e-4])
    hdiag = jnp.array([1e3, 1e3, 1.0, -5.0, 1.0, 0.0, 1e3])
    held = np.asarray(held_bounds(z, g, lo, hi, hdiag, eps))
    # on the bound and pushed out: held however stiff; near it, stiff: free (its Newton
    # step 7e-7 stops short of the 6e-4 gap); near it, soft or non-convex: held; pulled
    # inwards: free; far from a bound: free; the same at the upper bound
    assert held.tolist() == [True, False, True, True, False, False, False]
    assert bool(held_bounds(z, g, lo, hi, jnp.ones(7), eps)[6])


@pytest.mark.slow
def test_inner_tolerance_schedules_reach_the_same_optimum(robot, single):
    """The schedule changes the path, not the answer: the geometric one converges to the
    default's verified optimum (cost within 1e-5 relative)."""
    problem, sol = single
    other = jtraj.solve(problem, options=SolverOptions(inner_tol_ratio=0.0))
    assert sol.converged and other.converged
    assert float(other.cost) == pytest.approx(float(sol.cost), rel=1e-5)
    np.testing.assert_allclose(np.asarray(other.q), np.asarray(sol.q), atol=1e-3)


def test_compacted_batch_equals_single_solves(robot, batch):
    """Lanes refilled as problems finish, the last ones on fewer lanes: every problem must
    take the iterations of its single solve and reach the same point (the options and the
    lanes' programs are those of ``single`` and ``batch``: no compilation of its own)."""
    q0, q1, lanes = batch
    for i in range(3):
        one = jtraj.solve(jtraj.Problem(robot, q0[i], q1[i], N=N, weights=W))
        assert int(lanes.status[i]) == int(one.status)
        assert int(lanes.iterations[i]) == int(one.iterations)
        np.testing.assert_allclose(np.asarray(lanes.h[i]), np.asarray(one.h), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(float(lanes.cost[i]), float(one.cost), rtol=1e-9)
    with pytest.raises(ValueError, match="slots"):
        jtraj.solve_batch(robot, q0, q1, N=N, slots=0)


# slots=None: a program of its own (a minute or more of compilation on a slow 2-core
# machine); slots=2 runs the interior-point pool's program that ``batch`` ends on (2 lanes),
# here with a queue: three problems through two lanes, a lane refilled inside the loop
@pytest.mark.parametrize("slots", [pytest.param(None, marks=pytest.mark.slow), 2])
def test_one_shot_and_two_lane_batches_equal_the_compacted_batch(robot, batch, slots):
    """All problems solved at once (slots=None), or through 2 lanes throughout: every
    problem must take the same iterations and reach the same point as in the default
    compacted batch (4 lanes stepping down to 2 for its three valid problems)."""
    q0, q1, sol = batch
    other = jtraj.solve_batch(robot, q0, q1, N=N, weights=W, slots=slots, segment=7)
    np.testing.assert_array_equal(np.asarray(other.status), np.asarray(sol.status))
    np.testing.assert_array_equal(np.asarray(other.iterations), np.asarray(sol.iterations))
    # same iterations; XLA may round differently at another batch width (seen: 5e-12)
    np.testing.assert_allclose(np.asarray(other.h), np.asarray(sol.h), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(other.cost), np.asarray(sol.cost), rtol=1e-9)


def test_kkt_error_tells_an_optimum_from_a_feasible_point(single_al, single, via):
    """The end-of-run certificate (:func:`jtraj.solver.certify.kkt_error`, least-squares
    multipliers of the original problem): small at the optimum, large at a trajectory that
    meets the same constraints but optimises under one more (the via point of ``via``,
    whose own certificate is small). The AL loop's Solution reports that measure; the
    interior-point method's (``single``) the KKT error with its own multipliers."""
    import equinox as eqx

    from jtraj._testing import NLP, SolverOptions, kkt_error
    from jtraj.transcription import Transcription

    problem, sol = single_al
    tr = Transcription("decoupled")
    nlp = NLP(problem=problem, tr=tr, layout=tr.layout(problem), sd=tr.stage_data(problem))
    kkt = eqx.filter_jit(kkt_error)

    def z_of(s):
        return nlp.layout.pack(tr.controls_of(s), s.h)

    tol = SolverOptions().tol_optimality
    assert float(kkt(nlp, z_of(sol))) <= tol
    ip = single[1]
    # (with the least-squares certificate the interior-point optimum, stopped at a
    # barrier parameter near 2e-6, is above tol: see test_warm_start_from_solution_is_immediate)
    assert float(ip.kkt_error) <= tol
    # the Solution reports the same measure at the trajectory it returns
    assert float(sol.kkt_error) == pytest.approx(float(kkt(nlp, z_of(sol))), rel=1e-6, abs=1e-12)
    other = via[1]
    assert other.converged and float(other.max_violation["overall"]) <= 1e-6
    assert float(jnp.max(jnp.abs(other.v - sol.v))) > 0.05  # another trajectory (measured 2.9)
    assert float(kkt(nlp, z_of(other))) > 10 * tol  # measured 0.14
    # the via-point problem's own optimum: certified (by the AL's stationarity, which
    # allows a KKT error near the tolerance: measured 2.5e-4 and 3.0e-4 as rounding moved)
    assert float(other.kkt_error) <= 2 * tol


def test_least_squares_multipliers_match_numpy_lstsq(single_al):
    """The certificate's multipliers (solved in the variables' space by the push-through
    identity) are the ridge-regularised least-squares solution of grad f + J_A^T lam = 0
    over the free variables, solved in the rows' space by NumPy (to 1e-8), and within the
    ridge's bias (1e-4) the minimum-norm one of NumPy's SVD-based lstsq (inequality
    multipliers clipped at 0)."""
    import equinox as eqx

    from jtraj._testing import NLP, ls_multipliers
    from jtraj.transcription import Transcription

    problem, sol = single_al
    tr = Transcription("decoupled")
    nlp = NLP(problem=problem, tr=tr, layout=tr.layout(problem), sd=tr.stage_data(problem))
    z = nlp.layout.pack(tr.controls_of(sol), sol.h)
    lam, J, gf, n_eq = (np.asarray(x) for x in eqx.filter_jit(ls_multipliers)(nlp, z))
    lo, hi, zz = (np.asarray(x) for x in (nlp.layout.z_lo, nlp.layout.z_hi, z))
    free = ~((zz <= lo + 1e-12) | (zz >= hi - 1e-12))
    Jf = np.where(free[None, :], J, 0.0)
    eps = 1e-10 * (1.0 + np.max(np.sum(Jf**2, axis=1)))  # the solver's ridge
    ridge = np.linalg.solve(Jf @ Jf.T + eps * np.eye(len(J)), -Jf @ np.where(free, gf, 0.0))
    svd = np.linalg.lstsq(J[:, free].T, -gf[free], rcond=None)[0]
    for ref, rtol in ((ridge, 1e-8), (svd, 1e-4)):
        ref[n_eq:] = np.clip(ref[n_eq:], 0.0, None)
        assert np.count_nonzero(np.abs(ref) > 1e-3) >= 6  # the goal rows at least
        np.testing.assert_allclose(lam, ref, rtol=rtol, atol=rtol * 1e-3 * np.max(np.abs(ref)))


def test_restart_resumes_a_run_cut_short(single):
    """A run that ends uncertified is restarted once (solver.restart_state): with the first
    run cut to 12 iterations, the restart must still reach the default solve's optimum."""
    problem, sol = single
    again = jtraj.solve(problem, options=RESTART)
    assert again.converged, again.status_message
    assert int(again.iterations) > 12  # 12 in the first run, the rest after the restart
    assert float(again.cost) == pytest.approx(float(sol.cost), rel=1e-4)
    with pytest.raises(ValueError, match="restart_iter"):
        SolverOptions(restart_iter=-1)


def test_options_differing_in_numbers_share_one_compilation(single_al):
    """Numeric options are traced (solver.TRACED_OPTIONS): solves with other limits,
    tolerances and penalties reuse the compiled solver of ``single_al``, and act."""
    problem, sol = single_al
    compiles = []

    def timed(event, secs, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(event)

    def counted(event, **kwargs):  # a compilation served by the run's persistent cache too
        if event == "/jax/compilation_cache/compile_requests_use_cache":
            compiles.append(event)

    jax.monitoring.register_event_duration_secs_listener(timed)
    jax.monitoring.register_event_listener(counted)
    try:
        cut = jtraj.solve(problem, options=SolverOptions(max_iter=5, restart_iter=1, method="al"))
        tight = jtraj.solve(problem, options=SolverOptions(tol_optimality=3e-5, penalty_init=20.0, method="al"))
        # the exits that 0 switches off: no restart, no stall test (both traced too)
        plain = jtraj.solve(problem, options=SolverOptions(restart_iter=0, stall_window=0, max_iter=5, method="al"))
    finally:
        jax.monitoring.unregister_event_duration_listener(timed)
        jax.monitoring.unregister_event_listener(counted)
    assert compiles == []
    assert 5 <= int(cut.iterations) <= 6 and not bool(cut.converged)  # 5, then at most 1 after a restart
    assert int(plain.iterations) == 5 and int(plain.status) == Status.MAX_ITERATIONS
    assert bool(tight.converged) and int(tight.iterations) > int(sol.iterations)  # a tighter tolerance
    assert float(tight.cost) == pytest.approx(float(sol.cost), rel=1e-4)
    # structure (a switch at 0) does compile another program
    assert S.split_options(SolverOptions(kink_margin=0.0)).static != S.split_options(SolverOptions()).static


@pytest.mark.slow
def test_compacted_batch_restarts_like_single_solves(robot, batch):
    """The compacted batch restarts a run that ends uncertified on its lane (the lane
    driver's restart program) and runs it on: every problem must take exactly the
    iterations of its single solve (RESTART's numbers are traced: the programs of
    ``single`` and ``batch`` serve, plus the restart program of the batch's lanes)."""
    q0, q1, _ = batch
    lanes = jtraj.solve_batch(robot, q0, q1, N=N, weights=W, options=RESTART)
    for i in range(3):
        one = jtraj.solve(jtraj.Problem(robot, q0[i], q1[i], N=N, weights=W), options=RESTART)
        assert int(lanes.status[i]) == int(one.status)
        assert int(lanes.iterations[i]) == int(one.iterations) > 12
        np.testing.assert_allclose(float(lanes.cost[i]), float(one.cost), rtol=1e-9)
    assert int(lanes.status[3]) == Status.INVALID_INPUT


def test_kink_curvature_adds_the_penalty_curvature_of_nearly_active_rows_only():
    """solver.kink_curvature: zero value and gradient, Hessian ``mu a_i a_i^T`` summed
    over the rows with ``-mu margin < rho_i + mu g_i <= 0`` (closed form for linear g)."""
    from jtraj._testing import kink_curvature

    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 4))
    w0 = rng.normal(size=4)
    mu, margin = 50.0, 1e-3
    rho = np.array([0.0, 0.0, 0.0, 0.3, 0.0])
    # rows: just short of the kink, far from it, active, active through rho, exactly on it
    g0 = np.array([-0.5 * margin, -10 * margin, 1e-4, -1e-3, 0.0])
    b = g0 - A @ w0

    def term(w):
        return kink_curvature(A @ w + b, rho, mu, margin)

    assert float(term(w0)) == 0.0
    np.testing.assert_array_equal(np.asarray(jax.grad(term)(w0)), 0.0)
    near = np.array([True, False, False, False, True])
    expected = mu * A[near].T @ A[near]
    np.testing.assert_allclose(np.asarray(jax.hessian(term)(w0)), expected, rtol=1e-12, atol=1e-12)
    # margin 0: no row (the exact PHR Hessian alone)
    np.testing.assert_array_equal(np.asarray(jax.hessian(lambda w: kink_curvature(A @ w + b, rho, mu, 0.0))(w0)), 0.0)
    with pytest.raises(ValueError, match="kink_margin"):
        SolverOptions(kink_margin=-1.0)
    with pytest.raises(ValueError, match="kink_after"):
        SolverOptions(kink_after=-1)


@pytest.mark.slow
def test_stalled_subproblem_pair_reaches_ipopts_cost():
    """Benchmark pair 15 of seed 23 (N = 20): without the kink curvature
    (``kink_margin=0``) its subproblems stall on a torque bound crossed at its PHR kink and
    it is certified more than 0.3 % above IPOPT's cost; with the defaults it must be
    within 0.2 % of it."""
    P = pytest.importorskip("jtraj_peers.ipopt_peer")
    V = pytest.importorskip("jtraj_peers.verify")
    q0, q1 = P.benchmark_pairs(256, 23)
    ref = P.solve_pair(q0[15], q1[15], N=20)
    assert ref["success"]
    problem = jtraj.Problem(jtraj.robots.get("serial3"), q0[15], q1[15], N=20, weights=W)
    # the AL loop from Khoukhi's cycloid (the interior-point method has no kink)
    sol = jtraj.solve(problem, options=SolverOptions(method="al", guess="cycloidal"))
    plain = jtraj.solve(problem, options=SolverOptions(method="al", guess="cycloidal", kink_margin=0.0))
    assert sol.converged and plain.converged
    assert V.verify(q0[15], q1[15], np.asarray(sol.v), np.asarray(sol.h), tol=1e-6)["ok"]
    assert float(sol.cost) <= ref["cost"] * 1.002
    assert float(plain.cost) > ref["cost"] * 1.003  # the failure this guards against


@pytest.mark.slow
def test_chord_polish_reaches_the_gauss_newton_polish(single):
    """The finish's feasibility polish takes chord steps (the constraints' Jacobian at its
    starting point only); the restart's recomputes it at every step (Gauss-Newton). From
    the converged optimum perturbed by 1e-5 (a violation like the AL's at its end) both
    must remove the violation to below 1e-12 and land on the same point (1e-9 in the
    scaled unknowns), each without leaving the simple bounds."""
    from jtraj.transcription import Transcription
    import equinox as eqx

    problem, sol = single
    assert sol.converged, sol.status_message
    opts = SolverOptions()
    nlp, _, _ = S.prepare(problem, opts, Transcription("decoupled"), (sol.v, sol.h))
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    z_opt = nlp.layout.pack(sol.v, sol.h)
    noise = 1e-5 * np.random.default_rng(0).standard_normal(z_opt.shape)
    z = jnp.clip(z_opt + noise, lo, hi)
    violation = eqx.filter_jit(lambda n, zz: S.violation(*n.constraints(zz)))
    assert float(violation(nlp, z)) > 1e-6  # the polish has work to do
    polish = eqx.filter_jit(lambda n, zz, chord: S.polish(n, zz, chord=chord))
    z_chord, z_gn = polish(nlp, z, True), polish(nlp, z, False)
    for zz in (z_chord, z_gn):
        assert float(violation(nlp, zz)) <= 1e-12
        assert bool(jnp.all((zz >= lo) & (zz <= hi)))
    np.testing.assert_allclose(np.asarray(z_chord), np.asarray(z_gn), atol=1e-9)


@pytest.mark.slow
def test_polish_releases_rows_when_holding_them_leaves_a_violation():
    """Benchmark pair 16 of seed 21 (N = 20) with ``kink_margin=1e-4, kink_after=0``: the
    loop certifies a point 6e-6 off the goal, and the holding polish cannot remove it (its
    Gauss-Newton correction crosses a torque bound outside its active window, so no step
    is kept). The releasing polish over all rows must, and the result converge."""
    from jtraj.transcription import Transcription
    import equinox as eqx

    P = pytest.importorskip("jtraj_peers.ipopt_peer")
    V = pytest.importorskip("jtraj_peers.verify")
    q0, q1 = P.benchmark_pairs(256, 21)
    opts = SolverOptions(kink_margin=1e-4, kink_after=0)
    problem = jtraj.Problem(jtraj.robots.get("serial3"), q0[16], q1[16], N=20, weights=W)
    sol = jtraj.solve(problem, options=opts)
    assert sol.converged, sol.status_message
    assert V.verify(q0[16], q1[16], np.asarray(sol.v), np.asarray(sol.h), tol=1e-6)["ok"]
    # the precondition: the holding polish alone leaves the loop's point unverified
    tr = Transcription("decoupled")
    init = eqx.filter_jit(lambda p: S.initial_guess(p, opts, tr))(problem)
    nlp, state, _ = eqx.filter_jit(lambda p, i: S.prepare(p, opts, tr, i))(problem, init)
    state = eqx.filter_jit(lambda n, s: S.run_with_restart(n, s, opts))(nlp, state)
    held = eqx.filter_jit(lambda n, z: S.violation(*n.constraints(S.polish(n, z))))(nlp, state.z)
    assert float(held) > opts.verify_tol


def _identical(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_solver_objects_solve_as_the_options_they_replace(single, single_al):
    """``jtraj.Auto()`` and ``jtraj.AugmentedLagrangian()`` map onto the default options and
    ``method="al"``: the same compiled programs, bit-identical solutions
    (tests/test_solver_objects.py checks the map itself)."""
    problem, sol = single
    _identical(jtraj.solve(problem, solver=jtraj.Auto()), sol)
    problem, sol = single_al
    _identical(jtraj.solve(problem, solver=jtraj.AugmentedLagrangian()), sol)


def test_batched_problem_equals_the_array_form(robot, batch):
    """``solve_batch(Problem(robot, (B, n), (B, n)))`` is the array form's solve; a sample
    infeasible on its face is accepted by the batch's Problem and flagged by the solve.
    The batch fixture's shapes (its non-finite goal made finite), so its programs."""
    q0, q1, _ = batch
    q1 = q1.copy()
    q1[3] = q0[3] + 0.05
    problem = jtraj.Problem(robot, q0, q1, N=N, weights=W)
    assert problem.batch_size == 5 and problem.qd_goal.shape == (5, 3) and problem.T_max.shape == (5,)
    a = jtraj.solve_batch(problem)
    _identical(a, jtraj.solve_batch(robot, q0, q1, N=N, weights=W))
    assert int(a.status[4]) == Status.INVALID_INPUT and bool(a.converged[3])


@pytest.mark.slow  # a batch of 12 on 4 lanes compiles its own preparation and finish programs
def test_batch_progress_is_reported_as_problems_finish_without_changing_the_results(robot, batch):
    """``solve_batch(progress=...)``: the interior-point pool returns to the host in rounds
    (here 12 problems on 4 lanes, rounds of 4) and goes on; the results are the same bits."""
    rng = np.random.default_rng(5)
    q0 = rng.uniform(-1.2, 1.2, (12, 3))
    q1 = q0 + rng.uniform(-0.25, 0.25, (12, 3))
    calls = []
    a = jtraj.solve_batch(robot, q0, q1, N=N, weights=W, slots=4, progress=lambda k, B: calls.append((k, B)))
    _identical(a, jtraj.solve_batch(robot, q0, q1, N=N, weights=W, slots=4))
    counts = [k for k, B in calls]
    assert all(B == 12 for _, B in calls) and counts == sorted(counts) and counts[-1] == 12
    assert len(set(counts) - {0, 12}) >= 2, calls  # reported inside the batch
    with pytest.raises(ValueError, match="progress"):
        jtraj.solve_batch(robot, q0, q1, N=N, weights=W, progress="yes")
