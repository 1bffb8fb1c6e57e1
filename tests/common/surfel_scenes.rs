//! Small surfel scenes for the shading tests (`tests/render.rs`, `tests/replay.rs`): a
//! Fibonacci sphere, a floor, a camera, a random environment.

use glam::{Quat, Vec3};
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::Material;
use lightfuse::scene::{Camera, Component, Environment, Rigid, Scene, Surfels};

/// Fibonacci-sphere surfels of radius `r` about `c`: radial normals, σ = the mean spacing, so
/// every point is covered by many discs and the sphere is opaque.
pub fn sphere(c: Vec3, r: f32, n: usize, m: Material) -> Surfels {
    let mut s = Surfels::with_sh_degree(0);
    let spacing = (4.0 * std::f32::consts::PI * r * r / n as f32).sqrt();
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    for i in 0..n {
        let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
        let rad = (1.0 - y * y).sqrt();
        let phi = golden * i as f32;
        let nrm = Vec3::new(rad * phi.cos(), y, rad * phi.sin());
        let q = Quat::from_rotation_arc(Vec3::Z, nrm);
        push_disc(&mut s, (c + r * nrm).to_array(), q, spacing, m);
    }
    s
}

/// A square floor at height `y`, normal +Y, half-size `half`.
pub fn floor(y: f32, half: f32, spacing: f32, m: Material) -> Surfels {
    let mut s = Surfels::with_sh_degree(0);
    let q = Quat::from_rotation_arc(Vec3::Z, Vec3::Y);
    let k = (2.0 * half / spacing) as i32;
    for i in 0..=k {
        for j in 0..=k {
            let p = [-half + i as f32 * spacing, y, -half + j as f32 * spacing];
            push_disc(&mut s, p, q, spacing, m);
        }
    }
    s
}

pub fn scene_of(parts: Vec<Surfels>) -> Scene {
    let mut scene = Scene::from_background(Surfels::with_sh_degree(0));
    scene.components = parts
        .into_iter()
        .enumerate()
        .map(|(i, surfels)| Component {
            name: if i == 0 {
                "background".into()
            } else {
                format!("obj{i}")
            },
            id: i as u32,
            surfels,
        })
        .collect();
    scene.states[0].transforms = vec![Rigid::IDENTITY; scene.components.len()];
    scene
}

/// A camera at `eye` looking down −Z, `w`×`h`, focal length `fl` pixels.
pub fn camera(eye: Vec3, w: u32, h: u32, fl: f32) -> Camera {
    Camera {
        transform_matrix: [
            [1.0, 0.0, 0.0, eye.x],
            [0.0, 1.0, 0.0, eye.y],
            [0.0, 0.0, 1.0, eye.z],
            [0.0, 0.0, 0.0, 1.0],
        ],
        fl_x: fl,
        fl_y: fl,
        cx: w as f32 / 2.0,
        cy: h as f32 / 2.0,
        w,
        h,
    }
}

pub fn random_env(w: usize, h: usize, seed: u64, scale: f32) -> Environment {
    let mut rng = SplitMix(seed);
    let px = (0..w * h)
        .map(|_| [rng.f32(), rng.f32(), rng.f32()].map(|v| scale * (0.1 + 3.0 * v * v)))
        .collect();
    Environment::new("random", w, h, px)
}

pub fn mat(base: [f32; 3], metallic: f32, roughness: f32) -> Material {
    Material {
        base_color: base,
        metallic,
        roughness,
    }
}

/// An axis-aligned box standing on y = `base.y` centred on `base` in x and z, of size `size`
/// (x, y, z), its five visible faces (no bottom) tiled by surfels `spacing` apart, normals out.
pub fn cuboid(base: Vec3, size: Vec3, spacing: f32, m: Material) -> Surfels {
    let mut s = Surfels::with_sh_degree(0);
    let c = base + Vec3::new(0.0, size.y / 2.0, 0.0);
    let h = size / 2.0;
    // (normal, the face's two in-plane axes): +X, −X, +Y, +Z, −Z.
    let faces = [
        (Vec3::X, Vec3::Y, Vec3::Z),
        (Vec3::NEG_X, Vec3::Y, Vec3::Z),
        (Vec3::Y, Vec3::X, Vec3::Z),
        (Vec3::Z, Vec3::X, Vec3::Y),
        (Vec3::NEG_Z, Vec3::X, Vec3::Y),
    ];
    for (n, a, b) in faces {
        let q = Quat::from_rotation_arc(Vec3::Z, n);
        let (ea, eb) = ((h * a).length(), (h * b).length());
        let centre = c + n * (h * n).length();
        let (ka, kb) = (
            (2.0 * ea / spacing).ceil() as i32,
            (2.0 * eb / spacing).ceil() as i32,
        );
        for i in 0..=ka {
            for j in 0..=kb {
                let u = -ea + 2.0 * ea * i as f32 / ka as f32;
                let v = -eb + 2.0 * eb * j as f32 / kb as f32;
                push_disc(&mut s, (centre + u * a + v * b).to_array(), q, spacing, m);
            }
        }
    }
    s
}

/// One opaque (0.99) disc of `spacing` diameter at `p`, oriented by `q` (its local +Z the
/// normal), with material `m` and no view-dependent colour: the fixtures' one surfel.
fn push_disc(s: &mut Surfels, p: [f32; 3], q: Quat, spacing: f32, m: Material) {
    s.push(
        p,
        q.to_array(),
        [spacing, spacing],
        0.99,
        &[[0.0; 3]],
        m.base_color,
        m.metallic,
        m.roughness,
    );
}
