#!/usr/bin/env bash
# The GPU preset's training (docs/ranking.md, "The GPU preset"), run on a GPU machine that has Python,
# torch and numpy and nothing else of ours: motion+contact and action-vector trained at once on one GPU,
# from the tensor pack `imac-model ranking --stages ...,pack` wrote, for the same wall-clock budget each.
# PyYAML and safetensors travel as wheels beside the pack (runs/ranking/gpu/wheels/) when the machine
# lacks them. Checkpoints (float16 EMA weights) and logs go to $OUT/<mode>.*; `imac-model ranking
# --import-gpu DIR` puts them back into the work directory as trained runs.
#   OUT=/tmp/gpu_out MINUTES=5 bash scripts/gpu_ranking.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PACK=${PACK:-runs/ranking/gpu/pack.npz}
MINUTES=${MINUTES:-5}
: "${OUT:?set OUT to the directory for the checkpoints}"
PY=${PYTHON:-$(command -v python3 || command -v python)}
[ -f "$PACK" ] || { echo "gpu_ranking: no tensor pack at $PACK (imac-model ranking --stages simulate,build,decode,pack)" >&2; exit 2; }
echo "[gpu] $($PY --version) at $PY; torch $($PY -c 'import torch; print(torch.__version__, torch.cuda.is_available())')"
site=$(mktemp -d)
if ! "$PY" -c "import yaml, safetensors" 2>/dev/null; then
  for wheel in "$(dirname "$PACK")"/wheels/*.whl; do "$PY" -m zipfile -e "$wheel" "$site"; done
fi
export PYTHONPATH="$PWD:$site${PYTHONPATH:+:$PYTHONPATH}"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,memory.used --format=csv,noheader
pids=()
for mode in motion+contact action-vector; do
  "$PY" -m imac_model.training.pack train --pack "$PACK" --mode "$mode" --minutes "$MINUTES" \
    --output "$OUT/${mode//[+-]/_}" &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=1; done
# the GPU machine returns files at the top of $OUT only: <mode>.model.json, .model.safetensors, .log.jsonl
for dir in "$OUT"/*/; do
  mode=$(basename "$dir")
  ckpt=$(ls -d "$dir"checkpoints/step_* | tail -n 1)
  mv "$ckpt/model.json" "$OUT/$mode.model.json"
  mv "$ckpt/model.safetensors" "$OUT/$mode.model.safetensors"
  mv "$dir/log.jsonl" "$OUT/$mode.log.jsonl"
  rm -r "$dir"
done
ls -la "$OUT"
exit $status
