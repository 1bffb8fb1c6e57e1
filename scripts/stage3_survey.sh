#!/usr/bin/env bash
# Stage 3 (`lightfuse invert`) before and after a change, on every scene it should hold on, and
# one table of how well it separates material from lighting (issue 44): per scene and variant,
# Table 1 without and with the median albedo rescale, the ghost-shadow share of the base colour
# over surfaces of uniform true albedo, the base colour error raw and rescaled, each recovered
# environment's irradiance error and upper-hemisphere log error (against a uniform map's), the
# recovered metallic of every mirror (chrome) object, the training views' PSNR, and stage 3's
# wall time. Definitions: docs/lighting-metrics.md.
#
# A variant is a name and the `lightfuse invert` options it adds to the fast preset:
# --variants "default= levels8=--env-levels 8" (space-separated name=options, the options with
# commas for spaces: "prior=--base-color-prior,0.3"). Stages 1 and 2 (fast preset) run once per
# scene and every variant starts from a copy of their outputs, so the variants differ in stage 3
# alone; a scene's variants run one after another in the same sitting.
#
# Scenes: the demo, the plain family (sunroom atelier: untextured floors, sun skies, chrome),
# the four presets (bedroom playroom livingroom kitchen) and the second family (study gallery
# workshop), each at its default size (the presets and the second family with 8 test views,
# as scripts/paper_tables.sh). Every step is skipped when its output exists and resumes from its
# checkpoint when it was killed, so the script can be stopped and run again. Each variant's
# invert/report.json (as invert.json), eval.json, eval.md and time.txt (one line per invocation
# of invert: wall seconds, peak RSS in KiB) are kept in <results>/<scene>/<variant> (by default
# docs/results/stage3, committed: the survey can be measured over several sittings on machines
# that keep no data between them), and a variant whose results are there is not run again.
# With --prune a scene's dataset and work folders (~GB) are deleted once every variant is kept.
# Writes the table, made from every result kept in <results>, to --table (default
# docs/results/stage3-survey.md) and prints it. A hand-written note.md in a variant's results
# folder becomes its row's footnote.
#
# Usage: bash scripts/stage3_survey.sh [--out data/survey3] [--results docs/results/stage3]
#            [--table docs/results/stage3-survey.md] [--scenes "demo sunroom atelier ..."]
#            [--variants "default= levels8=--env-levels,8"] [--prune] [--table-only]
# A dataset (or a stage 1-2 work folder) made elsewhere can be linked in as <out>/<scene>/dataset
# (<out>/<scene>/work). Cost on a 2-core machine, per scene: demo ~10 min for stages 1-2 and
# ~10 min a variant; the plain family ~10 min generation, ~15 min stages 1-2, ~12 min a variant;
# a preset ~15 min generation, ~1 h stages 1-2 and ~25 min a variant.
set -euo pipefail
cd "$(dirname "$0")/.."
out=data/survey3
res=docs/results/stage3
table=docs/results/stage3-survey.md
scenes="demo sunroom atelier bedroom playroom livingroom kitchen study gallery workshop"
variants="default= levels8=--env-levels,8"
prune=0
table_only=0
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out=$2; shift 2 ;;
    --results) res=$2; shift 2 ;;
    --scenes) scenes=$2; shift 2 ;;
    --variants) variants=$2; shift 2 ;;
    --table) table=$2; shift 2 ;;
    --prune) prune=1; shift ;;
    --table-only) table_only=1; shift ;;
    -h | --help) sed -n '2,37p' "$0"; exit 0 ;;
    *) echo "stage3_survey.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
for s in $scenes; do
  case "$s" in
    demo | sunroom | atelier | bedroom | playroom | livingroom | kitchen | study | gallery | workshop) ;;
    *) echo "stage3_survey.sh: --scenes: unknown scene $s (expected demo, sunroom, atelier, bedroom, playroom, livingroom, kitchen, study, gallery or workshop)" >&2; exit 2 ;;
  esac
done
for v in $variants; do
  case "$v" in
    *=*) name=${v%%=*}
      if ! [[ "$name" =~ ^[A-Za-z0-9_.-]+$ ]]; then
        echo "stage3_survey.sh: --variants: $v: the name before = must be letters, digits, _ . or -" >&2; exit 2
      fi ;;
    *) echo "stage3_survey.sh: --variants: $v: expected name=options (e.g. levels8=--env-levels,8)" >&2; exit 2 ;;
  esac
done

if [ "$table_only" = 0 ]; then
bash scripts/setup.sh
# LIGHTFUSE=<binary> runs another build (a copy, so that builds beside the survey do not change it)
lf=${LIGHTFUSE:-$PWD/target/release/lightfuse}
py=$PWD/.venv/bin/python
say() { echo "== $*" >&2; }

for s in $scenes; do
  todo=0
  for v in $variants; do [ -f "$res/$s/${v%%=*}/eval.json" ] || todo=1; done
  [ "$todo" = 1 ] || continue
  ds=$out/$s/dataset
  w=$out/$s/work
  if [ ! -f "$ds/dataset.json" ]; then
    say "$s: generating the dataset with Cycles ($ds)"
    case "$s" in
      demo) "$py" blender/generate.py --demo --seed 0 --out "$ds" --force --quiet >&2 ;;
      sunroom | atelier) "$py" blender/generate.py --preset "$s" --seed 0 --out "$ds" --force --quiet >&2 ;;
      *) "$py" blender/generate.py --preset "$s" --seed 0 --test-views 8 --out "$ds" --force --quiet >&2 ;;
    esac
  fi
  mkdir -p "$w"
  if [ ! -f "$w/refined.glb" ]; then
    say "$s: stages 1 and 2 (fast preset)"
    "$lf" reconstruct "$ds" -o "$w" --preset fast --resume >&2
    "$lf" refine "$ds" "$w" --preset fast --resume >&2
  fi
  for v in $variants; do
    name=${v%%=*}
    opts=${v#*=}
    opts=${opts//,/ }
    keep=$res/$s/$name
    [ -f "$keep/eval.json" ] && continue
    vw=$out/$s/$name
    mkdir -p "$vw"
    # Stages 1-2's outputs, as every variant's starting point (not stage 3's or the evaluation's).
    for f in "$w"/*; do
      case "$(basename "$f")" in
        invert | relightable.* | eval | run.json) ;;
        *) [ -e "$vw/$(basename "$f")" ] || cp -a "$f" "$vw/" ;;
      esac
    done
    if [ ! -f "$vw/invert/report.json" ] || [ ! -f "$vw/relightable.glb" ]; then
      say "$s / $name: lightfuse invert --preset fast $opts"
      # shellcheck disable=SC2086  # the variant's options are words
      /usr/bin/time -f "%e %M" -a -o "$vw/time.txt" "$lf" invert "$ds" "$vw" --preset fast --resume $opts >&2
    fi
    # (evaluate renders with the bounces the variant trained with: its invert/report.json)
    say "$s / $name: lightfuse evaluate --no-images"
    "$lf" evaluate "$ds" "$vw" --no-images >&2
    mkdir -p "$keep"
    cp -p "$vw/invert/report.json" "$keep/invert.json"
    cp -p "$vw/time.txt" "$vw/eval/eval.md" "$keep/"
    echo "$v" > "$keep/variant.txt"
    # eval.json last: its presence marks the variant as done.
    cp -p "$vw/eval/eval.json" "$keep/"
  done
  if [ "$prune" = 1 ]; then
    say "$s: results kept in $res/$s; deleting its dataset and work folders (--prune)"
    for v in $variants; do rm -rf "${out:?}/$s/${v%%=*}"; done
    rm -rf "${w:?}"
    if [ -L "$ds" ]; then rm "$ds"; else rm -rf "${ds:?}"; fi
  fi
done
fi

mkdir -p "$(dirname "$table")"
python3 scripts/stage3_table.py "$res" > "$table.tmp"
mv "$table.tmp" "$table"
cat "$table"
