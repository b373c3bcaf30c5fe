"""The ranking world model's ablations, one table: each is an arm that trains the gated mode's run
with one design choice changed (run-config fields), compared with the run it changes
(``motion_contact`` unless said). The GPU preset trains the plan's ``gpu_ablations`` beside its
modes from the pack (:func:`imac_model.experiments.ranking.gpu.runs_file`); on the CPU an arm continues
the preset's run from a checkpoint (``python -m benchmarks.cpu_ablation``). Both measure arms the
same way (``python -m benchmarks.ablation``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from imac_data.errors import InputError


@dataclass(frozen=True)
class Ablation:
    arm: str  # the arm's run name
    changes: dict = field(default_factory=dict)  # run-config fields it sets
    baseline: str = "motion_contact"  # the run it is compared with
    why: str = ""


NOISE = {"flow.reference_noise": 0.3}  # the CPU preset's best arm: later arms keep it

ABLATIONS: dict[str, Callable[[int], Ablation]] = {  # name -> (the plan's chunks per episode) -> the arm
    "focus": lambda chunks: Ablation("motion_contact_uniform", {"flow.focus_weight": 0.0},
                                     why="a uniform loss against one weighted on what moves"),
    "no-rollout": lambda chunks: Ablation("motion_contact_no_rollout", {"rollout.chunks": 1},
                                          why="no training-time rollout, against a run that has one"),
    "rollout": lambda chunks: Ablation(f"motion_contact_rollout{chunks}", {"rollout.chunks": chunks},
                                       why="clips as long as the replays, every later chunk from the model's own frame"),
    "reference-noise": lambda chunks: Ablation("motion_contact_noise03", dict(NOISE),
                                               why="noise on the clean reference latent"),
    "first-frame": lambda chunks: Ablation("motion_contact_first_frame", {**NOISE, "conditioning.first_frame": True},
                                           why="the episode's first frame as memory"),
    "rollout2": lambda chunks: Ablation("motion_contact_rollout2", {**NOISE, "rollout.chunks": 2},
                                        why="clips of two chunks, the grasp chunk among them from the model's frame"),
    "scene-warp": lambda chunks: Ablation("motion_contact_scene_warp", {**NOISE, "conditioning.scene_warp": True},
                                          why="the reference scene splatted into the future cameras"),
    "guidance": lambda chunks: Ablation("motion_contact_guidance", {**NOISE, "conditioning.dropout": 0.1},
                                        why="a tenth of the samples without controls, for classifier-free guidance"),
    "contact": lambda chunks: Ablation("motion_contact_rebuilt", {"rollout.contact": "rebuilt"},
                                       why="a rolled-out chunk's contact images painted from its own reference"),
}


def ablation(name: str, chunks: int) -> Ablation:
    """The arm ``name`` for a plan of ``chunks`` chunks per episode."""
    if name not in ABLATIONS:
        raise InputError(f"ablation {name!r}: the ablations are {sorted(ABLATIONS)}")
    return ABLATIONS[name](chunks)


__all__ = ["ABLATIONS", "Ablation", "ablation"]
