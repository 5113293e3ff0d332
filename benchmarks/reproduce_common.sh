# Sourced by benchmarks/reproduce_*.sh after they set OUT, DRY_RUN and RESUME. A new reproduction refuses
# an existing $OUT; RESUME=1 continues the one in $OUT instead. Defines step (run a command inside $OUT,
# or print it under DRY_RUN=1, with its output in logs/<name>.log) and train (the same for a training).
if [ "$DRY_RUN" != 1 ]; then
  if [ "$RESUME" = 1 ]; then
    if [ ! -d "$OUT/logs" ]; then echo "error: RESUME=1: $OUT holds no reproduction to continue" >&2; exit 2; fi
  elif [ -e "$OUT" ]; then
    echo "error: $OUT exists; choose another OUT=, or RESUME=1 to continue the reproduction in it" >&2
    exit 2
  fi
  mkdir -p "$OUT/logs"
fi

# attempt name command...: run it inside $OUT, output appended to logs/<name>.log after the command
# line; on success logs/<name>.done marks the step finished. Returns the command's exit status.
attempt() {
  local name=$1; shift
  echo "$*" >> "$OUT/logs/$name.log"
  (cd "$OUT" && "$@") >> "$OUT/logs/$name.log" 2>&1 && touch "$OUT/logs/$name.done"
}

# step name command...: runs once. A finished step is not run again under RESUME=1; a failed one is
# reported and the others go on.
step() {
  local name=$1; shift
  if [ "$DRY_RUN" = 1 ]; then echo "$*"; return 0; fi
  if [ -e "$OUT/logs/$name.done" ]; then echo "done before, not run again: $name"; return 0; fi
  attempt "$name" "$@" || echo "failed (exit $?): $* (see $OUT/logs/$name.log)"
}

# train name command...: a step whose script saves and takes --resume. Under RESUME=1 a training that
# started before and did not finish continues from its last save; one that stopped before its first save
# has nothing to continue and starts again (--overwrite drops the TensorBoard folder it began).
train() {
  local name=$1; shift
  if [ "$DRY_RUN" = 1 ] || [ ! -e "$OUT/logs/$name.log" ] || [ -e "$OUT/logs/$name.done" ]; then
    step "$name" "$@"
    return 0
  fi
  attempt "$name" "$@" --resume && return 0
  local rc=$?
  if tail -n 2 "$OUT/logs/$name.log" | grep -q "no checkpoint"; then
    step "$name" "$@" --overwrite
  else
    echo "failed (exit $rc): $* --resume (see $OUT/logs/$name.log)"
  fi
}
