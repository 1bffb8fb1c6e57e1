//! Stage 1, initialisation from RGB-D observations: every observed pixel becomes a world point,
//! points are thinned on a voxel grid, and the survivors become the initial surfels of the
//! background and of each object (paper §"Interactive Scene Reconstruction", eq.
//! gaussian-primitive and eq. state-assembly).
//!
//! **Back-projection.** Pixel (x, y) has its centre at (x + 0.5, y + 0.5); with planar depth z
//! along the camera's −Z axis the camera-space point is ((u − c_x) z / f_x, −(v − c_y) z / f_y,
//! −z), then the camera-to-world matrix places it (docs/design.md §2). The reference normal is used when
//! the normal pass has one (flipped to face the camera); otherwise a normal is estimated from the
//! neighbouring depth pixels of the same mask id. The footprint is the side of the pixel on the
//! surface: z / f (f = √(f_x f_y)) divided by the obliquity |cos θ| between the view ray and the
//! normal (clamped at [`MIN_OBLIQUITY`]).
//!
//! **Thinning.** [`voxel_thin`] keeps one point per occupied voxel and mask id: the point nearest
//! the voxel centre (ties broken by a total order on the point's values), carrying the mean
//! colour, the normalised mean normal (oriented like the representative's) and the smallest
//! footprint of the voxel's points. The points of a voxel are summed in that same total order,
//! so the result does not depend on the input order.
//!
//! **Frames.** The background never moves: its points from every training state share the world
//! frame. An object's surfels live in the reference state's frame (docs/design.md §2, "object frame");
//! a point seen in state k is mapped back by T_{k,o}⁻¹, the inverse of the object's pose in
//! that state (eq. state-assembly), which [`super::register`] estimates.

use crate::error::{Error, Result};
use crate::io::dataset::{Dataset, Observation};
use crate::scene::{sh_coeffs, Camera, Component, Rigid, Surfels, BACKGROUND, SH_C0};
use glam::{Mat3, Quat, Vec3};
use rayon::prelude::*;

/// Smallest |cos θ| used when the footprint is stretched for oblique views: beyond ~75° a pixel
/// covers a sliver that says little about the surface, and 4 footprints is the most we allow.
pub const MIN_OBLIQUITY: f32 = 0.25;

/// A normal pass vector shorter than this counts as "no normal" (the pass stores 0 there).
const MIN_NORMAL_LENGTH: f32 = 0.5;

/// Observed points as a struct of arrays, all in the world frame of the state they were seen in
/// unless a function says otherwise.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    /// Metres.
    pub position: Vec<[f32; 3]>,
    /// Unit normal facing the camera that saw the point.
    pub normal: Vec<[f32; 3]>,
    /// Scene-linear RGB as observed.
    pub rgb: Vec<[f32; 3]>,
    /// Object id (0 = background).
    pub mask: Vec<u8>,
    /// Index of the dataset state the point was seen in.
    pub state: Vec<u32>,
    /// Side of the pixel on the surface, metres.
    pub footprint: Vec<f32>,
}

impl PointCloud {
    pub fn len(&self) -> usize {
        self.position.len()
    }

    pub fn is_empty(&self) -> bool {
        self.position.is_empty()
    }

    pub fn push(
        &mut self,
        position: [f32; 3],
        normal: [f32; 3],
        rgb: [f32; 3],
        mask: u8,
        state: u32,
        footprint: f32,
    ) {
        self.position.push(position);
        self.normal.push(normal);
        self.rgb.push(rgb);
        self.mask.push(mask);
        self.state.push(state);
        self.footprint.push(footprint);
    }

    pub fn extend(&mut self, other: &PointCloud) {
        self.position.extend_from_slice(&other.position);
        self.normal.extend_from_slice(&other.normal);
        self.rgb.extend_from_slice(&other.rgb);
        self.mask.extend_from_slice(&other.mask);
        self.state.extend_from_slice(&other.state);
        self.footprint.extend_from_slice(&other.footprint);
    }

    /// The points at `indices`, in that order.
    pub fn select(&self, indices: &[usize]) -> PointCloud {
        PointCloud {
            position: indices.iter().map(|&i| self.position[i]).collect(),
            normal: indices.iter().map(|&i| self.normal[i]).collect(),
            rgb: indices.iter().map(|&i| self.rgb[i]).collect(),
            mask: indices.iter().map(|&i| self.mask[i]).collect(),
            state: indices.iter().map(|&i| self.state[i]).collect(),
            footprint: indices.iter().map(|&i| self.footprint[i]).collect(),
        }
    }

    /// The points whose mask id is `id`.
    pub fn with_mask(&self, id: u8) -> PointCloud {
        let idx: Vec<usize> = (0..self.len()).filter(|&i| self.mask[i] == id).collect();
        self.select(&idx)
    }

    /// Positions and normals moved by `t` (x ↦ R x + t, n ↦ R n).
    pub fn transformed(&self, t: &Rigid) -> PointCloud {
        let q = t.quat().normalize();
        let tr = Vec3::from_array(t.translation);
        let mut out = self.clone();
        out.position
            .par_iter_mut()
            .zip(out.normal.par_iter_mut())
            .for_each(|(p, n)| {
                *p = (q * Vec3::from_array(*p) + tr).to_array();
                *n = (q * Vec3::from_array(*n)).to_array();
            });
        out
    }
}

/// Options of [`backproject`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BackprojectOptions {
    /// Skip pixels on an object-mask boundary or a depth discontinuity. Their depth and colour
    /// often mix two surfaces (antialiased passes), so registration leaves them out.
    pub skip_edges: bool,
    /// A neighbour whose depth differs by more than this fraction of the pixel's depth is on
    /// another surface (used by `skip_edges` and by the normal estimate).
    pub depth_jump: f32,
}

impl Default for BackprojectOptions {
    fn default() -> Self {
        BackprojectOptions {
            skip_edges: false,
            // 5 %: a plane seen at 80° from its normal changes depth by ~tan(80°)/f ≈ 5 % of z
            // per pixel at f ≈ 120 px, so real surfaces stay connected; a step between objects
            // is far larger.
            depth_jump: 0.05,
        }
    }
}

/// World point of pixel (x, y) at planar depth z: the pixel centre (x + 0.5, y + 0.5) pushed
/// along its ray to camera-space −Z = z.
pub fn pixel_to_world(cam: &Camera, x: usize, y: usize, z: f32) -> [f32; 3] {
    cam.pixel_to_world(x as f32 + 0.5, y as f32 + 0.5, z)
}

/// Every view of one state back-projected into one cloud ([`backproject`]).
pub fn state_cloud(views: &[Observation], opts: &BackprojectOptions) -> PointCloud {
    let mut c = PointCloud::default();
    for o in views {
        c.extend(&backproject(o, opts));
    }
    c
}

/// Every pixel with depth > 0 of one observation as a world point (see the module docs).
pub fn backproject(obs: &Observation, opts: &BackprojectOptions) -> PointCloud {
    let cam = &obs.camera;
    let (w, h) = (cam.w as usize, cam.h as usize);
    let r = Camera::rotation(cam);
    let f = (cam.fl_x * cam.fl_y).sqrt();
    let depth = |x: usize, y: usize| obs.depth[y * w + x];
    // Same surface: a valid depth, the same mask id, no depth jump.
    let same = |x: usize, y: usize, x2: usize, y2: usize| {
        let (z, z2) = (depth(x, y), depth(x2, y2));
        z2 > 0.0
            && obs.mask[y2 * w + x2] == obs.mask[y * w + x]
            && (z2 - z).abs() <= opts.depth_jump * z
    };
    let cam_pt = |x: usize, y: usize| {
        Vec3::from_array(cam.pixel_to_camera(x as f32 + 0.5, y as f32 + 0.5, depth(x, y)))
    };
    let rows: Vec<PointCloud> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut out = PointCloud::default();
            for x in 0..w {
                let i = y * w + x;
                let z = obs.depth[i];
                if z <= 0.0 {
                    continue;
                }
                let left = x > 0 && same(x, y, x - 1, y);
                let right = x + 1 < w && same(x, y, x + 1, y);
                let up = y > 0 && same(x, y, x, y - 1);
                let down = y + 1 < h && same(x, y, x, y + 1);
                if opts.skip_edges && !(left && right && up && down) {
                    continue;
                }
                let pc = cam_pt(x, y);
                let view = pc.normalize(); // camera-space direction from the eye to the point
                let view_w = r * view;
                let n_pass = Vec3::from_array(obs.normal[i]);
                let mut n = if n_pass.length() >= MIN_NORMAL_LENGTH {
                    n_pass.normalize()
                } else {
                    // Central (or one-sided) differences of neighbouring points on the surface.
                    let dx = match (left, right) {
                        (true, true) => Some(cam_pt(x + 1, y) - cam_pt(x - 1, y)),
                        (false, true) => Some(cam_pt(x + 1, y) - pc),
                        (true, false) => Some(pc - cam_pt(x - 1, y)),
                        _ => None,
                    };
                    let dy = match (up, down) {
                        (true, true) => Some(cam_pt(x, y + 1) - cam_pt(x, y - 1)),
                        (false, true) => Some(cam_pt(x, y + 1) - pc),
                        (true, false) => Some(pc - cam_pt(x, y - 1)),
                        _ => None,
                    };
                    let est = match (dx, dy) {
                        (Some(a), Some(b)) => a.cross(b).try_normalize(),
                        _ => None,
                    };
                    // No neighbours: the only honest guess is facing the camera.
                    r * est.unwrap_or(-view)
                };
                if n.dot(view_w) > 0.0 {
                    n = -n;
                }
                let cos = n.dot(view_w).abs().max(MIN_OBLIQUITY);
                out.push(
                    cam.camera_to_world(pc.to_array()),
                    n.to_array(),
                    obs.rgb[i],
                    obs.mask[i],
                    obs.state as u32,
                    z / f / cos,
                );
            }
            out
        })
        .collect();
    let mut cloud = PointCloud::default();
    for r in &rows {
        cloud.extend(r);
    }
    cloud
}

/// All views of state `k` of a dataset, back-projected into one cloud.
pub fn observe_state(dataset: &Dataset, k: usize, opts: &BackprojectOptions) -> Result<PointCloud> {
    if k >= dataset.states.len() {
        return Err(Error::invalid(
            &dataset.file,
            "states",
            format!(
                "expected a state index below {}, found {k}",
                dataset.states.len()
            ),
        ));
    }
    let mut cloud = PointCloud::default();
    for v in 0..dataset.states[k].frames.len() {
        cloud.extend(&backproject(&dataset.observation(k, v)?, opts));
    }
    Ok(cloud)
}

/// Integer voxel coordinates of `p` on a grid of pitch `voxel` anchored at the origin.
pub fn voxel_of(p: [f32; 3], voxel: f32) -> [i32; 3] {
    p.map(|c| (c / voxel).floor() as i32)
}

/// A total order on a point's values: the tie-breaker that makes thinning independent of the
/// input order.
fn point_order(c: &PointCloud, a: usize, b: usize) -> std::cmp::Ordering {
    let key = |i: usize| {
        let mut k = [0u32; 13];
        for d in 0..3 {
            k[d] = c.position[i][d].to_bits();
            k[3 + d] = c.normal[i][d].to_bits();
            k[6 + d] = c.rgb[i][d].to_bits();
        }
        k[9] = c.footprint[i].to_bits();
        k[10] = c.state[i];
        k[11] = c.mask[i] as u32;
        k
    };
    key(a).cmp(&key(b))
}

/// One point per occupied (voxel, mask id): see the module docs. Output sorted by mask id, then
/// voxel coordinates.
pub fn voxel_thin(cloud: &PointCloud, voxel: f32) -> PointCloud {
    assert!(voxel > 0.0 && voxel.is_finite(), "voxel size must be > 0");
    let keys: Vec<(u8, [i32; 3])> = (0..cloud.len())
        .map(|i| (cloud.mask[i], voxel_of(cloud.position[i], voxel)))
        .collect();
    let mut order: Vec<usize> = (0..cloud.len()).collect();
    order.par_sort_unstable_by(|&a, &b| keys[a].cmp(&keys[b]).then(point_order(cloud, a, b)));
    let mut runs = Vec::new();
    let mut start = 0;
    for j in 1..=order.len() {
        if j == order.len() || keys[order[j]] != keys[order[start]] {
            runs.push(start..j);
            start = j;
        }
    }
    let picked: Vec<(usize, [f32; 3], [f32; 3], f32)> = runs
        .par_iter()
        .map(|run| {
            let members = &order[run.clone()];
            let v = keys[members[0]].1;
            let centre = Vec3::from_array(v.map(|c| (c as f32 + 0.5) * voxel));
            let mut best = members[0];
            let mut best_d = f32::INFINITY;
            let (mut rgb, mut n) = (Vec3::ZERO, Vec3::ZERO);
            let mut fp = f32::INFINITY;
            for &i in members {
                let d = Vec3::from_array(cloud.position[i]).distance_squared(centre);
                // Members are in the total order, so `<` keeps the first of equals.
                if d < best_d {
                    best_d = d;
                    best = i;
                }
                rgb += Vec3::from_array(cloud.rgb[i]);
                n += Vec3::from_array(cloud.normal[i]);
                fp = fp.min(cloud.footprint[i]);
            }
            let rep_n = Vec3::from_array(cloud.normal[best]);
            let mut n = n.try_normalize().unwrap_or(rep_n);
            if n.dot(rep_n) < 0.0 {
                n = -n;
            }
            (
                best,
                (rgb / members.len() as f32).to_array(),
                n.to_array(),
                fp,
            )
        })
        .collect();
    let mut out = cloud.select(&picked.iter().map(|p| p.0).collect::<Vec<_>>());
    for (j, (_, rgb, n, fp)) in picked.into_iter().enumerate() {
        out.rgb[j] = rgb;
        out.normal[j] = n;
        out.footprint[j] = fp;
    }
    out
}

/// A right-handed rotation whose third axis is `n` (unit), tangent axes chosen continuously
/// (Duff et al. 2017, "Building an orthonormal basis, revisited").
pub fn rotation_from_normal(n: [f32; 3]) -> [f32; 4] {
    let n = Vec3::from_array(n).normalize();
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    let t = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
    let bt = Vec3::new(b, sign + n.y * n.y * a, -n.y);
    Quat::from_mat3(&Mat3::from_cols(t, bt, n))
        .normalize()
        .to_array()
}

/// Options of the surfel initialisation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InitOptions {
    /// Voxel pitch of the thinning, metres.
    pub voxel: f32,
    /// Initial opacity α of every surfel. 0.5 leaves the optimiser room both ways (2DGS starts
    /// at 0.1 from sparse points; ours come from dense depth, so surfaces start half covered).
    pub opacity: f32,
    /// SH degree of the splatting appearance (higher coefficients start at 0).
    pub sh_degree: u8,
    /// In-plane scale σ as a multiple of the point spacing (the larger of the voxel pitch and
    /// the point's footprint): 1.0 as in `surfelize::SIGMA_PER_SPACING`, which makes a lattice
    /// of that spacing opaque.
    pub sigma_per_spacing: f32,
}

impl Default for InitOptions {
    fn default() -> Self {
        InitOptions {
            voxel: 0.01,
            opacity: 0.5,
            sh_degree: 0,
            sigma_per_spacing: crate::scene::surfelize::SIGMA_PER_SPACING,
        }
    }
}

/// The points as surfels: rotation with the normal as third axis, σ = `sigma_per_spacing` ×
/// max(voxel, footprint) on both in-plane axes, SH DC = (c − 0.5)/C₀ from the observed RGB (as
/// `surfelize` sets it), base colour = RGB clamped to [0, 1], metallic 0, roughness 0.5.
pub fn points_to_surfels(cloud: &PointCloud, opts: &InitOptions) -> Surfels {
    let mut s = Surfels::with_sh_degree(opts.sh_degree);
    let mut sh = vec![[0.0f32; 3]; sh_coeffs(opts.sh_degree)];
    for i in 0..cloud.len() {
        let c = cloud.rgb[i];
        sh[0] = c.map(|x| (x.max(0.0) - 0.5) / SH_C0);
        let sigma = opts.sigma_per_spacing * opts.voxel.max(cloud.footprint[i]);
        s.push(
            cloud.position[i],
            rotation_from_normal(cloud.normal[i]),
            [sigma, sigma],
            opts.opacity,
            &sh,
            c.map(|x| x.clamp(0.0, 1.0)),
            0.0,
            0.5,
        );
    }
    s
}

/// One object of the scene: its mask id and component name.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectRef {
    pub id: u8,
    pub name: String,
}

/// The initial components (eq. state-assembly): the background from the mask-0 points of every
/// state (world frame), then one component per object from its points of every state mapped
/// into the reference frame by T_{k,o}⁻¹.
///
/// `states[j]` is the cloud of the j-th training state (world frame of that state), and
/// `poses[j][o]` the pose of `objects[o]` in it relative to the reference state (identity for
/// the reference state itself). Points of ids not in `objects` are dropped.
pub fn initial_components(
    states: &[PointCloud],
    objects: &[ObjectRef],
    poses: &[Vec<Rigid>],
    opts: &InitOptions,
) -> Vec<Component> {
    assert_eq!(states.len(), poses.len(), "one pose list per state");
    let mut background = PointCloud::default();
    let mut per_object = vec![PointCloud::default(); objects.len()];
    for (cloud, pose) in states.iter().zip(poses) {
        assert_eq!(pose.len(), objects.len(), "one pose per object");
        background.extend(&cloud.with_mask(0));
        for (o, obj) in objects.iter().enumerate() {
            let pts = cloud.with_mask(obj.id);
            per_object[o].extend(&pts.transformed(&pose[o].inverse()));
        }
    }
    let mut out = vec![Component {
        name: BACKGROUND.into(),
        id: 0,
        surfels: points_to_surfels(&voxel_thin(&background, opts.voxel), opts),
    }];
    for (obj, pts) in objects.iter().zip(&per_object) {
        out.push(Component {
            name: obj.name.clone(),
            id: obj.id as u32,
            surfels: points_to_surfels(&voxel_thin(pts, opts.voxel), opts),
        });
    }
    out
}
