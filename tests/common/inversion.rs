//! Stage 3 set up on a known scene as `lightfuse invert` sets it up: the training states from
//! each state's captures and poses, and every surfel at the settings' initial material.

use super::surfel_scenes::camera;
use glam::Vec3;
use lightfuse::io::dataset::Observation;
use lightfuse::scene::{Environment, Scene};
use lightfuse::shade::envmap::{uv_to_direction, EnvMap};
use lightfuse::shade::estimator::{self_hit_epsilon, Estimator, PixelFilter, DEFAULT_FILTER_WIDTH};
use lightfuse::stages::invert::cache::TrainState;
use lightfuse::stages::invert::train::Settings;
use lightfuse::trace::TraceScene;

/// One training state per state of `scene`, seeing `captures[k]` (every view of state k).
pub fn train_states<'a>(scene: &Scene, captures: &'a [Vec<Observation>]) -> Vec<TrainState<'a>> {
    captures
        .iter()
        .enumerate()
        .map(|(k, views)| TrainState {
            views: views.iter().collect(),
            transforms: scene.states[k].transforms.clone(),
            eps: self_hit_epsilon(scene, &scene.states[k]),
        })
        .collect()
}

/// Every surfel of `scene` at the settings' initial base colour, metallic and roughness (the
/// grey that stage 3 starts from).
pub fn grey_start(scene: &mut Scene, settings: &Settings) {
    for c in &mut scene.components {
        for i in 0..c.surfels.len() {
            c.surfels.base_color[i] = [settings.init_base_color; 3];
            c.surfels.metallic[i] = settings.init_metallic;
            c.surfels.roughness[i] = settings.init_roughness;
        }
    }
}

/// A smooth sky: a vertical gradient, a coloured horizon band and a small bright sun at `sun`
/// (cos²⁵⁶: ~4° across).
pub fn sky(ew: usize, eh: usize, sun: Vec3, tint: [f32; 3]) -> Environment {
    let px = (0..ew * eh)
        .map(|i| {
            let (x, y) = (i % ew, i / ew);
            let d = uv_to_direction([(x as f32 + 0.5) / ew as f32, (y as f32 + 0.5) / eh as f32]);
            let up = d.y.max(0.0);
            let sunny = (d.dot(sun).max(0.0)).powi(256) * 150.0;
            [0, 1, 2].map(|c| (0.3 + 0.7 * up) * tint[c] + sunny + 0.1)
        })
        .collect();
    Environment::new("sky", ew, eh, px)
}

/// `cam` turned about the world's vertical by `yaw` degrees after being pitched up by `pitch`
/// degrees about its own x axis: R = R_y(yaw) R_x(pitch).
pub fn oriented(
    mut cam: lightfuse::scene::Camera,
    yaw: f32,
    pitch: f32,
) -> lightfuse::scene::Camera {
    let r = glam::Mat3::from_rotation_y(yaw.to_radians())
        * glam::Mat3::from_rotation_x(pitch.to_radians());
    let m = &mut cam.transform_matrix;
    for (i, row) in m.iter_mut().take(3).enumerate() {
        for (j, v) in row.iter_mut().take(3).enumerate() {
            *v = r.col(j)[i];
        }
    }
    cam
}

/// Captures of `scene`'s states, state k under `envs[k]`: eight cameras per state (three 48x48
/// of the objects, five 32x32 of the sky), rendered by LightFuse at `spp`, with planar depth.
pub fn captures(scene: &Scene, envs: &[Environment], spp: u32) -> Vec<Vec<Observation>> {
    let trace = TraceScene::new(scene);
    let filter = PixelFilter::new(DEFAULT_FILTER_WIDTH);
    scene
        .states
        .iter()
        .enumerate()
        .map(|(k, st)| {
            let placed = trace.place_state(st);
            let map = EnvMap::new(&envs[k], 0.0);
            let est = Estimator::new(&placed, &map, self_hit_epsilon(scene, st));
            // Three views of the objects, and five of the sky from above the floor: one
            // straight up (~120° across) and four at 25° in the four compass directions (~90°
            // across), so every direction above the horizon is seen and the captures, not the
            // optimiser's prior, decide the environment (and with it the albedos' scale).
            let objects = [-0.7f32, 0.0, 0.7].map(|x| (Vec3::new(x, 0.2, 2.4), 0.0, 0.0, 40.0, 48));
            let up = Vec3::new(0.0, 0.8, 0.0);
            let sky = [
                (up, 0.0, 90.0, 9.0, 32),
                (up, 0.0, 25.0, 16.0, 32),
                (up, 90.0, 25.0, 16.0, 32),
                (up, 180.0, 25.0, 16.0, 32),
                (up, 270.0, 25.0, 16.0, 32),
            ];
            objects
                .iter()
                .chain(&sky)
                .enumerate()
                .map(|(v, &(eye, yaw, pitch, fl, size))| {
                    let cam = oriented(camera(eye, size, size, fl), yaw, pitch);
                    observe(&est, &filter, cam, (k, v), spp, 77)
                })
                .collect()
        })
        .collect()
}

/// View `at` = (state, view) as `cam` sees it through `est`: every pixel at `spp` samples of
/// seed `seed`, with planar depth and normals, no object mask.
pub fn observe(
    est: &Estimator,
    filter: &PixelFilter,
    cam: lightfuse::scene::Camera,
    at: (usize, usize),
    spp: u32,
    seed: u32,
) -> Observation {
    let n = cam.w * cam.h;
    let pixels: Vec<_> = (0..n)
        .map(|i| est.pixel(&cam, filter, (i % cam.w, i / cam.w), spp, seed))
        .collect();
    Observation {
        state: at.0,
        view: at.1,
        camera: cam,
        rgb: pixels.iter().map(|p| p.rgb).collect(),
        depth: pixels.iter().map(|p| p.depth).collect(),
        normal: pixels.iter().map(|p| p.normal).collect(),
        mask: vec![0; n as usize],
    }
}

/// The two training skies of the tests' known scenes: a blue one with the sun up to the
/// south-east, a warm one with it lower to the north-west.
pub fn two_skies(ew: usize, eh: usize) -> Vec<Environment> {
    vec![
        sky(
            ew,
            eh,
            Vec3::new(0.5, 0.7, 0.5).normalize(),
            [0.5, 0.7, 1.0],
        ),
        sky(
            ew,
            eh,
            Vec3::new(-0.6, 0.5, -0.3).normalize(),
            [1.0, 0.8, 0.6],
        ),
    ]
}
