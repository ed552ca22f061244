#!/usr/bin/env bash
# The photo stand-ins (EVALUATION.md, sessions 70, 83 and 84): three synthetic sets rendered larger and more crowded
# than the tabletop models' training scenes, turned into labelled "photos" and pooled per split. Nothing may be
# chosen on the five labelled real photos; settings are chosen on data/standins/pooled_val (and, for greyscale photos,
# data/standins/gray_pooled_val), then read once on the test folders.
#   bash scripts/photo_standins.sh            # colour: data/standins/pooled_{val,test}
#   bash scripts/photo_standins.sh gray       # the same photos made grey: data/standins/gray_pooled_{val,test}
# Close-ups (1-3 large objects, session 86) are labelled on their own: data/standins/[gray/]closeup_photos/{val,test}.
# About 2 minutes for the scenes (two workers) and 1 minute per look.
set -euo pipefail
look=${1:-colour}
D=${STANDINS:-data/standins}   # STANDINS=FOLDER: make them elsewhere
if [ ! -f $D/sparse/meta.json ]; then
python3 -m prismonet data clevr --randomize-range focal_scale=0.8,1.8 --randomize-range camera_elevation_deg=55,85 --objects 28 \
    --min-objects 14 --area 4.5 --size 192 --shadows --colors clevr,white,silver,black --split 0,40,40 --seed 70 --workers 1 --out $D/tiny
python3 -m prismonet data clevr --randomize --randomize-range focal_scale=0.8,1.8 --randomize-range camera_elevation_deg=18,85 \
    --objects 20 --min-objects 8 --area 4 --size 192 --shadows --split 0,40,40 --seed 71 --workers 1 --out $D/crowded
python3 -m prismonet data clevr --randomize --randomize-range focal_scale=0.8,1.8 --randomize-range camera_elevation_deg=18,85 \
    --objects 8 --min-objects 1 --area 2.5 --size 192 --shadows --split 0,40,40 --seed 72 --workers 1 --out $D/sparse
fi
if [ ! -f $D/closeup/meta.json ]; then  # session 86: 1-3 objects large in the frame (close-ups); read on its own, not pooled
python3 -m prismonet data clevr --randomize --randomize-range camera_elevation_deg=25,85 --objects 3 --min-objects 1 --area 0.8 \
    --size 192 --shadows --split 0,40,40 --seed 86 --workers 1 --out $D/closeup
fi
case $look in
  colour) flag=""; sub=""; pooled=pooled ;;
  gray) flag="--gray"; sub=gray/; pooled=gray_pooled ;;
  *) echo "photo_standins.sh: expected 'colour' or 'gray', got '$look'" >&2; exit 2 ;;
esac
for sp in val test; do
  python3 scripts/labelled_photos.py $D/tiny --split $sp --out $D/${sub}tiny_photos/$sp --ground-gray 0.08,0.2 $flag
  python3 scripts/labelled_photos.py $D/crowded --split $sp --out $D/${sub}crowded_photos/$sp $flag
  python3 scripts/labelled_photos.py $D/sparse --split $sp --out $D/${sub}sparse_photos/$sp $flag
  python3 scripts/labelled_photos.py $D/closeup --split $sp --out $D/${sub}closeup_photos/$sp $flag
  python3 scripts/pool_photos.py tiny=$D/${sub}tiny_photos/$sp crowded=$D/${sub}crowded_photos/$sp \
      sparse=$D/${sub}sparse_photos/$sp --out $D/${pooled}_$sp
done
