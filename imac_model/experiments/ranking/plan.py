"""One run of the ranking benchmark: its sizes, budget, policies and where everything goes
(``plan.json`` in the work directory, loadable back)."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import yaml

from imac_data.errors import InputError
from imac_data.sources.sim.rig import RIG_CAMERAS
from imac_model.config import load_run_config
from imac_model.evaluate.policies import lerobot_dir, split_noisy, with_lerobot_dir
from imac_model.experiments.ranking.policies import POLICIES, TRAINING_OFFSETS, VIEWS, WORKSPACE
from imac_model.experiments.stages import REPO_ROOT, python
from imac_model.modes import MODES, ConditioningMode, conditioning_mode

POLICY_MODULE = "imac_model.experiments.ranking.policies"
JUDGE = "python:imac_model.experiments.ranking.judge:lift_judge"
RECIPE = REPO_ROOT / "recipes" / "aloha_sim_lift.yaml"
CONFIG = REPO_ROOT / "imac_model" / "configs" / "ranking.yaml"
CHECKPOINTS = REPO_ROOT / "imac_model" / "configs" / "ranking_checkpoints.yaml"  # the checkpoint preset's settings
CAMERAS = tuple(RIG_CAMERAS.values())  # what the simulated rig records
# the benchmark's choices among the conditioning modes (imac_model.modes.MODES lists them all): the headline mode,
# gated early (gate.py) and judged at both sampler steps; the baseline it is compared against; the harness check
GATED_MODE = "motion+contact"
BASELINE_MODE = "action-vector"
CHECK_MODE = "none"  # policy-blind: trained on none_minutes, run once, its frames bit-identical across policies
SEED_MARK = "@seed"  # "motion+contact@seed1": motion+contact trained again, from training seed plan.seed + 1
STAGES = ("simulate", "build", "decode", "pack", "train", "judges", "evaluate", "report")
EVAL_SEED0 = 100_000  # evaluation start of group g, episode i: EVAL_SEED0 + 1000 g + i
TRAIN_SEED0 = 200_000  # the training rollouts' starts: never an evaluation start
TRAIN_REPO, EVAL_REPO = "local/ranking_train", "local/ranking_eval"
# the toy run of the CI test: the tiny backbone, a few steps
TOY_MODEL = {"backbone.unet.channels": [8, 16], "backbone.unet.blocks": 1, "backbone.unet.frame_dim": 4,
             "train.max_steps": 6, "train.eval_every": 3, "train.checkpoint_every": 6,
             "train.log_every": 3, "train.warmup_steps": 1}


def base_mode(run: str) -> str:
    """The conditioning mode a run of the plan trains: ``MODE``, or ``MODE@seedK``, the same from another seed."""
    return run.split(SEED_MARK, 1)[0]


def run_mode(run: str) -> ConditioningMode:
    return conditioning_mode(base_mode(run))


def slug(spec: str) -> str:
    """A policy's name in tables and paths: ``python:M:NAME`` -> ``NAME``; a lerobot-train checkpoint,
    ``lerobot:.../checkpoints/STEP/pretrained_model`` -> ``lerobot_STEP``; under noise, ``noisy:0.05:SPEC`` ->
    ``<SPEC's name>_noise0p05``."""
    std, inner = split_noisy(spec)
    if std is not None:
        return f"{slug(inner)}_noise{std:g}".replace(".", "p")
    parts = Path(spec.split(":", 1)[-1]).parts
    if spec.startswith("lerobot:") and len(parts) >= 3 and parts[-3:-2] == ("checkpoints",) and parts[-2].isdigit():
        return f"lerobot_{parts[-2]}"
    return spec.rsplit(":", 1)[-1].replace("/", "_")


@dataclass
class RankingPlan:
    """Everything one benchmark run is: sizes, budget, policies. Saved as ``plan.json``."""

    work: Path
    docs: Path
    policies: tuple[str, ...] = tuple(f"python:{POLICY_MODULE}:{p}" for p in POLICIES)
    groups: int = 2  # evaluation groups (the statistics' bootstrap resamples within each)
    real_per_group: int = 25  # MuJoCo episodes per policy and group
    wm_per_group: int = 15  # world-model episodes per policy and group (the group's first starts)
    train_episodes: int = 192  # the world model's training rollouts
    held_out: int = 16  # of them, held out of training (the held-out loss and the early gate)
    # how far off the cube the training rollouts grasp (policies.TRAINING_OFFSETS); work directories made before
    # 2026-11-28 used "disc"
    training_offsets: str = "across"
    # policies (python:/lerobot:/noisy: specs) whose own rollouts join the training data, in turn, at the share
    # training_policy_share of the rollouts spread evenly; the rest stay the scripted mix (docs/ranking.md,
    # "Training on the ranked family"); none in plans saved before 2026-12-03
    training_policies: tuple[str, ...] = ()
    training_policy_share: float = 0.25
    # motion is left out of the default: the comparison is motion+contact against action-vector, and none is
    # the harness check; at 8 CPU-hours a fourth equal budget does not fit (docs/ranking.md, "Modes")
    modes: tuple[str, ...] = (GATED_MODE, BASELINE_MODE, CHECK_MODE)
    cpu_minutes: float = 120.0  # training budget of each compared mode (process CPU minutes, one thread)
    none_minutes: float = 10.0  # none's (any policy-blind mode's): a harness check (bit-identity), not a comparison
    # the early gate (gate.py): motion+contact trains first, measured every gate_every CPU-minutes on the
    # held-out training rollouts; the benchmark stops if it has not reached gate_min by gate_by
    gate_every: float | None = 60.0
    gate_min: float = 0.7
    gate_by: float = 180.0
    # noise seeds per gate replay, pooled: one seed decides 9-10 of 16 replays' verdicts by itself (docs/ranking.md)
    gate_seeds: int = 3
    chunks: int = 4  # world-model chunks per episode (8 frames each)
    steps: int = 10  # Euler steps of the evaluation sampler
    check_steps: int = 20  # the training default: the judges are checked at both
    recorded: int = 24  # evaluation episodes replayed in the world model, half successes where possible
    jobs: int = 2  # processes at a time
    seed: int = 0
    view_size: tuple[int, int] = (48, 64)  # what the policies, the judges and the world model see
    # the cameras they see (the world model generates these): the workspace view alone, where the model draws the
    # outcome (docs/ranking.md, "The views"); plans saved before 2026-11-29 saw the right wrist view too
    views: tuple[str, ...] = (WORKSPACE,)
    config: str = str(CONFIG)  # the world models' run config
    device: str = "cpu"  # where the world models sample
    # physics run before every episode's first frame: gym-aloha's box starts 3 cm up and falls in the first 0.1 s,
    # so the first chunk's controls were made from a scene that was gone (docs/ranking.md); plans made before: 0
    settle_s: float = 0.3
    gpu_minutes: float | None = None  # the GPU preset: each compared mode trained this long on one GPU from the pack
    gpu_ablations: tuple[str, ...] = ()  # the GPU preset also trains these arms (ablations.ABLATIONS) beside its modes
    # every mode is evaluated as it ships: its EMA weights in float16 (shipped.py), so that anyone rerunning the shipped
    # models gets the report's verdicts; plans saved before 2026-12-01 evaluated the float32 EMA
    evaluate_half: bool = True
    toy: bool = False  # the CI run: tiny backbone, a few training steps
    overrides: dict = field(default_factory=dict)  # extra run-config overrides for every mode

    def __post_init__(self) -> None:
        self.work, self.docs = Path(self.work), Path(self.docs)
        self.policies = tuple(self.policies)
        names = [slug(p) for p in self.policies]
        if len(self.policies) < 2 or len(set(names)) != len(names):
            raise InputError(f"ranking: need at least two policies with distinct names, got {names}")
        unknown = [m for m in self.modes if base_mode(m) not in MODES
                   or (SEED_MARK in m and not m.split(SEED_MARK, 1)[1].isdigit())]
        if unknown or not self.modes:
            raise InputError(f"ranking: modes {unknown or list(self.modes)}; choose from {list(MODES)}, each with "
                             f"{SEED_MARK}K for a run from another training seed")
        if not 0 < self.wm_per_group <= self.real_per_group:
            raise InputError("ranking: wm_per_group must be between 1 and real_per_group")
        if not 0 <= self.held_out < self.train_episodes:
            raise InputError("ranking: held_out must be below train_episodes")
        if self.training_offsets not in TRAINING_OFFSETS:
            raise InputError(f"ranking: training_offsets {self.training_offsets!r}; choose from {list(TRAINING_OFFSETS)}")
        self.training_policies = tuple(self.training_policies)
        if not 0 < self.training_policy_share <= 1:
            raise InputError(f"ranking: training_policy_share must be in (0, 1], got {self.training_policy_share}")
        odd = [p for p in self.training_policies if not p.startswith(("python:", "lerobot:", "noisy:"))]
        if odd:
            raise InputError(f"ranking: training_policies {odd}: give python:MODULE:NAME, lerobot:DIR or noisy:STD:SPEC")
        self.view_size = tuple(int(x) for x in self.view_size)
        self.views = tuple(self.views)
        if WORKSPACE not in self.views or len(set(self.views)) != len(self.views) or set(self.views) - set(CAMERAS):
            raise InputError(f"ranking: views {list(self.views)}: distinct cameras of the simulated rig "
                             f"({sorted(CAMERAS)}), {WORKSPACE} among them (the judge reads it)")
        if len(self.view_size) != 2 or min(self.view_size) < 8:
            raise InputError(f"ranking: view_size must be (height, width) of at least 8, got {self.view_size}")
        for name in ("groups", "chunks", "steps", "check_steps", "jobs", "gate_seeds"):
            if getattr(self, name) < 1:
                raise InputError(f"ranking: {name} must be >= 1")
        if self.gate_every is not None and not 0 < self.gate_every <= self.cpu_minutes:
            raise InputError(f"ranking: gate_every must be in (0, cpu_minutes], got {self.gate_every}")

    def check_policies(self, which: Literal["all", "training", "ranked"] = "all") -> None:
        """Refuse ``lerobot:`` checkpoints that are not there, naming them all, before a stage runs a policy:
        ``"all"``, ranked and training ones; ``"training"``, the ``training_policies`` alone (the world models'
        training side, which may start while the ranked checkpoints still train); ``"ranked"``, the ``policies``
        alone (an evaluation of trained models, ``--from-models``)."""
        specs = {"all": (*self.policies, *self.training_policies), "training": self.training_policies,
                 "ranked": self.policies}[which]
        missing = [p for p in specs if lerobot_dir(p) and not Path(lerobot_dir(p), "config.json").is_file()]
        if missing:
            raise InputError(f"ranking: no LeRobot checkpoint (config.json) at {', '.join(missing)}; "
                             "`python -m benchmarks.lerobot_policy` trains the checkpoint preset's (docs/ranking.md, "
                             "\"LeRobot checkpoints\"), and `--stages train` trains the world models meanwhile")

    # ------------------------------------------------------------------ paths and indices
    @property
    def names(self) -> list[str]:
        return [slug(p) for p in self.policies]

    def eval_seeds(self) -> list[tuple[str, int]]:
        """``(group, seed)`` of every evaluation start, in order."""
        return [(f"g{g}", EVAL_SEED0 + 1000 * g + i) for g in range(self.groups) for i in range(self.real_per_group)]

    def eval_episode(self, policy: int, start: int) -> int:
        """The evaluation dataset's episode of ``policy`` (index) from ``start`` (index into eval_seeds)."""
        return policy * self.groups * self.real_per_group + start

    def wm_starts(self) -> list[int]:
        """Indices into eval_seeds of the world model's starts: each group's first wm_per_group."""
        return [g * self.real_per_group + i for g in range(self.groups) for i in range(self.wm_per_group)]

    def sim_dir(self, name: str) -> Path:
        return self.work / "sim" / "eval" / name

    @property
    def train_dataset(self) -> Path:
        return self.work / "datasets" / "train"

    @property
    def eval_dataset(self) -> Path:
        return self.work / "datasets" / "eval"

    @property
    def pack(self) -> Path:
        """The training chunks as one tensor pack: what the GPU preset carries to the GPU machine."""
        return self.work / "gpu" / "pack.npz"

    def run_dir(self, mode: str) -> Path:
        return self.work / "runs" / mode.replace("+", "_").replace("-", "_").replace("@", "_")

    def shipped_archive(self, mode: str) -> Path:
        """``mode``'s trained run as it ships (:mod:`.shipped`): a run archive of its float16 EMA weights."""
        return self.work / "shipped" / f"{self.run_dir(mode).name}.tar.xz"

    def evaluated_model(self, mode: str) -> Path:
        """The checkpoint ``mode`` is evaluated with: its shipped archive unpacked, or (``evaluate_half`` off, plans
        saved before it) the run's latest checkpoint."""
        return self.work / "shipped" / self.run_dir(mode).name if self.evaluate_half else self.run_dir(mode)

    def wm_dir(self, mode: str) -> Path:
        return self.work / "wm" / mode.replace("+", "_").replace("-", "_").replace("@", "_")

    def training_policy_of(self, index: int) -> str | None:
        """The ``training_policies`` spec that runs training rollout ``index``, or None (the scripted mix): the
        rollouts where ``floor((index + 1) * share)`` steps up, spread evenly, the specs in turn."""
        if not self.training_policies:
            return None
        share = self.training_policy_share
        k = math.floor((index + 1) * share)
        if k == math.floor(index * share):
            return None
        return self.training_policies[(k - 1) % len(self.training_policies)]

    def held_out_episodes(self) -> list[int]:
        """The training rollouts kept out of training: the last ``held_out``."""
        return list(range(self.train_episodes - self.held_out, self.train_episodes))

    @property
    def compared_modes(self) -> tuple[str, ...]:
        """The modes that see the policy's actions: every mode but a blind one (``none``, the harness check)."""
        return tuple(m for m in self.modes if not run_mode(m).blind)

    @property
    def on_gpu(self) -> bool:
        """The GPU preset: the compared modes train from the tensor pack on a GPU (``gpu_minutes`` each)."""
        return self.gpu_minutes is not None

    @property
    def budget_minutes(self) -> float:
        """A compared mode's training budget: GPU wall minutes for the GPU preset, else CPU minutes."""
        return self.gpu_minutes if self.on_gpu else self.cpu_minutes

    def cpu_budget(self, mode: str) -> float:
        """``mode``'s training budget in CPU-minutes: ``none_minutes`` for a policy-blind mode (the harness
        check), else ``cpu_minutes``."""
        return self.none_minutes if run_mode(mode).blind else self.cpu_minutes

    def mode_overrides(self, mode: str) -> dict:
        out = {"data.dataset": TRAIN_REPO, "data.root": str(self.train_dataset),
               "data.cache_dir": str(self.work / "chunkcache"), "data.held_out_episodes": self.held_out_episodes(),
               "train.max_cpu_minutes": self.cpu_budget(mode), "train.output_dir": str(self.run_dir(mode)),
               "train.seed": self.seed + int(mode.split(SEED_MARK)[1] if SEED_MARK in mode else 0),
               "conditioning.mode": base_mode(mode), "data.view_height": self.view_size[0],
               "data.view_width": self.view_size[1], "data.views": list(self.views)}
        return {**out, **(TOY_MODEL if self.toy else {}), **self.overrides}

    def run_config(self, mode: str):
        return load_run_config(self.config, self.mode_overrides(mode))

    def to_dict(self) -> dict:
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(self).items()}

    def save(self) -> Path:
        """Write the plan where :func:`plan_path` names it (what ``--status`` and ``--plan`` read back)."""
        self.work.mkdir(parents=True, exist_ok=True)
        path = plan_path(self.work)
        path.write_text(json.dumps(self.to_dict(), indent=1))
        return path

    @classmethod
    def load(cls, path: Path) -> RankingPlan:
        return cls.from_dict(json.loads(Path(path).read_text()))

    @classmethod
    def from_dict(cls, data: dict) -> RankingPlan:
        """A plan from :meth:`to_dict`'s output (``plan.json``, or the ``plan`` of a report's ``results.json``)."""
        # a plan saved before these settings existed
        data = {"training_offsets": "disc", "settle_s": 0.0, "views": VIEWS, "evaluate_half": False, **data}
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()})


def plan_path(work: Path) -> Path:
    """The plan a work directory's run was made with."""
    return Path(work) / "plan.json"


def gpu_plan(work: Path, docs: Path) -> RankingPlan:
    """The GPU preset: the CPU preset's data, model and evaluation, with motion+contact and action-vector
    trained for 8 minutes each on one GPU from the tensor pack (``scripts/gpu_train.py``) instead of the
    CPU budget; a short GPU loan fits it (docs/ranking.md, "The GPU preset")."""
    return RankingPlan(work=work, docs=docs, modes=(GATED_MODE, BASELINE_MODE), gpu_minutes=8.0,
                       gate_every=None)


def checkpoints_plan(work: Path, docs: Path, path: Path = CHECKPOINTS) -> RankingPlan:
    """The checkpoint preset (docs/ranking.md, "Ranking checkpoints"): ``path``'s settings, a YAML file of
    RankingPlan fields, over the defaults; its ``lerobot:`` policies are relative to the repository (the
    stages that run them refuse a missing one: :meth:`RankingPlan.check_policies`)."""
    data = yaml.safe_load(Path(path).read_text()) or {}
    unknown = set(data) - {f.name for f in dataclasses.fields(RankingPlan)} | {"work", "docs"} & set(data)
    if unknown:
        raise InputError(f"{path}: not settings of a ranking plan: {sorted(unknown)}")
    policies = [with_lerobot_dir(s, lambda d: REPO_ROOT / d) for s in data.get("policies", ())]
    data.update({"policies": policies} if policies else {})
    return RankingPlan(work=work, docs=docs, **{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


def toy_plan(work: Path, docs: Path) -> RankingPlan:
    """The CI run: 2 policies, 4 episodes each, 2 chunks, 2 modes, 2 sampler steps."""
    return RankingPlan(work=work, docs=docs, policies=tuple(f"python:{POLICY_MODULE}:{p}"
                                                            for p in ("closed_loop", "open_loop_3cm")),
                       groups=2, real_per_group=2, wm_per_group=1, train_episodes=4, held_out=1,
                       modes=(GATED_MODE, CHECK_MODE), cpu_minutes=1.0, none_minutes=1.0, chunks=2, steps=2, check_steps=2,
                       recorded=2, toy=True, gate_every=1.0, gate_min=0.0, gate_seeds=2)


# the plan fields `imac-model ranking` sets from its flags (imac_model/cli/parser.py), by field
FLAGS = {"policies": "--policies", "modes": "--modes", "cpu_minutes": "--cpu-minutes", "gpu_minutes": "--gpu-minutes",
         "steps": "--steps", "training_offsets": "--training-offsets", "training_policies": "--training-policies",
         "training_policy_share": "--training-policy-share", "settle_s": "--settle", "views": "--views"}
PRESETS = {"cpu": RankingPlan, "gpu": gpu_plan, "checkpoints": checkpoints_plan}
UNCHANGED = {"work", "docs", "jobs", "gate_every"}  # jobs changes no figure; gate_every follows --gpu-minutes
POLICY_FIELDS = ("policies", "training_policies")


def _in_repository(directory: str) -> str:
    path = Path(directory)
    return str(path.relative_to(REPO_ROOT)) if path.is_absolute() and path.is_relative_to(REPO_ROOT) else directory


def _shown(plan: RankingPlan, key: str):
    """A plan field as the command line gives it: paths in the repository (LeRobot checkpoints, the config)
    relative to it."""
    value = getattr(plan, key)
    if key == "config":
        return _in_repository(str(value))
    return tuple(with_lerobot_dir(s, _in_repository) for s in value) if key in POLICY_FIELDS else value


def command_flags(plan: RankingPlan) -> tuple[list[str], list[str]]:
    """The preset and flags of ``imac-model ranking`` that make ``plan`` (from the preset it differs least
    from; ``--toy`` for the CI run), and the fields that no flag sets (a plan edited by hand)."""
    if plan.toy:
        base, flags = toy_plan(plan.work, plan.docs), ["--toy"]
    else:
        name, base = min(((n, make(plan.work, plan.docs)) for n, make in PRESETS.items()),
                         key=lambda nb: sum(_shown(nb[1], k) != _shown(plan, k) for k in FLAGS))
        flags = [] if name == "cpu" else ["--preset", name]
    differ = [f.name for f in dataclasses.fields(RankingPlan)
              if f.name not in UNCHANGED and _shown(plan, f.name) != _shown(base, f.name)]
    for key in differ:
        value = _shown(plan, key)
        if key in FLAGS:
            flags += [FLAGS[key], *map(str, value)] if isinstance(value, tuple) else \
                [FLAGS[key], f"{value:g}" if isinstance(value, float) else str(value)]
        elif key == "overrides":
            flags += [x for k, v in value.items() if base.overrides.get(k) != v for x in ("--set", f"{k}={v}")]
    return flags, [k for k in differ if k not in FLAGS and k != "overrides"]


def internal(plan: RankingPlan, what: str, *extra: str) -> list[str]:
    """argv of one of the benchmark's steps in a fresh process (``imac-model ranking --internal``: LeRobot's
    decoders and MuJoCo's GL context must not be forked after use)."""
    return python() + ["-m", "imac_model", "ranking", "--plan", str(plan_path(plan.work)), "--internal", what,
                       *extra]
