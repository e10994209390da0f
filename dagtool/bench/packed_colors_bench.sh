#!/usr/bin/env bash
# Packed colours (spec §12.6): sizes, encode cost and decode cost, printed as Markdown.
#
#   dagtool/bench/packed_colors_bench.sh
#
# Environment: FORMATS (default ../shared/formats beside the repository), RUNS (default 5),
# OUT (scratch folder, default a temporary folder, removed afterwards), BIN (the folder of
# the dagtool and dagtrace binaries, default target/release), WIDTH/HEIGHT (render size,
# default 1024x768), GPU (1: also render on the GPU, the default adapter; default 1), ENCODE
# (0: convert each file once, untimed, or reuse the files already in OUT; default 1), BACKENDS
# (the render back ends, default "cpu gpu", "cpu" with GPU=0), RENDER_ARGS (more arguments of
# every render, e.g. --no-validate to time the render without the file's validation).
#
# - encode: `dagtool convert spot_textured.obj --depth 12 --colors` with raw colours, with
#   `--color-error 0` and with `--color-error 8`, RUNS runs interleaved: median wall time and
#   its ratio to raw.
# - decode: `dagtrace render --shade color` of those three files at depth 12, on the CPU and
#   (GPU=1) on the GPU, RUNS runs interleaved: median wall time of the whole command and its
#   ratio to raw. On the CPU the colours are decoded on the host by the attribute index; on the
#   GPU the colour section lies on the device as stored (compressed for E = 0 and E = 8) and the
#   colour pass decodes each hit's colour there (dagtrace/src/gpu/colors.wgsl).
# - sizes: the colour section of each file, from `dagtool info`.
#
# Timings on a shared machine vary with its load; the load average is printed with each table.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$(pwd)
FORMATS=${FORMATS:-$ROOT/../shared/formats}
RUNS=${RUNS:-5}
BIN=${BIN:-$ROOT/target/release}
WIDTH=${WIDTH:-1024}
HEIGHT=${HEIGHT:-768}
GPU=${GPU:-1}
if [[ -z "${OUT:-}" ]]; then
    OUT=$(mktemp -d)
    trap 'rm -rf "$OUT"' EXIT
fi
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp}
SRC=$FORMATS/spot_textured.obj
[[ -f $SRC ]] || { echo "no $SRC" >&2; exit 1; }

now() { date +%s.%N; }
median() { sort -g | awk '{a[NR]=$1} END {print (NR%2) ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2}'; }
timed() { local t0; t0=$(now); "$@" >/dev/null 2>&1 || { echo "failed: $*" >&2; exit 1; }; echo "$(now) - $t0" | bc -l; }

declare -A ENC
variants=(raw e0 e8)
flags() { case $1 in raw) echo "--colors";; e0) echo "--colors --color-error 0";; e8) echo "--colors --color-error 8";; esac; }
ENC_RUNS=$RUNS
if [[ ${ENCODE:-1} == 0 ]]; then
    ENC_RUNS=0
    for v in "${variants[@]}"; do
        # shellcheck disable=SC2046
        [[ -f $OUT/$v.vdag ]] || "$BIN/dagtool" convert "$SRC" --depth 12 $(flags $v) -o "$OUT/$v.vdag" --force -q
    done
fi
for ((r = 0; r < ENC_RUNS; r++)); do
    for v in "${variants[@]}"; do
        # shellcheck disable=SC2046
        ENC[$v]+="$(timed "$BIN/dagtool" convert "$SRC" --depth 12 $(flags $v) -o "$OUT/$v.vdag" --force -q) "
    done
done
if [[ $ENC_RUNS == 0 ]]; then
    echo "### colour sections"
    echo
    for v in "${variants[@]}"; do
        echo "- $v: $("$BIN/dagtool" info "$OUT/$v.vdag" | sed -n 's/^colours: *//p')"
    done
    echo
else
echo "### encode: spot_textured.obj, depth 12, $RUNS runs (load $(cut -d' ' -f1-3 /proc/loadavg))"
echo
echo "| colours | median s | ratio to raw | colour section |"
echo "|---|---:|---:|---|"
raw_med=$(tr ' ' '\n' <<<"${ENC[raw]}" | grep . | median)
for v in "${variants[@]}"; do
    med=$(tr ' ' '\n' <<<"${ENC[$v]}" | grep . | median)
    line=$("$BIN/dagtool" info "$OUT/$v.vdag" | sed -n 's/^colours: *//p')
    printf '| %s | %.2f | %.3f | %s |\n' "$v" "$med" "$(echo "$med / $raw_med" | bc -l)" "$line"
done
echo
fi
backends=(cpu)
[[ $GPU == 1 ]] && backends+=(gpu)
read -r -a backends <<<"${BACKENDS:-${backends[*]}}"
for b in "${backends[@]}"; do
    load0=$(cut -d' ' -f1 /proc/loadavg)
    declare -A DEC=()
    for ((r = 0; r < RUNS; r++)); do
        for v in "${variants[@]}"; do
            # shellcheck disable=SC2086
            DEC[$v]+="$(timed "$BIN/dagtrace" render "$OUT/$v.vdag" --shade color --backend "$b" \
                --width "$WIDTH" --height "$HEIGHT" -o "$OUT/$v-$b.png" --force ${RENDER_ARGS:-}) "
        done
    done
    echo "### decode: render --shade color ${RENDER_ARGS:-}${RENDER_ARGS:+ }${WIDTH}x$HEIGHT, backend $b, $RUNS runs (load $load0 at the start, $(cut -d' ' -f1-3 /proc/loadavg) at the end)"
    echo
    echo "| colours | median s | ratio to raw |"
    echo "|---|---:|---:|"
    raw_med=$(tr ' ' '\n' <<<"${DEC[raw]}" | grep . | median)
    for v in "${variants[@]}"; do
        med=$(tr ' ' '\n' <<<"${DEC[$v]}" | grep . | median)
        printf '| %s | %.3f | %.3f |\n' "$v" "$med" "$(echo "$med / $raw_med" | bc -l)"
    done
    cmp -s "$OUT/raw-$b.png" "$OUT/e0-$b.png" && echo && echo "(raw and lossless images identical on $b)"
    echo
done
