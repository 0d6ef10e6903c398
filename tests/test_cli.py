"""The ``jtraj`` command line, called in-process (``jtraj.cli.main``).

The solve test's move fits N = 10 intervals and must converge (exit code 0, the goal met
within the strict 1e-6); the other tests check the plumbing, the consistency of what is
written and the bad-input paths.
"""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from jtraj import cli

# a move that fits N = 10 intervals (N h_max = 1 s): its optimum takes T = 0.97 s with
# every period interior, so the test can demand exit code 0.
START, GOAL = "0,30,30", "10,25,30"


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in ("solve", "gradcheck", "robots"):
        assert name in out
    with pytest.raises(SystemExit):
        cli.main(["solve", "--help"])
    out = capsys.readouterr().out
    for opt in ("--start-q", "--goal-xy", "--deg", "--json", "--plot", "--transcription", "--via"):
        assert opt in out


def test_solve_draws_no_figure_of_a_non_finite_solution(tmp_path, capsys, monkeypatch):
    """A solution holding NaN (a failed solve's): the JSON is written, no figure, a line
    on stderr says why, and the exit code is the status's."""
    import equinox as eqx

    import jtraj

    real = jtraj.solve

    def nan_solve(*a, **k):
        sol = real(*a, **k)
        return eqx.tree_at(lambda s: s.q, sol, sol.q * jnp.nan)

    monkeypatch.setattr(jtraj, "solve", nan_solve)
    out_json, out_png = tmp_path / "sol.json", tmp_path / "sol.png"
    rc = cli.main(["solve", "--robot", "serial3", "--start-q", START, "--goal-q", GOAL, "--deg", "--N", "10",
                   "--json", str(out_json), "--plot", str(out_png)])
    captured = capsys.readouterr()
    d = _strict_json(out_json)
    assert rc in (0, 1) and rc == (0 if d["converged"] else 1) and d["q"][0] == [None] * 3
    assert not out_png.exists() and f"no figure written to {out_png}" in captured.err


@pytest.mark.slow
def test_solve_writes_consistent_json_and_png(tmp_path, capsys, monkeypatch):
    from jtraj import _testing

    monkeypatch.setitem(_testing.setup_state, "seen", set())  # as in a new process: the first solve is announced
    out_json, out_png = tmp_path / "sol.json", tmp_path / "sol.png"
    rc = cli.main(["solve", "--robot", "serial3", "--start-q", START, "--goal-q", GOAL, "--deg", "--N", "10",
                   "--weights", "time=1,energy=0.5", "--json", str(out_json), "--plot", str(out_png), "--rate", "200"])
    captured = capsys.readouterr()
    text = captured.out
    d = json.loads(out_json.read_text())
    assert rc == 0 and d["converged"] and d["status_name"] == "CONVERGED", (rc, d["status_name"])
    # one line on stderr says that the solver is compiled (or loaded from the cache)
    lines = [ln for ln in captured.err.splitlines() if "the solver for serial3 (n = 3), N = 10" in ln]
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(("jtraj: compiling the solver for serial3 (n = 3), N = 10 (first use",
                                "jtraj: loading the compiled solver for serial3")), captured.err
    assert "status:" in text and "T =" in text and "max violation" in text and "solve" in text
    for key in ("converged", "status", "status_message", "T", "cost", "cost_terms", "max_violation", "q", "qd",
                "v", "tau", "h", "iterations", "solve_seconds", "compile_seconds", "robot", "N", "weights",
                "kkt_error"):
        assert key in d, key
    assert "KKT error (optimality; a converged solution's is <= 0.0003 by default)" in text
    assert np.isfinite(d["kkt_error"]) and d["kkt_error"] >= 0
    assert d["robot"] == "serial3" and d["N"] == 10 and d["weights"]["energy"] == 0.5
    assert d["solve_seconds"] > 0 and d["compile_seconds"] >= 0
    q, qd, v, h = (np.asarray(d[k], float) for k in ("q", "qd", "v", "h"))
    assert q.shape == (11, 3) and qd.shape == (11, 3) and v.shape == (10, 3) and h.shape == (10,)
    assert np.asarray(d["tau"]).shape == (10, 3)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(h))
    # the start and goal are the requested ones, in radians
    np.testing.assert_allclose(d["q_start"], np.deg2rad([0, 30, 30]), atol=1e-12)
    np.testing.assert_allclose(d["q_goal"], np.deg2rad([10, 25, 30]), atol=1e-12)
    # re-simulate the returned v and h: the states, T and the reported goal violation agree
    q_sim, qd_sim = np.zeros((11, 3)), np.zeros((11, 3))  # Khoukhi's recursion, written out here
    q_sim[0] = d["q_start"]
    for k in range(10):
        q_sim[k + 1] = q_sim[k] + h[k] * qd_sim[k] + 0.5 * h[k] ** 2 * v[k]
        qd_sim[k + 1] = qd_sim[k] + h[k] * v[k]
    np.testing.assert_allclose(q_sim, q, rtol=0, atol=1e-9)
    np.testing.assert_allclose(qd_sim, qd, rtol=0, atol=1e-9)
    assert math.isclose(d["T"], h.sum(), rel_tol=1e-12)
    goal_err = max(np.max(np.abs(q_sim[-1] - d["q_goal"])), np.max(np.abs(qd_sim[-1])))
    assert goal_err <= d["max_violation"]["goal"] + 1e-9 and goal_err <= 1e-6
    assert d["T"] < 1.0  # the optimum is interior: not every period at h_max
    assert d["max_violation"]["overall"] >= d["max_violation"]["goal"]
    assert np.all(h >= 0.005 - 1e-12) and np.all(h <= 0.1 + 1e-12)
    assert math.isclose(d["cost"], sum(d["cost_terms"].values()), rel_tol=1e-9)
    # the motion between the samples: the 200 Hz grid from 0 to T, its ends the solution's,
    # and the effort ratio along it at least the samples' own
    r = d["resampled"]
    t = np.asarray(r["t"])
    assert r["rate"] == 200 and t[0] == 0 and math.isclose(t[-1], d["T"], rel_tol=1e-12)
    assert np.allclose(np.diff(t[:-1]), 1 / 200) and 0 < t[-1] - t[-2] <= 1 / 200 + 1e-12
    np.testing.assert_allclose(np.asarray(r["q"])[[0, -1]], q[[0, -1]], atol=1e-12)
    assert np.asarray(r["tau"]).shape == (t.size, 3) and d["efforts"] == "samples"
    tau_max = np.asarray(__import__("jtraj").robots.get("serial3").limits.tau_max)
    assert d["effort_between_samples"] >= np.max(np.abs(np.asarray(d["tau"])) / tau_max) - 1e-12
    assert "efforts between the samples" in text
    png = out_png.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


@pytest.mark.parametrize("argv, needle", [
    (["--robot", "no_such_robot", "--start-q", START, "--goal-q", GOAL], "--robot"),
    (["--start-q", "0,abc,30", "--goal-q", GOAL], "--start-q"),
    (["--start-q", "nan,30,30", "--goal-q", GOAL], "--start-q"),
    (["--start-q", START, "--goal-q", "1,2"], "--goal-q"),
    (["--start-q", START, "--goal-q", "inf,0,0"], "--goal-q"),
    (["--start-q", START], "goal"),
    (["--goal-q", GOAL], "start"),
    (["--start-q", START, "--goal-q", GOAL, "--N", "1"], "--N"),
    (["--start-q", START, "--goal-q", GOAL, "--weights", "time=1,speed=2"], "--weights"),
    (["--start-q", START, "--goal-q", GOAL, "--T-max", "nan"], "--T-max"),
    (["--start-q", START, "--goal-q", GOAL, "--via", "1,x"], "--via"),
    (["--start-q", START, "--goal-q", "170,10,20", "--deg", "--N", "10"], "--N"),  # too far for N h_max
    (["--start-q", START, "--goal-xy", "1.3"], "--goal-xy"),
    (["--start-q", START, "--goal-xy", "5,5"], "--goal-xy"),  # unreachable (runs the IK)
    (["--start-q", START, "--goal-q", GOAL, "--json", "x.json", "--rate", "0"], "--rate"),
    (["--start-q", START, "--goal-q", GOAL, "--rate", "100"], "--rate"),  # needs --json
    (["--start-q", START, "--goal-q", GOAL, "--json", "x.json", "--rate", "100", "--transcription", "spline"],
     "--rate"),
    (["--start-q", START, "--goal-q", GOAL, "--efforts", "intervals", "--transcription", "coupled"], "--efforts"),
])
def test_solve_bad_input_exits_2(argv, needle, capsys):
    rc = cli.main(["solve", "--deg", *argv] if "--deg" not in argv else ["solve", *argv])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("jtraj solve: error:") and needle in err, err


def test_negative_vectors_need_no_equals_sign(capsys):
    assert cli.attach_negative_lists(["solve", "--start-q", "-10,30,30", "--goal-q", "-.5,1e-3,-2", "--T-max", "-1",
                                      "--via=-1,2", "--deg"]) == [
        "solve", "--start-q=-10,30,30", "--goal-q=-.5,1e-3,-2", "--T-max", "-1", "--via=-1,2", "--deg"]
    # parsed all the way to the input checks: the start is accepted, the goal's NaN named
    rc = cli.main(["solve", "--start-q", "-10,30,30", "--goal-q", "-10,nan,0", "--deg"])
    err = capsys.readouterr().err
    assert rc == 2 and "--goal-q must be finite numbers" in err, err


@pytest.mark.parametrize("argv, needle", [
    (["solve", "--start-q", START, "--goal-q", GOAL, "--deg", "--json", "{missing}/sol.json"], "--json"),
    (["solve", "--start-q", START, "--goal-q", GOAL, "--deg", "--plot", "{tmp}"], "--plot"),
    (["gradcheck", "--json", "{missing}/g.json"], "--json"),
    (["train", "--data", "{tmp}", "--out", "{missing}/m.anfis"], "--out"),
    (["query", "--model", "{missing}/m.anfis", "--start", "0,0,0", "--goal", "1,1,1"], "--model"),
    (["dataset", "plot", "{tmp}", "--out", "{missing}/p.png"], "--out"),
])
def test_paths_are_checked_before_any_compute(argv, needle, tmp_path, capsys, monkeypatch):
    # an unusable output path is refused up front, not after the solve it would lose
    import jtraj

    def never(*a, **k):
        raise AssertionError("computed before checking the paths")

    monkeypatch.setattr(jtraj, "solve", never)
    argv = [a.format(tmp=tmp_path, missing=tmp_path / "no_such_folder") for a in argv]
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith(f"jtraj {argv[0]}: error: {needle}"), err


def test_gradcheck_command(monkeypatch, tmp_path, capsys):
    """Command plumbing with a stubbed checker (the real check is tests/test_gradcheck.py)."""
    from jtraj import gradcheck as gc

    calls = {}

    def fake(robot, **kw):
        calls.update(kw, robot=robot)
        res = gc.RobotResult(robot="serial3", status=status, N=kw["N"], points=kw["points"], cost_adjoint=1e-16,
                             cost_fd=1e-10, al_adjoint=2e-16, al_fd=3e-9 if status == "ok" else 1e-3)
        skipped = gc.RobotResult(robot="wmr", status="skipped", note="model not available yet")
        return gc.Report(results=[res, skipped])

    monkeypatch.setattr(gc, "gradcheck", fake)
    for status, expected in (("ok", 0), ("FAIL", 1)):
        out = tmp_path / f"{status}.json"
        rc = cli.main(["gradcheck", "--robot", "serial3", "--N", "4", "--points", "2", "--json", str(out)])
        text = capsys.readouterr().out
        assert rc == expected
        assert calls["robot"] == "serial3" and calls["N"] == 4 and calls["points"] == 2
        assert "serial3" in text and "skipped" in text and ("PASSED" if expected == 0 else "FAILED") in text
        d = json.loads(out.read_text())
        assert d["passed"] is (expected == 0) and d["robots"][1]["cost_fd"] is None  # NaN -> null


    # --robot-param: the checked robot carries the parameters
    status = "ok"
    assert cli.main(["gradcheck", "--robot", "serial3", "--robot-param", "masses=3,2,1", "--N", "4"]) == 0
    capsys.readouterr()
    assert calls["robot"].name == "serial3" and np.allclose(calls["robot"].masses, (3, 2, 1))


@pytest.mark.parametrize("argv, needle", [
    (["--robot", "nope"], "--robot"),
    (["--robot-param", "qdd_max=5"], "--robot-param needs one robot"),
    (["--robot", "serial3", "--robot-param", "nope=5"], "--robot-param"),
    (["--robot", "serial3", "--N", "1"], "--N"),
    (["--robot", "serial3", "--points", "0"], "--points"),
    (["--robot", "serial3", "--fd-step", "-1"], "--fd-step"),
])
def test_gradcheck_bad_input_exits_2(argv, needle, capsys):
    rc = cli.main(["gradcheck", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err, err


@pytest.mark.skipif(not hasattr(__import__("os"), "sched_setaffinity"), reason="CPU affinity is Linux-only")
def test_pin_to_one_cpu_restricts_the_process():
    """In a child process (pinning this one would change the rest of the suite): the
    affinity becomes the one CPU returned, chosen modulo the allowed CPUs."""
    import os
    import subprocess
    import sys

    allowed = sorted(os.sched_getaffinity(0))
    code = ("import os, jtraj; c = jtraj.pin_to_one_cpu({i}); "
            "print(c, sorted(os.sched_getaffinity(0)))")
    for i in (0, len(allowed) + 1):
        out = subprocess.run([sys.executable, "-c", code.format(i=i)], capture_output=True, text=True, check=True)
        cpu, aff = out.stdout.split(maxsplit=1)
        assert int(cpu) == allowed[i % len(allowed)]
        assert aff.strip() == f"[{int(cpu)}]"


# --- jtraj query: the start and the goal checked as jtraj solve checks them -------------

@pytest.fixture(scope="module")
def plan_model(tmp_path_factory):
    """A small plan model of serial3 at N = 10 (a synthetic dataset: no solve)."""
    from jtraj import mappings

    data = mappings.synthetic_dataset(P=40, N=10, seed=0)
    model = mappings.train_mapping(data, "plan", n_rules=4, epochs=5)[0]
    path = tmp_path_factory.mktemp("query") / "plan.anfis"
    model.save(path)
    return str(path), data


def _strict_json(path):
    """The file's JSON, refusing NaN and infinities (which JSON does not have)."""
    def bad(token):
        raise ValueError(f"invalid JSON constant {token}")

    with open(path) as fh:
        return json.load(fh, parse_constant=bad)


@pytest.mark.parametrize("argv, needle", [
    (["--start", "0,0.5,nan", "--goal", "0.2,0.4,0.5"], "--start must be finite"),
    (["--start", "0,0.5,0.5", "--goal", "0.2,inf,0.5"], "--goal must be finite"),
    (["--start", "0,30,30", "--goal", "10,25,30"], "add --deg"),  # degrees without --deg
    (["--start", "0,0.5", "--goal", "0.2,0.4,0.5"], "--start must have 3 values"),
    (["--start", "0,0.5,0.5", "--goal", "0.2,0.4,0.5", "--N", "12"], "give --refine"),
    (["--start", "0,0.5,0.5", "--goal", "0.2,0.4,0.5", "--no-compare"], "--no-compare set"),
    (["--start", "0,0.5,0.5", "--goal", "0.2,0.4,0.5", "--refine", "--N", "1"], "--N must be"),
    (["--start", "0,0.5,0.5", "--goal", "0.2,0.4,0.5", "--refine", "--weights", "speed=1"], "--weights"),
])
def test_query_bad_input_exits_2_and_writes_nothing(argv, needle, plan_model, tmp_path, capsys, monkeypatch):
    import jtraj

    def never(*a, **k):
        raise AssertionError("solved a refused query")

    monkeypatch.setattr(jtraj, "solve", never)
    out = tmp_path / "q.json"
    rc = cli.main(["query", "--model", plan_model[0], *argv, "--json", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("jtraj query: error:") and needle in err, err
    assert not out.exists()


def test_joint_values_outside_the_joint_box_name_the_option_and_degrees_only_for_angles(tmp_path):
    """A start or goal outside the joint box is refused as jtraj solve refuses it, naming
    the option; where the angles fit the box once read as degrees, or lie beyond 2 pi,
    the message says --deg. Lengths are not angles: parallel3's coordinates (m) get no
    such hint, wmr's x and y of 23 m are not 'beyond 2 pi', and --deg converts wmr's
    heading alone."""
    import equinox as eqx

    import jtraj
    from jtraj.commands.solve import angular, check_joint_values, parse_vector

    base = jtraj.robots.get("serial3")
    robot = eqx.tree_at(lambda r: (r.limits.q_min, r.limits.q_max), base,
                        (jnp.full(3, -1.0), jnp.full(3, 1.0)), is_leaf=lambda x: x is None)
    inside = np.array([0.1, -0.2, 0.3])
    check_joint_values(robot, {"--start": inside, "--goal": inside}, deg=False)  # accepted
    # angles that fit the box once read as degrees: the message says --deg
    with pytest.raises(ValueError, match=r"--goal = \[0.1, 5.0, 0.0\] is outside the joint limits.*add --deg"):
        check_joint_values(robot, {"--start": inside, "--goal": [0.1, 5.0, 0.0]}, deg=False)
    # given with --deg (converted to radians by then): no hint
    with pytest.raises(ValueError, match=r"--start = \[5.0, -5.0, 0.0\] is outside the joint limits") as exc:
        check_joint_values(robot, {"--start": [5.0, -5.0, 0.0], "--goal": inside}, deg=True)
    assert "--deg" not in str(exc.value)
    with pytest.raises(ValueError, match=r"--goal = \[0.0, 30.0, 0.0\] has an angle beyond 2 pi.*add --deg"):
        check_joint_values(robot, {"--start": inside, "--goal": [0.0, 30.0, 0.0]}, deg=False)
    # parallel3's coordinates are lengths: refused without a word of degrees
    p3 = jtraj.robots.get("parallel3")
    assert not angular(p3).any()
    for goal in ([0.1, 1.0], [0.0, 30.0]):
        with pytest.raises(ValueError, match=r"--goal = .* is outside the joint limits") as exc:
            check_joint_values(p3, {"--start": [0.1, -0.2], "--goal": goal}, deg=False)
        assert "--deg" not in str(exc.value)
    # wmr: x and y in metres, the heading in radians
    wmr = jtraj.robots.get("wmr")
    np.testing.assert_array_equal(angular(wmr), [False, False, True])
    check_joint_values(wmr, {"--start-q": [3.0, 3.0, 0.0], "--goal-q": [23.0, 23.0, 0.5]}, deg=False)
    with pytest.raises(ValueError, match=r"has an angle beyond 2 pi.*add --deg"):
        check_joint_values(wmr, {"--start-q": [3.0, 3.0, 0.0], "--goal-q": [23.0, 23.0, 30.0]}, deg=False)
    np.testing.assert_allclose(parse_vector("23,23,30", "--goal-q", 3, deg=True, angles=angular(wmr)),
                               [23.0, 23.0, np.pi / 6], rtol=1e-15)


def test_query_writes_strict_json_and_reads_degrees(plan_model, tmp_path, capsys):
    path, data = plan_model
    qs, qg = data["q_start"][0], data["q_goal"][0]
    out, png = tmp_path / "q.json", tmp_path / "q.png"
    rc = cli.main(["query", "--model", path, "--start", ",".join(map(str, np.rad2deg(qs))),
                   "--goal", ",".join(map(str, np.rad2deg(qg))), "--deg", "--json", str(out), "--plot", str(png)])
    assert rc == 0, capsys.readouterr().err
    d = _strict_json(out)
    np.testing.assert_allclose(d["q"][0], qs, atol=1e-12)  # the plan starts at the start, in radians
    assert len(d["q"]) == 11 and isinstance(d["feasible"], bool)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"wrote {png}" in capsys.readouterr().out


def test_query_json_has_null_where_the_plan_is_not_finite(plan_model, tmp_path, monkeypatch, capsys):
    """A model may predict NaN: the report says nan, the JSON null (never invalid JSON)."""
    from jtraj import online

    real = online.Planner.query

    def nan_query(self, *a, **k):
        out = real(self, *a, **k)
        out.update(goal_error=float("nan"), T=float("inf"), q=[[float("nan")] * 3] * 11)
        return out

    monkeypatch.setattr(online.Planner, "query", nan_query)
    out, png = tmp_path / "q.json", tmp_path / "q.png"
    rc = cli.main(["query", "--model", plan_model[0], "--start", "0,0.5,0.5", "--goal", "0.2,0.4,0.5",
                   "--json", str(out), "--plot", str(png)])
    printed = capsys.readouterr()
    assert rc == 0 and "goal error nan" in printed.out
    d = _strict_json(out)
    assert d["goal_error"] is None and d["T"] is None and d["q"][0] == [None] * 3
    # no figure of a trajectory that is not one, and the report says so (the JSON is kept)
    assert not png.exists() and f"no figure written to {png}" in printed.err


def test_planner_checks_the_start_and_goal_and_resamples_for_another_N(plan_model):
    import jtraj
    from jtraj.online import Planner, _resampled

    planner = Planner(plan_model[0])
    with pytest.raises(ValueError, match="q_start must be finite"):
        planner.query([0.0, np.nan, 0.5], [0.2, 0.4, 0.5])
    with pytest.raises(ValueError, match=r"q_goal must have shape \(3,\)"):
        planner.query([0.0, 0.5, 0.5], [0.2, 0.4])
    with pytest.raises(ValueError, match="N must be an integer >= 2"):
        planner.query([0.0, 0.5, 0.5], [0.2, 0.4, 0.5], N=1)
    lim = jtraj.robots.get("serial3").limits
    v = np.arange(10.0)[:, None] * np.ones((1, 3))
    h = np.full(10, 0.05)
    v2, h2 = _resampled(v, h, 10, lim)
    np.testing.assert_array_equal(v2, v) and np.testing.assert_array_equal(h2, h)
    v2, h2 = _resampled(v, h, 5, lim)  # periods 0.1 s: midpoints 0.05, 0.15, ... fall in intervals 1, 3, ...
    np.testing.assert_allclose(h2, 0.1) and np.testing.assert_array_equal(v2[:, 0], [1, 3, 5, 7, 9])


@pytest.mark.slow  # the refined query is checked through the library in test_online_plan.py
def test_query_refine_exit_code_and_json(plan_model, tmp_path, capsys):
    """--refine at the model's N (the solve test's serial3 program at N = 10): the exit
    code says whether the refined solution converged, the JSON is strict."""
    import jtraj

    path, data = plan_model
    robot = jtraj.robots.get("serial3")

    def fits(i):  # the synthetic dataset's moves are not all feasible at N = 10
        try:
            jtraj.Problem(robot, data["q_start"][i], data["q_goal"][i], N=10)
        except ValueError:
            return False
        return True

    i = next(i for i in range(len(data["q_start"])) if fits(i))
    qs, qg = data["q_start"][i], data["q_goal"][i]
    out, png = tmp_path / "r.json", tmp_path / "r.png"
    rc = cli.main(["query", "--model", path, "--start", ",".join(map(str, qs)), "--goal", ",".join(map(str, qg)),
                   "--refine", "--N", "10", "--json", str(out), "--plot", str(png)])
    text = capsys.readouterr().out
    d = _strict_json(out)
    assert d["refined_N"] == 10 and "refined (primal warm start, N = 10)" in text
    assert rc == (0 if d["refined_converged"] else 1)
    # the refined trajectory: N periods summing to its T, from the start (to the goal where converged)
    h, q = np.asarray(d["refined_h"]), np.asarray(d["refined_q"])
    assert h.shape == (10,) and q.shape == (11, 3) and np.shape(d["refined_tau"]) == (10, 3)
    np.testing.assert_allclose(h.sum(), d["refined_T"], rtol=1e-12)
    np.testing.assert_allclose(q[0], qs, atol=1e-12)
    if d["refined_converged"]:
        np.testing.assert_allclose(q[-1], qg, atol=1e-6)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"wrote {png}" in text
    # without the comparison solve: the same refined solve, no cycloidal entries
    rc2 = cli.main(["query", "--model", path, "--start", ",".join(map(str, qs)), "--goal", ",".join(map(str, qg)),
                    "--refine", "--N", "10", "--no-compare", "--json", str(out)])
    alone = _strict_json(out)
    assert rc2 == rc and "cycloidal start" not in capsys.readouterr().out
    assert not any(k.startswith("cycloidal_") for k in alone)
    assert alone["refined_iterations"] == d["refined_iterations"] and alone["refined_h"] == d["refined_h"]


def test_robots_lists_every_robot_with_a_one_line_summary_and_shows_units(capsys):
    """``jtraj robots``: one line per built-in robot with its degrees of freedom and a
    self-contained summary (its factory docstring's first paragraph); ``jtraj robots
    NAME`` adds the units of the coordinates and of the efforts."""
    from jtraj import robots

    assert cli.main(["robots"]) == 0
    lines = capsys.readouterr().out.splitlines()
    for name in robots.names():
        text = robots.summary(name)
        assert 20 < len(text) < 120 and "\n" not in text and "``" not in text and "docstring" not in text, name
        row = [line for line in lines if line.split()[:1] == [name]]
        assert len(row) == 1 and f"n = {robots.get(name).n}" in row[0] and row[0].endswith(text), name
    assert cli.main(["robots", "gough_stewart"]) == 0
    out = capsys.readouterr().out
    assert robots.summary("gough_stewart") in out and "coordinates 3 m, 3 rad; efforts 6 N" in out
    assert cli.main(["robots", "wmr"]) == 0
    assert "coordinates 2 m, 1 rad; efforts 2 N m" in capsys.readouterr().out


def test_robots_without_example_robot_data_name_the_extra_to_install(tmp_path, monkeypatch, capsys):
    """Without the URDF files of example-robot-data (a plain ``pip install jtraj``), the
    list still shows every robot, marks the URDF arms with the extra to install, and
    ``jtraj robots panda`` and ``jtraj solve --robot panda`` say so in one line (status
    2, no traceback)."""
    monkeypatch.setenv("JTRAJ_ROBOT_DATA", str(tmp_path))
    assert cli.main(["robots"]) == 0
    rows = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines() if line[:1].isalpha())
    assert rows["panda"].startswith("n = ?") and rows["panda"].endswith("(install the robots extra: pip install 'jtraj[robots]')")
    assert rows["serial3"].startswith("n = 3") and "install" not in rows["serial3"]
    for args in (["robots", "panda"], ["solve", "--robot", "panda", "--start-q", "0,0,0,-1,0,1,0",
                                       "--goal-q", "0.1,0,0,-1,0,1,0"]):
        assert cli.main(args) == 2, args
        err = capsys.readouterr().err
        assert err.startswith(f"jtraj {args[0]}: error: ") and "pip install 'jtraj[robots]'" in err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_robots_shows_a_urdf_arm_and_joint_names(tmp_path, capsys):
    """``jtraj robots --urdf``: the arm ``solve --urdf`` and ``dataset --urdf`` would load,
    with its joint names and limits (the tip link choosing the branch's end); the names
    reappear in the errors on a wrong number of joint values and a value outside its box."""
    import jtraj
    from helpers import arm_urdf

    urdf = tmp_path / "arm.urdf"
    urdf.write_text(arm_urdf())
    assert cli.main(["robots", "--urdf", str(urdf)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("arm3: n = 3, SpatialSerial") and "joints   shoulder, elbow, gripper" in out
    assert "tau_max  [40. 40. 40.]" in out
    assert "qdd_max is jtraj's default 10; set your arm's with --robot-param qdd_max=" in out
    assert cli.main(["robots", "--urdf", str(urdf), "--tip-link", "tool", "--robot-param", "qdd_max=4,5"]) == 0
    out = capsys.readouterr().out
    assert "n = 2" in out and "qdd_max  [4. 5.]" in out and "jtraj's default" not in out
    args = cli.build_parser().parse_args(["solve", "--urdf", str(urdf), "--robot-param", "tau_max=7",
                                          "--start-q", "0,0,0", "--goal-q", "0.1,0.1,0.1"])
    from jtraj.commands.solve import build_problem

    robot, problem = build_problem(args)
    np.testing.assert_array_equal(problem.robot.limits.tau_max, [7.0, 7.0, 7.0])
    assert cli.main(["robots", "panda"]) == 0
    assert "joints   panda_joint1, panda_joint2," in capsys.readouterr().out
    for args, message in ((["robots", "--tip-link", "tool"], "--tip-link needs --urdf"),
                          (["robots", "panda", "--urdf", str(urdf)], "not both"),
                          (["robots", "--urdf", str(urdf), "--tip-link", "hand"], "tip_link 'hand' is not a link"),
                          (["robots", "nosuchbot"], "name must be one of"),
                          (["robots", "--robot-param", "qdd_max=1"], "--robot-param needs a robot"),
                          (["solve", "--robot", "serial3", "--robot-param", "tau_max=-1", "--start-q", "0,0,0",
                            "--goal-q", "0.1,0.1,0.1"], "--robot-param: tau_max must be > 0"),
                          (["solve", "--urdf", str(urdf), "--start-q", "0,0", "--goal-q", "0.1,0.1,0.1"],
                           "--start-q must have 3 values for this robot (shoulder, elbow, gripper), got 2"),
                          (["solve", "--urdf", str(urdf), "--start-q", "0,0,0", "--goal-q", "0.1,1.6,0.1"],
                           "joint 'elbow' (index 1) at 1.6, outside [-1.5, 1.5]")):
        assert cli.main(args) == 2, args
        assert message in capsys.readouterr().err, args
    robot = jtraj.robots.get("pkm2")  # a robot without joint names: the index
    with pytest.raises(ValueError, match=r"q_goal .* joint limits: joint 0 at 5, outside \[-0.8, 0.8\]"):
        jtraj.Problem(robot, [0.0, -1.2], [5.0, -1.2], N=4)


@pytest.mark.slow
def test_gradcheck_of_a_urdf_arm(tmp_path, capsys):
    """``jtraj gradcheck --urdf``: a two-joint arm (its manipulability, in the
    singularity term the check switches on, from ``J^T J``) passes against the adjoint
    and finite differences."""
    from helpers import arm_urdf

    urdf = tmp_path / "arm.urdf"
    urdf.write_text(arm_urdf())
    assert cli.main(["gradcheck", "--urdf", str(urdf), "--tip-link", "tool", "--N", "4", "--points", "1"]) == 0
    out = capsys.readouterr().out
    assert "arm3" in out and "PASSED" in out
    assert cli.main(["gradcheck", "--urdf", str(urdf), "--robot", "panda"]) == 2
    assert "not both" in capsys.readouterr().err


def test_a_closed_output_pipe_stops_quietly(monkeypatch, capsys):
    """``jtraj robots | head -1``: the reader leaves, the command stops with status 1 and
    no error line (not a traceback, not ``error: [Errno 32] Broken pipe``)."""
    import sys

    class Closed:
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

    monkeypatch.setattr(sys, "stdout", Closed())
    assert cli.main(["robots"]) == 1
    assert capsys.readouterr().err == ""
