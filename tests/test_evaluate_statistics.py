"""World-model vs real statistics: scipy and SIMPLER as oracles, hand-made MMRV cases,
bootstrap coverage on synthetic data of known correlation, and the scatter plot."""

import itertools
import json
import math
import warnings

import matplotlib.image
import numpy as np
import pytest
import scipy.stats

from imac_data.errors import InputError
from imac_model.evaluate.statistics import (
    STATISTIC_FUNCTIONS,
    STATISTICS,
    balanced_accuracy,
    best_two_level_guess,
    kendall_tau_b,
    mmrv,
    pearson,
    plot_policy_scatter,
    policy_correlation,
    scatter_figure,
    spearman,
)


def simpler_mmrv(perf_sim, perf_real):
    """SIMPLER's loop (simpler_env/utils/metrics.py), transcribed as the oracle."""
    violations = []
    for i in range(len(perf_sim)):
        worst = 0.0
        for j in range(len(perf_sim)):
            if (perf_sim[i] > perf_sim[j]) != (perf_real[i] > perf_real[j]):
                worst = max(worst, abs(perf_real[i] - perf_real[j]))
        violations.append(worst)
    return float(np.mean(violations))


def scipy_value(name, x, y):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if name == "pearson":
            if np.all(x == x[0]) or np.all(y == y[0]):
                return math.nan
            return scipy.stats.pearsonr(x, y).statistic
        if name == "spearman":
            return scipy.stats.spearmanr(x, y).statistic
        return scipy.stats.kendalltau(x, y, variant="b").statistic


def test_correlations_match_scipy_with_ties_and_batches():
    rng = np.random.default_rng(0)
    for n in (2, 3, 5, 9):
        # tie-heavy rates (multiples of 1/4), continuous values, and constant rows, in one batch
        x = np.concatenate([rng.integers(0, 5, (20, n)) / 4, rng.random((10, n)), np.full((2, n), 0.5)])
        y = np.concatenate([rng.integers(0, 5, (20, n)) / 4, rng.random((10, n)), rng.random((2, n))])
        batch = {"pearson": pearson(x, y), "spearman": spearman(x, y), "kendall": kendall_tau_b(x, y)}
        for name, ours in batch.items():
            assert ours.shape == (32,)
            ref = np.array([scipy_value(name, a, b) for a, b in zip(x, y)])
            assert np.array_equal(np.isnan(ours), np.isnan(ref)), name
            np.testing.assert_allclose(ours[~np.isnan(ref)], ref[~np.isnan(ref)], atol=1e-12, err_msg=name)
    # leading axes are kept
    assert kendall_tau_b(rng.random((3, 4, 6)), rng.random((3, 4, 6))).shape == (3, 4)


def test_mmrv_hand_made_rankings():
    # same ranking: no violation
    assert mmrv([0.1, 0.5, 0.9], [0.2, 0.4, 0.8]) == 0.0
    # policies 1 and 2 swapped: each of them violates by the real gap 0.4, policy 0 by nothing
    assert mmrv([0.1, 0.5, 0.9], [0.2, 0.8, 0.4]) == pytest.approx((0 + 0.4 + 0.4) / 3)
    # tie in the world model only: policy 1 is really better (strict >), a violation of 0.4 for it
    assert mmrv([0.5, 0.5], [0.2, 0.6]) == pytest.approx(0.4 / 2)
    # tie in reality only: the violation exists but weighs |R_i - R_j| = 0
    assert mmrv([0.2, 0.6], [0.5, 0.5]) == 0.0
    # a world model that ties everything: each policy's violation is its largest real lead (strict R_i > R_j):
    # 0 for the worst, 0.3 and 0.8 for the others (with >= the attribution flips and gives (0.8 + 0.5) / 3)
    assert mmrv([0.2, 0.2, 0.2], [0.1, 0.4, 0.9]) == pytest.approx((0 + 0.3 + 0.8) / 3)
    # ties on both sides agree: no violation
    assert mmrv([0.3, 0.3, 0.7], [0.1, 0.1, 0.9]) == 0.0
    # the worst violation counts, not the sum: policy 0 is ranked above both others but is the worst
    assert mmrv([0.9, 0.5, 0.1], [0.1, 0.6, 0.3]) == pytest.approx((0.5 + 0.5 + 0.2) / 3)
    # order of arguments matters: the weight is the REAL gap
    assert mmrv([0.1, 0.9], [0.5, 0.4]) == pytest.approx(0.1)
    assert mmrv([0.5, 0.4], [0.1, 0.9]) == pytest.approx(0.8)


def test_mmrv_matches_simpler_on_tie_heavy_data():
    rng = np.random.default_rng(1)
    v = rng.integers(0, 4, (200, 7)) / 3
    r = rng.integers(0, 4, (200, 7)) / 3
    ours = mmrv(v, r)
    np.testing.assert_allclose(ours, [simpler_mmrv(a, b) for a, b in zip(v, r)], atol=1e-15)


def test_the_best_two_level_guess_is_the_best_of_every_two_level_labelling():
    # the committed six-policy set (docs/ranking/results.json): the near grasps high, the rest low
    six = dict(zip("abcdef", [1.0, 0.68, 1.0, 0.0, 0.0, 0.0]))
    assert best_two_level_guess(six) == {"mmrv": pytest.approx((0.32 + 0.32 + 0) / 6), "high": ["a", "b", "c"]}
    assert best_two_level_guess({"a": 0.5, "b": 0.5}) == {"mmrv": None, "high": []}
    # brute force with SIMPLER's loop over every labelling of the policies with two values, split or not
    rng = np.random.default_rng(3)
    for trial in range(300):
        n = int(rng.integers(3, 9))
        rates = rng.integers(0, 6, n) / 5 if trial % 2 else rng.random(n)
        if np.unique(rates).size < 2:
            continue
        brute = min(simpler_mmrv(np.array(v, float), rates)
                    for v in itertools.product((0, 1), repeat=n) if 0 < sum(v) < n)
        assert best_two_level_guess(dict(enumerate(rates)))["mmrv"] == pytest.approx(brute, abs=1e-12)


def test_balanced_accuracy_by_hand():
    real = [True, True, True, False]
    assert balanced_accuracy(real, [True, True, False, False]) == pytest.approx((2 / 3 + 1) / 2)
    assert balanced_accuracy(real, [True] * 4) == 0.5  # blind verdicts: a half, however unbalanced the starts
    assert balanced_accuracy([True, True], [True, False]) == 0.5  # one class: its recall
    assert balanced_accuracy([], []) is None
    with pytest.raises(InputError, match="3 real outcomes, 2"):
        balanced_accuracy([True, False, True], [True, False])


def _true_rates(n_policies, rho, seed):
    """Fixed policies whose true world-model and real rates have Pearson correlation
    exactly ``rho`` (an affine map to [0.1, 0.9] leaves it unchanged)."""
    rng = np.random.default_rng(seed)
    z = np.linspace(-1, 1, n_policies)
    z = (z - z.mean()) / z.std()
    e = rng.standard_normal(n_policies)
    e -= e.mean()
    e -= (e @ z) / (z @ z) * z
    e /= e.std()
    w = rho * z + math.sqrt(1 - rho**2) * e
    to_rate = lambda u: 0.1 + 0.8 * (u - u.min()) / (u.max() - u.min())  # noqa: E731
    return to_rate(w), to_rate(z)


def test_bootstrap_intervals_cover_the_true_value_at_the_nominal_rate():
    """Six policies x two groups x 30 episodes (the paper's design), true rates of known
    correlation 0.5. Over R = 300 independent experiments, each 90 % interval (400
    replicates) should contain the statistic of the true rates about 90 % of the time.
    Tolerance: 3 Monte-Carlo standard errors, 3 * sqrt(0.9 * 0.1 / 300) = 0.052, plus 0.02
    for the bias-corrected bootstrap's own O(1/n) coverage error at 60 episodes per
    policy (measured, see benchmarks/evaluate_statistics.py): |coverage - 0.9| <= 0.072."""
    n_policies, n_groups, n_episodes, rho, reps = 6, 2, 30, 0.5, 300
    pw, pr = _true_rates(n_policies, rho, seed=1)
    truth = {name: float(STATISTIC_FUNCTIONS[name](pw, pr)) for name in STATISTICS}
    assert truth["pearson"] == pytest.approx(rho)
    rng = np.random.default_rng(2)
    hits = {("policy", s): 0 for s in STATISTICS} | {("group", "pearson"): 0}
    for rep in range(reps):
        wm = {(f"p{i}", g): rng.random(n_episodes) < pw[i] for i in range(n_policies) for g in range(n_groups)}
        real = {(f"p{i}", g): rng.random(n_episodes) < pr[i] for i in range(n_policies) for g in range(n_groups)}
        res = policy_correlation(wm, real, replicates=400, confidence=0.9, seed=rep)
        for level, name in hits:
            lo, hi = res["levels"][level][name]["ci"]
            hits[(level, name)] += lo is not None and lo <= truth[name] <= hi
    coverage = {k: v / reps for k, v in hits.items()}
    print("coverage of 90% intervals:", coverage)
    for key, c in coverage.items():
        assert abs(c - 0.9) <= 0.072, (key, c)


def test_bootstrap_resamples_episodes_within_each_cell():
    wm = {("a", "g1"): [1] * 10, ("a", "g2"): [1, 0] * 5, ("b", "g1"): [0] * 10, ("c", "g1"): [1, 1, 0, 0, 0]}
    real = {("a", "g1"): [1] * 8, ("a", "g2"): [1, 0, 0, 0] * 3, ("b", "g1"): [1, 0] * 6, ("c", "g1"): [0, 0, 1]}
    res = policy_correlation(wm, real, replicates=500, seed=0)
    pts = {(p["policy"], p["group"]): p for p in res["points"]}
    # an all-success or all-failure cell cannot move when its own episodes are resampled
    assert pts[("a", "g1")]["world_model_ci"] == [1.0, 1.0] and pts[("b", "g1")]["world_model_ci"] == [0.0, 0.0]
    assert pts[("a", "g1")]["real_ci"] == [1.0, 1.0]
    lo, hi = pts[("a", "g2")]["world_model_ci"]
    assert lo < 0.5 < hi
    # rates and pooling
    assert pts[("a", "g2")]["real"] == pytest.approx(3 / 12)
    assert res["levels"]["group"]["n_points"] == 4 and res["levels"]["policy"]["n_points"] == 3
    pooled_wm = {"a": 15 / 20, "b": 0.0, "c": 2 / 5}
    pooled_real = {"a": 11 / 20, "b": 0.5, "c": 1 / 3}
    keys = ["a", "b", "c"]
    assert res["levels"]["policy"]["pearson"]["value"] == pytest.approx(
        scipy.stats.pearsonr([pooled_wm[k] for k in keys], [pooled_real[k] for k in keys]).statistic)
    assert res["levels"]["policy"]["mmrv"]["value"] == pytest.approx(
        simpler_mmrv([pooled_wm[k] for k in keys], [pooled_real[k] for k in keys]))
    # reproducible, JSON-ready
    again = policy_correlation(wm, real, replicates=500, seed=0)
    assert json.dumps(again, sort_keys=True) == json.dumps(res, sort_keys=True)
    # paired: the same indices on both sides, so equal outcomes never diverge
    same = {("a", "1"): [1, 0, 1, 1, 0], ("b", "1"): [0, 0, 1, 0, 0], ("c", "1"): [1, 1, 1, 0, 1]}
    paired = policy_correlation(same, same, replicates=300, paired=True)
    assert paired["levels"]["group"]["pearson"]["ci"] == [pytest.approx(1.0), pytest.approx(1.0)]
    assert paired["levels"]["group"]["mmrv"]["ci"] == [0.0, 0.0]
    unpaired = policy_correlation(same, same, replicates=300)
    assert unpaired["levels"]["group"]["pearson"]["ci"][0] < 0.99


def test_normalisation_changes_mmrv_only():
    wm = {"a": [1, 0, 0, 0], "b": [1, 1, 0, 0], "c": [1, 1, 1, 0]}
    real = {"a": [0, 0, 0, 0, 1], "b": [0, 0, 0, 0, 0], "c": [1, 1, 0, 0, 0]}
    plain = policy_correlation(wm, real, replicates=50)
    for how in ("max", "minmax"):
        norm = policy_correlation(wm, real, replicates=50, normalize=how)
        for name in ("pearson", "spearman", "kendall"):
            assert norm["levels"]["policy"][name]["value"] == pytest.approx(plain["levels"]["policy"][name]["value"])
    # a and b are swapped in reality (0.2 vs 0): MMRV weighs the real gap, 0.2 raw, 0.5 after max-normalising
    assert plain["levels"]["policy"]["mmrv"]["value"] == pytest.approx(0.2 * 2 / 3)
    assert policy_correlation(wm, real, replicates=50, normalize="max")["levels"]["policy"]["mmrv"]["value"] \
        == pytest.approx(0.5 * 2 / 3)


@pytest.mark.parametrize("wm, real, kwargs, message", [
    ({"a": [1], "b": [0]}, {"a": [1]}, {}, r"only in world_model: \['b'\]"),
    ({"a": [1, 0]}, {"a": [1]}, {}, "at least two policies"),
    ({"a": [1, float("nan")], "b": [0]}, {"a": [1], "b": [0]}, {}, r"world_model\['a'\]: outcomes must be finite"),
    ({"a": [], "b": [0]}, {"a": [1], "b": [0]}, {}, r"world_model\['a'\]: expected a non-empty 1-D"),
    ({"a": [1, 0], "b": [0]}, {"a": [1], "b": [0]}, {"paired": True}, "paired episodes must match"),
    ({"a": [1], "b": [0]}, {"a": [1], "b": [0]}, {"confidence": 1.5}, "confidence"),
    ({"a": [1], "b": [0]}, {"a": [1], "b": [0]}, {"normalize": "zscore"}, "normalize"),
    ({("a", 1, 2): [1], "b": [0]}, {("a", 1, 2): [1], "b": [0]}, {}, "policy or a"),
])
def test_bad_input(wm, real, kwargs, message):
    with pytest.raises(InputError, match=message):
        policy_correlation(wm, real, replicates=10, **kwargs)


def test_scatter_plot_one_marker_per_policy(tmp_path):
    rng = np.random.default_rng(3)
    wm = {(p, g): rng.random(30) < q for p, q in (("pi05_early", 0.2), ("pi05_late", 0.6), ("giga", 0.8))
          for g in ("g1", "g2")}
    real = {k: rng.random(30) < 0.7 for k in wm}
    res = policy_correlation(wm, real, replicates=200)
    fig = scatter_figure(res, title="task 1")
    collections = fig.axes[0].collections
    markers = {}
    for policy in res["policies"]:
        [coll] = [c for c in collections if c.get_label() == policy]
        # both groups of the policy are in its one collection (shared colour and marker)
        expected = [(p["real"], p["world_model"]) for p in res["points"] if p["policy"] == policy]
        np.testing.assert_allclose(coll.get_offsets(), expected)
        markers[policy] = (tuple(coll.get_facecolor()[0]), coll.get_paths()[0].vertices.tobytes())
    assert len(set(markers.values())) == 3
    png = plot_policy_scatter(res, tmp_path / "fig" / "scatter.png", title="task 1")
    image = matplotlib.image.imread(png)
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 300
    with pytest.raises(InputError, match="PNG"):
        plot_policy_scatter(res, tmp_path / "scatter.pdf")
