#!/usr/bin/env bash
# The seventh GPU loan, prepared (docs/ranking.md, "What the outcome needs next", items 1 and 2): the fourth to sixth
# runs' weights are gone, so four runs (three with WARP=0) start from scratch on one GPU for the same minutes, as
# three calls of scripts/gpu_ranking.sh side by side:
#   a: motion+contact and motion+contact with the scene-warp stream, one-step references (ROLLOUT=4, ROLLOUT_STEPS=0);
#   b: action-vector, its best recipe: clips of 2 chunks from 4 sampler steps (ROLLOUT=2, ROLLOUT_STEPS=4);
#   c: motion+contact on action-vector's recipe, its contact images painted from its own sampled references
#      (ABLATION=contact: motion_contact_rebuilt), what kept motion+contact from that recipe so far.
# CALL=1 carries the pack (PACK_DIR, default runs/side_settled/gpu) and keeps it and the weights in /tmp/keep;
# CALL=2 goes on from there (nothing carried), each run from the weights call 1 left (KEEP_WEIGHTS).
# action-vector and motion_contact_rebuilt keep pace with motion_contact (PACE_WITH: never more than a step ahead of its
# samples, stopping at its count), so the compared runs get equal budgets in samples and their waits go to the others.
#   OUT=/tmp/out CALL=1 MINUTES=8.4 bash benchmarks/results/ranking_gpu/seventh_run/loan.sh   (then CALL=2 MINUTES=3.2)
# The workspace view alone (docs/ranking.md, "The views"): PACK_DIR=runs/side_one_view/gpu WARP=0, without the
# scene-warp arm, whose fixed camera's warp is the reference scene itself.
# CALL=2 ends with the rebuild's cost on the GPU (python -m benchmarks.packed_contact on CONTACT_CHUNKS chunks, 64:
# $OUT/packed_contact.json), at most 40 s, so it runs 3.2 minutes instead of the sixth loan's 3.5.
set -uo pipefail
cd "$(dirname "$0")/../../../.."
: "${OUT:?}" "${CALL:?}" "${MINUTES:?}"
KEEP=${KEEP:-/tmp/keep}
init_a="" init_b="" init_c=""
if [ "$CALL" = 1 ]; then
  mkdir -p "$KEEP/gpu" && cp -r "${PACK_DIR:-runs/side_settled/gpu}/." "$KEEP/gpu/"
else
  init_a=$KEEP/a init_b=$KEEP/b init_c=$KEEP/c
fi
common=(BATCH="${BATCH:-512}" LR=1.2e-3 WARMUP=50 EVAL_EVERY="${EVAL_EVERY:-100}" REF_NOISE=0.3 MINUTES="$MINUTES"
        PACK="$KEEP/gpu/pack.npz")
mkdir -p "$OUT"
command -v nvidia-smi >/dev/null && { nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 20 \
  > "$OUT/smi$CALL.csv" & smi=$!; }
if [ "${WARP:-1}" = 1 ]; then warp=(ABLATION=scene-warp RUNS="motion_contact motion_contact_scene_warp")
else warp=(RUNS=motion_contact); fi
env "${common[@]}" "${warp[@]}" INIT="$init_a" KEEP_WEIGHTS="$KEEP/a" PROGRESS_DIR="$KEEP/progress$CALL" \
  ROLLOUT=4 ROLLOUT_STEPS=0 OUT="$OUT/a" \
  bash scripts/gpu_ranking.sh > "$OUT/a$CALL.log" 2>&1 & a=$!
env "${common[@]}" INIT="$init_b" KEEP_WEIGHTS="$KEEP/b" RUNS=action_vector ROLLOUT=2 ROLLOUT_STEPS=4 OUT="$OUT/b" \
  PACE_WITH="$KEEP/progress$CALL/motion_contact.json" bash scripts/gpu_ranking.sh > "$OUT/b$CALL.log" 2>&1 & b=$!
env "${common[@]}" INIT="$init_c" KEEP_WEIGHTS="$KEEP/c" ABLATION=contact RUNS=motion_contact_rebuilt ROLLOUT=2 \
  ROLLOUT_STEPS=4 OUT="$OUT/c" PACE_WITH="$KEEP/progress$CALL/motion_contact.json" bash scripts/gpu_ranking.sh \
  > "$OUT/c$CALL.log" 2>&1 & c=$!
wait $a; ra=$?; wait $b; rb=$?; wait $c; rc=$?
[ -n "${smi:-}" ] && kill "$smi"
if [ "$CALL" = 2 ]; then  # a few seconds: what the rebuild costs a step here, and brute force against KD-trees
  py=${PYTHON:-python3} site=$(mktemp -d)
  "$py" -c "import yaml, safetensors" 2>/dev/null || for w in "$KEEP"/gpu/wheels/*.whl; do "$py" -m zipfile -e "$w" "$site"; done
  PYTHONPATH="$PWD:$site" timeout 40 "$py" -m benchmarks.packed_contact --pack "$KEEP/gpu/pack.npz" \
    --chunks "${CONTACT_CHUNKS:-64}" \
    --json "$OUT/packed_contact.json" > "$OUT/packed_contact.log" 2>&1
  rm -rf "$site"
fi
tail -n 4 "$OUT/a$CALL.log" "$OUT/b$CALL.log" "$OUT/c$CALL.log"
echo "loan call $CALL: a rc $ra, b rc $rb, c rc $rc"
exit $(( ra || rb || rc ))
