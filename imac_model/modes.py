"""The world model's conditioning modes: how the actions enter the model, one registry entry each.

A mode is one :class:`ConditioningMode` in :data:`MODES`: the control image streams it injects (paper
eq. 2), whether the raw actions go in through the MLP baseline, and its words in a report. Every list of
modes in the package (the config's check, the command line's choices, the ranking benchmark's plan and
report) reads this dict, so a new mode is one entry here (``tests/test_modes.py``). The stream names the
modes and the datasets share are here too.

Importing this module imports nothing heavy: the command line's parser reads it."""

from __future__ import annotations

from dataclasses import dataclass

from imac_data.errors import InputError

CONTROL_STREAMS = ("motion", "contact_s2g", "contact_r2s")  # the order of paper eq. 2: P_m, P_s2g, P_r2s
CONTACT_STREAMS = CONTROL_STREAMS[1:]  # those the dataset stores that are rebuilt from the scene's depth
SCENE_WARP = "scene_warp"  # not in the paper: the reference scene splatted into the future cameras (data.scene_warp)
DERIVED_STREAMS = (SCENE_WARP,)  # made from a chunk's reference, state and actions, never stored in the dataset
REBUILT_STREAMS = CONTACT_STREAMS + DERIVED_STREAMS  # those a rollout rebuilds from the reference frame's depth


@dataclass(frozen=True)
class ConditioningMode:
    """One way the actions enter the world model (``conditioning.mode`` names it)."""

    streams: tuple[str, ...] = ()  # the control image streams it injects, in the order of paper eq. 2
    label: str = ""  # its words in a report, e.g. "motion images"
    action_vector: bool = False  # the raw actions through the MLP baseline, cross-attended

    def __post_init__(self) -> None:
        unknown = [s for s in self.streams if s not in CONTROL_STREAMS]
        if unknown:
            raise InputError(f"conditioning mode {self.label!r}: streams {unknown} are not control streams "
                             f"{list(CONTROL_STREAMS)}")

    @property
    def blind(self) -> bool:
        """Takes no action input: its frames do not depend on the policy (bit-identical across policies from
        the same starts and seeds), so the ranking benchmark runs it once, as the harness check."""
        return not self.streams and not self.action_vector

    @property
    def staged(self) -> bool:
        """Training stage one applies (``rollout.stage_one_epochs``): the motion stream alone first, the
        others added after."""
        return self.streams[:1] == ("motion",) and len(self.streams) > 1


MODES: dict[str, ConditioningMode] = {
    "none": ConditioningMode(label="no action input"),
    "motion": ConditioningMode(streams=("motion",), label="motion images"),
    "motion+contact": ConditioningMode(streams=CONTROL_STREAMS, label="motion and both contact streams"),
    "action-vector": ConditioningMode(action_vector=True, label="an action MLP, cross-attended"),
}


def conditioning_mode(name: str) -> ConditioningMode:
    """The registered mode ``name``; an :class:`~imac_data.errors.InputError` naming the known ones if none is."""
    try:
        return MODES[name]
    except (KeyError, TypeError):
        raise InputError(f"conditioning.mode: must be one of {list(MODES)} (got {name!r})") from None


def streams_of_mode(mode: str) -> tuple[str, ...]:
    """The control streams a conditioning mode injects (paper eq. 2)."""
    return conditioning_mode(mode).streams


__all__ = ["CONTACT_STREAMS", "CONTROL_STREAMS", "ConditioningMode", "DERIVED_STREAMS", "MODES", "REBUILT_STREAMS",
           "SCENE_WARP", "conditioning_mode", "streams_of_mode"]
