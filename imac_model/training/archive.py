"""A trained run as one file, ``<run>.tar`` or ``<run>.tar.xz``: its latest checkpoint's ``model.json`` and
``model.safetensors``, its ``log.jsonl`` and, where it has one, its early gates' ``gates.json``, flat. The GPU
machine returns each run of a loan (:mod:`.runs`) this way (a loan returns few files); ``imac-model ranking
--import-gpu`` reads them back into a work directory, ``--export-runs`` writes them from one (xz-compressed, to be
committed: the hub is out of reach), and ``train.init`` starts from one. ``docs/ranking.md`` ("Weights between
loans") has the procedure."""

from __future__ import annotations

import io
import os
import tarfile
from pathlib import Path

from imac_data.errors import InputError
from imac_model.models.checkpoint import EMA, SPEC, WEIGHTS, read_weights
from imac_model.training.log import LOG_FILE

MEMBERS = (SPEC, WEIGHTS, LOG_FILE)
GATES = "gates.json"  # the ranking's early gates of a run (an optional member): a report reads them
SUFFIXES = (".tar.xz", ".tar")


def run_name(path: str | Path) -> str | None:
    """The run an archive holds, from its file name (``motion_contact.tar.xz`` -> ``motion_contact``);
    None for a file that is not named as one."""
    name = Path(path).name
    return next((name[: -len(s)] for s in SUFFIXES if name.endswith(s) and len(name) > len(s)), None)


def archives_in(directory: str | Path) -> list[Path]:
    """The run archives of ``directory``, by name (one per run: a ``.tar.xz`` and a ``.tar`` of the same run
    are refused, since which one holds the weights is not decidable)."""
    found = sorted(p for p in Path(directory).iterdir() if p.is_file() and run_name(p))
    names = [run_name(p) for p in found]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"{directory}: runs {twice} are there both as .tar and .tar.xz; keep one of each")
    return found


def read_archive(path: str | Path) -> dict[str, bytes]:
    """The members of a run archive (any compression tarfile reads), refused with the members it
    holds when it is not one."""
    path = Path(path)
    try:
        with tarfile.open(path) as archive:
            names = set(archive.getnames())
            if not set(MEMBERS) <= names:
                raise InputError(f"{path}: not a run archive (it holds {sorted(names)}; "
                                 f"a run needs {list(MEMBERS)})")
            return {n: archive.extractfile(n).read() for n in (*MEMBERS, GATES) if n in names}
    except (tarfile.TarError, EOFError) as e:
        raise InputError(f"{path}: not a readable tar archive ({e})") from None


def unpack_checkpoint(path: str | Path, directory: str | Path) -> Path:
    """The checkpoint of a run archive, written into ``directory`` (``model.json``, ``model.safetensors``)."""
    files = read_archive(path)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name in (SPEC, WEIGHTS):
        (directory / name).write_bytes(files[name])
    return directory


def _ema_half(checkpoint: Path) -> bytes:
    """The checkpoint's weights with its EMA applied, in float16: what sampling loads, at half the size."""
    from safetensors.torch import save

    weights = read_weights(checkpoint / WEIGHTS)
    if (checkpoint / EMA).is_file():
        weights.update(read_weights(checkpoint / EMA))
    return save({k: (v.half() if v.is_floating_point() else v).contiguous() for k, v in weights.items()})


def write_archive(checkpoint: str | Path, log: str | Path, path: str | Path, *, ema_half: bool = False,
                  gates: str | Path | None = None) -> Path:
    """``checkpoint``'s spec and weights, the log file ``log`` and the gates file ``gates`` (where it exists) as
    the run archive ``path`` (xz-compressed when it ends in ``.tar.xz``), written atomically. ``ema_half``: the
    weights are the EMA's, in float16 (a trained run handed back; its optimizer state stays behind)."""
    path = Path(path)
    if run_name(path) is None:
        raise InputError(f"{path}: a run archive is named <run>{' or <run>'.join(SUFFIXES)}")
    sources = {SPEC: Path(checkpoint) / SPEC, WEIGHTS: Path(checkpoint) / WEIGHTS, LOG_FILE: Path(log)}
    if gates is not None and Path(gates).is_file():
        sources[GATES] = Path(gates)
    missing = [str(p) for p in sources.values() if not p.is_file()]
    if missing:
        raise InputError(f"run archive {path}: missing {missing}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    xz = path.name.endswith(".tar.xz")
    try:
        with (tarfile.open(tmp, "w:xz", preset=9) if xz else tarfile.open(tmp, "w")) as archive:
            for name, source in sources.items():
                data = _ema_half(Path(checkpoint)) if ema_half and name == WEIGHTS else source.read_bytes()
                info = tarfile.TarInfo(name)
                info.size, info.mode = len(data), 0o644
                archive.addfile(info, io.BytesIO(data))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # a half-written archive is never left behind
    return path


__all__ = ["GATES", "MEMBERS", "archives_in", "read_archive", "run_name", "unpack_checkpoint", "write_archive"]
