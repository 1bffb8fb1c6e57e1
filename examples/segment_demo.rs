//! Measures the background/object graph cut on a real dataset:
//!
//! ```text
//! cargo run --release --example segment_demo -- DATASET [STATE [DEPTH_TOLERANCE [SMOOTHNESS]]]
//! ```
//!
//! Surfels come from the back-projected depth of every view of the state (one per pixel with a
//! hit), thinned to one per 1 cm grid cell. Their labels come only from the graph cut; the
//! mask id of each surfel's source pixel is used afterwards, as the truth to score against.

use lightfuse::io::dataset::Dataset;
use lightfuse::stages::reconstruct::completion::seed_points;
use lightfuse::stages::reconstruct::segment::{
    neighbour_pairs, potts_weights, project, segment, unary_costs, Potts, SegmentParams,
    SurfelPoints,
};
use std::collections::HashMap;
use std::time::Instant;

/// Thinning grid, metres (the brief's 1 cm).
const GRID: f32 = 0.01;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let path = args.next().ok_or_else(|| {
        anyhow::anyhow!("usage: segment_demo DATASET [STATE [DEPTH_TOLERANCE [SMOOTHNESS]]]")
    })?;
    let data = Dataset::read(std::path::Path::new(&path))?;
    let k = match args.next() {
        Some(s) => s.parse()?,
        None => *data
            .train_states()
            .first()
            .ok_or_else(|| anyhow::anyhow!("no training state"))?,
    };
    let t0 = Instant::now();
    let observations = (0..data.states[k].frames.len())
        .map(|v| data.observation(k, v))
        .collect::<lightfuse::Result<Vec<_>>>()?;
    let t_load = t0.elapsed();

    let t1 = Instant::now();
    let mut points = SurfelPoints::default();
    let mut truth = Vec::new();
    let mut source = Vec::new();
    let mut cells: HashMap<[i32; 3], ()> = HashMap::new();
    let mut raw = 0;
    for o in &observations {
        let all = vec![true; o.depth.len()];
        let seeds = seed_points(o, &all)?;
        raw += seeds.len();
        for i in 0..seeds.len() {
            let key = seeds.position[i].map(|x| (x / GRID).floor() as i32);
            if cells.insert(key, ()).is_none() {
                points.position.push(seeds.position[i]);
                points.normal.push(seeds.normal[i]);
                points.color.push(seeds.rgb[i]);
                truth.push(seeds.mask[i]);
                source.push((o.view, seeds.pixel[i] as usize));
            }
        }
    }
    let t_points = t1.elapsed();

    // Optional overrides, to measure the sensitivity: depth tolerance, then smoothness λ.
    let mut params = SegmentParams::default();
    if let Some(t) = args.next() {
        params.depth_tolerance = t.parse()?;
    }
    if let Some(l) = args.next() {
        params.smoothness = l.parse()?;
    }
    let t2 = Instant::now();
    let seg = segment(&points, &observations, &params)?;
    let t_seg = t2.elapsed();

    println!(
        "state {} ({}), {} views: {raw} back-projected pixels -> {} surfels on a {} cm grid",
        k,
        data.states[k].name,
        observations.len(),
        points.len(),
        GRID * 100.0
    );
    println!(
        "depth tolerance {}, smoothness {}",
        params.depth_tolerance, params.smoothness
    );
    println!(
        "graph: {} edges; energy {:.1} (argmax of votes) -> {:.1} after {} sweeps",
        seg.edge_count, seg.energy_before, seg.energy_after, seg.sweeps
    );
    let unseen = seg
        .votes
        .chunks(seg.n_labels)
        .filter(|r| r.iter().all(|&c| c == 0))
        .count();
    println!("surfels seen by no view: {unseen}");
    let mut names = vec!["background".to_string(); seg.n_labels];
    for o in &data.objects {
        if (o.id as usize) < names.len() {
            names[o.id as usize] = o.name.clone();
        }
    }
    // A harder variant: every surfel surely votes in the view it came from (its own pixel at its
    // own depth). Withdraw that vote and rerun the same energy on the other views' votes only.
    let mut votes = seg.votes.clone();
    for (i, &(v, pix)) in source.iter().enumerate() {
        let o = &observations[v];
        if let Some((p, d)) = project(&o.camera, points.position[i]) {
            let observed = o.depth[p];
            if p == pix && (d - observed).abs() <= params.depth_tolerance * observed {
                votes[i * seg.n_labels + o.mask[p] as usize] -= 1;
            }
        }
    }
    let potts = Potts {
        n_labels: seg.n_labels,
        unary: unary_costs(&votes, seg.n_labels, params.vote_prior, params.share_floor),
        edges: potts_weights(
            &points,
            &neighbour_pairs(&points.position, params.neighbours, params.radius),
            &params,
        ),
    };
    let loo_init = potts.unary_argmin();
    let (loo, _) = potts.alpha_expansion(loo_init.clone(), params.max_sweeps);
    let loo_unseen = votes
        .chunks(seg.n_labels)
        .filter(|r| r.iter().all(|&c| c == 0))
        .count();
    println!("without the own-view vote, surfels seen by no other view: {loo_unseen}");
    println!("label        surfels  graph cut  argmax | without own view: graph cut  argmax");
    for (l, name) in names.iter().enumerate() {
        let on = (0..truth.len()).filter(|&i| truth[i] as usize == l);
        let total = on.clone().count();
        let cut = on.clone().filter(|&i| seg.labels[i] as usize == l).count();
        let arg = on
            .clone()
            .filter(|&i| seg.initial_labels[i] as usize == l)
            .count();
        let loo_cut = on.clone().filter(|&i| loo[i] as usize == l).count();
        let loo_arg = on.filter(|&i| loo_init[i] as usize == l).count();
        let pct = |c: usize| 100.0 * c as f64 / total as f64;
        if total > 0 {
            println!(
                "{l} {name:<10} {total:>7}  {:>8.2}%  {:>6.2}% |                   {:>8.2}%  {:>6.2}%",
                pct(cut),
                pct(arg),
                pct(loo_cut),
                pct(loo_arg)
            );
        }
    }
    let right = (0..truth.len())
        .filter(|&i| seg.labels[i] == truth[i])
        .count();
    println!(
        "all: {:.2}% correct; wall time: load {:.2} s, points {:.2} s, segment {:.2} s ({} threads)",
        100.0 * right as f64 / truth.len() as f64,
        t_load.as_secs_f64(),
        t_points.as_secs_f64(),
        t_seg.as_secs_f64(),
        rayon::current_num_threads()
    );
    Ok(())
}
