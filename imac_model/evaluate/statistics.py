"""World-model vs real success: does the world model rank policies as reality does?

Per-episode outcomes of each policy (or checkpoint) in groups of episodes, in the world model
and in reality, become Pearson, Spearman, Kendall tau-b and SIMPLER's MMRV (strict
comparisons; lower is better), at the level of (policy, group) points and of pooled policies,
with episode-bootstrap intervals (bias-corrected by default) and the scatter plot. The
statistics are numpy functions over the last axis, vectorised for the bootstrap. Why the
default interval: ``docs/evaluation.md``."""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from imac_data.errors import InputError

STATISTICS = ("pearson", "spearman", "kendall", "mmrv")
NORMALIZATIONS = ("none", "max", "minmax")
INTERVALS = ("bc", "percentile", "basic")
_PAIRWISE_BUDGET = 1 << 22  # elements per (rows, N, N) block: memory stays bounded for any row count


# --------------------------------------------------------------------------- vectorised statistics


def _rows(x, y) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    if x.ndim == 0:
        raise InputError("expected arrays with the points on the last axis, got scalars")
    lead = x.shape[:-1]
    return x.reshape(-1, x.shape[-1]), y.reshape(-1, y.shape[-1]), lead


def _blockwise(fn, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Apply a pairwise (rows, N, N) computation in row blocks of bounded size."""
    n = x.shape[-1]
    step = max(1, _PAIRWISE_BUDGET // max(1, n * n))
    out = np.empty(x.shape[0], dtype=np.float64)
    for s in range(0, x.shape[0], step):
        out[s:s + step] = fn(x[s:s + step], y[s:s + step])
    return out


def _undefined(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rows where a correlation is undefined: a NaN, or a constant side."""
    nan = np.isnan(x).any(-1) | np.isnan(y).any(-1)
    const = np.all(x == x[:, :1], -1) | np.all(y == y[:, :1], -1)
    return nan | const


def _pearson_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    xc = x - x.mean(-1, keepdims=True)
    yc = y - y.mean(-1, keepdims=True)
    den = np.sqrt((xc * xc).sum(-1) * (yc * yc).sum(-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (xc * yc).sum(-1) / den
    return np.clip(r, -1.0, 1.0)


def pearson(x, y) -> np.ndarray:
    """Pearson's r over the last axis (NaN where a side is constant or has a NaN)."""
    x2, y2, lead = _rows(x, y)
    r = _pearson_rows(x2, y2)
    r[_undefined(x2, y2)] = np.nan
    return r.reshape(lead)


def average_ranks(x) -> np.ndarray:
    """Ranks 1..N over the last axis, ties given their average rank (scipy's 'average')."""
    x = np.asarray(x, dtype=np.float64)
    xi, xj = x[..., :, None], x[..., None, :]
    return (xj < xi).sum(-1) + ((xj == xi).sum(-1) + 1) / 2.0


def spearman(x, y) -> np.ndarray:
    """Spearman's rho over the last axis: Pearson's r of the average ranks."""
    x2, y2, lead = _rows(x, y)
    r = _blockwise(lambda a, b: _pearson_rows(average_ranks(a), average_ranks(b)), x2, y2)
    r[_undefined(x2, y2)] = np.nan
    return r.reshape(lead)


def _kendall_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    sx = np.sign(x[:, :, None] - x[:, None, :])
    sy = np.sign(y[:, :, None] - y[:, None, :])
    # every unordered pair counted twice in all three sums, so the factor cancels
    concordance = (sx * sy).sum((-2, -1))
    untied = np.abs(sx).sum((-2, -1)) * np.abs(sy).sum((-2, -1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.clip(concordance / np.sqrt(untied), -1.0, 1.0)


def kendall_tau_b(x, y) -> np.ndarray:
    """Kendall's tau-b over the last axis (ties on either side handled as scipy's
    ``kendalltau(variant='b')``)."""
    x2, y2, lead = _rows(x, y)
    r = _blockwise(_kendall_rows, x2, y2)
    r[_undefined(x2, y2)] = np.nan
    return r.reshape(lead)


def _mmrv_rows(v: np.ndarray, r: np.ndarray) -> np.ndarray:
    violated = (v[:, :, None] > v[:, None, :]) != (r[:, :, None] > r[:, None, :])
    gap = np.abs(r[:, :, None] - r[:, None, :])
    return np.where(violated, gap, 0.0).max(-1).mean(-1)


def mmrv(world_model, real) -> np.ndarray:
    """SIMPLER's mean maximum rank violation over the last axis (lower is better).

    ``world_model`` are the evaluator's scores V, ``real`` the reference R; the
    violation of a pair is weighted by the real gap |R_i - R_j|.
    """
    v, r, lead = _rows(world_model, real)
    out = _blockwise(_mmrv_rows, v, r)
    out[np.isnan(v).any(-1) | np.isnan(r).any(-1)] = np.nan
    return out.reshape(lead)


def best_two_level_guess(real: Mapping[Hashable, float]) -> dict:
    """The blind baseline of a policy set: the lowest MMRV of a guess that splits the policies at a real rate and
    gives each side one value, over every split (``mmrv``, ``high``: the policies guessed better). No two-level
    guess does better, split or not (tests/test_evaluate_statistics.py): a set where it is low cannot tell a
    world model from a guess."""
    names, r = list(real), np.asarray([real[k] for k in real], dtype=np.float64)
    splits = np.unique(r)[1:]
    if splits.size == 0:
        return {"mmrv": None, "high": []}
    guesses = (r[None] >= splits[:, None]).astype(np.float64)
    scores = mmrv(guesses, np.broadcast_to(r, guesses.shape))
    best = int(np.argmin(scores))
    return {"mmrv": float(scores[best]), "high": [n for n, g in zip(names, guesses[best]) if g]}


def balanced_accuracy(real, world_model) -> float | None:
    """The mean over real outcomes (success, failure) of the share of starts where the world model's verdict
    agrees: 0.5 for any verdict blind to the start. A class absent from ``real`` is left out; None without
    starts."""
    real, wm = np.asarray(real, dtype=bool), np.asarray(world_model, dtype=bool)
    if real.shape != wm.shape:
        raise InputError(f"balanced_accuracy: {real.shape[0]} real outcomes, {wm.shape[0]} world-model verdicts")
    recalls = [float(np.mean(wm[real == c] == c)) for c in (True, False) if np.any(real == c)]
    return float(np.mean(recalls)) if recalls else None


STATISTIC_FUNCTIONS = {"pearson": pearson, "spearman": spearman, "kendall": kendall_tau_b, "mmrv": mmrv}


def normalize_rates(x, how: str) -> np.ndarray:
    """Per-row normalisation of rates over the last axis: ``none``; ``max`` (the best
    point becomes 1); ``minmax`` (best 1, worst 0). NaN where undefined (all zero,
    or all equal for minmax). Correlations are invariant to both; MMRV is not."""
    x = np.asarray(x, dtype=np.float64)
    if how == "none":
        return x
    hi = x.max(-1, keepdims=True)
    lo = x.min(-1, keepdims=True) if how == "minmax" else np.zeros_like(hi)
    span = hi - lo
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(span > 0, (x - lo) / np.where(span > 0, span, 1.0), np.nan)


# --------------------------------------------------------------------------- bootstrap


@dataclass(frozen=True)
class BootstrapConfig:
    """How :func:`policy_correlation` builds its intervals."""

    replicates: int = 2000
    confidence: float = 0.95
    seed: int = 0
    paired: bool = False  # world-model and real episode i share a start configuration: resample them together
    normalize: str = "none"  # none | max | minmax, applied to each side per replicate
    interval: str = "bc"  # bc | percentile | basic (see _interval)

    def __post_init__(self) -> None:
        if not isinstance(self.replicates, (int, np.integer)) or isinstance(self.replicates, bool) \
                or self.replicates < 1:
            raise InputError(f"BootstrapConfig.replicates: must be a positive integer (got {self.replicates!r})")
        if not 0.0 < float(self.confidence) < 1.0:
            raise InputError(f"BootstrapConfig.confidence: must be in (0, 1) (got {self.confidence!r})")
        if self.normalize not in NORMALIZATIONS:
            raise InputError(f"BootstrapConfig.normalize: must be one of {NORMALIZATIONS} (got {self.normalize!r})")
        if self.interval not in INTERVALS:
            raise InputError(f"BootstrapConfig.interval: must be one of {INTERVALS} (got {self.interval!r})")


@dataclass(frozen=True)
class Cell:
    """One (policy, group): its per-episode outcomes in the world model and in reality."""

    policy: str
    group: str | None
    world_model: np.ndarray
    real: np.ndarray


def _outcomes(name: str, key, values) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 1 or a.size == 0:
        raise InputError(f"{name}[{key!r}]: expected a non-empty 1-D sequence of per-episode outcomes, "
                         f"got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{name}[{key!r}]: outcomes must be finite (success labels 0/1 or scores)")
    return a


def _split_key(key: Hashable) -> tuple[str, str | None]:
    if isinstance(key, tuple):
        if len(key) != 2:
            raise InputError(f"outcome key {key!r}: expected a policy or a (policy, group) pair")
        return str(key[0]), str(key[1])
    return str(key), None


def collect_cells(world_model: Mapping, real: Mapping, *, paired: bool = False) -> list[Cell]:
    """Validate and pair the two outcome mappings (keys: policy, or (policy, group))."""
    missing_real = [k for k in world_model if k not in real]
    missing_wm = [k for k in real if k not in world_model]
    if missing_real or missing_wm:
        raise InputError("world-model and real outcomes must cover the same (policy, group) keys: "
                         f"only in world_model: {missing_real}, only in real: {missing_wm}")
    cells = []
    for key in world_model:
        policy, group = _split_key(key)
        w, r = _outcomes("world_model", key, world_model[key]), _outcomes("real", key, real[key])
        if paired and w.size != r.size:
            raise InputError(f"paired bootstrap: {key!r} has {w.size} world-model and {r.size} real episodes; "
                             "paired episodes must match one to one")
        cells.append(Cell(policy, group, w, r))
    seen = [(c.policy, c.group) for c in cells]
    if len(set(seen)) != len(seen):
        raise InputError(f"duplicate (policy, group) keys after conversion to strings: {seen}")
    if len({c.policy for c in cells}) < 2:
        raise InputError("need at least two policies to compare rankings")
    return cells


def _resampled_sums(cells: Sequence[Cell], config: BootstrapConfig, rng: np.random.Generator):
    """(replicates, cells) sums of resampled outcomes, world model and real."""
    b = config.replicates
    wm = np.empty((b, len(cells)))
    real = np.empty((b, len(cells)))
    for c, cell in enumerate(cells):
        nw, nr = cell.world_model.size, cell.real.size
        step = max(1, _PAIRWISE_BUDGET // max(nw, nr))
        for s in range(0, b, step):
            rows = min(step, b - s)
            iw = rng.integers(0, nw, size=(rows, nw))
            ir = iw if config.paired else rng.integers(0, nr, size=(rows, nr))
            wm[s:s + rows, c] = cell.world_model[iw].sum(1)
            real[s:s + rows, c] = cell.real[ir].sum(1)
    return wm, real


def _statistics(wm: np.ndarray, real: np.ndarray, normalize: str) -> dict[str, np.ndarray]:
    v, r = normalize_rates(wm, normalize), normalize_rates(real, normalize)
    return {name: STATISTIC_FUNCTIONS[name](v, r) for name in STATISTICS}


def _interval(samples: np.ndarray, estimate: float, confidence: float, method: str) -> list[float | None]:
    """A bootstrap interval from the replicates of one statistic.

    ``percentile``: the replicates' quantiles. ``bc``: bias-corrected percentile
    (Efron): the quantile levels are shifted by z0 = Phi^-1(share of replicates below
    the estimate), which undoes the median bias of the estimate (for correlations of
    rates measured with binomial noise, an attenuation towards 0). ``basic``: the
    percentile interval reflected about the estimate. Coverage of each on synthetic
    data: ``benchmarks/evaluate_statistics.py``; ``bc`` is the default because it
    is the most even across regimes (the percentile interval inherits the attenuation
    of correlations of noisy rates twice and can miss badly when policies are close).
    """
    from scipy.stats import norm

    finite = samples[np.isfinite(samples)]
    if finite.size == 0 or not np.isfinite(estimate):
        return [None, None]
    a = (1.0 - confidence) / 2.0
    if method == "percentile":
        levels = [a, 1.0 - a]
    elif method == "bc" and finite.min() < estimate < finite.max():
        below = (np.sum(finite < estimate) + 0.5 * np.sum(finite == estimate)) / finite.size
        z0 = norm.ppf(below)
        levels = [norm.cdf(2 * z0 + norm.ppf(a)), norm.cdf(2 * z0 + norm.ppf(1.0 - a))]
    elif method == "bc":
        # the estimate is at the edge of the replicates (e.g. a perfect observed
        # correlation): z0 is infinite and BC would collapse onto the estimate, so the
        # plain percentile interval is given instead
        levels = [a, 1.0 - a]
    elif method == "basic":
        lo, hi = np.quantile(finite, [a, 1.0 - a])
        return [float(2 * estimate - hi), float(2 * estimate - lo)]
    else:
        raise InputError(f"unknown interval method {method!r}")
    lo, hi = np.quantile(finite, levels)
    return [float(lo), float(hi)]


def _num(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


@dataclass(frozen=True)
class BootstrapDraws:
    """Rates and statistics of the observed data and of every bootstrap replicate."""

    cells: list[Cell]
    policies: list[str]
    rates: dict  # level -> (world_model (P,), real (P,)) observed rates, P points of the level
    replicate_rates: dict  # level -> (world_model (B, P), real (B, P))
    point: dict  # level -> {statistic: float}
    replicates: dict  # level -> {statistic: (B,)}


def bootstrap_draws(world_model: Mapping, real: Mapping, config: BootstrapConfig) -> BootstrapDraws:
    """Resample episodes within each (policy, group) and evaluate every statistic on
    the observed and resampled rates, at the group and the policy level."""
    cells = collect_cells(world_model, real, paired=config.paired)
    policies = list(dict.fromkeys(c.policy for c in cells))
    member = np.array([[c.policy == p for p in policies] for c in cells], dtype=np.float64)  # cells x policies
    n_wm = np.array([c.world_model.size for c in cells], dtype=np.float64)
    n_real = np.array([c.real.size for c in cells], dtype=np.float64)
    sum_wm = np.array([c.world_model.sum() for c in cells])
    sum_real = np.array([c.real.sum() for c in cells])
    boot_wm, boot_real = _resampled_sums(cells, config, np.random.default_rng(config.seed))
    rates, replicate_rates, point, replicates = {}, {}, {}, {}
    for level, (w_sum, r_sum, bw, br, nw, nr) in {
        "group": (sum_wm, sum_real, boot_wm, boot_real, n_wm, n_real),
        "policy": (sum_wm @ member, sum_real @ member, boot_wm @ member, boot_real @ member,
                   n_wm @ member, n_real @ member),
    }.items():
        rates[level] = (w_sum / nw, r_sum / nr)
        replicate_rates[level] = (bw / nw, br / nr)
        point[level] = {k: float(v) for k, v in _statistics(*rates[level], config.normalize).items()}
        replicates[level] = _statistics(*replicate_rates[level], config.normalize)
    return BootstrapDraws(cells, policies, rates, replicate_rates, point, replicates)


def policy_correlation(world_model: Mapping, real: Mapping, *, replicates: int = 2000, confidence: float = 0.95,
                       seed: int = 0, paired: bool = False, normalize: str = "none",
                       interval: str = "bc") -> dict:
    """Pearson, Spearman, Kendall tau-b and MMRV of world-model vs real success, with
    bootstrap intervals.

    ``world_model`` and ``real`` map a policy (or a ``(policy, group)`` pair, for
    repeated groups) to its per-episode outcomes (success 0/1, or scores). Returns a
    JSON-ready dict: ``levels.group`` (one point per key) and ``levels.policy`` (one
    point per policy, its groups' episodes pooled), each with ``n_points`` and per
    statistic ``value``, ``ci`` and ``undefined_fraction`` (replicates where it was
    NaN, e.g. every resampled rate tied); ``points`` (rates and their percentile
    intervals); and ``bootstrap`` (the configuration).
    """
    config = BootstrapConfig(replicates=replicates, confidence=confidence, seed=seed, paired=paired,
                             normalize=normalize, interval=interval)
    draws = bootstrap_draws(world_model, real, config)
    levels = {}
    for level in ("group", "policy"):
        levels[level] = {"n_points": int(draws.rates[level][0].size)} | {
            name: {"value": _num(draws.point[level][name]),
                   "ci": _interval(draws.replicates[level][name], draws.point[level][name], config.confidence,
                                   config.interval),
                   "undefined_fraction": float(np.mean(~np.isfinite(draws.replicates[level][name])))}
            for name in STATISTICS
        }
    w_rate, r_rate = draws.rates["group"]
    bw_rate, br_rate = draws.replicate_rates["group"]
    wn, rn = normalize_rates(w_rate, config.normalize), normalize_rates(r_rate, config.normalize)
    bwn, brn = normalize_rates(bw_rate, config.normalize), normalize_rates(br_rate, config.normalize)
    points = []
    for c, cell in enumerate(draws.cells):
        points.append({
            "policy": cell.policy, "group": cell.group,
            "n_world_model": int(cell.world_model.size), "n_real": int(cell.real.size),
            "world_model": float(w_rate[c]), "real": float(r_rate[c]),
            "world_model_plotted": _num(wn[c]), "real_plotted": _num(rn[c]),
            "world_model_ci": _interval(bwn[:, c], wn[c], config.confidence, "percentile"),
            "real_ci": _interval(brn[:, c], rn[c], config.confidence, "percentile"),
        })
    return {
        "levels": levels,
        "points": points,
        "policies": draws.policies,
        "bootstrap": asdict(config) | {
            "resampling": "episodes with replacement within each (policy, group); "
                          + ("world-model and real episodes resampled together (paired)" if paired
                             else "world model and reality resampled independently"),
        },
        "mmrv_definition": "SIMPLER: mean_i max_j 1[(V_i > V_j) != (R_i > R_j)] |R_i - R_j|, "
                           "V = world model, R = real",
    }


# --------------------------------------------------------------------------- figure

_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "*", "h", "p")


def scatter_figure(result: Mapping, title: str | None = None):
    """The correlation figure as a matplotlib ``Figure`` (no pyplot state): real rate on
    x, world-model rate on y, one colour and marker per policy shared by its groups,
    bootstrap intervals as error bars, the diagonal, and the group-level statistics."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.8, 4.4), dpi=120)
    ax = fig.add_subplot()
    cmap = [f"C{i % 10}" for i in range(len(result["policies"]))]
    for i, policy in enumerate(result["policies"]):
        pts = [p for p in result["points"] if p["policy"] == policy]
        x = np.array([np.nan if p["real_plotted"] is None else p["real_plotted"] for p in pts])
        y = np.array([np.nan if p["world_model_plotted"] is None else p["world_model_plotted"] for p in pts])
        xerr = np.array([[0.0, 0.0] if None in p["real_ci"] else [xi - p["real_ci"][0], p["real_ci"][1] - xi]
                         for p, xi in zip(pts, x)]).T
        yerr = np.array([[0.0, 0.0] if None in p["world_model_ci"]
                         else [yi - p["world_model_ci"][0], p["world_model_ci"][1] - yi]
                         for p, yi in zip(pts, y)]).T
        ax.errorbar(x, y, xerr=np.clip(xerr, 0, None), yerr=np.clip(yerr, 0, None), fmt="none",
                    ecolor=cmap[i], alpha=0.35, lw=1)
        ax.scatter(x, y, marker=_MARKERS[i % len(_MARKERS)], color=cmap[i], s=46, label=policy,
                   edgecolors="black", linewidths=0.5, zorder=3)
    normalized = result["bootstrap"]["normalize"] != "none"
    ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--", zorder=1)
    ax.set_xlim(-0.03, 1.03)
    ax.set_ylim(-0.03, 1.03)
    suffix = " (normalised)" if normalized else ""
    ax.set_xlabel("real success rate" + suffix)
    ax.set_ylabel("world-model success rate" + suffix)
    g = result["levels"]["group"]

    def fmt(name):
        v = g[name]["value"]
        return "n/a" if v is None else f"{v:.3f}"

    stats = f"r={fmt('pearson')}  rho={fmt('spearman')}  tau={fmt('kendall')}  MMRV={fmt('mmrv')}"
    ax.set_title(stats if title is None else f"{title}\n{stats}", fontsize=8)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)  # off the points
    ax.grid(alpha=0.25)
    fig.tight_layout()
    return fig


def plot_policy_scatter(result: Mapping, path: str | Path, title: str | None = None) -> Path:
    """Write :func:`scatter_figure` of a :func:`policy_correlation` result as a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"{path}: the scatter plot is written as PNG; give a .png path")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = scatter_figure(result, title)
    FigureCanvasAgg(fig)
    tmp = path.with_name(f".{path.name}.tmp")
    fig.savefig(tmp, format="png", bbox_inches="tight")
    tmp.replace(path)
    return path
