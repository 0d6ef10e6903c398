"""ANFIS benchmark: Jang's Mackey-Glass accuracy, training time, query latency.

    .venv/bin/python benchmarks/bench_anfis.py [--samples 2000] [--repeat 2000]
        [--data DATASET [--mappings nefotc,nefumop,nefik,plan] [--rules R]
                        [--goal-inputs none|append|relative] [--phase|--no-phase]]

Prints
* Mackey-Glass (Jang 1993 set-up, 16 rules, first-order TSK) train and check RMSE
  (goal: check <= 0.003; Jang reports 0.0016), and training time;
* training time on ``--samples`` Mackey-Glass pairs (same embedding, t = 118 ...) with
  16 rules, cold (compilation included) and warm (goal <= 10 s);
* single-query latency of ``model.predict(x)`` (jitted, float64; goal <= 200 us) and
  of the float32 copy, median over ``--repeat`` calls;
* batch throughput (queries/s) for a batch of 10,000;
* with ``--data``, the trajectory models of a ``jtraj dataset`` (converged trajectories
  only; test split = last 10 % of them in dataset order): ANFIS test RMSE against the
  linear least-squares and 5-nearest-neighbour baselines fitted on the same split
  (goal: ANFIS <= 0.5 x linear), training seconds and rules.

All in float64 unless said; the machine's CPU (2 cores here) is what is measured.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jtraj import anfis  # noqa: E402
from jtraj.anfis import datasets  # noqa: E402


def rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def latency(f, x, repeat):
    jax.block_until_ready(f(x))
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(f(x))
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), float(np.percentile(ts, 90))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=2000)
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--data", help="also benchmark the trajectory models of this dataset")
    ap.add_argument("--mappings", default="nefotc,nefumop,nefik,plan")
    ap.add_argument("--rules", type=int, default=None,
                    help="rules of the trajectory models (default: radius chosen on the validation split)")
    ap.add_argument("--ridge", type=float, default=1e-6, help="relative ridge (as jtraj train)")
    ap.add_argument("--goal-inputs", nargs="?", const="append", default=None,
                    choices=["none", "append", "relative"],
                    help="nefotc / nefumop with the offset to the goal (default: as jtraj train, see its --help)")
    ap.add_argument("--phase", action=argparse.BooleanOptionalAction, default=None,
                    help="nefotc / nefumop with the phase k/N (default: as jtraj train)")
    args = ap.parse_args(argv)
    if args.data:
        trajectory_models(args)

    Xtr, ytr, Xck, yck = datasets.jang_mackey_glass()
    t0 = time.perf_counter()
    model, hist = anfis.train(Xtr, ytr, n_rules=16, epochs=args.epochs)
    t_mg = time.perf_counter() - t0
    print(f"Mackey-Glass, 16 rules (radius {hist.radius:.4f}), {hist.epochs} epochs (best {hist.best_epoch}, "
          f"{hist.stop_reason}): train RMSE {rmse(model.predict(Xtr), ytr):.5f}, "
          f"check RMSE {rmse(model.predict(Xck), yck):.5f} (goal <= 0.003, Jang 0.0016), {t_mg:.2f} s")

    # --- 2000-sample training time
    P = args.samples
    _, x = datasets.mackey_glass(float(118 + P + 6 + 2000))
    t = np.arange(118, 118 + P + 2000)
    X = np.stack([x[t - 18], x[t - 12], x[t - 6], x[t]], axis=1)
    y = x[t + 6]
    for label in ("cold", "warm"):
        t0 = time.perf_counter()
        m2, h2 = anfis.train(X[:P], y[:P], n_rules=16, epochs=args.epochs)
        dt = time.perf_counter() - t0
        print(f"training on {P} samples ({label}{', compilation included' if label == 'cold' else ''}): "
              f"{dt:.2f} s, {h2.epochs} epochs, check RMSE on the next 2000 "
              f"{rmse(m2.predict(X[P:]), y[P:]):.5f} (goal <= 10 s)")

    # --- latency
    xq = Xck[0]
    # model.predict looked up at every call, as a user writes it (a method bound once and
    # reused hid equinox's per-lookup cost, ~130 us, before predict avoided it)
    med, p90 = latency(lambda x: model.predict(x), xq, args.repeat)
    print(f"single query model.predict(x), float64: median {med * 1e6:.1f} us, p90 {p90 * 1e6:.1f} us "
          f"(goal <= 200 us)")
    m32 = model.astype(jnp.float32)
    med32, p9032 = latency(lambda x: m32.predict(x), xq.astype(np.float32), args.repeat)
    print(f"single query, float32 copy: median {med32 * 1e6:.1f} us, p90 {p9032 * 1e6:.1f} us")
    f = jax.jit(model.predict_fn())
    xj = jnp.asarray(xq)[None, :]
    medf, _ = latency(f, xj, args.repeat)
    print(f"single query, raw jitted predict_fn on a device array: median {medf * 1e6:.1f} us")

    # --- batch
    B = 10_000
    Xb = jnp.asarray(np.resize(Xck, (B, 4)))
    med_b, _ = latency(model.predict, Xb, 50)
    print(f"batch of {B}: {med_b * 1e3:.2f} ms, {B / med_b:,.0f} queries/s")


def trajectory_models(args):
    from jtraj import mappings

    data = mappings.load_data(args.data)
    for mapping in args.mappings.split(","):
        extra = mapping in ("nefotc", "nefumop")
        goal = args.goal_inputs if extra else False
        phase = args.phase if extra else False
        _, r, _ = mappings.train_mapping(data, mapping, n_rules=args.rules, epochs=args.epochs, ridge=args.ridge,
                                           goal=goal, phase=phase)
        print(f"{mapping} (inputs {', '.join(r['inputs'])}; augment {r['augment']}): {r['n_rules']} rules, "
              f"{r['epochs']} epochs, "
              f"{r['seconds']:.1f} s, "
              f"{r['n_trajectories_train']}/{r['n_trajectories_test']} train/test trajectories; test RMSE ANFIS "
              f"{r['test_rmse']:.4g}, linear {r['linear_test_rmse']:.4g}, 5-NN {r['knn_test_rmse']:.4g}; "
              f"ANFIS / linear {r['ratio_to_linear']:.3f} (goal <= 0.5)"
              + (f"; linear on the thesis' inputs {r['thesis_linear_test_rmse']:.4g}, ANFIS / that "
                 f"{r['ratio_to_thesis_linear']:.3f}" if "thesis_linear_test_rmse" in r else ""), flush=True)


if __name__ == "__main__":
    main()
