#!/usr/bin/env bash
# Benchmarks of `dagtool convert` (release build), printed as Markdown tables.
#
#   dagtool/bench/convert_bench.sh [what...]      what: dragon14 dragon16 solid14 ooc14 ooc16
#                                                 vdb sizes (default: all)
#
# Environment: MESHES (default ../shared/meshes beside the repository), RUNS (default 3),
# OUT (scratch folder, default a temporary folder, removed afterwards), CARGO_TARGET_DIR.
#
# - dragon14: dragon.obj at depth 14, RUNS runs: wall time, user CPU time, peak RSS.
# - dragon16: dragon.obj at depth 16, once: wall time, peak RSS.
# - solid14:  dragon.obj at depth 14 with --solid, once: wall time, peak RSS.
# - ooc14:    dragon.obj at depth 14 in memory and under --memory-limit LIMITS14 (default
#             "1G 512M 256M"), RUNS runs each, interleaved: medians of wall time, user CPU and peak
#             RSS, runs spilled, bytes written to temporary files; every file validates and is
#             byte-identical to the in-memory one, with the same `dagtool info --json` levels.
# - ooc16:    dragon.obj at depth 16 in memory and under --memory-limit LIMITS16 (default
#             "2G 1G"), once each: the same figures; every file validates and is identical.
# - vdb:      OpenVDB's vdb_tool (mesh to level set, 2048^3, narrow band of 1 voxel) against
#             `dagtool convert` at depth 11 (2048^3), RUNS runs each, medians of wall time and
#             peak RSS (/usr/bin/time -v), and the output sizes.
# - sizes:    every mesh at depths 10, 12, 14: .vdag bytes, the same DAG with 32-bit pointers
#             (classic SVDAG layout) and as an SVO, and the pointer-entropy bound (headers +
#             leaves + the zero-order entropy of the pointers), all from dagtool info --json.
#
# Timings on a shared machine vary with its load; the load average is printed with each table.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$(pwd)
MESHES=${MESHES:-$ROOT/../shared/meshes}
RUNS=${RUNS:-3}
WHAT=${*:-dragon14 dragon16 solid14 ooc14 ooc16 vdb sizes}
LIMITS14=${LIMITS14:-1G 512M 256M}
LIMITS16=${LIMITS16:-2G 1G}
if [ ! -d "$MESHES" ]; then
    echo "meshes not found at $MESHES (set MESHES)" >&2
    exit 1
fi
cargo build --release -p dagtool >&2
TARGET=${CARGO_TARGET_DIR:-$ROOT/target}
DAGTOOL=$TARGET/release/dagtool
SCRATCH=${OUT:-$(mktemp -d)}
mkdir -p "$SCRATCH"
[ -z "${OUT:-}" ] && trap 'rm -rf "$SCRATCH"' EXIT

median() { sort -g | awk '{ v[NR] = $1 } END { if (NR % 2) print v[(NR + 1) / 2]; else print (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }

# Runs a command under /usr/bin/time -v; prints "wall_s user_s maxrss_kb". Its standard
# output is kept in $SCRATCH/stdout.log.
measure() {
    local log=$SCRATCH/time.log
    /usr/bin/time -v "$@" >"$SCRATCH/stdout.log" 2>"$log"
    local wall user rss
    wall=$(awk -F': ' '/Elapsed \(wall clock\)/ { n = split($2, p, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + p[i]; print s }' "$log")
    user=$(awk -F': ' '/User time/ { print $2 }' "$log")
    rss=$(awk -F': ' '/Maximum resident set size/ { print $2 }' "$log")
    echo "$wall $user $rss"
}

load() { cut -d' ' -f1-3 /proc/loadavg; }

# From the last conversion's summary: "runs temp_bytes".
spilled() {
    local runs temp
    runs=$(sed -n 's/.*spilled \([0-9]*\) run.*/\1/p' "$SCRATCH/stdout.log")
    temp=$(sed -n 's/.*(\([0-9]*\) bytes) written to unnamed temporary files.*/\1/p' "$SCRATCH/stdout.log")
    echo "${runs:-0} ${temp:-0}"
}

# Asserts that FILE validates and holds the same bytes and `info --json` levels as REFERENCE.
same_as() {
    "$DAGTOOL" validate "$1" >/dev/null || { echo "$1 is INVALID" >&2; exit 1; }
    cmp -s "$1" "$2" || { echo "$1 differs from $2" >&2; exit 1; }
    "$DAGTOOL" info --json "$1" >"$SCRATCH/a.json"
    "$DAGTOOL" info --json "$2" >"$SCRATCH/b.json"
    python3 - "$SCRATCH/a.json" "$SCRATCH/b.json" <<'EOF'
import json, sys
a, b = (json.load(open(p))["levels"] for p in sys.argv[1:])
assert a == b, "level tables differ"
EOF
}

# Out-of-core table: dragon.obj at DEPTH, in memory and under each limit, N runs each.
ooc() {
    local depth=$1 n=$2; shift 2
    local limits=("" "$@")
    local ref=$SCRATCH/ooc-ref.vdag
    for i in $(seq "$n"); do
        for l in "${limits[@]}"; do
            local tag=${l:-in-memory}
            local args=()
            [ -n "$l" ] && args=(--memory-limit "$l")
            local out=$SCRATCH/ooc-$tag.vdag
            read -r wall user rss < <(measure "$DAGTOOL" convert "$MESHES/dragon.obj" -o "$out" --depth "$depth" --force "${args[@]}")
            read -r runs temp < <(spilled)
            echo "$wall $user $rss $runs $temp $(stat -c %s "$out")" >>"$SCRATCH/ooc-$tag"
            if [ -z "$l" ]; then
                "$DAGTOOL" validate "$out" >/dev/null || { echo "$out is INVALID" >&2; exit 1; }
                mv "$out" "$ref"
            else
                same_as "$out" "$ref"
                rm -f "$out"
            fi
        done
    done
    echo "| --memory-limit | wall (s) | user CPU (s) | peak RSS (MiB) | runs spilled | temp bytes written | file bytes |"
    echo "|---|---:|---:|---:|---:|---:|---:|"
    for l in "${limits[@]}"; do
        local f=$SCRATCH/ooc-${l:-in-memory}
        echo "| ${l:-(default: in memory)} | $(cut -d' ' -f1 "$f" | median) | $(cut -d' ' -f2 "$f" | median) | $(( $(cut -d' ' -f3 "$f" | median | cut -d. -f1) / 1024 )) | $(cut -d' ' -f4 "$f" | median) | $(cut -d' ' -f5 "$f" | median) | $(cut -d' ' -f6 "$f" | head -1) |"
    done
    echo
    echo "every run (wall user rss_kb runs temp_bytes file_bytes):"
    for l in "${limits[@]}"; do
        echo "- ${l:-in memory}: $(tr '\n' ';' <"$SCRATCH/ooc-${l:-in-memory}")"
    done
    echo
    echo "every file valid and byte-identical to the in-memory one, same \`dagtool info --json\` levels"
    rm -f "$ref" "$SCRATCH"/ooc-*
}

for what in $WHAT; do
case $what in
dragon14)
    echo "### dragon.obj at depth 14 ($RUNS runs; load average $(load); $(nproc) cores)"
    echo
    echo '`'"dagtool convert dragon.obj -o dragon14.vdag --depth 14 --force -q"'`'
    echo
    echo "| run | wall (s) | user CPU (s) | peak RSS (MiB) |"
    echo "|---|---|---|---|"
    : >"$SCRATCH/d14"
    for i in $(seq "$RUNS"); do
        read -r wall user rss < <(measure "$DAGTOOL" convert "$MESHES/dragon.obj" -o "$SCRATCH/dragon14.vdag" --depth 14 --force -q)
        echo "$wall $user $rss" >>"$SCRATCH/d14"
        echo "| $i | $wall | $user | $((rss / 1024)) |"
    done
    echo "| median | $(cut -d' ' -f1 "$SCRATCH/d14" | median) | $(cut -d' ' -f2 "$SCRATCH/d14" | median) | $(( $(cut -d' ' -f3 "$SCRATCH/d14" | median | cut -d. -f1) / 1024 )) |"
    "$DAGTOOL" validate "$SCRATCH/dragon14.vdag" >/dev/null && echo && echo "output: $(stat -c %s "$SCRATCH/dragon14.vdag") bytes, valid"
    rm -f "$SCRATCH/dragon14.vdag"
    echo
    ;;
dragon16)
    echo "### dragon.obj at depth 16 (once; load average $(load))"
    echo
    read -r wall user rss < <(measure "$DAGTOOL" convert "$MESHES/dragon.obj" -o "$SCRATCH/dragon16.vdag" --depth 16 --force -q)
    echo "| wall (s) | user CPU (s) | peak RSS (MiB) | file bytes |"
    echo "|---|---|---|---|"
    echo "| $wall | $user | $((rss / 1024)) | $(stat -c %s "$SCRATCH/dragon16.vdag") |"
    "$DAGTOOL" validate "$SCRATCH/dragon16.vdag" >/dev/null && echo && echo "output valid"
    rm -f "$SCRATCH/dragon16.vdag"
    echo
    ;;
solid14)
    echo "### dragon.obj at depth 14 with --solid (once; load average $(load))"
    echo
    read -r wall user rss < <(measure "$DAGTOOL" convert "$MESHES/dragon.obj" -o "$SCRATCH/solid14.vdag" --depth 14 --solid --force -q)
    echo "| wall (s) | user CPU (s) | peak RSS (MiB) | file bytes |"
    echo "|---|---|---|---|"
    echo "| $wall | $user | $((rss / 1024)) | $(stat -c %s "$SCRATCH/solid14.vdag") |"
    "$DAGTOOL" validate "$SCRATCH/solid14.vdag" >/dev/null && echo && echo "output valid"
    rm -f "$SCRATCH/solid14.vdag"
    echo
    ;;
ooc14)
    echo "### dragon.obj at depth 14, in memory and out of core ($RUNS runs each; load average $(load); $(nproc) cores)"
    echo
    echo '`'"dagtool convert dragon.obj -o d14.vdag --depth 14 --force [--memory-limit L]"'`'
    echo
    # shellcheck disable=SC2086
    ooc 14 "$RUNS" $LIMITS14
    echo "load average after: $(load)"
    echo
    ;;
ooc16)
    echo "### dragon.obj at depth 16, in memory and out of core (once each; load average $(load); $(nproc) cores)"
    echo
    echo '`'"dagtool convert dragon.obj -o d16.vdag --depth 16 --force [--memory-limit L]"'`'
    echo
    # shellcheck disable=SC2086
    ooc 16 1 $LIMITS16
    echo "load average after: $(load)"
    echo
    ;;
vdb)
    if ! command -v vdb_tool >/dev/null; then
        echo "vdb_tool not installed: skipping the OpenVDB comparison"
        continue
    fi
    echo "### OpenVDB vdb_tool vs dagtool at 2048^3 (dragon.obj, $RUNS runs each, medians; load average $(load))"
    echo
    echo '- `vdb_tool -read dragon.obj -mesh2ls dim=2048 width=1 -write out.vdb`'
    echo '- `dagtool convert dragon.obj -o out.vdag --depth 11 --force -q`'
    echo
    : >"$SCRATCH/vdb"
    : >"$SCRATCH/dag"
    for i in $(seq "$RUNS"); do
        rm -f "$SCRATCH/out.vdb"
        measure vdb_tool -read "$MESHES/dragon.obj" -mesh2ls dim=2048 width=1 -write "$SCRATCH/out.vdb" >>"$SCRATCH/vdb"
        measure "$DAGTOOL" convert "$MESHES/dragon.obj" -o "$SCRATCH/out.vdag" --depth 11 --force -q >>"$SCRATCH/dag"
    done
    echo "| tool | wall (s) | user CPU (s) | peak RSS (MiB) | file bytes |"
    echo "|---|---|---|---|---|"
    for t in vdb dag; do
        f=$SCRATCH/$t
        file=$SCRATCH/out.$([ $t = vdb ] && echo vdb || echo vdag)
        name=$([ $t = vdb ] && echo "vdb_tool -mesh2ls" || echo "dagtool convert")
        echo "| $name | $(cut -d' ' -f1 "$f" | median) | $(cut -d' ' -f2 "$f" | median) | $(( $(cut -d' ' -f3 "$f" | median | cut -d. -f1) / 1024 )) | $(stat -c %s "$file") |"
    done
    echo
    echo "all runs (wall user rss_kb): vdb_tool: $(tr '\n' ';' <"$SCRATCH/vdb") dagtool: $(tr '\n' ';' <"$SCRATCH/dag")"
    echo
    ;;
sizes)
    echo "### Sizes: .vdag vs the same DAG with 32-bit pointers vs SVO"
    echo
    echo "| mesh | depth | voxels | .vdag bytes | classic 32-bit bytes | SVO bytes | vdag / classic | SVO / vdag | entropy bound / classic |"
    echo "|---|---|---|---|---|---|---|---|---|"
    for obj in "$MESHES"/*.obj; do
        name=$(basename "$obj")
        for d in 10 12 14; do
            "$DAGTOOL" convert "$obj" -o "$SCRATCH/s.vdag" --depth "$d" --force -q
            "$DAGTOOL" info --json "$SCRATCH/s.vdag" >"$SCRATCH/s.json"
            python3 - "$name" "$d" "$SCRATCH/s.json" <<'EOF'
import json, sys
name, depth, path = sys.argv[1], sys.argv[2], sys.argv[3]
j = json.load(open(path))
f, c, s = int(j["file_bytes"]), int(j["classic_svdag_bytes"]), int(j["svo_bytes"])
e = int(j["pointer_entropy_bound_bytes"])
print(f"| {name} | {depth} | {j['voxel_count']:,} | {f:,} | {c:,} | {s:,} | {f / c:.2f} | {s / f:.2f} | {e / c:.2f} |")
EOF
            rm -f "$SCRATCH/s.vdag"
        done
    done
    echo
    ;;
*)
    echo "unknown benchmark $what (dragon14 dragon16 solid14 ooc14 ooc16 vdb sizes)" >&2
    exit 2
    ;;
esac
done
