//! Adam (Kingma & Ba 2015) over named parameter groups, with the settings and the state handling
//! of 3DGS: β1 = 0.9, β2 = 0.999, ε = 1e-15, bias correction, one step counter per group,
//! per-group learning-rate schedules (constant, or the exponential decay 3DGS uses for
//! positions), and moments that follow densification (new points start with zero moments, the
//! group's step counter goes on) and pruning (keep a subset of points by index).
//!
//! The optimiser owns only its state; parameters and gradients stay with the caller as flat
//! `f32` slices, one per group, laid out point-major with `width` values per point (3 for
//! positions, 48 for degree-3 SH, 1 for opacities; any width for non-point groups such as
//! environment texels, which are never resized). The whole state is serde-serialisable for
//! checkpoints; after loading one, [`Adam::validate`] and [`Adam::expect_group`] turn a file
//! that does not fit into an [`Error::invalid`].

use crate::error::{Error, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Parameters per rayon task in [`Adam::step`].
const CHUNK: usize = 1 << 14;

/// One update's constants: β1, β2, 1 − β1, 1 − β2, ε, the learning rate, and the bias-corrected
/// step size lr / (1 − β1^t) and 1 / √(1 − β2^t) at the update's step t.
struct Coefficients {
    b1: f32,
    b2: f32,
    c1: f32,
    c2: f32,
    eps: f32,
    lr: f32,
    step_size: f32,
    inv_sqrt_bc2: f32,
}

/// Learning rate as a function of the group's step counter t (0 for the first update).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Schedule {
    Constant {
        lr: f32,
    },
    /// Log-linear from `lr_init` at t = 0 to `lr_final` at t = `steps`, then constant (3DGS
    /// `get_expon_lr_func` without its delay): lr(t) = exp((1 − s) ln lr_init + s ln lr_final),
    /// s = min(t / steps, 1).
    Exponential {
        lr_init: f32,
        lr_final: f32,
        steps: u64,
    },
}

impl Schedule {
    pub fn lr(&self, t: u64) -> f32 {
        match *self {
            Schedule::Constant { lr } => lr,
            Schedule::Exponential {
                lr_init,
                lr_final,
                steps,
            } => {
                let s = if steps == 0 {
                    1.0
                } else {
                    (t as f64 / steps as f64).min(1.0)
                };
                ((1.0 - s) * (lr_init as f64).ln() + s * (lr_final as f64).ln()).exp() as f32
            }
        }
    }

    fn check(&self) -> std::result::Result<(), String> {
        let ok = |v: f32| v.is_finite() && v >= 0.0;
        match *self {
            Schedule::Constant { lr } if ok(lr) => Ok(()),
            Schedule::Exponential {
                lr_init, lr_final, ..
            } if ok(lr_init) && ok(lr_final) && lr_init > 0.0 && lr_final > 0.0 => Ok(()),
            Schedule::Constant { .. } => Err("expected a finite learning rate >= 0".into()),
            Schedule::Exponential { .. } => {
                Err("expected finite learning rates > 0 for an exponential schedule".into())
            }
        }
    }
}

/// One parameter group: its schedule and its Adam state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Group {
    pub name: String,
    /// Values per point (the unit of [`Adam::append_points`] and [`Adam::keep_points`]).
    pub width: usize,
    pub schedule: Schedule,
    /// Updates applied so far.
    step: u64,
    /// First and second moment estimates, one per parameter.
    exp_avg: Vec<f32>,
    exp_avg_sq: Vec<f32>,
}

impl Group {
    pub fn len(&self) -> usize {
        self.exp_avg.len()
    }

    pub fn is_empty(&self) -> bool {
        self.exp_avg.is_empty()
    }

    pub fn points(&self) -> usize {
        self.len() / self.width
    }

    pub fn steps(&self) -> u64 {
        self.step
    }

    pub fn exp_avg(&self) -> &[f32] {
        &self.exp_avg
    }

    pub fn exp_avg_sq(&self) -> &[f32] {
        &self.exp_avg_sq
    }

    /// The learning rate the next update will use.
    pub fn lr(&self) -> f32 {
        self.schedule.lr(self.step)
    }
}

/// Adam with parameter groups; see the module doc.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// Kept in f64 so that 1 − β is exact enough (0.999 is not an f32), as in PyTorch.
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    groups: Vec<Group>,
}

impl Default for Adam {
    fn default() -> Self {
        Self::new()
    }
}

impl Adam {
    /// No groups, 3DGS hyper-parameters.
    pub fn new() -> Self {
        Adam {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
            groups: Vec::new(),
        }
    }

    /// Adds a group of `len` parameters (`width` per point) with zero moments; returns its
    /// index. Names must be unique.
    pub fn add_group(&mut self, name: &str, len: usize, width: usize, schedule: Schedule) -> usize {
        assert!(width > 0, "group {name}: width must be positive");
        assert!(
            len % width == 0,
            "group {name}: {len} values are not whole points of width {width}"
        );
        assert!(
            self.group_index(name).is_none(),
            "group {name} already exists"
        );
        if let Err(m) = schedule.check() {
            panic!("group {name}: {m}");
        }
        self.groups.push(Group {
            name: name.to_string(),
            width,
            schedule,
            step: 0,
            exp_avg: vec![0.0; len],
            exp_avg_sq: vec![0.0; len],
        });
        self.groups.len() - 1
    }

    pub fn group_index(&self, name: &str) -> Option<usize> {
        self.groups.iter().position(|g| g.name == name)
    }

    pub fn groups(&self) -> &[Group] {
        &self.groups
    }

    pub fn group(&self, g: usize) -> &Group {
        &self.groups[g]
    }

    pub fn set_schedule(&mut self, g: usize, schedule: Schedule) {
        if let Err(m) = schedule.check() {
            panic!("group {}: {m}", self.groups[g].name);
        }
        self.groups[g].schedule = schedule;
    }

    /// Group `g` checked against the lengths of an update's parameters and gradients, its step
    /// counter advanced, and the update's coefficients at the new step (shared by [`Adam::step`]
    /// and [`Adam::step_shared`]).
    fn begin(&mut self, g: usize, params: usize, grads: usize) -> (&mut Group, Coefficients) {
        let (b1, b2) = (self.beta1, self.beta2);
        let eps = self.eps as f32;
        let group = &mut self.groups[g];
        assert_eq!(
            params,
            group.len(),
            "group {}: {} parameters, the optimiser holds {}",
            group.name,
            params,
            group.len()
        );
        assert_eq!(grads, params, "group {}: gradient length", group.name);
        let lr = group.schedule.lr(group.step) as f64;
        group.step += 1;
        let t = group.step as i32;
        let coefficients = Coefficients {
            b1: b1 as f32,
            b2: b2 as f32,
            c1: (1.0 - b1) as f32,
            c2: (1.0 - b2) as f32,
            eps,
            lr: lr as f32,
            step_size: (lr / (1.0 - b1.powi(t))) as f32,
            inv_sqrt_bc2: (1.0 / (1.0 - b2.powi(t)).sqrt()) as f32,
        };
        (group, coefficients)
    }

    /// One Adam update of group `g` (PyTorch's formulation):
    /// m ← β1 m + (1 − β1) g, v ← β2 v + (1 − β2) g², t ← t + 1,
    /// p ← p − lr(t − 1) / (1 − β1^t) · m / (√v / √(1 − β2^t) + ε).
    pub fn step(&mut self, g: usize, params: &mut [f32], grads: &[f32]) {
        let (group, k) = self.begin(g, params.len(), grads.len());
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks(CHUNK))
            .zip(group.exp_avg.par_chunks_mut(CHUNK))
            .zip(group.exp_avg_sq.par_chunks_mut(CHUNK))
            .for_each(|(((p, gr), m), v)| {
                for (((p, &g), m), v) in p.iter_mut().zip(gr).zip(m).zip(v) {
                    *m = k.b1 * *m + k.c1 * g;
                    *v = k.b2 * *v + k.c2 * g * g;
                    *p -= k.step_size * *m / (v.sqrt() * k.inv_sqrt_bc2 + k.eps);
                }
            });
    }

    /// One update of group `g` whose second moment is shared by the whole group (NovoGrad's
    /// layer-wise moment, Ginsburg et al. 2019): v ← β2 v + (1 − β2) mean(g²) for every
    /// parameter, the first moment and the step as [`Adam::step`], each parameter's step then
    /// limited to `max_step` times the learning rate. Parameters keep their relative gradient
    /// sizes: one whose gradient is consistently ten times another's moves ten times as far,
    /// where per-parameter Adam moves both by about the learning rate. The limit bounds the
    /// step of a parameter that carries nearly all the gradient (√len times the learning rate
    /// unbounded).
    pub fn step_shared(&mut self, g: usize, params: &mut [f32], grads: &[f32], max_step: f32) {
        let mean_sq = (grads.iter().map(|&g| g as f64 * g as f64).sum::<f64>()
            / grads.len().max(1) as f64) as f32;
        let (group, k) = self.begin(g, params.len(), grads.len());
        let limit = max_step * k.lr;
        for (((p, &g), m), v) in params
            .iter_mut()
            .zip(grads)
            .zip(&mut group.exp_avg)
            .zip(&mut group.exp_avg_sq)
        {
            *m = k.b1 * *m + k.c1 * g;
            *v = k.b2 * *v + k.c2 * mean_sq;
            let d = k.step_size * *m / (v.sqrt() * k.inv_sqrt_bc2 + k.eps);
            *p -= d.clamp(-limit, limit);
        }
    }

    /// Densification: `count` new points at the end of group `g`, with zero moments (3DGS).
    pub fn append_points(&mut self, g: usize, count: usize) {
        let group = &mut self.groups[g];
        let len = group.len() + count * group.width;
        group.exp_avg.resize(len, 0.0);
        group.exp_avg_sq.resize(len, 0.0);
    }

    /// Pruning (or any gather): group `g` becomes the points `keep` of the old group, in that
    /// order, with their moments.
    pub fn keep_points(&mut self, g: usize, keep: &[usize]) {
        let group = &mut self.groups[g];
        let (w, points) = (group.width, group.points());
        let gather = |src: &[f32]| -> Vec<f32> {
            keep.iter()
                .flat_map(|&k| {
                    assert!(k < points, "keep index {k} out of {points} points",);
                    src[k * w..(k + 1) * w].iter().copied()
                })
                .collect()
        };
        group.exp_avg = gather(&group.exp_avg);
        group.exp_avg_sq = gather(&group.exp_avg_sq);
    }

    /// Checks a deserialised optimiser (e.g. from a checkpoint `file`) for internal consistency.
    pub fn validate(&self, file: &Path) -> Result<()> {
        let unit = |v: f64| (0.0..1.0).contains(&v);
        if !unit(self.beta1) || !unit(self.beta2) {
            return Err(Error::invalid(
                file,
                "optimizer.beta1/beta2",
                format!(
                    "expected betas in [0, 1), found {} and {}",
                    self.beta1, self.beta2
                ),
            ));
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return Err(Error::invalid(
                file,
                "optimizer.eps",
                format!("expected a positive epsilon, found {}", self.eps),
            ));
        }
        for (i, g) in self.groups.iter().enumerate() {
            let field = |f: &str| format!("optimizer.groups[{i}] ({}).{f}", g.name);
            if self.groups[..i].iter().any(|o| o.name == g.name) {
                return Err(Error::invalid(file, field("name"), "duplicate group name"));
            }
            g.schedule
                .check()
                .map_err(|m| Error::invalid(file, field("schedule"), m))?;
            if g.width == 0 || g.exp_avg.len() % g.width != 0 {
                return Err(Error::invalid(
                    file,
                    field("width"),
                    format!(
                        "expected a positive width dividing {} values, found {}",
                        g.exp_avg.len(),
                        g.width
                    ),
                ));
            }
            if g.exp_avg_sq.len() != g.exp_avg.len() {
                return Err(Error::invalid(
                    file,
                    field("exp_avg_sq"),
                    format!(
                        "expected {} values like exp_avg, found {}",
                        g.exp_avg.len(),
                        g.exp_avg_sq.len()
                    ),
                ));
            }
            if g.exp_avg.iter().any(|v| !v.is_finite()) {
                return Err(Error::invalid(
                    file,
                    field("exp_avg"),
                    "expected finite values",
                ));
            }
            if g.exp_avg_sq.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
                return Err(Error::invalid(
                    file,
                    field("exp_avg_sq"),
                    "expected finite values >= 0",
                ));
            }
        }
        Ok(())
    }

    /// The index of group `name`, checked to hold `len` parameters; an error naming `file` if
    /// the checkpoint does not have it.
    pub fn expect_group(&self, file: &Path, name: &str, len: usize) -> Result<usize> {
        let g = self.group_index(name).ok_or_else(|| {
            Error::invalid(
                file,
                "optimizer.groups",
                format!("expected a group named {name}"),
            )
        })?;
        if self.groups[g].len() != len {
            return Err(Error::invalid(
                file,
                format!("optimizer.groups[{g}] ({name})"),
                format!(
                    "expected {len} values to match the scene, found {}",
                    self.groups[g].len()
                ),
            ));
        }
        Ok(g)
    }
}
