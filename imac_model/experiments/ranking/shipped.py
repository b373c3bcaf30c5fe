"""The world models behind a ranking report, as the repository ships them, and a ranking from them with no training
(``imac-model ranking --from-models``; docs/ranking.md, "The shipped world models").

* the models are frozen as they ship by :mod:`~imac_model.experiments.ranking.freeze`, before evaluation;
* :func:`ship_models`: the archives of :data:`SHIPPED_MODES`, copied beside the report (``<docs>/models``).
* :func:`rerun_plan` and :func:`run_from_models`: the report's plan on other policies (or a few of its starts),
  with the shipped models in place of training; :func:`rerun_report` puts their rows beside the report's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import time
from pathlib import Path

import numpy as np

from imac_data.errors import InputError
from imac_model.evaluate.policies import lerobot_dir, with_lerobot_dir
from imac_model.evaluate.statistics import best_two_level_guess, policy_correlation
from imac_model.experiments.ranking.datasets import stage_build
from imac_model.experiments.ranking.evaluation import JUDGE_COLUMNS, policy_dir
from imac_model.experiments.ranking.freeze import unpack_run
from imac_model.experiments.ranking.plan import BASELINE_MODE, GATED_MODE, RankingPlan, internal, slug
from imac_model.experiments.ranking.simulate import stage_simulate
from imac_model.experiments.stages import REPO_ROOT, cpu_seconds, run_all
from imac_model.training.archive import archives_in, run_name

SHIPPED_MODES = (GATED_MODE, BASELINE_MODE)  # training seed 0's motion+contact, and the baseline at its budget
MODELS = "models"  # the report directory's folder of shipped models
REPORT = "results.json"  # the report a models folder belongs to, one level up
MAX_BYTES = 12 * 2**20  # one shipped model at most: the repository travels to a GPU machine within 64 MiB


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def ship_models(plan: RankingPlan) -> dict[str, dict]:
    """The archives of the plan's :data:`SHIPPED_MODES` copied to ``<docs>/models`` (any other archive there is
    removed: the folder holds the models of the report beside it). Returns ``{run: {"sha256", "bytes"}}``."""
    if not plan.evaluate_half:
        return {}
    out, shipped = plan.docs / MODELS, {}
    out.mkdir(parents=True, exist_ok=True)
    keep = [m for m in SHIPPED_MODES if m in plan.modes and plan.shipped_archive(m).is_file()]
    names = {plan.shipped_archive(m).name for m in keep}
    for old in archives_in(out):
        if old.name not in names:
            old.unlink()
    for mode in keep:
        src = plan.shipped_archive(mode)
        dest = out / src.name
        if not dest.is_file() or sha256(dest) != sha256(src):
            shutil.copy(src, dest)
        shipped[run_name(src)] = {"mode": mode, "sha256": sha256(dest), "bytes": dest.stat().st_size}
    return shipped


# --------------------------------------------------------------------------- --from-models


def _in_repo(value: str) -> str:
    """A path the committed report names relative to the repository, made absolute (``lerobot:`` specs too)."""
    if lerobot_dir(value):
        return with_lerobot_dir(value, _in_repo)
    return value if Path(value).is_absolute() else str(REPO_ROOT / value)


def read_report(models: Path) -> dict:
    saved = Path(models).parent / REPORT
    if not saved.is_file():
        raise InputError(f"--from-models {models}: no report beside it ({saved}); the shipped models live in the "
                         f"{MODELS}/ folder of the report they were evaluated for (docs/ranking/{MODELS})")
    return json.loads(saved.read_text())


def rerun_plan(models: Path, work: Path, docs: Path, policies: tuple[str, ...] = (),
               starts: int | None = None) -> RankingPlan:
    """The plan of the report beside ``models``, on ``policies`` (default: the report's) from its evaluation starts,
    or from the first ``starts`` of them, with the shipped models' modes. The report's first policy always runs
    first: its MuJoCo episodes give every policy's first frame, as in the report (the camera videos are coded
    lossily, so an episode's first frame depends on the frames after it)."""
    models = Path(models)
    report = read_report(models)
    data = dict(report["plan"])
    data.update(work=str(work), docs=str(docs), config=_in_repo(data["config"]),
                policies=[with_lerobot_dir(p, _in_repo) for p in data["policies"]])
    base = RankingPlan.from_dict(data)
    if not base.evaluate_half:
        raise InputError(f"{models.parent / REPORT}: this report evaluated float32 weights, so no model of it ships; "
                         "rank from a report written since 2026-12-01")
    runs = {run_name(a) for a in archives_in(models)} if models.is_dir() else set()
    modes = tuple(m for m in base.modes if base.run_dir(m).name in runs)
    if not modes:
        raise InputError(f"--from-models {models}: no run archive of the report's modes there "
                         f"({[base.run_dir(m).name + '.tar.xz' for m in base.modes]})")
    chosen = tuple(dict.fromkeys((base.policies[0], *(policies or base.policies))))
    sizes = {}
    if starts is not None:
        if not 0 < starts <= base.wm_per_group:
            raise InputError(f"--starts {starts}: the report ran {base.wm_per_group} starts of each group in the world "
                             "model; give 1 to that many (its first group's first starts)")
        sizes = {"groups": 1, "real_per_group": starts, "wm_per_group": starts}
    return dataclasses.replace(base, policies=chosen, modes=modes, **sizes)


def run_from_models(plan: RankingPlan, models: Path) -> None:
    """The evaluation side alone: every policy in MuJoCo from the plan's starts and built, the shipped models put in
    place of training, every policy closed loop in each; then :func:`rerun_report`."""
    t0, c0 = time.time(), cpu_seconds()
    stage_simulate(plan, ("eval",))
    stage_build(plan, ("eval",))
    for mode in plan.modes:
        archive = plan.shipped_archive(mode)
        src = Path(models) / archive.name
        if not archive.is_file() or sha256(archive) != sha256(src):
            archive.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, archive)
            shutil.rmtree(plan.wm_dir(mode), ignore_errors=True)  # evaluations of another model
            unpack_run(archive, plan.evaluated_model(mode))
    run_all([(f"evaluate {m} {slug(p)}", internal(plan, "evaluate", m, p),
              plan.work / "logs" / f"evaluate_{slug(m.replace('+', '_'))}_{slug(p)}.log")
             for m in plan.modes for p in plan.policies
             if not (policy_dir(plan, m, p) / "closed_loop.json").is_file()], plan.jobs, tag="ranking")
    rerun_report(plan, read_report(models), wall_s=time.time() - t0, cpu_s=cpu_seconds() - c0)


def _verdicts(plan: RankingPlan, rows: list[dict], starts: list[int]) -> dict[int, bool]:
    """Evaluation seed -> lift-judge verdict, for rows in the order of ``starts`` (indices into eval_seeds)."""
    seeds = plan.eval_seeds()
    return {seeds[s][1]: bool(r[JUDGE_COLUMNS["lift_geometry"]]) for s, r in zip(starts, rows)}


def _mujoco(plan: RankingPlan, name: str) -> dict[int, bool]:
    rows = json.loads((plan.sim_dir(name) / "outcomes.json").read_text())["episodes"]
    return {seed: bool(r["success"]) for (_, seed), r in zip(plan.eval_seeds(), rows)}


def _report_side(report: dict) -> tuple[RankingPlan, dict]:
    """The report's plan, and per policy its MuJoCo outcomes and each mode's verdicts, by evaluation seed."""
    base = RankingPlan.from_dict({**report["plan"], "work": ".", "docs": "."})
    seeds = base.eval_seeds()
    side = {}
    for name in base.names:
        real = {}
        for g in range(base.groups):
            group = [s for gg, s in seeds if gg == f"g{g}"]
            real.update(zip(group, report["real"][f"{name}/g{g}"]))
        wm = {mode: _verdicts(base, e["policies"][name]["episodes"], base.wm_starts())
              for mode, e in report["evaluations"].items() if name in e["policies"]}
        side[name] = {"real": real, "wm": wm}
    return base, side


def rerun_report(plan: RankingPlan, report: dict, wall_s: float = 0.0, cpu_s: float = 0.0) -> Path:
    """``<docs>/README.md`` and ``rerun.json``: each policy's MuJoCo rate and each shipped model's, beside the report's
    where the report ranked the policy, how many per-start verdicts equal the report's, and, from the report's whole
    set of starts, the ranking statistics over the report's policies with this run's rows added or replacing theirs."""
    base, theirs = _report_side(report)
    wm_seeds = [plan.eval_seeds()[s][1] for s in plan.wm_starts()]
    rows = {}
    for name in plan.names:
        real = _mujoco(plan, name)
        row = {"real": [real[s] for s in wm_seeds], "modes": {}}
        for mode in plan.modes:
            ours = _verdicts(plan, json.loads((policy_dir(plan, mode, name) / "closed_loop.json").read_text())
                             ["episodes"], plan.wm_starts())
            entry = {"verdicts": [ours[s] for s in wm_seeds]}
            reported = theirs.get(name, {}).get("wm", {}).get(mode)
            if reported is not None:
                entry["same_as_report"] = sum(ours[s] == reported[s] for s in wm_seeds)
            row["modes"][mode] = entry
        if name in theirs:
            row["real_same_as_report"] = sum(real[s] == theirs[name]["real"][s] for s in wm_seeds)
        rows[name] = row
    whole = sorted(wm_seeds) == sorted(base.eval_seeds()[s][1] for s in base.wm_starts())
    stats = _union_statistics(plan, base, theirs, rows) if whole else {}
    out = {"report": {k: report.get(k) for k in ("commit", "written")}, "models": {
        plan.shipped_archive(m).name: sha256(plan.shipped_archive(m)) for m in plan.modes},
        "seeds": wm_seeds, "policies": rows, "statistics": stats,
        "wall_s": round(wall_s, 1), "cpu_s": round(cpu_s, 1)}
    plan.docs.mkdir(parents=True, exist_ok=True)
    (plan.docs / "rerun.json").write_text(json.dumps(out, indent=1))
    (plan.docs / "README.md").write_text(_rerun_markdown(plan, report, out))
    return plan.docs / "README.md"


def _union_statistics(plan: RankingPlan, base: RankingPlan, theirs: dict, rows: dict) -> dict:
    """Per shipped mode, the report's policies with this run's rows added (or replacing theirs): the policy-level
    statistics (:func:`~imac_model.evaluate.statistics.policy_correlation`, the report's bootstrap), and the best
    two-level guess on the same set."""
    wm_seeds = [base.eval_seeds()[s][1] for s in base.wm_starts()]
    out = {}
    for mode in plan.modes:
        real, wm = {}, {}
        for name, side in theirs.items():
            if mode in side["wm"]:
                real[name], wm[name] = [side["real"][s] for s in wm_seeds], [side["wm"][mode][s] for s in wm_seeds]
        for name, row in rows.items():
            order = [plan.eval_seeds()[s][1] for s in plan.wm_starts()]
            by_seed = dict(zip(order, row["real"])), dict(zip(order, row["modes"][mode]["verdicts"]))
            real[name], wm[name] = [by_seed[0][s] for s in wm_seeds], [by_seed[1][s] for s in wm_seeds]
        corr = policy_correlation(wm, real, replicates=2000, seed=plan.seed)["levels"]["policy"]
        guess = best_two_level_guess({k: float(np.mean(v)) for k, v in real.items()})
        out[mode] = {"policies": sorted(real), "pearson": corr["pearson"]["value"],
                     "spearman": corr["spearman"]["value"], "mmrv": corr["mmrv"]["value"],
                     "best_two_level_guess_mmrv": guess["mmrv"]}
    return out


def _rate(values: list[bool]) -> str:
    return f"{np.mean(values):.2f}" if values else "-"


def _rerun_markdown(plan: RankingPlan, report: dict, out: dict) -> str:
    n = len(out["seeds"])
    lines = [f"# Ranking from the shipped world models ({', '.join(plan.modes)})", "",
             f"The models of the report written {report.get('written')} at commit {report.get('commit')} "
             f"({', '.join(f'`{k}` {v[:12]}' for k, v in out['models'].items())}), with no training: {n} start{'s' if n > 1 else ''} a "
             f"policy (evaluation seeds {out['seeds'][0]}..{out['seeds'][-1]}), in {out['wall_s'] / 60:.1f} min wall "
             f"and {out['cpu_s'] / 60:.1f} CPU-minutes. Verdicts are the lift judge's; \"as the report\" counts the "
             "starts where this run's verdict equals the report's.", ""]
    head = ["policy", "MuJoCo", "as the report"] + [x for m in plan.modes for x in (m, "as the report")]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, row in out["policies"].items():
        same = row.get("real_same_as_report")
        cells = [name, _rate(row["real"]), "new" if same is None else f"{same}/{n}"]
        for mode in plan.modes:
            e = row["modes"][mode]
            cells += [_rate(e["verdicts"]), f"{e['same_as_report']}/{n}" if "same_as_report" in e else "new"]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    if out["statistics"]:
        lines += ["Over the report's policies with this run's rows added (policy level; MMRV as the report counts it):",
                  "", "| mode | policies | Pearson | Spearman | MMRV | best two-level guess's MMRV |", "|---|---|---|---|---|---|"]
        for mode, s in out["statistics"].items():
            f = [("-" if s[k] is None else f"{s[k]:.3f}") for k in ("pearson", "spearman", "mmrv",
                                                                   "best_two_level_guess_mmrv")]
            lines.append(f"| {mode} | {len(s['policies'])} | " + " | ".join(f) + " |")
    else:
        lines.append(f"These are {n} of the report's starts: the ranking statistics need all of them.")
    return "\n".join(lines) + "\n"


__all__ = ["MAX_BYTES", "MODELS", "SHIPPED_MODES", "rerun_plan", "rerun_report", "run_from_models",
           "ship_models"]
