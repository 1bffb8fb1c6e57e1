//! Stage 3 set up on a known scene as `lightfuse invert` sets it up: the training states from
//! each state's captures and poses, and every surfel at the settings' initial material.

use lightfuse::io::dataset::Observation;
use lightfuse::scene::Scene;
use lightfuse::shade::estimator::self_hit_epsilon;
use lightfuse::stages::invert::cache::TrainState;
use lightfuse::stages::invert::train::Settings;

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
