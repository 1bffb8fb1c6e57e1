//! The scene model: surfels grouped into components (background + named objects), states that
//! place the objects and light the scene, layouts, cameras and environment maps.

pub mod camera;
pub mod color;
pub mod edit;
pub mod environment;
pub mod layout;
pub mod material;
pub mod mesh;
pub mod surfelize;
pub mod surfels;
pub mod symmetry;
pub mod synthetic;
pub mod transform;

pub use camera::Camera;
pub use edit::{Edit, MaterialChange, MaterialEdit};
pub use environment::Environment;
pub use layout::Layout;
pub use material::Material;
pub use surfels::{quat_axes, sh_coeffs, Surfels, MAX_SH_DEGREE, SH_C0};
pub use symmetry::Symmetry;
pub use transform::Rigid;

use crate::error::{Error, Result};
use std::path::Path;

/// Name of component 0.
pub const BACKGROUND: &str = "background";

/// A group of surfels that moves as one: the background (index 0, never moves) or an object.
#[derive(Clone, Debug, PartialEq)]
pub struct Component {
    pub name: String,
    /// Object-mask value in the dataset (0 = background).
    pub id: u32,
    pub surfels: Surfels,
}

/// Which environment lights a state, and its rotation about +Y.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EnvRef {
    /// Index into [`Scene::environments`].
    pub index: usize,
    /// Degrees about +Y (Cycles' mapping Z rotation after the axis change).
    pub rotation_deg: f32,
}

/// One captured (or edited) configuration: a rigid transform per component relative to the
/// reference state (index 0, the background, is always identity) and its lighting.
#[derive(Clone, Debug, PartialEq)]
pub struct State {
    pub name: String,
    pub transforms: Vec<Rigid>,
    pub environment: Option<EnvRef>,
}

/// A LightFuse scene: what `scene.glb` and `scene.usda` hold.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    pub components: Vec<Component>,
    pub states: Vec<State>,
    /// Index of the state whose world frame the object surfels live in.
    pub reference_state: usize,
    pub environments: Vec<Environment>,
}

impl Scene {
    /// A scene with only a background and one identity state called `state0`.
    pub fn from_background(surfels: Surfels) -> Scene {
        Scene {
            components: vec![Component {
                name: BACKGROUND.into(),
                id: 0,
                surfels,
            }],
            states: vec![State {
                name: "state0".into(),
                transforms: vec![Rigid::IDENTITY],
                environment: None,
            }],
            reference_state: 0,
            environments: Vec::new(),
        }
    }

    pub fn surfel_count(&self) -> usize {
        self.components.iter().map(|c| c.surfels.len()).sum()
    }

    pub fn component_index(&self, name: &str) -> Option<usize> {
        self.components.iter().position(|c| c.name == name)
    }

    pub fn state_index(&self, name: &str) -> Option<usize> {
        self.states.iter().position(|s| s.name == name)
    }

    /// Checks that the parts agree with each other and every surfel is valid. `file` names the
    /// source in errors.
    pub fn validate(&self, file: &Path) -> Result<()> {
        if self.components.is_empty() {
            return Err(Error::invalid(
                file,
                "components",
                "expected at least the background component",
            ));
        }
        let mut seen = std::collections::HashSet::new();
        for (i, c) in self.components.iter().enumerate() {
            if c.name.is_empty() {
                return Err(Error::invalid(
                    file,
                    format!("components[{i}].name"),
                    "expected a non-empty name",
                ));
            }
            if !seen.insert(c.name.as_str()) {
                return Err(Error::invalid(
                    file,
                    format!("components[{i}].name"),
                    format!("expected unique names, \"{}\" appears twice", c.name),
                ));
            }
            c.surfels
                .validate(file, &format!("component \"{}\"", c.name))?;
        }
        if self.states.is_empty() {
            return Err(Error::invalid(
                file,
                "states",
                "expected at least one state",
            ));
        }
        if self.reference_state >= self.states.len() {
            return Err(Error::invalid(
                file,
                "referenceState",
                format!(
                    "expected an index below {}, found {}",
                    self.states.len(),
                    self.reference_state
                ),
            ));
        }
        let mut names = std::collections::HashSet::new();
        for (k, s) in self.states.iter().enumerate() {
            let field = |f: &str| format!("states[{k}] \"{}\": {f}", s.name);
            if !names.insert(s.name.as_str()) {
                return Err(Error::invalid(
                    file,
                    field("name"),
                    "expected unique state names",
                ));
            }
            if s.transforms.len() != self.components.len() {
                return Err(Error::invalid(
                    file,
                    field("transforms"),
                    format!(
                        "expected one per component ({}), found {}",
                        self.components.len(),
                        s.transforms.len()
                    ),
                ));
            }
            if !s.transforms[0].is_identity() {
                return Err(Error::invalid(
                    file,
                    field("background transform"),
                    "expected identity: the background never moves",
                ));
            }
            for (o, t) in s.transforms.iter().enumerate() {
                let n2: f32 = t.rotation.iter().map(|x| x * x).sum();
                if t.rotation
                    .iter()
                    .chain(&t.translation)
                    .any(|x| !x.is_finite())
                    || (n2 - 1.0).abs() > 1e-3
                {
                    return Err(Error::invalid(
                        file,
                        field(&format!("transform of \"{}\"", self.components[o].name)),
                        "expected a unit quaternion and a finite translation",
                    ));
                }
            }
            if let Some(e) = s.environment {
                if e.index >= self.environments.len() {
                    return Err(Error::invalid(
                        file,
                        field("environment"),
                        format!(
                            "expected an index below {}, found {}",
                            self.environments.len(),
                            e.index
                        ),
                    ));
                }
                if !e.rotation_deg.is_finite() {
                    return Err(Error::invalid(
                        file,
                        field("environmentRotation"),
                        "expected a finite angle",
                    ));
                }
            }
        }
        for (i, env) in self.environments.iter().enumerate() {
            if env.width == 0 || env.height == 0 || env.pixels.len() != env.width * env.height {
                return Err(Error::invalid(
                    file,
                    format!("environments[{i}]"),
                    "expected a non-empty image",
                ));
            }
            if let Some(p) = env
                .pixels
                .iter()
                .flatten()
                .find(|x| !x.is_finite() || **x < 0.0)
            {
                return Err(Error::invalid(
                    file,
                    format!("environments[{i}] \"{}\"", env.name),
                    format!("expected finite non-negative radiance, found {p}"),
                ));
            }
        }
        Ok(())
    }

    /// The state with the given layout applied: objects the layout names take its transform,
    /// the others keep the reference state's placement (identity).
    pub fn state_from_layout(&self, name: &str, layout: &Layout, file: &Path) -> Result<State> {
        let mut transforms = vec![Rigid::IDENTITY; self.components.len()];
        for (obj, t) in &layout.objects {
            let idx = self
                .component_index(obj)
                .filter(|&i| i != 0)
                .ok_or_else(|| {
                    let known: Vec<_> = self.components[1..]
                        .iter()
                        .map(|c| c.name.as_str())
                        .collect();
                    Error::invalid(
                        file,
                        format!("objects.{obj}"),
                        format!("expected one of the scene's objects {known:?}"),
                    )
                })?;
            transforms[idx] = *t;
        }
        Ok(State {
            name: name.into(),
            transforms,
            environment: None,
        })
    }

    /// Bounds of all surfel centres in a state's placement (None for an empty scene).
    pub fn bounds_in_state(&self, state: &State) -> Option<([f32; 3], [f32; 3])> {
        let all =
            (0..self.components.len()).filter_map(|i| self.component_bounds_in_state(i, state));
        all.reduce(|(lo, hi), (l, h)| {
            (
                std::array::from_fn(|k| lo[k].min(l[k])),
                std::array::from_fn(|k| hi[k].max(h[k])),
            )
        })
    }

    /// Bounds of one component's surfel centres placed as in `state`.
    pub fn component_bounds_in_state(
        &self,
        component: usize,
        state: &State,
    ) -> Option<([f32; 3], [f32; 3])> {
        let t = state.transforms[component];
        let mut out: Option<([f32; 3], [f32; 3])> = None;
        for p in &self.components[component].surfels.position {
            let q = t.transform_point(*p);
            let (lo, hi) = out.get_or_insert((q, q));
            for k in 0..3 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        out
    }
}
