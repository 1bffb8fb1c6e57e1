"""The stage-3 survey's table (scripts/stage3_survey.sh) from the results it keeps:
<results>/<scene>/<variant>/{eval.json, invert.json, time.txt, variant.txt[, note.md]}.
Plain Python (no packages): run by the survey, or alone to rewrite the table:
    python3 scripts/stage3_table.py docs/results/stage3 > docs/results/stage3-survey.md
"""

from __future__ import annotations

import json
import os
import sys

# What a variant without options ran: the fast preset of the binary it ran with.
NO_OPTIONS = {
    "default": "(the fast preset of its day: every `default` row here was measured before 2026-12-03, "
    "when the preset was the paper's method, `--papers-method` since)",
    None: "(no options: the fast preset's defaults of the binary it ran with; each row's note says which)",
}

ORDER = ["demo", "sunroom", "atelier", "bedroom", "playroom", "livingroom", "kitchen", "study", "gallery",
         "workshop"]
PLAIN = {"sunroom", "atelier"}
SECOND = {"study", "gallery", "workshop"}
# A mirror: what the generator records for chrome (metallic 1, roughness 0.05).
MIRROR_ROUGHNESS = 0.1


def load(path):
    with open(path) as f:
        return json.load(f)


def wall_seconds(path):
    total = 0.0
    if os.path.isfile(path):
        with open(path) as f:
            for line in f:
                p = line.split()
                if len(p) == 2:
                    total += float(p[0])
    return total


def mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else None


def pct(x):
    return None if x is None else 100 * x


def fmt(x, spec, unit=""):
    return "–" if x is None else f"{x:{spec}}{unit}"


def row(scene, variant, d):
    e, inv = load(os.path.join(d, "eval.json")), load(os.path.join(d, "invert.json"))
    lf = e["relighting"].get("lightfuse", {})
    raw, resc = lf.get("raw"), lf.get("rescaled")
    t2 = (e.get("synthesis") or {}).get("lightfuse", {}).get("raw")
    u = e.get("albedo_uniformity")
    alb = inv.get("albedo") or {}
    envs = [s["environment"] for s in inv["states"] if s.get("environment")]
    sg = e.get("shadow_ghosts") or {}
    shadowed = [s["figures"] for s in sg.get("states", []) if s.get("figures")]
    in_shadows = (sum(f["ghost_share"] * f["pixels"] for f in shadowed) / sum(f["pixels"] for f in shadowed)
                  if shadowed else None)
    mirrors = [m for m in inv.get("materials", [])
               if m.get("metallic_truth", 0) >= 0.9 and m.get("roughness_truth", 1) <= MIRROR_ROUGHNESS]
    return dict(
        scene=scene, variant=variant,
        t1=raw and raw["psnr_srgb_db"], ssim=raw and raw["ssim_srgb"], t1r=resc and resc["psnr_srgb_db"],
        t2=t2 and t2["psnr_srgb_db"],
        ghost=u and u["ghost_share"], spread=u and u["spread"],
        ghost_lit=(sg.get("lit") or {}).get("ghost_share"), ghost_shadows=in_shadows,
        ghost_seams=(e.get("albedo_away_from_seams") or {}).get("ghost_share"),
        alb_raw=alb.get("raw_error"), alb_scaled=alb.get("scaled_error"),
        irr=mean(v["irradiance_error"] for v in envs), irr_u=mean(v["irradiance_error_uniform"] for v in envs),
        up=mean(v.get("log_rmse_upper") for v in envs), up_u=mean(v.get("log_rmse_upper_uniform") for v in envs),
        mirrors=[(m["object"], m["metallic"], m["roughness"]) for m in mirrors],
        train=[s["training"]["psnr_srgb_db"] for s in inv["states"]],
        wall=wall_seconds(os.path.join(d, "time.txt")),
    )


def seams(r):
    """The ghost share away from the seams between true albedos, in rows evaluated since it exists."""
    return "" if r["ghost_seams"] is None else f"; off seams {100 * r['ghost_seams']:.1f} %"


def main(res):
    rows, notes = [], []
    variants = []
    for scene in ORDER:
        sd = os.path.join(res, scene)
        if not os.path.isdir(sd):
            continue
        for v in sorted(os.listdir(sd), key=lambda v: (v != "default", v)):
            d = os.path.join(sd, v)
            if not os.path.isfile(os.path.join(d, "eval.json")):
                continue
            r = row(scene, v, d)
            if os.path.isfile(os.path.join(d, "note.md")):
                with open(os.path.join(d, "note.md")) as f:
                    notes.append(f"{scene} / {v}: " + " ".join(f.read().split()))
                r["note"] = len(notes)
            rows.append(r)
            if v not in variants:
                variants.append(v)
    print("# Stage 3 on every scene: separating material from lighting\n")
    print(f"Written by `scripts/stage3_survey.sh` from the results kept in `{res}/` (do not edit by hand: "
          "a row's footnote is its `note.md` there). Machines: VMs with 2 cores, 24 GiB and no GPU.\n")
    print("Each scene at its default size; stages 1 and 2 once per scene (fast preset), then each variant's "
          "`lightfuse invert --preset fast <options>` from a copy of their outputs and `lightfuse evaluate "
          "--no-images` (32 spp, denoised); a scene's variants in one sitting. Scenes: the demo, the plain "
          "family (**bold**: untextured floors and walls, sun skies, chrome), the presets and the second family "
          "(*italic*). Columns (docs/lighting-metrics.md): Table 1 = LightFuse's novel-state relighting, PSNR / "
          "SSIM on sRGB without rescale, then PSNR after the median albedo rescale; Table 2 = the test "
          "arrangement under each training state's recovered lighting (PSNR sRGB: how well the environments "
          "light the scene); ghost = share of the test "
          "views' base colour more than 15 % off its surface's median over surfaces of uniform true albedo, "
          "then the same share among background pixels lit in every training state and among those in a "
          "training state's shadow and lit in another (`shadow_ghosts`: painted shadows show as the second "
          "far above the first; off seams = the share over pixels at least 2 px from another true albedo, so a "
          "texture's blurred edges do not count, in rows evaluated since 2026-12-07's third sitting); "
          "base colour = error against the albedo pass on the training views, raw and after the rescale; "
          "irradiance and log (upper hemisphere) = the recovered environments against the truth, mean over the "
          "training states, a uniform map's in brackets; mirrors = recovered metallic / roughness of each chrome "
          "object (truth 1 / 0.05); training = each training state's views, PSNR sRGB; wall = stage 3 alone.\n")
    print("Variants:")
    for v in variants:
        specs = set()
        for scene in ORDER:
            p = os.path.join(res, scene, v, "variant.txt")
            if os.path.isfile(p):
                with open(p) as f:
                    specs.add(f.read().strip().split("=", 1)[1].replace(",", " ") or NO_OPTIONS.get(v, NO_OPTIONS[None]))
        print(f"- `{v}`: {'; '.join(sorted(specs)) or '?'}")
    print()
    print("| Scene | Variant | Table 1 | rescaled | Table 2 | ghost (lit / shadows) | base colour raw / rescaled | irradiance (uniform) "
          "| log upper (uniform) | mirrors metallic / roughness | training views | wall |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        name = f"**{r['scene']}**" if r["scene"] in PLAIN else f"*{r['scene']}*" if r["scene"] in SECOND else r["scene"]
        mark = f" [{r['note']}]" if "note" in r else ""
        mirrors = ", ".join(f"{o} {m:.2f} / {g:.2f}" for o, m, g in r["mirrors"]) or "–"
        train = " / ".join(f"{x:.1f}" for x in r["train"])
        print(f"| {name} | {r['variant']}{mark} | {fmt(r['t1'], '.2f')} / {fmt(r['ssim'], '.3f')} "
              f"| {fmt(r['t1r'], '.2f')} | {fmt(r['t2'], '.2f')} | {fmt(pct(r['ghost']), '.1f', ' %')} "
              f"({fmt(pct(r['ghost_lit']), '.0f')} / {fmt(pct(r['ghost_shadows']), '.0f')} %{seams(r)}) "
              f"| {fmt(r['alb_raw'] and 100 * r['alb_raw'], '.1f')} / {fmt(r['alb_scaled'] and 100 * r['alb_scaled'], '.1f')} % "
              f"| {fmt(r['irr'] and 100 * r['irr'], '.1f')} % ({fmt(r['irr_u'] and 100 * r['irr_u'], '.0f')} %) "
              f"| {fmt(r['up'], '.2f')} ({fmt(r['up_u'], '.2f')}) | {mirrors} | {train} | {r['wall']:.0f} s |")
    print()
    print("Per variant, over the scenes it has (aims of issue 44 in brackets):\n")
    print("| Variant | scenes | Table 1 mean (≥ 27) / lowest (≥ 25) | ghost mean (≤ 10 %) | base colour raw, worst "
          "(≤ 10 %) | irradiance mean (≤ 10 %) | mirrors' metallic, lowest (≥ 0.7) |")
    print("|---|---|---|---|---|---|---|")
    for v in variants:
        rs = [r for r in rows if r["variant"] == v]
        t1 = [r["t1"] for r in rs if r["t1"] is not None]
        mir = [m for r in rs for _o, m, _g in r["mirrors"]]
        alb = [r["alb_raw"] for r in rs if r["alb_raw"] is not None]
        print(f"| {v} | {len(rs)} | {fmt(mean(t1), '.2f')} / {fmt(min(t1) if t1 else None, '.2f')} dB "
              f"| {fmt(mean(r['ghost'] for r in rs) and 100 * mean(r['ghost'] for r in rs), '.1f', ' %')} "
              f"| {fmt(max(alb) * 100 if alb else None, '.1f', ' %')} "
              f"| {fmt(mean(r['irr'] for r in rs) and 100 * mean(r['irr'] for r in rs), '.1f', ' %')} "
              f"| {fmt(min(mir) if mir else None, '.2f')} |")
    if notes:
        print()
        for i, n in enumerate(notes, 1):
            print(f"[{i}] {n}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python3 scripts/stage3_table.py <results folder>")
    main(sys.argv[1])
