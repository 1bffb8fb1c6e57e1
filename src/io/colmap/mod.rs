//! COLMAP sparse models: `cameras`, `images` and `points3D`, binary (`.bin`) or text (`.txt`),
//! as COLMAP's `sparse/0` folders hold them (the format: colmap.github.io/format.html; the
//! readers: `src/colmap/scene/reconstruction_io.cc`). COLMAP ≥ 3.12 also writes `rigs` and
//! `frames`; an image's pose in `images` is still its own camera-from-world, which is all we
//! read, so those two files are not needed.
//!
//! Written by hand: no maintained crate reads COLMAP's binary model. Checked against files
//! written by real COLMAP (pycolmap, `tests/data/colmap/`) in `tests/colmap.rs`.

pub mod lens;

use crate::error::{Error, Result};
use lens::{Lens, LensModel};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// One registered image: its camera, name (path relative to the image folder, `/`-separated)
/// and pose, COLMAP's world-to-camera rotation (unit quaternion w, x, y, z) and translation.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    pub camera_id: u32,
    pub name: String,
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    /// Keypoints `(x, y)` in pixels and the id of their 3D point (-1 for none).
    pub points2d: Vec<([f64; 2], i64)>,
}

impl ColmapImage {
    /// Camera-from-world as a 3x4 row-major matrix (COLMAP's axes: +Z forward, +Y down).
    pub fn cam_from_world(&self) -> [[f64; 4]; 3] {
        let [w, x, y, z] = self.qvec;
        let r = [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ];
        let t = self.tvec;
        [
            [r[0][0], r[0][1], r[0][2], t[0]],
            [r[1][0], r[1][1], r[1][2], t[1]],
            [r[2][0], r[2][1], r[2][2], t[2]],
        ]
    }

    /// The camera's centre in the world, `-Rᵀ t`.
    pub fn centre(&self) -> [f64; 3] {
        let m = self.cam_from_world();
        let mut c = [0.0; 3];
        for (j, cj) in c.iter_mut().enumerate() {
            *cj = -(0..3).map(|i| m[i][j] * m[i][3]).sum::<f64>();
        }
        c
    }
}

/// A triangulated point: position, colour, mean reprojection error (pixels) and track
/// (image id, keypoint index).
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapPoint {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
    pub track: Vec<(u32, u32)>,
}

/// A sparse model: cameras and images by id, points in file order.
#[derive(Clone, Debug, Default)]
pub struct Model {
    pub cameras: BTreeMap<u32, Lens>,
    pub images: BTreeMap<u32, ColmapImage>,
    pub points: Vec<ColmapPoint>,
    /// The folder the model was read from.
    pub dir: PathBuf,
}

/// Reads the model in `dir`: `cameras.bin`, `images.bin`, `points3D.bin`, or the `.txt` three
/// when the binary ones are absent. A folder holding numbered models (`sparse/` with `0/`,
/// `1/`) is refused with their names: COLMAP splits a capture it could not register into one
/// world that way, and LightFuse needs every state in one.
pub fn read_model(dir: &Path) -> Result<Model> {
    let has = |ext: &str| {
        ["cameras", "images", "points3D"]
            .iter()
            .all(|n| dir.join(format!("{n}.{ext}")).is_file())
    };
    let mut model = if has("bin") {
        Model {
            cameras: read_cameras_bin(&dir.join("cameras.bin"))?,
            images: read_images_bin(&dir.join("images.bin"))?,
            points: read_points_bin(&dir.join("points3D.bin"))?,
            dir: dir.to_path_buf(),
        }
    } else if has("txt") {
        Model {
            cameras: read_cameras_txt(&dir.join("cameras.txt"))?,
            images: read_images_txt(&dir.join("images.txt"))?,
            points: read_points_txt(&dir.join("points3D.txt"))?,
            dir: dir.to_path_buf(),
        }
    } else {
        let mut sub: Vec<String> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok())
            .filter(|e| {
                e.path().join("cameras.bin").is_file() || e.path().join("cameras.txt").is_file()
            })
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        sub.sort();
        let message = if sub.len() > 1 {
            format!(
                "expected one COLMAP model; this folder holds {} ({}): COLMAP registered the images \
                 as separate worlds. Reconstruct again so that one model holds every state, or \
                 point at one of them",
                sub.len(),
                sub.join(", ")
            )
        } else if sub.len() == 1 {
            format!("expected a COLMAP model here; it is in {}/", sub[0])
        } else {
            "expected a COLMAP sparse model: cameras, images and points3D as .bin or .txt".into()
        };
        return Err(Error::invalid(dir, "model", message));
    };
    model.check()?;
    Ok(model)
}

impl Model {
    /// Every image's camera exists and has the model's number of parameters; every track names
    /// an image and one of its keypoints.
    fn check(&mut self) -> Result<()> {
        for (id, c) in &self.cameras {
            if c.params.len() != c.model.num_params() {
                return Err(Error::invalid(
                    self.file("cameras"),
                    format!("camera {id}.params"),
                    format!(
                        "expected {} parameters for {}, found {}",
                        c.model.num_params(),
                        c.model.name(),
                        c.params.len()
                    ),
                ));
            }
            if c.width == 0 || c.height == 0 {
                return Err(Error::invalid(
                    self.file("cameras"),
                    format!("camera {id}.width/height"),
                    "expected a non-zero image size",
                ));
            }
        }
        for (id, im) in &self.images {
            if !self.cameras.contains_key(&im.camera_id) {
                return Err(Error::invalid(
                    self.file("images"),
                    format!("image {id}.camera_id"),
                    format!("camera {} is not in the model's cameras", im.camera_id),
                ));
            }
            let n = im.qvec.iter().map(|q| q * q).sum::<f64>().sqrt();
            if !(n.is_finite() && (n - 1.0).abs() < 1e-3) {
                return Err(Error::invalid(
                    self.file("images"),
                    format!("image {id}.qvec"),
                    format!("expected a unit quaternion, found norm {n}"),
                ));
            }
        }
        for p in &self.points {
            for &(img, k) in &p.track {
                let ok = self
                    .images
                    .get(&img)
                    .is_some_and(|im| (k as usize) < im.points2d.len());
                if !ok {
                    return Err(Error::invalid(
                        self.file("points3D"),
                        format!("point {}.track", p.id),
                        format!("keypoint {k} of image {img} is not in the model's images"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The file a part of the model was read from, for errors.
    pub fn file(&self, part: &str) -> PathBuf {
        let bin = self.dir.join(format!("{part}.bin"));
        if bin.is_file() {
            bin
        } else {
            self.dir.join(format!("{part}.txt"))
        }
    }
}

/// Little-endian reads over a file's bytes; a short file is an error naming it and the field
/// being read.
struct Bytes<'a> {
    data: &'a [u8],
    at: usize,
    file: &'a Path,
}

impl<'a> Bytes<'a> {
    fn new(data: &'a [u8], file: &'a Path) -> Self {
        Bytes { data, at: 0, file }
    }
    fn take(&mut self, n: usize, field: &dyn Fn() -> String) -> Result<&'a [u8]> {
        if self.data.len() - self.at < n {
            return Err(Error::invalid(
                self.file,
                field(),
                format!(
                    "the file ends at byte {} (truncated?): expected {n} more bytes",
                    self.data.len()
                ),
            ));
        }
        let s = &self.data[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    fn u64(&mut self, field: &dyn Fn() -> String) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8, field)?.try_into().unwrap()))
    }
    fn u32(&mut self, field: &dyn Fn() -> String) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4, field)?.try_into().unwrap()))
    }
    fn i32(&mut self, field: &dyn Fn() -> String) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(4, field)?.try_into().unwrap()))
    }
    fn i64(&mut self, field: &dyn Fn() -> String) -> Result<i64> {
        Ok(i64::from_le_bytes(self.take(8, field)?.try_into().unwrap()))
    }
    fn f64(&mut self, field: &dyn Fn() -> String) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8, field)?.try_into().unwrap()))
    }
    /// A count that must fit in what is left of the file at `each` bytes per item (a corrupt
    /// count would otherwise allocate without bound).
    fn count(&mut self, each: usize, field: &dyn Fn() -> String) -> Result<usize> {
        let n = self.u64(field)?;
        let left = (self.data.len() - self.at) as u64;
        if n.saturating_mul(each as u64) > left {
            return Err(Error::invalid(
                self.file,
                field(),
                format!(
                    "a count of {n} does not fit in the {left} bytes left (truncated or corrupt)"
                ),
            ));
        }
        Ok(n as usize)
    }
    fn done(&self) -> Result<()> {
        if self.at != self.data.len() {
            return Err(Error::invalid(
                self.file,
                "end of file",
                format!(
                    "{} bytes left over after the last record",
                    self.data.len() - self.at
                ),
            ));
        }
        Ok(())
    }
}

fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

fn lens_model(file: &Path, field: &str, id: Option<i32>, name: Option<&str>) -> Result<LensModel> {
    let m = match (id, name) {
        (Some(i), _) => LensModel::from_id(i),
        (_, Some(n)) => LensModel::from_name(n),
        _ => None,
    };
    m.ok_or_else(|| {
        let found = id
            .map(|i| i.to_string())
            .or(name.map(str::to_string))
            .unwrap_or_default();
        Error::invalid(
            file,
            field,
            format!(
                "unknown camera model {found}; COLMAP's are {}",
                LensModel::names()
            ),
        )
    })
}

pub fn read_cameras_bin(path: &Path) -> Result<BTreeMap<u32, Lens>> {
    let data = read_bytes(path)?;
    let mut b = Bytes::new(&data, path);
    let n = b.count(24, &|| "num_cameras".into())?;
    let mut out = BTreeMap::new();
    for i in 0..n {
        let f = move || format!("camera[{i}]");
        let id = b.u32(&f)?;
        let model = lens_model(path, &f(), Some(b.i32(&f)?), None)?;
        let width = b.u64(&f)?;
        let height = b.u64(&f)?;
        let params = (0..model.num_params())
            .map(|_| b.f64(&f))
            .collect::<Result<Vec<_>>>()?;
        out.insert(id, lens_from(path, &f(), model, width, height, params)?);
    }
    b.done()?;
    Ok(out)
}

fn lens_from(
    file: &Path,
    field: &str,
    model: LensModel,
    width: u64,
    height: u64,
    params: Vec<f64>,
) -> Result<Lens> {
    let (Ok(width), Ok(height)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(Error::invalid(
            file,
            format!("{field}.width/height"),
            "expected an image size below 2^32",
        ));
    };
    if let Some(bad) = params.iter().find(|p| !p.is_finite()) {
        return Err(Error::invalid(
            file,
            format!("{field}.params"),
            format!("expected finite parameters, found {bad}"),
        ));
    }
    Ok(Lens {
        model,
        width,
        height,
        params,
    })
}

pub fn read_images_bin(path: &Path) -> Result<BTreeMap<u32, ColmapImage>> {
    let data = read_bytes(path)?;
    let mut b = Bytes::new(&data, path);
    let n = b.count(64, &|| "num_reg_images".into())?;
    let mut out = BTreeMap::new();
    for i in 0..n {
        let f = move || format!("image[{i}]");
        let id = b.u32(&f)?;
        let qvec = [b.f64(&f)?, b.f64(&f)?, b.f64(&f)?, b.f64(&f)?];
        let tvec = [b.f64(&f)?, b.f64(&f)?, b.f64(&f)?];
        let camera_id = b.u32(&f)?;
        let mut name = Vec::new();
        loop {
            let c = b.take(1, &|| format!("image[{i}].name"))?[0];
            if c == 0 {
                break;
            }
            name.push(c);
        }
        let name = String::from_utf8(name)
            .map_err(|_| Error::invalid(path, format!("image[{i}].name"), "expected UTF-8 text"))?;
        let np = b.count(24, &|| format!("image[{i}].num_points2D"))?;
        let mut points2d = Vec::with_capacity(np);
        for _ in 0..np {
            let x = b.f64(&f)?;
            let y = b.f64(&f)?;
            let p = b.i64(&f)?;
            points2d.push(([x, y], p));
        }
        out.insert(
            id,
            ColmapImage {
                id,
                camera_id,
                name,
                qvec,
                tvec,
                points2d,
            },
        );
    }
    b.done()?;
    Ok(out)
}

pub fn read_points_bin(path: &Path) -> Result<Vec<ColmapPoint>> {
    let data = read_bytes(path)?;
    let mut b = Bytes::new(&data, path);
    let n = b.count(51, &|| "num_points3D".into())?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let f = move || format!("point[{i}]");
        let id = b.u64(&f)?;
        let xyz = [b.f64(&f)?, b.f64(&f)?, b.f64(&f)?];
        let rgb: [u8; 3] = b.take(3, &f)?.try_into().unwrap();
        let error = b.f64(&f)?;
        let nt = b.count(8, &|| format!("point[{i}].track_length"))?;
        let track = (0..nt)
            .map(|_| Ok((b.u32(&f)?, b.u32(&f)?)))
            .collect::<Result<Vec<_>>>()?;
        out.push(ColmapPoint {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    b.done()?;
    Ok(out)
}

/// The non-comment lines of a text model file, with their line numbers (1-based).
fn text_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    Ok(text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim().to_string()))
        .filter(|(_, l)| !l.starts_with('#'))
        .collect())
}

fn parse<T: std::str::FromStr>(file: &Path, line: usize, what: &str, s: Option<&str>) -> Result<T> {
    let s = s.ok_or_else(|| {
        Error::invalid(
            file,
            format!("line {line}"),
            format!("expected {what}, found the end of the line"),
        )
    })?;
    s.parse().map_err(|_| {
        Error::invalid(
            file,
            format!("line {line}"),
            format!("expected {what}, found {s:?}"),
        )
    })
}

pub fn read_cameras_txt(path: &Path) -> Result<BTreeMap<u32, Lens>> {
    let mut out = BTreeMap::new();
    for (ln, l) in text_lines(path)? {
        if l.is_empty() {
            continue;
        }
        let mut t = l.split_whitespace();
        let id: u32 = parse(path, ln, "CAMERA_ID", t.next())?;
        let name = t.next();
        let model = lens_model(path, &format!("line {ln}"), None, Some(name.unwrap_or("")))?;
        let width: u64 = parse(path, ln, "WIDTH", t.next())?;
        let height: u64 = parse(path, ln, "HEIGHT", t.next())?;
        let params = t
            .map(|s| parse(path, ln, "a parameter", Some(s)))
            .collect::<Result<Vec<f64>>>()?;
        out.insert(
            id,
            lens_from(path, &format!("camera {id}"), model, width, height, params)?,
        );
    }
    Ok(out)
}

pub fn read_images_txt(path: &Path) -> Result<BTreeMap<u32, ColmapImage>> {
    let lines = text_lines(path)?;
    let mut out = BTreeMap::new();
    // Two lines per image; the second (keypoints) may be empty, so blank lines count here.
    let mut it = lines.into_iter();
    while let Some((ln, l)) = it.next() {
        if l.is_empty() {
            continue;
        }
        let mut t = l.split_whitespace();
        let id: u32 = parse(path, ln, "IMAGE_ID", t.next())?;
        let mut q = [0.0; 4];
        for (k, qk) in q.iter_mut().enumerate() {
            *qk = parse(path, ln, ["QW", "QX", "QY", "QZ"][k], t.next())?;
        }
        let mut tv = [0.0; 3];
        for (k, tk) in tv.iter_mut().enumerate() {
            *tk = parse(path, ln, ["TX", "TY", "TZ"][k], t.next())?;
        }
        let camera_id: u32 = parse(path, ln, "CAMERA_ID", t.next())?;
        // The name is the rest of the line: COLMAP allows spaces in it.
        let rest: Vec<&str> = t.collect();
        if rest.is_empty() {
            return Err(Error::invalid(
                path,
                format!("line {ln}"),
                "expected NAME, found the end of the line",
            ));
        }
        let name = rest.join(" ");
        let mut points2d = Vec::new();
        if let Some((ln2, l2)) = it.next() {
            let v: Vec<&str> = l2.split_whitespace().collect();
            if v.len() % 3 != 0 {
                return Err(Error::invalid(
                    path,
                    format!("line {ln2}"),
                    "expected POINTS2D as (X, Y, POINT3D_ID) triples",
                ));
            }
            for c in v.chunks(3) {
                points2d.push((
                    [
                        parse(path, ln2, "X", Some(c[0]))?,
                        parse(path, ln2, "Y", Some(c[1]))?,
                    ],
                    parse(path, ln2, "POINT3D_ID", Some(c[2]))?,
                ));
            }
        }
        out.insert(
            id,
            ColmapImage {
                id,
                camera_id,
                name,
                qvec: q,
                tvec: tv,
                points2d,
            },
        );
    }
    Ok(out)
}

pub fn read_points_txt(path: &Path) -> Result<Vec<ColmapPoint>> {
    let mut out = Vec::new();
    for (ln, l) in text_lines(path)? {
        if l.is_empty() {
            continue;
        }
        let mut t = l.split_whitespace();
        let id: u64 = parse(path, ln, "POINT3D_ID", t.next())?;
        let mut xyz = [0.0; 3];
        for (k, x) in xyz.iter_mut().enumerate() {
            *x = parse(path, ln, ["X", "Y", "Z"][k], t.next())?;
        }
        let mut rgb = [0u8; 3];
        for (k, c) in rgb.iter_mut().enumerate() {
            *c = parse(path, ln, ["R", "G", "B"][k], t.next())?;
        }
        let error: f64 = parse(path, ln, "ERROR", t.next())?;
        let rest: Vec<&str> = t.collect();
        if rest.len() % 2 != 0 {
            return Err(Error::invalid(
                path,
                format!("line {ln}"),
                "expected TRACK as (IMAGE_ID, POINT2D_IDX) pairs",
            ));
        }
        let track = rest
            .chunks(2)
            .map(|c| {
                Ok((
                    parse(path, ln, "IMAGE_ID", Some(c[0]))?,
                    parse(path, ln, "POINT2D_IDX", Some(c[1]))?,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        out.push(ColmapPoint {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    Ok(out)
}
