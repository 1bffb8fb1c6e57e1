//! Stage-1 initialisation: back-projection, voxel thinning, surfels, component assembly.
//!
//! Tolerances: the synthetic depth maps are exact (analytic ray–surface hits in f64, stored as
//! f32), so back-projected points are off the true surface only by f32 rounding of coordinates of
//! size ~5 m: a few 1e-7 relative, hence 1e-4 m, which still catches a half-pixel shift (~1e-2 m
//! at these focal lengths and depths) or a wrong axis by orders of magnitude.

use glam::{DVec3, Quat, Vec3};
use lightfuse::io::dataset::Observation;
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::{quat_axes, Camera, Rigid, SH_C0};
use lightfuse::stages::reconstruct::init::*;

/// A camera at `eye` looking at `target` (+Y up), 64x48 pixels, f = 60 px, principal point off
/// centre so that a swapped cx/cy or a missing +0.5 shows.
fn camera(eye: [f32; 3], target: [f32; 3]) -> Camera {
    Camera {
        fl_y: 62.0,
        cx: 31.0,
        cy: 25.5,
        ..Camera::look_at(eye, target, 64, 48, 60.0)
    }
}

/// Analytic surfaces: a sphere (centre, radius) and the floor plane y = 0, mask ids 1 and 0.
struct World {
    centre: DVec3,
    radius: f64,
}

impl World {
    /// Nearest hit of the ray: (distance, normal, mask id).
    fn hit(&self, o: DVec3, d: DVec3) -> Option<(f64, DVec3, u8)> {
        let mut best: Option<(f64, DVec3, u8)> = None;
        let oc = o - self.centre;
        let b = oc.dot(d);
        let disc = b * b - (oc.length_squared() - self.radius * self.radius);
        if disc > 0.0 {
            let t = -b - disc.sqrt();
            if t > 0.0 {
                best = Some((t, (o + t * d - self.centre) / self.radius, 1));
            }
        }
        if d.y < 0.0 {
            let t = -o.y / d.y;
            if best.is_none_or(|b| t < b.0) {
                best = Some((t, DVec3::Y, 0));
            }
        }
        best
    }

    fn observe(&self, cam: &Camera, with_normals: bool) -> Observation {
        let m = &cam.transform_matrix;
        let o = DVec3::new(m[0][3] as f64, m[1][3] as f64, m[2][3] as f64);
        let fwd = -DVec3::new(m[0][2] as f64, m[1][2] as f64, m[2][2] as f64);
        let n = (cam.w * cam.h) as usize;
        let mut obs = Observation {
            state: 2,
            view: 0,
            camera: *cam,
            rgb: vec![[0.0; 3]; n],
            depth: vec![0.0; n],
            normal: vec![[0.0; 3]; n],
            mask: vec![0; n],
        };
        for y in 0..cam.h as usize {
            for x in 0..cam.w as usize {
                let (_, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
                let d = DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64).normalize();
                if let Some((t, nrm, id)) = self.hit(o, d) {
                    let i = y * cam.w as usize + x;
                    obs.depth[i] = (t * d.dot(fwd)) as f32; // planar depth
                    if with_normals {
                        obs.normal[i] = nrm.as_vec3().to_array();
                    }
                    obs.mask[i] = id;
                    obs.rgb[i] = [0.2 + 0.1 * id as f32, 0.5, 1.5];
                }
            }
        }
        obs
    }

    fn distance_to_surface(&self, p: [f32; 3], id: u8) -> f64 {
        let p = Vec3::from_array(p).as_dvec3();
        match id {
            1 => ((p - self.centre).length() - self.radius).abs(),
            _ => p.y.abs(),
        }
    }

    fn true_normal(&self, p: [f32; 3], id: u8) -> Vec3 {
        match id {
            1 => (Vec3::from_array(p).as_dvec3() - self.centre)
                .normalize()
                .as_vec3(),
            _ => Vec3::Y,
        }
    }
}

fn world() -> World {
    World {
        centre: DVec3::new(0.3, 0.5, -0.2),
        radius: 0.5,
    }
}

#[test]
fn backprojection_lands_on_the_true_surface_with_the_true_normal() {
    let w = world();
    let cam = camera([1.5, 1.3, 1.6], [0.2, 0.3, -0.1]);
    let obs = w.observe(&cam, true);
    let cloud = backproject(&obs, &BackprojectOptions::default());
    let hits = obs.depth.iter().filter(|z| **z > 0.0).count();
    assert_eq!(cloud.len(), hits, "one point per pixel with depth");
    let sphere = cloud.mask.iter().filter(|&&m| m == 1).count();
    assert!(
        sphere > 200 && cloud.len() - sphere > 200,
        "both surfaces seen"
    );
    let eye = Vec3::new(1.5, 1.3, 1.6);
    for i in 0..cloud.len() {
        let (p, id) = (cloud.position[i], cloud.mask[i]);
        let err = w.distance_to_surface(p, id);
        assert!(
            err < 1e-4,
            "point {p:?} (id {id}) is {err} m off its surface"
        );
        // The reference normal is carried (it already faces the camera).
        let n = Vec3::from_array(cloud.normal[i]);
        assert!(n.dot(w.true_normal(p, id)) > 0.9999);
        assert!(n.dot(eye - Vec3::from_array(p)) > 0.0, "faces the camera");
        assert_eq!(cloud.state[i], 2);
        assert_eq!(cloud.rgb[i][0], 0.2 + 0.1 * id as f32);
        // Footprint: z / f / |cos θ| ≥ z / f_max, and ≤ 4 z / f_min (obliquity clamp).
        let z = (eye - Vec3::from_array(p)).length();
        assert!(cloud.footprint[i] > 0.0 && cloud.footprint[i] < 4.0 * z / 60.0);
    }
    // Pixel centres: the point of pixel (x, y) is on the ray through (x + 0.5, y + 0.5).
    let (x, y) = (40usize, 30usize);
    let z = obs.depth[y * 64 + x];
    let p = Vec3::from_array(pixel_to_world(&cam, x, y, z));
    let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
    let v = (p - Vec3::from_array(o)).normalize();
    assert!(v.dot(Vec3::from_array(d)) > 1.0 - 1e-6);
}

#[test]
fn normals_are_flipped_to_face_the_camera_and_estimated_when_missing() {
    let w = world();
    let cam = camera([-1.5, 2.5, 2.0], [0.3, 0.4, -0.2]);
    // Flipped pass: every normal points away from the camera.
    let mut flipped = w.observe(&cam, true);
    for n in &mut flipped.normal {
        *n = n.map(|c| -c);
    }
    let a = backproject(&w.observe(&cam, true), &BackprojectOptions::default());
    let b = backproject(&flipped, &BackprojectOptions::default());
    assert_eq!(a.normal, b.normal);

    // No normal pass: estimated from neighbouring depth pixels. On the plane the differences
    // are exact up to f32 rounding. On the sphere, one pixel covers ~5.5 cm at 3.3 m (f = 60),
    // i.e. 0.11 rad of a 0.5 m sphere; perspective makes the ±1 pixel chords unequal, which
    // tilts a central-difference normal by a fraction of that angle. Away from grazing views
    // (n·view > 0.5) we ask for less than 0.08 rad (measured worst: 0.059).
    let c = backproject(&w.observe(&cam, false), &BackprojectOptions::default());
    let interior = backproject(
        &w.observe(&cam, false),
        &BackprojectOptions {
            skip_edges: true,
            ..Default::default()
        },
    );
    for i in 0..c.len() {
        let n = Vec3::from_array(c.normal[i]);
        let t = w.true_normal(c.position[i], c.mask[i]);
        assert!((n.length() - 1.0).abs() < 1e-5);
        if c.mask[i] == 0 {
            assert!(n.dot(t) > 1.0 - 1e-6, "plane normal {n} vs {t}");
        }
    }
    let eye = Vec3::new(-1.5, 2.5, 2.0);
    let mut worst = 1.0f32;
    for i in 0..interior.len() {
        let n = Vec3::from_array(interior.normal[i]);
        let t = w.true_normal(interior.position[i], interior.mask[i]);
        let to_eye = (eye - Vec3::from_array(interior.position[i])).normalize();
        if t.dot(to_eye) > 0.5 {
            worst = worst.min(n.dot(t));
        }
    }
    assert!(
        worst > (0.08f32).cos(),
        "interior estimate off by {}",
        worst.acos()
    );
    assert!(interior.len() < c.len(), "edges were skipped");
}

fn random_cloud(seed: u64, n: usize) -> PointCloud {
    let mut rng = SplitMix(seed);
    let mut c = PointCloud::default();
    for _ in 0..n {
        let n3 = Vec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), 1.0).normalize();
        c.push(
            [
                rng.range(-0.3, 0.3),
                rng.range(0.0, 0.2),
                rng.range(-0.3, 0.3),
            ],
            n3.to_array(),
            [rng.f32(), rng.f32(), rng.f32()],
            (rng.next_u64() % 3) as u8,
            (rng.next_u64() % 2) as u32,
            rng.range(0.001, 0.02),
        );
    }
    c
}

#[test]
fn thinning_keeps_one_point_per_voxel_and_ignores_input_order() {
    let cloud = random_cloud(7, 5000);
    let voxel = 0.05;
    let thin = voxel_thin(&cloud, voxel);
    // One output per occupied (mask, voxel), and every one represented.
    let key = |c: &PointCloud, i: usize| (c.mask[i], voxel_of(c.position[i], voxel));
    let mut occupied: Vec<_> = (0..cloud.len()).map(|i| key(&cloud, i)).collect();
    occupied.sort();
    occupied.dedup();
    let mut kept: Vec<_> = (0..thin.len()).map(|i| key(&thin, i)).collect();
    let sorted = kept.windows(2).all(|w| w[0] < w[1]);
    assert!(sorted, "outputs sorted by key and unique");
    kept.dedup();
    assert_eq!(kept, occupied);
    // Slow reference for the representative and the colour mean.
    for (j, k) in kept.iter().enumerate() {
        let members: Vec<usize> = (0..cloud.len()).filter(|&i| key(&cloud, i) == *k).collect();
        let centre = Vec3::from_array(k.1.map(|c| (c as f32 + 0.5) * voxel));
        let d = |i: usize| Vec3::from_array(cloud.position[i]).distance(centre);
        let best = members
            .iter()
            .copied()
            .min_by(|&a, &b| d(a).total_cmp(&d(b)))
            .unwrap();
        assert_eq!(thin.position[j], cloud.position[best]);
        let mean: Vec3 = members
            .iter()
            .map(|&i| Vec3::from_array(cloud.rgb[i]))
            .sum::<Vec3>()
            / members.len() as f32;
        // Sums of up to ~10 values in [0, 1] in a different order: a few ulps.
        assert!(Vec3::from_array(thin.rgb[j]).distance(mean) < 1e-5);
        let fp = members
            .iter()
            .map(|&i| cloud.footprint[i])
            .fold(f32::INFINITY, f32::min);
        assert_eq!(thin.footprint[j], fp);
        assert!((Vec3::from_array(thin.normal[j]).length() - 1.0).abs() < 1e-5);
    }
    // Any permutation of the input gives the same bits.
    let mut rng = SplitMix(99);
    let mut perm: Vec<usize> = (0..cloud.len()).collect();
    for i in (1..perm.len()).rev() {
        perm.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    assert_eq!(voxel_thin(&cloud.select(&perm), voxel), thin);
}

#[test]
fn surfels_face_their_normals_and_carry_colour() {
    let cloud = random_cloud(3, 500);
    let opts = InitOptions {
        voxel: 0.01,
        ..Default::default()
    };
    let s = points_to_surfels(&cloud, &opts);
    assert_eq!(s.len(), cloud.len());
    for i in 0..s.len() {
        let axes = quat_axes(s.rotation[i]);
        let n = Vec3::from_array(cloud.normal[i]);
        assert!(Vec3::from_array(axes[2]).dot(n) > 1.0 - 1e-5);
        // Right-handed frame (a proper rotation): t × b = n.
        let tb = Vec3::from_array(axes[0]).cross(Vec3::from_array(axes[1]));
        assert!(tb.dot(n) > 1.0 - 1e-5);
        let sigma = 0.01f32.max(cloud.footprint[i]);
        assert_eq!(s.scale[i], [sigma, sigma]);
        for c in 0..3 {
            assert!((s.sh[i][c] * SH_C0 + 0.5 - cloud.rgb[i][c]).abs() < 1e-6);
        }
        assert_eq!(s.base_color[i], cloud.rgb[i]);
        assert_eq!(
            (s.metallic[i], s.roughness[i], s.opacity[i]),
            (0.0, 0.5, 0.5)
        );
    }
    // Poles of the basis construction.
    for n in [
        [0.0, 0.0, 1.0],
        [0.0, 0.0, -1.0],
        [0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0],
    ] {
        let axes = quat_axes(rotation_from_normal(n));
        assert!(Vec3::from_array(axes[2]).dot(Vec3::from_array(n)) > 1.0 - 1e-6);
    }
    s.validate(std::path::Path::new("test"), "surfels").unwrap();
}

#[test]
fn components_map_object_points_back_to_the_reference_frame() {
    // State 0 and state 1 see the same object points; in state 1 the object was moved by T.
    let mut reference = random_cloud(11, 2000);
    reference
        .mask
        .iter_mut()
        .for_each(|m| *m = if *m == 0 { 0 } else { 4 });
    let pose = Rigid {
        rotation: Quat::from_rotation_y(2.0).to_array(),
        translation: [0.5, 0.1, -0.7],
    };
    let mut moved = reference.clone();
    for i in 0..moved.len() {
        if moved.mask[i] == 4 {
            moved.position[i] = pose.transform_point(moved.position[i]);
            moved.normal[i] = (pose.quat() * Vec3::from_array(moved.normal[i])).to_array();
        }
    }
    let objects = [ObjectRef {
        id: 4,
        name: "thing".into(),
    }];
    let opts = InitOptions {
        voxel: 0.04,
        ..Default::default()
    };
    let comps = initial_components(
        &[reference.clone(), moved],
        &objects,
        &[vec![Rigid::IDENTITY], vec![pose]],
        &opts,
    );
    assert_eq!(comps.len(), 2);
    assert_eq!((comps[1].name.as_str(), comps[1].id), ("thing", 4));
    // Mapped back, the state-1 points coincide with the state-0 ones (up to f32 rounding of
    // the round trip, ~1e-7 m), so thinning both gives what thinning the reference alone gives.
    let alone = voxel_thin(&reference.with_mask(4), 0.04);
    assert_eq!(comps[1].surfels.len(), alone.len());
    for (p, q) in comps[1].surfels.position.iter().zip(&alone.position) {
        assert!(Vec3::from_array(*p).distance(Vec3::from_array(*q)) < 1e-5);
    }
    // The background never moves: both states' copies merge.
    assert_eq!(
        comps[0].surfels.len(),
        voxel_thin(&reference.with_mask(0), 0.04).len()
    );
}
