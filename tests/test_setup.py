"""``scripts/setup.sh``'s choice of interpreter, run as a user runs it: ``PYTHON`` (else ``python3``)
is named, a Python older than 3.11 and an interpreter that does not run are refused, and an
environment made by another Python is refused rather than reused. Each case stops before pip."""

from __future__ import annotations

import glob
import os
import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROBE = 'import os, sys; print(os.path.realpath(sys._base_executable), "%d.%d.%d" % sys.version_info[:3])'


def run_setup(tmp_path: Path, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(ROOT / "scripts" / "setup.sh")], env={**os.environ, **env},
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)


def interpreters() -> dict[str, tuple[str, str]]:
    """Every Python on this machine that runs: ``{path: (real file, version)}`` (pyenv keeps
    its versions off the PATH, so its folder is looked in too)."""
    found = {}
    pyenv = os.environ.get("PYENV_ROOT", str(Path.home() / ".pyenv"))
    for path in sorted(glob.glob(f"{pyenv}/versions/*/bin/python")) + ["/usr/bin/python3", sys.executable]:
        try:
            out = subprocess.run([path, "-c", PROBE], capture_output=True, text=True, timeout=30)
        except OSError:
            continue
        if out.returncode == 0:
            exe, version = out.stdout.split()
            found[path] = (exe, version)
    return found


def test_an_interpreter_that_does_not_run_is_named(tmp_path):
    out = run_setup(tmp_path, PYTHON="/nonexistent/python3", VENV=str(tmp_path / "v"))
    assert out.returncode == 1
    assert "cannot run '/nonexistent/python3' (from PYTHON)" in out.stderr
    assert not (tmp_path / "v").exists()


def test_a_python_older_than_3_11_is_refused_by_name(tmp_path):
    old = {p: v for p, v in interpreters().items() if tuple(map(int, v[1].split(".")[:2])) < (3, 11)}
    if not old:
        pytest.skip("no Python older than 3.11 on this machine")
    path, (exe, version) = next(iter(old.items()))
    out = run_setup(tmp_path, PYTHON=path, VENV=str(tmp_path / "v"))
    assert out.returncode == 1
    assert f"[setup] Python {version} at {exe}, from PYTHON" in out.stdout
    assert f"is Python {version} ({exe}); the project needs Python 3.11 or newer" in out.stderr
    assert not (tmp_path / "v").exists()


def test_a_venv_made_by_another_python_is_refused(tmp_path):
    mine = interpreters()[sys.executable]
    others = {p: v for p, v in interpreters().items()
              if v[0] != mine[0] and tuple(map(int, v[1].split(".")[:2])) >= (3, 11)}
    if not others:
        pytest.skip("no second Python 3.11+ on this machine")
    path, (exe, version) = next(iter(others.items()))
    venv.create(tmp_path / "v", with_pip=False)  # made by this test's Python
    out = run_setup(tmp_path, PYTHON=path, VENV=str(tmp_path / "v"))
    assert out.returncode == 1
    assert (f"{tmp_path / 'v'} was made by Python {mine[1]} ({mine[0]}), not by the Python asked for, "
            f"{version} ({exe})") in out.stderr
    assert not (tmp_path / "v" / ".imac-install-stamp").exists()  # nothing installed into it
