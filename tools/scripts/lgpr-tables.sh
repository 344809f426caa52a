#!/usr/bin/env bash
# The LGPR tables (seed 001 Tables IV-V, Figs. 15, 17, 18, 19; tables in docs/results.md): for each
# highway world, the mapping pass into a map store (graphs/lgpr-map.yaml), every tracking
# pass (16-97 km/h, lateral offsets, wetter soil) through graphs/lgpr-fuse.yaml against it
# (the tracker's map fixes and the estimator fusing them), and `gprflow lgpr-eval` over both. highway.yaml is the world the tracker's settings were
# chosen on; highway_b.yaml is held out. Simulated recordings are kept and reused.
# Then a two-lane map: the world's second mapping pass (map_lane2, one lane over) aligned to the
# map (graphs/lgpr-map-align.yaml) and joined to it (gprflow lgpr-merge), and every tracking pass
# tracked against the two lanes (graphs/lgpr-track.yaml).
# Results: out/lgpr-tables/WORLD/{table.md,table-overlapping.md,table-fused.md,table-two-lanes.md,
# track.log,fig/}. About 10 minutes a world (plus 5 to simulate it the first time).
#
# usage: tools/scripts/lgpr-tables.sh [WORLD...]   (default: highway highway_b)
set -euo pipefail
cd "$(dirname "$0")/../.."
worlds=("$@")
[[ ${#worlds[@]} -gt 0 ]] || worlds=(highway highway_b)
cargo build -q -p gprflow-cli
g=${CARGO_TARGET_DIR:-target}/debug/gprflow
runs=(track_16 track_48 track_64 track_80 track_97 track_97_offset)
for w in "${worlds[@]}"; do
    sc=tools/sim/scenarios/$w.yaml
    out=out/lgpr-tables/$w
    mkdir -p "$out"
    [[ -f $out/map.mcap ]] || $g sim "$sc" -o "$out/map.mcap" --run map >/dev/null
    rm -rf "$out/map.lgprmap"
    $g launch graphs/lgpr-map.yaml --set recording="$out/map.mcap" --set map="$out/map.lgprmap" 2>&1 |
        grep "map written" | sed 's/.*INFO //' > "$out/track.log"
    fixes=()
    for r in "${runs[@]}"; do
        [[ -f $out/$r.mcap ]] || $g sim "$sc" -o "$out/$r.mcap" --run "$r" >/dev/null
        $g launch graphs/lgpr-fuse.yaml --set recording="$out/$r.mcap" --set map="$out/map.lgprmap" \
            --record "$out/$r-fixes.mcap" 2>&1 | grep "lgpr_track: done" | sed "s/.*done/$r:/" >> "$out/track.log"
        fixes+=("$out/$r-fixes.mcap")
    done
    echo "== $w"
    cat "$out/track.log"
    $g lgpr-eval "${fixes[@]}" --baseline "$out/map.mcap" --format markdown --plot-dir "$out/fig" | tee "$out/table.md"
    # the same without the pass beyond the overlap limit (1.3 m: one channel over the map)
    $g lgpr-eval "${fixes[@]:0:5}" --baseline "$out/map.mcap" --format markdown | tee "$out/table-overlapping.md"
    # the estimator's fusion of the same fixes with the IMU and the wheel
    $g lgpr-eval "${fixes[@]}" --baseline "$out/map.mcap" --topic /estimate/state --format markdown | tee "$out/table-fused.md"
    # the second lane, aligned to the map and joined to it; every pass against both lanes
    [[ -f $out/map_lane2.mcap ]] || $g sim "$sc" -o "$out/map_lane2.mcap" --run map_lane2 >/dev/null
    rm -rf "$out/lane2.lgprmap" "$out/two-lanes.lgprmap"
    $g launch graphs/lgpr-map-align.yaml --set recording="$out/map_lane2.mcap" --set map="$out/map.lgprmap" \
        --set aligned="$out/lane2.lgprmap" 2>&1 | grep "placed by" | sed 's/.*INFO //' >> "$out/track.log"
    $g lgpr-merge "$out/map.lgprmap" "$out/lane2.lgprmap" --into "$out/two-lanes.lgprmap" >> "$out/track.log"
    fixes=()
    for r in "${runs[@]}"; do
        $g launch graphs/lgpr-track.yaml --set recording="$out/$r.mcap" --set map="$out/two-lanes.lgprmap" \
            --record "$out/$r-two-lanes.mcap" 2>&1 | grep "lgpr_track: done" | sed "s/.*done/$r (two lanes):/" >> "$out/track.log"
        fixes+=("$out/$r-two-lanes.mcap")
    done
    echo "== $w, two lanes"
    $g lgpr-eval "${fixes[@]}" --baseline "$out/map.mcap" --max-offset-m 2 --format markdown | tee "$out/table-two-lanes.md"
done
