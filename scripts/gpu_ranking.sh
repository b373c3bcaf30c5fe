#!/usr/bin/env bash
# The GPU preset's training (docs/ranking.md, "The GPU preset"), run on a GPU machine that has Python,
# torch and numpy and nothing else of ours: motion+contact and action-vector trained at once on one GPU,
# from the tensor pack `imac-model ranking --stages ...,pack` wrote, for the same wall-clock budget each.
# ROLLOUT=R trains every run with training-time rollout over clips of R chunks (default 1: none).
# ABLATION=1 (or focus) also trains motion+contact with a uniform loss (focus_weight 0) as motion_contact_uniform,
# the loss-weighting ablation (python -m benchmarks.ablation focus); ABLATION=rollout trains motion+contact without
# rollout as motion_contact_no_rollout, the rollout ablation; ABLATION=first-frame trains motion+contact conditioned
# on the episode's first frame as motion_contact_first_frame, the memory ablation; ABLATION=scene-warp trains it with the
# scene-warp stream as motion_contact_scene_warp; ABLATION=contact (with ROLLOUT) trains it with the contact images of
# each rolled-out chunk painted from that chunk's own reference (the pack's contact geometry,
# imac_model/pipelines/packed_contact.py) instead of the recorded ones, as motion_contact_rebuilt. DROPOUT=P trains every run with a
# share P of its samples without controls (conditioning.dropout), so the models can be sampled with guidance. PyYAML and safetensors travel as wheels
# beside the pack (runs/ranking_gpu/gpu/wheels/) when the machine lacks them. COMPILE=1 trains every run through
# torch.compile of the U-Net's trunk (--compile; the compilation counts in each run's minutes; the default, auto, compiles
# on a GPU only: on a CPU the compilation takes minutes); SPEED=1 then measures
# eager against compiled alone on the GPU (python -m benchmarks.pack_speed) into $OUT/speed.json. Each run comes back as one
# file, $OUT/<run>.tar (model.json, model.safetensors: float16 EMA weights, log.jsonl), since the GPU
# machine returns few files; `imac-model ranking --preset gpu --import-gpu DIR` puts them back here.
# RUNS="name ..." trains only those of the runs above (e.g. RUNS=motion_contact), so that two calls of this script
# with other settings can share one GPU.
# INIT=DIR starts every run from the weights of DIR/<run> (a run directory of an earlier loan, as
# `--import-gpu` put it back: its latest checkpoint) or of DIR/<run>.tar.xz or DIR/<run>.tar (a run archive, as
# `--export-runs` writes and a loan returns), so training goes on over several loans. KEEP_WEIGHTS=DIR also
# leaves each run's weights in DIR/<run> as INIT reads them, so a second call on the same machine goes on from there.
# PROGRESS_DIR=DIR: each run keeps its trained samples in DIR/<run>.json; PACE_WITH=FILE (such a file of a run of
# another call): every run here stays within a step of that run's samples and stops at its final count, so the two
# get equal budgets in samples and this call's waits go to the other (imac_model/training/pace.py).
#   OUT=/tmp/gpu_out MINUTES=8 bash scripts/gpu_ranking.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PACK=${PACK:-runs/ranking_gpu/gpu/pack.npz}
MINUTES=${MINUTES:-8}
SAMPLES=${SAMPLES:-}  # each run also stops once it has trained this many samples (equal budgets in samples)
BATCH=${BATCH:-128}  # chunks a step (the tests run the script at toy size with fewer)
LR=${LR:-6e-4}  # AdamW's peak learning rate (scale it with BATCH)
WARMUP=${WARMUP:-200}  # steps of learning-rate warm-up (fewer at a larger BATCH: the same samples)
EVAL_EVERY=${EVAL_EVERY:-500}  # steps between held-out losses in each run's log
REF_NOISE=${REF_NOISE:-}  # flow.reference_noise for every run (default: the pack's spec)
ROLLOUT_STEPS=${ROLLOUT_STEPS:-0}  # with ROLLOUT: chunk r > 1 starts from this many sampler steps (0: the one-step estimate)
ABLATION=${ABLATION:-0}
ROLLOUT=${ROLLOUT:-1}
DROPOUT=${DROPOUT:-0}
COMPILE=${COMPILE:-auto}
SPEED=${SPEED:-0}
INIT=${INIT:-}
KEEP_WEIGHTS=${KEEP_WEIGHTS:-}
RUNS=${RUNS:-}
PROGRESS_DIR=${PROGRESS_DIR:-}
PACE_WITH=${PACE_WITH:-}
: "${OUT:?set OUT to the directory for the checkpoints}"
mkdir -p "$OUT"
PY=${PYTHON:-$(command -v python3 || command -v python)}
[ -f "$PACK" ] || { echo "gpu_ranking: no tensor pack at $PACK (imac-model ranking --stages simulate,build,decode,pack)" >&2; exit 2; }
read -r torch_version cuda < <("$PY" -c 'import torch; print(torch.__version__, torch.cuda.is_available())') \
  || { echo "gpu_ranking: $PY cannot import torch" >&2; exit 2; }
echo "[gpu] $($PY --version) at $PY; torch $torch_version $cuda"
[ "$COMPILE" = auto ] && { [ "$cuda" = True ] && COMPILE=1 || COMPILE=0; }
"$PY" -c "import lzma" 2>/dev/null || { echo "gpu_ranking: $PY has no lzma module, and the pack's arrays are LZMA-compressed (imac_model/training/pack.py)" >&2; exit 2; }
site=$(mktemp -d)
trap 'rm -rf "$site"' EXIT  # the unpacked wheels, if any
if ! "$PY" -c "import yaml, safetensors" 2>/dev/null; then
  for wheel in "$(dirname "$PACK")"/wheels/*.whl; do "$PY" -m zipfile -e "$wheel" "$site"; done
fi
export PYTHONPATH="$PWD:$site${PYTHONPATH:+:$PYTHONPATH}"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,memory.used --format=csv,noheader
extra=""
[ "$COMPILE" = 1 ] && extra="--compile"
[ -n "$REF_NOISE" ] && extra="$extra --reference-noise $REF_NOISE"
[ -n "$SAMPLES" ] && extra="$extra --max-samples $SAMPLES"
[ -n "$PACE_WITH" ] && extra="$extra --pace-with $PACE_WITH"
extra="$extra --rollout-reference-steps $ROLLOUT_STEPS"
runs=("motion_contact motion+contact --rollout-chunks $ROLLOUT" "action_vector action-vector --rollout-chunks $ROLLOUT")
case "$ABLATION" in
  1|focus) runs+=("motion_contact_uniform motion+contact --focus-weight 0 --rollout-chunks $ROLLOUT") ;;
  rollout) runs+=("motion_contact_no_rollout motion+contact --rollout-chunks 1") ;;
  first-frame) runs+=("motion_contact_first_frame motion+contact --first-frame --rollout-chunks $ROLLOUT") ;;
  scene-warp) runs+=("motion_contact_scene_warp motion+contact --scene-warp --rollout-chunks $ROLLOUT") ;;
  contact) [ "$ROLLOUT" -gt 1 ] || { echo "gpu_ranking: ABLATION=contact rebuilds a rollout's contact images; set ROLLOUT > 1" >&2; exit 2; }
           runs+=("motion_contact_rebuilt motion+contact --rebuild-contact --rollout-chunks $ROLLOUT") ;;
  0) ;;
  *) echo "gpu_ranking: ABLATION must be 0, 1 (focus), rollout, first-frame, scene-warp or contact, got $ABLATION" >&2; exit 2 ;;
esac
if [ -n "$RUNS" ]; then  # the chosen subset, in the order above, each name checked
  known=" $(for run in "${runs[@]}"; do set -- $run; printf '%s ' "$1"; done)"
  for name in $RUNS; do
    [[ "$known" == *" $name "* ]] || { echo "gpu_ranking: RUNS names $name; the runs are:$known" >&2; exit 2; }
  done
  chosen=()
  for run in "${runs[@]}"; do set -- $run; [[ " $RUNS " == *" $1 "* ]] && chosen+=("$run"); done
  runs=("${chosen[@]}")
fi
init_of() {  # run $1's start under INIT: its run directory, else its run archive
  local c
  for c in "$INIT/$1" "$INIT/$1.tar.xz" "$INIT/$1.tar"; do [ -e "$c" ] && { echo "$c"; return 0; }; done
  return 1
}
if [ -n "$INIT" ]; then  # every run's start, checked before any training
  for run in "${runs[@]}"; do
    set -- $run
    init_of "$1" >/dev/null || { echo "gpu_ranking: INIT=$INIT has no run $1 to start from ($1/, $1.tar.xz or $1.tar)" >&2; exit 2; }
  done
fi
pids=()
for run in "${runs[@]}"; do
  set -- $run
  name=$1; shift
  own=""  # this run's own options
  [ -n "$INIT" ] && own="--init $(init_of "$name")"
  [ -n "$PROGRESS_DIR" ] && own="$own --report $PROGRESS_DIR/$name.json"
  "$PY" -m imac_model.training.pack train --pack "$PACK" --mode "$@" --minutes "$MINUTES" --batch-size "$BATCH" --lr "$LR" --warmup "$WARMUP" --eval-every "$EVAL_EVERY" --dropout "$DROPOUT" $extra $own --output "$OUT/$name" \
    > "$OUT/$name.stdout" 2>&1 &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=1; done
for run in "${runs[@]}"; do
  set -- $run
  dir="$OUT/$1"
  tail -n 3 "$OUT/$1.stdout"
  ckpt=$(ls -d "$dir"/checkpoints/step_* 2>/dev/null | tail -n 1) || true
  if [ -n "$ckpt" ]; then
    if [ -n "$KEEP_WEIGHTS" ]; then  # after the run: its INIT may be this very directory
      rm -rf "${KEEP_WEIGHTS:?}/$1" && mkdir -p "$KEEP_WEIGHTS/$1/checkpoints" && cp -r "$ckpt" "$KEEP_WEIGHTS/$1/checkpoints/"
    fi
    tar -cf "$OUT/$1.tar" -C "$ckpt" model.json model.safetensors -C "$dir" log.jsonl -C "$OUT" "$1.stdout"
    rm -r "$dir" "$OUT/$1.stdout"
  fi
done
if [ "$SPEED" = 1 ]; then  # after the checkpoints are safe: a budget of its own, and its caches are warm
  timeout 100 "$PY" -m benchmarks.pack_speed --pack "$PACK" --rollout-chunks "$ROLLOUT" --batch-size "$BATCH" \
    --json "$OUT/speed.json" || echo "gpu_ranking: the speed benchmark did not finish" >&2
fi
ls -la "$OUT"
exit $status
