#!/usr/bin/env bash
# The merge step alone: `dagtool merge` of the same parts by two dagtool builds, interleaved,
# printed as a Markdown table (wall, user+sys CPU, CPU/wall, peak RSS per run, then medians).
#
#   dagtool/bench/merge_bench.sh OLD_DAGTOOL NEW_DAGTOOL PARTS_DIR [merge options...]
#
# PARTS_DIR holds the parts (*.part, e.g. the 8 of `dagtool convert --region 1:X,Y,Z` of one
# mesh with one --bounds). Environment: RUNS (rounds, default 3), OUT (scratch folder, default
# a temporary folder, removed afterwards). Every output is compared with the first one, byte
# for byte (the merge is exact: both builds must write the same file), and the load average
# is printed with each round: on a shared machine wall times vary with it.
set -euo pipefail
old=$1 new=$2 parts=$3
shift 3
RUNS=${RUNS:-3}
own_out=
if [ -z "${OUT:-}" ]; then
    OUT=$(mktemp -d)
    own_out=1
fi
mkdir -p "$OUT"
cleanup() { if [ -n "$own_out" ]; then rm -rf "$OUT"; fi; }
trap cleanup EXIT
mapfile -t files < <(ls "$parts"/*.part)
echo "parts: ${#files[@]}, $(cat "${files[@]}" | wc -c) bytes; options: $*" >&2
printf '| round | build | wall (s) | user+sys (s) | CPU/wall | peak RSS (MiB) | load average |\n|---:|---|---:|---:|---:|---:|---|\n'
declare -A walls cpus
for r in $(seq 1 "$RUNS"); do
    for which in old new; do
        bin=$old
        [ "$which" = new ] && bin=$new
        out=$OUT/$which.vdag
        load=$(cut -d' ' -f1-3 /proc/loadavg)
        /usr/bin/time -f '%e %U %S %M' -o "$OUT/time" "$bin" merge "${files[@]}" -o "$out" --force "$@" >"$OUT/summary" 2>&1 || {
            cat "$OUT/summary" >&2
            exit 1
        }
        read -r wall user sys rss <"$OUT/time"
        cpu=$(echo "$user + $sys" | bc)
        printf '| %d | %s | %.1f | %.1f | %.2f | %d | %s |\n' "$r" "$which" "$wall" "$cpu" "$(echo "$cpu / $wall" | bc -l)" $((rss / 1024)) "$load"
        walls[$which]+="$wall "
        cpus[$which]+="$cpu "
        if [ -f "$OUT/first.vdag" ]; then
            cmp -s "$OUT/first.vdag" "$out" || {
                echo "$which (round $r) wrote different bytes" >&2
                exit 1
            }
            rm "$out"
        else
            mv "$out" "$OUT/first.vdag"
        fi
    done
done
median() { tr ' ' '\n' | grep . | sort -g | awk '{a[NR]=$1} END {print (NR % 2) ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2}'; }
mo=$(echo "${walls[old]}" | median) mn=$(echo "${walls[new]}" | median)
co=$(echo "${cpus[old]}" | median) cn=$(echo "${cpus[new]}" | median)
echo
echo "medians: old ${mo} s wall (${co} s CPU), new ${mn} s wall (${cn} s CPU): new/old wall $(printf '%.2f' "$(echo "$mn / $mo" | bc -l)"); output $(stat -c %s "$OUT/first.vdag") bytes, identical"
