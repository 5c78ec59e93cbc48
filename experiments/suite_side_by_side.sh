#!/usr/bin/env bash
# Test files' time at two revisions, side by side on one machine: each revision checked out in its own git
# worktree, the files run cold (an empty JAX persistent cache in a fresh $TMPDIR) on two pytest-xdist workers, as
# `make test` runs them, the revisions alternating for ROUNDS rounds. Prints one line per run:
# "round revision wall_seconds pytest's summary". Uses this checkout's .venv (run `make venv` first).
#
#   experiments/suite_side_by_side.sh OLD_REV NEW_REV ROUNDS tests/test_pulse.py tests/test_mc.py ...
#
# The twenty-eighth session's run (2026-12-01, 528d146 against 7a43c6c, one round, ten files):
# docs/results/suite_side_by_side_2026-12-01.txt.
set -euo pipefail
if [ $# -lt 4 ]; then
  echo "usage: $0 OLD_REV NEW_REV ROUNDS TEST_FILE..." >&2
  exit 2
fi
old=$1 new=$2 rounds=$3
shift 3
root=$(cd "$(dirname "$0")/.." && pwd)
py="$root/.venv/bin/python"
[ -x "$py" ] || { echo "error: $py missing (run make venv)" >&2; exit 2; }
case "$rounds" in ''|*[!0-9]*|0) echo "error: ROUNDS must be a positive integer" >&2; exit 2;; esac
work=$(mktemp -d)
trap 'git -C "$root" worktree remove --force "$work/old" >/dev/null 2>&1 || true;
      git -C "$root" worktree remove --force "$work/new" >/dev/null 2>&1 || true; rm -rf "$work"' EXIT
git -C "$root" worktree add -q --detach "$work/old" "$old"
git -C "$root" worktree add -q --detach "$work/new" "$new"
for ((r = 1; r <= rounds; r++)); do
  order="old new"
  [ $((r % 2)) -eq 0 ] && order="new old"
  for v in $order; do
    rm -rf "$work/tmp" && mkdir -p "$work/tmp"
    start=$(date +%s.%N)
    (cd "$work/$v" && TMPDIR="$work/tmp" PYTHONPATH="$work/$v" "$py" -m pytest -q -n 2 --dist loadfile \
      -p no:cacheprovider "$@" > "$work/log" 2>&1) || true
    end=$(date +%s.%N)
    rev=$old; [ "$v" = new ] && rev=$new
    echo "$r $rev $(echo "$end - $start" | bc) $(grep -Eo '[0-9]+ (passed|failed)[^=]*' "$work/log" | tail -1)"
  done
done
