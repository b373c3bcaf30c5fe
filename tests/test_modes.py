"""The conditioning modes are one registry (``imac_model.modes.MODES``): a mode is one entry, and
every list of modes in the package reads it.

* No module of ``imac_model`` but ``modes.py`` spells a list of modes (a tuple, list or set literal,
  or a ``Literal[...]``, holding two or more mode names) or compares a mode with a mode's name
  (``mode == "action-vector"``): read from the source with ``ast``.
* A toy mode registered here (and only here) is a valid ``conditioning.mode``, a choice of the
  command line and of a ranking plan, and builds its model. ``tests/test_ranking.py`` takes one through
  the ranking benchmark's training, gate and report.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

from imac_data.errors import InputError
from imac_model.cli.parser import build_parser
from imac_model.config import (
    BackboneConfig,
    ConditioningConfig,
    FlowConfig,
    ModelSpec,
    RunConfig,
    SmallDiTConfig,
    load_run_config,
)
from imac_model.experiments.ranking.plan import RankingPlan
from imac_model.models.world_model import WorldModel
from imac_model.modes import CONTROL_STREAMS, MODES, ConditioningMode, conditioning_mode, streams_of_mode

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "imac_model"
REGISTRY = PACKAGE / "modes.py"
MODE_VARIABLES = {"mode", "m"}  # names (or attributes) that hold a mode's name


def _mode_names(nodes) -> list[str]:
    return [n.value for n in nodes if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in MODES]


def _holds_a_mode(node: ast.AST) -> bool:
    return (isinstance(node, ast.Name) and node.id in MODE_VARIABLES) or \
        (isinstance(node, ast.Attribute) and node.attr in MODE_VARIABLES)


def spelled_modes(source: str) -> list[str]:
    """``"line: what"`` for each list of modes, ``Literal[...]`` of modes and comparison of a mode with a mode's
    name in ``source``."""
    found, literal = [], set()
    for node in ast.walk(ast.parse(source)):  # a node's parent comes before it
        if isinstance(node, ast.Subscript) and (
                (isinstance(node.value, ast.Name) and node.value.id == "Literal")
                or (isinstance(node.value, ast.Attribute) and node.value.attr == "Literal")):
            literal.add(id(node.slice))
            args = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            if len(_mode_names(args)) >= 2:
                found.append(f"{node.lineno}: Literal of modes {_mode_names(args)}")
        elif isinstance(node, (ast.Tuple, ast.List, ast.Set)) and id(node) not in literal and \
                len(_mode_names(node.elts)) >= 2:
            found.append(f"{node.lineno}: a list of modes {_mode_names(node.elts)}")
        elif isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            names = _mode_names(operands)
            if names and any(_holds_a_mode(o) for o in operands) and \
                    any(isinstance(op, (ast.Eq, ast.NotEq, ast.Is, ast.IsNot)) for op in node.ops):
                found.append(f"{node.lineno}: {ast.unparse(node)}")
    return sorted(found, key=lambda hit: int(hit.split(":")[0]))


def offenders() -> list[str]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if path == REGISTRY:
            continue
        out += [f"{rel}:{hit}" for hit in spelled_modes(path.read_text())]
    return out


def test_no_module_spells_out_a_list_of_modes_or_compares_with_a_modes_name():
    found = offenders()
    assert not found, ("modes spelled out outside imac_model/modes.py (read MODES, a mode's fields, or a named "
                       "choice of the ranking plan):\n" + "\n".join(found))


def test_the_check_catches_each_way_of_spelling_modes():
    source = ('CHOICES = ("none", "motion", "max")\n'
              'x: Literal["motion+contact", "action-vector"] = "motion"\n'
              'if mode == "action-vector" or plan.mode != "none" or "none" == m:\n    pass\n'
              'ok = ("none", "max") if how == "none" else [mode, "motion"]\n')
    assert [hit.split(":")[0] for hit in spelled_modes(source)] == ["1", "2", "3", "3", "3"]


def test_the_registry_names_its_modes_and_their_streams():
    assert list(MODES) == ["none", "motion", "motion+contact", "action-vector"]  # the command line's order
    assert streams_of_mode("motion+contact") == CONTROL_STREAMS and streams_of_mode("motion") == ("motion",)
    assert [m for m, c in MODES.items() if c.blind] == ["none"]
    assert [m for m, c in MODES.items() if c.action_vector] == ["action-vector"]
    with pytest.raises(InputError, match=r"conditioning.mode: must be one of \['none', 'motion', 'motion\+contact', "
                                         r"'action-vector'\] \(got 'motion-toy'\)"):
        conditioning_mode("motion-toy")
    with pytest.raises(InputError, match="streams \\['depth'\\] are not control streams"):
        ConditioningMode(streams=("depth",), label="depth")


def test_a_bad_mode_in_a_config_is_named_by_its_field(tmp_path):
    config = tmp_path / "run.yaml"
    config.write_text("conditioning:\n  mode: motion-toy\n")
    with pytest.raises(InputError, match=r"run.yaml: conditioning.mode: must be one of \['none', 'motion', "
                                         r"'motion\+contact', 'action-vector'\] \(got 'motion-toy'\)"):
        load_run_config(config)
    with pytest.raises(InputError, match="conditioning.mode: must be one of"):
        RunConfig().replace(**{"conditioning.mode": "motion-toy"})


def test_a_toy_mode_is_one_entry(monkeypatch, tmp_path):
    """Registered here alone: the config, the command line, a ranking plan and the model take it."""
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--mode", "vector-toy"])
    monkeypatch.setitem(MODES, "vector-toy", ConditioningMode(action_vector=True, label="toy action vector"))
    monkeypatch.setitem(MODES, "motion-toy", ConditioningMode(streams=("motion",), label="toy motion"))
    assert build_parser().parse_args(["train", "--mode", "vector-toy"]).mode == "vector-toy"
    run = RunConfig().replace(**{"conditioning.mode": "motion-toy"})
    assert run.conditioning.streams == ("motion",)
    plan = RankingPlan(work=tmp_path / "work", docs=tmp_path / "docs", modes=("motion-toy", "vector-toy"))
    assert plan.cpu_budget("vector-toy") == plan.cpu_minutes and plan.run_config("motion-toy").conditioning.mode == \
        "motion-toy"
    spec = ModelSpec(backbone=BackboneConfig(kind="small", small=SmallDiTConfig(unshuffle=2, patch=2, dim=16, depth=1,
                                                                                heads=2, context_dim=8)),
                     conditioning=ConditioningConfig(mode="vector-toy", action_hidden=8), flow=FlowConfig(),
                     views=("cam",), view_height=8, view_width=8, chunk=2, action_dim=2, fps=10.0,
                     action_mean=(0.0, 0.0), action_std=(1.0, 1.0))
    model = WorldModel(spec)
    assert model.action_encoder is not None and model.controls is None
    assert torch.isfinite(model.action_encoder(torch.zeros(1, 2, 2))).all()
