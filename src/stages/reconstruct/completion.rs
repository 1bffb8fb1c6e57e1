//! Completion from depth discrepancy (paper §"Object segmentation and completion",
//! eq. completion-mask): pixels where the current reconstruction, rendered into a view of some
//! state, lies clearly *behind* what that view observed show a surface the reconstruction is
//! missing (typically one uncovered when an object moved). Their observations seed new surfels.

use crate::error::{Error, Result};
use crate::io::dataset::Observation;

/// The completion mask H = { p | D̂(p) − D*(p) > τ_D } (eq. completion-mask) of a rendered
/// depth map D̂ against the reference (observed) depth D*, row-major, 0 = no hit in both.
///
/// Pixels the render left empty (D̂ = 0) but the reference sees (D* > 0) are *included*: an
/// empty render is depth +∞, the limit of a render whose surface recedes, so they satisfy the
/// inequality; they are exactly the holes completion must fill. Pixels the reference does not
/// see (D* = 0) are never included: there is nothing observed to seed a surfel from.
pub fn completion_mask(rendered: &[f32], reference: &[f32], tau_d: f32) -> Result<Vec<bool>> {
    if rendered.len() != reference.len() {
        return Err(Error::invalid(
            "depth maps",
            "rendered",
            format!(
                "expected as many pixels as the reference ({}), found {}",
                reference.len(),
                rendered.len()
            ),
        ));
    }
    if !(tau_d.is_finite() && tau_d >= 0.0) {
        return Err(Error::invalid(
            "completion",
            "tau_d",
            format!("expected a finite threshold >= 0 metres, found {tau_d}"),
        ));
    }
    Ok(rendered
        .iter()
        .zip(reference)
        .map(|(&r, &d)| d > 0.0 && (r <= 0.0 || r - d > tau_d))
        .collect())
}

/// Points back-projected from selected pixels of an observation, to seed surfels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SeedPoints {
    /// World position from the reference planar depth through the pixel centre.
    pub position: Vec<[f32; 3]>,
    /// World unit normal from the observation; where it has none, facing the camera.
    pub normal: Vec<[f32; 3]>,
    /// Scene-linear RGB of the pixel.
    pub rgb: Vec<[f32; 3]>,
    /// Pixel footprint at that depth, metres (D / f): a natural initial surfel scale.
    pub footprint: Vec<f32>,
    /// Row-major source pixel.
    pub pixel: Vec<u32>,
    /// Mask id of the source pixel (0 = background).
    pub mask: Vec<u8>,
}

impl SeedPoints {
    pub fn len(&self) -> usize {
        self.position.len()
    }

    pub fn is_empty(&self) -> bool {
        self.position.is_empty()
    }

    /// Adds each point to `clouds[c]`, c the component whose mask id (`ids[c]`) the point
    /// carries (the background, 0, when none does), moved into that component's frame:
    /// `transforms[c]` places component c in the state the points were seen in
    /// (eq. state-assembly), whose index `state` each point records.
    pub fn add_to_components(
        &self,
        ids: &[u32],
        transforms: &[crate::scene::Rigid],
        state: u32,
        clouds: &mut [super::init::PointCloud],
    ) {
        for i in 0..self.len() {
            let c = ids
                .iter()
                .position(|&id| id == self.mask[i] as u32)
                .unwrap_or(0);
            let inv = transforms[c].inverse();
            let n = inv.quat() * glam::Vec3::from_array(self.normal[i]);
            clouds[c].push(
                inv.transform_point(self.position[i]),
                n.to_array(),
                self.rgb[i],
                self.mask[i],
                state,
                self.footprint[i],
            );
        }
    }
}

/// Back-projects the pixels of `obs` where `select` is true and the depth is positive.
pub fn seed_points(obs: &Observation, select: &[bool]) -> Result<SeedPoints> {
    let cam = &obs.camera;
    let (w, h) = (cam.w as usize, cam.h as usize);
    let field = |f: &str| format!("state {} view {}: {f}", obs.state, obs.view);
    for (name, len) in [
        ("select", select.len()),
        ("depth", obs.depth.len()),
        ("normal", obs.normal.len()),
        ("rgb", obs.rgb.len()),
        ("mask", obs.mask.len()),
    ] {
        if len != w * h {
            return Err(Error::invalid(
                "observation",
                field(name),
                format!("expected {} pixels ({w}x{h}), found {len}", w * h),
            ));
        }
    }
    let mut out = SeedPoints::default();
    for (p, _) in select.iter().enumerate().filter(|(_, &s)| s) {
        let d = obs.depth[p];
        if !(d > 0.0 && d.is_finite()) {
            continue;
        }
        let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
        let pw = cam.pixel_to_world(x, y, d);
        let n = obs.normal[p];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let normal = if len > 0.5 {
            n.map(|c| c / len)
        } else {
            let (_, dir) = cam.ray(x, y);
            dir.map(|c| -c)
        };
        out.position.push(pw);
        out.normal.push(normal);
        out.rgb.push(obs.rgb[p]);
        out.footprint.push(d / cam.fl_x.min(cam.fl_y));
        out.pixel.push(p as u32);
        out.mask.push(obs.mask[p]);
    }
    Ok(out)
}
