"""The ranking benchmark's report: ``README.md``, ``results.json`` and figures in ``--docs``,
written from the work directory's outputs only; nothing is typed in by hand. This module collects the
results and draws the figures; :mod:`.report_text` writes the text from the results alone."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from imac_data import lerobot_compat as lr
from imac_data.errors import InputError
from imac_data.layout import image_key
from imac_model.evaluate.pictures import label
from imac_model.evaluate.policies import lerobot_dir, with_lerobot_dir
from imac_model.evaluate.statistics import plot_policy_scatter, policy_correlation
from imac_model.experiments.ranking.evaluation import JUDGE_COLUMNS
from imac_model.experiments.ranking.gate import read_gates
from imac_model.experiments.ranking.plan import EVAL_REPO, RankingPlan, run_mode, slug
from imac_model.experiments.ranking.report_text import markdown, shown_path, stopped_markdown
from imac_model.experiments.ranking.shipped import ship_models
from imac_model.experiments.stages import REPO_ROOT, StageLog, git, machine
from imac_model.models.checkpoint import list_checkpoints, read_spec
from imac_model.models.world_model import WorldModel
from imac_model.training.log import read_log


def real_outcomes(plan: RankingPlan) -> dict[tuple[str, str], list[bool]]:
    """MuJoCo's success per (policy, group), from the simulator runs."""
    out: dict[tuple[str, str], list[bool]] = {}
    groups = [g for g, _ in plan.eval_seeds()]
    for name in plan.names:
        rows = json.loads((plan.sim_dir(name) / "outcomes.json").read_text())["episodes"]
        for g, row in zip(groups, rows):
            out.setdefault((name, g), []).append(bool(row["success"]))
    return out


def world_model_outcomes(plan: RankingPlan, mode: str, judge: str) -> dict[tuple[str, str], list[bool]]:
    """The world model's success per (policy, group) under ``judge``; ``none`` judged its one
    run, which stands for every policy (its frames do not depend on the policy)."""
    result = json.loads((plan.wm_dir(mode) / "outcomes.json").read_text())
    groups = [plan.eval_seeds()[s][0] for s in plan.wm_starts()]
    out = {}
    for name in plan.names:
        run = result["policies"].get(name) or next(iter(result["policies"].values()))
        for g, row in zip(groups, run["episodes"]):
            out.setdefault((name, g), []).append(bool(row[JUDGE_COLUMNS[judge]]))
    return out


def shown_mode(plan: RankingPlan) -> str:
    """The mode whose rollouts the report pictures: of the plan's modes, the one with the most control streams,
    else one with the action vector, else the first (read off the registry: motion+contact before motion before
    action-vector)."""
    return max(plan.modes, key=lambda m: (len(run_mode(m).streams), run_mode(m).action_vector))


def judges_of(plan: RankingPlan) -> list[str]:
    """The judges that ran (the classifier needs training rollouts of both outcomes)."""
    return [j for j in JUDGE_COLUMNS if j != "classifier" or (plan.work / "judges" / "classifier").is_dir()]


def _correlations(plan: RankingPlan, real: dict) -> dict:
    return {mode: {judge: policy_correlation(world_model_outcomes(plan, mode, judge), real, replicates=2000,
                                             seed=plan.seed)
                   for judge in judges_of(plan)} for mode in plan.modes}


# --------------------------------------------------------------------------- figures


def _frames(root: Path, repo: str, episode: int, views, times, size: tuple[int, int]) -> list[np.ndarray]:
    """Frames ``times`` of ``episode`` as uint8 HWC at ``size`` per view (what the policies see),
    the views side by side."""
    ds = lr.LeRobotDataset(repo, root=root)
    lo = int(ds.meta.episodes["dataset_from_index"][episode])
    rows = []
    for t in times:
        item = ds[lo + t]
        views_img = [torch.nn.functional.interpolate(item[image_key(v)][None].float(), size=size, mode="bilinear",
                                                     antialias=True)[0] for v in views]
        rows.append((torch.cat(views_img, -1).clamp(0, 1) * 255).round().byte().permute(1, 2, 0).numpy())
    return rows


def side_by_side(plan: RankingPlan, mode: str, policy: str, start: int, path: Path, scale: int = 3) -> None:
    """Real (MuJoCo) and generated frames of one start, every chunk's last frame."""
    H = 8
    times = [0] + [H * (n + 1) for n in range(plan.chunks)]
    p = plan.names.index(policy)
    real = _frames(plan.eval_dataset, EVAL_REPO, plan.eval_episode(p, plan.wm_starts()[start]), plan.views, times,
                   plan.view_size)
    gen_root = plan.wm_dir(mode) / policy
    gen = _frames(gen_root, f"local/{gen_root.name}", start, plan.views, times, plan.view_size)
    rows = []
    for name, frames in (("MuJoCo", real), (f"world model ({mode})", gen)):
        cells = [label(cv2.resize(f, (f.shape[1] * scale, f.shape[0] * scale), interpolation=cv2.INTER_NEAREST),
                       f"{name} t={t}") for f, t in zip(frames, times)]
        rows.append(np.concatenate(cells, axis=1))
    img = np.concatenate(rows, axis=0)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def _examples(plan: RankingPlan, real: dict, mode: str) -> dict[str, tuple[str, int]]:
    """One start where the first policy that has both outcomes in MuJoCo succeeded, one where it failed."""
    starts = plan.wm_starts()
    groups = [g for g, _ in plan.eval_seeds()]
    for name in plan.names:
        per_start = []
        for s in starts:
            g = groups[s]
            per_start.append(real[(name, g)][s - groups.index(g)])
        if any(per_start) and not all(per_start):
            return {"success": (name, per_start.index(True)), "failure": (name, per_start.index(False))}
    return {}


# --------------------------------------------------------------------------- the report


def write_report(plan: RankingPlan) -> Path:
    docs = plan.docs
    docs.mkdir(parents=True, exist_ok=True)
    stages = StageLog(plan.work / "stages.json").totals()
    trained = [m for m in plan.modes if (plan.run_dir(m) / "log.jsonl").is_file()]
    training = {m: training_log(plan.run_dir(m)) for m in trained}
    if training:
        plot_training(training, docs / "training_loss.png")
    gates = {m: rows for m in plan.modes if (rows := read_gates(plan, m))}
    shown_gate = next(iter(gates), None)  # motion+contact's, when it has any
    if shown_gate:
        latest = plan.run_dir(shown_gate) / f"gate_{gates[shown_gate][-1]['step']:06d}.png"
        if latest.is_file():
            shutil.copy(latest, docs / "gate.png")
    shown_plan = {k: (shown_path(Path(v)) if k in ("work", "docs", "config") else v) for k, v in plan.to_dict().items()}
    results = {"plan": shown_plan, "machine": machine(), "commit": git("rev-parse", "--short", "HEAD"),
               "dirty": _uncommitted_changes(docs), "written": time.strftime("%Y-%m-%d %H:%M"), "stages": stages,
               "gates": gates, "training": {m: {k: v for k, v in t.items() if k != "rows"} for m, t in training.items()},
               "policy_training": policy_training(plan)}
    if not all((plan.wm_dir(m) / "outcomes.json").is_file() for m in plan.modes):  # stopped at the early gate
        (docs / "results.json").write_text(json.dumps(_relative(results), indent=1, default=str))
        (docs / "README.md").write_text(stopped_markdown(plan, results))
        return docs / "README.md"
    real = real_outcomes(plan)
    stats = _correlations(plan, real)
    for mode in plan.modes:
        plot_policy_scatter(stats[mode]["lift_geometry"], docs / f"scatter_{slug(mode.replace('+', '_'))}.png",
                            title=f"{mode}: world model vs MuJoCo (lift judge)")
    shown = shown_mode(plan)
    examples = _examples(plan, real, shown)
    for outcome, (policy, start) in examples.items():
        side_by_side(plan, shown, policy, start, docs / f"rollout_{outcome}.png")
    results.update(shipped=ship_models(plan), real={f"{p}/{g}": v for (p, g), v in real.items()}, statistics=stats,
                   judges=json.loads((plan.work / "judges" / "real.json").read_text()),
                   evaluations={m: json.loads((plan.wm_dir(m) / "outcomes.json").read_text()) for m in plan.modes},
                   examples=examples)
    (docs / "results.json").write_text(json.dumps(_relative(results), indent=1, default=str))
    (docs / "README.md").write_text(markdown(plan, results))
    return docs / "README.md"


def rewrite_report(docs: Path) -> Path:
    """``docs/README.md`` written again from ``docs/results.json`` alone (no work directory, no pictures
    redrawn): a report kept in the repository follows a change of the report's text or tables."""
    saved = Path(docs) / "results.json"
    if not saved.is_file():
        raise InputError(f"{saved}: no report's results to write the report from (run the report stage first)")
    results = json.loads(saved.read_text())
    plan = RankingPlan.from_dict(results["plan"])
    done = "evaluations" in results  # otherwise the run stopped at the early gate, or trains on
    (Path(docs) / "README.md").write_text(markdown(plan, results) if done else stopped_markdown(plan, results))
    return Path(docs) / "README.md"


def training_log(run: Path) -> dict:
    """A trained run's log (``log.jsonl``): its rows with a loss, and a summary (steps, chunks trained, device,
    final held-out loss)."""
    rows = read_log(run)
    last = next((r for r in reversed(rows) if "step" in r), {})
    held = [r for r in rows if r.get("heldout_loss") is not None]
    steps, device = last.get("step"), last.get("device", "cpu")
    train_s = last.get("cpu_s" if device == "cpu" else "wall_s")  # GPU wall s, or CPU s
    spec = read_spec(list_checkpoints(run)[-1])
    backbone = getattr(spec.backbone, spec.backbone.kind)
    shape = (f"U-Net {list(backbone.channels)} x {backbone.blocks} blocks" if spec.backbone.kind == "unet"
             else spec.backbone.kind)
    parameters = sum(p.numel() for p in WorldModel(spec).parameters() if p.requires_grad)
    rate = (f"{train_s / steps:.2f} CPU-s/step" if device == "cpu" else
            f"{last['samples'] / train_s:.0f} samples/s" if last.get("samples") else "") if steps and train_s else ""
    return {"rows": [r for r in rows if "step" in r], "steps": steps, "samples": last.get("samples"),
            "device": device, "finished": (run / "DONE.json").is_file(), "train_s": train_s,
            "backbone": shape, "parameters": int(parameters), "rate": rate,
            "final_heldout_loss": held[-1]["heldout_loss"] if held else None,
            "heldout": [(r["step"], r["heldout_loss"]) for r in held]}


def plot_training(training: dict, path: Path) -> None:
    """Training loss (a running mean over up to 20 logs) and held-out loss against the step, one colour per mode."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # matplotlib is heavy: imported by the report only
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for k, (mode, t) in enumerate(training.items()):
        colour = f"C{k}"
        train = [(r["step"], r["loss"]) for r in t["rows"] if r.get("loss") is not None]
        if train:
            steps, loss = map(np.asarray, zip(*train))
            window = max(1, min(20, len(loss) // 8))  # a short GPU log keeps its first steps in the plot
            smooth = np.convolve(loss, np.ones(window) / window, mode="valid")
            ax.plot(steps[len(steps) - len(smooth):], smooth, color=colour, alpha=0.6, label=f"{mode}: training")
        if t["heldout"]:
            ax.plot(*zip(*t["heldout"]), "o-", color=colour, label=f"{mode}: held out")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("flow loss")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def policy_training(plan: RankingPlan) -> dict[str, dict]:
    """The stage totals of the runs that trained the plan's LeRobot policies (``benchmarks.lerobot_policy``'s
    ``stages.json``, found above each checkpoint), by run directory: the budget counts the policies' training too."""
    out = {}
    for spec in plan.policies:
        found = lerobot_dir(spec) and next((d for d in Path(lerobot_dir(spec)).parents
                                            if (d / "stages.json").is_file()), None)
        if found and str(found) not in out:
            out[str(found)] = StageLog(found / "stages.json").totals()
    return out


def _uncommitted_changes(docs: Path) -> bool:
    """Whether tracked files differ from the commit, the report's own directory aside."""
    docs = docs.resolve()
    own = [f":(exclude){docs.relative_to(REPO_ROOT)}"] if docs.is_relative_to(REPO_ROOT) else []
    return git("status", "--porcelain", "--untracked-files=no", "--", ".", *own) not in ("", "unknown")


def _relative(value):
    """``value`` with every path inside the repository (a string or a Path, at any depth) made relative
    to it, so a committed ``results.json`` names no machine's directories."""
    if isinstance(value, dict):
        return {k: _relative(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_relative(v) for v in value]
    if isinstance(value, str) and lerobot_dir(value):  # a policy spec
        return with_lerobot_dir(value, _relative)
    if isinstance(value, (str, Path)) and Path(value).is_absolute() and Path(value).is_relative_to(REPO_ROOT):
        return shown_path(Path(value))
    return value


