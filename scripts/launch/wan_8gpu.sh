#!/usr/bin/env bash
# Wan2.2-TI2V-5B with the iMaC controls on 1 node x 8 GPUs (80 GB each): FSDP2 over 8 processes on NCCL.
# The plan (imac-model plan --config imac_model/configs/wan2.2_ti2v_5b.yaml): 20.1 GB per GPU at the
# config's micro-batch of 8 (global batch 64). docs/scale.md has the details; nothing here has run on a GPU yet.
#   DATASET=local/my_task scripts/launch/wan_8gpu.sh [--set backbone.wan.pretrained=/path/to/Wan2.2-TI2V-5B-Diffusers]
set -euo pipefail
cd "$(dirname "$0")/../.."
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-8}
export PYTORCH_CUDA_ALLOC_CONF=${PYTORCH_CUDA_ALLOC_CONF:-expandable_segments:True}
torchrun --standalone --nnodes 1 --nproc-per-node 8 -m imac_model train \
  --dataset "${DATASET:?set DATASET=local/<name>}" --config imac_model/configs/wan2.2_ti2v_5b.yaml "$@"
# The same launched by accelerate (a launcher only: the trainer shards the model itself):
#   accelerate launch --config_file scripts/launch/accelerate_8gpu.yaml -m imac_model train --dataset ... --config ...
# ZeRO-2-like, as the public release (bf16 weights stay gathered from forward to backward, 29.2 GB per GPU):
#   ... --set train.sharding.reshard_after_forward=false
