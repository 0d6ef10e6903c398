"""The solvers as objects (``jtraj.Auto``, ``jtraj.IPM``, ``jtraj.AugmentedLagrangian``) and
``solve_batch``'s batched :class:`jtraj.Problem`.

* an object and the deprecated ``SolverOptions`` it maps onto are the same options: the
  same static structure, the same traced values;
* the traced/static split comes from the fields' marking, and it is the split the
  programs were built with;
* bad batched shapes raise naming the argument.

Nothing here compiles the solver: the solves with the objects and the batched Problem are
in test_solver.py, on its fixtures' programs.
"""

import dataclasses

import jax
import numpy as np
import pytest

import jtraj
from jtraj import _testing as S
from jtraj.solver import (IPM, AugmentedLagrangian, Auto, Curvature, InequalityPenalty, Schedule, SolverOptions,
                          as_solver, from_options)
from jtraj.solver.options import to_options

N = 10
W = jtraj.Weights(time=1.0, energy=0.1)
Q0 = np.array([1.077, -0.096, 0.619])
Q1 = np.array([1.2, -0.049, 0.9])

#: the traced options the compiled programs were built with (the flat set's names)
TRACED = {"max_iter", "max_inner", "tol_feasibility", "tol_optimality", "inner_tol_ratio", "pbm_inner_tol_ratio",
          "penalty_init", "penalty_growth", "penalty_max", "feasibility_ratio", "damping_init", "verify_tol",
          "detect_infeasible", "restart_iter", "restart_penalty_max", "kink_margin", "kink_after", "stall_window",
          "stall_ratio", "stall_min_viol", "stall_after", "pbm_fallback_iter", "detect_min_viol", "ip_dual_tol",
          "ip_compl_tol", "ip_project_tol", "ip_damping", "ip_mu_init", "ip_bound_push", "ip_first_shift"}
SWITCHES = {"inner_tol_ratio", "pbm_inner_tol_ratio", "kink_margin", "pbm_fallback_iter"}


@pytest.fixture(scope="module")
def robot():
    return jtraj.robots.get("serial3")


@pytest.fixture(scope="module")
def problem(robot):
    return jtraj.Problem(robot, Q0, Q1, N=N, weights=W)


# ----- the options' marking and the map onto SolverOptions ---------------------------------
def test_traced_options_are_the_fields_marked_traced():
    assert set(S.TRACED_OPTIONS) == TRACED
    # the traced fields are the objects' pytree leaves, the static ones their structure
    al_leaves = {f.name for f in dataclasses.fields(AugmentedLagrangian) if not f.metadata.get("static")}
    ip_leaves = {"ip_" + f.name for f in dataclasses.fields(IPM) if not f.metadata.get("static")} - {"ip_fallback"}
    assert al_leaves | ip_leaves == TRACED
    assert len(jax.tree.leaves(Auto())) == len(TRACED)
    split = S.split_options(SolverOptions(kink_margin=0.0, stall_window=10))
    assert {k for k, v in split.static.__dict__.items() if k in TRACED} == TRACED
    assert split.static.kink_margin == 0.0 and split.static.inner_tol_ratio == 1.0  # the switches: 0 or 1
    assert {k for k in TRACED if getattr(split.static, k) != getattr(SolverOptions(), k)} == SWITCHES


def test_objects_map_onto_the_options():
    assert to_options(Auto()) == SolverOptions()
    assert to_options(AugmentedLagrangian()) == SolverOptions(method="al")
    assert to_options(IPM(tol=1e-8, curvature="exact", fallback=AugmentedLagrangian(max_iter=80))) == SolverOptions(
        method="ip", ip_tol=1e-8, ip_curvature="exact", max_iter=80)
    assert to_options(AugmentedLagrangian.pbm()) == SolverOptions.pbm(method="al")
    for opts in (SolverOptions(), SolverOptions(method="al", schedule="thesis", penalty_init=3.0),
                 SolverOptions.pbm(), SolverOptions(method="ip", ip_max_iter=40, ip_dual_tol=1e-3, verify_tol=1e-7)):
        assert to_options(from_options(opts)) == opts
    assert type(from_options(SolverOptions(method="ip"))) is IPM
    # what the functions that still take options= accept
    assert as_solver(None) is None and as_solver(Auto()) == Auto()
    assert as_solver(SolverOptions(method="al", max_iter=80)) == AugmentedLagrangian(max_iter=80)
    with pytest.raises(ValueError, match="options"):
        as_solver({"method": "al"})
    # concrete 0-d arrays are numbers; traced ones are refused
    assert to_options(IPM(dual_tol=np.float64(1e-3), fallback=AugmentedLagrangian(max_iter=np.asarray(80)))) \
        == SolverOptions(method="ip", ip_dual_tol=1e-3, max_iter=80)
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda t: to_options(Auto(IPM(damping=t))).ip_damping)(0.01)
    # enumerations or their strings: the same plain strings reach the programs
    a = AugmentedLagrangian(schedule=Schedule.THESIS, inequality_penalty=InequalityPenalty.PBM)
    assert a == AugmentedLagrangian(schedule="thesis", inequality_penalty="pbm")
    assert type(a.schedule) is str and type(IPM(curvature=Curvature.GAUSS_NEWTON).curvature) is str


def test_numbers_share_a_program_structure_does_not():
    base = S.split_options(to_options(IPM()))
    assert S.split_options(to_options(IPM(dual_tol=1e-3, fallback=AugmentedLagrangian(tol_optimality=1e-4)))).static \
        == base.static
    # the start's barrier parameter, bound push and first shift are numbers too (a warm
    # start's settings reuse the cold start's program); the iteration cap shapes the program
    assert S.split_options(to_options(IPM(mu_init=1e-3, bound_push=1e-6, first_shift=1e-2))).static == base.static
    assert S.split_options(to_options(IPM(max_iter=80))).static != base.static


def test_bad_solver_options_raise_naming_the_field(problem):
    with pytest.raises(ValueError, match=r"IPM\.tol"):
        IPM(tol=-1.0)
    with pytest.raises(ValueError, match=r"IPM\.damping"):
        IPM(damping=float("nan"))
    for push in (0.0, 0.5, float("inf")):
        with pytest.raises(ValueError, match=r"IPM\.bound_push"):
            IPM(bound_push=push)
    for shift in (0.0, 1e-7, 1e9, float("nan")):
        with pytest.raises(ValueError, match=r"IPM\.first_shift"):
            IPM(first_shift=shift)
    with pytest.raises(ValueError, match="schedule"):
        AugmentedLagrangian(schedule="fast")
    with pytest.raises(ValueError, match=r"AugmentedLagrangian\.penalty_growth"):
        AugmentedLagrangian(penalty_growth=0.5)
    with pytest.raises(ValueError, match="fallback"):
        IPM(fallback=SolverOptions())
    with pytest.raises(ValueError, match="solver"):
        jtraj.solve(problem, solver=SolverOptions())
    with pytest.raises(ValueError, match="not both"):
        jtraj.solve(problem, solver=Auto(), options=SolverOptions())


# ----- the deprecation ---------------------------------------------------------------------
def test_deprecated_options_warn_and_name_the_replacement(problem):
    # (the warning comes before the solve: a bad init then stops it before any compilation;
    # test_solver.py solves with the objects and compares with the options)
    with pytest.warns(DeprecationWarning, match=r"solver=jtraj\.Auto\(\), jtraj\.IPM"):
        with pytest.raises(ValueError, match="init"):
            jtraj.solve(problem, options=SolverOptions(), init=(np.zeros((N, 2)), np.ones(N)))
    with pytest.warns(DeprecationWarning, match="from_options"):
        with pytest.raises(ValueError, match="init"):
            jtraj.solve_batch(problem.robot, Q0[None], Q1[None], N=N, options=SolverOptions(method="al"),
                              init=(np.zeros((1, N, 2)), np.ones((1, N))))


def test_sensitivity_and_the_planner_take_solver_and_deprecate_options(problem):
    # the argument is read first: a bad argument after it stops before any solve
    from jtraj.online import Planner

    with pytest.warns(DeprecationWarning, match="solver="):
        with pytest.raises(ValueError, match="unknown parameter"):
            jtraj.sensitivity(problem, "no_such_parameter", options=SolverOptions())
    with pytest.raises(ValueError, match="not both"):
        jtraj.sensitivity(problem, solver=Auto(), options=SolverOptions())
    with pytest.raises(ValueError, match="solver must be"):
        jtraj.sensitivity(problem, solver=SolverOptions())
    planner = object.__new__(Planner)  # (query reads its solver before the planner's state)
    with pytest.warns(DeprecationWarning, match="solver="):
        with pytest.raises(ValueError, match="warm"):
            planner.query(Q0, Q1, options=SolverOptions(method="al"), warm="cold")
    with pytest.raises(ValueError, match="solver must be"):
        planner.query(Q0, Q1, solver="ipm")


# ----- the shared options and the flat overrides ---------------------------------------------
def test_shared_options_forward_to_the_fallback():
    tight = AugmentedLagrangian(tol_optimality=1e-6, verify_tol=1e-8, guess="trapezoidal")
    assert Auto(tol_optimality=1e-6, verify_tol=1e-8, guess="trapezoidal") == Auto(ipm=IPM(fallback=tight))
    assert IPM(max_iter=80, tol_optimality=1e-6, verify_tol=1e-8, guess="trapezoidal") == IPM(max_iter=80,
                                                                                              fallback=tight)
    # onto a given fallback, whose other fields stay
    pbm = AugmentedLagrangian.pbm()
    assert Auto(ipm=IPM(fallback=pbm), tol_feasibility=1e-7).ipm.fallback == dataclasses.replace(
        pbm, tol_feasibility=1e-7)
    # the traced values reach the programs' options (IPM's tolerances are capped by them)
    assert to_options(Auto(tol_optimality=1e-6)).tol_optimality == 1e-6
    with pytest.raises(TypeError, match="max_iter"):  # not shared: IPM's and the fallback's differ
        Auto(max_iter=10)
    with pytest.raises(ValueError, match=r"AugmentedLagrangian\.tol_optimality"):
        Auto(tol_optimality=-1.0)


def test_overrides_round_trip():
    from jtraj.solver.options import from_overrides, overrides

    for solver in (Auto(), IPM(mu_init=0.01, tol_optimality=1e-5), AugmentedLagrangian.pbm(max_iter=300),
                   Auto(ipm=IPM(curvature="exact"))):
        flat = overrides(solver)
        assert from_overrides(flat) == solver
        assert flat["method"] == {Auto: "auto", IPM: "ip", AugmentedLagrangian: "al"}[type(solver)]
    assert overrides(AugmentedLagrangian(max_iter=300)) == {"max_iter": 300, "method": "al"}
    with pytest.raises(ValueError, match="unknown solver option 'ip_tolerance'"):
        from_overrides({"ip_tolerance": 1.0})


def test_dataset_spec_takes_a_solver_object():
    from jtraj import dataset

    def identity(**kw):
        return dataset.make_spec("serial3", 10, 0, **kw).identity()["solver_options"]

    by_dict = identity(options={"method": "ip", "tol_optimality": 1e-5, "max_iter": 300})
    assert identity(solver=IPM(tol_optimality=1e-5, fallback=AugmentedLagrangian(max_iter=300))) == by_dict
    assert identity(options=IPM(tol_optimality=1e-5, fallback=AugmentedLagrangian(max_iter=300))) == by_dict
    assert by_dict != identity(options={"method": "ip"})
    with pytest.raises(ValueError, match="not both"):
        dataset.make_spec("serial3", 10, 0, solver=IPM(), options={"max_iter": 3})
    with pytest.raises(ValueError, match="options"):
        dataset.make_spec("serial3", 10, 0, options={"tol_optimality": 0.0})


def test_cli_solver_and_option_arguments():
    import argparse

    from jtraj.commands import dataset, query, solve, solver_from_args

    def parsed(module, *argv):
        parser = argparse.ArgumentParser()
        module.configure(parser)
        extra = ("--model", "m", "--start", "0", "--goal", "0") if module is query else ()
        return parser.parse_args([*extra, *argv])

    for module in (solve, query, dataset):
        args = parsed(module, "--solver", "ipm", "--option", "tol_optimality=1e-8", "--option", "ip_max_iter=300")
        assert solver_from_args(args) == IPM(max_iter=300, tol_optimality=1e-8)
    # the old spellings
    assert solver_from_args(parsed(solve, "--method", "al", "--inequalities", "pbm")) == AugmentedLagrangian.pbm()
    assert solver_from_args(parsed(dataset, "--max-iter", "40")) == Auto(ipm=IPM(fallback=AugmentedLagrangian(
        max_iter=40)))
    assert solver_from_args(parsed(solve, "--option", "detect_infeasible=off", "--option", "guess=cycloidal")) \
        == Auto(ipm=IPM(fallback=AugmentedLagrangian(detect_infeasible=False, guess="cycloidal")))
    for argv, message in ((("--option", "tol=1"), "--option tol: unknown"),
                          (("--option", "max_iter=2.5"), "must be an integer"),
                          (("--option", "max_iter"), "NAME=VALUE"),
                          (("--option", "verify_tol=-1"), "--option: verify_tol"),
                          (("--solver", "ipm", "--method", "al"), "disagree"),
                          (("--solver", "newton"), "--solver must be")):
        with pytest.raises(ValueError, match=message):
            solver_from_args(parsed(solve, *argv))


# ----- batched Problem (its solve: test_solver.py) -----------------------------------------
@pytest.fixture(scope="module")
def pairs():
    q0 = np.stack([Q0, Q0 + 0.02])
    q1 = np.stack([Q1, Q1 - 0.03])
    return q0, q1


def test_bad_batched_shapes_raise_naming_the_argument(robot, pairs, problem):
    q0, q1 = pairs
    with pytest.raises(ValueError, match="q_goal"):
        jtraj.Problem(robot, q0, q1[:1], N=N)
    with pytest.raises(ValueError, match="q_goal"):
        jtraj.Problem(robot, q0, Q1, N=N)
    with pytest.raises(ValueError, match="q_start"):
        jtraj.Problem(robot, q0[None], q1[None], N=N)
    with pytest.raises(ValueError, match="q_start"):
        jtraj.Problem(robot, q0[:, :2], q1, N=N)
    with pytest.raises(ValueError, match="qd_start"):
        jtraj.Problem(robot, q0, q1, N=N, qd_start=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="qd_goal"):
        jtraj.Problem(robot, q0, q1, N=N, qd_goal=np.full((2, 3), np.nan))
    with pytest.raises(ValueError, match="T_max"):
        jtraj.Problem(robot, q0, q1, N=N, T_max=np.ones(3))
    with pytest.raises(ValueError, match="T_max"):
        jtraj.Problem(robot, q0, q1, N=N, T_max=np.array([1.0, -1.0]))
    batch = jtraj.Problem(robot, q0, q1, N=N)
    with pytest.raises(ValueError, match="solve_batch"):
        jtraj.solve(batch)
    with pytest.raises(ValueError, match="N is the problem's own"):
        jtraj.solve_batch(batch, N=N)
    with pytest.raises(ValueError, match="q_start is the problem's own"):
        jtraj.solve_batch(batch, q0, q1)
    with pytest.raises(ValueError, match="batch"):
        jtraj.solve_batch(problem)
    with pytest.raises(ValueError, match="problem"):
        jtraj.solve_batch("serial3", q0, q1)
