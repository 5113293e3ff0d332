# Sourced by benchmarks/reproduce_*.sh after they set OUT and DRY_RUN: refuse an existing $OUT, make its
# logs/ folder, and define step, which runs a command inside $OUT (or prints it under DRY_RUN=1) with its
# output in logs/<name>.log.
if [ "$DRY_RUN" != 1 ]; then
  if [ -e "$OUT" ]; then echo "error: $OUT exists; choose another OUT=" >&2; exit 2; fi
  mkdir -p "$OUT/logs"
fi

step() {
  local name=$1; shift
  if [ "$DRY_RUN" = 1 ]; then echo "$*"; return 0; fi
  echo "$*" > "$OUT/logs/$name.log"
  (cd "$OUT" && "$@") >> "$OUT/logs/$name.log" 2>&1 || echo "failed (exit $?): $* (see $OUT/logs/$name.log)"
}
