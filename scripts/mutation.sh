#!/usr/bin/env bash
# Mutation testing with mutmut (pip install -e ".[mutation]"): small changes are made to the code
# one at a time (a flipped sign, < for <=, a changed constant, a dropped call) and the tests
# that guard that code must fail for each. Prints, per target, the mutants killed / survived /
# not covered and the share killed, and writes them to docs/mutation.json.
#
#   ./scripts/mutation.sh                 # every target below
#   ./scripts/mutation.sh vgq             # one target
#   JOBS=2 ./scripts/mutation.sh vgq      # mutmut's parallel children (default: cores)
#
# Each target runs in a throw-away copy of the tracked files (mutmut writes mutants/ there), so
# the working tree is never touched. Not part of the default suite (minutes to tens of minutes).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PYTHON:-$ROOT/.venv/bin/python}
JOBS=${JOBS:-$(nproc)}
OUT=${OUT:-$ROOT/docs/mutation.json}

# target -> "source paths|tests" (paths relative to the repository root). Tests that need the
# session fixtures of a trained model (model_dir) are left out: mutmut reruns them per mutant.
declare -A TARGETS=(
  [vgq]="vgq/|tests/test_vgq_*.py tests/test_datagen_crops.py tests/test_datagen_storage.py tests/test_planning_collision.py"
  [service_grasps]="service/grasps.py|tests/test_service_units.py"
  [datagen_quality]="datagen/quality.py|tests/test_datagen_quality.py tests/test_datagen_quality_values.py"
)
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(vgq service_grasps datagen_quality)

"$PY" -c "import mutmut" 2>/dev/null || { echo "mutmut is not installed: pip install -e '.[mutation]'" >&2; exit 2; }
for name in "${names[@]}"; do
  [ -n "${TARGETS[$name]:-}" ] || { echo "unknown target: $name (one of: ${!TARGETS[*]})" >&2; exit 2; }
done

for name in "${names[@]}"; do
  IFS='|' read -r src tests <<<"${TARGETS[$name]}"
  tests=$(echo $tests)  # expand the globs
  work=$(mktemp -d "${TMPDIR:-/tmp}/vgq-mutation-$name.XXXXXX")
  trap 'rm -rf "$work"' EXIT
  git ls-files -z | xargs -0 -I{} cp --parents {} "$work"
  for f in $src $tests; do [ -e "$work/$f" ] || cp --parents "$f" "$work"; done  # uncommitted targets too
  # mutmut's settings ([tool.mutmut] in the copy's pyproject.toml; JSON lists are TOML arrays):
  # pytest runs the target's own tests only
  {
    echo
    echo "[tool.mutmut]"
    echo "source_paths = $("$PY" -c 'import json, sys; print(json.dumps(sys.argv[1:]))' $src)"
    echo "pytest_add_cli_args_test_selection = $("$PY" -c 'import json, sys; print(json.dumps(sys.argv[1:]))' $tests)"
    echo 'pytest_add_cli_args = ["-p", "no:cacheprovider"]'
    # the unmutated rest of the code too (every package), not the installed copy
    echo "also_copy = $("$PY" -c 'import json, sys; print(json.dumps(sys.argv[1:]))' examples/ models/ $(cd "$work" && ls -d */__init__.py | xargs -n1 dirname))"
  } >>"$work/pyproject.toml"
  echo "== $name: mutating $src, tests: $tests"
  (cd "$work" && "$PY" -m mutmut run --max-children "$JOBS" >"$work/run.log" 2>&1) \
    || { tail -30 "$work/run.log" >&2; exit 1; }
  (cd "$work" && "$PY" -m mutmut export-cicd-stats >/dev/null && cat mutants/mutmut-cicd-stats.json) >"$work/stats.json"
  (cd "$work" && "$PY" -m mutmut results 2>/dev/null) >"$work/survivors.txt" || true
  "$PY" - "$name" "$src" "$tests" "$work/stats.json" "$work/survivors.txt" "$OUT" <<'EOF'
import json, sys
from pathlib import Path

name, src, tests, stats, survivors, out = sys.argv[1:]
s = json.loads(Path(stats).read_text())
tried = s["total"] - s.get("skipped", 0)
killed = s["killed"] + s.get("timeout", 0) + s.get("segfault", 0)  # a hang or a crash is caught too
rows = [ln.strip().rsplit(": ", 1) for ln in Path(survivors).read_text().splitlines() if ": " in ln]
rec = {"source": src.split(), "tests": tests.split(), "mutants": tried, "killed": killed,
       "survived": s["survived"], "no_tests": s.get("no_tests", 0), "suspicious": s.get("suspicious", 0),
       "share_killed": round(killed / tried, 4) if tried else None,
       "not_killed": {name: status for name, status in rows}}
doc = json.loads(Path(out).read_text()) if Path(out).exists() else {}
doc[name] = rec
Path(out).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
print(f"{name}: {killed} of {tried} mutants killed ({100 * killed / max(tried, 1):.1f}%), "
      f"{s['survived']} survived, {s.get('no_tests', 0)} not reached by the tests")
EOF
  rm -rf "$work"
  trap - EXIT
done
