"""Policies that act in the world model and in the simulator: callables from an observation to
an action chunk.

A policy is any ``policy(observation) -> (K, D) actions`` with an optional ``reset()``. Both
runners (:mod:`imac_model.evaluate.closed_loop` in the world model,
:mod:`imac_model.evaluate.simulator` in MuJoCo) give it the same observation
(:func:`make_observation`, ``docs/evaluation.md``, "The observation"):

* ``observation.images.<view>``: ``(3, h, w)`` float in [0, 1], at the world model's view size;
* ``observation.depth.<view>``: ``(h, w)`` float32 metres, 0 where unknown (decoded from the
  generated colour depth in the world model, rendered in MuJoCo);
* ``observation.state``: ``(D,)`` the robot's measured configuration at the episode's first
  frame, afterwards the last commanded configuration (phi of the actions so far);
* ``task``: the instruction.

:class:`ActionQueue` gives it LeRobot's ``select_action`` semantics (asked again only when its
queue is empty, which both runners check at chunk boundaries); :class:`LeRobotPolicy` adapts a
LeRobot checkpoint with its own processors; the recorded replay and holding the start state
are scripted baselines. LeRobot's policy names come from :func:`lerobot_name`, the policy
code's one place for LeRobot (``docs/lerobot.md``)."""

from __future__ import annotations

import hashlib
import importlib
import os
import sys
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from imac_data.errors import InputError
from imac_data.layout import IMAGE_PREFIX, STATE, depth_key, image_key

STATE_KEY = STATE

Observation = dict  # see the module docstring
Policy = Callable[[Observation], torch.Tensor]


def make_observation(rgb: torch.Tensor, depth: torch.Tensor | None, state, views: Sequence[str],
                     task: str = "") -> Observation:
    """The observation of one time step (the module docstring): ``rgb (V, 3, h, w)`` in [0, 1],
    ``depth (V, h, w)`` metres (0 = unknown; None: no depth keys), ``state (D,)``."""
    rgb = torch.as_tensor(rgb)
    if rgb.ndim != 4 or rgb.shape[0] != len(views) or rgb.shape[1] != 3:
        raise InputError(f"observation: expected RGB of shape ({len(views)}, 3, h, w), got {tuple(rgb.shape)}")
    obs = {image_key(v): rgb[i].float().clamp(0, 1).cpu() for i, v in enumerate(views)}
    if depth is not None:
        depth = torch.as_tensor(depth)
        if tuple(depth.shape) != (len(views), *rgb.shape[-2:]):
            raise InputError(f"observation: expected depth of shape ({len(views)}, {rgb.shape[-2]}, {rgb.shape[-1]}), "
                             f"got {tuple(depth.shape)}")
        depth = torch.nan_to_num(depth.float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0).cpu()
        obs.update({depth_key(v): depth[i] for i, v in enumerate(views)})
    obs[STATE_KEY] = torch.as_tensor(state).float().cpu()
    obs["task"] = task or ""
    return obs


# LeRobot's policy-side names and their modules (the same in 0.4.4 and 0.6.x)
LEROBOT_POLICY_NAMES = {
    "FeatureType": "lerobot.configs.types",
    "PolicyFeature": "lerobot.configs.types",
    "PreTrainedConfig": "lerobot.configs.policies",
    "get_policy_class": "lerobot.policies.factory",
    "make_pre_post_processors": "lerobot.policies.factory",
    "ACTConfig": "lerobot.policies.act.configuration_act",
    "ACTPolicy": "lerobot.policies.act.modeling_act",
}


def lerobot_name(name: str):
    """LeRobot's policy-side ``name``, imported on first use (LeRobot's policies take seconds to import)."""
    return getattr(importlib.import_module(LEROBOT_POLICY_NAMES[name]), name)


def policy_name(policy) -> str:
    return str(getattr(policy, "name", None) or getattr(policy, "__name__", None) or type(policy).__name__)


WORLD_MODEL = "the world model's dataset"  # what a closed loop's actions must fit


def as_action_chunk(actions, action_dim: int, who: str = "policy", target: str = WORLD_MODEL) -> torch.Tensor:
    """A policy's output as a float ``(K, D)`` tensor on the CPU, checked: a leading batch
    dimension of 1 is dropped; the action dimension must be ``target``'s (named in the error)."""
    a = torch.as_tensor(actions).detach().float().cpu()
    if a.ndim == 3 and a.shape[0] == 1:
        a = a[0]
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[0] < 1:
        raise InputError(f"{who} returned actions of shape {tuple(a.shape)}; expected an (K, D) chunk")
    if a.shape[1] != action_dim:
        raise InputError(f"{who} returned {a.shape[1]}-dimensional actions; {target} has "
                         f"{action_dim}-dimensional actions")
    if not torch.isfinite(a).all():
        raise InputError(f"{who} returned non-finite actions")
    return a


def reset_policy(policy: Policy, start: int | None = None) -> None:
    """A new episode for ``policy``, if it has a ``reset``: ``reset(start)`` for one that declares
    ``takes_start = True`` (told the simulated start's seed, None where unknown), ``reset()`` for any other, as
    LeRobot's policies are reset."""
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset(start) if getattr(policy, "takes_start", False) else reset()


class ActionQueue:
    """``select_action`` semantics for a chunk policy (see the module docstring); ``target``
    names what the actions drive, for the error on a wrong action size."""

    def __init__(self, policy: Policy, action_dim: int, target: str = WORLD_MODEL):
        if not callable(policy):
            raise InputError(f"a policy must be callable (observation -> actions), got {type(policy).__name__}")
        self.policy, self.action_dim, self.target = policy, int(action_dim), target
        self.queue: deque[torch.Tensor] = deque()
        self.calls = 0

    def reset(self, start: int | None = None) -> None:
        """A new episode from ``start`` (the simulated start's seed, None where unknown)."""
        self.queue.clear()
        reset_policy(self.policy, start)

    def take(self, observation: Observation, n: int) -> torch.Tensor:
        """The next ``n`` actions ``(n, D)``; the policy sees ``observation`` whenever the queue runs out."""
        out = []
        while len(out) < n:
            if not self.queue:
                self.queue.extend(as_action_chunk(self.policy(observation), self.action_dim, policy_name(self.policy),
                                                  self.target))
                self.calls += 1
            out.append(self.queue.popleft())
        return torch.stack(out)


def check_task(policy, instruction: str, asked: str) -> None:
    """Refuse, before any work, a policy that declares the instructions it acts on (its
    ``tasks`` attribute) when ``instruction`` (what ``asked`` runs) is not one of them."""
    tasks = getattr(policy, "tasks", None)
    if tasks is None:
        return
    tasks = (tasks,) if isinstance(tasks, str) else tuple(tasks)
    if instruction not in tasks:
        raise InputError(f"policy {policy_name(policy)} acts on {list(tasks)} (its tasks), but {asked} is "
                         f"{instruction!r}")


# --------------------------------------------------------------------------- scripted policies


def recorded_actions_policy(actions: torch.Tensor, name: str = "recorded") -> Policy:
    """Replays ``actions (T, D)`` in order whatever it sees (then holds the last one): with the
    world model's closed loop this is an open-loop replay of a recorded episode."""
    actions = torch.as_tensor(actions).float()
    state = {"t": 0}

    def policy(observation: Observation) -> torch.Tensor:
        t = state["t"]
        state["t"] += 1
        return actions[min(t, len(actions) - 1)][None]

    policy.reset = lambda: state.update(t=0)
    policy.name = name
    return policy


def hold_policy(observation: Observation) -> torch.Tensor:
    """Commands the current state (absolute joint-position actions): the robot stays put."""
    return torch.as_tensor(observation[STATE_KEY]).float()[None]


hold_policy.name = "hold"


# --------------------------------------------------------------------------- LeRobot policies


class LeRobotPolicy:
    """A LeRobot policy checkpoint as a policy callable (see the module docstring).

    ``camera_map``: ``{policy camera key: world-model view}``; by default each of the policy's
    ``observation.images.X`` keys reads view ``X``.
    """

    def __init__(self, policy, preprocessor, postprocessor, *, camera_map: Mapping[str, str] | None = None,
                 name: str | None = None):
        FeatureType = lerobot_name("FeatureType")
        self.policy, self.preprocessor, self.postprocessor = policy, preprocessor, postprocessor
        self.config = policy.config
        self.name = name or f"lerobot:{self.config.type}"
        inputs = dict(self.config.input_features or {})
        self.image_shapes = {k: tuple(f.shape) for k, f in inputs.items() if f.type is FeatureType.VISUAL}
        self.other_inputs = {k: tuple(f.shape) for k, f in inputs.items()
                             if f.type is not FeatureType.VISUAL and k != STATE_KEY}
        self.state_shape = tuple(inputs[STATE_KEY].shape) if STATE_KEY in inputs else None
        out = dict(self.config.output_features or {})
        self.action_dim = int(out["action"].shape[0]) if "action" in out else None
        self.camera_map = dict(camera_map) if camera_map else {
            k: k[len(IMAGE_PREFIX):] for k in self.image_shapes if k.startswith(IMAGE_PREFIX)}
        self.n_action_steps = int(getattr(self.config, "n_action_steps", 1) or 1)

    @classmethod
    def from_pretrained(cls, path: str | Path, *, camera_map: Mapping[str, str] | None = None, device: str = "cpu",
                        name: str | None = None) -> LeRobotPolicy:
        """Load a local checkpoint directory (``config.json``, ``model.safetensors`` and the
        processors' files, as ``save_pretrained`` writes them). Nothing is downloaded."""
        PreTrainedConfig = lerobot_name("PreTrainedConfig")
        get_policy_class, make_pre_post_processors = (lerobot_name(n) for n in ("get_policy_class",
                                                                                "make_pre_post_processors"))
        path = Path(path)
        for f in ("config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"):
            if not (path / f).is_file():
                raise InputError(f"{path}: not a LeRobot policy checkpoint directory (no {f}; a checkpoint is what "
                                 "`policy.save_pretrained`, `preprocessor.save_pretrained` and "
                                 "`postprocessor.save_pretrained` write, e.g. lerobot-train's "
                                 "checkpoints/<step>/pretrained_model)")
        try:
            config = PreTrainedConfig.from_pretrained(str(path), local_files_only=True)
        except Exception as e:  # draccus / json errors of many kinds
            raise InputError(f"{path / 'config.json'}: unreadable LeRobot policy config: {type(e).__name__}: {e}") \
                from None
        config.device = device
        config.pretrained_path = str(path)
        policy = get_policy_class(config.type).from_pretrained(str(path), config=config, local_files_only=True)
        overrides = {"device_processor": {"device": device}}
        pre, post = make_pre_post_processors(config, pretrained_path=str(path), preprocessor_overrides=overrides)
        return cls(policy, pre, post, camera_map=camera_map, name=name or f"lerobot:{config.type}:{path.name}")

    def check(self, *, views: Sequence[str], action_dim: int, state_dim: int | None) -> None:
        """Refuse a policy the world model cannot serve: camera keys it would not get, another
        action or state dimension, inputs other than images and the state."""
        where = f"policy {self.name}"
        if self.action_dim is not None and self.action_dim != action_dim:
            raise InputError(f"{where} outputs {self.action_dim}-dimensional actions, but the world model's dataset has "
                             f"{action_dim}-dimensional actions")
        if self.state_shape is not None and state_dim is not None and self.state_shape != (state_dim,):
            raise InputError(f"{where} expects observation.state of shape {self.state_shape}, but the world model's "
                             f"dataset has ({state_dim},)")
        if self.state_shape is not None and state_dim is None:
            raise InputError(f"{where} needs observation.state, but the world model's dataset has none")
        if self.other_inputs:
            raise InputError(f"{where} needs inputs the world model does not generate: {sorted(self.other_inputs)}")
        if not self.image_shapes:
            return
        unmapped = [k for k in self.image_shapes if k not in self.camera_map]
        bad = {k: v for k, v in self.camera_map.items() if k in self.image_shapes and v not in views}
        extra = [k for k in self.camera_map if k not in self.image_shapes]
        if unmapped or bad or extra:
            raise InputError(
                f"{where}: its camera keys {sorted(self.image_shapes)} do not match the world model's views "
                f"{list(views)}" + (f"; no view for {unmapped}" if unmapped else "")
                + (f"; mapped to unknown views {bad}" if bad else "")
                + (f"; the camera map names keys the policy does not have: {extra}" if extra else "")
                + " (map them with camera_map / --camera-map POLICY_KEY=VIEW)")

    def reset(self) -> None:
        self.policy.reset()

    def observation(self, observation: Observation) -> dict:
        """The world model's observation under the policy's keys, images at its shapes."""
        out = {}
        for key, view in self.camera_map.items():
            img = torch.as_tensor(observation[image_key(view)]).float()
            shape = self.image_shapes[key]
            if tuple(img.shape[-2:]) != tuple(shape[-2:]):
                img = F.interpolate(img[None], size=tuple(shape[-2:]), mode="bilinear", antialias=True,
                                    align_corners=False)[0].clamp(0, 1)
            out[key] = img
        if self.state_shape is not None:
            out[STATE_KEY] = torch.as_tensor(observation[STATE_KEY]).float()
        if "task" in observation:
            out["task"] = observation["task"] or ""
        return out

    @torch.no_grad()
    def __call__(self, observation: Observation) -> torch.Tensor:
        batch = self.preprocessor(self.observation(observation))
        actions = torch.stack([self.policy.select_action(batch) for _ in range(self.n_action_steps)], dim=1)
        return self.postprocessor(actions)[0].float().cpu()  # (n_action_steps, D)


# --------------------------------------------------------------------------- graded action noise

NOISY = "noisy:"  # noisy:STD:SPEC, the policy SPEC with Gaussian noise of STD on every action


def split_noisy(spec: str) -> tuple[float | None, str]:
    """``noisy:STD:SPEC`` -> ``(STD, SPEC)``; any other spec -> ``(None, spec)``."""
    if not spec.startswith(NOISY):
        return None, spec
    std, _, inner = spec[len(NOISY):].partition(":")
    try:
        value = float(std)
    except ValueError:
        value = -1.0
    if not inner or not value >= 0 or value == float("inf"):
        raise InputError(f"policy {spec!r}: expected noisy:STD:SPEC with STD a finite number >= 0 (action units) "
                         "and SPEC a policy, e.g. noisy:0.05:lerobot:DIR")
    return value, inner


def lerobot_dir(spec: str) -> str | None:
    """The LeRobot checkpoint directory a policy spec runs (``lerobot:DIR``, under noise or not), else None."""
    inner = split_noisy(spec)[1]
    return inner[len("lerobot:"):] if inner.startswith("lerobot:") else None


def with_lerobot_dir(spec: str, change: Callable[[str], str]) -> str:
    """``spec`` with its LeRobot checkpoint directory replaced by ``change(dir)`` (any other spec as it is)."""
    inner = split_noisy(spec)[1]
    if not inner.startswith("lerobot:"):
        return spec
    return spec[:len(spec) - len(inner)] + "lerobot:" + str(change(inner[len("lerobot:"):]))  # noise prefix kept


class NoisyPolicy:
    """``policy`` with Gaussian noise of standard deviation ``std`` (action units) added to every action it returns:
    a graded family of worse policies from one good one. Each episode draws its noise from a generator seeded by
    ``seed`` and the start the runner names (``reset(start)``: the simulated start's seed, in MuJoCo and in the world
    model alike), or, where the runner names none, the episode's first state (rounded to 0.1 mrad)."""

    takes_start = True

    def __init__(self, policy: Policy, std: float, seed: int = 0, name: str | None = None):
        self.policy, self.std, self.seed = policy, float(std), int(seed)
        self.name = name or f"{NOISY}{std:g}:{policy_name(policy)}"
        self.start: int | None = None
        self.generator: torch.Generator | None = None  # seeded at an episode's first call
        if hasattr(policy, "tasks"):
            self.tasks = policy.tasks

    def check(self, **kwargs) -> None:
        check = getattr(self.policy, "check", None)
        if callable(check):
            check(**kwargs)

    def reset(self, start: int | None = None) -> None:
        self.start, self.generator = start, None
        reset_policy(self.policy, start)

    def __call__(self, observation: Observation) -> torch.Tensor:
        if self.generator is None:
            key = (np.array([self.start], np.int64) if self.start is not None else
                   torch.as_tensor(observation[STATE_KEY]).double().mul(1e4).round().to(torch.int64).numpy())
            digest = hashlib.sha256(key.tobytes() + self.seed.to_bytes(8, "little", signed=True)).digest()
            self.generator = torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") >> 1)
        actions = torch.as_tensor(self.policy(observation)).float()
        return actions + self.std * torch.randn(actions.shape, generator=self.generator)


def import_from_cwd(module: str):
    """Import ``module`` as ``python -m`` would: the current directory first, then
    ``PYTHONPATH``. A console script's ``sys.path`` starts with its own bin directory instead,
    so the current directory is put first (and kept: the module may import its neighbours
    later)."""
    cwd = os.getcwd()
    if not sys.path or os.path.abspath(sys.path[0] or os.curdir) != cwd:
        sys.path.insert(0, cwd)
    return importlib.import_module(module)


def python_object(spec: str, what: str):
    """``python:MODULE:NAME``: the callable ``NAME`` of module ``MODULE`` (imported from the
    current directory first, then ``PYTHONPATH``); a class, or a function marked
    ``is_factory``, is called once without arguments to make it."""
    parts = spec[len("python:"):].split(":")
    if not spec.startswith("python:") or len(parts) != 2 or not all(parts):
        raise InputError(f"{what} {spec!r}: expected python:MODULE:NAME")
    try:
        module = import_from_cwd(parts[0])
    except ImportError as e:
        if e.name and (parts[0] + ".").startswith(e.name + "."):  # MODULE (or its package) itself is missing
            raise InputError(f"{what} {spec!r}: no module {parts[0]!r} in the current directory {os.getcwd()}, "
                             "PYTHONPATH or the installed packages") from None
        raise InputError(f"{what} {spec!r}: importing {parts[0]!r} failed: {e}") from None
    try:
        obj = getattr(module, parts[1])
    except AttributeError:
        raise InputError(f"{what} {spec!r}: module {parts[0]!r} ({getattr(module, '__file__', '?')}) has no "
                         f"{parts[1]!r}") from None
    if isinstance(obj, type) or getattr(obj, "is_factory", False):
        obj = obj()
    if not callable(obj) and not hasattr(obj, "judge"):
        raise InputError(f"{what} {spec!r} is not callable")
    return obj


def load_policy(spec: str, *, camera_map: Mapping[str, str] | None = None, device: str = "cpu") -> Policy:
    """A policy from a command-line spec: ``lerobot:DIR`` (a LeRobot checkpoint directory),
    ``hold``, ``python:MODULE:NAME`` (:func:`python_object`), or any of these under graded action noise,
    ``noisy:STD:SPEC`` (:class:`NoisyPolicy`). ``recorded`` is resolved per episode by the closed loop."""
    std, inner = split_noisy(spec)
    if std is not None:
        return NoisyPolicy(load_policy(inner, camera_map=camera_map, device=device), std, name=spec)
    if spec.startswith("lerobot:"):
        return LeRobotPolicy.from_pretrained(spec[len("lerobot:"):], camera_map=camera_map, device=device)
    if camera_map:
        raise InputError("--camera-map only applies to lerobot: policies")
    if spec == "hold":
        return hold_policy
    if spec.startswith("python:"):
        return python_object(spec, "policy")
    raise InputError(f"unknown policy {spec!r}: use recorded, hold, lerobot:DIR, python:MODULE:NAME or "
                     "noisy:STD:SPEC")


__all__ = ["NOISY", "ActionQueue", "LeRobotPolicy", "NoisyPolicy", "as_action_chunk", "check_task", "hold_policy",
           "image_key", "import_from_cwd", "lerobot_dir", "load_policy", "make_observation", "policy_name",
           "python_object", "recorded_actions_policy", "reset_policy", "split_noisy", "with_lerobot_dir"]
