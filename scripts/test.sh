#!/usr/bin/env bash
# `make test`: the whole suite, as `cargo test --workspace --no-fail-fast` would run it, but with
# its test binaries run RELFUSION_TEST_JOBS (default 3) at a time.
#
# Why: cargo runs test binaries one after another, and most end-to-end binaries wait on servers,
# timeouts and child processes: on the 2-core machine they use about one core (map_localize 1.1
# cores over 119 s, service_hardening 0.9 over 117 s). Run side by side, they fill both cores.
# Heaviest first, so the pool finishes together. Fails when any binary fails; every binary runs.
set -euo pipefail
cd "$(dirname "$0")/.."

jobs_max="${RELFUSION_TEST_JOBS:-3}"
logs="${CARGO_TARGET_DIR:-target}/test-logs"
rm -rf "$logs" && mkdir -p "$logs"

# Everything built first, once, in one cargo call: the test binaries and the binaries the
# end-to-end tests spawn (relfusion_tests::bin_path builds with these same flags, so its build is
# then a no-op). These are the units of `cargo test --workspace --no-run` plus the `relfusion`
# binary; built after them, that binary compiled alone on one core for 30-97 s (issue 36).
cargo build --workspace --bins --tests

# The integration test targets of every workspace package (those whose required features are on).
# Read into a variable first: a failure inside `< <(...)` would go unnoticed and skip binaries.
metadata=$(cargo metadata --format-version 1 --no-deps)
mapfile -t targets < <(python3 -c '
import json, sys
for p in json.load(sys.stdin)["packages"]:
    for t in p["targets"]:
        if "test" in t["kind"] and not t.get("required-features"):
            print(t["name"])' <<< "$metadata")

# Longest first (measured 2026-12-03, docs/build-time.md); the rest in metadata order.
heavy=(--lib map_localize bench_accuracy_cli service_hardening client_stream service_soak
       service_zenoh prior_pydnet service_maps service_http)
# Alone, after the pool: service_overload calibrates its load on an idle machine (one session's
# rate, then four streams at twice it) and fails when other binaries share the cores.
alone=(service_overload)
queue=("${heavy[@]}")
for t in "${targets[@]}"; do
  [[ " ${heavy[*]} ${alone[*]} " == *" $t "* ]] || queue+=("$t")
done
queue+=(--bins --doc)

failed=()
declare -A running=()   # pid -> job
finish_one() {   # waits for any running job and prints its log
  local pid rc=0
  wait -n -p pid || rc=$?
  local job="${running[$pid]}"
  unset "running[$pid]"
  echo "===== $job: exit $rc, at $(( $(date +%s) - start )) s"
  cat "$logs/${job#--}.log" "$logs/${job#--}.time"
  [ "$rc" -eq 0 ] || failed+=("$job")
}
launch() {   # starts one job in the background: a test target's name, or a cargo flag
  local job="$1" args
  if [[ "$job" == --* ]]; then args=("$job"); else args=(--test "$job"); fi
  # bash's `time` adds the job's CPU (cargo, the test binary and what it spawned) to its log.
  # --no-fail-fast: `--lib` runs every crate's unit tests; without it one failure skipped the rest.
  { TIMEFORMAT="cpu of $job: %U s user, %S s sys, %R s wall"
    time cargo test --workspace --no-fail-fast "${args[@]}" > "$logs/${job#--}.log" 2>&1; } 2> "$logs/${job#--}.time" &
  running[$!]="$job"
}
start=$(date +%s)
for job in "${queue[@]}"; do
  while [ "${#running[@]}" -ge "$jobs_max" ]; do finish_one; done
  launch "$job"
done
while [ "${#running[@]}" -gt 0 ]; do finish_one; done
for job in "${alone[@]}"; do launch "$job"; finish_one; done

echo "===== $(( ${#queue[@]} + ${#alone[@]} )) test jobs in $(( $(date +%s) - start )) s"
if [ "${#failed[@]}" -gt 0 ]; then
  echo "FAILED: ${failed[*]}"
  exit 1
fi
