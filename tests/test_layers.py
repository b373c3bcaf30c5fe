"""The layers are folders, and imports go one way: read from the source with ``ast``.

* Every import of our own modules sits at the top of its module (a ``TYPE_CHECKING`` block
  counts as annotations only).
* A module imports only its own layer and the layers below (docs/architecture.md).
* There are no import cycles.
* ``imac_data`` never imports ``imac_model``.
* The contact modules share only public names: the GPU painter (``batched``) uses the helpers of
  ``images`` as any caller would.
* The heavy libraries of the renderer, the robot model and sharding are imported where they are
  used: the suite and the benchmarks start hundreds of processes that read datasets or train and
  never need them.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Lowest first; a module may import its own layer and the ones before it.
LAYERS = {
    "imac_data": [
        ("base", ["imac_data", "imac_data.errors", "imac_data.config", "imac_data.layout", "imac_data.console",
                  "imac_data.lerobot_compat", "imac_data.metadata"]),
        ("core", ["imac_data.core"]),
        ("recipes", ["imac_data.recipes"]),
        ("sources", ["imac_data.sources"]),
        ("augment", ["imac_data.augment"]),
        ("dataset", ["imac_data.dataset"]),
        ("build", ["imac_data.build", "imac_data.calibrate"]),
        ("qa", ["imac_data.qa"]),
        ("cli", ["imac_data.cli", "imac_data.__main__", "imac_data.build.__main__"]),
    ],
    "imac_model": [
        ("base", ["imac_model", "imac_model.config", "imac_model.modes"]),
        ("data", ["imac_model.data"]),
        ("models", ["imac_model.models", "imac_model.schedulers"]),
        ("pipelines", ["imac_model.pipelines"]),
        ("training", ["imac_model.training"]),
        ("evaluate", ["imac_model.evaluate"]),
        ("experiments", ["imac_model.experiments"]),
        ("cli", ["imac_model.cli", "imac_model.__main__"]),
    ],
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in LAYERS for p in sorted((ROOT / pkg).rglob("*.py"))}


def _resolve(mod: str, path: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports(mod: str, path: Path, known: dict[str, Path]) -> tuple[list[tuple[str, int, bool]], list[tuple[str, int]]]:
    """``([(imported module, line, at top), ...], [(module, line) imported under TYPE_CHECKING])``
    for the imports of our own packages."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    typing_only = {id(n) for t in tree.body if _is_type_checking(t) for n in ast.walk(t)}
    found, annotations = [], []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(mod, path, node)
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        for target in targets:
            if target.split(".")[0] not in LAYERS:
                continue
            if id(node) in typing_only:
                annotations.append((target, node.lineno))
            else:
                found.append((target, node.lineno, id(node) in top))
    return found, annotations


def layer_of(mod: str) -> tuple[str, int]:
    pkg = mod.split(".")[0]
    best = None
    for rank, (name, prefixes) in enumerate(LAYERS[pkg]):
        for prefix in prefixes:
            inside = mod == prefix or (prefix != pkg and mod.startswith(prefix + "."))  # the root: itself only
            if inside and (best is None or len(prefix) > best[2]):
                best = (name, rank, len(prefix))
    assert best is not None, f"{mod} is in no layer: add it to LAYERS (tests/test_layers.py) and docs/architecture.md"
    return best[0], best[1]


def test_every_module_has_a_layer():
    for mod in modules():
        layer_of(mod)


def test_our_imports_sit_at_the_top_of_the_module():
    known = modules()
    inner = [f"{known[m].relative_to(ROOT)}:{line} imports {t}" for m in known
             for t, line, top in imports(m, known[m], known)[0] if not top]
    assert not inner, "imports of our own modules inside functions:\n" + "\n".join(inner)


def test_no_lower_layer_imports_a_higher_one():
    known = modules()
    wrong = []
    for mod, path in known.items():
        name, rank = layer_of(mod)
        for target, line, _ in imports(mod, path, known)[0]:
            if target.split(".")[0] != mod.split(".")[0]:
                if mod.startswith("imac_data") and target.startswith("imac_model"):
                    wrong.append(f"{path.relative_to(ROOT)}:{line}: imac_data imports {target}")
                continue
            t_name, t_rank = layer_of(target)
            if t_rank > rank:
                wrong.append(f"{path.relative_to(ROOT)}:{line}: {name} module {mod} imports {t_name} module {target}")
    assert not wrong, "imports against the layers:\n" + "\n".join(wrong)


def test_no_import_cycles():
    known = modules()
    graph = {m: sorted({t for t, _, _ in imports(m, p, known)[0] if t in known and t != m}) for m, p in known.items()}
    for mod in known:  # a submodule import also runs its packages' __init__
        parts = mod.split(".")
        graph[mod] = sorted(set(graph[mod]) | {".".join(parts[:i]) for i in range(1, len(parts))} - {mod})
    cycles, state = [], {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = "open"
        for nxt in graph.get(node, []):
            if state.get(nxt) == "open":
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for mod in sorted(graph):
        if mod not in state:
            visit(mod, [mod])
    # a package's __init__ that imports its own submodules is not a cycle worth reporting
    real = [c for c in cycles if not all(c[i].startswith(c[i + 1] + ".") or c[i + 1].startswith(c[i] + ".")
                                         for i in range(len(c) - 1))]
    assert not real, "import cycles:\n" + "\n".join(" -> ".join(c) for c in real)


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_few_modules_at_the_top_of_each_package(package):
    top = sorted(p.name for p in (ROOT / package).glob("*.py"))
    assert len(top) <= 12, f"{package} has {len(top)} top-level modules: {top}"


def test_the_layer_check_catches_a_core_module_importing_the_dataset_layer(tmp_path):
    """The check fails when it should: a core module that imports the dataset layer."""
    path = ROOT / "imac_data" / "core" / "depth.py"
    bad = tmp_path / "depth.py"
    bad.write_text("from imac_data.dataset.info import read_info\n" + path.read_text())
    known = modules()
    found, _ = imports("imac_data.core.depth", bad, known)
    ranks = {t: layer_of(t)[1] for t, _, _ in found}
    assert ranks["imac_data.dataset.info"] > layer_of("imac_data.core.depth")[1]


# imported where used; each takes 0.3-1 s to import (python -X importtime)
HEAVY_WHERE_USED = ("pytorch_kinematics", "trimesh", "yourdfpy", "open3d", "torch.distributed.fsdp",
                    "torch.distributed.tensor", "lerobot", "datasets")


READING_AND_TRAINING = ("imac_data.dataset.validate", "imac_model.data.chunks", "imac_model.experiments.ranking.judge",
                        "imac_model.training.train")


def test_reading_and_training_modules_import_no_renderer_robot_or_sharding_library():
    """A training, judging or validating process imports the renderer's, the robot model's and
    FSDP's libraries only when it renders, builds a robot or shards. One process imports the
    modules in turn, so the first that pulls in a heavy library is the one named."""
    probe = ("import importlib, sys\n"
             f"for module in {READING_AND_TRAINING!r}:\n"
             "    importlib.import_module(module)\n"
             f"    print(module, [m for m in {HEAVY_WHERE_USED!r} if m in sys.modules])\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    heavy = [line for line in done.stdout.splitlines() if not line.endswith(" []")]
    assert len(done.stdout.splitlines()) == len(READING_AND_TRAINING) and not heavy, \
        "importing these modules imports:\n" + "\n".join(heavy)


def private_sibling_imports(mod: str, path: Path) -> list[str]:
    """``"line: module._name"`` for each private name that ``mod`` imports from its own package."""
    package = mod.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            source = _resolve(mod, path, node)
            if source == package or source.startswith(package + "."):
                found += [f"{node.lineno}: {source}.{a.name}" for a in node.names if a.name.startswith("_")]
    return found


def test_the_contact_modules_import_no_private_name_from_each_other():
    contact = ROOT / "imac_data" / "core" / "contact"
    wrong = [f"{path.relative_to(ROOT)}:{hit}" for path in sorted(contact.glob("*.py"))
             for hit in private_sibling_imports(module_name(path), path)]
    assert not wrong, "private names imported from a sibling module (make them public):\n" + "\n".join(wrong)


def test_the_private_import_check_catches_one(tmp_path):
    bad = tmp_path / "batched.py"
    bad.write_text("from imac_data.core.contact.images import _stream_cap, colorize\nfrom .nearest import _box_distance\n")
    assert private_sibling_imports("imac_data.core.contact.batched", bad) == [
        "1: imac_data.core.contact.images._stream_cap", "2: imac_data.core.contact.nearest._box_distance"]


def environment_reads(source: str) -> list[str]:
    """``"line: code"`` for each read of an environment variable (``os.environ``, ``os.getenv``) in ``source``."""
    return sorted(f"{node.lineno}: {ast.unparse(node)}" for node in ast.walk(ast.parse(source))
                  if isinstance(node, ast.Attribute) and node.attr in ("environ", "getenv"))


def test_results_hold_results_and_the_gpu_entry_reads_no_environment():
    """benchmarks/results/ holds no code (no .sh or .py, nothing executable); the GPU machine's entry point and the
    runs it trains take their settings from the runs file, not from environment variables."""
    results = ROOT / "benchmarks" / "results"
    code = [str(p.relative_to(ROOT)) for p in results.rglob("*")
            if p.is_file() and (p.suffix in (".sh", ".py") or p.stat().st_mode & 0o111)]
    assert not code, f"code in the results folder: {code}"
    for path in (ROOT / "scripts" / "gpu_train.py", ROOT / "imac_model" / "training" / "runs.py"):
        assert not environment_reads(path.read_text()), (path, environment_reads(path.read_text()))
    assert environment_reads("import os\nx = os.environ.get('OUT')\ny = os.getenv('MINUTES')\n") == [
        "2: os.environ", "3: os.getenv"]
