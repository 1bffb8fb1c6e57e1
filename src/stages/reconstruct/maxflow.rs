//! Maximum s–t flow / minimum cut by Dinic's algorithm, for the α-expansion moves of the
//! object segmentation (GaussianCut, Jain et al. 2024).
//!
//! Hand-written on purpose: the Rust graph crates we know of that are well kept (`petgraph`,
//! `pathfinding`) offer only augmenting-path max flow (Ford–Fulkerson / Edmonds–Karp, O(V E²)),
//! which is far too slow for graph cuts over 10⁵ surfels, and there is no maintained
//! Boykov–Kolmogorov crate. Dinic's blocking flows are short, have no recursion here (paths in a
//! surfel graph can be 10⁵ nodes long) and keep their buffers between solves, so one
//! `MaxFlow` serves every expansion move.
//!
//! Capacities are `f64`; a residual below `EPS_REL` × the largest capacity counts as saturated,
//! so rounding in the augmentations can never create endless tiny paths.

use std::collections::VecDeque;

/// Residuals below this share of the largest capacity are treated as zero (f64 has ~1e-16
/// relative precision, so sums of a few thousand augmentations stay far above it).
const EPS_REL: f64 = 1e-12;

/// A directed flow network over nodes `0..n`. Each `add_edge` stores the edge and its reverse
/// (with the reverse capacity), so edge `e` and `e ^ 1` are partners.
#[derive(Clone, Debug, Default)]
pub struct MaxFlow {
    n: usize,
    from: Vec<u32>,
    to: Vec<u32>,
    /// Capacity as added.
    cap: Vec<f64>,
    /// Residual capacity after `solve`.
    residual: Vec<f64>,
    // CSR adjacency built by `solve`: the edges leaving node u are `adj[start[u]..start[u + 1]]`.
    start: Vec<u32>,
    adj: Vec<u32>,
    level: Vec<i32>,
    cursor: Vec<u32>,
    eps: f64,
}

impl MaxFlow {
    pub fn new(n: usize) -> Self {
        let mut g = MaxFlow::default();
        g.reset(n);
        g
    }

    /// Removes all edges and sets the node count, keeping the allocations.
    pub fn reset(&mut self, n: usize) {
        self.n = n;
        self.from.clear();
        self.to.clear();
        self.cap.clear();
        self.residual.clear();
    }

    pub fn node_count(&self) -> usize {
        self.n
    }

    /// Number of stored edges (each `add_edge` stores two).
    pub fn edge_count(&self) -> usize {
        self.to.len()
    }

    /// Adds u → v with capacity `cap` and v → u with `rev_cap` (both ≥ 0). Returns the id of
    /// u → v; its partner is `id ^ 1`.
    pub fn add_edge(&mut self, u: usize, v: usize, cap: f64, rev_cap: f64) -> usize {
        assert!(
            u < self.n && v < self.n,
            "edge {u} -> {v} outside 0..{}",
            self.n
        );
        assert!(
            cap >= 0.0 && rev_cap >= 0.0 && cap.is_finite() && rev_cap.is_finite(),
            "capacities must be finite and non-negative, got {cap}, {rev_cap}"
        );
        let id = self.to.len();
        self.from.extend([u as u32, v as u32]);
        self.to.extend([v as u32, u as u32]);
        self.cap.extend([cap, rev_cap]);
        id
    }

    /// Endpoints and capacity of edge `e`.
    pub fn edge(&self, e: usize) -> (usize, usize, f64) {
        (self.from[e] as usize, self.to[e] as usize, self.cap[e])
    }

    /// Net flow pushed along edge `e` by the last `solve` (negative when it runs backwards).
    pub fn flow(&self, e: usize) -> f64 {
        self.cap[e] - self.residual[e]
    }

    /// Pushes a maximum flow from `s` to `t` and returns its value.
    pub fn solve(&mut self, s: usize, t: usize) -> f64 {
        assert!(s < self.n && t < self.n && s != t, "bad terminals {s}, {t}");
        self.build_adjacency();
        self.residual.clone_from(&self.cap);
        let max_cap = self.cap.iter().fold(0.0f64, |a, &c| a.max(c));
        self.eps = max_cap * EPS_REL;
        let mut total = 0.0;
        let mut path: Vec<u32> = Vec::new();
        while self.bfs_levels(s, t) {
            self.cursor.clear();
            self.cursor.extend_from_slice(&self.start[..self.n]);
            total += self.blocking_flow(s, t, &mut path);
        }
        total
    }

    /// After `solve`: true for the nodes on the source side of a minimum cut (reachable from
    /// `s` through unsaturated residual edges).
    pub fn source_side(&self, s: usize) -> Vec<bool> {
        let mut seen = vec![false; self.n];
        let mut queue = VecDeque::from([s]);
        seen[s] = true;
        while let Some(u) = queue.pop_front() {
            for &e in &self.adj[self.start[u] as usize..self.start[u + 1] as usize] {
                let v = self.to[e as usize] as usize;
                if !seen[v] && self.residual[e as usize] > self.eps {
                    seen[v] = true;
                    queue.push_back(v);
                }
            }
        }
        seen
    }

    /// After `solve`: true for the nodes that can still reach `t` through unsaturated residual
    /// edges: the sink side of the minimum cut with the *largest* source side, so nodes whose
    /// side does not matter to the cut value stay with the source.
    pub fn sink_side(&self, t: usize) -> Vec<bool> {
        let mut seen = vec![false; self.n];
        let mut queue = VecDeque::from([t]);
        seen[t] = true;
        while let Some(v) = queue.pop_front() {
            // Edge e leaves v, so its partner e ^ 1 runs u -> v.
            for &e in &self.adj[self.start[v] as usize..self.start[v + 1] as usize] {
                let u = self.to[e as usize] as usize;
                if !seen[u] && self.residual[e as usize ^ 1] > self.eps {
                    seen[u] = true;
                    queue.push_back(u);
                }
            }
        }
        seen
    }

    fn build_adjacency(&mut self) {
        self.start.clear();
        self.start.resize(self.n + 1, 0);
        for &u in &self.from {
            self.start[u as usize + 1] += 1;
        }
        for u in 0..self.n {
            self.start[u + 1] += self.start[u];
        }
        self.adj.clear();
        self.adj.resize(self.from.len(), 0);
        let mut fill = self.start.clone();
        for (e, &u) in self.from.iter().enumerate() {
            self.adj[fill[u as usize] as usize] = e as u32;
            fill[u as usize] += 1;
        }
    }

    /// Breadth-first levels from `s` over unsaturated edges; false when `t` is unreachable.
    fn bfs_levels(&mut self, s: usize, t: usize) -> bool {
        self.level.clear();
        self.level.resize(self.n, -1);
        self.level[s] = 0;
        let mut queue = VecDeque::from([s]);
        while let Some(u) = queue.pop_front() {
            for &e in &self.adj[self.start[u] as usize..self.start[u + 1] as usize] {
                let v = self.to[e as usize] as usize;
                if self.level[v] < 0 && self.residual[e as usize] > self.eps {
                    self.level[v] = self.level[u] + 1;
                    queue.push_back(v);
                }
            }
        }
        self.level[t] >= 0
    }

    /// One Dinic phase, iterative: advance along admissible edges (level + 1, unsaturated),
    /// retreat from dead ends (which leave the level graph), augment when `t` is reached and
    /// restart from the tail of the first saturated edge.
    fn blocking_flow(&mut self, s: usize, t: usize, path: &mut Vec<u32>) -> f64 {
        let mut pushed = 0.0;
        path.clear();
        let mut u = s;
        loop {
            if u == t {
                let bottleneck = path
                    .iter()
                    .map(|&e| self.residual[e as usize])
                    .fold(f64::INFINITY, f64::min);
                let mut first_saturated = path.len();
                for (k, &e) in path.iter().enumerate() {
                    self.residual[e as usize] -= bottleneck;
                    self.residual[e as usize ^ 1] += bottleneck;
                    if first_saturated == path.len() && self.residual[e as usize] <= self.eps {
                        first_saturated = k;
                    }
                }
                pushed += bottleneck;
                path.truncate(first_saturated);
                u = match path.last() {
                    Some(&e) => self.to[e as usize] as usize,
                    None => s,
                };
                continue;
            }
            let end = self.start[u + 1];
            let mut advanced = false;
            while self.cursor[u] < end {
                let e = self.adj[self.cursor[u] as usize] as usize;
                let v = self.to[e] as usize;
                if self.residual[e] > self.eps && self.level[v] == self.level[u] + 1 {
                    path.push(e as u32);
                    u = v;
                    advanced = true;
                    break;
                }
                self.cursor[u] += 1;
            }
            if advanced {
                continue;
            }
            // Dead end: nothing more reaches t through u in this phase.
            self.level[u] = -1;
            match path.pop() {
                None => return pushed,
                Some(e) => {
                    u = self.from[e as usize] as usize;
                    self.cursor[u] += 1;
                }
            }
        }
    }
}
