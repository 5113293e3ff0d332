#!/usr/bin/env bash
# Every Simple Shapes experiment behind docs/figures, for seeds 1..N, then the figures.
#
#   bash benchmarks/reproduce_simple_shapes.sh 10            # N = 10 seeds (default 3)
#   DRY_RUN=1 bash benchmarks/reproduce_simple_shapes.sh 2   # print the commands only
#
# Runs JOBS (default 2) trainings at a time, each with --torch-threads 1 (two 1-thread runs share a 2-core
# CPU best). Time per seed on a 2-core AMD EPYC CPU (torch 2.13.0, two runs side by side, measured
# 2026-11, docs/results/simple_shapes_runs.csv): GW-Dreamer 5-17 min, CLIP-Dreamer 16-17 min, GW-Dreamer
# end-to-end about 2 h (measured under the earlier, costlier schedule), Dreamer about 40 min, VAE-Dreamer
# 18-25 min, GW-PPO and VAE-PPO 1-2 min, CLIP-PPO 3-6 min, PPO 9-23 min, the modality ablations a few
# minutes: about 4.5 CPU-hours per seed, so about 2.3 hours per seed at two jobs and 23 hours for N = 10,
# after 21 min of pre-training (VAEs + GW 6 min, CLIP-like model 15 min).
#
# Everything goes to $OUT (default: reproduced/): data/, checkpoints/, runs/ (TensorBoard), logs/,
# results/ (the CSV records) and figures/. Nothing outside it is written, and an existing $OUT is refused.
# RESUME=1 (same N, MODELS, TASKS) continues a reproduction that was stopped: finished steps are not run
# again, a training that was cut continues from its last save (--resume), a pre-training its unfinished
# stage, and the figures are redrawn.
set -euo pipefail
N=${1:-3}
JOBS=${JOBS:-2}
OUT=${OUT:-reproduced}
DRY_RUN=${DRY_RUN:-0}
RESUME=${RESUME:-0}
REPO="$(cd "$(dirname "$0")/.." && pwd)"
# $OUT refused if it exists, and step (run a command inside $OUT, its output in logs/<name>.log).
# shellcheck source=benchmarks/reproduce_common.sh
source "$REPO/benchmarks/reproduce_common.sh"

# 1. Pre-training: the VAEs and GW (--cpu-preset, as the bundled ones), then the CLIP-like model.
step pretrain python "$REPO/pretrain_vae_gw.py" --env simple_shapes --cpu-preset --data-dir data \
  --checkpoint-dir checkpoints
step pretrain_clip python "$REPO/pretrain_vae_gw.py" --env simple_shapes --cpu-preset --data-dir data \
  --checkpoint-dir checkpoints --stages gw --loss-preset clip --gw-steps 60000

# 2. The agents, JOBS at a time: train to the criterion or --total-steps, then the modality ablation of
#    the trained agent (50 episodes with both modalities, without vision, without attributes).
agents() {
  for s in $(seq 1 "$N"); do
    echo "gw_dreamer.py --env simple_shapes --seed $s|--total-steps 20000"
    echo "gw_dreamer.py --env simple_shapes --seed $s --gw-checkpoint checkpoints/simple_shapes/clip.pt|--total-steps 20000"
    echo "gw_dreamer_e2e.py --env simple_shapes --cpu-preset --seed $s|--total-steps 60000"
    echo "dreamer_baseline.py --env simple_shapes --seed $s|--total-steps 100000"
    echo "dreamer_baseline.py --env simple_shapes --obs vae --seed $s|--total-steps 100000"
    for v in gw vae clip raw; do
      echo "ppo_variants.py --env simple_shapes --variant $v --seed $s|--total-steps 300000"
    done
  done
}
agent() {  # "<script> <flags>|<training-only flags>"
  local spec=$1 script flags train_flags name
  read -r script flags <<< "${spec%%|*}"
  train_flags=${spec#*|}
  name=$(echo "$script $flags" | tr -c 'A-Za-z0-9_.\n' '_')
  local common="--checkpoint-dir checkpoints --torch-threads 1"
  # shellcheck disable=SC2086  # flags are words
  train "$name" python "$REPO/$script" $flags $train_flags $common --stop-at-criterion
  # a training that failed or was cut is not evaluated (RESUME=1 continues it, then evaluates it)
  [ "$DRY_RUN" = 1 ] || [ -e "$OUT/logs/$name.done" ] || return 0
  local run_dir=""
  local stem  # the run's name: its agent checkpoint's, printed at the end (agents/<name>.pt)
  [ "$DRY_RUN" = 1 ] || stem=$(grep -o "agents/[A-Za-z0-9_]*\.pt" "$OUT/logs/$name.log" | tail -1 || true)
  [ -z "${stem:-}" ] || run_dir="runs/$(basename "$stem" .pt)"
  for drop in none vision attr; do
    # shellcheck disable=SC2086
    step "${name}_drop_$drop" python "$REPO/$script" $flags $common --eval-only --drop $drop --eval-episodes 50
    if [ -n "$run_dir" ]; then grep "\[eval\]" "$OUT/logs/${name}_drop_$drop.log" > "$OUT/$run_dir/eval_drop_$drop.txt" || true; fi
  done
}
export -f attempt step train agent
export OUT REPO DRY_RUN RESUME
if [ "$DRY_RUN" = 1 ]; then
  agents | while read -r spec; do agent "$spec"; done
else
  agents | xargs -P "$JOBS" -I{} bash -c 'agent "$1"' _ {}
fi

# 3. The figures and the records they are drawn from, redrawn on every call (RESUME=1 included).
[ "$DRY_RUN" = 1 ] || rm -f "$OUT/logs/figures.done"
step figures python "$REPO/benchmarks/paper_figures.py" --runs runs --export results --out figures \
  --gw-checkpoint checkpoints/simple_shapes/gw.pt --vae-checkpoint checkpoints/simple_shapes/vae.pt
[ "$DRY_RUN" = 1 ] || echo "done: $OUT/figures, $OUT/results (copy them over docs/ to replace the committed ones)"
