"""The ranking report's text: its ``README.md`` as a function of its ``results.json`` alone (what
:func:`.report.write_report` collects), so a committed report can be written again after a change of
its tables (:func:`.report.rewrite_report`) with no work directory at hand."""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np

from imac_model.evaluate.policies import split_noisy
from imac_model.evaluate.statistics import STATISTICS, balanced_accuracy, best_two_level_guess, mmrv, pearson, spearman
from imac_model.experiments.ranking.evaluation import JUDGE_COLUMNS
from imac_model.experiments.ranking.gate import GATED_MODE, cube_by_view, gate_verdict
from imac_model.experiments.ranking.plan import BASELINE_MODE, RankingPlan, base_mode, command_flags, slug
from imac_model.experiments.stages import REPO_ROOT


def shown_path(path: Path) -> str:
    """``path`` as the command line gave it: relative to the repository when inside it."""
    return str(path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path)


def _fmt(x, digits: int = 3) -> str:
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{digits}f}"


def _ci(ci) -> str:
    return "" if not ci or ci[0] is None else f" [{_fmt(ci[0], 2)}, {_fmt(ci[1], 2)}]"


def wilson(k: float, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval (95 %) of a success rate k / n."""
    p = k / n
    centre, half = (p + z * z / (2 * n)) / (1 + z * z / n), z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def _rate(k: float, n: int) -> str:
    lo, hi = wilson(k, n)
    return f"{k / n:.2f} [{lo:.2f}, {hi:.2f}] ({n})"


GOAL = {"pearson": 0.95, "mmrv": 0.03, "balanced_accuracy": 0.8}  # policy level; per start on the graded policies
GRADED = (0.15, 0.85)  # MuJoCo rates strictly between these: the policies whose starts the per-start goal reads


def _verdict(stats: dict) -> str:
    """The ranking goal, read off the figures: at the policy level, the mean Pearson and MMRV over the training
    seeds of the headline mode (``GATED_MODE``, motion+contact; lift judge) within ``GOAL``, with the baseline
    (``BASELINE_MODE``, action-vector) beside it."""
    def values(mode, name):
        runs = [m for m in stats if base_mode(m) == mode]
        got = [stats[m]["lift_geometry"]["levels"]["policy"][name]["value"] for m in runs]
        return [v for v in got if v is not None], len(runs)

    def mean(mode, name):
        got, runs = values(mode, name)
        spread = f" over {runs} seeds: {', '.join(_fmt(v) for v in got)}" if runs > 1 else ""
        return (float(np.mean(got)) if got and len(got) == runs else None), spread

    (p, p_seeds), (m, m_seeds) = mean(GATED_MODE, "pearson"), mean(GATED_MODE, "mmrv")
    if p is None and m is None:
        return f"**Goal.** Not measured: no `{GATED_MODE}` run, or its world-model rates do not vary."
    met = p is not None and m is not None and p >= GOAL["pearson"] and m <= GOAL["mmrv"]
    text = (f"**Goal** (policy level, lift judge, the mean over training seeds: Pearson >= {GOAL['pearson']} and "
            f"MMRV <= {GOAL['mmrv']} for `{GATED_MODE}`): {'met' if met else 'not met'} (Pearson {_fmt(p)}{p_seeds}; "
            f"MMRV {_fmt(m)}{m_seeds}).")
    if any(base_mode(x) == BASELINE_MODE for x in stats):
        text += (f" `{BASELINE_MODE}`: Pearson {_fmt(mean(BASELINE_MODE, 'pearson')[0])}, "
                 f"MMRV {_fmt(mean(BASELINE_MODE, 'mmrv')[0])}.")
    return text


def real_rates(plan: RankingPlan, r: dict) -> dict[str, float]:
    """MuJoCo's success rate of each policy over all its starts, from a report's results ``r``."""
    return {name: float(np.mean([o for g in range(plan.groups) for o in r["real"][f"{name}/g{g}"]]))
            for name in plan.names}


def _against_a_guess(plan: RankingPlan, r: dict) -> list[str]:
    """What a guess gets on the policy set, and how often the world model draws MuJoCo's outcome start by start."""
    rates = real_rates(plan, r)
    guess = best_two_level_guess(rates)
    graded = [n for n in plan.names if GRADED[0] < rates[n] < GRADED[1]]
    lines = ["", "### Against a guess", "",
             f"**The best two-level guess** (the policies split at a MuJoCo rate, each side given one value, the split "
             f"with the lowest MMRV): MMRV {_fmt(guess['mmrv'])}, guessing {', '.join(guess['high']) or 'none'} "
             "better. A world model ranks the set better than a guess only below that.", "",
             f"**Per start:** the balanced accuracy of the world model's verdict against MuJoCo's on the same starts "
             f"(0.5 for any verdict blind to the start; the goal is {GOAL['balanced_accuracy']} on the policies "
             f"MuJoCo puts strictly between {GRADED[0]} and {GRADED[1]}: "
             f"{', '.join(graded) if graded else 'none in this set'}).", "",
             "| mode | all policies | starts | graded policies | starts |", "|---|---|---|---|---|"]
    for mode in plan.modes:
        pairs = {n: verdict_pairs(plan, r, mode, n) for n in plan.names}
        cells = []
        for names in (plan.names, graded):
            both = [p for n in names for p in pairs[n]]
            cells += [_fmt(balanced_accuracy([a for a, _ in both], [b for _, b in both])), str(len(both))]
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    return lines


FAMILIES = {"scripted": "python:", "LeRobot": "lerobot:"}  # a policy's family, by its spec's prefix (noise aside)


def _by_family(plan: RankingPlan, r: dict) -> list[str]:
    """The LeRobot policies alone and the scripted ones alone (no goal of their own): policy-level Pearson,
    Spearman and MMRV of each mode (lift judge, point values), with the family's best two-level guess beside."""
    families = {f: [n for n, spec in zip(plan.names, plan.policies) if split_noisy(spec)[1].startswith(prefix)]
                for f, prefix in FAMILIES.items()}
    families = {f: names for f, names in families.items() if len(names) >= 3 and len(names) < len(plan.names)}
    if not families:
        return []
    rates = real_rates(plan, r)
    lines = ["", "### Each family alone", "", "The scripted policies alone and the LeRobot policies alone (policy "
             "level, lift judge; no goal of their own, no intervals):", "",
             "| family | policies | mode | Pearson | Spearman | MMRV | best two-level guess's MMRV |",
             "|---|---|---|---|---|---|---|"]
    for family, names in families.items():
        real = np.asarray([rates[n] for n in names])
        guess = best_two_level_guess({n: rates[n] for n in names})["mmrv"]
        for mode in plan.modes:
            pts = r["statistics"][mode]["lift_geometry"]["points"]
            wm = np.asarray([sum(p["world_model"] * p["n_world_model"] for p in pts if p["policy"] == n)
                             / sum(p["n_world_model"] for p in pts if p["policy"] == n) for n in names])
            cells = [_fmt(float(f(wm, real))) for f in (pearson, spearman, mmrv)]
            lines.append(f"| {family} | {len(names)} | {mode} | " + " | ".join(cells) + f" | {_fmt(guess)} |")
    return lines


def budget(plan: RankingPlan, r: dict) -> tuple[float, float, dict[str, float]]:
    """CPU and wall seconds in all, and per stage the CPU seconds its record lacks. The stage log records an
    invocation only when it ends, so a stage stopped and resumed misses its first part; the training runs' logs and
    the closed loops' own files (``cpu_s``) still hold theirs."""
    logged = {"train": 0.0 if plan.on_gpu else sum(t["train_s"] or 0 for t in r["training"].values()),
              "evaluate": sum(p.get("cpu_s") or 0 for e in r.get("evaluations", {}).values()
                              for p in e["policies"].values())}
    missed = {stage: max(0.0, s - r["stages"].get(stage, {}).get("cpu_s", 0.0)) for stage, s in logged.items()}
    missed = {stage: s for stage, s in missed.items() if s >= 60}
    return sum(s["cpu_s"] for s in r["stages"].values()) + sum(missed.values()), \
        sum(s["wall_s"] for s in r["stages"].values()), missed


_LOGGED_BY = {"train": "training that its runs logged", "evaluate": "closed loops that their files logged"}


def _header(plan: RankingPlan, r: dict) -> list[str]:
    m = r["machine"]
    cpu_total, wall_total, missed = budget(plan, r)
    flags, by_hand = command_flags(plan)
    make = {(): " `make ranking`, i.e.", ("--preset", "checkpoints"): " `make ranking-checkpoints`, i.e."}
    lines = [
        "# Policy ranking in simulation: does the world model rank policies the way MuJoCo does?", "",
        "Generated by" + make.get(tuple(flags), ""), "", "```bash",
        shlex.join(["python", "-m", "imac_model", "ranking", "--work", shown_path(plan.work), "--docs",
                    shown_path(plan.docs), *flags]), "```", "",
        *([f"with settings no flag gives, edited into its plan.json: {', '.join(by_hand)}", ""] if by_hand else []),
        f"(every stage cached under the work directory; a rerun resumes). Written {r['written']}, commit "
        f"`{r['commit']}`{' (with uncommitted changes)' if r['dirty'] else ''}. Protocol: `docs/ranking.md`.", "",
        f"**Machine.** {m['cores']} cores ({m['cpu']}), {m['memory_gb']} GB, "
        f"{'GPU ' + m['gpu'] if m['gpu'] else 'no GPU'}; Python {m['python']}, torch {m['torch']}.", "",
        f"**Budget.** {cpu_total / 60:.1f} CPU-minutes in all (process and children); per stage at the end"
        + (", where " + " and ".join(f"the {stage} stage's record lacks {s / 60:.1f} CPU-minutes of "
                                        f"{_LOGGED_BY[stage]}" for stage, s in missed.items())
           + " (a stage stopped before its end is recorded from its last start; the wall time of those minutes is "
           "not known)" if missed else "") + f". {wall_total / 60:.1f} minutes wall as recorded. "
        + "Training: "
        + (f"{plan.gpu_minutes:g} wall minutes per compared mode on one GPU (each run's own time under Training; "
           "not in the CPU total)" + (f", {plan.none_minutes:g} CPU-minutes for `none`." if "none" in plan.modes else ".")
           if plan.on_gpu else
           f"{plan.cpu_minutes:g} CPU-minutes per compared mode, {plan.none_minutes:g} for `none`.")
        + _policy_training(r), "",
        f"**Sizes.** {len(plan.policies)} policies; in MuJoCo {plan.groups} groups of {plan.real_per_group} starts "
        f"each; in the world model the first {plan.wm_per_group} starts of each group, {plan.chunks} chunks of 8 "
        f"frames (10 fps), {plan.steps} Euler steps; {plan.train_episodes} training rollouts"
        + _training_policies(plan) + ".", "",
    ]
    if r.get("shipped"):
        lines += ["**Shipped models.** " + "; ".join(
            f"`models/{run}.tar.xz` ({s['mode']}, {s['bytes'] / 2**20:.1f} MiB, SHA-256 {s['sha256'][:12]})"
            for run, s in r["shipped"].items()) + ": the float16 EMA weights every verdict below comes from. "
            "`imac-model ranking --from-models` ranks any policy with them, with no training (docs/ranking.md, "
            "\"The shipped world models\").", ""]
    return lines


def _policy_training(r: dict) -> str:
    """The LeRobot policies' own training, which the stage table does not hold (another work directory)."""
    runs = r.get("policy_training") or {}
    if not runs:
        return ""
    parts = [f"`{shown_path(Path(d))}` {sum(t['cpu_s'] for t in stages.values()) / 60:.1f} CPU-minutes ("
             + ", ".join(f"{k} {t['cpu_s'] / 60:.1f}" for k, t in stages.items()) + ")" for d, stages in runs.items()]
    return (" The LeRobot policies were trained before, outside these totals, as their runs' stage logs record: "
            + "; ".join(parts) + " (a stage at 0 found its work done when the log began).")


def _training(r: dict) -> list[str]:
    lines = ["", "## Training", "", "Per mode, from its log (the held-out loss: the flow loss of the held-out "
              "episodes' chunks at fixed times and noise, each from its recorded frame; with `flow.focus_weight` it is "
              "the weighted loss. A run trained with rollout or reference noise logs that harder loss as its "
              "training loss, so its curve can sit above the held-out one).", "",
              "| mode | backbone | parameters | device | steps | samples | training (s: GPU wall, or CPU) | rate | "
              "final held-out loss |", "|---|---|---|---|---|---|---|---|---|"]
    for mode, t in r["training"].items():
        lines.append(f"| {mode}{'' if t['finished'] else ' (training)'} | {t['backbone']} | "
                     f"{t['parameters'] / 1e6:.2f} M | {t['device']} | {t['steps']} | {t['samples'] or ''} | "
                     f"{_fmt(t['train_s'], 0)} | {t['rate']} | {_fmt(t['final_heldout_loss'], 4)} |")
    return lines + (["", "![training and held-out loss](training_loss.png)"] if r["training"] else [])


def _gate(plan: RankingPlan, r: dict) -> list[str]:
    """The gate's table (docs/ranking.md, "The early gate"): every mode's gates, if measured."""
    gates = r.get("gates") or {}
    if not gates:
        return []
    k = max(len(g["from_chunk"]) for rows in gates.values() for g in rows)
    when = (f"`{GATED_MODE}` trained first, alone, and was measured after every {plan.gate_every:g} CPU-minutes; "
            f"the other modes once, after training. Goal: {plan.gate_min:g} from chunk 1 by "
            f"{min(plan.gate_by, plan.cpu_minutes):g} CPU-minutes." if plan.gate_every else
            "Each mode measured once, after training.")
    lines = ["", "## The early gate", "",
             f"The recorded actions of the {plan.held_out} held-out training rollouts replayed in the world model, the "
             "lift judge against MuJoCo's labels. Balanced accuracy (mean recall of successes and failures: painting "
             "one outcome everywhere scores 0.5); \"from chunk k\": the replay starts again at the recorded frame of "
             f"chunk k (the drift before it taken away). Each replay is sampled with every noise seed and the "
             f"verdicts are pooled, since one seed decides many verdicts by itself. {when}", "",
             "| mode | budget (min) | step | episodes (successes) | seeds | "
             + " | ".join(f"from chunk {i + 1}" for i in range(k)) + " | accuracy from chunk 1 |", "|" + "---|" * (6 + k)]
    for mode, rows in gates.items():
        for g in rows:
            cells = [_fmt(g["from_chunk"][str(i)]["balanced_accuracy"], 2) if str(i) in g["from_chunk"] else ""
                     for i in range(k)]
            lines.append(f"| {mode} | {g['budget_minutes']:g} | {g['step']} | {len(g['labels'])} ({sum(g['labels'])}) | "
                         f"{g.get('seeds', 1)} | " + " | ".join(cells) + f" | {_fmt(g['from_chunk']['0']['accuracy'], 2)} |")
    cubes = [(mode, g) for mode, rows in gates.items() for g in rows if g.get("cube_at_chunk_end")]
    if cubes:
        n = max(len(c["kept"]) for _, g in cubes for c in cube_by_view(g).values())
        lines += ["", "Where the cube goes wrong, at the last frame of each chunk of the full replays (from chunk 1), in "
                  "each view: the share of replays whose generated view keeps at least half of the recorded "
                  "cube's pixels / the median distance (px) between the generated and recorded cubes' centres "
                  "(a successful lift moves the cube 12-17 px in the workspace view, `python -m benchmarks.workspace_view`):", "",
                  "| mode | budget (min) | step | view | " + " | ".join(f"end of chunk {i + 1}" for i in range(n)) + " |",
                  "|" + "---|" * (4 + n)]
        for mode, g in cubes:
            for view, c in cube_by_view(g).items():
                lines.append(f"| {mode} | {g['budget_minutes']:g} | {g['step']} | {view} | "
                             + " | ".join(f"{_fmt(k, 2)} / {_fmt(d, 1)}" for k, d in zip(c["kept"], c["offset_px"])) + " |")
    if plan.gate_every and GATED_MODE in gates:
        lines += ["", f"**Verdict:** {gate_verdict(plan, gates[GATED_MODE])}."]
    lines += ["", f"The latest gate of `{next(iter(gates))}` (workspace view; top recorded, bottom generated):", "",
              "![gate](gate.png)"]
    return lines


def verdict_pairs(plan: RankingPlan, r: dict, mode: str, name: str) -> list[tuple[bool, bool]]:
    """``(MuJoCo, world model)`` success of policy ``name`` from each of the world model's starts (the lift judge),
    from a report's results ``r``."""
    run = r["evaluations"][mode]["policies"].get(name) or next(iter(r["evaluations"][mode]["policies"].values()))
    pairs = []
    for start, row in zip(plan.wm_starts(), run["episodes"]):
        group, i = divmod(start, plan.real_per_group)
        pairs.append((bool(r["real"][f"{name}/g{group}"][i]), bool(row[JUDGE_COLUMNS["lift_geometry"]])))
    return pairs


def _start_by_start(plan: RankingPlan, r: dict) -> list[str]:
    """Where the verdicts part, policy by policy: MuJoCo's and the world model's on the same starts."""
    lines = ["", "### Start by start", "",
             "Each policy from the world model's starts, MuJoCo's outcome against the world model's (lift judge). The "
             "open-loop policies act on the first frame alone, which both runners share (the world model's through "
             "the dataset's video, within 1 % a pixel on average), so both get about the same actions from them: "
             "where their verdicts part, the world model drew another outcome of those actions.", "",
             "| mode | policy | starts | both succeed | world model only | MuJoCo only | both fail | agree |",
             "|---|---|---|---|---|---|---|---|"]
    for mode in plan.modes:
        for name in plan.names:
            pairs = verdict_pairs(plan, r, mode, name)
            counts = [sum(p == (real, wm) for p in pairs) for real, wm in
                      ((True, True), (False, True), (True, False), (False, False))]
            agree = (counts[0] + counts[3]) / len(pairs)
            lines.append(f"| {mode} | {name} | {len(pairs)} | " + " | ".join(map(str, counts)) + f" | {agree:.2f} |")
    return lines


def parting_chunks(plan: RankingPlan, r: dict, mode: str, name: str) -> dict | None:
    """Of policy ``name``'s starts where MuJoCo's verdict and the world model's part: how many first differ at the
    end of chunk k (``first_at_chunk``, k = 1, 2, ...) in whether the cube is held up, how many at no chunk end
    (only the judge's majority over the last frames differs), and the median over them of the largest difference
    between the two runs' actions up to that chunk (rad; large where the closed loop's own frames had already
    steered the policy elsewhere). None where the results lack the readings at the chunks' ends (runs evaluated
    before 2026-11-29) or ``mode`` did not run ``name``."""
    run = r["evaluations"][mode]["policies"].get(name)
    if run is None or not all("chunk_held" in row for row in run["episodes"]):
        return None
    first, gaps = [0] * (plan.chunks + 1), []
    for (real, wm), row in zip(verdict_pairs(plan, r, mode, name), run["episodes"]):
        if real != wm:
            k = next((k for k, (a, b) in enumerate(zip(row["chunk_held"], row["real_chunk_held"])) if a != b),
                     plan.chunks)
            first[k] += 1
            gaps.append(max(row["action_gap"][:k + 1]))
    return {"parted": sum(first), "first_at_chunk": first[:-1], "at_no_chunk_end": first[-1],
            "action_gap_median": float(np.median(gaps)) if gaps else None}


def _which_chunk(plan: RankingPlan, r: dict) -> list[str]:
    """Where the verdicts part, chunk by chunk (:func:`parting_chunks`); nothing for results without it."""
    found = {(mode, name): parting_chunks(plan, r, mode, name) for mode in plan.modes for name in plan.names}
    if not any(found.values()):
        return []
    chunks = " | ".join(f"chunk {k}" for k in range(1, plan.chunks + 1))
    lines = ["", "Which chunk: of the starts where the two verdicts part, the first chunk at whose last frame the world "
             "model holds the cube up where MuJoCo does not, or the reverse (the lift judge on that frame); \"at no "
             "chunk end\" where only the judge's majority over the last frames differs. The action gap: over those "
             "starts, the median of the largest difference between the two runs' actions up to that chunk (small "
             "where the policy acted alike in both, as the open-loop ones do, and the world model drew another "
             "outcome of the same actions).", "",
             f"| mode | policy | parted | {chunks} | at no chunk end | action gap by then (rad) |",
             "|---|---|---|" + "---|" * plan.chunks + "---|---|"]
    for (mode, name), f in found.items():
        if f:
            lines.append(f"| {mode} | {name} | {f['parted']} | " + " | ".join(map(str, f["first_at_chunk"]))
                         + f" | {f['at_no_chunk_end']} | "
                         + ("" if f["action_gap_median"] is None else f"{f['action_gap_median']:.3f}") + " |")
    return lines


def stopped_markdown(plan: RankingPlan, r: dict) -> str:
    """The report of a run that stopped at the early gate: what the gate showed, and the training."""
    lines = _header(plan, r)
    stopped = gate_verdict(plan, r["gates"].get(GATED_MODE, [])) == "stop" if plan.gate_every else False
    lines += [("**Stopped at the early gate**" if stopped else "**Not evaluated yet** (training goes on)")
              + ": no closed loop was run, so no ranking is reported. What the gates showed:"]
    lines += _gate(plan, r) + _training(r) + _stage_times(plan, r)
    return "\n".join(lines) + "\n"


def _stage_times(plan: RankingPlan, r: dict) -> list[str]:
    cpu_total, wall_total, missed = budget(plan, r)
    lines = ["", "## Time per stage", "", "| stage | CPU min | wall min | commit |", "|---|---|---|---|"]
    for stage, t in r["stages"].items():
        lines.append(f"| {stage} | {t['cpu_s'] / 60:.1f} | {t['wall_s'] / 60:.1f} | {', '.join(t['commits'])} |")
    for stage, s in missed.items():
        lines.append(f"| {_LOGGED_BY[stage]} beyond the {stage} stage's record | "
                     f"{s / 60:.1f} | not known | |")
    lines.append(f"| total | {cpu_total / 60:.1f} | {wall_total / 60:.1f} | |")
    return lines


def markdown(plan: RankingPlan, r: dict) -> str:
    lines = _header(plan, r)
    lines += ["## Success per policy", "",
              "MuJoCo's success (all starts) and the world model's (lift judge), with 95 % Wilson intervals and the "
              "number of episodes.", ""]
    header = "| policy | MuJoCo | " + " | ".join(plan.modes) + " |"
    lines += [header, "|" + "---|" * (2 + len(plan.modes))]
    first = r["statistics"][plan.modes[0]]["lift_geometry"]
    for name in plan.names:
        real = [p for p in first["points"] if p["policy"] == name]
        n_real = sum(p["n_real"] for p in real)
        rate_real = sum(p["real"] * p["n_real"] for p in real) / n_real
        cells = [_rate(rate_real * n_real, n_real)]
        for mode in plan.modes:
            pts = [p for p in r["statistics"][mode]["lift_geometry"]["points"] if p["policy"] == name]
            n = sum(p["n_world_model"] for p in pts)
            cells.append(_rate(sum(p["world_model"] * p["n_world_model"] for p in pts), n))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "## Rank agreement", "",
              "Per mode and judge, at the level of policies (each policy's starts pooled: the level of the goal) and "
              "of (policy, group) points; bootstrap 95 % intervals (bias-corrected), episodes resampled within each "
              "point. MMRV: SIMPLER's mean maximum rank violation, as its released code counts it (strict "
              "comparisons: a tie in the world model against a real difference is a violation; 0 is a perfect "
              "ranking).", "", "| mode | judge | level | points | " + " | ".join(STATISTICS) + " |",
              "|" + "---|" * (4 + len(STATISTICS))]
    for mode in plan.modes:
        for judge in r["statistics"][mode]:
            for level in ("policy", "group"):
                g = r["statistics"][mode][judge]["levels"][level]
                cells = [f"{_fmt(g[s]['value'])}{_ci(g[s]['ci'])}" for s in STATISTICS]
                lines.append(f"| {mode} | {judge} | {level} | {g['n_points']} | " + " | ".join(cells) + " |")
    lines += ["", _verdict(r["statistics"])] + _against_a_guess(plan, r) + _by_family(plan, r)
    for mode in plan.modes:
        lines += ["", f"![{mode}](scatter_{slug(mode.replace('+', '_'))}.png)"]
    lines += _start_by_start(plan, r) + _which_chunk(plan, r)
    lines += _training(r)
    lines += _gate(plan, r)
    j = r["judges"]
    # replays written before 2026-11-29 used one noise seed
    pooled = any(rec.get("seeds", 1) > 1 for ev in r["evaluations"].values() for rec in (ev.get("recorded") or {}).values())
    masked = j.get("cube_masked", {})  # judges measured before 2026-11-28 have no such check

    def _masked(judge: str) -> str:
        return _fmt(masked[judge]["balanced_accuracy"]) if judge in masked else "not measured"

    lines += ["", "## Judges", "", "Accuracy against MuJoCo's labels; the last column is the balanced accuracy on the "
              "same frames with the cube painted out (0.5 is chance: the judge reads the cube, not the arm).", "",
              "| judge | real evaluation episodes | classifier's own held-out split | cube painted out |",
              "|---|---|---|---|",
              f"| lift_geometry | {_fmt(j['real']['lift_geometry']['accuracy'])} "
              f"({j['real']['lift_geometry']['n']}) | | {_masked('lift_geometry')} |",
              (f"| classifier | {_fmt(j['real']['classifier']['accuracy'])} ({j['real']['classifier']['n']}) | "
               f"{_fmt(j['classifier_training']['heldout']['accuracy'])} "
               f"({j['classifier_training']['heldout']['n']} training rollouts) | {_masked('classifier')} |"
               if "classifier" in j["real"]
               else f"| classifier | not trained: {j['classifier_training']['skipped']} | | |"), "",
              "On generated rollouts of the recorded actions (real episodes replayed in the world model, judged on "
              "the generated frames" + ("; each episode with every noise seed, the verdicts pooled, each seed's own in "
                                        "brackets):" if pooled else ", one noise seed each):"),
              "", "| mode | Euler steps | episodes | lift_geometry | classifier |", "|---|---|---|---|---|"]

    def _replayed(rec: dict, judge: str) -> str:
        per_seed = (rec.get("accuracy_per_seed") or {}).get(judge) or []
        return _fmt(rec["accuracy"].get(judge)) + (f" [{', '.join(_fmt(a) for a in per_seed)}]" if len(per_seed) > 1
                                                   else "")

    for mode, ev in r["evaluations"].items():
        for steps, rec in (ev.get("recorded") or {}).items():
            seeds = rec.get("seeds", 1)  # replays written before 2026-11-29 used one seed
            lines.append(f"| {mode} | {steps} | {len(rec['episodes'])} ({sum(rec['labels'])} successes)"
                         f"{f' x {seeds} seeds' if seeds > 1 else ''} | {_replayed(rec, 'lift_geometry')} | "
                         f"{_replayed(rec, 'classifier')} |")
    lines += ["", "RGB error (MSE, [0, 1]) of those replays against the recording, per chunk of 8 frames, in each view "
                  "and over both; the controls of every chunk after the first are rebuilt from the generated depth:", "",
              "| mode | Euler steps | view | " + " | ".join(f"chunk {n + 1}" for n in range(plan.chunks)) + " |",
              "|" + "---|" * (3 + plan.chunks)]
    for mode, ev in r["evaluations"].items():
        for steps, rec in (ev.get("recorded") or {}).items():
            by_view = {**(rec.get("mse_per_chunk_by_view") or {}), "all views": rec["mse_per_chunk"]}
            for view, errors in by_view.items():
                lines.append(f"| {mode} | {steps} | {view} | " + " | ".join(_fmt(x, 4) for x in errors) + " |")
    lines += ["", "The same replays: RGB error over the pixels that move in the recording (`mse_moving`), the share of "
                  "generated depth that decodes to metres, its median error, and chunk 2's s2g contact image in the "
                  "workspace view painting the cube near a future gripper (rebuilt online from the generated depth / "
                  "recorded):", "", "| mode | Euler steps | moving-pixel MSE per chunk | depth valid per chunk | "
                  "median depth error (mm) | chunk-2 cube contact, rebuilt / recorded |", "|---|---|---|---|---|---|"]
    for mode, ev in r["evaluations"].items():
        for steps, rec in (ev.get("recorded") or {}).items():
            contact = rec.get("chunk2_cube_contact") or {}
            cells = [", ".join(_fmt(x, 4) for x in rec.get("mse_moving_per_chunk", [])),
                     ", ".join(_fmt(x, 4) for x in rec.get("depth_valid_per_chunk", [])),
                     ", ".join(f"{1000 * x:.0f}" for x in rec.get("depth_median_error_m_per_chunk", [])),
                     (f"{contact['rebuilt_present']} / {contact['recorded_present']} of {contact['replays']}"
                      if contact.get("replays") else "no contact stream")]
            lines.append(f"| {mode} | {steps} | " + " | ".join(cells) + " |")
    blind = next(((mode, ev["none_check"]) for mode, ev in r["evaluations"].items() if ev.get("none_check")), None)
    if blind:
        mode, none = blind
        lines += ["", f"**Negative control.** `{mode}` from the same starts and seeds gives bit-identical frames to "
                      f"{' and '.join(none['policies'])}: {none['bit_identical']} (starts {none['starts']}); it is run "
                      "once per start and its verdicts stand for every policy."]
    lines += ["", "## Action sensitivity", "",
              "Mean |difference| of two samples that differ only in the right arm's waist and shoulder actions, "
              "inside the region where their motion images differ and outside both robots (same noise).", "",
              "| mode | inside | outside | ratio | samples |", "|---|---|---|---|---|"]
    for mode, ev in r["evaluations"].items():
        s = ev["sensitivity"]
        lines.append(f"| {mode} | {_fmt(s['inside'], 4)} | {_fmt(s['outside'], 4)} | {_fmt(s['ratio'], 2)} | "
                     f"{s['samples']} |")
    if r["examples"]:
        lines += ["", "## Rollouts side by side", ""]
        for outcome, (policy, start) in r["examples"].items():
            lines += [f"A start where `{policy}` {'succeeded' if outcome == 'success' else 'failed'} in MuJoCo "
                      f"(start {start}): top MuJoCo, bottom the world model; views: {', '.join(plan.views)}.", "",
                      f"![{outcome}](rollout_{outcome}.png)", ""]
    lines += _stage_times(plan, r)
    return "\n".join(lines) + "\n"


def _training_policies(plan) -> str:
    """Which training rollouts the plan's ``training_policies`` ran (none: the scripted mix alone)."""
    if not plan.training_policies:
        return ""
    n = sum(plan.training_policy_of(i) is not None for i in range(plan.train_episodes))
    return f", {n} of them by {', '.join(f'`{p}`' for p in plan.training_policies)} in turn"
