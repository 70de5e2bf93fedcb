#!/bin/bash
# Fills .data for a call on the GPU machine within the 64 MiB a call carries (the tree included):
#   bash bench/device_data.sh edit    the evaluation set's six captures, their COLMAP sparse/ folders packed
#   bash bench/device_data.sh suite   beercan and the bundled splats (the GPU suite's data)
# Both add .data/site.txz: the files of the wheels in .whl (../shared/device/wheels.sh), unpacked and packed
# again with xz, which bench/device_bench.sh unpacks into /tmp/site in place of pip. Carry [".data"] alone.
set -euo pipefail
cd "$(dirname "$0")/.."
SHARED=${VIRGI_SHARED_DATA:-../shared/data}
case "${1:-}" in
  edit) scenes="beercan blowtorch cup fern fox fruit" ;;
  suite) scenes="beercan splats" ;;
  *) echo "usage: bash bench/device_data.sh edit|suite" >&2; exit 2 ;;
esac
[ -d .whl ] || { echo "no .whl here: run bash ../shared/device/wheels.sh first" >&2; exit 1; }
for s in $scenes; do [ -d "$SHARED/$s" ] || { echo "$SHARED/$s is missing" >&2; exit 1; }; done
# built outside the tree, so a failure leaves nothing that would travel; .data is replaced only at the end
new=$(mktemp -d) site=$(mktemp -d)
trap 'rm -rf "$new" "$site"' EXIT
for s in $scenes; do cp -r "$SHARED/$s" "$new/"; done
if [ "$1" = edit ]; then
  tar cJf "$new/sparse.txz" -C "$new" beercan/sparse cup/sparse
  rm -rf "$new/beercan/sparse" "$new/cup/sparse"
fi
for w in .whl/*.whl; do python3 -m zipfile -e "$w" "$site"; done
tar cJf "$new/site.txz" -C "$site" .
rm -rf .data && cp -r "$new" .data
total=$(( $(git ls-files -z | xargs -0 du -cb --apparent-size | tail -n 1 | cut -f1) + $(du -sb --apparent-size .data | cut -f1) ))
echo ".data filled for '$1': with the tree, $(( total / 1048576 )) MiB travel (at most 64)"
