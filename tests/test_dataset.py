"""jtraj.dataset: sampling, durable chunked store, resume (also after kill -9), Ray, views, CLI.

Most tests inject the fast stand-in solver ``jtraj.dataset.testing:fake_solve_batch`` so
that storage and resume logic are tested in seconds; ``test_real_solver_end_to_end``
runs ``jtraj.solve_batch`` on 8 pairs.
"""

import importlib
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest

from jtraj import dataset
from jtraj.cli import main as cli_main
from jtraj.dataset import sampling, store
from jtraj.dataset.build import H_MAX_FACTOR

from helpers import arm_urdf, catalogue

FAKE = "jtraj.dataset.testing:fake_solve_batch"
FAKE_CPUS = "jtraj.dataset.testing:fake_solve_batch_cpus"  # iterations: the solving process's CPUs
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def fake_spec(pairs=40, seed=3, batch=16, **kw):
    return dataset.make_spec("serial3", pairs, seed, N=kw.pop("N", 6), batch=batch, solver=kw.pop("solver", FAKE),
                             **kw)


def assert_same(a, b):
    assert sorted(a.keys()) == sorted(b.keys())
    for k in a:
        if k == "metadata":
            assert a[k]["identity"] == b[k]["identity"]
            continue
        np.testing.assert_array_equal(a[k], b[k], err_msg=k, strict=True)


# ----------------------------------------------------------------------------- sampling

def test_sampling_is_a_function_of_seed_and_pair_index():
    from jtraj import robots

    r = robots.get("serial3")
    d = sampling.Distribution()
    qs, qg = sampling.sample_pairs(r, d, 7, 0, 150)
    a = sampling.sample_pairs(r, d, 7, 0, 37)
    b = sampling.sample_pairs(r, d, 7, 37, 150)
    np.testing.assert_array_equal(np.concatenate([a[0], b[0]]), qs)
    np.testing.assert_array_equal(np.concatenate([a[1], b[1]]), qg)
    assert qs.shape == qg.shape == (150, 3)
    assert np.all(np.abs(qs) <= 1.2) and np.all(np.abs(qg - qs) <= 0.8)
    assert np.all(np.linalg.norm(qg - qs, axis=1) >= d.min_separation)
    other = sampling.sample_pairs(r, d, 8, 0, 150)[0]
    assert not np.allclose(other, qs)


def test_sampling_stays_inside_a_joint_box_without_piling_goals_on_its_faces():
    from jtraj import robots

    r = robots.get("serial3", q_min=-0.5, q_max=(0.3, 0.4, 0.5))
    qs, qg = sampling.sample_pairs(r, sampling.Distribution(), 0, 0, 200)
    lo, hi = np.array([-0.5] * 3), np.array([0.3, 0.4, 0.5])
    for q in (qs, qg):
        assert np.all(q >= lo) and np.all(q <= hi)
    # redrawn, not clipped: no goal on a face of the box (a clip put about a third there)
    assert not np.any((qg == lo) | (qg == hi))
    assert np.all(np.abs(qg - qs) <= 0.8)


def test_sampling_keeps_starts_and_goals_inside_path_constraints():
    """parallel3's box holds points where a leg is (nearly) stretched: its path
    constraints forbid them, and sampled pairs avoid them (checked by the leg ratios
    themselves); robots without path constraints draw the plain law (serial3: block 0
    drawn here by hand equals the sampler's pairs)."""
    import jax

    from jtraj import robots

    r = robots.get("parallel3")
    qs, qg = sampling.sample_pairs(r, sampling.Distribution(), 1, 0, 128)
    for q in (qs, qg):
        ratio = np.asarray(jax.vmap(r.leg_ratios)(q))
        assert np.all(ratio <= r.rho_max) and np.all(ratio >= r.rho_min)
        assert np.all(np.abs(q) <= 0.5)
    # the box corner (0.5, 0.5) is outside the constraints (a leg nearly stretched)
    assert not sampling.admissible(r, np.array([[0.5, 0.5], [0.5, -0.5]])).any()
    assert sampling.admissible(r, np.array([[0.0, 0.0]])).all()
    s3 = robots.get("serial3")
    rng = np.random.default_rng([3, 0])  # the law of block 0 by hand: no rejection but the separation
    u = rng.random((64, 2, 3))
    a = -1.2 + 2.4 * u[:, 0]
    g = a + 0.8 * (2 * u[:, 1] - 1)
    keep = np.linalg.norm(g - a, axis=1) >= 0.05
    qs, qg = sampling.sample_pairs(s3, sampling.Distribution(), 3, 0, int(keep.sum()))
    np.testing.assert_array_equal(qs, a[keep])
    np.testing.assert_array_equal(qg, g[keep])


def test_a_dataset_of_a_slow_joint_draws_pairs_it_can_move_in_time():
    """serial3 with a first joint of 0.05 rad/s covers at most 0.2 rad in N h_max = 4 s:
    most steps of the law (up to 0.8 rad) are infeasible on their face, and the dataset's
    distribution redraws them; the pairs it keeps are ones jtraj.Problem accepts. Robots
    whose every step fits keep the plain law and their identity."""
    import jax

    import jtraj

    build = importlib.import_module("jtraj.dataset.build")
    slow = build.make_spec("serial3", 64, 0, robot_params={"qd_max": [0.05, 3.0, 3.0]})
    assert slow.distribution.max_move_time == pytest.approx(20 * float(slow.robot_model().limits.h_max))
    assert slow.identity()["distribution"]["max_move_time"] == slow.distribution.max_move_time
    assert sampling.Distribution.from_record(slow.identity()["distribution"]) == slow.distribution
    robot = slow.robot_model()
    plain = sampling.sample_pairs(robot, sampling.Distribution(), 0, 0, 64)
    qs, qg = sampling.sample_pairs(robot, slow.distribution, 0, 0, 64)

    def refused(q0, q1):  # what jtraj.Problem and solve_batch refuse, per pair
        return np.asarray(jax.vmap(lambda a, b: jtraj.Problem(robot, a, b, N=20, validate=False)
                                   .infeasible_on_its_face())(q0, q1))

    assert refused(*plain).mean() > 0.5  # the plain law: mostly refused
    assert not refused(qs, qg).any()
    assert np.abs(qg - qs)[:, 0].max() <= 0.05 * 20 * float(robot.limits.h_max) + 1e-12
    assert np.abs(qg - qs)[:, 0].max() > 0.1  # the slow joint still moves
    default = build.make_spec("serial3", 64, 0)
    assert default.distribution.max_move_time is None
    assert "max_move_time" not in default.identity()["distribution"]


@pytest.mark.slow  # ~20 s: compiles the vmapped IK
def test_task_space_sampling_reaches_its_points():
    import jax

    from jtraj import robots

    r = robots.get("serial3")
    qs, qg = sampling.sample_pairs(r, sampling.Distribution(space="task"), 1, 0, 10)
    box = sampling.workspace_box(r)
    for q in (qs, qg):
        p = np.asarray(jax.vmap(r.forward_kinematics)(q))
        assert np.all(p >= box[0] - 1e-9) and np.all(p <= box[1] + 1e-9)
    p0 = np.asarray(jax.vmap(r.forward_kinematics)(qs))
    p1 = np.asarray(jax.vmap(r.forward_kinematics)(qg))
    assert np.all(np.linalg.norm(p1 - p0, axis=1) >= 0.05)


# ----------------------------------------------------------------------------- build / load

def test_build_load_keeps_every_pair_with_its_status(tmp_path):
    spec = fake_spec(pairs=40, batch=16)
    stats = dataset.build(spec, str(tmp_path / "d"), progress=False)
    assert stats["complete"] and stats["pairs_done"] == 40
    data = dataset.load(str(tmp_path / "d"))
    P, N, n = 40, 6, 3
    shapes = {"q_start": (P, n), "q_goal": (P, n), "converged": (P,), "status": (P,), "q": (P, N + 1, n),
              "qd": (P, N + 1, n), "v": (P, N, n), "tau": (P, N, n), "h": (P, N), "T": (P,), "cost": (P,),
              "max_violation": (P,), "iterations": (P,), "energy": (P,)}
    for k, s in shapes.items():
        assert data[k].shape == s, k
    np.testing.assert_array_equal(data["index"], np.arange(P))
    np.testing.assert_array_equal(data["converged"], data["status"] == 0)
    assert 0 < data["converged"].sum() < P  # failures are kept, flagged
    qs, qg = sampling.sample_pairs(spec.robot_model(), spec.distribution, spec.seed, 0, P)
    np.testing.assert_array_equal(data["q_start"], qs)
    md = data["metadata"]
    for key in ("robot", "limits", "N", "seed", "sampling", "versions", "created", "identity"):
        assert key in md
    assert md["identity"]["weights"]["energy"] == 0.1 and md["versions"]["jax"]
    assert md["identity"]["solver_options"]["max_iter"] > 0
    assert data.complete and len(data.chunks) == 3


def test_resume_equals_uninterrupted_run(tmp_path):
    spec = fake_spec(pairs=50, batch=16)
    dataset.build(spec, str(tmp_path / "full"), progress=False)
    s1 = dataset.build(spec, str(tmp_path / "part"), progress=False, max_chunks=2)
    assert not s1["complete"]
    with pytest.raises(ValueError, match="incomplete"):
        dataset.load(str(tmp_path / "part"))
    part = dataset.load(str(tmp_path / "part"), partial=True)
    np.testing.assert_array_equal(part["index"], np.arange(32))
    # a stale temp file from a killed writer is ignored and removed
    stale = tmp_path / "part" / "chunks" / "chunk-000002.h5.tmp-99999"
    stale.write_bytes(b"garbage")
    s2 = dataset.build(spec, str(tmp_path / "part"), progress=False)
    assert s2["complete"] and s2["new_pairs"] == 18 and not stale.exists()
    assert_same(dataset.load(str(tmp_path / "full")), dataset.load(str(tmp_path / "part")))
    s3 = dataset.build(spec, str(tmp_path / "part"), progress=False)  # nothing left to do
    assert s3["new_pairs"] == 0


def test_resume_after_a_code_change_warns(tmp_path, monkeypatch):
    build_mod = sys.modules["jtraj.dataset.build"]  # (the package attribute `build` is the function)

    spec = fake_spec(pairs=32, batch=16)
    out = str(tmp_path / "d")
    dataset.build(spec, out, progress=False, max_chunks=1)
    monkeypatch.setattr(build_mod, "_source_hash", lambda: "edited")
    messages = []
    dataset.build(spec, out, progress=False, log=messages.append)
    assert any("warning" in m and "jtraj_source" in m for m in messages), messages


def test_run_killed_while_writing_its_manifest_restarts(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    (out / ".lock").write_bytes(b"")
    (out / "manifest.json.tmp-4242").write_bytes(b'{"format": "jtraj-da')
    s = dataset.build(fake_spec(pairs=16, batch=8), str(out), progress=False)
    assert s["complete"] and not (out / "manifest.json.tmp-4242").exists()
    assert dataset.load(str(out))["q"].shape[0] == 16


def test_different_parameters_are_refused_and_nothing_changes(tmp_path):
    out = str(tmp_path / "d")
    dataset.build(fake_spec(pairs=20, batch=8), out, progress=False)
    before = {p: os.stat(os.path.join(out, p)).st_mtime_ns for p in ("manifest.json", "chunks/chunk-000000.h5")}
    for kw, word in ((dict(seed=4), "seed"), (dict(batch=4), "batch"), (dict(N=7), "N"),
                     (dict(weights="time=1,energy=1"), "weights"), (dict(pairs=21), "pairs")):
        args = dict(pairs=20, batch=8, seed=3)
        args.update(kw)
        with pytest.raises(ValueError, match=f"different parameters.*{word}"):
            dataset.build(fake_spec(**args), out, progress=False)
    after = {p: os.stat(os.path.join(out, p)).st_mtime_ns for p in before}
    assert before == after


def test_bad_input_is_refused_before_compute(tmp_path):
    with pytest.raises(ValueError, match="unknown robot"):
        dataset.make_spec("nosuchbot", 10, 0)
    for pairs in (0, -3):
        with pytest.raises(ValueError, match="pairs"):
            dataset.make_spec("serial3", pairs, 0)
    with pytest.raises(ValueError, match="batch"):
        dataset.make_spec("serial3", 10, 0, batch=0)
    with pytest.raises(ValueError, match="space"):
        dataset.make_spec("serial3", 10, 0, space="cartesian")
    with pytest.raises(ValueError, match="efforts"):
        dataset.make_spec("serial3", 10, 0, efforts="ends")
    # the effort bound is part of a dataset's identity (a resume with another one is
    # refused), and absent where it is the default, as in datasets written before it existed
    assert "efforts" not in dataset.make_spec("serial3", 10, 0).identity()
    assert dataset.make_spec("serial3", 10, 0, efforts="intervals").identity()["efforts"] == "intervals"
    # so are the solver options added since (the PBM inequality term): a dataset started
    # before them resumes, one built with them differs
    from jtraj.solver import PBM_SETTINGS

    plain = dataset.make_spec("serial3", 10, 0).identity()["solver_options"]
    assert "max_iter" in plain
    assert not {"inequality_penalty", "pbm_init", "pbm_ratio", "pbm_fallback_iter", "detect_min_viol",
                 "pbm_inner_tol_ratio"} & set(plain)
    pbm = dataset.make_spec("serial3", 10, 0, options=PBM_SETTINGS).identity()["solver_options"]
    assert pbm["inequality_penalty"] == "pbm" and pbm["detect_min_viol"] == 0.01
    assert "pbm_init" not in pbm  # at its default
    spec = fake_spec(pairs=8, batch=8)
    f = tmp_path / "file.txt"
    f.write_text("precious")
    with pytest.raises(ValueError, match="not a directory"):
        dataset.build(spec, str(f), progress=False)
    assert f.read_text() == "precious"
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a jtraj dataset"):
        dataset.build(spec, str(other), progress=False)
    assert os.listdir(other) == ["notes.txt"]
    with pytest.raises(ValueError, match="cannot"):
        dataset.build(spec, str(f / "sub"), progress=False)
    with pytest.raises(ValueError, match="cannot"):
        dataset.build(spec, "/proc/jtraj-dataset-test", progress=False)
    with pytest.raises(ValueError, match="does not exist"):
        dataset.build(spec, str(tmp_path / "missing" / "d"), progress=False)
    pytest.importorskip("ray")
    with pytest.raises(ValueError, match="does not answer"):
        dataset.build(spec, str(tmp_path / "r"), ray="127.0.0.1:9", progress=False)
    assert not (tmp_path / "r").exists()


def test_ray_missing_gives_a_clear_error(tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def no_ray(name, *a, **k):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(ValueError, match="pip install"):
        dataset.build(fake_spec(pairs=8, batch=8), str(tmp_path / "d"), ray="auto", progress=False)
    assert not (tmp_path / "d").exists()


def test_chunk_files_are_checksummed_and_tied_to_their_dataset(tmp_path):
    import h5py

    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    dataset.build(fake_spec(pairs=16, batch=8), a, progress=False)
    dataset.build(fake_spec(pairs=16, batch=8, seed=4), b, progress=False)
    with h5py.File(os.path.join(a, "chunks", "chunk-000000.h5")) as f:
        assert f["q"].fletcher32
    # a chunk copied from another dataset is not accepted as finished
    os.replace(os.path.join(b, "chunks", "chunk-000001.h5"), os.path.join(a, "chunks", "chunk-000001.h5"))
    with pytest.raises(ValueError, match="another dataset"):
        dataset.load(a)["q"]
    s = dataset.build(fake_spec(pairs=16, batch=8), a, progress=False)
    assert s["new_pairs"] == 8
    assert dataset.load(a)["q"].shape == (16, 7, 3)


def test_field_missing_from_older_chunks_reads_as_nan(tmp_path):
    """A dataset resumed with a newer jtraj can hold chunks without a field that later
    chunks have (kkt_error was added so): such rows read as NaN, the others unchanged;
    a solver that does not report kkt_error leaves NaN."""
    import h5py

    a = str(tmp_path / "a")
    dataset.build(fake_spec(pairs=16, batch=8), a, progress=False)
    full = dataset.load(a)
    assert np.all(np.isnan(full["kkt_error"]))  # the fake solver does not report it
    assert "  KKT error: -" in dataset.summary(a)
    viol = full["max_violation"].copy()
    chunk0 = os.path.join(a, "chunks", "chunk-000000.h5")
    with h5py.File(chunk0, "a") as f:
        del f["max_violation"]
    # a field removed from a chunk with checksums: corrupt
    with pytest.raises(ValueError, match="chunk-000000.h5: corrupt chunk .*list of fields"):
        dataset.load(a)
    with h5py.File(chunk0, "a") as f:  # as if chunk 0 had been written before the field and the checksums existed
        for k in ("digest", "integrity"):
            del f.attrs[k]
        for k in f.keys():
            del f[k].attrs["sha256"]
    data = dataset.load(a)
    assert "max_violation" in data
    assert np.all(np.isnan(data["max_violation"][:8]))
    np.testing.assert_array_equal(data["max_violation"][8:], viol[8:])
    np.testing.assert_array_equal(data["q"], full["q"])


# ----------------------------------------------------------------------------- views

def test_views_rows_and_trajectory_index(tmp_path):
    import jax

    out = str(tmp_path / "d")
    dataset.build(fake_spec(pairs=24, batch=8), out, progress=False)
    data = dataset.load(out)
    conv = np.flatnonzero(data["converged"])
    N, n = 6, 3
    X, Y, traj = dataset.views.nefotc(data)
    assert X.shape == (len(conv) * N, 2 * n) and Y.shape == (len(conv) * N, n)
    np.testing.assert_array_equal(np.unique(traj), conv)
    i = conv[1]
    rows = np.flatnonzero(traj == i)
    np.testing.assert_array_equal(X[rows, :n], data["q"][i, :-1])
    np.testing.assert_array_equal(Y[rows], data["tau"][i])
    X, Y, traj = dataset.views.nefumop(data)
    assert X.shape == (len(conv) * N, 4) and Y.shape == (len(conv) * N, n + 1)
    rob = dataset.views.robot_of(data)
    k = 3
    p, pd = jax.jvp(rob.forward_kinematics, (data["q"][i, k],), (data["qd"][i, k],))
    np.testing.assert_allclose(X[rows[k]], np.concatenate([p, pd]), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(Y[rows[k]], np.append(data["tau"][i, k], data["h"][i, k]))
    X, Y, traj = dataset.views.nefik(data, converged_only=False)
    assert X.shape == (24 * (N + 1), 2) and Y.shape == (24 * (N + 1), n)
    np.testing.assert_array_equal(traj, np.repeat(np.arange(24), N + 1))


# ----------------------------------------------------------------------------- CLI

def test_default_chunk_size_grows_with_the_dataset():
    from jtraj.dataset.build import default_batch

    sizes = (1, 96, 1024, 2048, 3000, 4096, 10_000, 10**6)
    assert [default_batch(p, accelerator=False) for p in sizes] == [64, 64, 64, 128, 128, 256, 256, 256]
    assert [default_batch(p, accelerator=True) for p in sizes] == [256, 256, 256, 512, 512, 1024, 2304, 4096]
    assert fake_spec(pairs=20, batch=None).batch == 20  # never padded beyond P
    assert fake_spec(pairs=5000, batch=None).batch == 256


def _cli(*args):
    return cli_main(["dataset", *args])


def test_cli_build_info_plot(tmp_path, capsys):
    out = str(tmp_path / "A")
    assert _cli("--robot", "serial3", "--pairs", "20", "--seed", "5", "--out", out, "--N", "6", "--batch", "8",
                "--solver", FAKE, "--no-progress") == 0
    # resumes, nothing to do: without --batch the dataset's own chunk size is kept (the
    # default for 20 pairs would be 20 and be refused as a different dataset)
    assert _cli("build", "--robot", "serial3", "--pairs", "20", "--seed", "5", "--out", out, "--N", "6",
                "--solver", FAKE, "--no-progress") == 0
    assert dataset.load(out)["metadata"]["batch"] == 8
    capsys.readouterr()
    assert _cli("info", out) == 0
    text = capsys.readouterr().out
    assert "serial3" in text and "pairs 20/20" in text and "converged" in text
    fig = str(tmp_path / "fig.png")
    assert _cli("plot", out, "--out", fig) == 0
    assert os.path.getsize(fig) > 10_000
    assert _cli("--robot", "serial3", "--pairs", "0", "--out", str(tmp_path / "B")) == 2
    assert _cli("--robot", "nope", "--pairs", "3", "--out", str(tmp_path / "B")) == 2
    assert _cli("info", str(tmp_path)) == 2
    assert _cli("frobnicate", out) == 2
    err = capsys.readouterr().err
    assert "pairs must be" in err and "unknown robot" in err and "not a jtraj dataset" in err
    assert not (tmp_path / "B").exists()


def test_kill_9_mid_run_then_resume_equals_uninterrupted(tmp_path):
    args = ["--robot", "serial3", "--pairs", "64", "--seed", "5", "--N", "6", "--batch", "8", "--solver", FAKE,
            "--no-progress"]
    ref = str(tmp_path / "A")
    assert _cli(*args, "--out", ref) == 0
    out = str(tmp_path / "B")
    env = dict(os.environ, JTRAJ_FAKE_SOLVER_DELAY="0.4")
    proc = subprocess.Popen([sys.executable, "-m", "jtraj.cli", "dataset", *args, "--out", out], env=env, cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first = os.path.join(out, "chunks", "chunk-000000.h5")
    deadline = time.time() + 120
    while not os.path.exists(first) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.02)
    time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = store.finished_chunks(out)
    assert 1 <= len(done) < 8, done  # killed mid-run
    assert _cli(*args, "--out", out) == 0
    assert_same(dataset.load(ref), dataset.load(out))
    with open(os.path.join(out, "manifest.json")) as f:
        assert json.load(f)["identity"]["pairs"] == 64


def test_local_worker_processes_equal_this_process(tmp_path):
    spec = fake_spec(pairs=40, batch=8)
    dataset.build(spec, str(tmp_path / "one"), workers=1, progress=False)
    s = dataset.build(spec, str(tmp_path / "two"), workers=2, progress=False)
    assert s["complete"] and s["new_pairs"] == 40
    assert_same(dataset.load(str(tmp_path / "one")), dataset.load(str(tmp_path / "two")))
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="workers"):
            dataset.build(spec, str(tmp_path / "bad"), workers=bad, progress=False)
    assert not os.path.exists(tmp_path / "bad")


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs several CPUs (Linux)")
def test_every_chunk_is_solved_on_one_cpu(tmp_path):
    """XLA's rounding depends on how many CPUs the solving process may use, so by default
    every chunk is solved in a process restricted to one, also a resumed run's single
    last chunk (solved in the unpinned driver, it would land 1e-12 apart from the
    workers' with the real solver at N = 20). The stand-in solver reports the CPUs of the
    process that solved each pair as its ``iterations``."""
    spec = fake_spec(pairs=24, batch=8, solver=FAKE_CPUS)
    out = str(tmp_path / "d")
    dataset.build(spec, out, progress=False, max_chunks=1)  # one chunk: one worker
    dataset.build(spec, out, progress=False, max_chunks=1)  # resumed, one chunk again
    dataset.build(spec, out, progress=False)  # the last one
    np.testing.assert_array_equal(dataset.load(out)["iterations"], np.ones(24, np.int32))
    # workers=1 solves in this process, as documented (on all of its CPUs here)
    dataset.build(spec, str(tmp_path / "here"), progress=False, workers=1)
    assert set(dataset.load(str(tmp_path / "here"))["iterations"]) == {len(os.sched_getaffinity(0))}


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs several CPUs (Linux)")
def test_concurrent_workers_claim_different_cpus(tmp_path):
    """jtraj._cpu.claim_one_cpu (Ray's workers): two live processes get two CPUs, and a
    CPU is free again once its holder has exited."""
    code = ("import os, sys; from jtraj._cpu import claim_one_cpu; "
            "print(claim_one_cpu(), sorted(os.sched_getaffinity(0)), flush=True); sys.stdin.read()")
    env = dict(os.environ, TMPDIR=str(tmp_path))  # its own lock folder

    def start():
        return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                text=True, env=env, cwd=ROOT)

    def claimed(proc):
        cpu, affinity = proc.stdout.readline().split(" ", 1)
        assert json.loads(affinity) == [int(cpu)]  # pinned to the CPU it claimed
        return int(cpu)

    first, second = start(), start()
    try:
        a, b = claimed(first), claimed(second)
        assert a != b
        first.communicate("")  # exits: its lock goes with it
        third = start()
        assert claimed(third) == a
        third.communicate("")
    finally:
        for p in (first, second):
            if p.poll() is None:
                p.communicate("")


@pytest.mark.slow  # ~35 s on 2 cores: starts a local Ray instance
@pytest.mark.filterwarnings("ignore:os.fork")
def test_ray_local_cluster_two_workers_equals_single_process(tmp_path):
    pytest.importorskip("ray")
    # the stand-in solver reports each solving process's CPUs as `iterations`: Ray's
    # workers claim one CPU each, as the local ones are pinned (identical rounding)
    spec = fake_spec(pairs=40, batch=8, solver=FAKE_CPUS)
    dataset.build(spec, str(tmp_path / "single"), progress=False)
    s = dataset.build(spec, str(tmp_path / "ray"), ray="local:2", progress=False)
    assert s["complete"]
    assert_same(dataset.load(str(tmp_path / "single")), dataset.load(str(tmp_path / "ray")))
    np.testing.assert_array_equal(dataset.load(str(tmp_path / "ray"))["iterations"], np.ones(40, np.int32))


# ----------------------------------------------------------------------------- real solver

def test_sampling_period_bound_is_part_of_the_dataset(tmp_path):
    """The dataset's h_max: twice the robot's by default, the robot's own on request, a
    number otherwise; it reaches the solved problems and the metadata, and is refused
    when not above h_min."""
    from jtraj import robots

    own = robots.get("serial3").limits
    auto = fake_spec(pairs=8, batch=8)
    assert auto.h_max == H_MAX_FACTOR * own.h_max
    assert auto.robot_model().limits.h_max == auto.h_max
    assert fake_spec(pairs=8, batch=8, h_max="robot").robot_model().limits.h_max == own.h_max
    spec = fake_spec(pairs=8, batch=8, h_max=0.13)
    dataset.build(spec, str(tmp_path / "d"), progress=False)
    data = dataset.load(str(tmp_path / "d"))
    assert data["metadata"]["limits"]["h_max"] == 0.13
    assert data["metadata"]["identity"]["robot_model"]["limits"]["h_max"] == 0.13
    assert "h in [0.005, 0.13] s" in dataset.summary(str(tmp_path / "d"))
    # another bound into the same path is another dataset: refused
    with pytest.raises(ValueError):
        dataset.build(fake_spec(pairs=8, batch=8, h_max=0.14), str(tmp_path / "d"), progress=False)
    for bad in (own.h_min, -1.0, float("nan"), "fast", True):
        with pytest.raises(ValueError, match="h_max"):
            fake_spec(pairs=8, batch=8, h_max=bad)


@pytest.mark.slow
def test_real_solver_end_to_end(tmp_path):
    import jtraj

    spec = dataset.make_spec("serial3", 8, 11, N=10, batch=8)
    out = str(tmp_path / "d")
    # in this process, as the reference solve below (test_every_chunk_is_solved_on_one_cpu
    # covers the default, a pinned worker process)
    stats = dataset.build(spec, out, progress=False, workers=1)
    assert stats["complete"]
    data = dataset.load(out)
    assert data["q"].shape == (8, 11, 3) and data["tau"].shape == (8, 10, 3)
    np.testing.assert_array_equal(data["converged"], data["status"] == 0)
    assert set(np.unique(data["status"])) <= {int(s) for s in jtraj.Status}
    ref = jtraj.solve_batch(spec.robot_model(), data["q_start"], data["q_goal"], N=10,
                            weights=jtraj.Weights.parse("time=1,energy=0.1"))
    np.testing.assert_array_equal(np.asarray(ref.q), data["q"])
    np.testing.assert_array_equal(np.asarray(ref.status), data["status"])
    np.testing.assert_allclose(data["q"][:, 0], data["q_start"], atol=1e-12)
    assert data["metadata"]["identity"]["solver"] == "jtraj:solve_batch"
    # the optimality measure of every pair is kept (finite with the real solver)
    np.testing.assert_array_equal(np.asarray(ref.kkt_error), data["kkt_error"])
    assert np.all(np.isfinite(data["kkt_error"]))
    sel = data["kkt_error"][data["converged"]]
    assert len(sel) >= 5  # measured: 6 of 8 at N = 10
    assert f"KKT error: median {np.median(sel):.4g}" in dataset.summary(out)
    # every pair flagged converged passes the independent NumPy + Pinocchio re-simulation
    V = pytest.importorskip("jtraj_peers.verify")
    for i in np.flatnonzero(data["converged"]):
        r = V.verify(data["q_start"][i], data["q_goal"][i], data["v"][i], data["h"][i], h_max=spec.h_max,
                     weights=(1.0, 0.1, 0.0))
        assert r["ok"], (i, r["goal_error"], r["max_rel_violation"])
        assert r["cost"] == pytest.approx(float(data["cost"][i]), rel=1e-9)


@pytest.mark.slow  # compiles the solver at N = 20 in worker processes
def test_real_solver_resumed_last_chunk_equals_uninterrupted_run(tmp_path):
    """The issue's check (a run killed with one chunk left, then resumed) with the real
    solver at N = 20, where XLA's rounding depends on the CPUs of the solving process:
    a last chunk solved in the unpinned driver would land 1e-12 off."""
    spec = dataset.make_spec("serial3", 16, 2, N=20, batch=8)
    dataset.build(spec, str(tmp_path / "a"), progress=False)
    dataset.build(spec, str(tmp_path / "b"), progress=False, max_chunks=1)
    dataset.build(spec, str(tmp_path / "b"), progress=False)
    assert_same(dataset.load(str(tmp_path / "a")), dataset.load(str(tmp_path / "b")))


@pytest.mark.slow  # compiles the solver in each of the 2 Ray workers
@pytest.mark.filterwarnings("ignore:os.fork")
def test_ray_real_solver_equals_single_process(tmp_path):
    pytest.importorskip("ray")
    # N = 20: at N = 10 the rounding does not depend on the solving process's CPUs
    spec = dataset.make_spec("serial3", 16, 2, N=20, batch=8)
    dataset.build(spec, str(tmp_path / "single"), progress=False)
    dataset.build(spec, str(tmp_path / "ray"), ray="local:2", progress=False)
    assert_same(dataset.load(str(tmp_path / "single")), dataset.load(str(tmp_path / "ray")))


def test_progress_bar_counts_pairs_inside_a_chunk(tmp_path, capsys, monkeypatch):
    """The bar moves while a chunk is solved (the solver's progress), not only when a
    chunk ends."""
    monkeypatch.setattr("jtraj._progress.live", lambda: True)  # as in a terminal
    monkeypatch.setenv("JTRAJ_FAKE_SOLVER_PAIR_DELAY", "0.25")
    dataset.build(fake_spec(pairs=16, batch=8), str(tmp_path / "d"), progress=True, workers=1)
    err = capsys.readouterr().err.replace("\r", "\n")
    counts = [int(m) for m in re.findall(r"\| *(\d+)/16 ", err)]
    assert set(counts) - {0, 8, 16}, err  # a count inside a chunk
    assert counts[-1] == 16 and counts == sorted(counts), err  # never backwards


def test_progress_bar_in_a_log_redraws_once_a_minute(tmp_path, capsys, monkeypatch):
    """Where stderr is a file or a pipe (not watched live) the bar is drawn at its start
    and its end, and in between once every jtraj._progress.LOG_INTERVAL seconds: here,
    a build of a few seconds, never in between (a terminal redraws every second and at
    every chunk: the tests above)."""
    monkeypatch.setattr("jtraj._progress.live", lambda: False)
    monkeypatch.setenv("JTRAJ_FAKE_SOLVER_PAIR_DELAY", "0.15")
    dataset.build(fake_spec(pairs=16, batch=4), str(tmp_path / "d"), progress=True, workers=1)
    err = capsys.readouterr().err.replace("\r", "\n")
    counts = [int(m) for m in re.findall(r"\| *(\d+)/16 ", err)]
    assert counts[0] == 0 and counts[-1] == 16 and len(counts) <= 3, err


def test_training_progress_in_a_log_redraws_once_a_minute(capsys, monkeypatch):
    """The ANFIS training bar likewise: in a log, not once per epoch."""
    from jtraj import mappings

    data = mappings.synthetic_dataset(P=24, N=10, seed=0)
    monkeypatch.setattr("jtraj._progress.live", lambda: False)
    hist = mappings.train_mapping(data, "nefotc", n_rules=4, epochs=60, progress=True)[2]
    drawn = capsys.readouterr().err.replace("\r", "\n").count("/60 [")
    assert hist.epochs >= 10 and 1 <= drawn <= 2, (hist.epochs, drawn)  # (a redraw per epoch: one each)


def test_worker_progress_files(tmp_path, monkeypatch):
    """The worker processes' side of the bar's progress: one file per chunk in flight,
    summed, dropped when the chunk is done, the folder removed at the end."""
    from jtraj._testing import DatasetProgress

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    progress = DatasetProgress(files=True)
    assert os.path.dirname(progress.dir) == str(tmp_path)
    DatasetProgress.write(progress.dir, 3, 5)
    DatasetProgress.write(progress.dir, 4, 2)
    DatasetProgress.write(progress.dir, 3, 7)
    assert progress.partial() == 9
    progress.done(3)
    assert progress.partial() == 2
    progress.close()
    assert os.listdir(tmp_path) == []


def test_progress_bar_says_compiling_until_the_first_chunk(tmp_path, capsys, monkeypatch):
    """The first chunk waits for the solver's compilation: the bar says so (its clock
    running), then counts pairs."""
    import importlib

    build_mod = importlib.import_module("jtraj.dataset.build")  # (jtraj.dataset.build is the function)
    monkeypatch.setattr("jtraj._progress.live", lambda: True)  # as in a terminal
    monkeypatch.setenv("JTRAJ_FAKE_SOLVER_DELAY", "1.5")
    dataset.build(fake_spec(pairs=16, batch=8), str(tmp_path / "d"), progress=True, workers=1)
    err = capsys.readouterr().err.replace("\r", "\n")
    first = [ln for ln in err.splitlines() if "0/16" in ln]
    assert first and all(ln.startswith(build_mod.COMPILING) for ln in first), err
    assert any("[00:01<" in ln for ln in first), err  # redrawn while waiting
    assert any(ln.startswith("dataset: 100%") and "16/16" in ln for ln in err.splitlines()), err
    # nothing left to solve: no compiling label
    dataset.build(fake_spec(pairs=16, batch=8), str(tmp_path / "d"), progress=True, workers=1)
    assert build_mod.COMPILING not in capsys.readouterr().err


@pytest.mark.parametrize("name", catalogue(slow=("gough_stewart", "kinova", "so100", "ur10", "ur5")))
def test_every_robot_samples_admissible_pairs_and_stores_them(tmp_path, name):
    """The robot catalogue through sampling and storage (the stand-in solver): every pair
    inside the joint box and admissible as jtraj.Problem requires, separated, the same
    pairs on a second build (of the spatial robots, panda by default and the others with
    -m slow: each compiles its own kinematics)."""
    from jtraj import robots

    spec = dataset.make_spec(name, 8, 2, N=6, batch=8, solver=FAKE)
    dataset.build(spec, str(tmp_path / "a"), progress=False, workers=1)
    data = dataset.load(str(tmp_path / "a"))
    robot = robots.get(name)
    for q in (data["q_start"], data["q_goal"]):
        assert q.shape == (8, robot.n) and np.all(np.isfinite(q))
        assert np.all(sampling.admissible(robot, q))
        if robot.limits.q_min is not None:
            lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
            assert np.all(q >= lo - 1e-12) and np.all(q <= hi + 1e-12)
    assert np.all(np.linalg.norm(data["q_goal"] - data["q_start"], axis=1) >= 0.05)
    dataset.build(spec, str(tmp_path / "b"), progress=False, workers=1)
    np.testing.assert_array_equal(dataset.load(str(tmp_path / "b"))["q_goal"], data["q_goal"])


def test_urdf_arm_dataset_trains_and_queries_without_its_file(tmp_path, capsys):
    """``jtraj dataset --urdf``: the dataset keeps the file's text and tip link, so the
    dataset's robot, a model trained on it and ``jtraj query`` rebuild the arm after the
    file is gone; the same file resumes, another tip link is refused (the stand-in solver)."""
    from jtraj import robots
    from jtraj.dataset import views
    from jtraj.online import Planner

    urdf = tmp_path / "arm.urdf"
    urdf.write_text(arm_urdf())
    out = tmp_path / "d"
    build = ["dataset", "--urdf", str(urdf), "--tip-link", "tool", "--pairs", "24", "--batch", "12", "--N", "6",
             "--out", str(out), "--solver", FAKE, "--workers", "1", "--no-progress", "--robot-param", "qdd_max=5",
             "--robot-param", "tau_max=30,20"]
    assert cli_main(build) == 0
    arm = robots.from_urdf(str(urdf), tip_link="tool")
    assert arm.n == 2 and arm.joint_names == ("shoulder", "elbow")
    assert cli_main(build) == 0 and "0 new pairs" in capsys.readouterr().out  # the same file resumes
    assert cli_main(build[:3] + build[5:-4]) == 2  # the default tip (the gripper): another arm
    assert "different parameters" in capsys.readouterr().err
    assert cli_main(["dataset", "info", str(out)]) == 0
    assert ("robot arm3 (n = 2; a URDF arm, tip link tool; qdd_max = 5.0, tau_max = [30.0, 20.0])"
            in capsys.readouterr().out)
    assert cli_main(build[:-2]) == 2 and "different parameters" in capsys.readouterr().err  # tau_max left out
    urdf.unlink()
    data = dataset.load(str(out))
    robot = views.robot_of(data)
    assert (robot.name, robot.joint_names) == ("arm3", arm.joint_names)
    np.testing.assert_array_equal(robot.joint_translation, arm.joint_translation)
    assert float(robot.limits.h_max) == H_MAX_FACTOR * float(arm.limits.h_max)
    np.testing.assert_array_equal(robot.limits.qdd_max, [5.0, 5.0])
    np.testing.assert_array_equal(robot.limits.tau_max, [30.0, 20.0])
    model = tmp_path / "plan.anfis"
    assert cli_main(["train", "--data", str(out), "--mapping", "plan", "--order", "0", "--rules", "2",
                     "--epochs", "2", "--out", str(model), "--no-progress"]) == 0
    printed = capsys.readouterr().out  # the fit against its baselines; the plan mapping is never mirrored
    assert "ratio to linear" in printed and "below 1 the model beats a linear fit" in printed
    assert "mirror" not in printed
    planner = Planner(str(model))
    assert planner.robot.joint_names == arm.joint_names and float(planner.robot.limits.h_max) == float(
        robot.limits.h_max)
    np.testing.assert_array_equal(planner.robot.limits.tau_max, [30.0, 20.0])
    answer = tmp_path / "q.json"
    assert cli_main(["query", "--model", str(model), "--start", "0.1,-0.2", "--goal", "0.5,0.3",
                     "--json", str(answer)]) == 0
    result = json.loads(answer.read_text())
    assert result["feasible"] is True and np.allclose(result["q"][-1], [0.5, 0.3], atol=1e-6)
    assert cli_main(["query", "--model", str(model), "--start", "0.1", "--goal", "0.5,0.3"]) == 2
    assert "--start must have 2 values for this robot (shoulder, elbow), got 1" in capsys.readouterr().err


def test_urdf_dataset_bad_input_names_the_option(tmp_path, capsys):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(arm_urdf())
    text = tmp_path / "notes.txt"
    text.write_text("not xml")
    base = ["--pairs", "4", "--out", str(tmp_path / "d"), "--solver", FAKE]
    cases = [(["--urdf", str(urdf), "--robot", "panda"], "give --robot (a built-in robot) or --urdf"),
             (["--robot", "panda", "--tip-link", "tool"], "--tip-link needs --urdf"),
             (["--urdf", str(tmp_path / "missing.urdf")], "--urdf: cannot read"),
             (["--urdf", str(text)], "is not a URDF file"),
             (["--urdf", str(urdf), "--tip-link", "hand"], "--tip-link 'hand' is not a link"),
             (["--robot", "panda", "--robot-param", "qdd_max"], "--robot-param must look like NAME=VALUE"),
             (["--robot", "panda", "--robot-param", "qdd_max=fast"], "--robot-param qdd_max: expected a number"),
             (["--robot", "panda", "--robot-param", "mass=1"], "--robot-param: unknown override 'mass'"),
             (["--robot", "panda", "--robot-param", "tau_max=1,2"], "tau_max must have shape (7,), got (2,)"),
             (["--robot", "panda", "--robot-param", "h_max=0.3"], "h_max is the dataset's own option (--h-max)"),
             ([], "build needs --robot (or --urdf)")]
    for args, message in cases:
        assert cli_main(["dataset", *args, *base]) == 2, args
        assert message in capsys.readouterr().err, args
    assert not (tmp_path / "d").exists()
    with pytest.raises(ValueError, match="give robot .* or urdf"):
        dataset.make_spec("panda", 4, 0, urdf=str(urdf))
    with pytest.raises(ValueError, match="tip_link needs urdf"):
        dataset.make_spec("panda", 4, 0, tip_link="tool")
    spec = dataset.make_spec(None, 4, 0, urdf=arm_urdf("from_text"), solver=FAKE)  # the XML text itself
    assert spec.robot == "from_text" and spec.robot_model().n == 3
    # a (n, 3) parameter: recorded as nested tuples, so the spec stays hashable (the robot cache's key)
    com = np.full((3, 3), 0.05)
    spec = dataset.make_spec(None, 4, 0, urdf=arm_urdf(), robot_params={"com": com}, solver=FAKE)
    assert hash(spec) and np.array_equal(spec.robot_model().com, com)
    with pytest.raises(ValueError, match="robot_params must be a dict"):
        dataset.make_spec("panda", 4, 0, robot_params=[("qdd_max", 5.0)])
