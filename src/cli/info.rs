//! `lightfuse info`: what a scene holds, as text or JSON.

use super::{Cli, InfoArgs};
use lightfuse::error::Result;
use lightfuse::scene::Scene;
use serde_json::json;

pub fn summary(scene: &Scene) -> serde_json::Value {
    let components: Vec<_> = scene
        .components
        .iter()
        .map(|c| {
            let b = c.surfels.bounds();
            json!({
                "name": c.name, "id": c.id, "surfels": c.surfels.len(), "sh_degree": c.surfels.sh_degree,
                "bounds": b.map(|(lo, hi)| json!({"min": lo, "max": hi})),
            })
        })
        .collect();
    let states: Vec<_> = scene
        .states
        .iter()
        .map(|s| {
            let moved: Vec<_> = scene.components.iter().zip(&s.transforms).filter(|(_, t)| !t.is_identity()).map(|(c, _)| c.name.clone()).collect();
            let bounds = scene.bounds_in_state(s).map(|(lo, hi)| json!({"min": lo, "max": hi}));
            let component_bounds: serde_json::Map<String, serde_json::Value> = scene
                .components
                .iter()
                .enumerate()
                .map(|(i, c)| (c.name.clone(), scene.component_bounds_in_state(i, s).map_or(serde_json::Value::Null, |(lo, hi)| json!({"min": lo, "max": hi}))))
                .collect();
            json!({
                "name": s.name, "moved_objects": moved, "bounds": bounds, "component_bounds": component_bounds,
                "environment": s.environment.map(|e| json!({"name": scene.environments[e.index].name, "rotation_deg": e.rotation_deg})),
            })
        })
        .collect();
    let environments: Vec<_> = scene
        .environments
        .iter()
        .map(|e| {
            let i = e.integral();
            let four_pi = 4.0 * std::f64::consts::PI;
            json!({"name": e.name, "width": e.width, "height": e.height, "mean_radiance": [i[0] / four_pi, i[1] / four_pi, i[2] / four_pi]})
        })
        .collect();
    json!({
        "surfels": scene.surfel_count(),
        "reference_state": scene.states[scene.reference_state].name,
        "components": components, "states": states, "environments": environments,
    })
}

pub fn run(cli: &Cli, a: &InfoArgs) -> Result<()> {
    let scene = lightfuse::io::read_scene(&a.scene)?;
    let s = summary(&scene);
    if cli.json {
        println!("{}", serde_json::to_string_pretty(&s).expect("JSON"));
        return Ok(());
    }
    let fmt3 = |v: &serde_json::Value| {
        v.as_array()
            .map(|a| {
                a.iter()
                    .map(|x| format!("{:.3}", x.as_f64().unwrap_or(f64::NAN)))
                    .collect::<Vec<_>>()
                    .join(", ")
            })
            .unwrap_or_default()
    };
    let bounds = |b: &serde_json::Value| {
        if b.is_null() {
            "empty".to_string()
        } else {
            format!("[{}] .. [{}]", fmt3(&b["min"]), fmt3(&b["max"]))
        }
    };
    println!(
        "{}: {} surfels, {} components, {} states, {} environments",
        a.scene.display(),
        s["surfels"],
        scene.components.len(),
        scene.states.len(),
        scene.environments.len()
    );
    println!("components:");
    for c in s["components"].as_array().into_iter().flatten() {
        println!(
            "  {:<16} id {:<3} {:>9} surfels  SH degree {}  bounds {}",
            c["name"].as_str().unwrap_or(""),
            c["id"],
            c["surfels"],
            c["sh_degree"],
            bounds(&c["bounds"])
        );
    }
    println!(
        "states (reference: {}):",
        s["reference_state"].as_str().unwrap_or("")
    );
    for st in s["states"].as_array().into_iter().flatten() {
        let env = &st["environment"];
        let env = if env.is_null() {
            "no environment".to_string()
        } else {
            format!(
                "environment {} rotated {}°",
                env["name"], env["rotation_deg"]
            )
        };
        let moved: Vec<_> = st["moved_objects"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|v| v.as_str())
            .collect();
        println!(
            "  {:<16} moved: {:<24} {}  bounds {}",
            st["name"].as_str().unwrap_or(""),
            if moved.is_empty() {
                "-".into()
            } else {
                moved.join(",")
            },
            env,
            bounds(&st["bounds"])
        );
    }
    if !scene.environments.is_empty() {
        println!("environments:");
        for e in s["environments"].as_array().into_iter().flatten() {
            println!(
                "  {:<16} {}x{}  mean radiance [{}]",
                e["name"].as_str().unwrap_or(""),
                e["width"],
                e["height"],
                fmt3(&e["mean_radiance"])
            );
        }
    }
    Ok(())
}
