//! What `lightfuse evaluate` reports: the types of `eval.json` (Tables 1 and 2, per run and
//! per view), the rows and the selection of what to render, and `eval.md`. Apart from the
//! evaluation itself ([`super::relight`]) and its page ([`super::html`]), which both read it.

use crate::error::{Error, Result};
use crate::eval::metrics::{psnr_hdr, psnr_srgb8, ssim_srgb8};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The format tag of `eval.json`.
pub const FORMAT: &str = "lightfuse-eval/1";

/// The rows of the table, in order, with their keys in `eval.json`.
pub const ROWS: [(&str, &str); 3] = [
    ("lightfuse", "LightFuse"),
    ("baked", "Baked"),
    ("no_retracing", "No re-tracing"),
];

/// What an evaluation renders besides the LightFuse row, which it always does: the baseline
/// rows, and the runs of Table 1 (relighting) and Table 2 (synthesis). Leaving some out serves
/// ablations, which compare only LightFuse's relighting figure across variants (the baselines
/// do not depend on the switch being measured) and so need a fraction of the rendering.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Selection {
    pub baked: bool,
    pub no_retracing: bool,
    /// Table 1's runs: the test arrangement under environments no training state saw.
    pub relighting: bool,
    /// Table 2's runs: the test arrangement under each training state's recovered lighting.
    pub synthesis: bool,
}

impl Default for Selection {
    fn default() -> Selection {
        Selection::ALL
    }
}

impl Selection {
    pub const ALL: Selection = Selection {
        baked: true,
        no_retracing: true,
        relighting: true,
        synthesis: true,
    };

    /// `--rows` (keys of [`ROWS`], `-` for `_` accepted) and `--tables` ("1", "2"); "lightfuse"
    /// must be among the rows: it is what the evaluation is of.
    pub fn parse(rows: &[String], tables: &[String]) -> Result<Selection> {
        let mut s = Selection {
            baked: false,
            no_retracing: false,
            relighting: false,
            synthesis: false,
        };
        let mut lightfuse = false;
        for r in rows {
            match r.trim().replace('-', "_").as_str() {
                "lightfuse" => lightfuse = true,
                "baked" => s.baked = true,
                "no_retracing" => s.no_retracing = true,
                _ => {
                    return Err(Error::Usage(format!(
                        "--rows: expected lightfuse, baked or no-retracing, found {r:?}"
                    )))
                }
            }
        }
        if !lightfuse {
            return Err(Error::Usage(
                "--rows: expected lightfuse among the rows (the row the evaluation is of)".into(),
            ));
        }
        for t in tables {
            match t.trim() {
                "1" => s.relighting = true,
                "2" => s.synthesis = true,
                _ => {
                    return Err(Error::Usage(format!(
                        "--tables: expected 1 (relighting) or 2 (synthesis), found {t:?}"
                    )))
                }
            }
        }
        if !(s.relighting || s.synthesis) {
            return Err(Error::Usage("--tables: expected 1, 2 or both".into()));
        }
        Ok(s)
    }
}

/// What [`super::relight::evaluate`] records in the report's `denoise` when it denoises.
pub const DENOISER: &str = "Open Image Denoise 2.5 RT filter (HDR; albedo and normal guides)";

/// One image's figures.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct Metrics {
    pub psnr_srgb_db: f64,
    pub ssim_srgb: f64,
    pub psnr_hdr_db: f64,
}

impl Metrics {
    pub fn of(rendered: &[[f32; 3]], truth: &[[f32; 3]], w: u32, h: u32) -> Metrics {
        Metrics {
            psnr_srgb_db: psnr_srgb8(rendered, truth),
            ssim_srgb: ssim_srgb8(rendered, truth, w as usize, h as usize),
            psnr_hdr_db: psnr_hdr(rendered, truth),
        }
    }

    pub fn mean(all: &[Metrics]) -> Metrics {
        let n = all.len().max(1) as f64;
        Metrics {
            psnr_srgb_db: all.iter().map(|m| m.psnr_srgb_db).sum::<f64>() / n,
            ssim_srgb: all.iter().map(|m| m.ssim_srgb).sum::<f64>() / n,
            psnr_hdr_db: all.iter().map(|m| m.psnr_hdr_db).sum::<f64>() / n,
        }
    }
}

/// A row's figures: as rendered, and after the median albedo rescale (traced rows only).
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct RowFigures {
    pub raw: Metrics,
    pub rescaled: Option<Metrics>,
}

pub fn mean_rows(items: &[&BTreeMap<String, RowFigures>]) -> BTreeMap<String, RowFigures> {
    let mut out = BTreeMap::new();
    for (key, _) in ROWS {
        let rows: Vec<&RowFigures> = items.iter().filter_map(|m| m.get(key)).collect();
        if rows.is_empty() {
            continue;
        }
        let raw: Vec<Metrics> = rows.iter().map(|r| r.raw).collect();
        let scaled: Vec<Metrics> = rows.iter().filter_map(|r| r.rescaled).collect();
        out.insert(
            key.to_string(),
            RowFigures {
                raw: Metrics::mean(&raw),
                rescaled: (scaled.len() == rows.len()).then(|| Metrics::mean(&scaled)),
            },
        );
    }
    out
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ViewFigures {
    /// The Cycles frame compared against (relative to the dataset).
    pub frame: String,
    /// The comparison strip (relative to `<work>/eval`), when written.
    pub image: Option<String>,
    pub rows: BTreeMap<String, RowFigures>,
}

/// One test state under one environment.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct RunFigures {
    pub state: String,
    /// The dataset's environment file of the Cycles frames.
    pub environment: String,
    /// Synthesis runs: the training state whose lighting this is.
    pub training_state: Option<String>,
    /// What LightFuse and the other rows were lit with: the dataset's file, or the recovered
    /// environment of `training_state` in the relightable scene.
    pub lit_by: String,
    pub views: Vec<ViewFigures>,
    pub mean: BTreeMap<String, RowFigures>,
}

/// One test view's base colour against the dataset's albedo pass ([`Report::albedo_views`]).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ViewUniformity {
    pub state: String,
    pub frame: String,
    /// None when none of the view's pixels lies on a uniform surface.
    pub figures: Option<crate::eval::lighting::UniformityFigures>,
    /// Its strip (recovered base colour | albedo pass | ghost map), relative to `<work>/eval`,
    /// when written.
    pub image: Option<String>,
}

/// A training state's recovered environment against the dataset's
/// ([`crate::eval::lighting::compare_environments`]).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct StateEnvironment {
    pub state: String,
    pub figures: crate::eval::lighting::EnvFigures,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Report {
    pub format: String,
    pub dataset: String,
    pub relightable: String,
    pub baked: String,
    pub spp: u32,
    /// Indirect bounces of the traced rows (reports written before the field: the paper's 1).
    #[serde(default = "one_bounce")]
    pub bounces: u32,
    pub seed: u32,
    /// What denoised the traced rows: [`DENOISER`], or "none".
    pub denoise: String,
    /// What was rendered (reports written before the field: everything).
    #[serde(default)]
    pub selection: Selection,
    /// Per-channel median of true / recovered base colour over the test views' surface pixels.
    pub albedo_ratio: [f64; 3],
    pub albedo_pixels: usize,
    /// Ghost shadows in the test views' base colour: over surfaces whose true albedo is
    /// uniform, the share of pixels more than 15 % off their surface's median ratio
    /// ([`crate::eval::lighting::albedo_uniformity`]). Absent in reports written before the
    /// field, or when no surface qualifies.
    #[serde(default)]
    pub albedo_uniformity: Option<crate::eval::lighting::UniformityFigures>,
    /// The same figures over the pixels away from the seams between true albedos
    /// ([`crate::eval::lighting::away_from_seams`]): ghosts the light painted rather than a
    /// texture's edges blurred. Absent in reports written before the field.
    #[serde(default)]
    pub albedo_away_from_seams: Option<crate::eval::lighting::UniformityFigures>,
    /// The ghost figures taken apart by where the training states' shadows fell
    /// ([`crate::eval::shadows`]): over pixels lit in every training state, and per state over
    /// its moved shadows. Absent in reports written before the field, and for datasets without
    /// the training environments or the test views' masks.
    #[serde(default)]
    pub shadow_ghosts: Option<crate::eval::shadows::ShadowGhosts>,
    /// The ghost figures of each test view with an albedo pass (each pixel measured against
    /// its surface's median over every view, as in `albedo_uniformity`): where the ghosts
    /// are. Empty in reports written before the field.
    #[serde(default)]
    pub albedo_views: Vec<ViewUniformity>,
    /// Each training state's recovered environment against the one that lit its captures
    /// (states whose dataset has the file; empty in reports written before the field).
    #[serde(default)]
    pub environments: Vec<StateEnvironment>,
    /// Table 1: the mean over every relighting run's images.
    pub relighting: BTreeMap<String, RowFigures>,
    /// Table 2: the mean over every synthesis run's images (empty without such runs).
    pub synthesis: BTreeMap<String, RowFigures>,
    pub runs: Vec<RunFigures>,
    /// Rays traced (camera rays once per view, then the shading rays of every traced row).
    pub rays: u64,
    pub seconds: f64,
}

/// One sentence on [`Report::shadow_ghosts`], for `eval.md` and the report page: the ghost
/// share where no shadow fell against inside each training state's moved shadows.
pub fn shadow_ghosts_sentence(g: &crate::eval::shadows::ShadowGhosts) -> String {
    let fig = |f: &Option<crate::eval::lighting::UniformityFigures>| match f {
        Some(u) => format!(
            "{:.1} % ({} pixels, mean deviation {:.1} %)",
            100.0 * u.ghost_share,
            u.pixels,
            100.0 * u.spread
        ),
        None => "no pixels".into(),
    };
    let states: Vec<String> = g
        .states
        .iter()
        .map(|s| format!("{}: {}", s.state, fig(&s.figures)))
        .collect();
    format!(
        "By where the training states' shadows fell (background pixels; a state's true lighting \
         traced through the scene as stage 3 saw it): ghosts among pixels lit in every training \
         state {}; among pixels in a state's shadow and lit in another, {}.",
        fig(&g.lit),
        states.join("; ")
    )
}

/// `eval.md`: Tables 1 and 2 of this dataset.
pub fn markdown(r: &Report) -> String {
    let mut s = String::new();
    let table = |s: &mut String, title: &str, rows: &BTreeMap<String, RowFigures>| {
        s.push_str(&format!("### {title}\n\n"));
        s.push_str("| Method | PSNR ↑ | SSIM ↑ | HDR PSNR ↑ | PSNR (rescaled) | SSIM (rescaled) | HDR PSNR (rescaled) |\n");
        s.push_str("|---|---|---|---|---|---|---|\n");
        for (key, name) in ROWS {
            let Some(f) = rows.get(key) else { continue };
            let (a, b, c) = match f.rescaled {
                Some(m) => (
                    format!("{:.2}", m.psnr_srgb_db),
                    format!("{:.3}", m.ssim_srgb),
                    format!("{:.2}", m.psnr_hdr_db),
                ),
                None => ("–".into(), "–".into(), "–".into()),
            };
            s.push_str(&format!(
                "| {name} | {:.2} | {:.3} | {:.2} | {a} | {b} | {c} |\n",
                f.raw.psnr_srgb_db, f.raw.ssim_srgb, f.raw.psnr_hdr_db
            ));
        }
        s.push('\n');
    };
    s.push_str(&format!(
        "Evaluation of `{}` on `{}`: {} spp, denoising: {}; median albedo ratio {:.3}, {:.3}, {:.3} ({} pixels). PSNR and SSIM on 8-bit sRGB, HDR PSNR on scene-linear radiance with the reference's peak; means over images.\n\n",
        r.relightable, r.dataset, r.spp, r.denoise, r.albedo_ratio[0], r.albedo_ratio[1], r.albedo_ratio[2], r.albedo_pixels
    ));
    if let Some(u) = &r.albedo_uniformity {
        s.push_str(&format!(
            "Base colour over the {} surfaces of uniform true albedo ({} pixels): {:.1} % of pixels more than 15 % off their surface's median (ghost shadows), mean deviation {:.1} %.\n\n",
            u.surfaces,
            u.pixels,
            100.0 * u.ghost_share,
            100.0 * u.spread
        ));
    }
    if let Some(u) = &r.albedo_away_from_seams {
        s.push_str(&format!(
            "Away from the seams between true albedos ({} pixels at least {} from another): {:.1} % ghosts, mean deviation {:.1} %.\n\n",
            u.pixels,
            crate::eval::lighting::SEAM_PIXELS,
            100.0 * u.ghost_share,
            100.0 * u.spread
        ));
    }
    if let Some(g) = &r.shadow_ghosts {
        s.push_str(&shadow_ghosts_sentence(g));
        s.push_str("\n\n");
    }
    if !r.environments.is_empty() {
        s.push_str("Recovered environments against the truth (`docs/lighting-metrics.md`):\n\n| State | Irradiance error | Uniform map | Log error above the horizon | Uniform map | Luminous power |\n|---|---|---|---|---|---|\n");
        for e in &r.environments {
            let f = &e.figures;
            s.push_str(&format!(
                "| {} | {:.1} % | {:.1} % | {:.2} | {:.2} | {:+.0} % |\n",
                e.state,
                100.0 * f.irradiance_error,
                100.0 * f.irradiance_error_uniform,
                f.log_rmse_upper,
                f.log_rmse_upper_uniform,
                100.0 * f.power_error
            ));
        }
        s.push('\n');
    }
    if r.selection != Selection::ALL {
        let sel = r.selection;
        let rows: Vec<&str> = [
            ("LightFuse", true),
            ("Baked", sel.baked),
            ("No re-tracing", sel.no_retracing),
        ]
        .iter()
        .filter_map(|&(n, on)| on.then_some(n))
        .collect();
        let tables: Vec<&str> = [("1", sel.relighting), ("2", sel.synthesis)]
            .iter()
            .filter_map(|&(n, on)| on.then_some(n))
            .collect();
        s.push_str(&format!(
            "Rendered only: rows {}; Table {} (`--rows`, `--tables`).\n\n",
            rows.join(", "),
            tables.join(" and ")
        ));
    }
    if r.selection.relighting {
        table(
            &mut s,
            "Novel-state relighting (Table 1): the test arrangement under environments no training state saw",
            &r.relighting,
        );
    }
    if !r.synthesis.is_empty() {
        table(
            &mut s,
            "Novel-state synthesis (Table 2): the test arrangement under each training state's recovered lighting",
            &r.synthesis,
        );
    }
    s.push_str("### Per run\n\n| State | Environment | LightFuse | Baked | No re-tracing |\n|---|---|---|---|---|\n");
    for f in &r.runs {
        let db = |k: &str| {
            f.mean.get(k).map_or("–".into(), |m| {
                format!("{:.2} dB / {:.3}", m.raw.psnr_srgb_db, m.raw.ssim_srgb)
            })
        };
        let env = match &f.training_state {
            Some(t) => format!("{} (recovered, {t})", f.environment),
            None => f.environment.clone(),
        };
        s.push_str(&format!(
            "| {} | {env} | {} | {} | {} |\n",
            f.state,
            db("lightfuse"),
            db("baked"),
            db("no_retracing")
        ));
    }
    s
}

fn one_bounce() -> u32 {
    1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(s: &str) -> Vec<String> {
        s.split(',').map(str::to_string).collect()
    }

    #[test]
    fn selection_parses_rows_and_tables_and_refuses_the_rest() {
        let all = Selection::parse(&words("lightfuse,baked,no-retracing"), &words("1,2")).unwrap();
        assert_eq!(all, Selection::ALL);
        let ablation = Selection::parse(&words("lightfuse"), &words("1")).unwrap();
        assert_eq!(
            ablation,
            Selection {
                baked: false,
                no_retracing: false,
                relighting: true,
                synthesis: false
            }
        );
        assert!(
            Selection::parse(&words("no_retracing,lightfuse"), &words("2"))
                .unwrap()
                .no_retracing
        );
        for (rows, tables, what) in [
            ("baked", "1", "lightfuse among the rows"),
            ("lightfuse,cycles", "1", "found \"cycles\""),
            ("lightfuse", "3", "--tables"),
        ] {
            let e = Selection::parse(&words(rows), &words(tables)).unwrap_err();
            assert!(e.to_string().contains(what), "{e}");
        }
    }
}
