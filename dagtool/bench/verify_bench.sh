#!/usr/bin/env bash
# `dagtool verify` over the shared meshes at several depths, printed as a Markdown table.
#
#   dagtool/bench/verify_bench.sh [mesh...]     mesh: a name in $MESHES without .obj
#                                               (default: cow spot armadillo dragon bunny dragon_res2)
#
# Environment: MESHES (default ../shared/meshes beside the repository), DEPTHS (default
# "8 10 12 14"), RAYS (default 1000000), SEED (default 1), OUT (scratch folder for the .vdag
# files, default a temporary folder, removed afterwards), CARGO_TARGET_DIR. Needs jq.
#
# Each mesh is converted with `dagtool convert --depth D` and verified with
# `dagtool verify MESH.obj FILE.vdag --rays $RAYS --seed $SEED --json`. Columns: agreement over
# the rays that are not near misses, near misses (excluded from agreement), clean hits (the
# hit-hit rays in the error statistics) and the excluded hit-hit rays (grazing + near
# approaches), |t_dag - t_mesh| over clean hits in voxels, the depth error
# (t_mesh - t_dag)*cos, the largest t_dag - t_mesh over all hit-hit rays, and the verdict.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$(pwd)
MESHES=${MESHES:-$ROOT/../shared/meshes}
DEPTHS=${DEPTHS:-8 10 12 14}
RAYS=${RAYS:-1000000}
SEED=${SEED:-1}
WHAT=${*:-cow spot armadillo dragon bunny dragon_res2}
if [ ! -d "$MESHES" ]; then
    echo "meshes not found at $MESHES (set MESHES)" >&2
    exit 1
fi
command -v jq >/dev/null || { echo "jq is needed" >&2; exit 1; }
cargo build --release -p dagtool >&2
TARGET=${CARGO_TARGET_DIR:-$ROOT/target}
DAGTOOL=$TARGET/release/dagtool
SCRATCH=${OUT:-$(mktemp -d)}
mkdir -p "$SCRATCH"
[ -z "${OUT:-}" ] && trap 'rm -rf "$SCRATCH"' EXIT

echo "dagtool verify, $RAYS rays (seed $SEED), $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg)"
echo
echo "| mesh | depth | agreement % | near misses % | clean hits | excl. hits (grazing + approach) | \|Δt\| median | p99 | max | depth err. max | max late | verify s | result |"
echo "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
for mesh in $WHAT; do
    obj=$MESHES/$mesh.obj
    for depth in $DEPTHS; do
        file=$SCRATCH/$mesh-$depth.vdag
        "$DAGTOOL" convert "$obj" -o "$file" --depth "$depth" --force -q
        start=$(date +%s.%N)
        set +e
        json=$("$DAGTOOL" verify "$obj" "$file" --rays "$RAYS" --seed "$SEED" --json)
        rc=$?
        set -e
        secs=$(echo "$(date +%s.%N) - $start" | bc)
        if [ $rc -ge 2 ]; then
            echo "| $mesh | $depth | error (exit $rc) |"
            continue
        fi
        echo "$json" | jq -r --arg mesh "$mesh" --arg secs "$secs" '
            def f(n): if . == null then "-" else (. * pow(10; n) | round / pow(10; n) | tostring) end;
            "| \($mesh) | \(.depth) | \(.agreement.percent | f(4)) | \(100 * .near_misses / .rays.total | f(2)) | \(.hits.clean) | \(.hits.grazing) + \(.hits.near_approaches) | \(.error_voxels.median | f(3)) | \(.error_voxels.p99 | f(3)) | \(.error_voxels.max | f(3)) | \(.depth_error_voxels.max | f(3)) | \(.max_late_voxels | f(4)) | \($secs | tonumber | f(1)) | \(if .passed then "PASS" else "FAIL: " + ([.criteria[] | select(.passed | not) | .name] | join(", ")) end) |"'
        rm -f "$file"
    done
done
