"""Coverage of the world-model vs real bootstrap intervals, and the statistics' speed.

    python -m benchmarks.evaluate_statistics [--reps 300] [--replicates 400] [--markdown out.md]

Synthetic experiments of known truth: fixed policies whose true world-model and real
success rates have Pearson correlation exactly ``rho`` (rates mapped affinely onto
[0.1, 0.9], evenly spread in reality); each experiment draws Bernoulli episodes
(``groups`` x ``episodes`` per policy, independently in the world model and reality),
runs :func:`imac_model.evaluate.statistics.bootstrap_draws` once and forms every
interval method from the same replicates. Coverage = the share of experiments whose
interval contains the statistic of the true rates (group level for Pearson, whose
truth is the same at both levels; policy level for all four statistics, since at the
group level the true rates of a policy's groups tie, which rank statistics of noisy
rates never reproduce). Monte-Carlo standard error of a coverage near 0.9:
sqrt(0.09 / reps) (0.017 at 300).
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from imac_model.evaluate.statistics import (
    INTERVALS,
    STATISTIC_FUNCTIONS,
    STATISTICS,
    BootstrapConfig,
    _interval,
    bootstrap_draws,
    kendall_tau_b,
    mmrv,
    pearson,
    spearman,
)

SCENARIOS = [  # (policies, groups, episodes per group, rho)
    (6, 2, 30, 0.5), (6, 2, 30, 0.8), (6, 2, 30, 0.95),
    (6, 1, 100, 0.5), (6, 1, 100, 0.8), (6, 1, 100, 0.95),
    (12, 1, 30, 0.8), (12, 1, 100, 0.8), (12, 1, 100, 0.95),
]


def true_rates(n_policies: int, rho: float, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    z = np.linspace(-1, 1, n_policies)
    z = (z - z.mean()) / z.std()
    e = rng.standard_normal(n_policies)
    e -= e.mean()
    e -= (e @ z) / (z @ z) * z
    e /= e.std()
    w = rho * z + math.sqrt(1 - rho**2) * e

    def to_rate(u):
        return 0.1 + 0.8 * (u - u.min()) / (u.max() - u.min())

    return to_rate(w), to_rate(z)


def coverage(n_policies, n_groups, n_episodes, rho, reps, replicates, confidence=0.9) -> dict:
    pw, pr = true_rates(n_policies, rho)
    truth = {name: float(STATISTIC_FUNCTIONS[name](pw, pr)) for name in STATISTICS}
    rng = np.random.default_rng(2)
    targets = [("group", "pearson")] + [("policy", s) for s in STATISTICS]
    hits = {(m, lvl, s): 0 for m in INTERVALS for lvl, s in targets}
    for rep in range(reps):
        wm = {(f"p{i}", g): rng.random(n_episodes) < pw[i] for i in range(n_policies) for g in range(n_groups)}
        real = {(f"p{i}", g): rng.random(n_episodes) < pr[i] for i in range(n_policies) for g in range(n_groups)}
        draws = bootstrap_draws(wm, real, BootstrapConfig(replicates=replicates, confidence=confidence, seed=rep))
        for m in INTERVALS:
            for lvl, s in targets:
                lo, hi = _interval(draws.replicates[lvl][s], draws.point[lvl][s], confidence, m)
                hits[(m, lvl, s)] += lo is not None and lo <= truth[s] <= hi
    return {"truth": truth, "coverage": {k: v / reps for k, v in hits.items()}}


def speed() -> dict:
    rng = np.random.default_rng(0)
    x, y = rng.random((10000, 12)), rng.random((10000, 12))
    out = {}
    for name, fn in (("pearson", pearson), ("spearman", spearman), ("kendall", kendall_tau_b), ("mmrv", mmrv)):
        t, c = time.perf_counter(), time.process_time()
        fn(x, y)
        out[name] = {"wall_ms": 1e3 * (time.perf_counter() - t), "cpu_ms": 1e3 * (time.process_time() - c)}
    wm = {(f"p{i}", g): rng.random(30) < 0.1 * i for i in range(6) for g in range(2)}
    real = {(f"p{i}", g): rng.random(30) < 0.12 * i for i in range(6) for g in range(2)}
    from imac_model.evaluate.statistics import policy_correlation

    policy_correlation(wm, real, replicates=10)  # first call imports scipy.stats
    t, c = time.perf_counter(), time.process_time()
    policy_correlation(wm, real, replicates=2000)
    out["policy_correlation_6x2x30_2000"] = {"wall_ms": 1e3 * (time.perf_counter() - t),
                                             "cpu_ms": 1e3 * (time.process_time() - c)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=300)
    ap.add_argument("--replicates", type=int, default=400)
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args(argv)
    lines = [f"load average at start: {os.getloadavg()}", "",
             "speed, 10000 rows x 12 points (ms): " + ", ".join(
                 f"{k} {v['wall_ms']:.1f} wall / {v['cpu_ms']:.1f} cpu" for k, v in speed().items()), "",
             f"coverage of 90 % intervals, {args.reps} experiments x {args.replicates} replicates "
             "(columns: g:pearson, p:pearson p:spearman p:kendall p:mmrv)", "",
             "| policies x groups x episodes | rho | truth (r, rho_s, tau, mmrv) | " + " | ".join(INTERVALS) + " |",
             "|---|---|---|" + "---|" * len(INTERVALS)]
    print("\n".join(lines), flush=True)
    for n_p, n_g, n_e, rho in SCENARIOS:
        res = coverage(n_p, n_g, n_e, rho, args.reps, args.replicates)
        cells = []
        for m in INTERVALS:
            c = res["coverage"]
            cells.append(" ".join(f"{c[(m, lvl, s)]:.2f}" for lvl, s in [("group", "pearson")]
                                  + [("policy", s) for s in STATISTICS]))
        truth = ", ".join(f"{res['truth'][s]:.2f}" for s in STATISTICS)
        line = f"| {n_p} x {n_g} x {n_e} | {rho} | {truth} | " + " | ".join(cells) + " |"
        lines.append(line)
        print(line, flush=True)
    lines.append(f"\nload average at end: {os.getloadavg()}")
    print(lines[-1])
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
