//! `<work>/eval/report.html`: the evaluation as a page a person can open and judge — the tables,
//! every view as Cycles | LightFuse | Baked | No re-tracing | error, each recovered environment
//! beside the one that lit the captures, the recovered materials, and every stage's loss curves.
//!
//! The page is one self-contained file: styles and plots (SVG) inline, no script, no network;
//! the images are PNG files beside it (`images/`, `environments/`, `materials/`), referenced by
//! relative paths, so the folder can be copied or served as it is.
//!
//! The plots are written here as SVG polylines rather than with a plotting crate: a log-scale
//! line chart is ~80 lines of text output, and the crates that draw it (plotters & co.) bring a
//! font and raster stack this page does not need.

use crate::eval::tables::{Report, RowFigures, ROWS};
use crate::scene::Environment;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

/// An image beside the page.
#[derive(Clone, Debug)]
pub struct Figure {
    /// Path relative to the page (`/`-separated).
    pub file: String,
    pub caption: String,
}

/// One training state's lighting: what stage 3 recovered and what lit the captures.
#[derive(Clone, Debug)]
pub struct EnvironmentPair {
    pub state: String,
    pub recovered: Figure,
    pub truth: Option<Figure>,
    /// Irradiance spheres: the recovered map's, then the truth's when there is one.
    pub spheres: Vec<Figure>,
    /// The recovered map against the truth, when there is one.
    pub figures: Option<crate::eval::lighting::EnvFigures>,
}

/// One view's recovered material channels (and the dataset's albedo pass, when it has one).
#[derive(Clone, Debug)]
pub struct MaterialView {
    pub state: String,
    pub frame: String,
    pub figures: Vec<Figure>,
}

/// One stage's training log as series of (iteration, value).
#[derive(Clone, Debug)]
pub struct Curve {
    pub title: String,
    pub source: String,
    pub series: Vec<(String, Vec<(f64, f64)>)>,
}

/// Everything the page shows besides the report.
#[derive(Clone, Debug, Default)]
pub struct Assets {
    pub environments: Vec<EnvironmentPair>,
    pub materials: Vec<MaterialView>,
    pub curves: Vec<Curve>,
}

/// Keys of a stage log that are not losses.
const NOT_LOSSES: [&str; 5] = ["iteration", "surfels", "seconds", "training_seconds", "spp"];

/// Reads a stage's `log.jsonl` (one JSON object per line, `iteration` and the losses) into
/// curves; None when the file does not exist. A line that does not parse is skipped: the last
/// line of a run that was killed while writing it is the one case, and a page should still show
/// the rest.
pub fn read_curve(title: &str, path: &Path) -> Option<Curve> {
    let text = std::fs::read_to_string(path).ok()?;
    let mut series: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    for line in text.lines() {
        let Ok(serde_json::Value::Object(m)) = serde_json::from_str::<serde_json::Value>(line)
        else {
            continue;
        };
        let Some(it) = m.get("iteration").and_then(|v| v.as_f64()) else {
            continue;
        };
        for (k, v) in &m {
            if let (false, Some(v)) = (NOT_LOSSES.contains(&k.as_str()), v.as_f64()) {
                series.entry(k.clone()).or_default().push((it, v));
            }
        }
    }
    // "total" first: it is drawn heaviest.
    let mut series: Vec<(String, Vec<(f64, f64)>)> = series.into_iter().collect();
    series.sort_by_key(|(k, _)| k != "total");
    Some(Curve {
        title: title.into(),
        source: path.display().to_string(),
        series,
    })
}

/// A lat-long environment for display: box-averaged to at most 512 texels wide, exposed by its
/// own median luminance ([`latlong_exposure`]; so a map known only up to a global scale shows
/// its structure), then Reinhard's x / (1 + x) and the sRGB curve.
pub fn tonemap_latlong(env: &Environment) -> image::RgbImage {
    tonemap_latlong_exposed(env, latlong_exposure(env))
}

/// The exposure that puts a lat-long map's median luminance (over texels above zero, of the map
/// box-averaged as [`tonemap_latlong`] shows it) at 0.5 before the tone curve.
pub fn latlong_exposure(env: &Environment) -> f32 {
    let (small, _, _) = shrink(env);
    median_exposure(small.iter())
}

/// [`tonemap_latlong`] at a given exposure (a multiplier on the radiance): two maps shown at
/// one exposure can be compared pixel for pixel.
pub fn tonemap_latlong_exposed(env: &Environment, exposure: f32) -> image::RgbImage {
    let (small, w, h) = shrink(env);
    let mut out = image::RgbImage::new(w as u32, h as u32);
    for (i, p) in small.iter().enumerate() {
        out.put_pixel((i % w) as u32, (i / w) as u32, tone(p, exposure));
    }
    out
}

/// Values on a sphere image ([`crate::eval::lighting::irradiance_sphere`]), `width` wide, at a
/// given exposure with the tone curve of [`tonemap_latlong`]; pixels off the spheres white.
pub fn tonemap_sphere(px: &[Option<[f32; 3]>], width: usize, exposure: f32) -> image::RgbImage {
    let mut out = image::RgbImage::new(width as u32, (px.len() / width) as u32);
    for (i, p) in px.iter().enumerate() {
        let c = p.map_or(image::Rgb([255; 3]), |p| tone(&p, exposure));
        out.put_pixel((i % width) as u32, (i / width) as u32, c);
    }
    out
}

/// 0.5 / the median luminance of the values above zero (1 when there are none).
pub fn median_exposure<'a>(rgb: impl Iterator<Item = &'a [f32; 3]>) -> f32 {
    let lum = |p: &[f32; 3]| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2];
    let mut l: Vec<f32> = rgb.map(lum).filter(|v| *v > 0.0).collect();
    if l.is_empty() {
        return 1.0;
    }
    let mid = l.len() / 2;
    0.5 / l.select_nth_unstable_by(mid, f32::total_cmp).1.max(1e-12)
}

/// Reinhard's x / (1 + x) of exposure · p, then the sRGB curve, as bytes.
fn tone(p: &[f32; 3], exposure: f32) -> image::Rgb<u8> {
    image::Rgb(p.map(|v| {
        let x = (v * exposure).max(0.0);
        byte(crate::scene::color::srgb_encode(x / (1.0 + x)))
    }))
}

/// A lat-long map box-averaged by an integer factor to at most 512 texels wide.
fn shrink(env: &Environment) -> (Vec<[f32; 3]>, usize, usize) {
    let f = env.width.div_ceil(512).max(1);
    let (w, h) = ((env.width / f).max(1), (env.height / f).max(1));
    let mut small = vec![[0.0f32; 3]; w * h];
    for (i, p) in small.iter_mut().enumerate() {
        let (x, y) = (i % w, i / w);
        let mut n = 0.0;
        for yy in y * f..((y + 1) * f).min(env.height) {
            for xx in x * f..((x + 1) * f).min(env.width) {
                let q = env.pixels[yy * env.width + xx];
                for c in 0..3 {
                    p[c] += q[c];
                }
                n += 1.0;
            }
        }
        *p = p.map(|v| v / n);
    }
    (small, w, h)
}

/// An sRGB image of linear RGB values in [0, 1] (clamped).
pub fn srgb_image(rgb: &[[f32; 3]], w: u32, h: u32) -> image::RgbImage {
    let mut out = image::RgbImage::new(w, h);
    for (i, p) in rgb.iter().enumerate() {
        let px = p.map(crate::scene::color::srgb_byte);
        out.put_pixel(i as u32 % w, i as u32 / w, image::Rgb(px));
    }
    out
}

/// A ghost map: per pixel, how far the recovered base colour strays from the rest of its
/// uniform surface ([`crate::eval::lighting::albedo_deviation`]'s signed deviation d). Blue
/// where darker (a painted shadow), red where brighter, white where equal; within
/// [`GHOST_TOLERANCE`](crate::eval::lighting::GHOST_TOLERANCE) the colour rises to half, past
/// it (a ghost) it jumps to 60 % and saturates at twice the tolerance, so the ghosts the
/// figure counts stand out. Pixels measured on no uniform surface (`Some(None)`: a texture) are
/// mid grey, pixels not measured (`None`: sky, no albedo) black.
pub fn ghost_map(deviation: &[Option<Option<f64>>], w: u32, h: u32) -> image::RgbImage {
    let tol = crate::eval::lighting::GHOST_TOLERANCE;
    let mut out = image::RgbImage::new(w, h);
    for (i, d) in deviation.iter().enumerate() {
        let px = match d {
            None => [0; 3],
            Some(None) => [128; 3],
            Some(Some(d)) => {
                let a = d.abs();
                let t = if a <= tol {
                    0.5 * a / tol
                } else {
                    0.6 + 0.4 * ((a - tol) / tol).min(1.0)
                };
                let hue: [f64; 3] = if *d < 0.0 {
                    [30.0, 80.0, 255.0]
                } else {
                    [255.0, 50.0, 30.0]
                };
                hue.map(|c| (255.0 + t * (c - 255.0)).round() as u8)
            }
        };
        out.put_pixel(i as u32 % w, i as u32 / w, image::Rgb(px));
    }
    out
}

/// A grey image of values in [0, 1] shown as they are (roughness, metallic).
pub fn grey_image(values: &[f32], w: u32, h: u32) -> image::RgbImage {
    let mut out = image::RgbImage::new(w, h);
    for (i, v) in values.iter().enumerate() {
        out.put_pixel(i as u32 % w, i as u32 / w, image::Rgb([byte(*v); 3]));
    }
    out
}

fn byte(v: f32) -> u8 {
    (v * 255.0).round().clamp(0.0, 255.0) as u8
}

/// Escapes text for HTML content and attribute values.
fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            c => o.push(c),
        }
    }
    o
}

fn table(s: &mut String, title: &str, rows: &BTreeMap<String, RowFigures>) {
    let _ = write!(
        s,
        "<h3>{}</h3>\n<table><thead><tr><th>Method</th><th>PSNR ↑</th><th>SSIM ↑</th>\
         <th>HDR PSNR ↑</th><th>PSNR (rescaled)</th><th>SSIM (rescaled)</th>\
         <th>HDR PSNR (rescaled)</th></tr></thead><tbody>\n",
        esc(title)
    );
    for (key, name) in ROWS {
        let Some(f) = rows.get(key) else { continue };
        let rescaled = match f.rescaled {
            Some(m) => format!(
                "<td>{:.2}</td><td>{:.3}</td><td>{:.2}</td>",
                m.psnr_srgb_db, m.ssim_srgb, m.psnr_hdr_db
            ),
            None => "<td>–</td><td>–</td><td>–</td>".into(),
        };
        let _ = writeln!(
            s,
            "<tr><td>{name}</td><td>{:.2}</td><td>{:.3}</td><td>{:.2}</td>{rescaled}</tr>",
            f.raw.psnr_srgb_db, f.raw.ssim_srgb, f.raw.psnr_hdr_db
        );
    }
    s.push_str("</tbody></table>\n");
}

fn figure(s: &mut String, f: &Figure) {
    let _ = write!(
        s,
        "<figure><img src=\"{}\" alt=\"{}\" loading=\"eager\"><figcaption>{}</figcaption></figure>",
        esc(&f.file),
        esc(&f.caption),
        esc(&f.caption)
    );
}

const COLOURS: [&str; 8] = [
    "#111111", "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf",
];

/// A line chart of `curve`: iteration on x, the losses on a log y axis (non-positive values,
/// which a log axis cannot show, are left out).
pub fn svg_plot(curve: &Curve) -> String {
    let (w, h) = (640.0, 260.0);
    let (l, r, t, b) = (58.0, 150.0, 14.0, 34.0);
    let points = curve
        .series
        .iter()
        .flat_map(|(_, p)| p.iter().filter(|(_, v)| *v > 0.0 && v.is_finite()));
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in points {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y.log10());
        y1 = y1.max(y.log10());
    }
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
         viewBox=\"0 0 {w} {h}\" role=\"img\" aria-label=\"{}\">",
        esc(&curve.title)
    );
    if x0 > x1 {
        s.push_str("<text x=\"10\" y=\"20\">no positive losses logged</text></svg>");
        return s;
    }
    let (y0, y1) = (y0.floor(), y1.ceil().max(y0.floor() + 1.0));
    let x1 = if x1 > x0 { x1 } else { x0 + 1.0 };
    let px = |x: f64| l + (x - x0) / (x1 - x0) * (w - l - r);
    let py = |y: f64| t + (y1 - y.log10()) / (y1 - y0) * (h - t - b);
    let _ = write!(
        s,
        "<rect x=\"{l}\" y=\"{t}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#999\"/>",
        w - l - r,
        h - t - b
    );
    for e in (y0 as i32)..=(y1 as i32) {
        let y = py(10f64.powi(e));
        let _ = write!(
            s,
            "<line x1=\"{l}\" x2=\"{}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#ddd\"/>\
             <text x=\"{}\" y=\"{:.1}\" font-size=\"11\" text-anchor=\"end\">1e{e}</text>",
            w - r,
            l - 4.0,
            y + 4.0
        );
    }
    for k in 0..=4 {
        let x = x0 + (x1 - x0) * k as f64 / 4.0;
        let _ = write!(
            s,
            "<text x=\"{:.1}\" y=\"{}\" font-size=\"11\" text-anchor=\"middle\">{:.0}</text>",
            px(x),
            h - b + 14.0,
            x
        );
    }
    let _ = write!(
        s,
        "<text x=\"{:.1}\" y=\"{}\" font-size=\"11\" text-anchor=\"middle\">iteration</text>",
        l + (w - l - r) / 2.0,
        h - 4.0
    );
    for (i, (name, pts)) in curve.series.iter().enumerate() {
        let colour = COLOURS[i % COLOURS.len()];
        let line: Vec<String> = pts
            .iter()
            .filter(|(_, v)| *v > 0.0 && v.is_finite())
            .map(|&(x, y)| format!("{:.1},{:.1}", px(x), py(y)))
            .collect();
        let width = if name == "total" { 2.2 } else { 1.2 };
        let y = t + 8.0 + 15.0 * i as f64;
        let _ = write!(
            s,
            "<polyline fill=\"none\" stroke=\"{colour}\" stroke-width=\"{width}\" points=\"{}\"/>\
             <line x1=\"{}\" x2=\"{}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"{colour}\" stroke-width=\"{width}\"/>\
             <text x=\"{}\" y=\"{:.1}\" font-size=\"11\">{}</text>",
            line.join(" "),
            w - r + 8.0,
            w - r + 26.0,
            w - r + 30.0,
            y + 4.0,
            esc(name),
        );
    }
    s.push_str("</svg>");
    s
}

const STYLE: &str =
    "body{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}\
table{border-collapse:collapse;margin:8px 0 20px}td,th{border:1px solid #ccc;padding:4px 10px;\
text-align:right}td:first-child,th:first-child{text-align:left}figure{display:inline-block;\
margin:0 12px 12px 0;vertical-align:top}figure img{image-rendering:pixelated;display:block;\
max-width:100%}figcaption{font-size:12px;color:#555;max-width:640px}.cols{display:grid;\
grid-template-columns:repeat(5,1fr);font-size:12px;color:#555;text-align:center}\
.view{display:inline-block;width:960px;max-width:100%;margin:0 16px 16px 0;\
vertical-align:top}.view img{width:100%;image-rendering:pixelated;display:block}.env img{width:384px}\
.mat img{width:256px}.ghost{display:inline-block;width:576px;max-width:100%;\
margin:0 16px 16px 0;vertical-align:top}.ghost .cols{grid-template-columns:repeat(3,1fr)}\
.ghost img{width:100%;image-rendering:pixelated;display:block}code{font-size:90%}";

/// The section of every test view's base colour beside the albedo pass and its ghost map,
/// the worst views named first.
fn albedo_views(s: &mut String, views: &[crate::eval::tables::ViewUniformity]) {
    let tol = 100.0 * crate::eval::lighting::GHOST_TOLERANCE;
    s.push_str(
        "<h2>Base colour against the albedo pass</h2>\n<p>Every test view with an albedo pass: \
         the recovered base colour at each pixel centre's first hit, Cycles' albedo pass, and \
         the ghost map: on each surface of uniform true albedo, how far the base colour (over \
         the truth) strays from that surface's median over all views. Blue is darker than the \
         rest of the surface (a training state's shadow painted in), red brighter, white equal; \
         ",
    );
    let _ = write!(
        s,
        "the colour jumps where a pixel passes {tol:.0} % (a ghost, as counted above). Grey: a \
         textured surface (not measured), black: nothing measured.",
    );
    let mut worst: Vec<(&str, f64)> = views
        .iter()
        .filter_map(|v| {
            v.figures
                .as_ref()
                .map(|f| (v.frame.as_str(), f.ghost_share))
        })
        .collect();
    worst.sort_by(|a, b| b.1.total_cmp(&a.1));
    if !worst.is_empty() {
        let named: Vec<String> = worst
            .iter()
            .take(3)
            .map(|(f, g)| format!("{} ({:.1} %)", esc(f), 100.0 * g))
            .collect();
        let _ = write!(s, " Most ghosts: {}.", named.join(", "));
    }
    s.push_str("</p>\n");
    for v in views {
        let Some(img) = &v.image else { continue };
        let caption = match &v.figures {
            Some(f) => format!(
                "{}: ghosts {:.1} % of {} pixels on {} uniform surfaces, mean deviation {:.1} %",
                v.frame,
                100.0 * f.ghost_share,
                f.pixels,
                f.surfaces,
                100.0 * f.spread
            ),
            None => format!("{}: no pixel on a uniform surface", v.frame),
        };
        let _ = writeln!(
            s,
            "<div class=\"ghost\"><div class=\"cols\"><span>base colour</span><span>albedo \
             pass</span><span>ghost map</span></div><img src=\"{}\" alt=\"{}\" \
             loading=\"eager\"><figcaption>{}</figcaption></div>",
            esc(img),
            esc(&v.frame),
            esc(&caption)
        );
    }
}

/// The page.
pub fn page(r: &Report, a: &Assets) -> String {
    let mut s = String::new();
    let _ = write!(
        s,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>LightFuse evaluation: {}</title><style>{STYLE}</style></head><body>\n\
         <h1>LightFuse evaluation</h1>\n<p>Dataset <code>{}</code>; relightable scene \
         <code>{}</code>; baked scene <code>{}</code>. {} spp, denoising: {}. Median albedo \
         ratio {:.3}, {:.3}, {:.3} over {} pixels. PSNR and SSIM on 8-bit sRGB, HDR PSNR on \
         scene-linear radiance with the reference's peak; means over images. {} rays, {:.0} s.{}\
         </p>\n",
        esc(&r.dataset),
        esc(&r.dataset),
        esc(&r.relightable),
        esc(&r.baked),
        r.spp,
        esc(&r.denoise),
        r.albedo_ratio[0],
        r.albedo_ratio[1],
        r.albedo_ratio[2],
        r.albedo_pixels,
        r.rays,
        r.seconds,
        r.albedo_uniformity
            .as_ref()
            .map_or(String::new(), |u| format!(
            " Base colour over the {} surfaces of uniform true albedo: {:.1} % of their {} pixels \
             more than 15 % off their surface's median (ghost shadows), mean deviation {:.1} %.",
            u.surfaces,
            100.0 * u.ghost_share,
            u.pixels,
            100.0 * u.spread
        )),
    );
    if let Some(u) = &r.albedo_away_from_seams {
        let _ = writeln!(
            s,
            "<p>Away from the seams between true albedos ({} pixels at least {} from another, \
             so a texture's blurred edges do not count): {:.1} % ghosts, mean deviation \
             {:.1} %.</p>",
            u.pixels,
            crate::eval::lighting::SEAM_PIXELS,
            100.0 * u.ghost_share,
            100.0 * u.spread
        );
    }
    if let Some(g) = &r.shadow_ghosts {
        let _ = writeln!(
            s,
            "<p>{}</p>",
            esc(&crate::eval::tables::shadow_ghosts_sentence(g))
        );
    }
    table(
        &mut s,
        "Novel-state relighting (Table 1): the test arrangement under environments no training \
         state saw",
        &r.relighting,
    );
    if !r.synthesis.is_empty() {
        table(
            &mut s,
            "Novel-state synthesis (Table 2): the test arrangement under each training state's \
             recovered lighting",
            &r.synthesis,
        );
    }

    s.push_str("<h2>Views</h2>\n");
    for run in &r.runs {
        let lit = match &run.training_state {
            Some(t) => format!("{} (the recovered lighting of {t})", run.environment),
            None => run.environment.clone(),
        };
        let _ = write!(s, "<h3>{} under {}</h3>\n<p>", esc(&run.state), esc(&lit));
        for (key, name) in ROWS {
            if let Some(m) = run.mean.get(key) {
                let _ = write!(
                    s,
                    "{name}: {:.2} dB / {:.3}. ",
                    m.raw.psnr_srgb_db, m.raw.ssim_srgb
                );
            }
        }
        s.push_str("</p>\n");
        for v in &run.views {
            let Some(img) = &v.image else { continue };
            let figs: Vec<String> = ROWS
                .iter()
                .filter_map(|(k, n)| {
                    v.rows
                        .get(*k)
                        .map(|m| format!("{n} {:.2} dB", m.raw.psnr_srgb_db))
                })
                .collect();
            // The strip's columns (see `relight::strip`): a row left out is a grey tile.
            let col = |key: &str, name: &str| {
                if v.rows.contains_key(key) {
                    name.to_string()
                } else {
                    format!("{name} (not rendered)")
                }
            };
            let _ = writeln!(
                s,
                "<div class=\"view\"><div class=\"cols\"><span>Cycles</span><span>LightFuse\
                 </span><span>{}</span><span>{}</span><span>4× |LightFuse − \
                 Cycles|</span></div><img src=\"{}\" alt=\"{}\" loading=\"eager\">\
                 <figcaption>{}: {}</figcaption></div>",
                col("baked", "Baked"),
                col("no_retracing", "No re-tracing"),
                esc(img),
                esc(&v.frame),
                esc(&v.frame),
                esc(&figs.join(", "))
            );
        }
    }
    if r.runs
        .iter()
        .all(|run| run.views.iter().all(|v| v.image.is_none()))
    {
        s.push_str("<p>No view images (evaluated with <code>--no-images</code>).</p>\n");
    }

    if !a.environments.is_empty() {
        s.push_str(
            "<h2>Recovered environments</h2>\n<p>Each training state's environment as stage 3 \
             recovered it, beside the one that lit the captures, at one exposure: the recovered \
             map (known up to a global scale, traded with the base colour) is brought to the \
             truth's luminous power, then both are exposed by the truth's median luminance, \
             Reinhard-tone-mapped, sRGB; lat-long, the map's centre is +X, up is +Y. Below each \
             pair, a white matte sphere lit by each map (seen from +X and from −X; the same gain, \
             both exposed by the truth sphere's median): the light a diffuse surface receives, \
             which is what relighting needs of the map. Without the truth, the recovered map at \
             its own exposure.</p>\n",
        );
        for e in &a.environments {
            let _ = write!(s, "<div class=\"env\"><h3>{}</h3>", esc(&e.state));
            if let Some(f) = &e.figures {
                let _ = write!(
                    s,
                    "<p>Irradiance error {:.1} % (a uniform map: {:.1} %); log error above the \
                     horizon {:.2} (uniform: {:.2}), whole sphere {:.2} (uniform: {:.2}); \
                     luminous power {:+.0} %.</p>",
                    100.0 * f.irradiance_error,
                    100.0 * f.irradiance_error_uniform,
                    f.log_rmse_upper,
                    f.log_rmse_upper_uniform,
                    f.log_rmse,
                    f.log_rmse_uniform,
                    100.0 * f.power_error
                );
            }
            figure(&mut s, &e.recovered);
            if let Some(t) = &e.truth {
                figure(&mut s, t);
            }
            s.push_str("<br>");
            for f in &e.spheres {
                figure(&mut s, f);
            }
            s.push_str("</div>\n");
        }
    }
    if r.albedo_views.iter().any(|v| v.image.is_some()) {
        albedo_views(&mut s, &r.albedo_views);
    }
    if !a.materials.is_empty() {
        s.push_str(
            "<h2>Recovered materials</h2>\n<p>Roughness and metallic (grey, 0 black to 1 \
             white) of the relightable scene in the test arrangement, at each pixel centre's \
             first hit, for one view per state; its base colour (sRGB) too when the dataset has \
             no albedo pass (with one, every view's is above).</p>\n",
        );
        for m in &a.materials {
            let _ = write!(
                s,
                "<div class=\"mat\"><h3>{}: {}</h3>",
                esc(&m.state),
                esc(&m.frame)
            );
            for f in &m.figures {
                figure(&mut s, f);
            }
            s.push_str("</div>\n");
        }
    }
    if !a.curves.is_empty() {
        s.push_str("<h2>Loss curves</h2>\n");
        for c in &a.curves {
            let _ = writeln!(
                s,
                "<h3>{}</h3><p><code>{}</code></p>{}",
                esc(&c.title),
                esc(&c.source),
                svg_plot(c)
            );
        }
    }
    s.push_str("</body></html>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ghost_maps_colour_by_sign_and_jump_at_the_tolerance() {
        let tol = crate::eval::lighting::GHOST_TOLERANCE;
        let d = [
            None,
            Some(None),
            Some(Some(0.0)),
            Some(Some(-tol)),
            Some(Some(-tol - 1e-6)),
            Some(Some(3.0 * tol)),
        ];
        let img = ghost_map(&d, 6, 1);
        let px = |x| img.get_pixel(x, 0).0;
        assert_eq!((px(0), px(1), px(2)), ([0; 3], [128; 3], [255; 3]));
        // Darker than the surface: blue, half way at the tolerance, 60 % just past it.
        assert_eq!(px(3), [143, 168, 255]);
        assert_eq!(px(4), [120, 150, 255]);
        // Brighter by twice the tolerance or more: the full red.
        assert_eq!(px(5), [255, 50, 30]);
    }

    #[test]
    fn text_is_escaped_and_plots_are_well_formed() {
        assert_eq!(esc("a<b & \"c\"'"), "a&lt;b &amp; &quot;c&quot;&#39;");
        let c = Curve {
            title: "t<1>".into(),
            source: "x".into(),
            series: vec![
                ("total".into(), vec![(0.0, 1.0), (50.0, 0.1), (100.0, 0.01)]),
                ("zero".into(), vec![(0.0, 0.0)]),
            ],
        };
        let svg = svg_plot(&c);
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>"));
        assert!(svg.contains("t&lt;1&gt;") && svg.contains("1e-2") && svg.contains("1e0"));
        // The three points span the plot: x from the left edge to the right one.
        assert!(svg.contains("points=\"58.0,14.0 "), "{svg}");
        let empty = Curve {
            series: vec![],
            ..c
        };
        assert!(svg_plot(&empty).contains("no positive losses"));
    }

    #[test]
    fn environments_are_shown_at_most_512_wide_with_their_own_exposure() {
        let mut px = vec![[1.0f32, 1.0, 1.0]; 1024 * 512];
        px[0] = [1e4, 0.0, 0.0]; // a sun: box-averaged with its neighbours, saturates red
        let env = Environment::new("e", 1024, 512, px.clone());
        let img = tonemap_latlong(&env);
        assert_eq!(img.dimensions(), (512, 256));
        // Median luminance 1 -> exposure 0.5 -> Reinhard 1/3 -> sRGB 0.61 -> 156.
        assert_eq!(img.get_pixel(100, 100).0, [156; 3]);
        assert_eq!(img.get_pixel(0, 0).0[0], 255);
        // The same map 100x brighter looks the same: each map has its own exposure.
        let bright = Environment::new(
            "b",
            1024,
            512,
            px.iter().map(|p| p.map(|v| v * 100.0)).collect(),
        );
        let b = tonemap_latlong(&bright);
        let most = b
            .as_raw()
            .iter()
            .zip(img.as_raw())
            .map(|(p, q)| p.abs_diff(*q))
            .max();
        assert!(most <= Some(1), "{most:?}"); // f32 rounding of the exposure, at most
    }

    #[test]
    fn a_log_with_a_torn_last_line_still_plots() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("log.jsonl");
        std::fs::write(
            &p,
            "{\"iteration\":10,\"surfels\":5,\"total\":2.0,\"l1\":1.5}\n\
             {\"iteration\":20,\"surfels\":5,\"total\":1.0,\"l1\":0.5}\n{\"iterat",
        )
        .unwrap();
        let c = read_curve("stage", &p).unwrap();
        assert_eq!(c.series[0].0, "total");
        assert_eq!(c.series[0].1, vec![(10.0, 2.0), (20.0, 1.0)]);
        assert_eq!(c.series[1], ("l1".into(), vec![(10.0, 1.5), (20.0, 0.5)]));
        assert!(read_curve("none", &dir.path().join("missing")).is_none());
    }
}
