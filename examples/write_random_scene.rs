//! Writes a deterministic random scene (every attribute exercised): the fixture that external
//! readers and validators are tested on. Usage: write_random_scene OUT [SEED] [SH_DEGREE]
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let out = std::path::PathBuf::from(
        args.get(1)
            .expect("usage: write_random_scene OUT [SEED] [SH_DEGREE]"),
    );
    let seed = args.get(2).map_or(1, |s| s.parse().expect("seed"));
    let degree = args.get(3).map_or(3, |s| s.parse().expect("SH degree"));
    let scene = lightfuse::scene::synthetic::random_scene(seed, 2, 3, 100, degree);
    if let Err(e) = lightfuse::io::write_scene(&scene, &out) {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
}
