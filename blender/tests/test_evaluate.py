"""`lightfuse evaluate` and `lightfuse run` end to end on the tiny generated dataset: the test
state's arrangement under each unseen environment (Table 1) and under each training state's
recovered lighting (Table 2), three rows (LightFuse, Baked, No re-tracing) against the Cycles
frames, eval.json / eval.md / a comparison strip per view / report.html (opened in headless
Chromium); `run` skips the stages whose outputs
are up to date, and a partial evaluation (`--rows`, `--tables`) keeps LightFuse's figures; bad input is one clear error with exit code 2 and nothing written. (The figures
are measured on the demo and reported in the README; `tests/evaluate.rs` checks the pieces.)"""
import json
import math
import shutil

import numpy as np
from PIL import Image

from bltest import ok, run, stages
from browser import open_page

ROWS = {"lightfuse", "baked", "no_retracing"}


def work_with_stage3(tiny_dataset, tmp_path):
    work = stages(tiny_dataset, tmp_path, refine=True)
    ok("--quiet", "invert", tiny_dataset["path"], work, "--iterations", "4", "--eval-spp", "1",
       "--eval-stride", "4")
    return work


def test_run_skips_finished_stages_and_evaluate_writes_both_tables(tiny_dataset, tmp_path):
    ds = tiny_dataset["path"]
    work = work_with_stage3(tiny_dataset, tmp_path)
    relightable = (work / "relightable.glb").read_bytes()
    p = run("run", ds, "-o", work)
    assert p.returncode == 0, p.stderr
    for stage in ("stage 1: reconstruct", "stage 2: refine", "stage 3: invert"):
        assert f"{stage}: skipped (up to date)" in p.stderr, p.stderr
    assert "evaluate: ran" in p.stderr and "Table 1" in p.stdout, p.stderr
    assert (work / "relightable.glb").read_bytes() == relightable
    assert json.loads((work / "run.json").read_text())["preset"] == "fast"
    # Now everything is up to date.
    p = run("run", ds, "-o", work)
    assert p.returncode == 0 and "evaluate: skipped (up to date)" in p.stderr, p.stderr
    # Stage 3's options given to `run` are compared with what its report records: the same
    # values keep it (options not given are not compared: `invert`'s --iterations 4 counts).
    # (stage 3's defaults, spelled out: l2, four bounces, the light fit)
    p = run("run", ds, "-o", work, "--iterations", "4", "--loss", "l2", "--bounces", "4",
            "--light-fit")
    assert p.returncode == 0 and "stage 3: invert: skipped (up to date)" in p.stderr, p.stderr

    assert "Open Image Denoise" in json.loads((work / "eval" / "eval.json").read_text())["denoise"]
    check_report_in_browser(work / "eval")
    # An evaluation made with the other denoising setting is out of date.
    p = run("run", ds, "-o", work, "--no-denoise")
    assert p.returncode == 0 and "evaluate: ran" in p.stderr, p.stderr
    assert json.loads((work / "eval" / "eval.json").read_text())["denoise"] == "none"

    report = json.loads(ok("--json", "evaluate", ds, work, "--spp", "2"))
    assert report["format"] == "lightfuse-eval/1" and report["spp"] == 2
    assert "Open Image Denoise" in report["denoise"], report["denoise"]
    test = next(s for s in tiny_dataset["json"]["states"] if s["split"] == "test")
    assert len(report["runs"]) == len(test["relight"])
    synthesis = [r for r in report["runs"] if r["training_state"]]
    assert [r["training_state"] for r in synthesis] == ["state0", "state1"]
    assert all(r["lit_by"].startswith("recovered") for r in synthesis)
    assert all(r["lit_by"].startswith("dataset") for r in report["runs"] if not r["training_state"])
    assert set(report["relighting"]) == ROWS and set(report["synthesis"]) == ROWS
    assert report["relighting"]["baked"]["rescaled"] is None
    assert all(v > 0 for v in report["albedo_ratio"]) and report["albedo_pixels"] > 0
    for r in report["runs"]:
        assert len(r["views"]) == len(test["relight"][0]["frames"])
        for v in r["views"]:
            assert set(v["rows"]) == ROWS
            assert (work / "eval" / v["image"]).is_file()
            for row in v["rows"].values():
                for m in [row["raw"]] + ([row["rescaled"]] if row["rescaled"] else []):
                    assert math.isfinite(m["psnr_srgb_db"]) and -1 <= m["ssim_srgb"] <= 1, m
    md = (work / "eval" / "eval.md").read_text()
    assert "Table 1" in md and "Table 2" in md and "No re-tracing" in md

    # An ablation's evaluation: LightFuse alone, Table 1's runs only. Each row draws its own
    # samples, so the LightFuse figures are the full evaluation's to the bit; `run` counts the
    # partial report as out of date.
    part = json.loads(ok("--json", "evaluate", ds, work, "--spp", "2", "--rows", "lightfuse",
                         "--tables", "1", "--no-images"))
    assert set(part["relighting"]) == {"lightfuse"} and part["synthesis"] == {}, part["synthesis"]
    relit = [r for r in report["runs"] if not r["training_state"]]
    assert [r["environment"] for r in part["runs"]] == [r["environment"] for r in relit]
    assert part["relighting"]["lightfuse"] == report["relighting"]["lightfuse"]
    assert all(set(v["rows"]) == {"lightfuse"} for r in part["runs"] for v in r["views"])
    assert "Rendered only: rows LightFuse; Table 1" in (work / "eval" / "eval.md").read_text()
    p = run("run", ds, "-o", work, "--no-denoise")
    assert p.returncode == 0 and "evaluate: ran" in p.stderr, p.stderr


def check_report_in_browser(eval_dir):
    """report.html in headless Chromium: the tables, every image (view strips, environments,
    materials) loaded, the loss curves drawn, and a screenshot that is not blank; then with one
    image removed, the browser reports exactly that one missing (so the check can fail)."""
    report = json.loads((eval_dir / "eval.json").read_text())
    strips = [v["image"] for r in report["runs"] for v in r["views"]]
    page = open_page(eval_dir / "report.html")
    assert page.title.startswith("LightFuse evaluation"), page.title
    assert page.tables >= 2, page.tables  # Tables 1 and 2
    srcs = [i[0] for i in page.images]
    assert set(strips) <= set(srcs), (strips, srcs)
    assert any(s.startswith("environments/") and s.endswith("-recovered.png") for s in srcs), srcs
    assert any(s.startswith("environments/") and s.endswith("-truth.png") for s in srcs), srcs
    # Each training state's irradiance spheres, and its figures against the truth in eval.json.
    trained = [e["state"] for e in report["environments"]]
    assert trained, report.keys()
    for st in trained:
        for kind in ("recovered-irradiance", "truth-irradiance"):
            assert f"environments/{st}-{kind}.png" in srcs, srcs
    for e in report["environments"]:
        f = e["figures"]
        assert 0.0 <= f["irradiance_error"] and f["irradiance_error_uniform"] > 0.0, e
    assert "Irradiance error" in (eval_dir / "report.html").read_text()
    ball = np.asarray(Image.open(eval_dir / f"environments/{trained[0]}-truth-irradiance.png"))
    h, w, _ = ball.shape
    assert w == 2 * h and (ball[0, 0] == 255).all(), ball.shape  # two discs, white outside
    assert (ball[h // 2, [h // 2, w - h // 2]] < 255).any(axis=1).all(), "a sphere is blank"
    for m in ("roughness", "metallic"):
        assert any(s.startswith("materials/") and s.endswith(f"-{m}.png") for s in srcs), srcs
    # Every test view with an albedo pass: base colour | albedo pass | ghost map, and its ghost
    # figures; the map's pixels are coloured where the view has a uniform surface.
    assert "albedo_away_from_seams" in report, report.keys()
    views = report["albedo_views"]
    assert views and all(v["image"] in srcs for v in views), (views, srcs)
    for v in views:
        strip = np.asarray(Image.open(eval_dir / v["image"]).convert("RGB"))
        third = strip[:, 2 * strip.shape[1] // 3:]
        if v["figures"] is not None:
            f = v["figures"]
            assert f["pixels"] > 0 and 0.0 <= f["ghost_share"] <= 1.0, v
            assert (third.min(axis=2) > 128).any(), "no measured pixel drawn white to coloured"
    assert "Base colour against the albedo pass" in (eval_dir / "report.html").read_text()
    broken = [i for i in page.images if not i[1]]
    assert not broken, broken
    assert page.svgs >= 1, "no loss curve drawn"
    shot = page.screenshot.astype(float)
    ink = (shot.min(axis=2) < 200).mean()  # share of pixels that are not (near) white
    assert shot.std() > 20 and ink > 0.05, (shot.std(), ink)

    gone = eval_dir / strips[0]
    kept = gone.read_bytes()
    gone.unlink()
    try:
        broken = [i[0] for i in open_page(eval_dir / "report.html").images if not i[1]]
    finally:
        gone.write_bytes(kept)
    assert broken == [strips[0]], broken


def test_evaluate_bad_input_is_one_clear_error_and_writes_nothing(tiny_dataset, tmp_path):
    ds = tiny_dataset["path"]
    work = stages(tiny_dataset, tmp_path)
    p = run("evaluate", ds, work)
    assert p.returncode == 2 and "relightable.glb" in p.stderr and "invert" in p.stderr, p.stderr
    assert "panicked" not in p.stderr and not (work / "eval").exists()

    # A dataset without a test state has nothing to compare against.
    other = tmp_path / "no_test"
    shutil.copytree(ds, other)
    d = json.loads((other / "dataset.json").read_text())
    d["states"] = [s for s in d["states"] if s["split"] != "test"]
    (other / "dataset.json").write_text(json.dumps(d))
    for args in (("evaluate", other, work), ("run", other, "-o", tmp_path / "w2")):
        p = run(*args)
        assert p.returncode == 2 and "test state" in p.stderr and "panicked" not in p.stderr, p.stderr
    assert not (work / "eval").exists() and not (tmp_path / "w2").exists()
    p = run("evaluate", ds, work, "--spp", "0")
    assert p.returncode == 2 and "--spp" in p.stderr, p.stderr
    for args, what in ((("--rows", "baked"), "lightfuse among the rows"),
                       (("--tables", "3"), "--tables")):
        p = run("evaluate", ds, work, *args)
        assert p.returncode == 2 and what in p.stderr and "panicked" not in p.stderr, p.stderr
    p = run("run", ds, "-o", tmp_path / "w3", "--loss", "l3")
    assert p.returncode == 2 and "--loss" in p.stderr and not (tmp_path / "w3").exists(), p.stderr
    # Stage 3's options reach `run` as `invert` has them, checked before any stage runs.
    p = run("run", ds, "-o", tmp_path / "w4", "--light-fit", "--bounces", "9")
    assert p.returncode == 2 and "--bounces" in p.stderr and not (tmp_path / "w4").exists(), p.stderr
