//! `lightfuse edit`: a new named state (layout, materials, environment) written as a scene that
//! reads back (.glb and .usda) and survives .glb -> .usda -> .glb bit for bit; bad input is one
//! clear error, exit 2, and nothing written.

use lightfuse::io::layout::write_layout;
use lightfuse::scene::synthetic::random_scene;
use lightfuse::scene::{Environment, Layout, Rigid};
use std::process::Command;

fn lightfuse(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_lightfuse"))
        .args(args)
        .output()
        .expect("lightfuse runs")
}

#[test]
fn edit_writes_a_new_state_and_refuses_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = random_scene(2, 2, 2, 10, 0);
    let input = d.join("in.glb");
    lightfuse::io::write_scene(&scene, &input).unwrap();
    let mut layout = Layout::default();
    let moved = Rigid {
        rotation: glam::Quat::from_rotation_y(0.4).to_array(),
        translation: [0.3, 0.0, -0.2],
    };
    layout.objects.insert("object1".into(), moved);
    let lpath = d.join("layout.json");
    write_layout(&layout, &lpath).unwrap();
    let env = Environment::new("sky", 16, 8, vec![[0.5, 1.0, 2.0]; 128]);
    let epath = d.join("sky.exr");
    lightfuse::io::exr::write_environment(&env, &epath).unwrap();

    for out in ["out.glb", "out.usda"] {
        let o = d.join(out);
        let r = lightfuse(&[
            "--quiet".as_ref(),
            "edit".as_ref(),
            input.as_os_str(),
            "-o".as_ref(),
            o.as_os_str(),
            "--name".as_ref(),
            "moved".as_ref(),
            "--layout".as_ref(),
            lpath.as_os_str(),
            "--material".as_ref(),
            "object2:base_color=0.9,0.1,0.1".as_ref(),
            "--material".as_ref(),
            "background:roughness=0.2".as_ref(),
            "--env".as_ref(),
            epath.as_os_str(),
            "--env-rotation".as_ref(),
            "45".as_ref(),
        ]);
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        let back = lightfuse::io::read_scene(&o).unwrap();
        assert_eq!(back.states.len(), scene.states.len() + 1);
        let s = back.states.last().unwrap();
        assert_eq!(s.name, "moved");
        assert!(s.transforms[1].quat().angle_between(moved.quat()) < 1e-5);
        assert!(s.transforms[2].is_identity());
        let e = s.environment.expect("the new environment");
        assert!((e.rotation_deg - 45.0).abs() < 1e-4);
        assert_eq!(back.environments[e.index].pixels[0], [0.5, 1.0, 2.0]);
        let o2 = &back.components[2].surfels;
        assert!(o2.base_color.iter().all(|c| *c == [0.9, 0.1, 0.1]));
        assert!(back.components[0]
            .surfels
            .roughness
            .iter()
            .all(|&r| r == 0.2));
        assert_eq!(
            back.components[1].surfels.base_color,
            scene.components[1].surfels.base_color
        );
    }

    // The edit survives interchange bit for bit: edited .glb -> .usda -> .glb gives the same
    // scene (every f32 the same bits, the state, materials and environment) and the same bytes.
    let edited = d.join("out.glb");
    let (usda, back) = (d.join("edited.usda"), d.join("back.glb"));
    for (from, to) in [(&edited, &usda), (&usda, &back)] {
        let r = lightfuse(&[
            "--quiet".as_ref(),
            "convert".as_ref(),
            from.as_os_str(),
            to.as_os_str(),
        ]);
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    }
    assert_eq!(
        lightfuse::io::read_scene(&back).unwrap(),
        lightfuse::io::read_scene(&edited).unwrap()
    );
    assert!(
        std::fs::read(&back).unwrap() == std::fs::read(&edited).unwrap(),
        "edited .glb -> .usda -> .glb changed the file's bytes"
    );

    let o = d.join("bad.glb");
    let not_latlong = d.join("not_latlong.exr");
    lightfuse::io::exr::write_environment(
        &Environment::new("e", 30, 20, vec![[1.0; 3]; 600]),
        &not_latlong,
    )
    .unwrap();
    for (args, what) in [
        (vec!["--env", not_latlong.to_str().unwrap()], "2 x height"),
        (vec!["--material", "object1:roughness=-0.1"], "[0, 1]"),
        (vec!["--material", "object9:metallic=0.5"], "object9"),
        (vec!["--material", "object1:metallic=1.5"], "[0, 1]"),
        (vec!["--name", "state0"], "state0"),
        (vec!["--state", "nowhere"], "nowhere"),
    ] {
        let mut a: Vec<&std::ffi::OsStr> = vec!["edit".as_ref(), input.as_os_str()];
        a.extend(["-o".as_ref(), o.as_os_str()]);
        a.extend(args.iter().map(std::ffi::OsStr::new));
        let r = lightfuse(&a);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains(what) && !err.contains("panicked"),
            "{args:?}: {err}"
        );
        assert!(!o.exists(), "{args:?} wrote {}", o.display());
    }
}
