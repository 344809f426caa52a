#!/usr/bin/env bash
# Soak: a graph run again and again on one recording for a while. While each run goes, five
# times a second, the resident set and open file descriptors of each of its processes are sampled;
# after each, the shared-memory entries (/dev/shm, /tmp/iceoryx2) and run folders (/tmp/gprflow-*) are
# counted. It fails when a run fails, when two runs disagree on any message count (a message
# lost; but for what a feedback input read, which ends with the consumer), when anything is
# left behind after a run, or when a process's peak RSS grows from the first run to the last or
# its open files from the first half of the runs to the second.
#
# usage: tools/bench/soak.sh [MINUTES (30)] [GRAPH (localize)] [RECORDING (the graph's own)]
#   GPRFLOW=path/to/gprflow picks the binary (default: a release build, made here).
#   CI runs a short one: GPRFLOW=target/debug/gprflow tools/bench/soak.sh 0.5 odometry
# Results: out/soak/{run-N.json, samples.tsv, summary.txt}.
set -euo pipefail
cd "$(dirname "$0")/../.."
minutes=${1:-30}
graph=${2:-localize}
recording=${3:-}
out=out/soak
if [ -z "${GPRFLOW:-}" ]; then
    cargo build -q --release -p gprflow-cli
    GPRFLOW=${CARGO_TARGET_DIR:-target}/release/gprflow
fi
rm -rf "$out"
mkdir -p "$out"
sets=()
if [ -n "$recording" ]; then sets=(--set "recording=$recording"); fi

# a run's iceoryx2 resources are named gf{run id}_... in /dev/shm and under /tmp/iceoryx2
count_shm() { find /dev/shm /tmp/iceoryx2 -maxdepth 4 -name 'gf*' 2> /dev/null | wc -l || true; }
# pids whose parent is $1 (from /proc, without procps)
children() { awk -v p="$1" '$4 == p { print $1 }' /proc/[0-9]*/stat 2> /dev/null || true; }
count_runs() { find /tmp -maxdepth 1 -name 'gprflow-*' 2> /dev/null | wc -l || true; }
shm0=$(count_shm)
runs0=$(count_runs)
# the plan says which inputs are feedback (an estimate read back upstream): the consumer ends
# with its primary inputs, before the producer, so how many it read is a matter of timing
"$GPRFLOW" launch "graphs/$graph.yaml" "${sets[@]}" --dry-run > "$out/plan.json"
printf 'run\tnode\tt_s\trss_kib\tfds\n' > "$out/samples.tsv"
: > "$out/leftovers.tsv"
end=$(python3 -c "import time; print(time.time() + 60 * float('$minutes'))")
n=0
while :; do
    n=$((n + 1))
    "$GPRFLOW" launch "graphs/$graph.yaml" "${sets[@]}" --log warn --report "$out/run-$n.json" \
        2> "$out/run-$n.log" &
    launcher=$!
    start=$(date +%s.%N)
    while kill -0 "$launcher" 2> /dev/null; do
        # the stage processes of this launcher: `gprflow stage KIND --spec /tmp/gprflow-ID/NODE.json`
        for pid in $(children "$launcher"); do
            # (a process may end between the listing and the reads)
            spec=$( (tr '\0' ' ' < "/proc/$pid/cmdline") 2> /dev/null | grep -o '[^ /]*\.json' || true)
            rss=$(awk '/^VmRSS/ {print $2}' "/proc/$pid/status" 2> /dev/null || true)
            fds=$(find "/proc/$pid/fd" -mindepth 1 -maxdepth 1 2> /dev/null | wc -l || true)
            now=$(date +%s.%N)
            # a live process holds at least its standard streams: 0 is a read that failed (the
            # process starting or ending), not a count
            if [ -n "$spec" ] && [ -n "$rss" ] && [ "${fds:-0}" -gt 0 ]; then
                printf '%s\t%s\t%.1f\t%s\t%s\n' "$n" "${spec%.json}" "$(awk -v a="$now" -v b="$start" 'BEGIN { print a - b }')" "$rss" "$fds" \
                    >> "$out/samples.tsv"
            fi
        done
        # runs of the odometry graph last under a second: sampled once a second, most were not
        # sampled at all and the few that were could be caught starting (10 open files, 32 once
        # its bus is open), which read as a leak between the halves
        sleep 0.2
    done
    wait "$launcher" || { echo "run $n failed: see $out/run-$n.log" >&2; exit 1; }
    printf '%s\t%s\t%s\n' "$n" "$(( $(count_shm) - shm0 ))" "$(( $(count_runs) - runs0 ))" >> "$out/leftovers.tsv"
    if python3 -c "import sys, time; sys.exit(0 if time.time() >= $end else 1)"; then
        break
    fi
done

python3 - "$out" "$n" <<'PY' | tee "$out/summary.txt"
import csv, json, sys
out, runs = sys.argv[1], int(sys.argv[2])
problems = []
reports = [json.load(open(f"{out}/run-{i}.json")) for i in range(1, runs + 1)]
feedback = {(p["node"], i["topic"]) for p in json.load(open(f"{out}/plan.json"))
            for i in p["inputs"] if i["feedback_delay_ns"] is not None}
def counts(r):
    return {n["node"]: ([c for c in n["report"]["received"] if (n["node"], c[0]) not in feedback],
                        n["report"]["sent"]) for n in r["nodes"] if n["report"]}
first = counts(reports[0])
for i, r in enumerate(reports, 1):
    if not r["succeeded"]:
        problems.append(f"run {i} did not succeed")
    if counts(r) != first:
        problems.append(f"run {i}: message counts differ from run 1")
for row in csv.reader(open(f"{out}/leftovers.tsv"), delimiter="\t"):
    if row[1] != "0" or row[2] != "0":
        problems.append(f"run {row[0]}: {row[1]} /dev/shm entries and {row[2]} run folders left behind")
rss = lambda r: {n["node"]: n["report"]["peak_rss_bytes"] for n in r["nodes"] if n["report"]}
a, b = rss(reports[0]), rss(reports[-1])
for node in a:
    grew = (b[node] - a[node]) / 2**20
    if grew > 4:
        problems.append(f"{node}: peak RSS grew {grew:.1f} MiB from run 1 to run {runs}")
fds = {}
for row in csv.DictReader(open(f"{out}/samples.tsv"), delimiter="\t"):
    fds.setdefault(row["node"], {}).setdefault(int(row["run"]), []).append(int(row["fds"]))
# A run of a second or two is sampled once or twice, maybe only while a process starts (its
# bus not open yet), so one run's peak says little: the peak over the first half of the sampled
# runs against the peak over the second half (a leak raises the second).
for node, per_run in fds.items():
    peaks = [max(v) for _, v in sorted(per_run.items())]
    if len(peaks) > 1:
        half = len(peaks) // 2
        early, late = max(peaks[:half]), max(peaks[half:])
        if late > early + 2:
            problems.append(f"{node}: open files {early} at most in the first {half} sampled runs, "
                            f"{late} in the last {len(peaks) - half}")
wall = sum(r["wall_s"] for r in reports)
print(f"{runs} runs of {reports[0]['graph']} in {wall:.0f} s of wall time; "
      f"{sum(len(v) for p in fds.values() for v in p.values())} samples")
for node in a:
    print(f"  {node}: peak RSS {a[node] / 2**20:.1f} -> {b[node] / 2**20:.1f} MiB, "
          f"sent {sum(c for _, c in first[node][1])} per run")
print("\n".join(problems) if problems else "nothing grew, nothing was left behind, no message lost")
sys.exit(1 if problems else 0)
PY
