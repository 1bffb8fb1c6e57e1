//! The `lightfuse` command line: a thin layer over the library. Each subcommand's options are
//! one clap struct whose `///` docs are its `--help`.

mod bench;
mod info;
mod render;

use clap::{Parser, Subcommand};
use lightfuse::error::{Error, Result};
use lightfuse::io::work::WorkDir;
use lightfuse::stages::invert::train::Overrides;
use lightfuse::stages::reconstruct::train::PoseRefinement;
use lightfuse::stages::Preset;
use std::path::PathBuf;

/// The range of every `--bounces` option, as the library bounds it
/// (`shade::replay::check_bounces`, which `lightfuse invert` and `run` go through).
fn bounces_range() -> clap::builder::RangedI64ValueParser<u32> {
    clap::value_parser!(u32).range(1..=lightfuse::shade::replay::MAX_BOUNCES as i64)
}

#[derive(Parser, Debug)]
#[command(
    name = "lightfuse",
    version,
    about = "Relightable, rearrangeable 2D Gaussian surfel scenes"
)]
pub struct Cli {
    /// Print nothing but errors.
    #[arg(long, global = true)]
    pub quiet: bool,
    /// Print machine-readable JSON instead of text.
    #[arg(long, global = true)]
    pub json: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Components, surfel counts, states, environments and bounds of a scene.
    Info(InfoArgs),
    /// Convert a scene between .glb, .gltf and .usda, or export it as a 3DGS .ply.
    Convert(ConvertArgs),
    /// Turn a glTF mesh scene (PBR metallic-roughness) into a surfel scene.
    Surfelize(SurfelizeArgs),
    /// Read an environment map (any EXR compression, e.g. Blender's DWAB HDRIs), optionally
    /// resample it (area-weighted, energy kept), and write it as float RGB EXR.
    Env(EnvArgs),
    /// Time LightFuse and Cycles rendering the same dataset state (cameras, resolution, spp,
    /// bounces limited to one indirect), back to back; print both times and their ratio.
    Bench(BenchArgs),
    /// Path-trace images of a scene (one-bounce estimator) for a state or layout, an
    /// environment and a set of cameras: per camera an HDR EXR with AOVs and an sRGB PNG.
    Render(RenderArgs),
    /// Stage 1: reconstruct a dataset's training states as a shared background and movable
    /// objects of 2D Gaussian surfels with per-state object poses (scene.glb, report.json,
    /// log.jsonl, checkpoint.json in --out).
    Reconstruct(ReconstructArgs),
    /// Stage 2: refine stage 1's geometry for ray tracing (depth, normals, coverage, scale;
    /// no colour) over every training state; writes <work>/refined.glb and
    /// <work>/refine/{report.json, log.jsonl, checkpoint.json}.
    Refine(RefineArgs),
    /// Stage 3: inverse rendering with path replay backpropagation: every surfel's base
    /// colour, metallic and roughness and each training state's HDR environment, geometry and
    /// poses fixed; writes <work>/relightable.{glb,usda} and
    /// <work>/invert/{report.json, log.jsonl, checkpoint.json}.
    Invert(InvertArgs),
    /// Edit a scene: a new named state from a layout, per-object materials and a new
    /// environment, written as .glb, .gltf or .usda (materials are shared by every state).
    Edit(EditArgs),
    /// Novel-state relighting and synthesis (the paper's Tables 1 and 2): every test state's
    /// arrangement under its environments, LightFuse against Baked and No re-tracing, compared
    /// with the dataset's Cycles frames; writes <work>/eval/{eval.json, eval.md, report.html}
    /// and the images the report shows.
    Evaluate(EvaluateArgs),
    /// Turn a capture made elsewhere into a LightFuse dataset: `import colmap` reads a COLMAP
    /// sparse model and its photos (docs/real-captures.md).
    #[command(subcommand)]
    Import(ImportCommand),
    /// Stages 1-3 and the evaluation in order; a stage whose output is newer than its inputs
    /// is skipped, a killed run resumes from the stage's checkpoint.
    Run(RunArgs),
}

#[derive(clap::Args, Debug)]
pub struct EvaluateArgs {
    /// Dataset (dataset.json or its folder) with a test state.
    pub dataset: PathBuf,
    /// Work folder holding stage 1's scene.glb and stage 3's relightable.glb.
    pub work: PathBuf,
    /// Samples per pixel of the path-traced rows (the paper's evaluation: 32).
    #[arg(long, default_value_t = lightfuse::eval::relight::DEFAULT_SPP)]
    pub spp: u32,
    /// Seed of the Sobol scrambles.
    #[arg(long, default_value_t = 0)]
    pub seed: u32,
    /// Do not write the comparison images.
    #[arg(long)]
    pub no_images: bool,
    /// Compare the traced rows as rendered, without Open Image Denoise (the paper denoised).
    #[arg(long)]
    pub no_denoise: bool,
    /// Rows to render, comma-separated: lightfuse (always), baked, no-retracing. Ablations,
    /// which compare only LightFuse across variants, render "lightfuse" alone.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "lightfuse,baked,no-retracing"
    )]
    pub rows: Vec<String>,
    /// The paper's tables whose runs to render, comma-separated: 1 (relighting under unseen
    /// environments), 2 (synthesis under the training states' recovered lighting).
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    pub tables: Vec<String>,
    /// Indirect bounces of the path-traced rows (1: the paper's one-bounce estimator; up to 4,
    /// as Cycles' max bounces); default: what stage 3 trained with (its report's settings).
    #[arg(long, value_parser = bounces_range())]
    pub bounces: Option<u32>,
}

#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Dataset (dataset.json or its folder).
    pub dataset: PathBuf,
    /// Work folder (every stage's output; see docs/formats.md).
    #[arg(short, long)]
    pub out: PathBuf,
    /// Every stage's settings: fast (this machine, minutes) or paper.
    #[arg(long, value_enum, default_value_t = Preset::Fast)]
    pub preset: Preset,
    /// Run every stage again even when its output is up to date.
    #[arg(long)]
    pub force: bool,
    /// Evaluate without Open Image Denoise (the paper denoised).
    #[arg(long)]
    pub no_denoise: bool,
    /// Stage 3's options, as `lightfuse invert`'s (each absent one: the preset's); a stage-3
    /// output trained with other settings is out of date.
    #[command(flatten)]
    pub stage3: Overrides,
}

#[derive(clap::Args, Debug)]
pub struct EditArgs {
    /// The scene to edit (.glb, .gltf or .usda), e.g. <work>/relightable.glb.
    pub scene: PathBuf,
    /// The edited scene (.glb, .gltf or .usda); the input is not changed.
    #[arg(short, long)]
    pub output: PathBuf,
    /// The new state's name.
    #[arg(long, default_value = "edit")]
    pub name: String,
    /// The state the edit starts from (placement and environment; default the reference).
    #[arg(long)]
    pub state: Option<String>,
    /// Layout (layout.json, or a .glb/.gltf with named object nodes): object transforms relative
    /// to the reference placement; objects it does not name stay there.
    #[arg(long)]
    pub layout: Option<PathBuf>,
    /// OBJECT:base_color=R,G,B, OBJECT:metallic=M or OBJECT:roughness=R (values in [0, 1]; the
    /// background is "background"); repeatable.
    #[arg(long = "material")]
    pub materials: Vec<String>,
    /// A new environment (equirectangular EXR, scene-linear) for the new state.
    #[arg(long)]
    pub env: Option<PathBuf>,
    /// Its rotation about +Y in degrees (Cycles' convention).
    #[arg(long, requires = "env", default_value_t = 0.0)]
    pub env_rotation: f32,
}

#[derive(clap::Args, Debug)]
pub struct InvertArgs {
    /// Dataset (dataset.json or its folder) that stages 1 and 2 reconstructed.
    pub dataset: PathBuf,
    /// Work folder of stages 1-2 (holds refined.glb); relightable.* and invert/ are written there.
    pub work: PathBuf,
    /// The scene to invert, if not <work>/refined.glb.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Settings: fast (minutes for the demo on a laptop) or paper (15,000 iterations of
    /// 16,384 pixels, 8/16/32 spp).
    #[arg(long, value_enum, default_value_t = Preset::Fast)]
    pub preset: Preset,
    /// Stage 3's options (each absent one: the preset's).
    #[command(flatten)]
    pub stage3: Overrides,
    /// Evaluation: samples per pixel, and every N-th pixel in x and y of each view.
    #[arg(long, default_value_t = lightfuse::stages::invert::run::DEFAULT_EVAL_SPP)]
    pub eval_spp: u32,
    #[arg(long, default_value_t = lightfuse::stages::invert::run::DEFAULT_EVAL_STRIDE)]
    pub eval_stride: u32,
    /// Continue from <work>/invert/checkpoint.json if it is there.
    #[arg(long)]
    pub resume: bool,
}

#[derive(clap::Args, Debug)]
pub struct RefineArgs {
    /// Dataset (dataset.json or its folder) that stage 1 reconstructed.
    pub dataset: PathBuf,
    /// Work folder of stage 1 (holds scene.glb); refined.glb and refine/ are written there.
    pub work: PathBuf,
    /// Stage 1's scene, if not <work>/scene.glb.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Settings: fast (minutes on a laptop) or paper (16,384 rays per iteration, 5,000
    /// iterations).
    #[arg(long, value_enum, default_value_t = Preset::Fast)]
    pub preset: Preset,
    /// Iterations (default: the preset's).
    #[arg(long)]
    pub iterations: Option<u32>,
    /// Drop the coverage term L_alpha (the paper's Table 3).
    #[arg(long)]
    pub no_coverage: bool,
    /// Drop the scale regulariser L_s.
    #[arg(long)]
    pub no_scale: bool,
    /// Drop the depth term L_D.
    #[arg(long)]
    pub no_depth: bool,
    /// Drop the normal terms L_N and L_DN^ray.
    #[arg(long)]
    pub no_normal: bool,
    /// Continue from <work>/refine/checkpoint.json if it is there.
    #[arg(long)]
    pub resume: bool,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

#[derive(clap::Args, Debug)]
pub struct ReconstructArgs {
    /// Dataset (dataset.json or its folder).
    pub dataset: PathBuf,
    /// Work folder: scene.glb, report.json, log.jsonl, checkpoint.json.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Settings: fast (minutes on a laptop) or paper (2DGS's 30k iterations).
    #[arg(long, value_enum, default_value_t = Preset::Fast)]
    pub preset: Preset,
    /// Iterations (default: the preset's).
    #[arg(long)]
    pub iterations: Option<u32>,
    /// Use the dataset's ground-truth object poses instead of estimating them.
    #[arg(long)]
    pub oracle_poses: bool,
    /// Refine the object poses by the splatting gradients from a third of the iterations on:
    /// photometric (every term), geometry (the coverage, depth and normal terms only, which
    /// a change of lighting does not bias) or off (default: the presets' choice, stage 1's
    /// registered poses are kept; on the demo both refinements moved them farther from the
    /// truth: `train::Settings::fast`). A run resumed with more --iterations keeps the start
    /// its checkpoint had.
    #[arg(long, value_enum)]
    pub refine_poses: Option<PoseRefinement>,
    /// Continue from --out/checkpoint.json if it is there.
    #[arg(long)]
    pub resume: bool,
    /// Voxel pitch of the initial point thinning, metres.
    #[arg(long, default_value_t = lightfuse::stages::reconstruct::run::DEFAULT_VOXEL)]
    pub voxel: f32,
    /// Depth-discrepancy threshold of the completion (eq. completion-mask), metres.
    #[arg(long, default_value_t = lightfuse::stages::reconstruct::run::DEFAULT_TAU_D)]
    pub tau_d: f32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("placement").required(true).multiple(true).args(["state", "layout"])))]
pub struct RenderArgs {
    /// Scene file (.glb, .gltf, .usda).
    pub scene: PathBuf,
    /// State to render: its object placement and its environment.
    #[arg(long)]
    pub state: Option<String>,
    /// Layout (layout.json, or a .glb/.gltf with named object nodes): object transforms relative
    /// to the reference state. The environment is --state's (default: the reference state's).
    #[arg(long)]
    pub layout: Option<PathBuf>,
    /// Environment (.exr, equirectangular 2:1) replacing the state's.
    #[arg(long)]
    pub env: Option<PathBuf>,
    /// Rotation of the environment about +Y, degrees (default: the state's, or 0 with --env).
    #[arg(long, allow_negative_numbers = true)]
    pub env_rotation: Option<f32>,
    /// Cameras: a dataset (dataset.json or its folder) or a cameras.json {"frames": [...]} with
    /// dataset frame fields (transform_matrix, fl_x, fl_y, cx, cy, w, h, file_path).
    #[arg(long)]
    pub cameras: PathBuf,
    /// With a dataset: the state whose frames are rendered, or "all" (default: --state if the
    /// dataset has it, else its first state).
    #[arg(long)]
    pub frames: Option<String>,
    /// Samples per pixel.
    #[arg(long, default_value_t = 32)]
    pub spp: u32,
    /// Seed of the Sobol scrambles; camera k of the selection uses seed + k.
    #[arg(long, default_value_t = 0)]
    pub seed: u32,
    /// Pixel filter width (Blackman-Harris, as Cycles' default 1.5); 0 for a box over the pixel.
    #[arg(long, default_value_t = lightfuse::shade::estimator::DEFAULT_FILTER_WIDTH)]
    pub filter_width: f32,
    /// Indirect bounces, counted as Cycles' max bounces: 1 is the paper's one-bounce
    /// estimator; up to 4, each more a BSDF continuation shaded by next-event estimation.
    #[arg(long, default_value_t = 1, value_parser = bounces_range())]
    pub bounces: u32,
    /// Output folder: NAME.exr (R,G,B,A,Z,N.X,N.Y,N.Z,albedo.R,albedo.G,albedo.B) and NAME.png
    /// per camera, NAME the frame's file stem.
    #[arg(long)]
    pub out: PathBuf,
    /// Draw the baked splatting appearance (SH) by 2DGS splatting instead of path tracing:
    /// the reconstruction's own view, and the baked-appearance baseline after a rearrangement.
    /// Writes R,G,B (over black), A, Z, N; ignores the environment and --spp.
    #[arg(long)]
    pub baked: bool,
    /// Denoise R, G, B with Open Image Denoise (HDR, albedo and normal guides; needs the
    /// `denoise` build feature, which `bash scripts/setup.sh` builds).
    #[arg(long)]
    pub denoise: bool,
}

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// LightFuse scene to render (e.g. the oracle scene of `surfelize --dataset`).
    pub scene: PathBuf,
    /// Dataset (folder or dataset.json) whose scene.blend Cycles renders and whose cameras both use.
    #[arg(long)]
    pub dataset: PathBuf,
    /// State to render: the scene's state and the dataset's cameras, layout and environment.
    #[arg(long, default_value = "state0")]
    pub state: String,
    /// Samples per pixel, the same for both renderers.
    #[arg(long, default_value_t = 32)]
    pub spp: u32,
    /// Max bounces of both renderers: Cycles' `max_bounces`, LightFuse's `--bounces` (1 is
    /// the paper's one-bounce estimator; LightFuse goes to 4).
    #[arg(long, default_value_t = 1, value_parser = bounces_range())]
    pub max_bounces: u32,
    /// Environment file for Cycles (default: the dataset state's own).
    #[arg(long)]
    pub env: Option<PathBuf>,
    /// Python with bpy (default: the checkout's .venv).
    #[arg(long)]
    pub python: Option<PathBuf>,
    /// LightFuse's `blender/` folder (default: found beside the binary, i.e. in the checkout
    /// it was built in, or in the current folder).
    #[arg(long)]
    pub toolkit: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct EnvArgs {
    /// Input lat-long environment (.exr).
    pub input: PathBuf,
    /// Output environment (.exr, float RGB, ZIP).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Target size WIDTHxHEIGHT, e.g. 256x128 (the paper's per-state environment).
    #[arg(long, value_parser = parse_size)]
    pub size: Option<(usize, usize)>,
}

fn parse_size(s: &str) -> std::result::Result<(usize, usize), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("expected WIDTHxHEIGHT, found {s:?}"))?;
    let w: usize = w
        .parse()
        .map_err(|_| format!("expected a width in pixels, found {w:?}"))?;
    let h: usize = h
        .parse()
        .map_err(|_| format!("expected a height in pixels, found {h:?}"))?;
    if w == 0 || h == 0 || w > 16384 || h > 8192 {
        return Err(format!(
            "expected a size within 1x1 ..= 16384x8192, found {w}x{h}"
        ));
    }
    Ok((w, h))
}

#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    /// Scene file (.glb, .gltf, .usda).
    pub scene: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct ConvertArgs {
    /// Input scene (.glb, .gltf, .usda).
    pub input: PathBuf,
    /// Output scene (.glb, .gltf, .usda, .ply).
    pub output: PathBuf,
    /// For .ply output: the state whose placement is exported (default: the reference state).
    #[arg(long)]
    pub state: Option<String>,
}

#[derive(clap::Args, Debug)]
pub struct SurfelizeArgs {
    /// Input glTF mesh scene (.glb or .gltf) with PBR metallic-roughness materials.
    pub mesh: PathBuf,
    /// Output surfel scene (.glb, .gltf, .usda or .ply).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Distance between neighbouring surfels, metres.
    #[arg(long, default_value_t = 0.02)]
    pub spacing: f32,
    /// Names of top-level nodes that become object components (repeatable). Default: every
    /// named top-level node; `--objects none` puts everything in the background.
    #[arg(long = "objects", value_delimiter = ',')]
    pub objects: Vec<String>,
    /// Opacity of each surfel.
    #[arg(long, default_value_t = 0.99)]
    pub opacity: f32,
    /// Degree of the SH appearance written (0..=3; higher coefficients are zero).
    #[arg(long, default_value_t = 0)]
    pub sh_degree: u8,
    /// Seed of the jittered placement.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Oracle scene: give it every state of this dataset (dataset.json or its folder), placed
    /// by the ground-truth object poses and lit by the ground-truth environments; each relit
    /// test environment becomes a state `<state>_<environment>`. The mesh scene must be the
    /// dataset's reference state (what `blender/export_mesh_scene.py` writes by default).
    #[arg(long)]
    pub dataset: Option<PathBuf>,
    /// Resample the dataset's environments to WIDTHxHEIGHT (area-weighted, energy kept).
    #[arg(long, value_parser = parse_size, requires = "dataset")]
    pub env_size: Option<(usize, usize)>,
}

/// Runs the CLI; returns the process exit code (0 ok, 2 bad input, 1 internal failure).
pub fn main() -> i32 {
    let cli = Cli::parse();
    match run(&cli) {
        Ok(()) => 0,
        Err(e) => {
            if cli.json {
                println!("{}", serde_json::json!({ "error": e.to_string() }));
            }
            eprintln!("error: {e}");
            if e.is_user_error() {
                2
            } else {
                1
            }
        }
    }
}

pub fn run(cli: &Cli) -> Result<()> {
    match &cli.command {
        Command::Info(a) => info::run(cli, a),
        Command::Convert(a) => convert(cli, a),
        Command::Surfelize(a) => surfelize(cli, a),
        Command::Env(a) => env(cli, a),
        Command::Render(a) => render::run(cli, a),
        Command::Bench(a) => bench::run(cli, a),
        Command::Reconstruct(a) => reconstruct(cli, a),
        Command::Refine(a) => refine(cli, a),
        Command::Invert(a) => invert(cli, a),
        Command::Edit(a) => edit(cli, a),
        Command::Evaluate(a) => evaluate(cli, a),
        Command::Run(a) => run_all(cli, a),
        Command::Import(c) => import(cli, c),
    }
}

#[derive(Subcommand, Debug)]
pub enum ImportCommand {
    /// A COLMAP sparse model (binary or text) and its photos: states from the photos' folders,
    /// distorted lenses resampled into pinhole images, sRGB linearised, the world turned to
    /// +Y up and scaled to metres; writes <out>/dataset.json, import.json, images/, masks/.
    Colmap(ImportColmapArgs),
    /// A nerfstudio transforms.json: per-frame or shared intrinsics, camera_model, mask_path,
    /// depth_file_path; otherwise as `import colmap` (writes depth/ too).
    Nerfstudio(ImportNerfstudioArgs),
}

#[derive(clap::Args, Debug)]
pub struct ImportColmapArgs {
    /// The sparse model folder (cameras, images, points3D as .bin or .txt; e.g. sparse/0).
    pub model: PathBuf,
    /// The folder the model's image names are relative to (COLMAP's --image_path).
    #[arg(long)]
    pub images: PathBuf,
    /// Object-id masks: <masks>/<image name>.png, 8-bit, 0 = background, the same id for one
    /// object in every state.
    #[arg(long)]
    pub masks: Option<PathBuf>,
    #[command(flatten)]
    pub common: ImportCommonArgs,
}

#[derive(clap::Args, Debug)]
pub struct ImportNerfstudioArgs {
    /// The transforms.json (paths in it are relative to its folder).
    pub transforms: PathBuf,
    /// Metres per stored depth unit (nerfstudio's depth_unit_scale_factor: 1e-3 for its
    /// millimetre PNGs).
    #[arg(long, default_value_t = 1e-3)]
    pub depth_unit_scale: f64,
    #[command(flatten)]
    pub common: ImportCommonArgs,
}

#[derive(clap::Args, Debug)]
pub struct ImportCommonArgs {
    /// A JSON object {"<photo name>": "<state>"}; by default a photo's state is the name of
    /// the folder holding it (state1/IMG_0001.jpg).
    #[arg(long)]
    pub states: Option<PathBuf>,
    /// States held out for evaluation, comma-separated.
    #[arg(long, value_delimiter = ',')]
    pub test_states: Vec<String>,
    /// The world's up direction in the source's frame, X,Y,Z (default: the dominant
    /// supporting plane's normal, towards the cameras).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub up: Option<[f64; 3]>,
    /// Metres per source unit (default 1: SfM units are arbitrary, so say it).
    #[arg(long, allow_hyphen_values = true, conflicts_with = "scale_points")]
    pub scale: Option<f64>,
    /// The scale from two points a known distance apart: A B METRES, each point X,Y,Z in the
    /// source's frame or point:ID (a COLMAP 3D point's id, as its GUI shows).
    #[arg(long, num_args = 3, value_names = ["A", "B", "METRES"], allow_hyphen_values = true)]
    pub scale_points: Option<Vec<String>>,
    /// The dataset folder to write (new or empty).
    #[arg(short, long)]
    pub out: PathBuf,
}

impl ImportCommonArgs {
    fn options(&self, quiet: bool) -> Result<lightfuse::io::import::ImportOptions> {
        let scale_points = self
            .scale_points
            .as_deref()
            .map(lightfuse::io::import::ScalePoints::parse)
            .transpose()?;
        Ok(lightfuse::io::import::ImportOptions {
            states: self.states.clone(),
            test_states: self.test_states.clone(),
            up: self.up,
            scale: self.scale,
            scale_points,
            out: self.out.clone(),
            quiet,
        })
    }
}

fn parse_vec3(s: &str) -> std::result::Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| format!("expected X,Y,Z, found {s:?}"))?;
    match v.as_slice() {
        [x, y, z] => Ok([*x, *y, *z]),
        _ => Err(format!("expected X,Y,Z, found {s:?}")),
    }
}

fn import(cli: &Cli, c: &ImportCommand) -> Result<()> {
    use lightfuse::io::import;
    let (summary, common) = match c {
        ImportCommand::Colmap(a) => (
            import::import_colmap(&import::ColmapImport {
                model: a.model.clone(),
                images: a.images.clone(),
                masks: a.masks.clone(),
                options: a.common.options(cli.quiet)?,
            })?,
            &a.common,
        ),
        ImportCommand::Nerfstudio(a) => (
            import::import_nerfstudio(&import::NerfstudioImport {
                transforms: a.transforms.clone(),
                depth_unit_scale: a.depth_unit_scale,
                options: a.common.options(cli.quiet)?,
            })?,
            &a.common,
        ),
    };
    if cli.json {
        let states: Vec<_> = summary
            .states
            .iter()
            .map(|(n, s, k)| serde_json::json!({"name": n, "split": s, "frames": k}))
            .collect();
        println!(
            "{}",
            serde_json::json!({"dataset": summary.dataset, "states": states,
                "objects": summary.objects, "resampled_frames": summary.undistorted,
                "up_source": summary.frame.up_source})
        );
    } else if !cli.quiet {
        for (n, s, k) in &summary.states {
            eprintln!("state {n} ({s}): {k} frames");
        }
        eprintln!(
            "objects (mask ids): {:?}; {} frames resampled into pinhole images; up from {}",
            summary.objects, summary.undistorted, summary.frame.up_source
        );
        if common.scale.is_none() {
            eprintln!("note: no --scale: the source's units are taken as metres (LightFuse's thresholds are in metres)");
        }
        eprintln!("wrote {}", summary.dataset.display());
    }
    Ok(())
}

fn env(cli: &Cli, a: &EnvArgs) -> Result<()> {
    let env = lightfuse::io::exr::read_latlong(&a.input, None)?;
    let out = match a.size {
        Some((w, h)) => env.resample(w, h),
        None => env.clone(),
    };
    lightfuse::io::exr::write_environment(&out, &a.output)?;
    let (e0, e1) = (env.integral(), out.integral());
    let report = serde_json::json!({
        "input": {"width": env.width, "height": env.height, "integral_rgb": e0},
        "output": {"width": out.width, "height": out.height, "integral_rgb": e1},
    });
    if cli.json {
        println!("{report}");
    } else if !cli.quiet {
        eprintln!(
            "wrote {} ({}x{} -> {}x{}; integral of radiance over the sphere {:.6?} -> {:.6?})",
            a.output.display(),
            env.width,
            env.height,
            out.width,
            out.height,
            e0,
            e1
        );
    }
    Ok(())
}

fn edit(cli: &Cli, a: &EditArgs) -> Result<()> {
    use lightfuse::scene::{Edit, MaterialEdit};
    let materials = a
        .materials
        .iter()
        .map(|m| MaterialEdit::parse(m).map_err(|e| Error::Usage(format!("--material {e}"))))
        .collect::<Result<Vec<_>>>()?;
    if !a.env_rotation.is_finite() {
        return Err(Error::Usage(
            "--env-rotation: expected a finite angle".into(),
        ));
    }
    let mut scene = lightfuse::io::read_scene(&a.scene)?;
    let layout = match &a.layout {
        Some(p) => Some((lightfuse::io::layout::read_layout(p)?, p.clone())),
        None => None,
    };
    let environment = match &a.env {
        Some(p) => Some((lightfuse::io::exr::read_lighting(p, None)?, a.env_rotation)),
        None => None,
    };
    scene.apply_edit(
        &Edit {
            name: a.name.clone(),
            from_state: a.state.clone(),
            layout,
            materials,
            environment,
        },
        &a.scene,
    )?;
    lightfuse::io::write_scene(&scene, &a.output)?;
    if !cli.quiet {
        eprintln!(
            "wrote {}: state {:?} added ({} states)",
            a.output.display(),
            a.name,
            scene.states.len()
        );
    }
    Ok(())
}

fn convert(cli: &Cli, a: &ConvertArgs) -> Result<()> {
    let scene = lightfuse::io::read_scene(&a.input)?;
    let out_format = lightfuse::io::SceneFormat::from_path(&a.output)?;
    if out_format == lightfuse::io::SceneFormat::Ply {
        let state = match &a.state {
            Some(name) => scene
                .states
                .iter()
                .find(|s| &s.name == name)
                .ok_or_else(|| {
                    let names: Vec<_> = scene.states.iter().map(|s| s.name.as_str()).collect();
                    Error::Usage(format!("--state {name:?}: expected one of {names:?}"))
                })?,
            None => &scene.states[scene.reference_state],
        };
        lightfuse::io::ply::write_state(&scene, state, &a.output)?;
    } else {
        if a.state.is_some() {
            return Err(Error::Usage(
                "--state applies to .ply output only; other formats keep every state".into(),
            ));
        }
        lightfuse::io::write_scene(&scene, &a.output)?;
    }
    if !cli.quiet && !cli.json {
        eprintln!(
            "wrote {} ({} surfels, {} states)",
            a.output.display(),
            scene.surfel_count(),
            scene.states.len()
        );
    }
    Ok(())
}

fn surfelize(cli: &Cli, a: &SurfelizeArgs) -> Result<()> {
    use lightfuse::scene::surfelize::{surfelize, ObjectSelection, SurfelizeOptions};
    let objects = match a.objects.as_slice() {
        [] => ObjectSelection::AllNamedRoots,
        [none] if none == "none" => ObjectSelection::None,
        names => ObjectSelection::Named(names.to_vec()),
    };
    let opts = SurfelizeOptions {
        spacing: a.spacing,
        objects,
        opacity: a.opacity,
        sh_degree: a.sh_degree,
        seed: a.seed,
    };
    // Check the output's format before the work, so a typo fails at once.
    lightfuse::io::SceneFormat::from_path(&a.output)?;
    let mesh = lightfuse::io::mesh::read_mesh_scene(&a.mesh)?;
    let mut scene = surfelize(&mesh, &opts)?;
    if let Some(d) = &a.dataset {
        lightfuse::io::dataset::attach_ground_truth(&mut scene, d, a.env_size)?;
    }
    lightfuse::io::write_scene(&scene, &a.output)?;
    if cli.json {
        println!("{}", info::summary(&scene));
    } else if !cli.quiet {
        let parts: Vec<_> = scene
            .components
            .iter()
            .map(|c| format!("{} {}", c.name, c.surfels.len()))
            .collect();
        eprintln!(
            "wrote {}: {} surfels ({})",
            a.output.display(),
            scene.surfel_count(),
            parts.join(", ")
        );
    }
    Ok(())
}

fn reconstruct(cli: &Cli, a: &ReconstructArgs) -> Result<()> {
    use lightfuse::stages::reconstruct::{run, train::Settings};
    let mut settings = a.preset.pick(Settings::fast, Settings::paper);
    if let Some(n) = a.iterations {
        settings.iterations = n;
    }
    settings.seed = a.seed;
    if let Some(r) = a.refine_poses {
        r.apply(&mut settings);
    }
    if !(a.voxel > 0.0 && a.voxel.is_finite() && a.tau_d > 0.0 && a.tau_d.is_finite()) {
        return Err(Error::Usage(
            "--voxel and --tau-d: expected positive lengths in metres".into(),
        ));
    }
    let report = run::reconstruct(&run::Options {
        dataset: a.dataset.clone(),
        work: WorkDir::new(&a.out),
        settings,
        oracle_poses: a.oracle_poses,
        resume: a.resume,
        quiet: cli.quiet || cli.json,
        voxel: a.voxel,
        tau_d: a.tau_d,
    })?;
    if cli.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&report).expect("report serialises")
        );
    } else if !cli.quiet {
        eprintln!(
            "wrote {}: {} surfels in {:.0} s; held-out PSNR {:.2} dB (sRGB, covered pixels, {} views), median depth error {:.3} m ({:.2}% of the scene)",
            WorkDir::new(&a.out).scene().display(),
            report.surfels,
            report.seconds,
            report.heldout_psnr_srgb,
            report.heldout_views,
            report.heldout_median_depth_error_m,
            100.0 * report.heldout_median_depth_error_rel
        );
        eprintln!(
            "  training views: {:.2} dB (sRGB, covered pixels)",
            report.train_psnr_srgb
        );
        for v in &report.heldout {
            eprintln!(
                "  held-out {} view {}: {:.2} dB, median depth error {:.3} m ({})",
                v.state, v.view, v.psnr_srgb, v.median_depth_error_m, v.image
            );
        }
        let brief = |e: &lightfuse::eval::pose::PoseError| {
            format!(
                "{:.2} deg, {:.2} cm",
                e.rotation_deg,
                100.0 * e.translation_m
            )
        };
        for p in &report.pose_errors {
            let before = match (&p.registered, &p.aligned, &p.polished, &p.turned) {
                (r, Some(a), Some(q), Some(t)) => format!(
                    " (registered: {}; aligned: {}; polished: {}; turned: {})",
                    r.as_ref().map_or("none".into(), brief),
                    brief(a),
                    brief(q),
                    brief(t)
                ),
                _ => String::new(),
            };
            eprintln!(
                "  pose {} {}: {:.2} deg ({:.1} deg ignoring its symmetries), {:.2} cm at its origin or symmetry centre{before}",
                p.state,
                p.object,
                p.error.rotation_deg,
                p.error.rotation_deg_raw,
                100.0 * p.error.translation_m
            );
        }
        for ((name, share), (_, purity)) in report.label_share.iter().zip(&report.label_purity) {
            eprintln!(
                "  label share {name}: {:.1}% (its surfels on its own surface: {:.1}%)",
                100.0 * share,
                100.0 * purity
            );
        }
    }
    Ok(())
}

fn refine(cli: &Cli, a: &RefineArgs) -> Result<()> {
    use lightfuse::stages::refine::{self, Settings, Switches};
    let mut settings = a.preset.pick(Settings::fast, Settings::paper);
    if let Some(n) = a.iterations {
        settings.iterations = n;
    }
    settings.seed = a.seed;
    settings.switches = Switches {
        coverage: !a.no_coverage,
        scale: !a.no_scale,
        depth: !a.no_depth,
        normal: !a.no_normal,
    };
    let report = refine::refine(&refine::Options {
        dataset: a.dataset.clone(),
        work: WorkDir::new(&a.work),
        scene: a.scene.clone(),
        settings,
        leaks: Default::default(),
        resume: a.resume,
        quiet: cli.quiet || cli.json,
    })?;
    if cli.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&report).expect("report serialises")
        );
    } else if !cli.quiet {
        let (b, f) = (&report.before, &report.after);
        eprintln!(
            "wrote {}: {} surfels ({} pruned) in {:.0} s; held-out views, ray traced, before -> after:",
            WorkDir::new(&a.work).refined().display(),
            report.surfels_after,
            report.pruned,
            report.seconds
        );
        eprintln!(
            "  median depth error {:.2} -> {:.2} cm; mean normal error {:.2} -> {:.2} deg",
            100.0 * b.depth_median_m,
            100.0 * f.depth_median_m,
            b.normal_mean_deg,
            f.normal_mean_deg
        );
        eprintln!(
            "  holes {:.2}% -> {:.2}%; false occlusion {:.2}% -> {:.2}%; light leaks {:.2}% -> {:.2}% of {} blocked shadow rays",
            100.0 * b.holes,
            100.0 * f.holes,
            100.0 * b.false_occlusion,
            100.0 * f.false_occlusion,
            100.0 * b.light_leaks,
            100.0 * f.light_leaks,
            f.blocked_rays
        );
    }
    Ok(())
}

fn invert(cli: &Cli, a: &InvertArgs) -> Result<()> {
    use lightfuse::stages::invert::{self, Settings};
    let settings = a
        .stage3
        .apply(a.preset.pick(Settings::fast, Settings::paper))?;
    if a.eval_spp == 0 || a.eval_stride == 0 {
        return Err(Error::Usage(
            "--eval-spp and --eval-stride: expected at least 1".into(),
        ));
    }
    let report = invert::invert(&invert::Options {
        dataset: a.dataset.clone(),
        work: WorkDir::new(&a.work),
        scene: a.scene.clone(),
        settings,
        eval_spp: a.eval_spp,
        eval_stride: a.eval_stride,
        resume: a.resume,
        quiet: cli.quiet || cli.json,
    })?;
    if cli.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&report).expect("report serialises")
        );
    } else if !cli.quiet {
        eprintln!(
            "wrote {} and .usda: {} surfels, {} iterations in {:.0} s",
            WorkDir::new(&a.work).relightable().display(),
            report.surfels,
            report.iterations,
            report.seconds
        );
        let split = |f: &lightfuse::eval::stage3::ImageFigures| {
            let db = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
            format!(
                "surface {} / sky {}",
                db(f.psnr_srgb_surface_db),
                db(f.psnr_srgb_background_db)
            )
        };
        for s in &report.states {
            eprintln!(
                "  {}: training views {:.2} dB HDR / {:.2} dB sRGB ({}); held-out {:.2} / {:.2} dB ({})",
                s.state,
                s.training.psnr_hdr_db,
                s.training.psnr_srgb_db,
                split(&s.training),
                s.heldout.psnr_hdr_db,
                s.heldout.psnr_srgb_db,
                split(&s.heldout)
            );
        }
        if let Some(a) = &report.albedo {
            eprintln!(
                "  base colour against the albedo pass: {:.1} % raw, {:.1} % after the median ratio",
                100.0 * a.raw_error,
                100.0 * a.scaled_error
            );
            if let Some(u) = &a.uniformity {
                eprintln!(
                    "  ghost shadows: {:.1} % of the {} pixels on {} surfaces of uniform albedo more than 15 % off their median",
                    100.0 * u.ghost_share,
                    u.pixels,
                    u.surfaces
                );
            }
        }
    }
    Ok(())
}

fn evaluate(cli: &Cli, a: &EvaluateArgs) -> Result<()> {
    use lightfuse::eval::relight;
    let work = WorkDir::new(&a.work);
    let report = relight::evaluate(&relight::Options {
        dataset: a.dataset.clone(),
        work: work.clone(),
        spp: a.spp,
        bounces: a.bounces,
        seed: a.seed,
        images: !a.no_images,
        denoise: !a.no_denoise,
        selection: lightfuse::eval::tables::Selection::parse(&a.rows, &a.tables)?,
        quiet: cli.quiet || cli.json,
    })?;
    if cli.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&report).expect("report serialises")
        );
    } else if !cli.quiet {
        eprintln!(
            "wrote {} and {} in {:.0} s\n",
            work.eval_md().display(),
            work.report_html().display(),
            report.seconds
        );
        println!("{}", lightfuse::eval::tables::markdown(&report));
    }
    Ok(())
}

fn run_all(cli: &Cli, a: &RunArgs) -> Result<()> {
    use lightfuse::stages::pipeline;
    let work = WorkDir::new(&a.out);
    let steps = pipeline::run(&pipeline::Options {
        dataset: a.dataset.clone(),
        work: work.clone(),
        preset: a.preset,
        force: a.force,
        denoise: !a.no_denoise,
        invert: a.stage3.clone(),
        quiet: cli.quiet || cli.json,
    })?;
    let eval_md = work.eval_md();
    if cli.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&steps).expect("steps serialise")
        );
    } else if !cli.quiet {
        for s in &steps {
            eprintln!("  {}: {} ({:.0} s)", s.step, s.outcome, s.seconds);
        }
        let table = std::fs::read_to_string(&eval_md).map_err(|e| Error::io(&eval_md, e))?;
        println!("{table}");
        eprintln!("the report: {}", work.report_html().display());
    }
    Ok(())
}
