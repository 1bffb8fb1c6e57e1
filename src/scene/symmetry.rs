//! An object's rotational symmetries, as a dataset declares them (BOP's
//! `symmetries_continuous` / `symmetries_discrete`): what no image can tell apart, so pose
//! errors (`eval::pose`) are measured modulo them and registration need not resolve them.

/// A rotational symmetry of an object about an axis through `offset`, in its own frame.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Symmetry {
    /// Axis direction (any length > 0).
    pub axis: [f32; 3],
    /// 0 = continuous, n ≥ 2 = n-fold.
    pub order: u32,
    /// A point on the axis (object frame); the object's origin when absent.
    #[serde(default)]
    pub offset: [f32; 3],
}
