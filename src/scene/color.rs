//! The sRGB transfer function (IEC 61966-2-1), both ways, and the 8-bit code a PNG stores.
//! Everything inside LightFuse is scene-linear (docs/design.md §2); sRGB is for what people
//! look at (PNG previews, the report's images) and for the metrics that compare 8-bit images,
//! and every one of those encodes here. (Stage 1's display-referred loss uses a differentiable
//! variant with a linear tail above 1, `optim::loss`: another function, on purpose.)

/// The sRGB encoding of a linear value clamped to [0, 1].
pub fn srgb_encode(x: f32) -> f32 {
    // In f64 so that 1 encodes to exactly 1.
    let x = x.clamp(0.0, 1.0) as f64;
    (if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }) as f32
}

/// The 8-bit sRGB code of a linear value: clamped to [0, 1], encoded, rounded to the nearest
/// code; NaN is 0.
pub fn srgb_byte(x: f32) -> u8 {
    (srgb_encode(if x.is_nan() { 0.0 } else { x }) * 255.0).round() as u8
}

/// sRGB decoding, encoded → linear (an 8-bit texture's values, as k / 255).
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}
