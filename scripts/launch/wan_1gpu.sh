#!/usr/bin/env bash
# Wan2.2-TI2V-5B with the iMaC controls on one 80 GB GPU. The training states alone (fp32 weights, gradients,
# AdamW moments and EMA: 20 bytes x 5.0 B parameters = 100 GB) exceed the card, so the plan has nothing that
# fits on the GPU alone. What fits: FSDP2 on one process with CPU offload. The states live in host memory
# (100 GB, pinned; the optimizer step and the EMA update run on the CPU); the GPU holds the bf16 VAE, the
# gathered bf16 blocks, one block's gradients and the activations: 37.9 GB at the config's batch of 64 (3.8 GB
# at 1). Host memory: the 100 GB of states plus the run itself (about 110 GB; a 128 GB machine is tight).
# docs/scale.md has the details; nothing here has run on a GPU yet.
#   DATASET=local/my_task scripts/launch/wan_1gpu.sh [--set backbone.wan.pretrained=/path/to/Wan2.2-TI2V-5B-Diffusers]
set -euo pipefail
cd "$(dirname "$0")/../.."
export PYTORCH_CUDA_ALLOC_CONF=${PYTORCH_CUDA_ALLOC_CONF:-expandable_segments:True}
python -m imac_model train --dataset "${DATASET:?set DATASET=local/<name>}" \
  --config imac_model/configs/wan2.2_ti2v_5b.yaml --set train.sharding.cpu_offload=true "$@"
