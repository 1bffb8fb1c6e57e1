//! Spatial search: a static k-d tree for exact nearest neighbours in K dimensions. Stage 1's
//! registration matches points in position (K = 3) and in position and colour (K = 6); the
//! label measure (`eval::labels`) matches surfels to mask pixels. Kept rather than swapped for
//! a crate (`kiddo`) because stage 1's poses depend on its exact answers where points tie (the
//! first of equally near points in the tree's order wins; `nearest_within` is strict), and a
//! change there would have to be re-measured on every scene.

/// Points per leaf: below ~16 a linear scan beats more tree levels.
const LEAF_SIZE: usize = 12;

#[derive(Clone, Debug)]
enum Node {
    Leaf {
        start: u32,
        end: u32,
    },
    Split {
        dim: u8,
        value: f32,
        left: u32,
        right: u32,
    },
}

/// A static k-d tree over points in K dimensions (median split on the widest axis) for exact
/// nearest-neighbour queries in squared Euclidean distance.
#[derive(Clone, Debug)]
pub struct KdTree<const K: usize> {
    points: Vec<[f32; K]>,
    index: Vec<u32>,
    nodes: Vec<Node>,
}

impl<const K: usize> KdTree<K> {
    pub fn new(points: &[[f32; K]]) -> Self {
        let mut tree = KdTree {
            points: points.to_vec(),
            index: (0..points.len() as u32).collect(),
            nodes: Vec::new(),
        };
        if !points.is_empty() {
            tree.build(0, points.len());
        }
        tree
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    fn build(&mut self, start: usize, end: usize) -> u32 {
        let id = self.nodes.len() as u32;
        if end - start <= LEAF_SIZE {
            self.nodes.push(Node::Leaf {
                start: start as u32,
                end: end as u32,
            });
            return id;
        }
        let mut lo = [f32::INFINITY; K];
        let mut hi = [f32::NEG_INFINITY; K];
        for p in &self.points[start..end] {
            for d in 0..K {
                lo[d] = lo[d].min(p[d]);
                hi[d] = hi[d].max(p[d]);
            }
        }
        let dim = (0..K)
            .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
            .unwrap_or(0);
        let mid = (start + end) / 2;
        // Sort points and their indices together by the split coordinate.
        let mut pairs: Vec<([f32; K], u32)> = self.points[start..end]
            .iter()
            .copied()
            .zip(self.index[start..end].iter().copied())
            .collect();
        pairs.select_nth_unstable_by(mid - start, |a, b| a.0[dim].total_cmp(&b.0[dim]));
        for (j, (p, i)) in pairs.into_iter().enumerate() {
            self.points[start + j] = p;
            self.index[start + j] = i;
        }
        let value = self.points[mid][dim];
        self.nodes.push(Node::Leaf { start: 0, end: 0 }); // placeholder, replaced below
        let left = self.build(start, mid);
        let right = self.build(mid, end);
        self.nodes[id as usize] = Node::Split {
            dim: dim as u8,
            value,
            left,
            right,
        };
        id
    }

    /// The nearest point to `q` (its index in the input, squared distance), or `None` for an
    /// empty tree.
    pub fn nearest(&self, q: &[f32; K]) -> Option<(usize, f32)> {
        self.nearest_within(q, f32::INFINITY)
    }

    /// The nearest point strictly closer than √`max_d2`, if any.
    pub fn nearest_within(&self, q: &[f32; K], max_d2: f32) -> Option<(usize, f32)> {
        if self.points.is_empty() {
            return None;
        }
        let mut best = (usize::MAX, max_d2);
        self.search(0, q, &mut best);
        (best.0 != usize::MAX).then(|| (self.index[best.0] as usize, best.1))
    }

    fn search(&self, node: u32, q: &[f32; K], best: &mut (usize, f32)) {
        match self.nodes[node as usize] {
            Node::Leaf { start, end } => {
                for j in start as usize..end as usize {
                    let d2 = dist2(&self.points[j], q);
                    if d2 < best.1 {
                        *best = (j, d2);
                    }
                }
            }
            Node::Split {
                dim,
                value,
                left,
                right,
            } => {
                let diff = q[dim as usize] - value;
                let (near, far) = if diff < 0.0 {
                    (left, right)
                } else {
                    (right, left)
                };
                self.search(near, q, best);
                if diff * diff < best.1 {
                    self.search(far, q, best);
                }
            }
        }
    }

    /// Every point strictly closer than √`max_d2` to `q`, appended to `out` as (index in the
    /// input, squared distance), in the tree's order.
    pub fn within(&self, q: &[f32; K], max_d2: f32, out: &mut Vec<(usize, f32)>) {
        if !self.points.is_empty() {
            self.collect(0, q, max_d2, out);
        }
    }

    fn collect(&self, node: u32, q: &[f32; K], max_d2: f32, out: &mut Vec<(usize, f32)>) {
        match self.nodes[node as usize] {
            Node::Leaf { start, end } => {
                for j in start as usize..end as usize {
                    let d2 = dist2(&self.points[j], q);
                    if d2 < max_d2 {
                        out.push((self.index[j] as usize, d2));
                    }
                }
            }
            Node::Split {
                dim,
                value,
                left,
                right,
            } => {
                let diff = q[dim as usize] - value;
                // Points equal to `value` may sit on either side of a median split: a side is
                // skipped only when the query is strictly farther than the radius from it.
                if diff < 0.0 || diff * diff < max_d2 {
                    self.collect(left, q, max_d2, out);
                }
                if diff >= 0.0 || diff * diff < max_d2 {
                    self.collect(right, q, max_d2, out);
                }
            }
        }
    }
}

/// Squared Euclidean distance, summed over the dimensions in order (the searches' one copy).
#[inline]
fn dist2<const K: usize>(p: &[f32; K], q: &[f32; K]) -> f32 {
    let mut d2 = 0.0;
    for d in 0..K {
        let e = p[d] - q[d];
        d2 += e * e;
    }
    d2
}
