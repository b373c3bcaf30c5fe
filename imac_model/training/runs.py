"""Several runs trained one after another from one tensor pack, each returned as a run archive
(:mod:`.archive`): what the GPU machine does with a loan. The runs file (YAML, beside the pack) says
everything; nothing is read from the environment::

    pack: pack.npz                 # relative to this file
    base: {...}                    # a whole run config (imac_model.config.RunConfig) every run starts from
    runs:                          # name -> the run-config fields it sets on the base (dotted keys)
      motion_contact: {conditioning.mode: motion+contact}
      action_vector: {conditioning.mode: action-vector}

``imac-model ranking --stages pack`` writes one from the plan (its modes and ablations);
``scripts/gpu_train.py RUNS_FILE OUT`` runs it on the GPU machine, and ``--import-gpu OUT`` brings the
archives back. Each run trains through :func:`imac_model.training.train.train` with ``data.pack`` set,
into ``OUT/<name>/``; its archive ``OUT/<name>.tar`` holds its EMA weights in float16."""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from imac_data.console import run_command
from imac_data.errors import InputError
from imac_model.config import RunConfig, parse
from imac_model.training.archive import write_archive
from imac_model.training.train import train

RUNS_FILE = "runs.yaml"


@dataclass(frozen=True)
class RunsFile:
    """A runs file, parsed and checked (every run's config is validated before any trains)."""

    pack: str
    base: dict
    runs: dict[str, dict] = field(default_factory=dict)

    @classmethod
    def load(cls, path: str | Path) -> RunsFile:
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as e:
            raise InputError(f"{path}: not a readable runs file ({e})") from None
        if not isinstance(data, dict) or set(data) != {"pack", "base", "runs"} or not data["runs"]:
            raise InputError(f"{path}: a runs file has the keys pack, base and runs (at least one run)")
        pack = (path.parent / data["pack"]).resolve()
        if not pack.is_file():
            raise InputError(f"{path}: pack: no tensor pack at {pack}")
        runs = cls(pack=str(pack), base=data["base"], runs={str(k): dict(v or {}) for k, v in data["runs"].items()})
        for name in runs.runs:  # every run checked before any trains
            try:
                runs.config(name, Path("OUT"))
            except InputError as e:
                raise InputError(f"{path}: run {name}: {e}") from None
        return runs

    def config(self, name: str, out: Path) -> RunConfig:
        """Run ``name``'s config, training into ``out/<name>``."""
        base = parse(RunConfig, self.base, "runs file base")
        return base.replace(**{**self.runs[name], "data.pack": self.pack, "train.output_dir": str(out / name)})

    def to_yaml(self, path: str | Path) -> Path:
        """Written beside the pack (``pack`` as its file name)."""
        path = Path(path)
        text = yaml.safe_dump({"pack": Path(self.pack).name, "base": self.base, "runs": self.runs}, sort_keys=False)
        path.write_text(text)
        return path


def train_runs(runs: RunsFile, out: Path, names: list[str] | None = None, progress: bool = False) -> list[Path]:
    """Train ``names`` (default: all) one after another; returns their archives ``out/<name>.tar``."""
    unknown = [n for n in names or [] if n not in runs.runs]
    if unknown:
        raise InputError(f"--runs: {unknown} are not in the runs file (it has {list(runs.runs)})")
    archives = []
    for name in names or list(runs.runs):
        result = train(runs.config(name, out), progress=progress)
        rows = [r for r in result.log if "step" in r]
        print(json.dumps({"run": name, "step": result.step, "stopped": result.stopped,
                          "heldout_loss": next((r["heldout_loss"] for r in reversed(rows) if "heldout_loss" in r),
                                               None)}), flush=True)
        archive = write_archive(result.checkpoint, out / name / "log.jsonl", out / f"{name}.tar", ema_half=True)
        shutil.rmtree(out / name)  # the archive is what a loan returns
        archives.append(archive)
    return archives


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m imac_model.training.runs",
                                description="train the runs of a runs file from its tensor pack, one after another")
    p.add_argument("runs_file", help=f"the runs file ({RUNS_FILE} beside the pack)")
    p.add_argument("out", help="where the run archives go")
    p.add_argument("--runs", nargs="+", help="only these runs of the file")
    args = p.parse_args(argv)

    def body() -> None:
        runs, out = RunsFile.load(args.runs_file), Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        for path in train_runs(runs, out, args.runs):
            print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")

    return run_command(body)


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["RUNS_FILE", "RunsFile", "main", "train_runs"]
