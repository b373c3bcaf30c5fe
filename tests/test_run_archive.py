"""Run archives (imac_model/training/archive.py): a trained run as one file, read back byte for byte, and
clear errors for files that are not one. The GPU path that writes and reads them end to end is in
tests/test_ranking.py (the GPU preset's test)."""

import tarfile

import pytest

from imac_data.errors import InputError
from imac_model.training.archive import archives_in, read_archive, run_name, unpack_checkpoint, write_archive


@pytest.fixture
def run(tmp_path):
    ckpt = tmp_path / "run" / "checkpoints" / "step_000007"
    ckpt.mkdir(parents=True)
    (ckpt / "model.json").write_text('{"spec": 1}')
    (ckpt / "model.safetensors").write_bytes(bytes(range(256)) * 64)
    (tmp_path / "run" / "log.jsonl").write_text('{"step": 7}\n')
    return ckpt


def test_an_archive_holds_the_checkpoint_and_the_log_byte_for_byte(run, tmp_path):
    for name in ("motion_contact.tar.xz", "motion_contact.tar"):
        path = write_archive(run, run.parents[1] / "log.jsonl", tmp_path / "out" / name)
        with tarfile.open(path) as archive:  # another reader than ours: the standard library's, any compression
            assert sorted(archive.getnames()) == ["log.jsonl", "model.json", "model.safetensors"]
        files = read_archive(path)
        assert files["model.safetensors"] == (run / "model.safetensors").read_bytes()
        assert files["log.jsonl"] == b'{"step": 7}\n' and run_name(path) == "motion_contact"
        unpacked = unpack_checkpoint(path, tmp_path / "unpacked" / name)
        assert (unpacked / "model.json").read_bytes() == (run / "model.json").read_bytes()
    sizes = {p.name: p.stat().st_size for p in (tmp_path / "out").iterdir()}
    assert sizes["motion_contact.tar.xz"] < sizes["motion_contact.tar"]  # xz: what is committed and carried


def test_files_that_are_not_run_archives_are_named(run, tmp_path):
    assert run_name("a/run.tar.gz") is None and run_name(".tar") is None and run_name("x.tar") == "x"
    (tmp_path / "broken.tar.xz").write_bytes(b"not a tar at all")
    with pytest.raises(InputError, match="broken.tar.xz: not a readable tar archive"):
        read_archive(tmp_path / "broken.tar.xz")
    with tarfile.open(tmp_path / "partial.tar", "w") as archive:
        archive.add(run / "model.json", arcname="model.json")
    with pytest.raises(InputError, match=r"partial.tar: not a run archive \(it holds \['model.json'\]"):
        read_archive(tmp_path / "partial.tar")
    with pytest.raises(InputError, match="missing"):
        write_archive(run, tmp_path / "no_log.jsonl", tmp_path / "x.tar")
    with pytest.raises(InputError, match="is named <run>.tar.xz or <run>.tar"):
        write_archive(run, run.parents[1] / "log.jsonl", tmp_path / "x.zip")
    both = tmp_path / "both"
    both.mkdir()
    for name in ("motion_contact.tar", "motion_contact.tar.xz"):
        write_archive(run, run.parents[1] / "log.jsonl", both / name)
    with pytest.raises(InputError, match=r"runs \['motion_contact'\] are there both as .tar and .tar.xz"):
        archives_in(both)
