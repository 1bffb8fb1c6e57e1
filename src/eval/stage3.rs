//! Stage 3's own figures (`invert/report.json`): how well the recovered materials and
//! environments reproduce the captures they were fitted to and the views held out, and how
//! they compare with the dataset's truth. Measured by the tracer that relights the scene.

use crate::error::Result;
use crate::eval::lighting::{
    compare_albedo, compare_environments, compare_materials, AlbedoFigures, EnvFigures,
    MaterialFigures,
};
use crate::eval::metrics::{psnr_hdr, psnr_srgb};
use crate::io::dataset::{Dataset, Observation};
use crate::scene::Scene;
use crate::shade::envmap::EnvMap;
use crate::shade::estimator::{self_hit_epsilon, Estimator, PixelFilter, DEFAULT_FILTER_WIDTH};
use crate::trace::TraceScene;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Rendered against captured, over a set of views of one state.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ImageFigures {
    pub views: Vec<usize>,
    pub pixels: usize,
    /// PSNR of the scene-linear HDR images, peak = the captures' largest value over these
    /// pixels (no clamping).
    pub psnr_hdr_db: f64,
    /// PSNR after clamping to [0, 1] and sRGB encoding.
    pub psnr_srgb_db: f64,
    /// The same sRGB PSNR over the pixels where the capture sees a surface (depth > 0) and
    /// where it sees the environment: which of the two an error comes from (e.g. a held-out
    /// view looking at sky no training view saw). `None` when there are no such pixels.
    #[serde(default)]
    pub psnr_srgb_surface_db: Option<f64>,
    #[serde(default)]
    pub psnr_srgb_background_db: Option<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StateReport {
    pub state: String,
    pub training: ImageFigures,
    pub heldout: ImageFigures,
    /// The recovered environment against the dataset's (evaluation only; never used in
    /// training), [`crate::eval::lighting::compare_environments`].
    pub environment: Option<EnvFigures>,
}

/// What [`measure`] finds: per training state, then over every state.
pub struct Figures {
    pub states: Vec<StateReport>,
    pub albedo: Option<AlbedoFigures>,
    pub materials: Vec<MaterialFigures>,
}

/// A view's albedo pass from the dataset, when it has one.
type AlbedoPass = Option<Vec<[f32; 3]>>;

/// What the evaluation gathers besides the images: (predicted, true) base colours and
/// (object id, metallic, roughness) at pixel centres.
#[derive(Default)]
struct Gathered {
    albedo: Vec<([f32; 3], [f32; 3])>,
    materials: Vec<(u32, f32, f32)>,
}

/// Renders every `stride`-th pixel of `views` and compares with the captures; with `gather`,
/// also collects the material samples (`albedo[i]` = the dataset's albedo pass of `views[i]`).
fn image_figures(
    est: &Estimator,
    views: &[&Observation],
    spp: u32,
    stride: u32,
    mut gather: Option<(&mut Gathered, &[AlbedoPass])>,
) -> ImageFigures {
    let filter = PixelFilter::new(DEFAULT_FILTER_WIDTH);
    let mut pairs: Vec<([f32; 3], [f32; 3])> = Vec::new();
    let mut on_surface: Vec<bool> = Vec::new();
    for (vi, o) in views.iter().enumerate() {
        let cam = &o.camera;
        let coords: Vec<(u32, u32)> = (0..cam.h)
            .step_by(stride as usize)
            .flat_map(|y| (0..cam.w).step_by(stride as usize).map(move |x| (x, y)))
            .collect();
        let rendered: Vec<_> = coords
            .par_iter()
            .with_min_len(16)
            .map(|&(x, y)| est.pixel(cam, &filter, (x, y), spp, 0x5eed))
            .collect();
        for ((x, y), p) in coords.iter().zip(rendered) {
            let i = (y * cam.w + x) as usize;
            pairs.push((p.rgb, o.rgb[i]));
            on_surface.push(o.depth[i] > 0.0);
            if let Some((g, albedo)) = gather.as_mut() {
                let surface = p.depth > 0.0 && o.depth[i] > 0.0;
                if let Some(truth) = &albedo[vi] {
                    if surface && truth[i].iter().any(|&v| v > 0.0) {
                        g.albedo.push((p.albedo, truth[i]));
                    }
                }
                if surface && o.mask[i] > 0 {
                    g.materials
                        .push((o.mask[i] as u32, p.metallic, p.roughness));
                }
            }
        }
    }
    if pairs.is_empty() {
        return ImageFigures::default();
    }
    let (a, b): (Vec<[f32; 3]>, Vec<[f32; 3]>) = pairs.iter().copied().unzip();
    let part = |want: bool| {
        let (pa, pb): (Vec<[f32; 3]>, Vec<[f32; 3]>) = pairs
            .iter()
            .zip(&on_surface)
            .filter(|(_, &s)| s == want)
            .map(|(p, _)| *p)
            .unzip();
        (!pa.is_empty()).then(|| psnr_srgb(&pa, &pb))
    };
    ImageFigures {
        views: views.iter().map(|o| o.view).collect(),
        pixels: pairs.len(),
        psnr_hdr_db: psnr_hdr(&a, &b),
        psnr_srgb_db: psnr_srgb(&a, &b),
        psnr_srgb_surface_db: part(true),
        psnr_srgb_background_db: part(false),
    }
}

/// Stage 3's own figures for its report: every training state's training and held-out views
/// rendered with the state's *recovered* environment against the captures (every `stride`-th
/// pixel, `spp` samples, `bounces` indirect bounces), the recovered environment against the
/// dataset's, and the base colour and per-object metallic and roughness against the dataset's
/// truth (evaluation only: none of it feeds training). `names[j]` is the scene's state of
/// training state `dataset_states[j]`.
#[allow(clippy::too_many_arguments)]
pub fn measure(
    scene: &Scene,
    dataset: &Dataset,
    dataset_states: &[usize],
    names: &[String],
    train: &[Vec<Observation>],
    held: &[Vec<Observation>],
    spp: u32,
    stride: u32,
    bounces: u32,
) -> Result<Figures> {
    let trace = TraceScene::new(scene);
    let mut gathered = Gathered::default();
    let mut states = Vec::new();
    for (j, name) in names.iter().enumerate() {
        let k = dataset_states[j];
        let state = &scene.states[scene.state_index(name).expect("checked")];
        let placed = trace.place_state(state);
        let env_ref = state.environment.expect("set above");
        let recovered = &scene.environments[env_ref.index];
        let map = EnvMap::new(recovered, env_ref.rotation_deg);
        let est =
            Estimator::new(&placed, &map, self_hit_epsilon(scene, state)).with_bounces(bounces);
        let t: Vec<&Observation> = train[j].iter().collect();
        let hd: Vec<&Observation> = held[j].iter().collect();
        let albedo = t
            .iter()
            .map(|o| dataset.albedo(k, o.view))
            .collect::<Result<Vec<_>>>()?;
        let training = image_figures(&est, &t, spp, stride, Some((&mut gathered, &albedo)));
        let heldout = image_figures(&est, &hd, spp, stride, None);
        // The dataset's environment files are stored as Cycles used them (rotation applied),
        // i.e. in the world frame the recovered maps use.
        let environment = dataset
            .environment(k)?
            .map(|truth| compare_environments(recovered, &truth));
        states.push(StateReport {
            state: name.clone(),
            training,
            heldout,
            environment,
        });
    }
    Ok(Figures {
        states,
        albedo: (!gathered.albedo.is_empty()).then(|| compare_albedo(&gathered.albedo)),
        materials: compare_materials(&gathered.materials, &dataset.objects),
    })
}
