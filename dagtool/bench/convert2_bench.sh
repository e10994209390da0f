#!/usr/bin/env bash
# The 2.0 convert against the 1.0 convert of the same build (issue 42's target: a 2.0
# convert of dragon.obj at depth 14 takes at most 1.3x the 1.0 build's time), for two
# builds of dagtool, interleaved, printed as Markdown tables.
#
#   dagtool/bench/convert2_bench.sh BASE_DAGTOOL NEW_DAGTOOL [ROUNDS [DEPTH [MESH]]]
#
# Per round: base --format-version 1, base 2, new 1, new 2 (`dagtool convert MESH --depth
# DEPTH -q --force`), each under /usr/bin/time -v: wall, user + sys CPU, peak RSS. Prints
# every run, then per build the medians, the median of the per-round 2.0 / 1.0 wall ratios
# (the target), and the median per-round 2.0-minus-1.0 CPU seconds (the 2.0 encoding's own
# CPU, the steadier figure on a loaded machine). Checks that base and new write the same
# bytes in each version.
#
# Defaults: ROUNDS 3, DEPTH 14, MESH dragon.obj in MESHES (default ../shared/meshes beside
# the repository). OUT: scratch folder (default a temporary folder, removed afterwards).
set -euo pipefail
if [ $# -lt 2 ]; then
    sed -n '2,15p' "$0" >&2
    exit 2
fi
cd "$(dirname "$0")/../.."
ROOT=$(pwd)
BASE=$1
NEW=$2
ROUNDS=${3:-3}
DEPTH=${4:-14}
MESHES=${MESHES:-$ROOT/../shared/meshes}
MESH=${5:-$MESHES/dragon.obj}
SCRATCH=${OUT:-$(mktemp -d)}
mkdir -p "$SCRATCH"
[ -z "${OUT:-}" ] && trap 'rm -rf "$SCRATCH"' EXIT

median() { sort -g | awk '{ v[NR] = $1 } END { if (NR % 2) print v[(NR + 1) / 2]; else print (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }
load() { cut -d' ' -f1-3 /proc/loadavg; }

# Runs a command under /usr/bin/time -v; prints "wall_s cpu_s maxrss_kb" (cpu: user + sys).
measure() {
    local log=$SCRATCH/time.log
    /usr/bin/time -v "$@" >/dev/null 2>"$log"
    awk -F': ' '
        /Elapsed \(wall clock\)/ { n = split($2, p, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + p[i]; wall = s }
        /User time/ { cpu += $2 }
        /System time/ { cpu += $2 }
        /Maximum resident set size/ { rss = $2 }
        END { printf "%.2f %.2f %d\n", wall, cpu, rss }' "$log"
}

echo "### $(basename "$MESH") at depth $DEPTH: 2.0 / 1.0 ($ROUNDS rounds, interleaved; $(nproc) cores; load average before $(load))"
echo
echo "| round | build | 1.0 wall / CPU s | 2.0 wall / CPU s | 2.0 / 1.0 wall | 2.0 − 1.0 CPU s | peak RSS 1.0 / 2.0 MB | load |"
echo "|---:|---|---:|---:|---:|---:|---:|---|"
for i in $(seq "$ROUNDS"); do
    for build in base new; do
        bin=$BASE
        [ "$build" = new ] && bin=$NEW
        read -r w1 c1 r1 < <(measure "$bin" convert "$MESH" -o "$SCRATCH/$build-1.vdag" --depth "$DEPTH" -q --force --format-version 1)
        read -r w2 c2 r2 < <(measure "$bin" convert "$MESH" -o "$SCRATCH/$build-2.vdag" --depth "$DEPTH" -q --force --format-version 2)
        ratio=$(awk -v a="$w2" -v b="$w1" 'BEGIN { printf "%.3f", a / b }')
        extra=$(awk -v a="$c2" -v b="$c1" 'BEGIN { printf "%.2f", a - b }')
        echo "$w1 $c1 $r1 $w2 $c2 $r2 $ratio $extra" >>"$SCRATCH/$build"
        echo "| $i | $build | $w1 / $c1 | $w2 / $c2 | $ratio | $extra | $((r1 / 1024)) / $((r2 / 1024)) | $(load) |"
    done
    for v in 1 2; do
        cmp -s "$SCRATCH/base-$v.vdag" "$SCRATCH/new-$v.vdag" || { echo "base and new differ in version $v" >&2; exit 1; }
    done
done
echo
echo "Medians (base and new write the same bytes in both versions):"
echo
echo "| build | 1.0 wall / CPU s | 2.0 wall / CPU s | 2.0 / 1.0 wall (median of rounds) | 2.0 − 1.0 CPU s (median of rounds) | peak RSS 1.0 / 2.0 MB |"
echo "|---|---:|---:|---:|---:|---:|"
for build in base new; do
    f=$SCRATCH/$build
    col() { cut -d' ' -f"$1" "$f" | median; }
    echo "| $build | $(col 1) / $(col 2) | $(col 4) / $(col 5) | $(col 7) | $(col 8) | $(( $(col 3 | cut -d. -f1) / 1024 )) / $(( $(col 6 | cut -d. -f1) / 1024 )) |"
done
echo
echo "load average after: $(load)"
