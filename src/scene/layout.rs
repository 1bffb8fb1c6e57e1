//! Layouts: a rigid transform per object relative to the reference state (`layout.json`).

use super::Rigid;
use std::collections::BTreeMap;

pub const LAYOUT_FORMAT: &str = "lightfuse-layout/1";

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Layout {
    pub objects: BTreeMap<String, Rigid>,
}
