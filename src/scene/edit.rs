//! Scene edits (paper § "Scene Editing and Relighting"): a new named state made from an existing
//! one by a rearrangement (a layout), per-object material changes and a new environment.
//!
//! Materials live on the surfels and are shared by every state (as stage 3 recovers them), so a
//! material edit changes the object in every state of the written scene; the placement and the
//! environment belong to the new state alone.

use super::{EnvRef, Environment, Layout, Scene};
use crate::error::{Error, Result};
use std::path::{Path, PathBuf};

/// One per-object material change (`OBJECT:base_color=R,G,B`, `OBJECT:metallic=M`,
/// `OBJECT:roughness=R`; the background is the object `background`).
#[derive(Clone, Debug, PartialEq)]
pub enum MaterialChange {
    BaseColor([f32; 3]),
    Metallic(f32),
    Roughness(f32),
}

/// A material change for the component named `object`.
#[derive(Clone, Debug, PartialEq)]
pub struct MaterialEdit {
    pub object: String,
    pub change: MaterialChange,
}

impl MaterialEdit {
    /// Parses `OBJECT:base_color=R,G,B`, `OBJECT:metallic=M` or `OBJECT:roughness=R`, every
    /// value finite and in [0, 1]; the error says what was expected.
    pub fn parse(spec: &str) -> std::result::Result<MaterialEdit, String> {
        let expected = "expected OBJECT:base_color=R,G,B, OBJECT:metallic=M or OBJECT:roughness=R with values in [0, 1]";
        let (object, rest) = spec
            .rsplit_once(':')
            .ok_or_else(|| format!("{spec:?}: {expected}"))?;
        let (field, value) = rest
            .split_once('=')
            .ok_or_else(|| format!("{spec:?}: {expected}"))?;
        let unit = |s: &str| -> std::result::Result<f32, String> {
            match s.trim().parse::<f32>() {
                Ok(v) if v.is_finite() && (0.0..=1.0).contains(&v) => Ok(v),
                _ => Err(format!(
                    "{spec:?}: {s:?} is not a number in [0, 1]; {expected}"
                )),
            }
        };
        if object.is_empty() {
            return Err(format!("{spec:?}: no object named; {expected}"));
        }
        let change = match field.trim() {
            "base_color" => {
                let v: Vec<&str> = value.split(',').collect();
                if v.len() != 3 {
                    return Err(format!(
                        "{spec:?}: base_color needs three values R,G,B; {expected}"
                    ));
                }
                MaterialChange::BaseColor([unit(v[0])?, unit(v[1])?, unit(v[2])?])
            }
            "metallic" => MaterialChange::Metallic(unit(value)?),
            "roughness" => MaterialChange::Roughness(unit(value)?),
            other => return Err(format!("{spec:?}: unknown field {other:?}; {expected}")),
        };
        Ok(MaterialEdit {
            object: object.to_string(),
            change,
        })
    }
}

/// Everything one edit does; [`Scene::apply_edit`] applies it.
#[derive(Clone, Debug, Default)]
pub struct Edit {
    /// The new state's name (must not be taken).
    pub name: String,
    /// The state it starts from (placement and environment); `None`: the reference state.
    pub from_state: Option<String>,
    /// Objects moved, relative to the reference placement (as `lightfuse render --layout`),
    /// with the file it came from for errors. Objects it does not name keep the reference
    /// placement; without a layout the starting state's placement is kept.
    pub layout: Option<(Layout, PathBuf)>,
    pub materials: Vec<MaterialEdit>,
    /// A new environment and its rotation in degrees; `None`: the starting state's.
    pub environment: Option<(Environment, f32)>,
}

impl Scene {
    /// Adds the state `edit` describes (and changes the materials it names). `file` is the
    /// scene's path, for errors. Nothing is changed when an error is returned.
    pub fn apply_edit(&mut self, edit: &Edit, file: &Path) -> Result<()> {
        if edit.name.is_empty() || self.state_index(&edit.name).is_some() {
            let names: Vec<_> = self.states.iter().map(|s| s.name.as_str()).collect();
            return Err(Error::invalid(
                file,
                "states",
                format!(
                    "the edit's state needs a new, non-empty name (--name); the scene has {names:?}, asked for {:?}",
                    edit.name
                ),
            ));
        }
        let base = match &edit.from_state {
            Some(name) => {
                let i = self.state_index(name).ok_or_else(|| {
                    let names: Vec<_> = self.states.iter().map(|s| s.name.as_str()).collect();
                    Error::invalid(
                        file,
                        "states",
                        format!("--state {name:?}: expected one of {names:?}"),
                    )
                })?;
                self.states[i].clone()
            }
            None => self.states[self.reference_state].clone(),
        };
        let mut state = match &edit.layout {
            Some((layout, path)) => {
                let mut s = self.state_from_layout(&edit.name, layout, path)?;
                s.environment = base.environment;
                s
            }
            None => {
                let mut s = base;
                s.name = edit.name.clone();
                s
            }
        };
        let targets = edit
            .materials
            .iter()
            .map(|m| {
                self.component_index(&m.object).ok_or_else(|| {
                    let known: Vec<_> = self.components.iter().map(|c| c.name.as_str()).collect();
                    Error::invalid(
                        file,
                        "components",
                        format!(
                            "--material {:?}: expected one of the scene's objects {known:?}",
                            m.object
                        ),
                    )
                })
            })
            .collect::<Result<Vec<usize>>>()?;
        // Checked: from here on nothing fails.
        for (m, &c) in edit.materials.iter().zip(&targets) {
            let s = &mut self.components[c].surfels;
            for i in 0..s.len() {
                match m.change {
                    MaterialChange::BaseColor(v) => s.base_color[i] = v,
                    MaterialChange::Metallic(v) => s.metallic[i] = v,
                    MaterialChange::Roughness(v) => s.roughness[i] = v,
                }
            }
        }
        if let Some((env, rotation)) = &edit.environment {
            self.environments.push(env.clone());
            state.environment = Some(EnvRef {
                index: self.environments.len() - 1,
                rotation_deg: *rotation,
            });
        }
        self.states.push(state);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::random_scene;
    use crate::scene::Rigid;

    #[test]
    fn material_specs_parse_and_bad_ones_say_what_was_expected() {
        assert_eq!(
            MaterialEdit::parse("chair:base_color=0.1,0.2,1").unwrap(),
            MaterialEdit {
                object: "chair".into(),
                change: MaterialChange::BaseColor([0.1, 0.2, 1.0])
            }
        );
        assert_eq!(
            MaterialEdit::parse("background:roughness=0.25")
                .unwrap()
                .change,
            MaterialChange::Roughness(0.25)
        );
        for bad in [
            "chair",
            "chair:metallic",
            "chair:metallic=2",
            "chair:metallic=nan",
            "chair:base_color=0.1,0.2",
            "chair:shininess=0.5",
            ":metallic=0.5",
        ] {
            let e = MaterialEdit::parse(bad).expect_err(bad);
            assert!(e.contains("expected") || e.contains("[0, 1]"), "{bad}: {e}");
        }
    }

    #[test]
    fn an_edit_adds_a_state_and_changes_only_what_it_names() {
        let mut scene = random_scene(2, 2, 2, 10, 0);
        let before = scene.clone();
        let mut layout = Layout::default();
        let moved = Rigid {
            rotation: [0.0, 0.0, 0.0, 1.0],
            translation: [0.5, 0.0, 0.0],
        };
        layout.objects.insert("object2".into(), moved);
        let env = Environment::new("new", 8, 4, vec![[1.0, 2.0, 3.0]; 32]);
        let edit = Edit {
            name: "edited".into(),
            from_state: None,
            layout: Some((layout, "l.json".into())),
            materials: vec![MaterialEdit::parse("object1:metallic=1").unwrap()],
            environment: Some((env, 30.0)),
        };
        scene.apply_edit(&edit, Path::new("s.glb")).unwrap();
        assert_eq!(scene.states.len(), before.states.len() + 1);
        let s = scene.states.last().unwrap();
        assert_eq!(s.name, "edited");
        assert!(s.transforms[1].is_identity());
        assert_eq!(s.transforms[2], moved);
        let e = s.environment.unwrap();
        assert_eq!((e.index, e.rotation_deg), (before.environments.len(), 30.0));
        let c1 = &scene.components[1].surfels;
        assert!(c1.metallic.iter().all(|&m| m == 1.0));
        assert_eq!(c1.base_color, before.components[1].surfels.base_color);
        assert_eq!(scene.components[2], before.components[2]);
        assert_eq!(scene.states[..before.states.len()], before.states[..]);

        // A taken name, an unknown object or state: an error naming it, nothing changed.
        let snapshot = scene.clone();
        for (bad, what) in [
            (
                Edit {
                    name: "edited".into(),
                    ..Edit::default()
                },
                "edited",
            ),
            (
                Edit {
                    name: "x".into(),
                    materials: vec![MaterialEdit::parse("lamp:metallic=0").unwrap()],
                    ..Edit::default()
                },
                "lamp",
            ),
            (
                Edit {
                    name: "y".into(),
                    from_state: Some("nowhere".into()),
                    ..Edit::default()
                },
                "nowhere",
            ),
        ] {
            let e = scene
                .apply_edit(&bad, Path::new("s.glb"))
                .expect_err(what)
                .to_string();
            assert!(e.contains(what) && e.contains("s.glb"), "{e}");
            assert_eq!(scene.states, snapshot.states);
            assert_eq!(scene.components, snapshot.components);
        }
    }
}
