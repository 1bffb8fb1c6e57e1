//! Figures and images a stage's `report.json` is made of: PSNR in sRGB over the pixels a
//! capture saw a surface in, depth errors, capture | render | error strips, and pose errors
//! named by state and object.

use super::pose::PoseError;
use crate::error::{Error, Result};
use crate::scene::color::srgb_byte;
use serde::Serialize;
use std::path::Path;

fn srgb(x: f32) -> f64 {
    crate::scene::color::srgb_encode(x) as f64
}

/// PSNR in sRGB of `color` against the capture `reference` over the pixels where the capture
/// saw a surface (`reference_depth > 0`).
pub fn covered_psnr_srgb(
    color: &[[f32; 3]],
    reference: &[[f32; 3]],
    reference_depth: &[f32],
) -> f64 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for (i, c) in color.iter().enumerate() {
        if reference_depth[i] > 0.0 {
            for (&a, &b) in c.iter().zip(&reference[i]) {
                let d = srgb(a) - srgb(b);
                se += d * d;
            }
            n += 3;
        }
    }
    -10.0 * (se / n.max(1) as f64).max(1e-20).log10()
}

/// Saves a capture | render | 4 × |difference| strip as PNG (8-bit sRGB, [`comparison_strip`])
/// of the pixels where the capture saw a surface (`reference_depth > 0`); the rest is black.
pub fn save_comparison(
    color: &[[f32; 3]],
    reference: &[[f32; 3]],
    reference_depth: &[f32],
    width: u32,
    height: u32,
    path: &Path,
) -> Result<()> {
    let shown: Vec<bool> = reference_depth.iter().map(|&z| z > 0.0).collect();
    let strip = comparison_strip(reference, color, &[], Some(&shown), width, height);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    strip
        .save(path)
        .map_err(|e| Error::io(path, std::io::Error::other(e.to_string())))
}

/// Images side by side, `w` x `h` each, as 8-bit sRGB ([`srgb_byte`]): the truth, the render,
/// the `others` (a `None` is a mid-grey tile, so the columns keep their places), then
/// |render − truth| × 4 on the 8-bit values. Where `shown` is false every column is black.
/// Stage 1's held-out and training views and `lightfuse evaluate`'s per-view strips.
pub fn comparison_strip(
    truth: &[[f32; 3]],
    render: &[[f32; 3]],
    others: &[Option<&[[f32; 3]]>],
    shown: Option<&[bool]>,
    w: u32,
    h: u32,
) -> image::RgbImage {
    let n = others.len() as u32 + 3;
    let mut out = image::RgbImage::new(n * w, h);
    for i in 0..(w * h) as usize {
        if shown.is_some_and(|s| !s[i]) {
            continue;
        }
        let (x, y) = (i as u32 % w, i as u32 / w);
        let (t, r) = (truth[i].map(srgb_byte), render[i].map(srgb_byte));
        out.put_pixel(x, y, image::Rgb(t));
        out.put_pixel(x + w, y, image::Rgb(r));
        for (j, img) in others.iter().enumerate() {
            let px = img.map_or([128; 3], |img| img[i].map(srgb_byte));
            out.put_pixel(x + (j as u32 + 2) * w, y, image::Rgb(px));
        }
        let e = [0, 1, 2].map(|c| {
            let d = 4.0 * (r[c] as f32 - t[c] as f32).abs();
            d.round().min(255.0) as u8
        });
        out.put_pixel(x + (n - 1) * w, y, image::Rgb(e));
    }
    out
}

/// |D̂ − D*| at every pixel with reference depth, in pixel order; where the render saw nothing
/// (`alpha` 0) the error is the reference depth itself.
pub fn depth_errors(depth: &[f32], alpha: &[f32], reference_depth: &[f32]) -> Vec<f64> {
    (0..reference_depth.len())
        .filter(|&i| reference_depth[i] > 0.0)
        .map(|i| {
            if alpha[i] > 0.0 {
                (depth[i] - reference_depth[i]).abs() as f64
            } else {
                reference_depth[i] as f64
            }
        })
        .collect()
}

/// One object's estimated pose in one state against the ground truth, as `report.json` lists it.
#[derive(Clone, Debug, Serialize)]
pub struct ObjectPoseError {
    pub state: String,
    pub object: String,
    /// The pose the stage ended with.
    #[serde(flatten)]
    pub error: PoseError,
    /// The same error of the pose point-cloud registration found, of the one the rendered
    /// alignment chose, of the better of the two after the ICP polish, and of the turn of it
    /// the texture chose, where training started (absent with oracle poses and in work folders
    /// without `poses.json`): where an error entered.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub registered: Option<PoseError>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub aligned: Option<PoseError>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub polished: Option<PoseError>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub turned: Option<PoseError>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_counts_covered_pixels_only() {
        let color = [[0.5, 0.5, 0.5], [1.0, 0.0, 0.0]];
        let reference = [[0.5, 0.5, 0.5], [0.0, 1.0, 0.0]];
        let exact = covered_psnr_srgb(&color, &reference, &[1.0, 0.0]);
        assert!(exact >= 199.0, "{exact}");
        let wrong = covered_psnr_srgb(&color, &reference, &[1.0, 1.0]);
        assert!(wrong < 10.0, "{wrong}");
    }

    #[test]
    fn depth_errors_and_their_median() {
        let mut e = depth_errors(
            &[1.0, 2.5, 0.0, 7.0],
            &[1.0, 1.0, 0.0, 1.0],
            &[1.5, 2.0, 3.0, 0.0],
        );
        assert_eq!(e, [0.5, 0.5, 3.0]);
        assert_eq!(crate::stats::median(&mut e), Some(0.5));
    }

    #[test]
    fn pose_errors_keep_the_report_field_names() {
        let e = ObjectPoseError {
            state: "s1".into(),
            object: "mug".into(),
            error: PoseError {
                rotation_deg: 1.0,
                rotation_deg_raw: 2.0,
                translation_m: 0.5,
            },
            registered: None,
            aligned: None,
            polished: None,
            turned: None,
        };
        let text = serde_json::to_string(&e).expect("serialises");
        assert_eq!(
            text,
            r#"{"state":"s1","object":"mug","rotation_deg":1.0,"rotation_deg_ignoring_symmetry":2.0,"translation_cm":50.0}"#
        );
        let before = ObjectPoseError {
            registered: Some(e.error),
            ..e
        };
        let text = serde_json::to_string(&before).expect("serialises");
        assert!(
            text.ends_with(r#""translation_cm":50.0,"registered":{"rotation_deg":1.0,"rotation_deg_ignoring_symmetry":2.0,"translation_cm":50.0}}"#),
            "{text}"
        );
    }
}
