"""Resources: the prefix and suffix sums of the decoupled recursion against NumPy's
cumulative sums on both sides of their switch to ``cumsum``, and the memory estimate's
refusal (a ValueError naming N or the batch size, before anything is traced; the CLI's
bad-input exit code)."""

import jax
import numpy as np
import pytest

import jtraj
from jtraj import _resources
from jtraj import transcription as T
from jtraj import _testing


@pytest.mark.parametrize("N", [5, T.recursion.TRI_MAX, T.recursion.TRI_MAX + 1, 150])
def test_prefix_and_suffix_sums_match_numpy(N):
    rng = np.random.default_rng(N)
    X = rng.standard_normal((N, 3, 2))
    ref = np.concatenate([np.zeros((1, 3, 2)), np.cumsum(X, axis=0)])
    np.testing.assert_allclose(np.asarray(_testing.prefix_sums(X)), ref, rtol=1e-13, atol=1e-13)
    Y = rng.standard_normal((N + 1, 4))
    ref = np.array([Y[j + 1:].sum(axis=0) for j in range(N)])
    np.testing.assert_allclose(np.asarray(_testing.suffix_sums(Y)), ref, rtol=1e-13, atol=1e-12)


def test_prefix_sums_stay_linear_under_jacfwd():
    # the Jacobian of the prefix sums beyond the switch: its program holds no
    # (nz, N + 1, N) intermediate (XLA's temporary buffers stay within a few Jacobians)
    N = 400
    f = jax.jit(jax.jacfwd(lambda x: _testing.prefix_sums(x[:, None] * np.ones((1, 3)))))
    mem = f.lower(np.zeros(N)).compile().memory_analysis()
    if mem is None:
        pytest.skip("no memory analysis on this backend")
    jac_bytes = (N + 1) * 3 * N * 8
    assert mem.temp_size_in_bytes <= 4 * jac_bytes, (mem.temp_size_in_bytes, jac_bytes)


def test_estimate_grows_and_refuses_naming_N(monkeypatch):
    small, big = _resources.estimate(20, 3), _resources.estimate(2000, 3)
    assert big.memory_bytes > small.memory_bytes
    assert big.hlo_ops == small.hlo_ops  # the programs do not grow with N
    monkeypatch.setenv("JTRAJ_MEMORY_LIMIT_GB", "2")
    robot = jtraj.robots.get("serial3")
    q0, q1 = np.zeros(3), np.array([0.3, 0.2, 0.1])
    with pytest.raises(ValueError, match=r"N = 20000 .* GiB"):
        jtraj.solve(jtraj.Problem(robot, q0, q1, N=20000))
    with pytest.raises(ValueError, match=r"batch of 100000 problems"):
        jtraj.solve_batch(robot, np.zeros((100000, 3)), np.tile(q1, (100000, 1)), N=200, slots=None)
    monkeypatch.setenv("JTRAJ_MEMORY_LIMIT_GB", "0")  # off
    _resources.check(10**6, 3)


def test_cli_maps_the_refusal_to_bad_input(monkeypatch, capsys):
    from jtraj.cli import main

    monkeypatch.setenv("JTRAJ_MEMORY_LIMIT_GB", "2")
    code = main(["solve", "--robot", "serial3", "--start-q", "0,0.5,0.5", "--goal-q", "0.3,0.2,0.1", "--N", "20000"])
    assert code == 2
    assert "N = 20000" in capsys.readouterr().err
