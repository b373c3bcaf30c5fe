#!/usr/bin/env bash
# The sharded trainer on the CPU: 2 processes over gloo, the code path of the GPU launches (what
# tests/test_model_scale.py runs, with a tiny Wan config). Any imac dataset whose views patchify at 32x32.
#   DATASET=local/my_task CONFIG=my_tiny_wan.yaml scripts/launch/cpu_2proc.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
torchrun --standalone --nproc-per-node 2 -m imac_model train --dataset "${DATASET:?set DATASET}" \
  --config "${CONFIG:?set CONFIG}" --set train.sharding.strategy=fsdp2 --set train.cpu_threads=1 "$@"
