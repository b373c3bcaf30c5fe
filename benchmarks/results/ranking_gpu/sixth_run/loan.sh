#!/usr/bin/env bash
# The sixth GPU loan, as it ran (benchmarks/results/ranking_gpu/README.md, "The sixth GPU run"): two calls of scripts/gpu_ranking.sh side by
# side on one GPU, both from the fourth run's weights (runs/loan5/init):
#   a: motion+contact, the fourth run's own recipe (ROLLOUT=4, ROLLOUT_STEPS=0): the control;
#   b: motion+contact and action-vector over clips of 2 chunks from 4 sampler steps (ROLLOUT=2, ROLLOUT_STEPS=4):
#      every chunk is trained both from a recorded frame and from the model's own.
# CALL=1 carries the pack and keeps it and the weights in /tmp/keep; CALL=2 goes on from there (nothing carried).
#   OUT=/tmp/out CALL=1 MINUTES=8.6 bash benchmarks/results/ranking_gpu/sixth_run/loan.sh
set -uo pipefail
cd "$(dirname "$0")/../../../.."
: "${OUT:?}" "${CALL:?}" "${MINUTES:?}"
KEEP=/tmp/keep
if [ "$CALL" = 1 ]; then
  mkdir -p "$KEEP/gpu" && cp -r runs/loan5/gpu/. "$KEEP/gpu/"
  init_a=runs/loan5/init init_b=runs/loan5/init
else
  init_a=$KEEP/a init_b=$KEEP/b
fi
common=(BATCH="${BATCH:-512}" LR=1.2e-3 WARMUP=50 EVAL_EVERY=100 REF_NOISE=0.3 MINUTES="$MINUTES" PACK="$KEEP/gpu/pack.npz")
command -v nvidia-smi >/dev/null && { nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 20 \
  > "$OUT/smi$CALL.csv" & smi=$!; }
env "${common[@]}" INIT="$init_a" RUNS=motion_contact ROLLOUT=4 ROLLOUT_STEPS=0 OUT="$OUT/a" \
  bash scripts/gpu_ranking.sh > "$OUT/a$CALL.log" 2>&1 & a=$!
env "${common[@]}" INIT="$init_b" ROLLOUT=2 ROLLOUT_STEPS=4 OUT="$OUT/b" \
  bash scripts/gpu_ranking.sh > "$OUT/b$CALL.log" 2>&1 & b=$!
wait $a; ra=$?; wait $b; rb=$?
[ -n "${smi:-}" ] && kill "$smi"
for v in a b; do  # the weights, as INIT wants them, for the next call
  for tar in "$OUT/$v"/*.tar; do
    [ -f "$tar" ] || continue
    run=$(basename "$tar" .tar); dir="$KEEP/$v/$run/checkpoints/step_000001"
    rm -rf "$KEEP/$v/$run"; mkdir -p "$dir" && tar -xf "$tar" -C "$dir" model.json model.safetensors
  done
done
tail -n 4 "$OUT/a$CALL.log" "$OUT/b$CALL.log"
echo "loan call $CALL: a rc $ra, b rc $rb"
exit $(( ra || rb ))
