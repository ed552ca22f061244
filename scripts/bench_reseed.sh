# Time re-seeding on the 1-8 model: three interleaved passes of five settings, JSONs in $OUT (BENCHMARKS.md).
set -euo pipefail
mkdir -p "${OUT:-runs/bench_reseed}"
S="--search 3 --fit-color 50 --search-scales 0.8,0.9,1.1,1.25"
for r in 1 2 3; do
  python3 -m prismonet evaluate clevr1to8 data/clevr1to8 --split val --limit 96 --batch 32 --prune --quiet --json ${OUT:-runs/bench_reseed}/enc_$r.json
  python3 -m prismonet evaluate clevr1to8 data/clevr1to8 --split val --limit 96 --batch 32 --prune --reseed 6 --quiet --json ${OUT:-runs/bench_reseed}/rs_$r.json
  python3 -m prismonet evaluate clevr1to8 data/clevr1to8 --split val --limit 96 --batch 32 --prune $S --quiet --json ${OUT:-runs/bench_reseed}/s_$r.json
  python3 -m prismonet evaluate clevr1to8 data/clevr1to8 --split val --limit 96 --batch 32 --prune $S --reseed 6 --quiet --json ${OUT:-runs/bench_reseed}/rss_$r.json
  python3 -m prismonet evaluate clevr1to8 data/clevr1to8 --split val --limit 96 --batch 32 --prune $S --reseed 6 --reseed-cycles 3 --quiet --json ${OUT:-runs/bench_reseed}/rssc3_$r.json
done
