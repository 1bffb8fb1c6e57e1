#!/usr/bin/env bash
# Stage 1 (`lightfuse reconstruct`, fast preset) on every scene it should hold on, and one table
# of what every later stage inherits from it: per scene, the object poses (symmetry-aware
# rotation; translation at the point every symmetry fixes, the object's origin otherwise: see
# src/eval/pose.rs), the share of each object's surface carrying its label (src/eval/labels.rs),
# the held-out PSNR and median depth error, wall time and peak memory. Scenes: the demo, the
# four presets (bedroom playroom livingroom kitchen) and the second family, which no parameter
# was tuned on (study gallery workshop); each at its default size.
# Every step is skipped when its output exists, and a killed reconstruction resumes from its
# checkpoint. Each scene's report.json, poses.json and time.txt (one line per invocation:
# wall seconds, peak RSS in KiB; a hand-written note.md beside them becomes the row's footnote)
# are kept in <results>/<scene> (by default docs/results/stage1, committed: the survey can be
# measured over several sittings on machines that keep no data between them), and a scene whose
# results are there is not run again; with --prune its dataset and work folder (~GB) are
# deleted as soon as they are kept. Writes the table, made from every scene kept in <results>,
# to --table (default docs/results/stage1-survey.md) and prints it. --readme is an old name
# that does nothing more (the table is always written; the README holds no results).
#
# Usage: bash scripts/stage1_survey.sh [--out data/survey] [--results docs/results/stage1]
#            [--table docs/results/stage1-survey.md]
#            [--scenes "demo study gallery workshop bedroom playroom livingroom kitchen"] [--prune]
# A dataset already made elsewhere can be linked in as <out>/<scene>/dataset.
# Cost on a 2-core machine, per scene at its default size: generation ~7-15 min (demo 1),
# stage 1 ~25-40 min (demo 4).
set -euo pipefail
cd "$(dirname "$0")/.."
out=data/survey
res=docs/results/stage1
table=docs/results/stage1-survey.md
scenes="demo study gallery workshop bedroom playroom livingroom kitchen"
prune=0
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out=$2; shift 2 ;;
    --results) res=$2; shift 2 ;;
    --scenes) scenes=$2; shift 2 ;;
    --table) table=$2; shift 2 ;;
    --readme) shift ;; # deprecated: the table is always written to --table
    --prune) prune=1; shift ;;
    -h | --help) sed -n '2,24p' "$0"; exit 0 ;;
    *) echo "stage1_survey.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
for s in $scenes; do
  case "$s" in
    demo | study | gallery | workshop | bedroom | playroom | livingroom | kitchen) ;;
    *) echo "stage1_survey.sh: --scenes: unknown scene $s (expected demo, study, gallery, workshop, bedroom, playroom, livingroom or kitchen)" >&2; exit 2 ;;
  esac
done

bash scripts/setup.sh
lf=$PWD/target/release/lightfuse
py=$PWD/.venv/bin/python
say() { echo "== $*" >&2; }

for s in $scenes; do
  [ -f "$res/$s/report.json" ] && continue
  ds=$out/$s/dataset
  w=$out/$s/work
  if [ ! -f "$ds/dataset.json" ]; then
    say "$s: generating the dataset with Cycles ($ds)"
    # Stage 1 reads the training states only: the test state gets one view under one
    # environment (the demo keeps its own fixed layout).
    if [ "$s" = demo ]; then
      "$py" blender/generate.py --demo --seed 0 --out "$ds" --force --quiet >&2
    else
      "$py" blender/generate.py --preset "$s" --seed 0 --test-views 1 --relight 1 --out "$ds" --force --quiet >&2
    fi
  fi
  say "$s: lightfuse reconstruct (fast preset)"
  mkdir -p "$w"
  # One line per invocation, so a resumed run's wall time is the sum of its lines.
  /usr/bin/time -f "%e %M" -a -o "$out/$s/time.txt" "$lf" reconstruct "$ds" -o "$w" --preset fast --resume >&2
  mkdir -p "$res/$s"
  cp -p "$w/poses.json" "$out/$s/time.txt" "$res/$s/"
  # report.json last: its presence marks the scene as done.
  cp -p "$w/report.json" "$res/$s/"
  if [ "$prune" = 1 ]; then
    say "$s: results kept in $res/$s; deleting its dataset and work folder (--prune)"
    rm -rf "${w:?}"
    if [ -L "$ds" ]; then rm "$ds"; else rm -rf "${ds:?}"; fi
  fi
done

mkdir -p "$(dirname "$table")"
"$py" - "$res" > "$table.tmp" <<'PY'
import json, os, sys
res = sys.argv[1]
ORDER = ["demo", "bedroom", "playroom", "livingroom", "kitchen", "study", "gallery", "workshop"]
FAMILY = {"study", "gallery", "workshop"}
done = [s for s in ORDER if os.path.isfile(os.path.join(res, s, "report.json"))]
print("# Stage 1 on every scene\n")
print(f"Written by `scripts/stage1_survey.sh` from the results kept in `{res}/` (do not edit by hand: "
      "a scene's footnote is its `note.md` there). Machines: VMs with 2 cores, 24 GiB and no GPU.\n")
print("Measured by `bash scripts/stage1_survey.sh` (each scene at its default size, fast preset, "
      "3000 iterations; *italic*: the second family, never tuned on). Poses: every object in every "
      "state but the reference one, symmetry-aware rotation, translation at the point its symmetries "
      "fix; within = within 2 deg and 1 cm (aim: 90 % of them, and every one within 5 deg and 3 cm). "
      "Label share: the share of an object's surface (interior mask pixels of the reference state) "
      "whose nearest surfel carries its label (aim: every one 95 % or more); purity: the share of an "
      "object's surfels whose nearest observed surface point is its own (runs before it was measured: -). "
      "Wall time summed over the invocations of a resumed run; machines differ between sittings.\n")
print("| Scene | poses within | largest rotation / translation | within 5 deg / 3 cm | label shares (>= 95 %) "
      "| purity | held-out PSNR (training) | median depth error | wall | peak RSS |")
print("|---|---|---|---|---|---|---|---|---|---|")
tot = tot_in = tot_5 = lab = lab_ok = 0
notes = []
for s in done:
    with open(os.path.join(res, s, "report.json")) as f:
        r = json.load(f)
    errs = r.get("pose_errors") or []
    n = len(errs)
    within = sum(e["rotation_deg"] <= 2 and e["translation_cm"] <= 1 for e in errs)
    w5 = sum(e["rotation_deg"] <= 5 and e["translation_cm"] <= 3 for e in errs)
    rot = max((e["rotation_deg"] for e in errs), default=0)
    tr = max((e["translation_cm"] for e in errs), default=0)
    shares = [v for _, v in r.get("label_share") or []]
    ok = sum(v >= 0.95 for v in shares)
    tot, tot_in, tot_5, lab, lab_ok = tot + n, tot_in + within, tot_5 + w5, lab + len(shares), lab_ok + ok
    wall = rss = 0.0
    with open(os.path.join(res, s, "time.txt")) as f:
        for line in f:
            p = line.split()
            if len(p) == 2:
                wall += float(p[0])
                rss = max(rss, float(p[1]))
    name = f"*{s}*" if s in FAMILY else s
    # A scene's note.md (one line, written by hand) says what the figures alone do not (e.g. a
    # wall time from a run that shared the machine or lost an invocation's line).
    mark = ""
    if os.path.isfile(os.path.join(res, s, "note.md")):
        with open(os.path.join(res, s, "note.md")) as f:
            notes.append(f"{s}: " + " ".join(f.read().split()))
        mark = f" [{len(notes)}]"
    lo = f"{100 * min(shares):.1f}-{100 * max(shares):.1f} % ({ok} of {len(shares)})" if shares else "-"
    pur = [v for _, v in r.get("label_purity") or []]
    pu = f"{100 * min(pur):.1f}-{100 * max(pur):.1f} %" if pur else "-"
    print(f"| {name} | {within} of {n} | {rot:.2f} deg / {tr:.2f} cm | {w5} of {n} | {lo} | {pu} "
          f"| {r['heldout_psnr_srgb']:.2f} dB ({r['train_psnr_srgb']:.2f}) "
          f"| {100 * r['heldout_median_depth_error_m']:.2f} cm | {wall:.0f} s{mark} | {rss / 1048576:.2f} GB |")
missing = [s for s in ORDER if s not in done]
if done:
    print(f"| **all {len(done)} scene{'s' * (len(done) != 1)}** | **{tot_in} of {tot}** ({100 * tot_in / max(tot, 1):.0f} %) | "
          f"| {tot_5} of {tot} | {lab_ok} of {lab} | | | | | |")
if notes:
    print("\n" + "\n".join(f"[{i + 1}] {n}" for i, n in enumerate(notes)))
if missing:
    print(f"\nNot measured yet: {', '.join(missing)}.")
PY
mv "$table.tmp" "$table"
cat "$table"
say "table written to $table"
