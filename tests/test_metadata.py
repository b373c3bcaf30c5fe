"""One reader of a dataset's metadata (``imac_data.metadata``), and every function that takes
metadata accepts what both LeRobot lines give: ``ds.meta``, the dataset's root, the dict
``dataset_info`` gives (``meta/info.json`` with the ``imac`` block).

* The block is a file of its own, ``meta/imac/info.json`` (schema version 3), so LeRobot loads a
  built dataset without a warning about it; a dataset of the old layout (the block in
  ``meta/info.json``, version 2) reads as before, and its next write moves the block out.
* Found, not listed: every public function of the public modules whose first parameter is
  ``meta`` is called with each form on a built dataset, and gives the same answer for each.
* ``imac_model`` never touches the ``imac`` key itself (read from the source with ``ast``), and
  names the success column only through ``imac_data.layout``.
* In ``imac_data`` only the reader (``metadata``) and the writer (``dataset/info``) index the key.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import json
import logging
import shutil
import warnings
from collections.abc import Mapping
from pathlib import Path

import pytest
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

import imac_data
from imac_data.cli import main as imac_main
from imac_data.dataset.columns import add_frame_column
from imac_data.dataset.info import write_info
from imac_data.errors import InputError
from imac_data.layout import IMAC_INFO, INFO, SUCCESS_COLUMN
from imac_data.metadata import RIG_KEYS, SCHEMA_VERSION, SUPPORTED_VERSIONS, dataset_info, imac_block
from imac_data.recipes import RECIPES_DIR, AugmentSettings
from imac_data.sources.sim.recorder import SimConfig, record_dataset

ROOT = Path(__file__).resolve().parents[1]
REPO = "local/metadata_forms"
# the public modules whose functions may take metadata: imac_data's API, the reader, the model's reader
MODULES = sorted({*imac_data._API.values(), "imac_data.metadata", "imac_model.data.meta"})
# the arguments after ``meta`` of the functions that need more
EXTRA = {"missing_features": (("motion", "rgb"), ("cam_high",)), "feature_dim": ("action",)}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """One short simulated episode, built with the real builder at 48x64 (contact chunk 4)."""
    tmp = tmp_path_factory.mktemp("metadata")
    record_dataset(SimConfig(num_episodes=1, width=64, height=48, max_steps=12), tmp / "sim", progress=False)
    recipe = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    recipe["augment"] = {"height": 48, "width": 64, "contact_chunk": 4}
    recipe["source"]["episodes"] = 1
    (tmp / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    root = tmp / "ds"
    assert imac_main(["build", "--repo", REPO, "--recipe", str(tmp / "recipe.yaml"), "--source", str(tmp / "sim"),
                      "--root", str(root), "--no-progress", "--workers", "1"]) == 0
    return root


def metadata_functions() -> dict[str, object]:
    """``{qualified name: callable}`` of every public function and classmethod whose first
    parameter is ``meta``."""
    found = {}
    for name in MODULES:
        mod = importlib.import_module(name)
        public = getattr(mod, "__all__", [n for n in vars(mod) if not n.startswith("_")])
        for attr in public:
            obj = getattr(mod, attr)
            if getattr(obj, "__module__", None) != name:
                continue  # re-exported: tested where it is defined
            candidates = [(attr, obj)] if inspect.isfunction(obj) else []
            if inspect.isclass(obj):
                candidates = [(f"{attr}.{m}", getattr(obj, m)) for m in vars(obj)
                              if not m.startswith("_") and inspect.ismethod(getattr(obj, m))]
            for qual, fn in candidates:
                params = list(inspect.signature(fn).parameters)
                if params and params[0] == "meta":
                    found[f"{name}.{qual}"] = fn
    return found


def _plain(x):
    """A comparable form of a result: JSON-like data."""
    if hasattr(x, "to_info"):
        return x.to_info()
    if hasattr(x, "to_dict"):
        return x.to_dict()
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return dataclasses.asdict(x)
    if isinstance(x, Mapping):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


def _forms(root: Path) -> dict[str, object]:
    return {"ds.meta": LeRobotDatasetMetadata(REPO, root=root), "root (str)": str(root), "root (Path)": root,
            "info dict": dataset_info(root)}


def _call(fn, meta, root: Path):
    args = EXTRA.get(fn.__name__, ())
    if "root" in inspect.signature(fn).parameters and isinstance(meta, Mapping):
        return fn(meta, *args, root=root)  # a dict does not say where the robot description is
    return fn(meta, *args)


def test_the_metadata_functions_are_found():
    names = set(metadata_functions())
    for expected in ("imac_data.metadata.chunk_timestamps", "imac_data.core.depth.depth_codec_of",
                     "imac_data.core.rig.Rig.from_info", "imac_data.recipes.AugmentSettings.from_info",
                     "imac_model.data.meta.contact_chunk_size", "imac_model.data.meta.cameras",
                     "imac_model.data.meta.camera_names", "imac_model.data.meta.fps"):
        assert expected in names, f"{expected} is not found among {sorted(names)}"


def test_every_metadata_function_takes_every_form(built):
    forms = _forms(built)
    functions = metadata_functions()
    for qual, fn in functions.items():
        results = {form: _plain(_call(fn, meta, built)) for form, meta in forms.items()}
        if qual == "imac_data.metadata.dataset_root":  # the dict does not know its root
            assert results.pop("info dict") is None
        first = next(iter(results.values()))
        assert all(r == first for r in results.values()), f"{qual}: the forms disagree: {results}"
    # the answers are the dataset's own, not a default
    fps = json.loads((built / "meta" / "info.json").read_text())["fps"]
    assert imac_data.chunk_timestamps(built)["action"] == pytest.approx([k / fps for k in range(4)])
    assert AugmentSettings.from_info(built).resolution == (48, 64)
    assert AugmentSettings.from_info(built).contact_chunk == 4


def test_what_lerobot_loads_as_info(built):
    """``ds.meta.info`` has no ``imac`` block: LeRobot 0.4.4 loads ``meta/info.json`` as a dict,
    which no longer holds it (``meta/imac/info.json`` does), LeRobot 0.5.1 and later a
    ``DatasetInfo``. Either is refused with what to pass instead by every function that reads
    the block; LeRobot 0.4.4's dict still answers what is LeRobot's own (features, fps)."""
    info = LeRobotDatasetMetadata(REPO, root=built).info
    assert "imac" not in (info if isinstance(info, Mapping) else vars(info))
    own = {"dataset_root", "dataset_info", "unchecked_imac_block", "missing_features", "feature_dim", "fps"}
    for qual, fn in metadata_functions().items():
        if isinstance(info, Mapping) and qual.rsplit(".", 1)[1] in own:  # LeRobot 0.4.4: a dict is taken as is
            continue
        with pytest.raises(InputError, match="pass ds.meta or the dataset's root"):
            _call(fn, info, built)
    if isinstance(info, Mapping):
        assert imac_data.metadata.unchecked_imac_block(info) == {}
        for name in ("feature_dim", "fps"):
            fn = metadata_functions()[f"imac_model.data.meta.{name}"]
            assert _call(fn, info, built) == _call(fn, built, built)


@pytest.mark.parametrize("name", ["imac_data.metadata.chunk_timestamps", "imac_data.core.depth.depth_codec_of",
                                  "imac_data.core.rig.Rig.from_info", "imac_data.recipes.AugmentSettings.from_info",
                                  "imac_model.data.meta.contact_chunk_size"])
def test_a_dict_without_the_imac_block_names_the_file(built, name):
    info = dataset_info(built)
    info.pop("imac")
    with pytest.raises(InputError, match=r"meta/info\.json: no 'imac' block.*pass ds\.meta or the dataset's root"):
        _call(metadata_functions()[name], info, built)


def test_other_inputs_are_refused(built, tmp_path):
    with pytest.raises(InputError, match="is not a LeRobot dataset"):
        imac_data.depth_codec_of(tmp_path)
    with pytest.raises(InputError, match="got a int"):
        imac_data.chunk_timestamps(3)
    with pytest.raises(InputError, match="needs the dataset's root"):
        imac_data.Rig.from_info(dataset_info(built))
    info = dataset_info(built)
    info["imac"]["augment"]["contact_percentile"] = "high"
    with pytest.raises(InputError, match=r"meta/info\.json imac\.augment\.contact_percentile"):
        AugmentSettings.from_info(info)


# --------------------------------------------------------------------------- where the block lives


def _load_messages(root: Path, caplog) -> list[str]:
    """Every warning and every log record of WARNING or above that a plain ``LeRobotDataset``
    load of ``root`` emits."""
    caplog.clear()
    with caplog.at_level(logging.WARNING), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = LeRobotDataset(REPO, root=root)
        assert len(ds) > 0 and ds[0]
    return [str(w.message) for w in caught] + [r.getMessage() for r in caplog.records]


@pytest.fixture(scope="module")
def old_layout(built, tmp_path_factory) -> Path:
    """``built`` as builds before schema version 3 wrote it: the block under the ``imac`` key of
    ``meta/info.json``, schema version 2, no ``meta/imac/info.json``."""
    root = tmp_path_factory.mktemp("old_layout") / "ds"
    shutil.copytree(built, root)
    info = json.loads((root / INFO).read_text())
    block = json.loads((root / IMAC_INFO).read_text())
    (root / IMAC_INFO).unlink()
    info["imac"] = {**block, "schema_version": 2}
    (root / INFO).write_text(json.dumps(info, indent=4))
    return root


def test_a_new_build_keeps_the_block_in_its_own_file(built):
    info = json.loads((built / INFO).read_text())
    block = json.loads((built / IMAC_INFO).read_text())
    assert "imac" not in info
    assert block["schema_version"] == SCHEMA_VERSION == 3 and SUPPORTED_VERSIONS == (1, 2, 3)
    assert set(RIG_KEYS) <= set(block) and block["contact"]["chunk_size"] == 4
    assert dataset_info(built) == {**info, "imac": block}
    assert imac_block(built, require=RIG_KEYS) == block


def test_a_plain_lerobot_load_says_nothing_about_imac(built, old_layout, caplog):
    """LeRobot 0.6 warns about every key of ``meta/info.json`` it does not know ("Unknown fields in
    DatasetInfo: ['imac']"): a dataset built now loads without one. The old layout, where the block
    is such a key, shows that the capture sees the warning where LeRobot gives it (0.5.1 on;
    0.4.4 loads ``info.json`` as a plain dict and says nothing)."""
    assert [m for m in _load_messages(built, caplog) if "imac" in m] == []
    if not isinstance(LeRobotDatasetMetadata(REPO, root=built).info, Mapping):  # LeRobot >= 0.5.1: DatasetInfo
        assert any("Unknown fields" in m and "imac" in m for m in _load_messages(old_layout, caplog))


def _without_version(x):
    """A result with the block's schema version left out (the old layout's is 2)."""
    if isinstance(x, dict):
        return {k: _without_version(v) for k, v in x.items() if k != "schema_version"}
    return x


def test_the_old_layout_reads_as_before(built, old_layout):
    """A dataset of schema version 2 (the block in ``meta/info.json``) reads through the one reader,
    the rig and the model's reader included, with the same answers as the new layout's."""
    assert not (old_layout / IMAC_INFO).exists()
    assert dataset_info(old_layout)["imac"]["schema_version"] == 2
    assert imac_block(old_layout, require=RIG_KEYS)["schema_version"] == 2
    assert _without_version(dataset_info(old_layout)) == _without_version(dataset_info(built))
    assert imac_data.metadata.imac_block_path(old_layout) == old_layout / INFO
    for qual, fn in metadata_functions().items():
        if qual == "imac_data.metadata.dataset_root":
            continue
        for form, meta in _forms(old_layout).items():
            got = _plain(_call(fn, meta, old_layout))
            assert _without_version(got) == _without_version(_plain(_call(fn, built, built))), (qual, form)
    assert imac_data.Rig.from_dataset(old_layout).to_info() == imac_data.Rig.from_dataset(built).to_info()


def test_the_next_write_moves_the_block_out(old_layout, tmp_path):
    """A write of an old-layout dataset, direct (``write_info``) or staged (a column added), moves
    the block to ``meta/imac/info.json`` and takes it out of ``meta/info.json``, unchanged."""
    for how in ("write_info", "staged"):
        root = tmp_path / how
        shutil.copytree(old_layout, root)
        before = dataset_info(root)
        if how == "write_info":
            write_info(root, before)
        else:
            assert before["total_episodes"] == 1  # the one episode holds every frame
            add_frame_column(root, "extra", [[[0.0]] * before["total_frames"]], ["x"])
            before["features"]["extra"] = dataset_info(root)["features"]["extra"]
        assert "imac" not in json.loads((root / INFO).read_text()), how
        assert json.loads((root / IMAC_INFO).read_text()) == before["imac"], how
        assert dataset_info(root) == before, how
        assert imac_data.metadata.imac_block_path(root) == root / IMAC_INFO


# --------------------------------------------------------------------------- the source


def _imac_key_uses(tree: ast.AST) -> list[int]:
    """Lines where the string ``"imac"`` appears as a value (a key, an argument, a comparison...)."""
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value == "imac"]


def _success_literals(tree: ast.AST) -> list[int]:
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value == SUCCESS_COLUMN]


def test_imac_model_reads_the_imac_block_through_the_one_reader():
    """No ``["imac"]``, ``.get("imac")``, ``"imac" in``, ``{"imac": ...}`` or any other use of the key
    in ``imac_model``: the one reader is ``imac_data.metadata``. And the success column is named
    only by ``imac_data.layout.SUCCESS_COLUMN``."""
    wrong = []
    for path in sorted((ROOT / "imac_model").rglob("*.py")):
        tree = ast.parse(path.read_text())
        wrong += [f"{path.relative_to(ROOT)}:{line}: the imac key" for line in _imac_key_uses(tree)]
        wrong += [f"{path.relative_to(ROOT)}:{line}: {SUCCESS_COLUMN!r} spelled out" for line in _success_literals(tree)]
    assert not wrong, "\n".join(wrong)


def _imac_block_reads(tree: ast.AST) -> list[int]:
    """Lines that index the ``imac`` key: ``x["imac"]`` or ``x.get("imac", ...)`` (a docstring or a
    comment that mentions ``info["imac"]`` is not code)."""
    def is_imac(node) -> bool:
        return isinstance(node, ast.Constant) and node.value == "imac"

    return [n.lineno for n in ast.walk(tree)
            if (isinstance(n, ast.Subscript) and is_imac(n.slice))
            or (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "get"
                and n.args and is_imac(n.args[0]))]


def test_imac_data_indexes_the_imac_block_only_in_its_reader_and_writer():
    """``imac_data.metadata`` reads the block (``imac_block``, ``unchecked_imac_block``) and
    ``imac_data.dataset.info`` writes it; no other module indexes the key of an info dict."""
    allowed = {ROOT / "imac_data" / "metadata.py", ROOT / "imac_data" / "dataset" / "info.py"}
    wrong = [f"{path.relative_to(ROOT)}:{line}" for path in sorted((ROOT / "imac_data").rglob("*.py"))
             if path not in allowed for line in _imac_block_reads(ast.parse(path.read_text()))]
    assert not wrong, "the imac block read outside imac_data.metadata:\n" + "\n".join(wrong)
    assert all(_imac_block_reads(ast.parse(path.read_text())) for path in allowed)  # the check reads them


@pytest.mark.parametrize("source, lines", [('x = info["imac"]["augment"]', [1]), ('x = info.get("imac", {})', [1]),
                                           ('def f(info):\n    """Reads ``info["imac"]``."""\n    return 1', []),
                                           ('# info.get("imac")\nok = "imac" in info', [])])
def test_the_imac_data_check_reads_code_not_docstrings(source, lines):
    assert _imac_block_reads(ast.parse(source)) == lines


@pytest.mark.parametrize("source", ['x = info["imac"]["augment"]', 'x = info.get("imac", {})', 'ok = "imac" in info',
                                    'key = "imac"\nx = info[key]', 'row = {"imac/success": True}'])
def test_the_source_check_catches_each_form(source):
    tree = ast.parse(source)
    assert _imac_key_uses(tree) or _success_literals(tree)
