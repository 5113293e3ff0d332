#!/usr/bin/env bash
# The RoboDesk GW-Dreamer result behind docs/figures (push_green at the CPU scale), seeds 1..N, then the
# figures.
#
#   bash benchmarks/reproduce_robodesk.sh 3               # N = 3 seeds (default 3) on the bundled GW
#   PRETRAIN=1 bash benchmarks/reproduce_robodesk.sh 3    # first make the VAEs + GW anew (about 70 min)
#   DRY_RUN=1 bash benchmarks/reproduce_robodesk.sh 2     # print the commands only
#   MODELS="gw e2e dreamer vae_dreamer" bash benchmarks/reproduce_robodesk.sh 2   # the baselines too
#   TASKS="push_red push_blue open_slide open_drawer" bash benchmarks/reproduce_robodesk.sh 2   # Figures 6, 7
#   MODELS="gw_ppo ppo" bash benchmarks/reproduce_robodesk.sh 1   # PPO, to 1,000,000 frames
#
# Runs JOBS (default 2) trainings at a time, each with --torch-threads 1. A seed of
# `gw_dreamer.py --env robodesk --cpu-preset` runs to the criterion or 200,000 frames: up to about
# 2.3-3 h with two side by side on a 2-core AMD EPYC CPU with AVX-512, about 7.5 h without (torch 2.13.0,
# docs/gw_dreamer.md#robodesk-on-a-cpu), then
# its modality ablation (10 episodes each with both modalities, without vision, without attributes:
# about 3 min each).
#
# MODELS (default "gw") picks the agents, each at its --cpu-preset: gw (gw_dreamer.py), e2e
# (gw_dreamer_e2e.py), dreamer and vae_dreamer (dreamer_baseline.py --obs raw / vae: the 2M model, to
# 800,000 frames, several times GW-Dreamer's time); gw_ppo and ppo (ppo_variants.py --variant gw / raw at
# its defaults, 1,000,000 frames; raw on fast images, those of the bundled GW's data). TASKS (default
# "push_green") runs each of them on each task: the bundled GW saw push_green, open_slide, open_drawer,
# upright_block_off_table and flat_block_in_bin in its data, not push_red or push_blue.
#
# Everything goes to $OUT (default: reproduced_robodesk/): checkpoints/, runs/ (TensorBoard), logs/,
# results/ (the CSV records) and figures/. Nothing outside it is written, and an existing $OUT is refused.
# RESUME=1 (same N, MODELS, TASKS) continues a reproduction that was stopped: finished steps are not run
# again, a training that was cut continues from its last save (--resume), a pre-training its unfinished
# stage, and the figures are redrawn.
set -euo pipefail
N=${1:-3}
JOBS=${JOBS:-2}
OUT=${OUT:-reproduced_robodesk}
DRY_RUN=${DRY_RUN:-0}
RESUME=${RESUME:-0}
PRETRAIN=${PRETRAIN:-0}
MODELS=${MODELS:-gw}
TASKS=${TASKS:-push_green}
REPO="$(cd "$(dirname "$0")/.." && pwd)"
export MUJOCO_GL=${MUJOCO_GL:-egl}
# $OUT refused if it exists, and step (run a command inside $OUT, its output in logs/<name>.log).
# shellcheck source=benchmarks/reproduce_common.sh
source "$REPO/benchmarks/reproduce_common.sh"

# 1. Pre-training (optional): without it the agents read the bundled envs/pretrained/robodesk/.
if [ "$PRETRAIN" = 1 ]; then
  step pretrain python "$REPO/pretrain_vae_gw.py" --env robodesk --cpu-preset --data-dir data \
    --checkpoint-dir checkpoints
fi

# 2. The agents, JOBS at a time: train to the criterion or their frames, then the modality ablation.
agent() {  # model task seed
  local m=$1 t=$2 s=$3 script run
  local common="--env robodesk --task $t --seed $s --checkpoint-dir checkpoints --torch-threads 1"
  case $m in
    gw) script=gw_dreamer.py run=gw_dreamer_gw common="$common --cpu-preset" ;;
    e2e) script=gw_dreamer_e2e.py run=gw_dreamer_e2e_gw common="$common --cpu-preset" ;;
    dreamer) script=dreamer_baseline.py run=dreamer_raw_2m common="$common --cpu-preset --obs raw" ;;
    vae_dreamer) script=dreamer_baseline.py run=dreamer_vae_2m common="$common --cpu-preset --obs vae" ;;
    gw_ppo) script=ppo_variants.py run=ppo_gw common="$common --variant gw" ;;
    ppo) script=ppo_variants.py run=ppo_raw common="$common --variant raw --render-quality fast" ;;
    *) echo "unknown model $m in MODELS (gw, e2e, dreamer, vae_dreamer, gw_ppo, ppo)" >&2; return 2 ;;
  esac
  local name="${run}_robodesk_${t}_s$s"
  # shellcheck disable=SC2086  # flags are words
  train "$name" python "$REPO/$script" $common --stop-at-criterion
  # a training that failed or was cut is not evaluated (RESUME=1 continues it, then evaluates it)
  [ "$DRY_RUN" = 1 ] || [ -e "$OUT/logs/$name.done" ] || return 0
  for drop in none vision attr; do
    # shellcheck disable=SC2086
    step "${name}_drop_$drop" python "$REPO/$script" $common --eval-only --drop $drop --eval-episodes 10
    if [ "$DRY_RUN" != 1 ]; then
      grep "\[eval\]" "$OUT/logs/${name}_drop_$drop.log" > "$OUT/runs/$name/eval_drop_$drop.txt" || true
    fi
  done
}
export -f attempt step train agent
export OUT REPO DRY_RUN RESUME
jobs_list() {
  for m in $MODELS; do for t in $TASKS; do for s in $(seq 1 "$N"); do echo "$m $t $s"; done; done; done
}
if [ "$DRY_RUN" = 1 ]; then
  jobs_list | while read -r m t s; do agent "$m" "$t" "$s"; done
else
  jobs_list | xargs -P "$JOBS" -L 1 bash -c 'agent "$1" "$2" "$3"' _
fi

# 3. The figures and the records they are drawn from, redrawn on every call (RESUME=1 included).
[ "$DRY_RUN" = 1 ] || rm -f "$OUT/logs/figures.done"
step figures python "$REPO/benchmarks/paper_figures.py" --env robodesk --runs runs --export results \
  --out figures
[ "$DRY_RUN" = 1 ] || echo "done: $OUT/figures, $OUT/results (merge them into docs/ to replace the committed ones)"
