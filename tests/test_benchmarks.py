"""The benchmark scripts' plumbing (results, JSON summary, plot) with the fast stand-in
solver: the figures themselves come from real runs (README), not from tests."""

import json
import os
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "benchmarks"))

FAKE = "jtraj.dataset.testing:fake_solve_batch"


def test_bench_dataset_writes_its_summary(tmp_path):
    import bench_dataset

    out = tmp_path / "out"
    summary = bench_dataset.main(["--quick", "--no-ipopt", "--workers", "1", "--solver", FAKE,
                                  "--out-dir", str(out)])
    with open(out / "bench_dataset.json") as f:
        saved = json.load(f)
    assert saved == json.loads(json.dumps(summary))
    (r,) = saved["results"]
    # --quick: one chunk of 64 pairs warms the worker, one more is timed
    assert r["batch"] == 64 and r["pairs"] == 128 and r["timed_pairs"] == 64
    assert r["pairs_per_s"] > 0 and r["h_max"] == pytest.approx(0.2)
    # the stand-in flags the pairs with sum(q_goal) > 1 as failures
    assert 0.0 < r["converged_fraction"] < 1.0
    assert saved["ipopt"] is None and (out / "bench_dataset.png").stat().st_size > 0
