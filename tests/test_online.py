"""Trajectory models (jtraj train) and the online planner (jtraj query), on a small
synthetic dataset built here (no dependency on the dataset builder or the solver)."""

import json

import numpy as np
import pytest

from jtraj import anfis
from jtraj import mappings
from jtraj import _testing


@pytest.fixture(scope="module")
def data():
    return mappings.synthetic_dataset(P=40, N=10, seed=0)


def test_split_is_by_trajectory_and_last_ten_percent(data):
    X, Y, traj, names_in, names_out = mappings.view(data, "nefotc")
    conv = np.nonzero(data["converged"])[0]
    assert X.shape == (conv.size * 10, 6) and Y.shape == (conv.size * 10, 3)
    assert names_in[:1] == ["q1"] and names_out == ["tau1", "tau2", "tau3"]
    tr, te = mappings.split(traj)
    test_ids = np.unique(traj[te])
    np.testing.assert_array_equal(test_ids, conv[-round(0.1 * conv.size):])
    assert not set(np.unique(traj[tr])) & set(test_ids)


def test_baselines_exact_on_linear_data():
    rng = np.random.default_rng(0)
    X = rng.random((200, 3))
    Y = X @ np.array([[1.0], [2.0], [-1.0]]) + 0.5
    np.testing.assert_allclose(mappings.linear_baseline(X, Y, X[:5]), Y[:5], atol=1e-10)
    np.testing.assert_allclose(mappings.knn_baseline(X, Y, X[:5], k=1), Y[:5])


def test_train_command_report_and_plot(tmp_path, data, monkeypatch):
    from jtraj.commands import train as cmd

    monkeypatch.setattr(mappings, "load_data", lambda d: data)
    import os

    (tmp_path / "ds").mkdir()
    args = type("A", (), dict(data=str(tmp_path / "ds"), mapping="nefotc", out=str(tmp_path / "m.anfis"),
                              json=str(tmp_path / "r.json"), plot=str(tmp_path / "c.png"), rules=6, radius=0.5,
                              kind="tsk", order=1, epochs=10, ridge=1e-6, no_progress=True))
    assert cmd.run(args) == 0
    rep = json.load(open(args.json))
    for k in ("train_rmse", "test_rmse", "test_rmse_per_output", "n_rules", "epochs", "seconds",
              "linear_test_rmse", "knn_test_rmse"):
        assert k in rep
    assert rep["n_rules"] == 6 and set(rep["test_rmse_per_output"]) == {"tau1", "tau2", "tau3"}
    assert rep["inputs"][-1] == "phase" and "thesis_linear_test_rmse" in rep  # nefotc's default inputs
    assert np.isfinite(rep["test_rmse"]) and rep["test_rmse"] < 5 * rep["linear_test_rmse"]
    assert os.path.getsize(args.plot) > 1000
    model = anfis.load(args.out, mapping="nefotc")
    assert model.metadata["robot"] == "serial3"
    with pytest.raises(ValueError, match="mapping"):
        anfis.load(args.out, mapping="plan")


@pytest.mark.slow
def test_auto_radius_ensemble_weights_the_candidates_by_validation_error(tmp_path, data):
    model, rep, hist = mappings.train_mapping(data, "nefotc", epochs=5)
    sel = rep["radius_selection"]
    assert set(sel) == {str(r) for r in mappings.RADIUS_CANDIDATES}
    trained = {r: v for r, v in sel.items() if "skipped" not in v}
    assert isinstance(model, anfis.Ensemble) and rep["ensemble"] and len(model.members) == len(trained) >= 2
    # a larger radius never yields more rules
    counts = [sel[str(r)]["n_rules"] for r in mappings.RADIUS_CANDIDATES if str(r) in trained]
    assert len(counts) >= 2 and counts == sorted(counts, reverse=True)
    assert [m.n_rules for m in model.members] == counts and rep["n_rules"] == sum(counts)
    # weights 1 / MSE^2 of the validation split, normalised
    va = np.array([trained[str(r)]["validation_rmse"] for r in mappings.RADIUS_CANDIDATES if str(r) in trained])
    w = va**-4 / np.sum(va**-4)
    np.testing.assert_allclose(np.asarray(model.weights), w, rtol=1e-12)
    order = [str(r) for r in mappings.RADIUS_CANDIDATES if str(r) in trained]
    np.testing.assert_allclose([trained[r]["weight"] for r in order], w, rtol=1e-12)
    # the report's radius, history and the leading member are those of the lowest validation RMSE
    best = min(trained, key=lambda r: trained[r]["validation_rmse"])
    assert rep["radius"] == pytest.approx(float(best)) and model.leading.n_rules == sel[best]["n_rules"]
    assert min(hist.val_rmse) == pytest.approx(sel[best]["validation_rmse"])
    # predictions: the weighted average of the members', one sample or a batch, jitted or not
    X = mappings.view(data, "nefotc", goal="relative", phase=True)[0][:7]
    ref = sum(wk * np.asarray(m.predict(X)) for wk, m in zip(w, model.members))
    np.testing.assert_allclose(np.asarray(model.predict(X)), ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(model.predict(X[3])), ref[3], rtol=1e-12, atol=1e-12)
    import jax

    np.testing.assert_allclose(np.asarray(jax.jit(model.predict_fn())(X)), ref, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        model.predict(X[:, :3])
    # saved and loaded: same predictions, mapping checked
    model.save(tmp_path / "e.anfis")
    back = anfis.load(tmp_path / "e.anfis", mapping="nefotc")
    assert isinstance(back, anfis.Ensemble) and back.metadata == model.metadata
    np.testing.assert_array_equal(np.asarray(back.predict(X)), np.asarray(model.predict(X)))
    with pytest.raises(ValueError, match="mapping"):
        anfis.load(tmp_path / "e.anfis", mapping="plan")
    tagged = model.with_metadata(note="x")
    assert isinstance(tagged, anfis.Ensemble) and tagged.metadata["note"] == "x" and "note" not in model.metadata
    assert model.astype(np.float32).predict(X).dtype == np.float32
    # members trained on other data (another scaling) are refused; weights must be positive
    other = mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1, phase=True, test_fraction=0.3)[0]
    with pytest.raises(ValueError, match="scaling"):
        anfis.Ensemble.from_models([model.leading, other], [1.0, 1.0])
    with pytest.raises(ValueError, match="positive"):
        anfis.Ensemble.from_models(model.members, np.r_[-1.0, np.ones(len(counts) - 1)])
    # ensemble=False: the single model of lowest validation RMSE
    single, rep1, _ = mappings.train_mapping(data, "nefotc", epochs=5, ensemble=False)
    assert isinstance(single, anfis.Model) and not rep1["ensemble"] and rep1["n_rules"] == sel[best]["n_rules"]
    np.testing.assert_allclose(np.asarray(single.predict(X)), np.asarray(model.leading.predict(X)), rtol=1e-12)


@pytest.mark.slow
def test_mirror_augmentation_adds_the_reflected_trajectories_where_the_robot_is_symmetric(data, monkeypatch):
    from jtraj.anfis import training

    # serial3 (horizontal, no gravity): odd inverse dynamics, symmetric limits
    assert mappings.mirror_symmetry(data) is None
    m = mappings.mirrored(data)
    for k in ("q", "qd", "v", "tau", "q_start", "q_goal"):
        np.testing.assert_array_equal(m[k], -np.asarray(data[k]))
    np.testing.assert_array_equal(m["h"], data["h"])
    seen = []
    real_train = training.train
    monkeypatch.setattr(training, "train", lambda X, Y, **kw: seen.append((X, Y, kw["validation"]))
                        or real_train(X, Y, **kw))
    _, plain, _ = mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1, augment="none")
    _, aug, _ = mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1)  # "auto"
    assert plain["augment"] == "none" and aug["augment"] == "mirror" and "augment_note" not in aug
    (X0, Y0, (V0, W0)), (X1, Y1, (V1, W1)) = seen
    n = len(X0)
    # fit and validation rows: the originals, then their mirror images (inputs
    # q_goal - q and qd negated, the phase kept; torques negated)
    flip = np.r_[-np.ones(X0.shape[1] - 1), 1.0]
    np.testing.assert_array_equal(X1[:n], X0)
    np.testing.assert_array_equal(X1[n:], X0 * flip)
    np.testing.assert_array_equal(Y1, np.r_[Y0, -Y0])
    np.testing.assert_array_equal(V1, np.r_[V0, V0 * flip])
    np.testing.assert_array_equal(W1, np.r_[W0, -W0])
    # the rule cap of radius "auto" counts the mirror images as trajectories of their own
    counted = []
    monkeypatch.setattr(mappings, "_auto_radii", lambda X, Y, traj, o, sel: counted.append(
        (len(X), np.unique(traj).size)) or [1.4])
    for a in ("none", "mirror"):
        mappings.train_mapping(data, "nefotc", epochs=1, augment=a)
    assert counted[1] == (2 * counted[0][0], 2 * counted[0][1])
    # the test split and the baselines are the same
    for k in ("n_samples_test", "n_samples_train", "linear_test_rmse", "knn_test_rmse"):
        assert aug[k] == plain[k]
    # "auto" leaves large training sets alone; "mirror" still mirrors them
    monkeypatch.setattr(mappings, "MIRROR_AUTO_BELOW", 5)
    _, big, _ = mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1)
    assert big["augment"] == "none" and "training trajectories" in big["augment_note"]
    assert mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1, augment="mirror")[1]["augment"] == "mirror"
    monkeypatch.undo()
    _, ik, _ = mappings.train_mapping(data, "nefik", n_rules=2, epochs=1)  # not mirrored by "auto"
    assert ik["augment"] == "none" and "mappings" in ik["augment_note"]
    # a robot under gravity is not symmetric: "auto" skips, "mirror" refuses
    vertical = mappings.synthetic_dataset(P=20, N=10, seed=1, robot="serial3_vertical")
    assert "not odd" in mappings.mirror_symmetry(vertical)
    _, rep, _ = mappings.train_mapping(vertical, "nefotc", n_rules=2, epochs=1)
    assert rep["augment"] == "none" and "not odd" in rep["augment_note"]
    with pytest.raises(ValueError, match="augment='mirror': the inverse dynamics are not odd"):
        mappings.train_mapping(vertical, "nefotc", n_rules=2, epochs=1, augment="mirror")
    with pytest.raises(ValueError, match="augment must be one of"):
        mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1, augment="flip")
    # so do a singularity term in the cost and a joint box not symmetric about 0
    singular = dict(data, metadata=dict(data["metadata"], weights_text="time=1,energy=0.1,singularity=0.01"))
    assert "singularity" in mappings.mirror_symmetry(singular)
    zero = dict(data, metadata=dict(data["metadata"], weights_text="time=1,singularity=0"))
    assert mappings.mirror_symmetry(zero) is None
    from jtraj import robots
    from jtraj.dataset import views

    boxed = robots.get("serial3")
    boxed = boxed.replace(limits=type(boxed.limits).make(3, q_min=-1.0, q_max=2.0, tau_max=boxed.limits.tau_max))
    monkeypatch.setattr(views, "robot_of", lambda d: boxed)
    assert "joint box is not symmetric" in mappings.mirror_symmetry(data)


def test_auto_radius_skips_radii_with_more_rules_than_the_data_carry(monkeypatch):
    from jtraj.anfis.clustering import subclust

    rng = np.random.default_rng(0)
    X, Y = rng.random((400, 3)), rng.random((400, 1))  # no structure: small radii give many rules
    traj = np.arange(400) // 4  # 100 trajectories -> at most 25 rules
    counts = {r: subclust(np.c_[X, Y], r).centers.shape[0] for r in mappings.RADIUS_CANDIDATES}
    assert counts[0.4] > 25 >= counts[1.4]
    sel = {}
    kept = _testing.auto_radii(X, Y, traj, {}, sel)
    assert kept == [r for r in mappings.RADIUS_CANDIDATES if counts[r] <= 25]
    assert set(sel) == {str(r) for r in mappings.RADIUS_CANDIDATES if counts[r] > 25}
    assert all(v["skipped"] == "more than 25 rules" for v in sel.values())
    # when no radius is within the cap, the largest (fewest rules) is kept
    monkeypatch.setattr(mappings, "RADIUS_CANDIDATES", (0.4, 0.6))
    monkeypatch.setattr(mappings, "MAX_AUTO_RULES", counts[0.6] - 1)
    assert _testing.auto_radii(X, Y, traj, {}, {}) == [0.6]
    monkeypatch.setattr(mappings, "RADIUS_CANDIDATES", (0.4, 0.6, 0.9, 1.4))
    # the absolute cap
    monkeypatch.setattr(mappings, "TRAJECTORIES_PER_RULE", 1)
    monkeypatch.setattr(mappings, "MAX_AUTO_RULES", counts[0.9])
    assert 0.4 not in _testing.auto_radii(X, Y, traj, {}, {})


def test_train_command_rejects_a_bad_radius():
    import argparse

    from jtraj.commands import train as cmd

    parser = argparse.ArgumentParser()
    cmd.configure(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(["--data", "d", "--out", "m", "--radius", "wide"])
    assert parser.parse_args(["--data", "d", "--out", "m"]).radius == "auto"


@pytest.mark.slow  # the repaired planner (the default) is checked in test_online_plan.py
def test_planner_one_call_with_feasibility(tmp_path, data):
    from jtraj.online import Planner

    model, rep, _ = mappings.train_mapping(data, "plan", n_rules=4, epochs=5)
    planner = Planner(model, correct=False)  # the raw prediction (tests/test_online_plan.py: the repair)
    qs, qg = data["q_start"][0], data["q_goal"][0]
    p = planner.plan(qs, qg)
    assert p.q.shape == (11, 3) and p.tau.shape == (10, 3) and p.h.shape == (10,)
    # the plan is the model's output read as (v, h), run through the recursion, with the
    # efforts of Pinocchio's RNEA and the report's measures written out here
    N, n, lim = 10, 3, planner.robot.limits
    y = np.asarray(model.predict(np.concatenate([qs, qg])))
    np.testing.assert_allclose(p.v, y[:N * n].reshape(N, n), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(p.h, np.clip(y[N * n:], float(lim.h_min), float(lim.h_max)), rtol=1e-12)
    V = pytest.importorskip("jtraj_peers.verify")
    q_sim, qd_sim = V.simulate(qs, np.asarray(p.v), np.asarray(p.h))
    np.testing.assert_allclose(p.q, q_sim, atol=1e-12)
    np.testing.assert_allclose(p.qd, qd_sim, atol=1e-12)
    tau = np.array([V.rnea(q_sim[k], qd_sim[k], np.asarray(p.v)[k]) for k in range(N)])
    np.testing.assert_allclose(p.tau, tau, rtol=1e-9, atol=1e-9)
    tau_max, qd_max = np.asarray(lim.tau_max), np.asarray(lim.qd_max)
    assert float(p.tau_violation) == pytest.approx(max(np.max(np.abs(tau) / tau_max - 1), 0.0), abs=1e-12)
    assert float(p.qd_violation) == pytest.approx(max(np.max(np.abs(qd_sim) / qd_max - 1), 0.0), abs=1e-12)
    assert float(p.goal_error) == pytest.approx(np.linalg.norm(q_sim[-1] - qg), abs=1e-12)
    assert float(p.T) == pytest.approx(np.sum(np.asarray(p.h)), rel=1e-12)
    out = planner.query(qs, qg)
    worst = max(out["tau_violation"], out["qd_violation"], out["qdd_violation"], out["q_violation"],
                out["h_violation"], out["jerk_violation"])
    assert out["violation"] == worst
    assert out["feasible"] == (worst <= planner.tol and max(out["goal_error"], out["goal_velocity"]) <= planner.goal_tol)
    assert out["goal_error"] == pytest.approx(float(p.goal_error), rel=1e-12)
    # the efforts between the samples reach at least those at the samples and at every
    # interval's end (Pinocchio: the new state with the interval's own acceleration)
    ends = np.array([V.rnea(q_sim[k + 1], qd_sim[k + 1], np.asarray(p.v)[k]) for k in range(N)])
    lower = max(np.max(np.abs(tau) / tau_max), np.max(np.abs(ends) / tau_max))
    assert lower - 1e-9 <= out["effort_between_samples"] <= lower * 1.5
    # an ensemble plans too: of two copies of the model, the model's own plan
    twin = anfis.Ensemble.from_models([model, model], [1.0, 3.0], model.metadata)
    np.testing.assert_allclose(np.asarray(Planner(twin, correct=False).plan(qs, qg).q), np.asarray(p.q), rtol=1e-12,
                               atol=1e-12)
    path = tmp_path / "otc.anfis"
    mappings.train_mapping(data, "nefotc", n_rules=3, epochs=1)[0].save(path)
    with pytest.raises(ValueError, match="periods="):
        Planner(str(path))  # a nefotc model needs the periods of a nefumop model
    with pytest.raises(ValueError, match="periods= is for a nefotc model"):
        Planner(model, periods=str(path))
    with pytest.raises(ValueError, match="periods must be a nefumop model"):
        Planner(str(path), periods=model)
    thesis = mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1, goal=False, phase=False)[0]
    with pytest.raises(ValueError, match="no goal inputs"):
        Planner(thesis, periods=model)
    nefik = mappings.train_mapping(data, "nefik", n_rules=2, epochs=1)[0]
    with pytest.raises(ValueError, match="mapping 'plan', or 'nefotc'"):
        Planner(nefik)


@pytest.mark.slow
def test_closed_loop_planner_rolls_the_controller_out_through_the_dynamics(tmp_path, data):
    import jax.numpy as jnp

    from jtraj import robots
    from jtraj.online import Planner, model_inputs

    limits = {"h_max": 0.2}  # as a jtraj dataset records its limits: the planner's robot takes h_max
    d = dict(data, metadata=dict(data["metadata"], limits=limits))
    ctl = mappings.train_mapping(d, "nefotc", n_rules=3, epochs=2)[0]
    per = mappings.train_mapping(d, "nefumop", n_rules=3, epochs=2)[0]
    assert ctl.metadata["h_max"] == per.metadata["h_max"] == 0.2
    # the planner's inputs are the training view's rows (same goal offset and phase)
    robot = robots.get("serial3")
    for m, mapping in ((ctl, "nefotc"), (per, "nefumop")):
        X, _, traj, _, _ = mappings.view(d, mapping, goal=m.metadata["goal_inputs"], phase=True)
        i, k = int(traj[13]), 13 % 10
        mine = model_inputs(m.metadata, robot, jnp.asarray(d["q"][i, k]), jnp.asarray(d["qd"][i, k]),
                            jnp.asarray(d["q_goal"][i]), k, 10)
        np.testing.assert_allclose(np.asarray(mine), X[13], rtol=1e-12, atol=1e-12)
    planner = Planner(ctl, periods=per, correct=False)  # the raw rollout
    assert float(planner.robot.limits.h_max) == 0.2
    qs, qg = d["q_start"][2], d["q_goal"][2]
    p = planner.plan(qs, qg)
    assert p.q.shape == (11, 3) and p.v.shape == (10, 3) and p.h.shape == (10,)
    np.testing.assert_allclose(p.q[0], qs)
    np.testing.assert_array_equal(p.qd[0], 0.0)
    # the decoupled recursion holds, torques are the clipped controller outputs and the
    # accelerations their forward dynamics
    q, qd, v, h, tau = (np.asarray(a) for a in (p.q, p.qd, p.v, p.h, p.tau))
    np.testing.assert_allclose(q[1:], q[:-1] + h[:, None] * qd[:-1] + 0.5 * h[:, None] ** 2 * v, atol=1e-12)
    np.testing.assert_allclose(qd[1:], qd[:-1] + h[:, None] * v, atol=1e-12)
    tau_max = np.asarray(robot.limits.tau_max)
    for k in (0, 5):
        u = model_inputs(ctl.metadata, robot, jnp.asarray(q[k]), jnp.asarray(qd[k]), jnp.asarray(qg), k, 10)
        np.testing.assert_allclose(tau[k], np.clip(np.asarray(ctl.predict(u)), -tau_max, tau_max), atol=1e-8)
        h_k = np.asarray(per.predict(model_inputs(per.metadata, robot, jnp.asarray(q[k]), jnp.asarray(qd[k]),
                                                  jnp.asarray(qg), k, 10)))[-1]
        assert h[k] == pytest.approx(np.clip(h_k, robot.limits.h_min, 0.2), abs=1e-12)
        np.testing.assert_allclose(v[k], np.asarray(robot.forward_dynamics(*map(jnp.asarray, (q[k], qd[k], tau[k])))),
                                   atol=1e-9)
    assert float(p.tau_violation) <= 1e-9  # clipped into the torque box
    assert float(p.goal_error) == pytest.approx(np.linalg.norm(q[-1] - qg))
    out = planner.query(qs, qg)
    assert isinstance(out["feasible"], bool) and out["goal_error"] == pytest.approx(float(p.goal_error))
    # the command: jtraj query --model otc.anfis --periods mop.anfis
    from jtraj.commands import query as cmd

    ctl.save(tmp_path / "otc.anfis")
    per.save(tmp_path / "mop.anfis")
    args = type("A", (), dict(model=str(tmp_path / "otc.anfis"), periods=str(tmp_path / "mop.anfis"),
                              start=list(qs), goal=list(qg), refine=False, warm="primal",
                              json=str(tmp_path / "q.json")))
    assert cmd.run(args) == 0
    with open(args.json) as f:
        out = json.load(f)
    # the command's plan is the repaired rollout: on the goal, and the rollout's own miss reported
    assert out["predicted_goal_error"] == pytest.approx(float(p.goal_error), rel=1e-9)
    assert out["goal_error"] <= 1e-9 and out["goal_velocity"] <= 1e-9 and out["corrected"]
    args.periods = None
    with pytest.raises(ValueError, match="--periods"):
        cmd.run(args)


def test_goal_inputs_append_offset_to_goal(data):
    X, Y, traj, names_in, _ = mappings.view(data, "nefotc", goal=True)
    X0, Y0, traj0, _, _ = mappings.view(data, "nefotc")
    assert names_in[6:] == ["dq_goal1", "dq_goal2", "dq_goal3"]
    np.testing.assert_array_equal(X[:, :6], X0)
    np.testing.assert_array_equal(Y, Y0)
    np.testing.assert_allclose(X[:, 6:], data["q_goal"][traj] - X0[:, :3])
    Xu, _, _, names_u, _ = mappings.view(data, "nefumop", goal=True)
    assert Xu.shape[1] == 6 and names_u[4:] == ["dx_goal", "dy_goal"]
    Xr, _, _, names_r, _ = mappings.view(data, "nefotc", goal="relative")
    assert names_r == ["dq_goal1", "dq_goal2", "dq_goal3", "qd1", "qd2", "qd3"]
    np.testing.assert_array_equal(Xr, np.c_[X[:, 6:], X[:, 3:6]])
    with pytest.raises(ValueError, match="goal inputs"):
        mappings.view(data, "plan", goal=True)


def test_model_records_dataset_weights_and_goal_inputs(data):
    d = dict(data, metadata=dict(data["metadata"], weights_text="time=1,energy=0.1"))
    model, rep, _ = mappings.train_mapping(d, "nefotc", n_rules=3, epochs=1, goal=True, phase=False)
    assert model.metadata["weights"] == "time=1,energy=0.1" and model.metadata["goal_inputs"] == "append"
    assert rep["goal_inputs"] == "append" and not rep["phase_input"] and model.n_inputs == 9
    model, rep, _ = mappings.train_mapping(d, "nefotc", n_rules=3, epochs=1, goal="relative", phase=False)
    assert model.metadata["goal_inputs"] == "relative" and model.n_inputs == 6


def test_phase_input_is_the_samples_place_in_its_trajectory(data):
    X0, Y0, traj, names0, _ = mappings.view(data, "nefotc")
    X, Y, traj1, names, _ = mappings.view(data, "nefotc", phase=True)
    N = data["h"].shape[1]
    assert names == names0 + ["phase"]
    np.testing.assert_array_equal(X[:, :-1], X0)
    np.testing.assert_array_equal(Y, Y0)
    np.testing.assert_array_equal(traj1, traj)
    # row r is sample r mod N of its trajectory (rows are trajectories in order, N samples each)
    np.testing.assert_allclose(X[:, -1], (np.arange(len(X)) % N) / N)
    assert np.all(np.diff(X[traj == traj[0], -1]) > 0)
    with pytest.raises(ValueError, match="phase"):
        mappings.view(data, "nefik", phase=True)


def test_defaults_add_goal_offset_and_phase_with_the_thesis_baseline(data):
    model, rep, _ = mappings.train_mapping(data, "nefotc", n_rules=3, epochs=2)
    assert rep["inputs"] == ["dq_goal1", "dq_goal2", "dq_goal3", "qd1", "qd2", "qd3", "phase"]
    assert rep["goal_inputs"] == "relative" and rep["phase_input"] and model.metadata["phase_input"]
    # the thesis' (q, qd) -> tau linear baseline, fitted on the same split
    X0, Y0, traj, _, _ = mappings.view(data, "nefotc")
    tr, te = mappings.split(traj)
    ref = np.sqrt(np.mean((mappings.linear_baseline(X0[tr], Y0[tr], X0[te]) - Y0[te]) ** 2))
    assert rep["thesis_linear_test_rmse"] == pytest.approx(ref, rel=1e-12)
    assert rep["ratio_to_thesis_linear"] == pytest.approx(rep["test_rmse"] / ref, rel=1e-12)
    # nefumop: position, velocity, goal offset and phase; the thesis' inputs when asked
    _, rep_u, _ = mappings.train_mapping(data, "nefumop", n_rules=2, epochs=1)
    assert rep_u["inputs"] == ["x", "y", "xd", "yd", "dx_goal", "dy_goal", "phase"]
    _, rep_u, _ = mappings.train_mapping(data, "nefumop", n_rules=2, epochs=1, goal=False, phase=False)
    assert rep_u["inputs"] == ["x", "y", "xd", "yd"] and "thesis_linear_test_rmse" not in rep_u
    # nefik and plan have no extra inputs
    assert mappings.default_inputs("nefik") == (False, False) == mappings.default_inputs("plan")
    import argparse

    from jtraj.commands import train as cmd

    parser = argparse.ArgumentParser()
    cmd.configure(parser)
    a = parser.parse_args(["--data", "d", "--out", "m", "--goal-inputs", "none", "--no-phase"])
    assert a.goal_inputs == "none" and a.phase is False
    _, rep_t, _ = mappings.train_mapping(data, "nefotc", n_rules=2, epochs=1, goal=a.goal_inputs, phase=a.phase)
    assert rep_t["inputs"] == ["q1", "q2", "q3", "qd1", "qd2", "qd3"] and rep_t["goal_inputs"] is False
    assert "thesis_linear_test_rmse" not in rep_t
    a = parser.parse_args(["--data", "d", "--out", "m"])
    assert a.goal_inputs is None and a.phase is None


def test_views_of_a_partial_dataset_use_row_positions(data):
    # a partial dataset's "index" holds the pair indices of its finished chunks
    part = {k: (v if k == "metadata" else np.asarray(v)[20:]) for k, v in data.items()}
    part["index"] = np.arange(20, 40)
    X, _, traj, _, _ = mappings.view(part, "nefotc", goal="relative", phase=True)
    assert traj.min() >= 0 and traj.max() < 20
    Xf, _, trajf, _, _ = mappings.view(data, "nefotc", goal="relative", phase=True)
    np.testing.assert_array_equal(X, Xf[trajf >= 20])


def test_plan_default_rules_give_way_to_one_rule_where_it_validates_better(data):
    """The plan mapping's default rules and the one-rule model are both trained, and the
    one of lower validation RMSE is kept (the report's ``rules_selection``); order 1's
    one rule is an affine map of the pair, which the synthetic set's trajectories (one
    common goal, a linear controller) nearly are; an explicit ``n_rules`` trains only
    that model."""
    chosen = {}
    for order in (0, 1):
        model, rep, hist = mappings.train_mapping(data, "plan", order=order, epochs=3)
        va = rep["rules_selection"]["validation_rmse"]
        assert set(va) == {str(mappings.PLAN_RULES), "1"}
        chosen[order] = rep["rules_selection"]["chosen"]
        assert chosen[order] == (1 if va["1"] < va[str(mappings.PLAN_RULES)] else mappings.PLAN_RULES)
        assert rep["n_rules"] == model.n_rules == chosen[order]
        assert min(hist.val_rmse) == pytest.approx(min(va.values()), rel=1e-12)
    # order 0's one rule is the mean trajectory, far from trajectories that follow their start
    assert chosen == {0: mappings.PLAN_RULES, 1: 1}
    _, rep, _ = mappings.train_mapping(data, "plan", n_rules=4, epochs=1)
    assert "rules_selection" not in rep
