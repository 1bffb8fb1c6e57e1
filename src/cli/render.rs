//! `lightfuse render`: path-traced images of a scene in a state or layout, under a state's or a
//! given environment, for a set of cameras (the one-bounce estimator of
//! [`lightfuse::shade::estimator`]).
//!
//! Output, per camera, named after the frame's file stem (`state0/rgb/000.exr` → `000`; when two
//! selected frames share a stem, the frame's path with `/` → `_`):
//! - `<name>.exr`: float channels `R, G, B` (radiance, scene-linear Rec.709, the environment
//!   included behind partial coverage), `A` (mean coverage), `Z` (planar depth, docs/design.md §2; 0 = no
//!   hit), `N.X, N.Y, N.Z` (unit world normal facing the camera), `albedo.R/G/B` (base colour);
//!   the AOVs come from the record at the pixel centre;
//! - `<name>.png`: an 8-bit sRGB preview of R, G, B (clamped to [0, 1], sRGB OETF).
//!
//! With `--denoise`, R, G, B are Open Image Denoise's estimate (HDR, guided by the albedo and
//! normal AOVs, [`lightfuse::shade::denoise::denoise_render`]); the AOVs are unchanged.
//!
//! Frame k of the selection uses the Sobol streams `Sampler::new(y·w + x, seed + k)`.

use super::{Cli, RenderArgs};
use lightfuse::error::{Error, Result};
use lightfuse::io::cameras::read_views;
use lightfuse::io::exr::Channels;
use lightfuse::scene::color::srgb_byte;
use lightfuse::scene::{Environment, Scene, State};
use lightfuse::shade::denoise::denoise_render;
use lightfuse::shade::estimator::{Estimator, PixelFilter};
use lightfuse::shade::render::{environment_image, render_image, Aovs, RenderedImage};
use lightfuse::shade::EnvMap;
use lightfuse::trace::TraceScene;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub fn run(cli: &Cli, a: &RenderArgs) -> Result<()> {
    if a.spp == 0 || a.spp > lightfuse::shade::sobol::MAX_SAMPLES {
        return Err(Error::Usage(format!(
            "--spp: expected 1 ..= {}, found {}",
            lightfuse::shade::sobol::MAX_SAMPLES,
            a.spp
        )));
    }
    if !a.filter_width.is_finite() || a.filter_width < 0.0 {
        return Err(Error::Usage(format!(
            "--filter-width: expected a width >= 0 pixels, found {}",
            a.filter_width
        )));
    }
    if a.denoise && a.baked {
        return Err(Error::Usage(
            "--denoise: a --baked render is splatted and has no noise to remove".into(),
        ));
    }
    if a.denoise {
        lightfuse::shade::denoise::require("")?;
    }
    let scene = lightfuse::io::read_scene(&a.scene)?;
    let state = select_state(&scene, a)?;
    if a.baked {
        return render_baked(cli, a, &scene, &state);
    }
    let (environment, rotation, env_source) = select_environment(&scene, &state, a)?;
    let views = read_views(&a.cameras, a.frames.as_deref(), &state.name)?;

    let started = Instant::now();
    let trace = TraceScene::new(&scene);
    let placed = trace.place_state(&state);
    let map = EnvMap::new(&environment, rotation);
    let eps = lightfuse::shade::estimator::self_hit_epsilon(&scene, &state);
    let estimator = Estimator::new(&placed, &map, eps).with_bounces(a.bounces);
    let filter = PixelFilter::new(a.filter_width);

    let total: u64 = views
        .iter()
        .map(|v| v.camera.w as u64 * v.camera.h as u64)
        .sum();
    let bar = if cli.quiet || cli.json {
        indicatif::ProgressBar::hidden()
    } else {
        let bar = indicatif::ProgressBar::new(total);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{msg} [{bar:40}] {pos}/{len} px {elapsed_precise} eta {eta}",
            )
            .expect("a valid progress template")
            .progress_chars("=> "),
        );
        bar
    };
    let mut files = Vec::new();
    let mut rays = 0u64;
    for (k, view) in views.iter().enumerate() {
        bar.set_message(view.name.clone());
        let seed = a.seed.wrapping_add(k as u32);
        let (mut image, view_rays) =
            render_image(&estimator, &filter, &view.camera, a.spp, seed, &|n| {
                bar.inc(n)
            });
        rays += view_rays;
        if a.denoise {
            denoise(&mut image, &map, &view.camera)?;
        }
        files.extend(write_view(&image, &a.out, &view.name)?);
    }
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    if cli.json {
        println!(
            "{}",
            serde_json::json!({
                "files": files, "frames": views.len(), "seconds": seconds, "rays": rays,
                "spp": a.spp, "denoise": a.denoise, "seed": a.seed, "state": state.name, "epsilon": eps,
                "environment": env_source, "environment_rotation_deg": rotation,
            })
        );
    } else if !cli.quiet {
        eprintln!(
            "rendered {} views ({} spp) into {} in {seconds:.1} s ({:.2} Mrays/s)",
            views.len(),
            a.spp,
            a.out.display(),
            rays as f64 / seconds.max(1e-9) / 1e6
        );
    }
    Ok(())
}

/// Replaces the radiance by Open Image Denoise's estimate, guided by the image's own
/// pixel-centre AOVs ([`denoise_render`], as `lightfuse evaluate` denoises).
fn denoise(
    image: &mut RenderedImage,
    env: &EnvMap,
    camera: &lightfuse::scene::Camera,
) -> Result<()> {
    let bg = environment_image(env, camera);
    image.radiance = denoise_render(
        &image.radiance,
        &image.aovs,
        &bg,
        &[1.0; 3],
        image.width,
        image.height,
    )?;
    Ok(())
}

/// The placement: `--layout` (objects it names moved, the others at the reference placement),
/// else `--state` (default: the reference state). A layout keeps `--state`'s environment.
fn select_state(scene: &Scene, a: &RenderArgs) -> Result<State> {
    let base = match &a.state {
        Some(name) => {
            let i = scene.state_index(name).ok_or_else(|| {
                let names: Vec<_> = scene.states.iter().map(|s| s.name.as_str()).collect();
                Error::invalid(
                    &a.scene,
                    "states",
                    format!("--state {name:?}: expected one of {names:?}"),
                )
            })?;
            scene.states[i].clone()
        }
        None => scene.states[scene.reference_state].clone(),
    };
    match &a.layout {
        None => Ok(base),
        Some(path) => {
            let layout = lightfuse::io::layout::read_layout(path)?;
            let name = lightfuse::io::file_stem(path).unwrap_or_else(|| "layout".into());
            let mut state = scene.state_from_layout(&name, &layout, path)?;
            state.environment = base.environment;
            Ok(state)
        }
    }
}

/// `--env` (with `--env-rotation`, default 0), else the state's environment and rotation
/// (`--env-rotation` then overrides its rotation).
fn select_environment<'s>(
    scene: &'s Scene,
    state: &State,
    a: &RenderArgs,
) -> Result<(std::borrow::Cow<'s, Environment>, f32, String)> {
    if let Some(path) = &a.env {
        let env = lightfuse::io::exr::read_lighting(path, None)?;
        return Ok((
            std::borrow::Cow::Owned(env),
            a.env_rotation.unwrap_or(0.0),
            path.display().to_string(),
        ));
    }
    let r = state.environment.ok_or_else(|| {
        Error::Usage(format!(
            "{}: state {:?} has no environment; give one with --env FILE.exr",
            a.scene.display(),
            state.name
        ))
    })?;
    let env = &scene.environments[r.index];
    env.check_latlong(&a.scene, &format!("environments[{}]", r.index))?;
    Ok((
        std::borrow::Cow::Borrowed(env),
        a.env_rotation.unwrap_or(r.rotation_deg),
        format!("{}#{}", a.scene.display(), env.name),
    ))
}

/// `render --baked`: the SH appearance splatted by 2DGS (eq. state-assembly for the placement).
fn render_baked(cli: &Cli, a: &RenderArgs, scene: &Scene, state: &State) -> Result<()> {
    let views = read_views(&a.cameras, a.frames.as_deref(), &state.name)?;
    let started = Instant::now();
    let placements = lightfuse::splat::placements(scene, state);
    let mut files = Vec::new();
    for view in &views {
        let img = lightfuse::splat::forward(&placements, &view.camera).image;
        // The splatted normal is the alpha-blended one: unit length where it is not zero.
        let normal = img
            .normal
            .iter()
            .map(|n| {
                let v = glam::Vec3::from_array(*n);
                let l = v.length();
                if l > 0.0 {
                    (v / l).to_array()
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let image = RenderedImage {
            width: img.width as usize,
            height: img.height as usize,
            radiance: img.color,
            aovs: Aovs {
                alpha: img.alpha,
                depth: img.depth,
                normal,
                albedo: Vec::new(),
                metallic: Vec::new(),
                roughness: Vec::new(),
            },
        };
        files.extend(write_view(&image, &a.out, &view.name)?);
    }
    let seconds = started.elapsed().as_secs_f64();
    if cli.json {
        println!(
            "{}",
            serde_json::json!({"files": files, "frames": views.len(), "seconds": seconds, "state": state.name, "baked": true})
        );
    } else if !cli.quiet {
        eprintln!(
            "splatted {} views (baked appearance) into {} in {seconds:.2} s",
            views.len(),
            a.out.display()
        );
    }
    Ok(())
}

/// Writes `NAME.exr` (every channel) and `NAME.png` (sRGB preview) into `out`; returns both paths.
fn write_view(image: &RenderedImage, out: &Path, name: &str) -> Result<[PathBuf; 2]> {
    let exr = out.join(format!("{name}.exr"));
    let png = out.join(format!("{name}.png"));
    lightfuse::io::exr::write_channels(&Channels::from_render(image), &exr)?;
    write_png(image, &png)?;
    Ok([exr, png])
}

fn write_png(image: &RenderedImage, path: &Path) -> Result<()> {
    use image::ImageEncoder;
    let rgb: Vec<u8> = image
        .radiance
        .iter()
        .flat_map(|p| p.map(srgb_byte))
        .collect();
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(
            &rgb,
            image.width as u32,
            image.height as u32,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| Error::io(path, std::io::Error::other(e)))?;
    let mut files = lightfuse::io::AtomicFiles::new();
    files.write(path, &bytes)?;
    files.commit()
}
