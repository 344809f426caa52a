#!/usr/bin/env bash
# Which part of a `by_hand` run keeps the learned model from registering: the world's by_hand
# run simulated again (one repeat) with one of its effects taken out or weakened at a time
# (wander off the line, drying soil, uneven ground contact, the rebar grid), each localised
# with the learned model and the oracle (graphs/localize.yaml, oracle association, as
# tools/experiments/repeats.yaml), and summarised: learned registrations, their error, and the ATE.
# The scenario copies live in the output folder; the committed scenarios are not touched.
#
#   tools/scripts/by-hand-factors.sh                       # parking_garage, repeat 4
#   tools/scripts/by-hand-factors.sh basement 2            # another world and repeat
#   GPRFLOW=target/debug/gprflow tools/scripts/by-hand-factors.sh
# Output: out/by-hand-factors/<world>-<repeat>/ (recordings, logs, eval JSON) and the table on
# stdout. About 6 minutes for the garage on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/../.."
source tools/scripts/lib/worlds.sh
world=${1:-parking_garage}
k=${2:-4}
scenario=tools/sim/scenarios/$world.yaml
[[ -f $scenario ]] || { echo "by-hand-factors.sh: no scenario $scenario" >&2; exit 2; }
[[ $k =~ ^[1-9][0-9]*$ ]] || { echo "by-hand-factors.sh: the repeat must be a count, got $k" >&2; exit 2; }
choose_gprflow
out=out/by-hand-factors/$world-$k
mkdir -p "$out"

# The variants' scenario files: edits inside the by_hand run's block (and the world's rebar
# line); a variant whose edit changes nothing (no rebar in this world, say) is left out.
python3 - "$scenario" "$out" <<'EOF'
import pathlib, re, sys
scenario, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
text = scenario.read_text()
lines = text.splitlines(keepends=True)
start = next((i for i, l in enumerate(lines) if l.strip() == "- name: by_hand"), None)
if start is None:
    sys.exit(f"{scenario}: no run named by_hand")
end = next((i for i in range(start + 1, len(lines)) if lines[i].lstrip().startswith("- name:")), len(lines))

def in_run(edit):
    block = "".join(lines[start:end])
    return "".join(lines[:start]) + edit(block) + "".join(lines[end:])

def drop(key):
    return lambda b: re.sub(rf"(?m)^\s*{key}:.*\n", "", b)

def wander(sigma):
    return lambda b: re.sub(r"(wander: \{ sigma_m: )[0-9.]+", rf"\g<1>{sigma}", b)

variants = {
    "as_is": text,
    "no_wander": in_run(drop("wander")),
    "wander_0.04": in_run(wander(0.04)),
    "wander_0.02": in_run(wander(0.02)),
    "no_drying": in_run(drop("soil_moisture_per_min")),
    "no_ground_contact": in_run(drop("ground_contact")),
    "no_rebar": re.sub(r"(?m)^  rebar:.*\n", "", text),
}
names = []
for name, t in variants.items():
    if name != "as_is" and t == text:
        continue
    (out / f"{name}.yaml").write_text(t)
    names.append(name)
(out / "variants.txt").write_text("\n".join(names) + "\n")
EOF

while read -r v; do
    rec=$out/$v.mcap
    [[ -f $rec ]] || $g sim "$out/$v.yaml" -o "$rec" --run by_hand --repeat "$k" > /dev/null
    for m in learned oracle; do
        localise "$rec" "$m" "$out/$v-$m"
        rm -f "$out/$v-$m.mcap"
    done
    echo "$v done" >&2
done < "$out/variants.txt"

python3 - "$out" "$world" "$k" <<'EOF'
import json, pathlib, sys
out, world, k = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3]
print(f"{world} by_hand, repeat {k}: learned model and oracle (oracle association); "
      "ATE in m, registration error in cm")
print()
print("| variant | learned registrations | oracle registrations | learned registration RMSE | learned ATE | oracle ATE | learned / oracle |")
print("|---|---|---|---|---|---|---|")
for v in (out / "variants.txt").read_text().split():
    r = {m: json.loads((out / f"{v}-{m}.json").read_text()) for m in ("learned", "oracle")}
    reg = {m: (r[m].get("registration") or {}).get("along_track") for m in r}
    count = {m: reg[m]["count"] if reg[m] else 0 for m in r}
    rmse = f"{100 * reg['learned']['rmse']:.2f}" if reg["learned"] else "-"
    ate = {m: r[m]["ate"]["rmse"] for m in r}
    print(f"| {v} | {count['learned']} | {count['oracle']} | {rmse} | {ate['learned']:.3f} | "
          f"{ate['oracle']:.3f} | {ate['learned'] / ate['oracle']:.2f} |")
EOF
