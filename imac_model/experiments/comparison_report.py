"""The report of :mod:`imac_model.experiments.comparison`: ``docs/experiment/`` with README.md (tables,
command, budget, machine, commit, stage timings), results.json and the figures
(loss curves, error growth, rollout mosaics, action sensitivity). Everything in it is read
from the experiment's work directory; nothing is typed in by hand.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from imac_data.layout import SUCCESS_COLUMN, episodes_dir
from imac_model.data import meta as dataset_meta
from imac_model.evaluate.pictures import label
from imac_model.experiments.stages import git, machine
from imac_model.modes import MODES
from imac_model.training.log import read_log


def _fmt(x, digits=4):
    if x is None:
        return "n/a"
    if isinstance(x, float) and not np.isfinite(x):
        return "inf"
    return f"{x:.{digits}f}"


# --------------------------------------------------------------------------- figures


def _hwc(x) -> np.ndarray:
    return x.permute(1, 2, 0).numpy() if hasattr(x, "permute") else np.asarray(x)


def _save(img: np.ndarray, path: Path) -> None:
    import cv2

    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def rollout_figure(samples: dict, H: int, path: Path, scale: int = 2) -> None:
    """Rows: recorded, then each setting; columns: the last frame of chunks 1..N (RGB over depth)."""
    names = list(samples)
    first = samples[names[0]]
    n = first["generated"].shape[0] // H
    rows = []
    for row, key, src in [("recorded", "recorded", first)] + [(s, "generated", samples[s]) for s in names]:
        cells = [_hwc(src[key][(c + 1) * H - 1]) for c in range(n)]
        cells = [np.kron(c, np.ones((scale, scale, 1), np.uint8)) for c in cells]
        cells = [label(c, f"{row}, chunk {i + 1}" if i == 0 else f"chunk {i + 1}", scale=0.38)
                 for i, c in enumerate(cells)]
        rows.append(np.concatenate(cells, axis=1))
    _save(np.concatenate(rows, axis=0), path)


def sensitivity_figure(samples: dict, path: Path, scale: int = 2) -> None:
    """Rows: settings; columns: motion image A, B, generated A, B, |A - B| x 4 (RGB row, last frame)."""
    rows = []
    for name, s in samples.items():
        ex = s.get("sensitivity") or {}
        if not ex:
            continue
        cells = [ex["motion_a"], ex["motion_b"], ex["generated_a"], ex["generated_b"]]
        cells = [_hwc(c) for c in cells]
        diff = _hwc(ex["difference"][None].expand(3, -1, -1))
        cells.append(diff)
        cells = [np.kron(c, np.ones((scale, scale, 1), np.uint8)) for c in cells]
        titles = ["motion A (recorded)", "motion B (offset)", f"{name}: A", f"{name}: B", "|A - B| x4"]
        rows.append(np.concatenate([label(c, t, scale=0.38) for c, t in zip(cells, titles)], axis=1))
    if rows:
        _save(np.concatenate(rows, axis=0), path)


def loss_figure(logs: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4))
    ax1, ax2 = fig.subplots(1, 2)
    for name, rows in logs.items():
        held = [(r["cpu_s"] / 60, r["heldout_loss"]) for r in rows if "heldout_loss" in r]
        train = [(r["cpu_s"] / 60, r["loss"]) for r in rows if "loss" in r]
        if held:
            ax1.plot(*zip(*held), marker=".", label=name)
        if train:
            x, y = zip(*train)
            k = max(1, len(y) // 40)
            ys = np.convolve(y, np.ones(k) / k, mode="valid")
            ax2.plot(x[k - 1:], ys, label=name)
    ax1.set(xlabel="training CPU minutes", ylabel="held-out flow loss (fixed tau, noise)", yscale="log",
            title="held-out loss (single chunks, recorded references)")
    ax2.set(xlabel="training CPU minutes", ylabel="training loss (rolling mean)", yscale="log",
            title="training loss (rollout: mean over its R chunks)")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def growth_figure(results: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 3.6))
    axes = fig.subplots(1, 3)
    for name, r in results.items():
        n = range(1, len(r["chunks"]) + 1)
        for ax, m in zip(axes, ("mse", "psnr", "ssim")):
            ax.plot(n, [c[m] for c in r["chunks"]], marker="o", label=name)
    first = next(iter(results.values()))
    axes[0].plot(range(1, len(first["copy_reference_mse"]) + 1), first["copy_reference_mse"], "k--",
                 label="copy the first reference")
    for ax, m in zip(axes, ("MSE", "PSNR (dB)", "SSIM")):
        ax.set(xlabel="chunk of the rollout", ylabel=m, xticks=list(range(1, len(first["chunks"]) + 1)))
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


# --------------------------------------------------------------------------- the report


def write_report(plan, settings) -> Path:
    import torch

    docs = plan.docs
    docs.mkdir(parents=True, exist_ok=True)
    results, samples, logs = {}, {}, {}
    for s in settings:
        f = plan.eval_file(s)
        if not f.is_file():
            continue
        results[s.name] = json.loads(f.read_text())
        samples[s.name] = torch.load(f.with_suffix(".pt"), weights_only=False)
        logs[s.name] = read_log(plan.run_dir(s))
    if not results:
        raise RuntimeError("no evaluated setting to report")
    H = dataset_meta.contact_chunk_size(plan.dataset)
    import pyarrow.parquet as pq

    episodes = pq.read_table(sorted(episodes_dir(plan.dataset).rglob("*.parquet"))).to_pydict()
    success = [bool(x) for x in episodes[SUCCESS_COLUMN]]
    lengths = [int(x) for x in episodes["length"]]
    held = plan.held_out_episodes
    stages = json.loads((plan.work / "stages.json").read_text()) if (plan.work / "stages.json").is_file() else []
    build_t = (json.loads((plan.work / "build_timings.json").read_text())
               if (plan.work / "build_timings.json").is_file() else {})
    mach = machine()
    commit, dirty = git("rev-parse", "--short", "HEAD"), bool(git("status", "--porcelain", "--untracked-files=no"))

    loss_figure(logs, docs / "loss_curves.png")
    growth_figure(results, docs / "error_growth.png")
    rollout_figure(samples, H, docs / "rollouts.png")
    sensitivity_figure(samples, docs / "sensitivity.png")

    first = next(iter(results.values()))
    n = len(first["chunks"])
    L = []
    L += ["# The iMaC comparison at small scale: simulated cube transfer on a CPU", "",
          "Generated by `make experiment`, i.e.", "",
          "```bash", f"imac-model experiment --work {plan.work} --docs {plan.docs}", "```", "",
          f"(every stage cached under the work directory; a rerun resumes). Report written "
          f"{time.strftime('%Y-%m-%d %H:%M')}, commit `{commit}`{' (with uncommitted changes)' if dirty else ''}.",
          "", "## Setup", "",
          f"* **Data.** {len(success)} simulated ALOHA cube-transfer episodes (scripted policy, noise 0.5), "
          f"{sum(success)} successes, {int(np.sum(lengths))} frames at 96x128 per view, 25 fps, built with "
          f"`imac build` (`recipes/aloha_sim_transfer_cube_experiment.yaml`; contact chunk H = {H}). "
          f"Held out: episodes {held[0]}-{held[-1]} ({sum(success[e] for e in held)} successes, "
          f"{sum(not success[e] for e in held)} failures); the others train every setting.",
          "* **Model.** The small video DiT of `imac_model/configs/experiment.yaml` (as `small_cpu.yaml`): "
          "48x64 per view (mosaic 96x192, RGB over colour depth), 1 reference + 8 future frames, x-prediction, "
          f"EMA weights, {first['protocol'].get('sampler_steps')} Euler steps at evaluation.",
          f"* **Budget.** Each setting trains for {plan.cpu_minutes:g} minutes of process CPU time on one thread "
          f"(`train.max_cpu_minutes`), {plan.jobs} settings at a time. CPU time, not wall time, is the budget, so "
          "the settings get the same compute whatever else runs on the machine.",
          "* **Settings.** " + "".join(f"`{s.name}` ({MODES[s.name].label}), " for s in settings if s.name in MODES)
          + "and `motion+contact + rollout`: "
          "the same model trained with training-time rollout, R = 4 chunks per clip after a warm-up of "
          f"{plan.warmup_epochs:g} epochs of ordinary steps (`rollout.chunks: 4`, `rollout.warmup_epochs: "
          f"{plan.warmup_epochs:g}`); chunk r > 1 starts from the "
          "decoded last frame of chunk r-1's one-step clean estimate, its contact images rebuilt online from "
          "that frame's depth, loss (1/R) sum_r L_r.",
          f"* **Evaluation.** {first['rollouts']} rollouts of {n} chunks ({n * H} frames) from recorded reference "
          f"frames of the held-out episodes (every {n}th chunk, whole rollouts inside the episode). Chunk 1 gets "
          "the dataset's control images; chunks 2-4 start from the last generated frame, with motion and contact "
          "images rebuilt online from the generated depth and the recorded actions, the robot state at each "
          "boundary being the last commanded configuration (as in a closed loop). MSE, PSNR and SSIM "
          "(`imac_model.evaluate.video_metrics`) on the RGB views, pooled over the views' mosaic; the same noise "
          "seed for every setting.", "",
          f"* **Machine.** {mach['cores']} cores ({mach['cpu']}), {mach['memory_gb']} GB, no GPU"
          f"{'' if not mach['gpu'] else ' (' + mach['gpu'] + ')'}; Python {mach['python']}, torch {mach['torch']}. "
          "The machine was shared: load averages per stage are below.", ""]

    L += ["## First chunk (from recorded references)", "",
          "| setting | MSE | PSNR (dB) | SSIM |", "|---|---|---|---|"]
    for name, r in results.items():
        c = r["chunks"][0]
        L.append(f"| {name} | {_fmt(c['mse'])} | {_fmt(c['psnr'], 2)} | {_fmt(c['ssim'], 3)} |")
    L.append(f"| copy the reference forward | {_fmt(first['copy_reference_mse'][0])} | | |")
    L += ["", f"## {n}-chunk rollouts", "",
          "MSE per chunk of the rollout, and its growth relative to chunk 1:", "",
          "| setting | " + " | ".join(f"chunk {i + 1}" for i in range(n)) + " | growth chunk 2 / 3 / 4 |",
          "|---|" + "---|" * (n + 1)]
    for name, r in results.items():
        g = " / ".join(f"x{x:.2f}" for x in r["mse_growth"][1:])
        L.append(f"| {name} | " + " | ".join(_fmt(c["mse"]) for c in r["chunks"]) + f" | {g} |")
    L.append("| copy the first reference | " + " | ".join(_fmt(x) for x in first["copy_reference_mse"]) + " | |")
    for metric, digits, title in (("psnr", 2, "PSNR (dB)"), ("ssim", 3, "SSIM")):
        L += ["", f"{title} per chunk:", "", "| setting | " + " | ".join(f"chunk {i + 1}" for i in range(n)) + " |",
              "|---|" + "---|" * n]
        for name, r in results.items():
            L.append(f"| {name} | " + " | ".join(_fmt(c[metric], digits) for c in r["chunks"]) + " |")
    L += ["", "Mean MSE over the 4 chunks, by the held-out episode's outcome:", "",
          "| setting | successful episodes | failed episodes |", "|---|---|---|"]
    for name, r in results.items():
        cells = []
        for k in ("success", "failure"):
            b = r["by_outcome"].get(k)
            cells.append("n/a" if not b else f"{np.mean([c['mse'] for c in b['chunks']]):.4f} "
                                              f"({b['rollouts']} rollouts)")
        L.append(f"| {name} | " + " | ".join(cells) + " |")
    L += ["", "![error growth](error_growth.png)", "",
          "![rollouts: recorded, then each setting; the last frame of each chunk](rollouts.png)", ""]

    sens = first["sensitivity"]
    names = dataset_meta.state_names(plan.dataset) or ()
    offsets = ", ".join(f"{names[int(j)] if int(j) < len(names) else 'joint ' + str(j)} {float(v):+.2f}"
                        for j, v in sens["offsets_rad"].items())
    L += ["## Action sensitivity", "",
          f"The same reference frame and noise, two action sequences: the recorded one (A), and one whose waist and "
          f"shoulder targets deviate smoothly from it, linearly up to ({offsets}) rad at the last step of the chunk "
          f"(B). {sens['samples']} samples (chunks {', '.join(map(str, sens.get('start_chunks', [])))} of each "
          "held-out episode). *Inside*: mean absolute difference between the two generated RGB rows where the two "
          "motion "
          "images differ (the robot is somewhere else); *outside*: the same outside both robots (the scene should "
          "not change). A model that follows the actions has a large inside and a ratio well above 1.", "",
          "| setting | inside | outside | ratio |", "|---|---|---|---|"]
    for name, r in results.items():
        sv = r["sensitivity"]
        ratio = "identical futures" if sv["ratio"] is None else _fmt(sv["ratio"], 2)
        L.append(f"| {name} | {_fmt(sv['inside'])} | {_fmt(sv['outside'])} | {ratio} |")
    L += ["", f"The robot differs at {100 * sens['region_share']:.1f} % of the RGB pixels.", "",
          "![sensitivity](sensitivity.png)", ""]

    L += ["## Training", "", "| setting | steps | of which rollout steps | CPU s | wall s | held-out flow loss "
          "start -> end | invalid generated depth at rollout boundaries (evaluation) |",
          "|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        t = r["training"]
        inv = r.get("invalid_generated_depth")
        L.append(f"| {name} | {t['steps']} | {t['rollout_steps']} | {_fmt(t['cpu_s'], 0)} | {_fmt(t['wall_s'], 0)} | "
                 f"{_fmt(t['heldout_loss_first'], 3)} -> {_fmt(t['heldout_loss_last'], 3)} | "
                 f"{'n/a' if inv is None else f'{100 * inv:.1f} %'} |")
    L += ["", "A rollout step trains R = 4 chunks (four forward and backward passes, plus the online contact "
          "rebuild of three chunks), an ordinary step one chunk batch; all settings have the same CPU time.", "",
          "![loss curves](loss_curves.png)", ""]

    L += ["## Stage timings", "", "| stage | wall s | CPU s (this process and its children) | load average "
          "(1/5/15 min) at start | at end | finished |", "|---|---|---|---|---|---|"]
    for e in stages:
        L.append(f"| {e['stage']} | {e['wall_s']:.0f} | {e['cpu_s']:.0f} | {e['load_start']} | {e['load_end']} | "
                 f"{e['finished']} |")
    total_wall = sum(e["wall_s"] for e in stages)
    L += ["", f"Total: {total_wall / 60:.1f} minutes of wall time, "
              f"{sum(e['cpu_s'] for e in stages) / 60:.1f} minutes of CPU time "
              f"(budget: 90 minutes of wall time on an idle 2-core machine).", ""]
    if build_t:
        L += [f"Build: {build_t.get('frames')} frames, {build_t.get('wall_s', 0):.0f} s wall, "
              f"{build_t.get('cpu_s', 0):.0f} s CPU ({build_t.get('workers')} workers).", ""]
    L += ["Evaluation per setting: " + ", ".join(f"{k} {r['evaluation_cpu_s']:.0f} CPU s" for k, r in results.items())
          + ".", "", "Numbers, protocol and per-view metrics: `results.json`.", ""]
    (docs / "README.md").write_text("\n".join(L))
    (docs / "results.json").write_text(json.dumps({"results": results, "machine": mach, "commit": commit,
                                                   "dirty": dirty, "stages": stages, "build": build_t,
                                                   "plan": {k: str(v) for k, v in vars(plan).items()}}, indent=1))
    return docs / "README.md"
