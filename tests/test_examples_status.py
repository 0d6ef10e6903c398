"""The examples' status record (examples/run_all.py) and the trajectory figure's legends
and units (jtraj.plotting): no solve, a trajectory from the recursion."""

from __future__ import annotations

import json
import sys
import tempfile
import types
import typing
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj import robots

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import run_all  # noqa: E402


def _fake_solution(status, violation):
    return types.SimpleNamespace(status=np.int32(status), max_violation={"overall": np.float64(violation)})


def test_status_record_and_table(tmp_path, monkeypatch):
    monkeypatch.setattr(run_all, "STATUS", tmp_path)
    runs = [run_all.status_record("a", _fake_solution(jtraj.Status.CONVERGED, 1e-12)),
            run_all.status_record("b", _fake_solution(jtraj.Status.FEASIBLE_NOT_OPTIMAL, 3e-7)),
            run_all.status_record("c", _fake_solution(jtraj.Status.CONVERGED, 2e-9))]
    runs[0]["effort_between_samples"], runs[2]["effort_between_samples"] = 1.83, 1.002
    path = run_all.write_status("demo", runs, t_start=0.0)
    rec = json.loads(path.read_text())
    assert rec["experiment"] == "demo" and [r["run"] for r in rec["runs"]] == ["a", "b", "c"]
    assert rec["runs"][1]["status"] == "FEASIBLE_NOT_OPTIMAL" and rec["runs"][1]["effort_between_samples"] is None
    statuses, worst, effort = run_all.status_row("demo")
    assert statuses == "2 CONVERGED, 1 FEASIBLE_NOT_OPTIMAL"
    assert worst == "3.0e-07 (b)" and effort == "1.830 (a)"
    # an infeasible run's effort between samples measures its violation: the column reads the
    # feasible runs, and names an infeasible one only when no run is feasible
    bad = run_all.status_record("d", _fake_solution(jtraj.Status.LIKELY_INFEASIBLE, 0.4))
    bad["effort_between_samples"] = 1.4
    run_all.write_status("demo2", runs + [bad], t_start=0.0)
    assert run_all.status_row("demo2")[2] == "1.830 (a)"
    run_all.write_status("demo3", [bad], t_start=0.0)
    assert run_all.status_row("demo3")[2] == "1.400 (d, not feasible)"
    # a script without a record
    assert run_all.status_row("other") == ("no status reported", "-", "-")
    text = run_all.status_table(["demo", "other"], {"other": (12.0, "exit 0")})
    lines = text.splitlines()
    assert lines[2].startswith("| demo |") and "not run by this call" in lines[2]
    assert lines[3].startswith("| other | 12 | exit 0 | no status reported |")


def test_batch_records_and_note(tmp_path, monkeypatch):
    """One entry per kept trajectory of a batch, numbered within its group; the effort
    between samples of each trajectory equals that of the trajectory solved alone; a record
    without runs shows its note."""
    monkeypatch.setattr(run_all, "STATUS", tmp_path)
    robot = robots.get("serial3")
    problem = jtraj.Problem(robot, jnp.zeros(3), jnp.asarray([0.02, -0.01, 0.03]), N=4)
    v = jnp.asarray([[1.0, -0.5, 1.5], [0.5, 0.0, 0.5], [-0.5, 0.0, -0.5], [-1.0, 0.5, -1.5]])
    trajs = [_recursion_solution(problem, scale * v, jnp.full(4, 0.2)) for scale in (0.5, 2.0, 8.0)]
    batch = _Trajectory({k: jnp.stack([t[k] for t in trajs]) for k in trajs[0]})
    batch.update(status=np.array([0, 2, 6], np.int32), max_violation={"overall": np.array([1e-9, 2e-7, 0.3])})
    recs = run_all.batch_status_records("pair", batch, robot, rows=range(1, 3))
    assert [r["run"] for r in recs] == ["pair 1", "pair 2"]
    assert [r["status"] for r in recs] == [jtraj.Status(2).name, jtraj.Status(6).name]
    assert [r["max_violation"] for r in recs] == [2e-7, 0.3]
    from jtraj.resample import intersample_effort

    for r, t in zip(recs, trajs[1:]):
        assert r["effort_between_samples"] == pytest.approx(float(intersample_effort(t, robot)), rel=1e-12)
    assert recs[0]["effort_between_samples"] < recs[1]["effort_between_samples"]  # 16x the accelerations
    assert run_all.batch_status_records("x", batch)[2]["effort_between_samples"] is None  # no robot
    run_all.write_status("anfis", [], note="no trajectory solve")
    assert run_all.status_row("anfis") == ("no trajectory solve", "-", "-")


def test_committed_status_records_are_well_formed():
    """Each committed record names an experiment run_all lists and holds solver runs with a
    known status and a finite violation, or a note."""
    paths = sorted(run_all.STATUS.glob("*.json"))
    assert paths
    for path in paths:
        rec = json.loads(path.read_text())
        assert rec["experiment"] == path.stem and path.stem in run_all.EXPERIMENTS, path
        assert rec["runs"] or rec.get("note"), path
        for r in rec["runs"]:
            assert r["status"] in jtraj.Status.__members__, (path, r)
            assert np.isfinite(r["max_violation"]) and r["max_violation"] >= 0, (path, r)
            e = r["effort_between_samples"]
            assert e is None or (np.isfinite(e) and e > 0), (path, r)


class _Trajectory(dict):
    """A trajectory as a mapping (what jtraj.resample takes) with attribute access (what
    jtraj.plotting reads)."""

    __getattr__ = dict.__getitem__


def _recursion_solution(problem, v, h):
    q, qd = jtraj.transcription.integrate(problem.q_start, problem.qd_start, v, h)
    tau = jax.vmap(problem.robot.inverse_dynamics)(q[:-1], qd[:-1], v)
    return _Trajectory(q=q, qd=qd, v=v, tau=tau, h=h)


@pytest.mark.slow
def test_figure_units_and_one_legend_entry_per_kind():
    """parallel3: Cartesian coordinates in m, three torques in N m for two coordinates."""
    from jtraj.plotting import plot_solution

    robot = robots.get("parallel3")
    q_unit, tau_unit = "m", "N m"
    q0, q1 = jnp.asarray([-0.3, 0.2]), jnp.asarray([0.3, -0.3])
    problem = jtraj.Problem(robot, q0, q1, N=6)
    n = robot.n
    v = jnp.concatenate([jnp.tile(0.8 * (q1 - q0), (3, 1)), jnp.tile(-0.8 * (q1 - q0), (3, 1))]).reshape(6, n)
    fig = plot_solution(problem, _recursion_solution(problem, v, jnp.full(6, 0.1)))
    axes = {ax.get_title(): ax for ax in fig.axes}
    labels = {ax.get_ylabel() for ax in fig.axes}
    assert {f"q [{q_unit}]", f"qd [{q_unit}/s]", f"tau [{tau_unit}]"} <= labels
    for title, kinds in (("joint positions", ["optimum", "cycloidal guess"]),
                         ("joint velocities and limits", ["optimum", "cycloidal guess", "bound"]),
                         ("efforts at the samples (steps), between them (thin)",
                          ["optimum", "cycloidal guess", "between samples", "bound"])):
        texts = [t.get_text() for t in axes[title].get_legend().get_texts()]
        joints = [t for t in texts if t not in kinds and t != "bound"]
        assert len(joints) == (n if title != "efforts at the samples (steps), between them (thin)"
                               else int(np.shape(robot.limits.tau_max)[0]))
        for kind in kinds:  # every kind named once, not once per joint
            assert texts.count(kind) == 1, (title, texts)
    # the guess's duration is drawn beside the optimum's
    h_texts = [t.get_text() for t in axes["sampling periods"].get_legend().get_texts()]
    assert any(t.startswith("cycloidal guess (T = ") for t in h_texts)
    assert any(t.startswith("optimum (T = 0.600") for t in h_texts)


def test_figure_of_two_trajectories_names_both():
    """plot_solution(guess=<a trajectory>) draws that one dashed beside the first under the
    given names (jtraj query --plot: a refined optimum and its plan); the efforts between
    the samples are drawn for any object holding the arrays."""
    from jtraj.plotting import plot_solution

    robot = robots.get("serial3")
    q0, q1 = jnp.asarray([0.0, 0.5, 0.5]), jnp.asarray([0.6, 0.2, 0.9])
    problem = jtraj.Problem(robot, q0, q1, N=6, validate=False)  # (periods beyond h_max: drawn, not solved)
    v = jnp.concatenate([jnp.tile(q1 - q0, (3, 1)), jnp.tile(q0 - q1, (3, 1))])
    first = _recursion_solution(problem, v / 0.36, jnp.full(6, 0.2))  # T = 1.2 s
    second = _recursion_solution(problem, v / 0.81, jnp.full(6, 0.3))  # T = 1.8 s
    fig = plot_solution(problem, first, guess=second, label="refined optimum", guess_label="plan")
    axes = {ax.get_title(): ax for ax in fig.axes}
    texts = [t.get_text() for t in axes["joint positions"].get_legend().get_texts()]
    assert texts.count("refined optimum") == 1 and texts.count("plan") == 1 and "cycloidal guess" not in texts
    periods = axes["sampling periods"]
    h_texts = [t.get_text() for t in periods.get_legend().get_texts()]
    assert "refined optimum (T = 1.200 s)" in h_texts and "plan (T = 1.800 s)" in h_texts
    drawn = [np.asarray(line.get_ydata(), float) for line in periods.get_lines()[:2]]
    np.testing.assert_allclose(drawn[0], first.h)
    np.testing.assert_allclose(drawn[1], second.h)
    assert "efforts at the samples (steps), between them (thin)" in axes
    fig = plot_solution(problem, first, guess=False, label="plan")
    texts = [t.get_text() for t in fig.axes[1].get_legend().get_texts()]
    assert "plan" in texts and "optimum" not in texts and "cycloidal guess" not in texts
    broken = _Trajectory({**first, "q": first["q"].at[3, 0].set(jnp.nan)})
    with pytest.raises(ValueError, match="guess holds non-finite values"):
        plot_solution(problem, first, guess=broken)
    with pytest.raises(ValueError, match="solution holds non-finite values"):
        plot_solution(problem, broken, guess=False)


class _FakeSolution(typing.NamedTuple):
    """What run_all.solve_with_restart reads of a solution (a pytree of arrays)."""

    status: jax.Array
    converged: jax.Array
    v: jax.Array
    h: jax.Array
    max_violation: dict


def _fake(status, v, viol):
    return _FakeSolution(jnp.asarray(int(status)), jnp.asarray(status == jtraj.Status.CONVERGED),
                         jnp.asarray(v), jnp.full(3, 0.1), {"overall": jnp.asarray(viol)})


def test_solve_cache_resumes_each_try(tmp_path, monkeypatch):
    """solve_with_restart with a SolveCache: a run cut short during the restart keeps its
    first try; the resumed run solves only the restart, warm-started from the saved first
    try's end; a run with every try saved solves nothing and returns the same; the wall
    time adds up over the runs; loaded arrays are committed device arrays."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    first = _fake(jtraj.Status.MAX_ITERATIONS, [[1.0, 2.0]] * 3, 1e-3)
    second = _fake(jtraj.Status.CONVERGED, [[3.0, 4.0]] * 3, 1e-12)
    calls = []

    def fake_solve(problem, init=None):
        calls.append(init)
        if init is None:  # the cold first try
            return first, 5.0
        if cut_short:
            raise RuntimeError("time limit")
        return second, 2.0

    monkeypatch.setattr(run_all, "timed_solve", fake_solve)
    cut_short = True
    cache = run_all.SolveCache("demo")
    assert not cache.resumed and cache.path.parent == tmp_path
    with pytest.raises(RuntimeError):
        run_all.solve_with_restart(None, cache=cache, key="move")
    assert len(calls) == 2 and calls[0] is None
    saved_seconds = cache.data["seconds"]  # written with the first try

    cut_short, calls[:] = False, []
    assert not run_all.SolveCache("demo").data  # without resume: a fresh cache
    cache = run_all.SolveCache("demo", resume=True)
    assert cache.resumed and "move, try 0" in cache and "move, try 1" not in cache
    assert cache.seconds >= saved_seconds
    sol, t_first, t_last, tries = run_all.solve_with_restart(None, cache=cache, key="move")
    assert len(calls) == 1  # only the restart, from the saved first try's end
    np.testing.assert_array_equal(np.asarray(calls[0][0]), np.asarray(first.v))
    assert isinstance(calls[0][0], jax.Array) and calls[0][0].committed
    assert (t_first, t_last, tries) == (5.0, 2.0, ["MAX_ITERATIONS", "CONVERGED"])
    np.testing.assert_array_equal(np.asarray(sol.v), np.asarray(second.v))

    calls[:] = []
    again = run_all.solve_with_restart(None, cache=run_all.SolveCache("demo", resume=True), key="move")
    assert not calls and again[1:] == (5.0, 2.0, ["MAX_ITERATIONS", "CONVERGED"])
    with pytest.raises(FileNotFoundError, match="other"):
        run_all.SolveCache("other", must_exist=True)


def test_the_tip_path_names_via_points_once():
    """Several via points: one legend entry for all of them."""
    from jtraj.plotting import plot_path

    robot = robots.get("serial3")
    q0, q1 = jnp.asarray([0.2, 0.4, 0.3]), jnp.asarray([0.4, 0.3, 0.4])
    tip = np.asarray(robot.forward_kinematics((q0 + q1) / 2))
    problem = jtraj.Problem(robot, q0, q1, N=8, via_points=[tip, tip + 0.01, tip - 0.01])
    v = jnp.concatenate([jnp.tile(q1 - q0, (4, 1)), jnp.tile(-(q1 - q0), (4, 1))])
    fig = plot_path(problem, _recursion_solution(problem, v, jnp.full(8, 0.1)))
    texts = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert texts.count("via point") == 1, texts


def test_intervals_solve_only_where_the_bound_is_exceeded_between_samples(monkeypatch):
    """An optimum within its bound between samples needs no intervals solve (it is that
    problem's optimum too); one beyond it gets a warm-started solve and a status record."""
    robot = robots.get("serial3")
    problem = jtraj.Problem(robot, jnp.zeros(3), jnp.asarray([0.02, -0.01, 0.03]), N=4)
    v = jnp.asarray([[1.0, -0.5, 1.5], [0.5, 0.0, 0.5], [-0.5, 0.0, -0.5], [-1.0, 0.5, -1.5]])
    from jtraj.resample import intersample_effort

    calls = []

    def fake_solve(pr, init=None, cache=None, key=None):
        calls.append((pr, init))
        sol = _recursion_solution(problem, init[0] / 4, init[1])
        sol.update(T=jnp.sum(init[1]), status=np.int32(0), iterations=np.int32(3), outer_iterations=np.int32(0),
                   max_violation={"overall": np.float64(1e-12)})
        return sol, 1.0, 0.5, ["CONVERGED"]

    monkeypatch.setattr(run_all, "solve_with_restart", fake_solve)
    slow = _recursion_solution(problem, 0.1 * v, jnp.full(4, 0.2))
    assert float(intersample_effort(slow, robot)) < 1
    records = []
    cell = run_all.intervals_cell(lambda: pytest.fail("no solve expected"), slow, robot, "slow", records)
    assert cell.startswith("not needed") and records == [] and calls == []
    fast = _recursion_solution(problem, 4.0 * v, jnp.full(4, 0.2))
    fast.update(T=jnp.sum(fast.h))
    assert float(intersample_effort(fast, robot)) > 1
    cell = run_all.intervals_cell(lambda: "the intervals problem", fast, robot, "fast", records)
    assert calls[0][0] == "the intervals problem" and calls[0][1][0] is fast.v and calls[0][1][1] is fast.h
    assert [r["run"] for r in records] == ["fast, efforts=intervals"] and records[0]["status"] == "CONVERGED"
    assert cell.startswith("T = 0.8000 s (+0.00 %), CONVERGED (3 Newton it., 0 outer, 0.50 s)")
