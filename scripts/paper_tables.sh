#!/usr/bin/env bash
# The paper's tables on the synthetic presets, measured against Cycles:
#   Table 1  novel-state relighting on every preset (`lightfuse run`: stages 1-3 and evaluate),
#            LightFuse / Baked / No re-tracing, scenes averaged equally;
#   Table 3  stage 2's switches on bedroom (refine without coverage / scale / depth / normal,
#            each then inverted and evaluated like the full run);
#   Table 4  stage 3's switches on bedroom (invert with the naive estimator, fixed 8 spp,
#            8 -> 16 spp), on the full run's refined geometry.
# Every step is skipped when its output exists and resumes from its checkpoint when it was
# killed, so the script can be stopped and run again. Each evaluation's eval.json and eval.md,
# and each stage's report.json, are kept in <results>/<preset>[/<variant>] (~110 kB; by default
# docs/results/paper, which is committed: the tables can be measured over several sittings on
# machines that keep no data between them), and a row whose results are there is not run again:
# with --prune, a preset's dataset and work folders (~GBs) are deleted as soon as every
# requested table has what it needs from them. Writes the tables, made from every result kept
# in <results> (the tables not requested included), to --table (default docs/results/tables.md)
# and prints them. --readme is an old name that does nothing more (the tables are always
# written; the README holds no results).
#
# Usage: bash scripts/paper_tables.sh [--out data/paper] [--results docs/results/paper]
#            [--table docs/results/tables.md] [--presets "bedroom playroom livingroom kitchen"]
#            [--tables "1 3 4"] [--preset fast|paper] [--test-views 8] [--prune]
# Cost on a 2-core machine, fast preset, per preset: generation ~15 min, stage 1 ~25-45
# min, stage 2 ~20 min; Tables 3 and 4 add 7 variants of bedroom (4 x refine + invert + a
# LightFuse-only evaluation, 3 x invert + the same evaluation: ~1 h each).
# One preset's Table 1 row took 1.5-2 h (bedroom, playroom). Hours in all: run it overnight.
set -euo pipefail
cd "$(dirname "$0")/.."
out=data/paper
res=docs/results/paper
table=docs/results/tables.md
presets="bedroom playroom livingroom kitchen"
tables="1 3 4"
stage_preset=fast
test_views=8
prune=0
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out=$2; shift 2 ;;
    --results) res=$2; shift 2 ;;
    --presets) presets=$2; shift 2 ;;
    --tables) tables=$2; shift 2 ;;
    --preset) stage_preset=$2; shift 2 ;;
    --test-views) test_views=$2; shift 2 ;;
    --table) table=$2; shift 2 ;;
    --readme) shift ;; # deprecated: the tables are always written to --table
    --prune) prune=1; shift ;;
    -h | --help) sed -n '2,26p' "$0"; exit 0 ;;
    *) echo "paper_tables.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
case "$stage_preset" in fast | paper) ;; *) echo "paper_tables.sh: --preset: expected fast or paper, found $stage_preset" >&2; exit 2 ;; esac

bash scripts/setup.sh
lf=$PWD/target/release/lightfuse
py=$PWD/.venv/bin/python
say() { echo "== $*" >&2; }

# The preset's dataset, generated once (a generation that was killed left no dataset.json and
# starts again).
dataset() {
  local ds=$out/$1/dataset
  if [ ! -f "$ds/dataset.json" ]; then
    say "$1: generating the dataset with Cycles ($ds)"
    "$py" blender/generate.py --preset "$1" --seed 0 --test-views "$test_views" --out "$ds" --force --quiet >&2
  fi
  echo "$ds"
}

# Keeps an evaluation's small outputs, and each stage's report (the figures issues and notes
# quote: poses, leaks, recovered albedo), as stage1.json, refine.json, invert.json: $1 the work
# folder, $2 the results folder.
keep() {
  mkdir -p "$2"
  cp -p "$1/eval/eval.json" "$1/eval/eval.md" "$2/"
  local f
  for f in report.json:stage1.json refine/report.json:refine.json invert/report.json:invert.json; do
    if [ -f "$1/${f%%:*}" ]; then cp -p "$1/${f%%:*}" "$2/${f##*:}"; fi
  done
}

# Stages 1-3 and the evaluation of one preset: the full run every table starts from. Skipped
# when its results are kept, unless $2 = need (a variant is about to start from its outputs).
full_run() {
  local ds
  if [ -f "$res/$1/eval.json" ] && [ "${2:-}" != need ]; then return; fi
  if [ -f "$res/$1/eval.json" ] && [ -f "$out/$1/work/refined.glb" ]; then return; fi
  ds=$(dataset "$1")
  say "$1: lightfuse run ($stage_preset)"
  "$lf" run "$ds" -o "$out/$1/work" --preset "$stage_preset" >&2
  keep "$out/$1/work" "$res/$1"
}

# Deletes a preset's dataset and work folders (--prune) once nothing requested still needs them.
prune_preset() {
  [ "$prune" = 1 ] || return 0
  if [ "$1" = bedroom ]; then
    local v
    for v in t3-no-coverage t3-no-scale t3-no-depth t3-no-normal t4-naive t4-fixed8 t4-max16; do
      case "$v" in t3-*) [[ " $tables " == *" 3 "* ]] || continue ;; t4-*) [[ " $tables " == *" 4 "* ]] || continue ;; esac
      [ -f "$res/bedroom/$v/eval.json" ] || return 0
    done
  fi
  say "$1: results kept in $res/$1; deleting its dataset and work folders (--prune)"
  rm -rf "${out:?}/$1/dataset" "${out:?}/$1/work" "${out:?}/$1"/t[34]-*
}

# A variant work folder: the full run's earlier outputs copied in, then the variant's stages.
# $1 name, $2 files to copy from the full run, $3 refine flags ("" = reuse refined.glb),
# $4 invert flags.
variant() {
  local name=$1 files=$2 refine_flags=$3 invert_flags=$4
  local ds=$out/bedroom/dataset base=$out/bedroom/work w=$out/bedroom/$name
  [ -f "$res/bedroom/$name/eval.json" ] && return
  full_run bedroom need
  mkdir -p "$w"
  for f in $files; do [ -f "$w/$f" ] || cp -p "$base/$f" "$w/$f"; done
  if [ ! -f "$w/refined.glb" ]; then
    say "bedroom/$name: lightfuse refine $refine_flags"
    # shellcheck disable=SC2086 # the flags are words
    "$lf" refine "$ds" "$w" --preset "$stage_preset" --resume $refine_flags >&2
  fi
  if [ ! -f "$w/relightable.glb" ]; then
    say "bedroom/$name: lightfuse invert $invert_flags"
    # shellcheck disable=SC2086
    "$lf" invert "$ds" "$w" --preset "$stage_preset" --eval-spp 16 --eval-stride 2 --resume $invert_flags >&2
  fi
  if [ ! -f "$w/eval/eval.json" ]; then
    # The ablation tables compare LightFuse's relighting only (Baked does not depend on any
    # switch; Table 2 is not part of them): about half the rendering of a full evaluation.
    say "bedroom/$name: lightfuse evaluate (LightFuse, Table 1)"
    "$lf" evaluate "$ds" "$w" --no-images --rows lightfuse --tables 1 >&2
  fi
  keep "$w" "$res/bedroom/$name"
}

for t in $tables; do
  case "$t" in
    1) for p in $presets; do full_run "$p"; [ "$p" = bedroom ] || prune_preset "$p"; done ;;
    3)
      for s in coverage scale depth normal; do variant "t3-no-$s" "scene.glb" "--no-$s" ""; done ;;
    4)
      variant t4-naive "scene.glb refined.glb" "" "--estimator naive"
      variant t4-fixed8 "scene.glb refined.glb" "" "--spp-schedule fixed8"
      variant t4-max16 "scene.glb refined.glb" "" "--spp-schedule max16" ;;
    *) echo "paper_tables.sh: --tables: expected 1, 3 or 4, found $t" >&2; exit 2 ;;
  esac
done
[[ " $presets $tables " == *" bedroom "* || " $tables " == *" 3 "* || " $tables " == *" 4 "* ]] && prune_preset bedroom

# The Markdown: every figure read from the kept eval.json files.
mkdir -p "$(dirname "$table")"
"$py" - "$res" "$tables" "$presets" "$stage_preset" "$test_views" > "$table.tmp" <<'PY'
import json, os, sys
res, tables, presets, stage_preset, test_views = sys.argv[1], sys.argv[2].split(), sys.argv[3].split(), sys.argv[4], sys.argv[5]
ROWS = [("lightfuse", "LightFuse"), ("baked", "Baked"), ("no_retracing", "No re-tracing")]

# A row's figures: its eval.json, or, for rows measured before results were committed, a
# transcribed.json holding the same "relighting" figures and where they were transcribed from.
def source(folder):
    for name in ("eval.json", "transcribed.json"):
        path = os.path.join(res, folder, name)
        if os.path.isfile(path):
            return path
    return None

def ev(folder):
    with open(source(folder)) as f:
        return json.load(f)

def cells(rows):
    """One Table 1 row's figures: each method's PSNR and SSIM, then LightFuse rescaled."""
    return " | ".join(fig(rows[k]) for k, _ in ROWS) + f" | {fig(rows['lightfuse'], 'rescaled')} |"

def fig(row, key="raw"):
    m = row[key]
    return f"{m['psnr_srgb_db']:.2f} | {m['ssim_srgb']:.3f}"

T3_FOLDERS = ["t3-no-coverage", "t3-no-scale", "t3-no-depth", "t3-no-normal"]
T4_FOLDERS = ["t4-naive", "t4-fixed8", "t4-max16"]
# Every table with results kept, requested or not: the file is rewritten on every run, and a run
# of one table must not drop the others.
requested = tables
kept = {"1": any(source(p) for p in ["bedroom", "playroom", "livingroom", "kitchen"] + presets),
        "3": any(source(f"bedroom/{v}") for v in T3_FOLDERS),
        "4": any(source(f"bedroom/{v}") for v in T4_FOLDERS)}
tables = [t for t in ("1", "3", "4") if t in requested or kept[t]]
earlier = [p for p in ["bedroom", "playroom", "livingroom", "kitchen"] if p not in presets and source(p)]
transcribed = [p for p in earlier if source(p).endswith("transcribed.json")]
others = [t for t in tables if t not in requested]
print("# The paper's tables on the synthetic presets\n")
print(f"Written by `scripts/paper_tables.sh` from the results kept in `{res}/` (do not edit by hand: "
      "a paper-preset run's note is its `<preset>-paper/note.md` there). Machines: VMs with 2 cores, 24 GiB and no GPU.\n")
print(f"Measured by `bash scripts/paper_tables.sh --tables \"{' '.join(requested)}\" --presets \"{' '.join(presets)}\" "
      f"--preset {stage_preset} --test-views {test_views}`"
      + (f" (rows {', '.join(earlier)}: earlier sittings of the same command, with `--presets` naming them"
         + (f"; {', '.join(transcribed)}: transcribed to two decimals from the README of their sitting, the full results lost with that machine's data, so means may differ by 0.01"
            if transcribed else "") + ")" if earlier else "")
      + (f" (Table{'s' * (len(others) > 1)} {', '.join(others)}: earlier runs of the same command)" if others else "")
      + " (PSNR dB / SSIM on 8-bit sRGB, 32 spp, denoised; \"rescaled\": after "
      "the per-channel median albedo rescale; the test arrangement under the environments no training "
      "state saw).\n")
if "1" in tables:
    print("Table 1, novel-state relighting (paper: LightFuse 25.38 / 0.852 averaged over its four scenes)\n")
    print("| Scene | " + " | ".join(f"{n} PSNR | {n} SSIM" for _, n in ROWS) + " | LightFuse rescaled PSNR | SSIM |")
    print("|---" * (2 * len(ROWS) + 3) + "|")
    # Every preset measured so far (in any sitting), so the table can grow over several.
    every = ["bedroom", "playroom", "livingroom", "kitchen"] + [p for p in presets if p not in ("bedroom", "playroom", "livingroom", "kitchen")]
    have = lambda p: source(p) is not None
    per = {p: ev(p)["relighting"] for p in every if have(p)}
    for p in every:
        if p in per:
            rows = per[p]
            print(f"| {p} | {cells(rows)}")
        elif p in ("bedroom", "playroom", "livingroom", "kitchen"):
            print(f"| {p} | not measured yet |" + " |" * (2 * len(ROWS) + 1))
    mean = lambda k, key, m: sum(per[q][k][key][m] for q in per) / len(per)
    label = "**mean**" if len(per) == 4 else f"**mean of {len(per)} of 4**"
    print(f"| {label} | " + " | ".join(f"{mean(k, 'raw', 'psnr_srgb_db'):.2f} | {mean(k, 'raw', 'ssim_srgb'):.3f}" for k, _ in ROWS)
          + f" | {mean('lightfuse', 'rescaled', 'psnr_srgb_db'):.2f} | {mean('lightfuse', 'rescaled', 'ssim_srgb'):.3f} |\n")
    # Stage 3 on the paper preset, kept in <res>/<preset>-paper, beside stage 3 on the fast
    # preset from the same refined scene (<res>/<preset>-paper/fast): a table of its own, since
    # the rows above share one preset and their mean compares like with like. These runs are
    # not made by this script (stages 1-2 fast, stage 3 paper: the folder's note.md gives the
    # commands, and is printed under the table).
    paper = [p for p in every if source(f"{p}-paper")]
    if paper:
        print("Table 1 with stage 3 on the paper preset (15,000 iterations at 8 -> 16 -> 32 spp; stages 1 "
              "and 2 on the fast preset, on a dataset generated afresh), beside stage 3 on the fast preset "
              "from the same refined scene\n")
        print("| Scene | stage 3 | " + " | ".join(f"{n} PSNR | {n} SSIM" for _, n in ROWS) + " | LightFuse rescaled PSNR | SSIM |")
        print("|---" * (2 * len(ROWS) + 4) + "|")
        for p in paper:
            for label, folder in (("paper", f"{p}-paper"), ("fast", f"{p}-paper/fast")):
                if source(folder) is None:
                    print(f"| {p} | {label} | not measured yet |" + " |" * (2 * len(ROWS) + 1))
                    continue
                rows = ev(folder)["relighting"]
                print(f"| {p} | {label} | {cells(rows)}")
        print()
        for p in paper:
            note = os.path.join(res, f"{p}-paper", "note.md")
            if os.path.isfile(note):
                print(f"{p}: " + " ".join(open(note).read().split()) + "\n")

def ablation(title, variants):
    full = ev("bedroom")["relighting"]["lightfuse"]
    print(f"{title}\n")
    print("| Variant | PSNR | SSIM | rescaled PSNR | SSIM | paper PSNR | SSIM | PSNR change vs full: ours / paper |")
    print("|---|---|---|---|---|---|---|---|")
    for name, folder, paper in variants:
        if folder is not None and source(f"bedroom/{folder}") is None:
            print(f"| {name} | not measured yet | | | | {paper[0]:.2f} | {paper[1]:.3f} | |")
            continue
        row = full if folder is None else ev(f"bedroom/{folder}")["relighting"]["lightfuse"]
        d = row["raw"]["psnr_srgb_db"] - full["raw"]["psnr_srgb_db"]
        dp = paper[0] - variants[0][2][0]
        agree = "" if folder is None else (" (same direction)" if (d < 0) == (dp < 0) else " (**differs**)")
        change = "" if folder is None else f"{d:+.2f} / {dp:+.2f}{agree}"
        print(f"| {name} | {fig(row)} | {fig(row, 'rescaled')} | {paper[0]:.2f} | {paper[1]:.3f} | {change} |")
    print()

def refine_figures(title, variants):
    """Stage 2's own figures (issue 11) for the same rows: from each variant's refine.json."""
    def rj(folder):
        path = os.path.join(res, "bedroom" if folder is None else f"bedroom/{folder}", "refine.json")
        return json.load(open(path)) if os.path.isfile(path) else None
    print(f"{title}\n")
    print("| Variant | depth (mm) | normal (deg) | holes | false occlusion | light leaks |")
    print("|---|---|---|---|---|---|")
    for name, folder, _paper in variants:
        r = rj(folder)
        if r is None:
            print(f"| {name} | not measured yet | | | | |")
            continue
        b, a = r["before"], r["after"]
        pct = lambda k: f"{100 * b[k]:.2f} -> {100 * a[k]:.2f} %"
        print(f"| {name} | {1000 * b['depth_median_m']:.1f} -> {1000 * a['depth_median_m']:.1f} | "
              f"{b['normal_mean_deg']:.1f} -> {a['normal_mean_deg']:.1f} | {pct('holes')} | "
              f"{pct('false_occlusion')} | {pct('light_leaks')} |")
    print()

T3 = [("Full", None, (27.212, 0.8684)), ("w/o coverage", "t3-no-coverage", (27.067, 0.8824)),
      ("w/o scale", "t3-no-scale", (26.476, 0.8597)), ("w/o depth", "t3-no-depth", (20.030, 0.7778)),
      ("w/o normal", "t3-no-normal", (26.084, 0.8384))]
if "3" in tables:
    ablation("Table 3, stage 2's switches on bedroom", T3)
    refine_figures("Table 3's rows, stage 2's own figures (stage 1's scene -> refined: median depth error, "
                   "mean normal error, holes, false occlusion, light leaks; `lightfuse refine`'s report)", T3)
if "4" in tables:
    # The paper's spp (the paper preset's); the fast preset scales every count by a quarter.
    fast = stage_preset == "fast"
    ablation("Table 4, stage 3's switches on bedroom"
             + (" (spp as the paper names them; the fast preset runs a quarter of each)" if fast else ""), [
        ("Full (8 -> 16 -> 32 spp" + ("; fast: 2 -> 4 -> 8)" if fast else ")"), None, (27.212, 0.8684)),
        ("w/o Cycles-inspired estimator", "t4-naive", (24.789, 0.8630)),
        ("Fixed 8 spp" + (" (fast: 2)" if fast else ""), "t4-fixed8", (27.042, 0.8663)),
        ("Max 16 spp (8 -> 16" + ("; fast: 2 -> 4)" if fast else ")"), "t4-max16", (27.029, 0.8668))])
PY
mv "$table.tmp" "$table"
cat "$table"
say "tables written to $table"
