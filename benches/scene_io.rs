//! Writing and reading a 1M-surfel scene (SH degree 3, three states, two objects) as `.glb` and
//! `.usda`. Throughput is the file's size, so criterion reports MB/s.
//! Run: `cargo bench --bench scene_io`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightfuse::io;
use lightfuse::scene::synthetic::random_scene;
use std::time::Duration;

const SURFELS: usize = 1_000_000;

fn scene_io(c: &mut Criterion) {
    // Three components of a third each: one million surfels in all.
    let scene = random_scene(42, 2, 3, SURFELS / 3, 3);
    let dir = tempfile::tempdir().expect("temporary directory");
    let mut group = c.benchmark_group("scene_io_1M");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(20))
        .warm_up_time(Duration::from_secs(2));
    for ext in ["glb", "usda"] {
        let path = dir.path().join(format!("bench.{ext}"));
        io::write_scene(&scene, &path).expect("write");
        let bytes = std::fs::metadata(&path).expect("size").len();
        group.throughput(Throughput::Bytes(bytes));
        group.bench_function(format!("write_{ext}"), |b| {
            b.iter(|| io::write_scene(&scene, &path).expect("write"))
        });
        group.bench_function(format!("read_{ext}"), |b| {
            b.iter(|| io::read_scene(&path).expect("read"))
        });
    }
    group.finish();
}

criterion_group!(benches, scene_io);
criterion_main!(benches);
