"""A run's training log, ``<run>/log.jsonl``: one JSON row per logged step (loss, held-out loss,
times, chunks trained, device). ``log.csv`` beside it
holds the main columns for a spreadsheet. Written by the trainer, read by the experiments."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable
from pathlib import Path

LOG_FILE = "log.jsonl"
CSV_FILE = "log.csv"
CSV_FIELDS = ("step", "loss", "heldout_loss", "lr", "steps_per_s", "wall_s", "cpu_s", "load", "epoch")


def read_log(run: str | Path, upto: int | None = None) -> list[dict]:
    """The rows of ``run``'s log (none when it has none); ``upto``: only the steps up to it."""
    path = Path(run) / LOG_FILE
    if not path.is_file():
        return []
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return rows if upto is None else [r for r in rows if r.get("step", 0) <= upto]


def write_log(run: str | Path, rows: Iterable[dict], *, csv_only: bool = False) -> None:
    """``log.csv`` from ``rows``, and ``log.jsonl`` unless ``csv_only`` (whole files: a resumed
    run drops the rows after its checkpoint, so the logs hold one row per step)."""
    run = Path(run)
    run.mkdir(parents=True, exist_ok=True)
    rows = list(rows)
    if not csv_only:
        (run / LOG_FILE).write_text("".join(json.dumps(r) + "\n" for r in rows))
    with open(run / CSV_FILE, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(r for r in rows if "step" in r)


def append_log(run: str | Path, row: dict) -> None:
    """One row at the end of ``log.jsonl``."""
    with open(Path(run) / LOG_FILE, "a") as f:
        f.write(json.dumps(row) + "\n")


def progress_line(run: str | Path, cpu_minutes: float | None = None) -> str | None:
    """How far ``run`` has trained, from its log: step, CPU-minutes (of ``cpu_minutes``, the budget
    it trains to), the last losses; None before its first row."""
    rows = [r for r in read_log(run) if "step" in r]
    if not rows:
        return None
    last = rows[-1]
    said = f"step {last['step']:,}"
    if last.get("device", "cpu") != "cpu" and "wall_s" in last:  # a GPU's budget is wall time (train.max_minutes)
        said += f", {last['wall_s'] / 60:.1f} wall minutes on {last['device']}"
    elif "cpu_s" in last:
        said += f", {last['cpu_s'] / 60:.1f}" + (f" of {cpu_minutes:g}" if cpu_minutes else "") + " CPU-minutes"
        if cpu_minutes and last.get("wall_s") and last["cpu_s"] > 0:  # at the CPU a wall second it has had so far
            left = max(0.0, 60 * cpu_minutes - last["cpu_s"]) * last["wall_s"] / last["cpu_s"]
            said += f" (about {left / 60:.0f} min to go)"
    if last.get("loss") is not None:
        said += f", loss {last['loss']:.4g}"
    held = next((r for r in reversed(rows) if r.get("heldout_loss") is not None), None)
    if held:
        said += f", held-out {held['heldout_loss']:.4g} (step {held['step']:,})"
    return said
