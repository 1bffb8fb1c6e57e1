//! Layouts: `layout.json` (`lightfuse-layout/1`), or the named object nodes of a glTF or a
//! LightFuse scene (docs/formats.md).

use super::AtomicFiles;
use crate::error::{Error, Result};
use crate::scene::layout::LAYOUT_FORMAT;
use crate::scene::{Layout, Rigid};
use serde_json::{json, Value};
use std::path::Path;

/// Reads a layout from `layout.json`, a LightFuse scene (its default state), or any glTF whose
/// top-level nodes are named after the objects.
pub fn read_layout(path: &Path) -> Result<Layout> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("json") => read_layout_json(path),
        Some("glb") | Some("gltf") | Some("usda") => {
            let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
            let lightfuse =
                ext.as_deref() == Some("usda") || crate::io::gltf::read_bytes(path, &bytes).is_ok();
            if lightfuse {
                let scene = crate::io::read_scene(path)?;
                let state = &scene.states[scene.reference_state];
                Ok(Layout {
                    objects: scene
                        .components
                        .iter()
                        .zip(&state.transforms)
                        .skip(1)
                        .map(|(c, t)| (c.name.clone(), *t))
                        .collect(),
                })
            } else {
                read_layout_gltf(path)
            }
        }
        _ => Err(Error::invalid(
            path,
            "file extension",
            "expected a layout: .json, .glb, .gltf or .usda",
        )),
    }
}

fn read_layout_json(path: &Path) -> Result<Layout> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let v: Value = serde_json::from_slice(&bytes)
        .map_err(|e| Error::invalid(path, "JSON", format!("expected valid JSON: {e}")))?;
    let format = v.get("format").and_then(Value::as_str);
    if format != Some(LAYOUT_FORMAT) {
        return Err(Error::invalid(
            path,
            "format",
            format!("expected \"{LAYOUT_FORMAT}\", found {:?}", v.get("format")),
        ));
    }
    let objects = v.get("objects").and_then(Value::as_object).ok_or_else(|| {
        Error::invalid(
            path,
            "objects",
            "expected an object mapping names to 4x4 matrices",
        )
    })?;
    let mut layout = Layout::default();
    for (name, m) in objects {
        let field = format!("objects.{name}");
        let rows: [[f32; 4]; 4] = serde_json::from_value(m.clone()).map_err(|_| {
            Error::invalid(path, &field, "expected a 4x4 matrix as 4 rows of 4 numbers")
        })?;
        let t = Rigid::from_rows(&rows).map_err(|msg| Error::invalid(path, &field, msg))?;
        layout.objects.insert(name.clone(), t);
    }
    Ok(layout)
}

fn read_layout_gltf(path: &Path) -> Result<Layout> {
    let gltf = gltf::Gltf::open(path).map_err(|e| {
        Error::invalid(
            path,
            "glTF",
            format!("expected a glTF file with named object nodes: {e}"),
        )
    })?;
    let scene = gltf
        .default_scene()
        .or_else(|| gltf.scenes().next())
        .ok_or_else(|| Error::invalid(path, "scenes", "expected a scene"))?;
    let mut layout = Layout::default();
    for node in scene.nodes() {
        let Some(name) = node.name() else { continue };
        let m = node.transform().matrix();
        let rows = [0, 1, 2, 3].map(|r| [m[0][r], m[1][r], m[2][r], m[3][r]]);
        let t = Rigid::from_rows(&rows)
            .map_err(|msg| Error::invalid(path, format!("node {name:?}"), msg))?;
        layout.objects.insert(name.to_string(), t);
    }
    Ok(layout)
}

/// Writes `layout.json` atomically.
pub fn write_layout(layout: &Layout, path: &Path) -> Result<()> {
    let objects: serde_json::Map<String, Value> = layout
        .objects
        .iter()
        .map(|(k, t)| (k.clone(), json!(t.rows())))
        .collect();
    let v = json!({ "format": LAYOUT_FORMAT, "objects": objects });
    let mut files = AtomicFiles::new();
    files.write(
        path,
        &serde_json::to_vec_pretty(&v).expect("layout serialises"),
    )?;
    files.commit()
}
