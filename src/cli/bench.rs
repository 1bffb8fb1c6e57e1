//! `lightfuse bench`: the same scene, cameras, resolution and samples rendered by LightFuse and
//! by Cycles (`blender/render_layout.py`, bounces limited to match the one-bounce estimator),
//! back to back on this machine, each timed as a whole process (load, build, render, write);
//! prints both times, their ratio and the PSNR between the two renders.

use super::{BenchArgs, Cli};
use lightfuse::error::{Error, Result};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// The checkout whose `blender/` toolkit renders the Cycles side: `--toolkit`'s parent when
/// given, else the first folder holding `blender/render_layout.py` among the executable's
/// ancestors (`target/release/lightfuse` sits in the checkout it was built from) and the
/// current folder. Found at run time, not compiled in, so a moved or installed binary works.
fn checkout(toolkit: Option<&Path>) -> Result<PathBuf> {
    const SCRIPT: &str = "blender/render_layout.py";
    if let Some(t) = toolkit {
        let root = t.parent().unwrap_or(Path::new(".")).to_path_buf();
        if !root.join(SCRIPT).is_file() {
            return Err(Error::invalid(
                t,
                "--toolkit",
                "expected LightFuse's blender/ folder (with render_layout.py)",
            ));
        }
        return Ok(root);
    }
    let exe = std::env::current_exe().ok();
    let cwd = std::env::current_dir().ok();
    exe.iter()
        .flat_map(|e| e.ancestors().skip(1))
        .chain(cwd.as_deref())
        .find(|d| d.join(SCRIPT).is_file())
        .map(Path::to_path_buf)
        .ok_or_else(|| {
            Error::Usage(format!(
                "bench: cannot find LightFuse's {SCRIPT} beside the binary or here; give its folder with --toolkit DIR/blender"
            ))
        })
}

fn run_timed(what: &str, cmd: &mut Command) -> Result<f64> {
    let start = Instant::now();
    let out = cmd
        .output()
        .map_err(|e| Error::Usage(format!("bench: cannot start {what}: {e}")))?;
    let seconds = start.elapsed().as_secs_f64();
    if !out.status.success() {
        let tail: String = String::from_utf8_lossy(&out.stderr)
            .lines()
            .rev()
            .take(5)
            .collect::<Vec<_>>()
            .into_iter()
            .rev()
            .collect::<Vec<_>>()
            .join("\n");
        return Err(Error::Usage(format!(
            "bench: {what} failed ({}):\n{tail}",
            out.status
        )));
    }
    Ok(seconds)
}

pub fn run(cli: &Cli, a: &BenchArgs) -> Result<()> {
    let dataset_json = if a.dataset.is_dir() {
        a.dataset.join("dataset.json")
    } else {
        a.dataset.clone()
    };
    let dataset = lightfuse::io::dataset::Dataset::read(&dataset_json)?;
    let k = dataset
        .states
        .iter()
        .position(|s| s.name == a.state)
        .ok_or_else(|| {
            let names: Vec<_> = dataset.states.iter().map(|s| s.name.as_str()).collect();
            Error::invalid(
                &dataset.file,
                "states",
                format!(
                    "expected a state named {:?}; the dataset has {names:?}",
                    a.state
                ),
            )
        })?;
    let frames = &dataset.states[k].frames;
    let first = frames.first().ok_or_else(|| {
        Error::invalid(
            &dataset.file,
            format!("states[{k}].frames"),
            "expected at least one frame (a training state)",
        )
    })?;
    let blend = dataset.root.join("scene.blend");
    if !blend.is_file() {
        return Err(Error::invalid(
            &blend,
            "scene.blend",
            "expected the dataset's Blender scene (written by blender/generate.py)",
        ));
    }
    let repo = checkout(a.toolkit.as_deref())?;
    let python = a
        .python
        .clone()
        .unwrap_or_else(|| repo.join(".venv/bin/python"));
    let blender = repo.join("blender");
    let work = tempfile::Builder::new()
        .prefix("lightfuse-bench")
        .tempdir()
        .map_err(|e| Error::io(std::env::temp_dir(), e))?;
    let (lf_out, cy_out) = (work.path().join("lightfuse"), work.path().join("cycles"));
    let exe = std::env::current_exe()
        .map_err(|e| Error::Usage(format!("bench: cannot find the lightfuse binary: {e}")))?;
    let spp = a.spp.to_string();
    let threads = rayon::current_num_threads().to_string();
    if !cli.quiet && !cli.json {
        eprintln!("bench: {} views of {}x{} at {} spp, {} threads: LightFuse, then Cycles (max bounces {})", frames.len(), first.camera.w, first.camera.h, a.spp, threads, a.max_bounces);
    }
    let t_lf = run_timed(
        "lightfuse render",
        Command::new(&exe)
            .arg("render")
            .arg(&a.scene)
            .args(["--state", &a.state, "--spp", &spp, "--quiet"])
            .args(["--bounces", &a.max_bounces.to_string(), "--cameras"])
            .arg(&dataset_json)
            .arg("--out")
            .arg(&lf_out),
    )?;
    let mut cycles = Command::new(&python);
    cycles
        .arg(blender.join("render_layout.py"))
        .arg("--dataset")
        .arg(&dataset.root)
        .args(["--state", &a.state, "--spp", &spp, "--max-bounces"])
        .arg(a.max_bounces.to_string())
        .args(["--threads", &threads, "--rgb-only", "--quiet", "--out"])
        .arg(&cy_out);
    if let Some(env) = &a.env {
        cycles.arg("--env").arg(env);
    }
    let t_cy = run_timed("Cycles (blender/render_layout.py)", &mut cycles)?;
    let psnr = compare(&python, &blender, &cy_out, &lf_out);
    let report = json!({
        "views": frames.len(), "width": first.camera.w, "height": first.camera.h, "spp": a.spp,
        "threads": threads, "cycles_max_bounces": a.max_bounces,
        "lightfuse_seconds": t_lf, "cycles_seconds": t_cy, "ratio_lightfuse_over_cycles": t_lf / t_cy,
        "psnr_srgb": psnr,
    });
    if cli.json {
        println!("{report}");
    } else if !cli.quiet {
        println!(
            "LightFuse {t_lf:.2} s, Cycles {t_cy:.2} s, ratio LightFuse/Cycles {:.3}",
            t_lf / t_cy
        );
        if let Some(p) = psnr.get("mean_psnr").and_then(Value::as_f64) {
            println!("PSNR (sRGB) LightFuse vs Cycles: {p:.2} dB, mean over views");
        }
    }
    Ok(())
}

/// PSNR between the two renders via `blender/compare_renders.py --json` (null when it fails:
/// the timing is the point of the bench).
fn compare(python: &Path, blender: &Path, reference: &Path, test: &Path) -> Value {
    let out = Command::new(python)
        .arg(blender.join("compare_renders.py"))
        .arg("--ref")
        .arg(reference)
        .arg("--test")
        .arg(test)
        .arg("--json")
        .output();
    match out {
        Ok(o) if o.status.success() => serde_json::from_slice::<Value>(&o.stdout)
            .map(|v| json!({"mean_psnr": v.get("psnr_all").cloned().unwrap_or(Value::Null), "mean_psnr_background": v.get("psnr_background").cloned().unwrap_or(Value::Null)}))
            .unwrap_or(Value::Null),
        _ => Value::Null,
    }
}
