//! `lightfuse import colmap` end to end on captures built here from known cameras: COLMAP's
//! axes become the dataset's, distorted photos become pinhole images of the same rays, states
//! come from folders, and every bad input is one line naming the file and field, exit code 2.

use glam::{DMat3, DQuat, DVec3};
use lightfuse::io::colmap::lens::{Lens, LensModel};
use lightfuse::io::dataset::Dataset;
use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;

const W: u32 = 64;
const H: u32 = 48;
const OPENCV: [f64; 8] = [60.0, 58.0, 31.5, 24.5, -0.12, 0.03, 0.002, -0.001];

/// The radiance the test's scene sends along camera-frame ray (u, v, 1): smooth, so bilinear
/// resampling is accurate to well under 1 % (a pixel is ~0.018 in u: the error is about
/// h²/8 · 81 · 0.3 ≈ 1e-3), yet varied enough that a copy of the distorted photo is off by
/// more (checked: the test fails when the photo is copied instead of resampled).
fn radiance(u: f64, v: f64) -> [f32; 3] {
    [
        (0.45 + 0.3 * (9.0 * u).sin()) as f32,
        (0.35 + 0.25 * (7.0 * v).cos()) as f32,
        (0.2 + 0.15 * (5.0 * (u + v)).sin()) as f32,
    ]
}

fn srgb_encode(x: f32) -> f32 {
    lightfuse::scene::color::srgb_encode(x)
}

struct Capture {
    dir: tempfile::TempDir,
    /// (name, camera id, world-to-camera rotation, translation)
    images: Vec<(String, u32, DQuat, DVec3)>,
    points: Vec<DVec3>,
}

/// Three states of two images each around points near the origin, COLMAP's world turned so its
/// up is −Y (as COLMAP's world often is: the first camera's frame); camera 1 PINHOLE, camera 2
/// OPENCV. Every point is seen by every image, so the states share one world.
fn capture(states: &[&str]) -> Capture {
    let dir = tempfile::tempdir().unwrap();
    let mut images = Vec::new();
    for (k, s) in states.iter().enumerate() {
        for j in 0..2 {
            let i = 2 * k + j;
            // A camera 3 m from the origin at azimuth a, 20 degrees up, looking at it, in a
            // world whose up is -Y (COLMAP-like); world-to-camera in COLMAP's axes.
            let a = 0.6 * i as f64;
            let up = DVec3::NEG_Y;
            let eye = DVec3::new(3.0 * a.cos(), -1.0, 3.0 * a.sin());
            let fwd = (-eye).normalize();
            let right = fwd.cross(up).normalize(); // camera +X
            let down = fwd.cross(right); // camera +Y (down), right-handed with +Z forward
            let r = DMat3::from_cols(right, down, fwd).transpose();
            let q = DQuat::from_mat3(&r);
            let t = -(r * eye);
            images.push((format!("{s}/IMG_{i:04}.png"), 1 + (i as u32 % 2), q, t));
        }
    }
    let points: Vec<DVec3> = (0..60)
        .map(|i| {
            let f = i as f64;
            // Most on the floor plane y = 0.3 (COLMAP's y is down: the floor is below the
            // origin), some above it.
            let y = if i % 3 == 0 {
                0.3 - 0.2 * ((f * 0.7).sin() + 1.0)
            } else {
                0.3
            };
            DVec3::new(0.5 * (f * 1.3).sin(), y, 0.5 * (f * 0.9).cos())
        })
        .collect();
    let c = Capture {
        dir,
        images,
        points,
    };
    c.write_model();
    c.write_photos();
    c
}

impl Capture {
    fn root(&self) -> &Path {
        self.dir.path()
    }
    fn lens(&self, camera: u32) -> Lens {
        match camera {
            1 => Lens {
                model: LensModel::Pinhole,
                width: W,
                height: H,
                params: vec![55.0, 56.0, 32.0, 23.0],
            },
            _ => Lens {
                model: LensModel::OpenCv,
                width: W,
                height: H,
                params: OPENCV.to_vec(),
            },
        }
    }
    fn write_model(&self) {
        let m = self.root().join("sparse");
        std::fs::create_dir_all(&m).unwrap();
        let mut cams = String::from("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
        for id in [1, 2] {
            let l = self.lens(id);
            let p: Vec<String> = l.params.iter().map(|x| x.to_string()).collect();
            writeln!(cams, "{id} {} {W} {H} {}", l.model.name(), p.join(" ")).unwrap();
        }
        std::fs::write(m.join("cameras.txt"), cams).unwrap();
        let mut ims = String::new();
        for (k, (name, cam, q, t)) in self.images.iter().enumerate() {
            writeln!(
                ims,
                "{} {} {} {} {} {} {} {} {cam} {name}",
                k + 1,
                q.w,
                q.x,
                q.y,
                q.z,
                t.x,
                t.y,
                t.z
            )
            .unwrap();
            let kp: Vec<String> = (0..self.points.len())
                .map(|p| format!("1 1 {}", p + 1))
                .collect();
            writeln!(ims, "{}", kp.join(" ")).unwrap();
        }
        std::fs::write(m.join("images.txt"), ims).unwrap();
        let mut pts = String::new();
        for (i, p) in self.points.iter().enumerate() {
            let track: Vec<String> = (0..self.images.len())
                .map(|k| format!("{} {i}", k + 1))
                .collect();
            writeln!(
                pts,
                "{} {} {} {} 128 128 128 0.5 {}",
                i + 1,
                p.x,
                p.y,
                p.z,
                track.join(" ")
            )
            .unwrap();
        }
        std::fs::write(m.join("points3D.txt"), pts).unwrap();
    }
    /// 16-bit sRGB PNGs of `radiance` through each image's lens; id masks: 7 left of the
    /// principal point's column, 0 right of it.
    fn write_photos(&self) {
        for (name, cam, _, _) in &self.images {
            let lens = self.lens(*cam);
            let mut img = image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::new(W, H);
            for (x, y, p) in img.enumerate_pixels_mut() {
                let q = lens.unproject([x as f64 + 0.5, y as f64 + 0.5]).unwrap();
                let c = radiance(q[0], q[1]);
                *p = image::Rgb(c.map(|v| (srgb_encode(v) * 65535.0).round() as u16));
            }
            let path = self.root().join("photos").join(name);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            img.save_with_format(&path, image::ImageFormat::Png)
                .unwrap();
            let mask = image::GrayImage::from_fn(W, H, |x, _| {
                image::Luma([if (x as f64) < 32.0 { 7 } else { 0 }])
            });
            let mpath = self.root().join("masks").join(format!("{name}.png"));
            std::fs::create_dir_all(mpath.parent().unwrap()).unwrap();
            mask.save(&mpath).unwrap();
        }
    }
    fn import(&self, extra: &[&str]) -> std::process::Output {
        let root = self.root();
        Command::new(env!("CARGO_BIN_EXE_lightfuse"))
            .args(["--quiet", "import", "colmap"])
            .arg(root.join("sparse"))
            .arg("--images")
            .arg(root.join("photos"))
            .arg("-o")
            .arg(root.join("dataset"))
            .args(extra)
            .output()
            .unwrap()
    }
}

fn ok(out: &std::process::Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn refused(out: &std::process::Output, needles: &[&str]) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    for n in needles {
        assert!(err.contains(n), "{n:?} not in {err}");
    }
}

/// Every triangulated point lands on the same pixel through the dataset's camera as through
/// COLMAP's (the undistorted pinhole image's pixel for the OPENCV camera): the axes, the
/// quaternion convention and the world's similarity are all consistent. The up estimate finds
/// the floor: its points all get one height, y = 0, and the cameras are above it.
#[test]
fn colmap_poses_become_dataset_cameras_that_see_the_same_pixels() {
    let c = capture(&["state0", "state1", "test"]);
    ok(&c.import(&["--test-states", "test", "--scale", "0.5"]));
    let ds = Dataset::read(&c.root().join("dataset")).unwrap();
    let import: serde_json::Value =
        serde_json::from_slice(&std::fs::read(c.root().join("dataset/import.json")).unwrap())
            .unwrap();
    let wf = &import["world_from_source"];
    let rot: Vec<Vec<f64>> = wf["rotation"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect()
        })
        .collect();
    let origin: Vec<f64> = wf["origin"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    let scale = wf["scale"].as_f64().unwrap();
    assert_eq!(scale, 0.5);
    let to_world = |x: DVec3| {
        let d = x - DVec3::new(origin[0], origin[1], origin[2]);
        scale
            * DVec3::new(
                rot[0][0] * d.x + rot[0][1] * d.y + rot[0][2] * d.z,
                rot[1][0] * d.x + rot[1][1] * d.y + rot[1][2] * d.z,
                rot[2][0] * d.x + rot[2][1] * d.y + rot[2][2] * d.z,
            )
    };
    // States: in name order, training first; the test state held out.
    let names: Vec<(&str, &str)> = ds
        .states
        .iter()
        .map(|s| (s.name.as_str(), s.split.as_str()))
        .collect();
    assert_eq!(
        names,
        [("state0", "train"), ("state1", "train"), ("test", "test")]
    );
    let (mut checked, mut exact) = (0, 0);
    for (k, (name, cam, q, t)) in c.images.iter().enumerate() {
        let state = &ds.states[k / 2];
        let frame = &state.frames[k % 2];
        assert!(
            frame.file_path.ends_with(&name.replace(".png", ".exr")),
            "{} {name}",
            frame.file_path
        );
        let lens = c.lens(*cam);
        let pin = lens.pinhole().unwrap();
        let sparse = ds
            .frame_planes(
                frame.sparse_depth_file_path.as_deref().unwrap(),
                &["Z", "C"],
                &frame.camera,
            )
            .unwrap();
        let mut nearest = vec![0.0f32; (W * H) as usize];
        for p in &c.points {
            let pc = *q * *p + *t;
            // COLMAP's pixel in the pinhole image: the pinhole projection with pin's intrinsics.
            let want = [pin.fx * pc.x / pc.z + pin.cx, pin.fy * pc.y / pc.z + pin.cy];
            let w = to_world(*p);
            let (got, z) = frame
                .camera
                .project([w.x as f32, w.y as f32, w.z as f32])
                .unwrap();
            assert!(
                (got[0] as f64 - want[0]).abs() < 2e-3 && (got[1] as f64 - want[1]).abs() < 2e-3,
                "{name}: {got:?} vs {want:?}"
            );
            assert!((z as f64 - scale * pc.z).abs() < 1e-4, "depth in metres");
            // The nearest point landing in each pixel, as the sparse depth should hold it.
            let i = got[1] as usize * W as usize + got[0] as usize;
            if nearest[i] == 0.0 || z < nearest[i] {
                nearest[i] = z;
            }
            checked += 1;
        }
        // The sparse depth is exactly that, with confidence 1 / (1 + 0.5²) for the model's
        // ERROR of 0.5 px wherever a point landed, and 0 elsewhere.
        for i in 0..nearest.len() {
            let (sz, sc) = (sparse[0][i], sparse[1][i]);
            assert!(
                (sz - nearest[i]).abs() < 1e-4,
                "{name} pixel {i}: {sz} vs {}",
                nearest[i]
            );
            let want_c = if nearest[i] > 0.0 { 0.8 } else { 0.0 };
            assert!(
                (sc - want_c).abs() < 1e-6,
                "{name} pixel {i}: confidence {sc}"
            );
            exact += usize::from(nearest[i] > 0.0);
        }
        // The camera is above the floor, which is at y = 0.
        assert!(
            frame.camera.transform_matrix[1][3] > 0.1,
            "{name} above the floor"
        );
    }
    assert_eq!(checked, 6 * 60);
    // 60 points in a ~20 px patch of each photo: some share a pixel.
    assert!(exact > 200, "only {exact} pixels of 6 photos hold a point");
    // What the import writes is a dataset the schema accepts.
    let schema: serde_json::Value = serde_json::from_slice(
        &std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas/dataset.schema.json"))
            .unwrap(),
    )
    .unwrap();
    let written: serde_json::Value =
        serde_json::from_slice(&std::fs::read(c.root().join("dataset/dataset.json")).unwrap())
            .unwrap();
    let validator = jsonschema::validator_for(&schema).unwrap();
    let errors: Vec<String> = validator
        .iter_errors(&written)
        .map(|e| e.to_string())
        .collect();
    assert!(errors.is_empty(), "{errors:?}");
    for p in c.points.iter().filter(|p| (p.y - 0.3).abs() < 1e-12) {
        assert!(
            to_world(*p).y.abs() < 1e-6,
            "floor point at y = {}",
            to_world(*p).y
        );
    }
    // Points above the floor (smaller COLMAP y) are above it in the dataset.
    for p in c.points.iter().filter(|p| p.y < 0.29) {
        assert!(to_world(*p).y > 0.0);
    }
}

/// A photo through the OPENCV lens becomes a pinhole image of the same rays: each pixel of the
/// imported EXR holds the radiance of its own pinhole ray, within 1 % (bilinear resampling of
/// a smooth image and 16-bit quantisation); the PINHOLE camera's photo is copied exactly
/// (up to the sRGB round trip).
#[test]
fn distorted_photos_become_pinhole_images_of_the_same_rays() {
    let c = capture(&["a", "b"]);
    ok(&c.import(&[]));
    let ds = Dataset::read(&c.root().join("dataset")).unwrap();
    for (k, (name, cam, _, _)) in c.images.iter().enumerate() {
        let frame = &ds.states[k / 2].frames[k % 2];
        let cam_ = frame.camera;
        let rgb = ds.frame_rgb(&frame.file_path, &cam_).unwrap();
        let mut worst: f32 = 0.0;
        for y in 0..H {
            for x in 0..W {
                let u = (x as f64 + 0.5 - cam_.cx as f64) / cam_.fl_x as f64;
                let v = (y as f64 + 0.5 - cam_.cy as f64) / cam_.fl_y as f64;
                let want = radiance(u, v);
                let got = rgb[(y * W + x) as usize];
                for ch in 0..3 {
                    worst = worst.max((got[ch] - want[ch]).abs());
                }
            }
        }
        let tol = if *cam == 1 { 1e-4 } else { 1e-2 };
        assert!(
            worst < tol,
            "{name} (camera {cam}): worst pixel off by {worst}"
        );
        if *cam == 2 {
            // Barrel distortion records a wider field than the focal length says; the pinhole
            // image keeps it (and its border pixels still come from inside the photo, which
            // the worst-pixel check above would catch as clamped values otherwise).
            assert!(
                cam_.fl_x < OPENCV[0] as f32,
                "barrel distortion: the pinhole image zooms out"
            );
        }
    }
}

/// Masks are resampled with the photo: the id edge stays at the same rays, ids are kept, and
/// the objects the masks name are the dataset's objects.
#[test]
fn masks_follow_their_photos() {
    let c = capture(&["a", "b"]);
    let masks = c.root().join("masks");
    ok(&c.import(&["--masks", masks.to_str().unwrap()]));
    let ds = Dataset::read(&c.root().join("dataset")).unwrap();
    assert_eq!(ds.objects.len(), 1);
    assert_eq!(
        (ds.objects[0].id, ds.objects[0].name.as_str()),
        (7, "object_7")
    );
    for (k, (_, cam, _, _)) in c.images.iter().enumerate() {
        let frame = &ds.states[k / 2].frames[k % 2];
        let m = ds.frame_mask(frame).unwrap().unwrap();
        let lens = c.lens(*cam);
        let pin = lens.pinhole().unwrap();
        for y in 0..H {
            for x in 0..W {
                let s = lens
                    .source_pixel(&pin, [x as f64 + 0.5, y as f64 + 0.5])
                    .unwrap();
                let want = if s[0] < 32.0 { 7 } else { 0 };
                if (s[0] - 32.0).abs() > 1.0 {
                    assert_eq!(m[(y * W + x) as usize], want, "({x}, {y}) from {s:?}");
                }
            }
        }
    }
}

#[test]
fn bad_captures_are_refused_in_one_line() {
    // A photo that does not exist.
    let c = capture(&["a", "b"]);
    std::fs::remove_file(c.root().join("photos/b/IMG_0003.png")).unwrap();
    refused(&c.import(&[]), &["IMG_0003.png", "expected the photo here"]);
    // A photo whose size is not its camera's.
    let c = capture(&["a", "b"]);
    image::RgbImage::new(32, 48)
        .save(c.root().join("photos/a/IMG_0001.png"))
        .unwrap();
    refused(
        &c.import(&[]),
        &[
            "IMG_0001.png",
            "size",
            "expected 64x48 (camera 2 of",
            "found 32x48",
        ],
    );
    // A mask that does not exist, and one of another size.
    let c = capture(&["a", "b"]);
    std::fs::remove_file(c.root().join("masks/a/IMG_0000.png.png")).unwrap();
    refused(
        &c.import(&["--masks", c.root().join("masks").to_str().unwrap()]),
        &["IMG_0000.png.png", "id mask"],
    );
    // A photo in no state folder.
    let c = capture(&["a", "b"]);
    let p = c.root().join("sparse/images.txt");
    let t = std::fs::read_to_string(&p)
        .unwrap()
        .replace(" a/IMG_0000.png", " IMG_0000.png");
    std::fs::write(&p, t).unwrap();
    refused(
        &c.import(&[]),
        &["images.txt", "image 1.name", "no state folder"],
    );
    // States registered apart: no point seen from two states.
    let c = capture(&["a", "b"]);
    let p = c.root().join("sparse/points3D.txt");
    let t: String = std::fs::read_to_string(&p)
        .unwrap()
        .lines()
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            // Keep only the track entries of images 1 and 2 (state a) for even points, 3 and 4
            // (state b) for odd ones.
            let id: usize = f[0].parse().unwrap();
            let keep: Vec<&str> = f[8..]
                .chunks(2)
                .filter(|e| (e[0] == "1" || e[0] == "2") == (id % 2 == 0))
                .flatten()
                .copied()
                .collect();
            format!("{} {}\n", f[..8].join(" "), keep.join(" "))
        })
        .collect();
    std::fs::write(&p, t).unwrap();
    refused(
        &c.import(&[]),
        &[
            "points3D.txt",
            "shares no triangulated point",
            "registered separately",
        ],
    );
    // A spherical camera.
    let c = capture(&["a", "b"]);
    let p = c.root().join("sparse/cameras.txt");
    let t = std::fs::read_to_string(&p).unwrap();
    let t = t
        .lines()
        .map(|l| {
            if l.starts_with("1 ") {
                format!("1 EQUIRECTANGULAR {W} {H} {W} {H}\n")
            } else {
                format!("{l}\n")
            }
        })
        .collect::<String>();
    std::fs::write(&p, t).unwrap();
    refused(
        &c.import(&[]),
        &["cameras.txt", "camera 1.model", "EQUIRECTANGULAR"],
    );
    // An unknown test state; every state held out.
    let c = capture(&["a", "b"]);
    refused(
        &c.import(&["--test-states", "c"]),
        &["--test-states", "no state \"c\""],
    );
    refused(
        &c.import(&["--test-states", "a,b"]),
        &["every state is held out"],
    );
    // A folder that holds something else is not written into; the file is left as it was.
    let c = capture(&["a", "b"]);
    std::fs::create_dir_all(c.root().join("dataset")).unwrap();
    std::fs::write(c.root().join("dataset/notes.txt"), "mine").unwrap();
    refused(
        &c.import(&[]),
        &["dataset", "expected a new or empty folder", "notes.txt"],
    );
    assert_eq!(
        std::fs::read_to_string(c.root().join("dataset/notes.txt")).unwrap(),
        "mine"
    );
    // A --states file without a photo, and one whose state would be a path out of the output.
    let c = capture(&["a", "b"]);
    let map = c.root().join("map.json");
    let names: Vec<String> = c.images.iter().map(|i| i.0.clone()).collect();
    let mut m: serde_json::Map<String, serde_json::Value> =
        names.iter().map(|n| (n.clone(), "x".into())).collect();
    m.remove(&names[2]);
    std::fs::write(&map, serde_json::to_vec(&m).unwrap()).unwrap();
    refused(
        &c.import(&["--states", map.to_str().unwrap()]),
        &["map.json", &names[2], "expected this photo's state"],
    );
    m.insert(names[2].clone(), "../escape".into());
    std::fs::write(&map, serde_json::to_vec(&m).unwrap()).unwrap();
    refused(
        &c.import(&["--states", map.to_str().unwrap()]),
        &["map.json", "expected a state name", "../escape"],
    );
    assert!(!c.root().join("escape").exists());
    // Bad --up / --scale.
    refused(&c.import(&["--up", "0,0,0"]), &["--up"]);
    refused(&c.import(&["--scale", "-1"]), &["--scale"]);
}

/// `--scale-points`: two points a known distance apart, as COLMAP 3D point ids or as
/// coordinates in the source's frame, give the metres per source unit exactly; bad ones are
/// refused in one line (exit 2) before anything is written.
#[test]
fn two_points_a_known_distance_apart_set_the_scale() {
    let c = capture(&["state0", "test"]);
    let out = c.root().join("dataset");
    let scale = || -> f64 {
        let j: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("import.json")).unwrap()).unwrap();
        j["world_from_source"]["scale"].as_f64().unwrap()
    };
    // Points 1 and 5 (ids from 1) are c.points[0] and c.points[4].
    let (a, b) = (c.points[0], c.points[4]);
    let metres = 0.5 * a.distance(b);
    let m = metres.to_string();
    ok(&c.import(&[
        "--test-states",
        "test",
        "--scale-points",
        "point:1",
        "point:5",
        &m,
    ]));
    assert!((scale() - 0.5).abs() < 1e-12, "{}", scale());
    // The cameras follow: every distance between centres is half the source's.
    let ds = Dataset::read(&out).unwrap();
    let centres: Vec<DVec3> = ds
        .states
        .iter()
        .flat_map(|s| {
            s.frames.iter().map(|f| {
                let o = f.camera.origin();
                DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64)
            })
        })
        .collect();
    let source: Vec<DVec3> = c
        .images
        .iter()
        .map(|(_, _, q, t)| -(DMat3::from_quat(*q).transpose() * *t))
        .collect();
    assert_eq!(centres.len(), source.len());
    let ratio = centres[0].distance(centres[3]) / source[0].distance(source[3]);
    assert!((ratio - 0.5).abs() < 1e-5, "{ratio}");
    // The same two points by their coordinates.
    std::fs::remove_dir_all(&out).unwrap();
    let xyz = |p: DVec3| format!("{},{},{}", p.x, p.y, p.z);
    ok(&c.import(&[
        "--test-states",
        "test",
        "--scale-points",
        &xyz(a),
        &xyz(b),
        &m,
    ]));
    assert!((scale() - 0.5).abs() < 1e-12, "{}", scale());
    std::fs::remove_dir_all(&out).unwrap();
    let bad = |extra: &[&str], needles: &[&str]| {
        refused(&c.import(&[&["--scale-points"], extra].concat()), needles);
        assert!(!out.join("dataset.json").exists());
    };
    bad(
        &["point:1", "point:999", "1"],
        &["points3D", "--scale-points", "999"],
    );
    bad(&["point:1", "point:1", "1"], &["--scale-points", "same"]);
    bad(&["point:1", "point:5", "-1"], &["--scale-points", "> 0"]);
    bad(
        &["point:1", "1,2", "1"],
        &["--scale-points", "X,Y,Z", "\"1,2\""],
    );
    bad(
        &["point:1", "point:5", "far"],
        &["--scale-points", "metres", "far"],
    );
    // --scale and --scale-points say the same thing twice: clap refuses (exit 2).
    let both = c.import(&["--scale", "2", "--scale-points", "point:1", "point:5", "1"]);
    assert_eq!(both.status.code(), Some(2));
}

/// An interrupted import (images written, no dataset.json) is finished by running it again.
#[test]
fn an_interrupted_import_can_be_run_again() {
    let c = capture(&["a", "b"]);
    ok(&c.import(&[]));
    std::fs::remove_file(c.root().join("dataset/dataset.json")).unwrap();
    std::fs::remove_file(c.root().join("dataset/import.json")).unwrap();
    ok(&c.import(&[]));
    assert!(Dataset::read(&c.root().join("dataset")).is_ok());
}

/// The same capture as a nerfstudio transforms.json (camera-to-world with OpenGL axes, shared
/// PINHOLE intrinsics overridden per frame by OPENCV ones, masks and millimetre depth PNGs)
/// imports to the same cameras and pixels as the COLMAP model, up to the world's origin (the
/// COLMAP import centres on the SfM points, which transforms.json does not carry).
#[test]
fn nerfstudio_transforms_import_as_the_colmap_model_does() {
    let c = capture(&["a", "b"]);
    let root = c.root();
    let up = ["--up", "0,-1,0"];
    let masks = root.join("masks");
    ok(&c.import(&[&up[..], &["--masks", masks.to_str().unwrap()]].concat()));
    let mut frames = Vec::new();
    for (k, (name, cam, q, t)) in c.images.iter().enumerate() {
        let r = DMat3::from_quat(*q);
        let rt = r.transpose();
        let centre = -(rt * *t);
        let (x, y, z) = (rt.x_axis, -rt.y_axis, -rt.z_axis);
        let m = [
            [x.x, y.x, z.x, centre.x],
            [x.y, y.y, z.y, centre.y],
            [x.z, y.z, z.z, centre.z],
            [0.0, 0.0, 0.0, 1.0],
        ];
        // 1.5 m everywhere, in millimetres.
        let depth = format!("depth/{k}.png");
        std::fs::create_dir_all(root.join("depth")).unwrap();
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_pixel(W, H, image::Luma([1500]))
            .save(root.join(&depth))
            .unwrap();
        let mut f = serde_json::json!({
            "file_path": format!("photos/{name}"),
            "transform_matrix": m,
            "mask_path": format!("masks/{name}.png"),
            "depth_file_path": depth,
        });
        if *cam == 2 {
            let p = OPENCV;
            for (key, v) in ["fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"]
                .iter()
                .zip(p)
            {
                f[*key] = v.into();
            }
            f["camera_model"] = "OPENCV".into();
        }
        frames.push(f);
    }
    let l = c.lens(1).params;
    let tj = serde_json::json!({"camera_model": "PINHOLE", "fl_x": l[0], "fl_y": l[1], "cx": l[2], "cy": l[3],
        "w": W, "h": H, "frames": frames});
    std::fs::write(
        root.join("transforms.json"),
        serde_json::to_vec(&tj).unwrap(),
    )
    .unwrap();
    let ns = |extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_lightfuse"))
            .args(["--quiet", "import", "nerfstudio"])
            .arg(root.join("transforms.json"))
            .arg("-o")
            .arg(root.join("ns"))
            .args(extra)
            .output()
            .unwrap()
    };
    // A nerfstudio capture has no 3D point ids to mark.
    refused(
        &ns(&["--scale-points", "point:1", "point:2", "1"]),
        &["--scale-points", "point:1", "nerfstudio"],
    );
    ok(&ns(&[&up[..], &["--scale", "2"]].concat()));
    let a = Dataset::read(&root.join("dataset")).unwrap();
    let b = Dataset::read(&root.join("ns")).unwrap();
    assert_eq!(a.objects.len(), b.objects.len());
    let mut offset = None;
    for (sa, sb) in a.states.iter().zip(&b.states) {
        assert_eq!(sa.name, sb.name);
        for (fa, fb) in sa.frames.iter().zip(&sb.frames) {
            let (ca, cb) = (fa.camera, fb.camera);
            assert_eq!(
                (ca.fl_x, ca.fl_y, ca.cx, ca.cy, ca.w, ca.h),
                (cb.fl_x, cb.fl_y, cb.cx, cb.cy, cb.w, cb.h)
            );
            for r in 0..3 {
                for k in 0..3 {
                    assert!((ca.transform_matrix[r][k] - cb.transform_matrix[r][k]).abs() < 1e-6);
                }
                // Centres: scale 2 against 1, and another origin: b = 2 a + const.
                let d = cb.transform_matrix[r][3] - 2.0 * ca.transform_matrix[r][3];
                let o = offset.get_or_insert([0.0f32; 3]);
                if sa.name == "a" && fa.file_path.ends_with("0000.exr") {
                    o[r] = d;
                }
                assert!((d - o[r]).abs() < 1e-4, "centre {r}: {d} vs {}", o[r]);
            }
            assert_eq!(
                a.frame_rgb(&fa.file_path, &ca).unwrap(),
                b.frame_rgb(&fb.file_path, &cb).unwrap()
            );
            assert_eq!(a.frame_mask(fa).unwrap(), b.frame_mask(fb).unwrap());
            // 1500 mm at 1e-3 m per unit, times --scale 2.
            let z = b
                .frame_planes(fb.depth_file_path.as_deref().unwrap(), &["Z"], &cb)
                .unwrap();
            assert!(z[0].iter().all(|&v| (v - 3.0).abs() < 1e-6));
        }
    }
    // Bad input: a spherical camera, a frame without a pose, a depth of the wrong size.
    let mut bad = tj.clone();
    bad["camera_model"] = "EQUIRECTANGULAR".into();
    std::fs::write(
        root.join("transforms.json"),
        serde_json::to_vec(&bad).unwrap(),
    )
    .unwrap();
    refused(
        &ns(&[]),
        &[
            "transforms.json",
            "frames[0].camera_model",
            "EQUIRECTANGULAR",
        ],
    );
    let mut bad = tj.clone();
    bad["frames"][1]["transform_matrix"] = serde_json::json!([[1, 0, 0], [0, 1, 0]]);
    std::fs::write(
        root.join("transforms.json"),
        serde_json::to_vec(&bad).unwrap(),
    )
    .unwrap();
    refused(
        &ns(&[]),
        &["transforms.json", "frames[1].transform_matrix", "4x4"],
    );
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(W, H - 1)
        .save(root.join("depth/0.png"))
        .unwrap();
    std::fs::write(
        root.join("transforms.json"),
        serde_json::to_vec(&tj).unwrap(),
    )
    .unwrap();
    std::fs::remove_dir_all(root.join("ns")).unwrap();
    refused(&ns(&[]), &["0.png", "size", "expected 64x48"]);
}
