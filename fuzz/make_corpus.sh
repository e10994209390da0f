#!/bin/sh
# Fills fuzz/corpus/<target>/ (git-ignored, grows while fuzzing) from the
# committed seeds, the conformance cases and the regression inputs.
# Run from anywhere; existing corpus entries are kept.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
cases="$here/../conformance/cases"
for target in reader validator transport batch obj_import voxel_list gltf_import ply_import stl_import las_import vox_import binvox_import part_placement; do
    mkdir -p "$here/corpus/$target"
    for dir in "$here/seeds/$target" "$here/regressions/$target"; do
        [ -d "$dir" ] && find "$dir" -type f ! -name README.md -exec cp {} "$here/corpus/$target/" \;
    done
done
for target in reader validator; do
    cp "$cases"/trace/*.vdag "$cases"/validate/*.vdag "$here/corpus/$target/"
done
cp "$cases"/trace/*.rays "$here/corpus/batch/"
echo "corpus ready under $here/corpus"
