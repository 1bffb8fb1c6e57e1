//! OpenEXR through the `exr` crate: environment maps (any compression the crate decodes,
//! including the DWAB of Blender's bundled HDRIs) and multi-channel float images (AOVs).

use crate::error::{Error, Result};
use crate::scene::Environment;
use crate::shade::render::RenderedImage;
use exr::prelude::*;
use std::io::Cursor;
use std::path::Path;

/// Lossless ZIP in scanline blocks: the layout every EXR reader (OpenEXR, Blender, numpy-based
/// readers in `blender/`) handles; the crate's FAST_LOSSLESS preset writes tiles.
const SCANLINE_ZIP: Encoding = Encoding {
    compression: Compression::ZIP16,
    blocks: Blocks::ScanLines,
    line_order: LineOrder::Increasing,
};

/// Largest environment accepted: 16384 x 8192 texels (1.5 GiB as f32 RGB).
pub const MAX_ENVIRONMENT_TEXELS: usize = 16384 * 8192;

fn exr_err(file: &Path, e: exr::error::Error) -> Error {
    match e {
        exr::error::Error::Io(io) => Error::io(file, io),
        exr::error::Error::NotSupported(what) => Error::invalid(
            file,
            "EXR layout",
            format!("unsupported by LightFuse's EXR reader: {what}"),
        ),
        other => Error::invalid(
            file,
            "EXR",
            format!("expected a valid OpenEXR file: {other}"),
        ),
    }
}

/// An environment map from a file, checked: an EXR with R, G and B ([`read_environment`]) that
/// is an equirectangular lat-long map (width = 2 x height), its texels as stored. Named `name`,
/// or the file's stem. `lightfuse env` converts with it; everything that lights a scene reads
/// through [`read_lighting`].
pub fn read_latlong(path: &Path, name: Option<&str>) -> Result<Environment> {
    let name = name.map_or_else(
        || super::file_stem(path).unwrap_or_default(),
        str::to_string,
    );
    let env = read_environment(path, &name)?;
    env.check_latlong(path, "EXR data window")?;
    Ok(env)
}

/// A user's (or a dataset's) environment map, ready to light with: [`read_latlong`], negative
/// texels (a lossy codec's or a resampler's ringing, which no light emits) set to zero. Every
/// command that lights with a map from a file reads it here.
pub fn read_lighting(path: &Path, name: Option<&str>) -> Result<Environment> {
    let mut env = read_latlong(path, name)?;
    env.clamp_negative();
    Ok(env)
}

/// Reads an RGB environment from an EXR file as it is stored (scene files embed theirs; a
/// map from a user goes through [`read_lighting`]). Extra channels (A, ...) are ignored; a file
/// without R, G and B is refused.
pub fn read_environment(path: &Path, name: &str) -> Result<Environment> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    read_environment_bytes(&bytes, path, name)
}

/// Reads an environment from EXR bytes; `source` names them in errors.
pub fn read_environment_bytes(bytes: &[u8], source: &Path, name: &str) -> Result<Environment> {
    // Check the declared size before decoding allocates it: a corrupt header must not exhaust memory.
    let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
        .map_err(|e| exr_err(source, e))?;
    for header in meta.headers.iter() {
        let area = header.layer_size.area();
        if area > MAX_ENVIRONMENT_TEXELS {
            return Err(Error::invalid(
                source,
                "EXR data window",
                format!("expected an environment of at most {MAX_ENVIRONMENT_TEXELS} texels (16k x 8k), found {} x {}", header.layer_size.width(), header.layer_size.height()),
            ));
        }
    }
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgb_channels(
            |size, _| (size.width(), vec![[0.0f32; 3]; size.area()]),
            |(w, px), pos, (r, g, b): (f32, f32, f32)| px[pos.y() * *w + pos.x()] = [r, g, b],
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| match e {
            exr::error::Error::Invalid(msg) if msg.contains("channel") || msg.contains("layer") => {
                Error::invalid(
                    source,
                    "EXR channels",
                    format!(
                        "unsupported EXR layout: expected a layer with R, G and B channels ({msg})"
                    ),
                )
            }
            e => exr_err(source, e),
        })?;
    let size = image.layer_data.size;
    let (_, pixels) = image.layer_data.channel_data.pixels;
    if size.area() == 0 {
        return Err(Error::invalid(
            source,
            "EXR data window",
            "expected a non-empty image",
        ));
    }
    if let Some(v) = pixels.iter().flatten().find(|v| !v.is_finite()) {
        return Err(Error::invalid(
            source,
            "EXR pixels",
            format!("expected finite radiance, found {v}"),
        ));
    }
    Ok(Environment::new(name, size.width(), size.height(), pixels))
}

/// Encodes an environment as a float RGB EXR (ZIP, lossless, so files round-trip bit for bit).
pub fn environment_bytes(env: &Environment) -> Vec<u8> {
    let w = env.width;
    let channels = SpecificChannels::rgb(|pos: Vec2<usize>| {
        let p = env.pixels[pos.y() * w + pos.x()];
        (p[0], p[1], p[2])
    });
    let layer = Layer::new(
        (env.width, env.height),
        LayerAttributes::named(env.name.as_str()),
        SCANLINE_ZIP,
        channels,
    );
    let mut out = Cursor::new(Vec::new());
    Image::from_layer(layer)
        .write()
        .to_buffered(&mut out)
        .expect("encoding an in-memory EXR cannot fail");
    out.into_inner()
}

/// Writes an environment EXR atomically.
pub fn write_environment(env: &Environment, path: &Path) -> Result<()> {
    let mut files = super::AtomicFiles::new();
    files.write(path, &environment_bytes(env))?;
    files.commit()
}

/// A float image with named channels (AOVs: `R`, `G`, `B`, `A`, `Z`, `N.X`, ...).
#[derive(Clone, Debug, PartialEq)]
pub struct Channels {
    pub width: usize,
    pub height: usize,
    /// (name, row-major values), each `width * height` long.
    pub channels: Vec<(String, Vec<f32>)>,
}

impl Channels {
    /// The channels `lightfuse render` writes of a rendered view: `R, G, B` (radiance), `A`
    /// (coverage), `Z` (planar depth), `N.X, N.Y, N.Z` (normal) and, when the image has them,
    /// `albedo.R, albedo.G, albedo.B` (base colour). docs/formats.md names them.
    pub fn from_render(image: &RenderedImage) -> Channels {
        let plane3 = |v: &[[f32; 3]], k: usize| v.iter().map(|p| p[k]).collect::<Vec<f32>>();
        let aovs = &image.aovs;
        let mut channels = vec![
            ("R".to_string(), plane3(&image.radiance, 0)),
            ("G".to_string(), plane3(&image.radiance, 1)),
            ("B".to_string(), plane3(&image.radiance, 2)),
            ("A".to_string(), aovs.alpha.clone()),
            ("Z".to_string(), aovs.depth.clone()),
            ("N.X".to_string(), plane3(&aovs.normal, 0)),
            ("N.Y".to_string(), plane3(&aovs.normal, 1)),
            ("N.Z".to_string(), plane3(&aovs.normal, 2)),
        ];
        if !aovs.albedo.is_empty() {
            for (k, name) in ["albedo.R", "albedo.G", "albedo.B"].into_iter().enumerate() {
                channels.push((name.to_string(), plane3(&aovs.albedo, k)));
            }
        }
        Channels {
            width: image.width,
            height: image.height,
            channels,
        }
    }

    pub fn get(&self, name: &str) -> Option<&[f32]> {
        self.channels
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
    }
}

/// Writes a multi-channel float EXR (ZIP) atomically.
pub fn write_channels(image: &Channels, path: &Path) -> Result<()> {
    let size = (image.width, image.height);
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> = image
        .channels
        .iter()
        .map(|(name, values)| {
            assert_eq!(
                values.len(),
                image.width * image.height,
                "channel {name} size"
            );
            AnyChannel::new(name.as_str(), FlatSamples::F32(values.clone()))
        })
        .collect();
    let layer = Layer::new(
        size,
        LayerAttributes::default(),
        SCANLINE_ZIP,
        AnyChannels::sort(list),
    );
    let mut bytes = Cursor::new(Vec::new());
    Image::from_layer(layer)
        .write()
        .to_buffered(&mut bytes)
        .map_err(|e| exr_err(path, e))?;
    let mut files = super::AtomicFiles::new();
    files.write(path, &bytes.into_inner())?;
    files.commit()
}

/// Reads every channel of the first layer of an EXR as f32.
pub fn read_channels(path: &Path) -> Result<Channels> {
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|e| exr_err(path, e))?;
    let size = image.layer_data.size;
    let channels = image
        .layer_data
        .channel_data
        .list
        .iter()
        .map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect()))
        .collect();
    Ok(Channels {
        width: size.width(),
        height: size.height(),
        channels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn environment_round_trips_bit_for_bit() {
        let px: Vec<[f32; 3]> = (0..24)
            .map(|i| [i as f32 * 0.37, 1e-8 * i as f32, 65504.0 + i as f32])
            .collect();
        let env = Environment::new("e", 6, 4, px);
        let back =
            read_environment_bytes(&environment_bytes(&env), Path::new("mem.exr"), "e").unwrap();
        assert_eq!(back, env);
    }

    #[test]
    fn channels_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("aov.exr");
        let img = Channels {
            width: 3,
            height: 2,
            channels: vec![
                ("Z".into(), vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
                ("A".into(), vec![0.5; 6]),
            ],
        };
        write_channels(&img, &path).unwrap();
        let back = read_channels(&path).unwrap();
        assert_eq!(back.get("Z").unwrap(), img.get("Z").unwrap());
        assert_eq!(back.get("A").unwrap(), img.get("A").unwrap());
    }

    #[test]
    fn missing_rgb_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("z.exr");
        let img = Channels {
            width: 2,
            height: 2,
            channels: vec![("Z".into(), vec![1.0; 4])],
        };
        write_channels(&img, &path).unwrap();
        let err = read_environment(&path, "z").unwrap_err();
        assert!(err.is_user_error());
        assert!(err.to_string().contains("z.exr"), "{err}");
    }

    #[test]
    fn missing_file_names_the_file() {
        let err = read_environment(Path::new("/nonexistent/env.exr"), "x").unwrap_err();
        assert!(err.to_string().contains("/nonexistent/env.exr"));
        assert!(err.is_user_error());
    }
}
