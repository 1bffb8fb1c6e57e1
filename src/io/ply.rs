//! Export in the standard 3DGS PLY layout read by splat tools (viewers, editors, converters):
//! binary little-endian, `x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3`, with
//! log scale, logit opacity, channel-major `f_rest`, and the quaternion as (w, x, y, z).
//!
//! A PLY has no states, components or materials: it holds one placement of the whole scene.

use super::AtomicFiles;
use crate::error::Result;
use crate::scene::{quat_axes, sh_coeffs, Scene, State};
use std::io::Write;
use std::path::Path;

/// Log-scale written for the flat third axis: 1 µm, far below any surfel, so 3DGS renderers
/// draw flat discs, while log(0) would be −∞.
pub const FLAT_LOG_SCALE: f32 = -13.815_511; // ln(1e-6)
/// Opacity is clamped away from 0 and 1 so its logit stays finite.
const OPACITY_EPS: f32 = 1e-6;

fn logit(a: f32) -> f32 {
    let a = a.clamp(OPACITY_EPS, 1.0 - OPACITY_EPS);
    (a / (1.0 - a)).ln()
}

/// Writes every component placed as in `state` (the reference state if `None`).
pub fn write(scene: &Scene, path: &Path) -> Result<()> {
    write_state(scene, &scene.states[scene.reference_state], path)
}

pub fn write_state(scene: &Scene, state: &State, path: &Path) -> Result<()> {
    let degree = scene
        .components
        .iter()
        .map(|c| c.surfels.sh_degree)
        .max()
        .unwrap_or(0);
    let rest = sh_coeffs(degree) - 1;
    let n = scene.surfel_count();
    let mut header =
        String::from("ply\nformat binary_little_endian 1.0\ncomment written by LightFuse\n");
    header += &format!("element vertex {n}\n");
    for p in [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ] {
        header += &format!("property float {p}\n");
    }
    for k in 0..3 * rest {
        header += &format!("property float f_rest_{k}\n");
    }
    for p in [
        "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        header += &format!("property float {p}\n");
    }
    header += "end_header\n";
    let mut files = AtomicFiles::new();
    files.write_with(path, |w| {
        w.write_all(header.as_bytes())?;
        let mut row: Vec<f32> = Vec::with_capacity(17 + 3 * rest);
        for (c, t) in scene.components.iter().zip(&state.transforms) {
            let s = &c.surfels;
            for i in 0..s.len() {
                row.clear();
                let q = t.transform_rotation(s.rotation[i]);
                row.extend_from_slice(&t.transform_point(s.position[i]));
                row.extend_from_slice(&quat_axes(q)[2]);
                let sh = s.sh_of(i);
                row.extend_from_slice(&sh[0]);
                for ch in 0..3 {
                    row.extend((1..=rest).map(|j| sh.get(j).map_or(0.0, |c| c[ch])));
                }
                row.push(logit(s.opacity[i]));
                row.extend_from_slice(&[s.scale[i][0].ln(), s.scale[i][1].ln(), FLAT_LOG_SCALE]);
                row.extend_from_slice(&[q[3], q[0], q[1], q[2]]);
                w.write_all(bytemuck::cast_slice(&row))?;
            }
        }
        Ok(())
    })?;
    files.commit()
}
