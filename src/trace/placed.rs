//! The top level: components placed by rigid transforms, and the two ray queries.

use super::batch::{before, Hit, HitBatch};
use super::isa::Isa;
use super::node::{traverse_clipped, LeafGroups};
use super::record::{SurfaceRecord, WeightedHit};
use super::scene::TraceScene;
use super::surfel::hit4;
use super::T_MIN;
use crate::kernel::response;
use crate::scene::{Rigid, State};
use glam::{Mat3, Vec3};
use obvhs_glam::UVec2;

/// Placing is how a [`TraceScene`] becomes traceable: its constructor lives beside [`Placed`],
/// so that the scene (BVHs in component frames) does not name the view that borrows it.
impl TraceScene {
    /// Places the components with one rigid transform each (component frame → world): the
    /// top level only, no BVH is rebuilt.
    ///
    /// Panics unless there is exactly one transform per component (a validated [`State`] has).
    pub fn place(&self, transforms: &[Rigid]) -> Placed<'_> {
        assert_eq!(
            transforms.len(),
            self.blas.len(),
            "TraceScene::place: expected one transform per component"
        );
        Placed::new(self, transforms)
    }

    /// Places the components as a state does.
    pub fn place_state(&self, state: &State) -> Placed<'_> {
        self.place(&state.transforms)
    }
}

/// One component placed in the world.
#[derive(Clone, Copy, Debug)]
pub(super) struct Instance {
    /// World from component frame: x_w = R x + t.
    pub rotation: Mat3,
    pub translation: Vec3,
    /// World bounds of the component's supports; `None` for an empty component.
    bounds: Option<(Vec3, Vec3)>,
}

impl Instance {
    /// The ray in the component's frame: o' = Rᵀ(o − t), d' = Rᵀ d (same t along both).
    #[inline(always)]
    fn ray_to_local(&self, o: Vec3, d: Vec3) -> (Vec3, Vec3) {
        let rt = self.rotation.transpose();
        (rt * (o - self.translation), rt * d)
    }
}

/// Whether the ray meets the box for some t in [t_lo, t_hi]. A NaN slab (origin on a face,
/// direction parallel to it) is ignored by `min`/`max`, which only makes the test conservative.
#[inline(always)]
fn ray_box(o: Vec3, inv_d: Vec3, (lo, hi): (Vec3, Vec3), t_lo: f32, t_hi: f32) -> bool {
    let a = (lo - o) * inv_d;
    let b = (hi - o) * inv_d;
    let near = a.min(b).max_element().max(t_lo);
    let far = a.max(b).min_element().min(t_hi);
    near <= far
}

/// What rays cost, summed over the rays traced with [`Placed::composite_stats`] or
/// [`Placed::transmittance_stats`]: the figures a profile of the tracer starts from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RayStats {
    /// Rays traced.
    pub rays: u64,
    /// Surfels whose hit test ran (their leaf's bounds were entered).
    pub leaf_tests: u64,
    /// Hits that passed the test and were taken: into a composite's sorted batch (some later
    /// evicted or cut), or multiplied into a visibility ray's transmittance.
    pub hits: u64,
    /// Hits composited (a composite's `SurfaceRecord::hits`).
    pub composited: u64,
    /// BVH nodes whose children were tested against the ray.
    pub nodes: u64,
    /// BVH traversals: a composite traverses once per batch of [`super::BATCH`] hits, and each
    /// component whose world bounds the ray meets counts once.
    pub traversals: u64,
}

/// Where the traversals count their work: `()` counts nothing (and compiles to nothing), a
/// [`RayStats`] counts everything. One traversal serves both, so what is counted is exactly
/// what the fast path does.
pub(super) trait Tally {
    fn node(&mut self);
    fn leaf_test(&mut self);
    fn hit(&mut self);
    fn traversal(&mut self);
}

impl Tally for () {
    #[inline(always)]
    fn node(&mut self) {}
    #[inline(always)]
    fn leaf_test(&mut self) {}
    #[inline(always)]
    fn hit(&mut self) {}
    #[inline(always)]
    fn traversal(&mut self) {}
}

impl Tally for RayStats {
    #[inline(always)]
    fn node(&mut self) {
        self.nodes += 1;
    }
    #[inline(always)]
    fn leaf_test(&mut self) {
        self.leaf_tests += 1;
    }
    #[inline(always)]
    fn hit(&mut self) {
        self.hits += 1;
    }
    #[inline(always)]
    fn traversal(&mut self) {
        self.traversals += 1;
    }
}

/// A [`TraceScene`] in one placement (a state or a layout).
pub struct Placed<'a> {
    pub(super) scene: &'a TraceScene,
    pub(super) instances: Vec<Instance>,
    /// The non-empty components, smallest world bounds first: the order a composite traverses
    /// them in. Its result does not depend on the order (a batch holds the nearest hits
    /// whatever order they arrive in), but its cost does: a camera ray that meets an object in
    /// front of the background, traversing the object first, is cut at the object's surface
    /// before the background's traversal starts, which then prunes everything behind it; in
    /// component order it tested the wall's surfels first and then shifted each of the
    /// object's hits to the front of the sorted batch, settling the batch again each time. On
    /// the 200k room (`cargo bench --bench trace`): 54.4 leaf tests and 29.1 hits taken per
    /// camera ray rather than 60.5 and 33.1, 20 shifts per ray rather than 107.
    order: Vec<usize>,
    /// What the traversals run on: [`Isa::best`] unless chosen ([`Placed::with_isa`]).
    isa: Isa,
}

impl<'a> Placed<'a> {
    pub(crate) fn new(scene: &'a TraceScene, transforms: &[Rigid]) -> Self {
        let instances: Vec<Instance> = scene
            .blas
            .iter()
            .zip(transforms)
            .map(|(blas, tf)| {
                let rotation = Mat3::from_quat(tf.quat().normalize());
                let translation = Vec3::from_array(tf.translation);
                let bounds = blas.bvh.as_ref().map(|_| {
                    let (lo, hi) = (Vec3::from_array(blas.lo), Vec3::from_array(blas.hi));
                    let mut wlo = Vec3::INFINITY;
                    let mut whi = Vec3::NEG_INFINITY;
                    for c in 0..8 {
                        let corner = Vec3::select(
                            glam::BVec3::new(c & 1 != 0, c & 2 != 0, c & 4 != 0),
                            hi,
                            lo,
                        );
                        let w = rotation * corner + translation;
                        wlo = wlo.min(w);
                        whi = whi.max(w);
                    }
                    (wlo, whi)
                });
                Instance {
                    rotation,
                    translation,
                    bounds,
                }
            })
            .collect();
        let mut volumes: Vec<(f32, usize)> = instances
            .iter()
            .enumerate()
            .filter_map(|(c, inst)| {
                let (lo, hi) = inst.bounds?;
                Some(((hi - lo).max(Vec3::ZERO).element_product(), c))
            })
            .collect();
        // A stable sort, so equal volumes keep the component order (a NaN volume sorts last).
        volumes.sort_by(|a, b| a.0.total_cmp(&b.0));
        let order = volumes.into_iter().map(|(_, c)| c).collect();
        Placed {
            scene,
            instances,
            order,
            isa: Isa::best(),
        }
    }

    /// This placement with its traversals run on `isa` (by default the best the CPU has: the
    /// results are the same bit for bit, only their speed differs; see [`Isa`]).
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    /// The instruction set the traversals run on.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Composites the hits of the ray `origin + t dir`, `t_min < t < t_max`, front to back
    /// (eq. surface-record) until the transmittance falls below [`T_MIN`]. `dir` need not be
    /// unit length; `t` and thus `depth` are in its units.
    pub fn composite(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
    ) -> SurfaceRecord {
        self.composite_visit(origin, dir, t_min, t_max, &mut (), |_| {})
    }

    /// [`Placed::composite`], adding what the ray cost to `stats`.
    pub fn composite_stats(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        stats: &mut RayStats,
    ) -> SurfaceRecord {
        let record = self.composite_visit(origin, dir, t_min, t_max, stats, |_| {});
        stats.rays += 1;
        stats.composited += record.hits as u64;
        record
    }

    /// [`Placed::composite`], also appending every composited hit's surfel and weight to `hits`
    /// (front to back): what a record's material sums are made of, so they can be recomputed
    /// for other materials ([`SurfaceRecord::set_materials`]) and differentiated
    /// ([`super::scatter_material_grad`]) without tracing again.
    pub fn composite_hits(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        hits: &mut Vec<WeightedHit>,
    ) -> SurfaceRecord {
        self.composite_visit(origin, dir, t_min, t_max, &mut (), |h| hits.push(h))
    }

    /// [`Placed::composite_visit_on`] on the placement's instruction set ([`Isa`]).
    #[inline(always)]
    fn composite_visit(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        tally: &mut impl Tally,
        visit: impl FnMut(WeightedHit),
    ) -> SurfaceRecord {
        match self.isa {
            Isa::Baseline => self.composite_visit_on(origin, dir, t_min, t_max, tally, visit),
            #[cfg(target_arch = "x86_64")]
            // SAFETY: an `Isa::Avx2` exists only where the CPU has the features (`Isa::best`).
            Isa::Avx2(_) => unsafe {
                self.composite_visit_avx2(origin, dir, t_min, t_max, tally, visit)
            },
        }
    }

    /// [`Placed::composite_visit_on`] compiled for [`Isa::Avx2`].
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
    fn composite_visit_avx2(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        tally: &mut impl Tally,
        visit: impl FnMut(WeightedHit),
    ) -> SurfaceRecord {
        self.composite_visit_on(origin, dir, t_min, t_max, tally, visit)
    }

    #[inline(always)]
    fn composite_visit_on(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        tally: &mut impl Tally,
        visit: impl FnMut(WeightedHit),
    ) -> SurfaceRecord {
        let o = Vec3::from_array(origin);
        let d = Vec3::from_array(dir);
        let mut compositing = Compositing {
            placed: self,
            o,
            d,
            record: SurfaceRecord::default(),
            visit,
        };
        self.walk(o, d, t_min, t_max, tally, &mut compositing);
        compositing.record
    }

    /// Appends every hit [`Placed::composite`] composites along `o + t d` to `hits`, front to
    /// back, with its component: what the backward pass re-walks. On the placement's [`Isa`].
    pub(super) fn walk_hits(
        &self,
        o: Vec3,
        d: Vec3,
        t_min: f32,
        t_max: f32,
        hits: &mut Vec<(usize, Hit)>,
    ) {
        let mut push = |_, c, h: &Hit| hits.push((c, *h));
        match self.isa {
            Isa::Baseline => self.walk(o, d, t_min, t_max, &mut (), &mut push),
            #[cfg(target_arch = "x86_64")]
            // SAFETY: an `Isa::Avx2` exists only where the CPU has the features (`Isa::best`).
            Isa::Avx2(_) => unsafe { self.walk_avx2(o, d, t_min, t_max, &mut push) },
        }
    }

    /// [`Placed::walk`] compiled for [`Isa::Avx2`].
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
    fn walk_avx2(&self, o: Vec3, d: Vec3, t_min: f32, t_max: f32, visit: &mut impl Visit) {
        self.walk(o, d, t_min, t_max, &mut (), visit)
    }

    /// The traversal behind [`Placed::composite`] and its backward pass: calls
    /// `visit.hit(w, component, hit)` ([`Visit`]) for every hit that is composited, front to
    /// back, with its weight `w = T α` (eq. surface-record). One copy, so the backward pass
    /// sees exactly the forward's hits in the forward's order.
    #[inline(always)]
    pub(super) fn walk(
        &self,
        o: Vec3,
        d: Vec3,
        t_min: f32,
        t_max: f32,
        tally: &mut impl Tally,
        visit: &mut impl Visit,
    ) {
        let inv_d = d.recip();
        // Hits must come strictly after `after`; u64::MAX excludes every key at t_min itself.
        let mut after = (t_min, u64::MAX);
        let mut carry = 1.0f32;
        loop {
            let mut batch = HitBatch::new(carry, t_max);
            for &c in &self.order {
                let (inst, blas) = (&self.instances[c], &self.scene.blas[c]);
                let (Some(bounds), Some(bvh)) = (inst.bounds, blas.bvh.as_ref()) else {
                    continue;
                };
                if !ray_box(o, inv_d, bounds, after.0, batch.bound()) {
                    continue;
                }
                tally.traversal();
                let (lo, ld) = inst.ray_to_local(o, d);
                let key_base = (c as u64) << 32;
                // Nodes wholly before the last composited hit hold nothing this batch can take;
                // the batch's bound is the far clip, which shrinks as the batch fills.
                traverse_clipped!(bvh, lo, ld, after.0, batch.bound(), tally, |base, bits| {
                    for (slots, live) in LeafGroups::new(base, bits) {
                        let group = slots.map(|k| &blas.hit[k]);
                        let (kept, t, r2) = hit4(group, live, lo, ld, after.0, batch.bound());
                        for lane in 0..4 {
                            if live & (1 << lane) != 0 {
                                tally.leaf_test();
                            }
                            if kept & (1 << lane) == 0 {
                                continue;
                            }
                            let key = key_base | group[lane].index as u64;
                            let t = t[lane];
                            if !(before(after, (t, key)) && batch.accepts(t, key)) {
                                continue;
                            }
                            if let Some(r) = response(group[lane].alpha, r2[lane]) {
                                tally.hit();
                                batch.insert(Hit::new(t, r.alpha, key, slots[lane] as u32));
                            }
                        }
                    }
                });
            }
            batch.finish();
            for (w, h) in batch.weighted() {
                visit.hit(w, (h.key >> 32) as usize, h);
            }
            if batch.finishes() {
                return;
            }
            (after, carry) = batch.resume();
        }
    }

    /// Transmittance Π (1 − α_eff) along `origin + t dir`, `t_min < t < t_max`, multiplied in
    /// whatever order the BVH yields hits. Returns 0 as soon as it falls below [`T_MIN`].
    pub fn transmittance(&self, origin: [f32; 3], dir: [f32; 3], t_min: f32, t_max: f32) -> f32 {
        self.transmittance_tally(origin, dir, t_min, t_max, &mut ())
    }

    /// [`Placed::transmittance`], adding what the ray cost to `stats`.
    pub fn transmittance_stats(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        stats: &mut RayStats,
    ) -> f32 {
        stats.rays += 1;
        self.transmittance_tally(origin, dir, t_min, t_max, stats)
    }

    /// [`Placed::transmittance_on`] on the placement's instruction set ([`Isa`]).
    #[inline(always)]
    fn transmittance_tally(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        tally: &mut impl Tally,
    ) -> f32 {
        match self.isa {
            Isa::Baseline => self.transmittance_on(origin, dir, t_min, t_max, tally),
            #[cfg(target_arch = "x86_64")]
            // SAFETY: an `Isa::Avx2` exists only where the CPU has the features (`Isa::best`).
            Isa::Avx2(_) => unsafe { self.transmittance_avx2(origin, dir, t_min, t_max, tally) },
        }
    }

    /// [`Placed::transmittance_on`] compiled for [`Isa::Avx2`].
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
    fn transmittance_avx2(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        tally: &mut impl Tally,
    ) -> f32 {
        self.transmittance_on(origin, dir, t_min, t_max, tally)
    }

    #[inline(always)]
    fn transmittance_on(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
        tally: &mut impl Tally,
    ) -> f32 {
        let o = Vec3::from_array(origin);
        let d = Vec3::from_array(dir);
        let inv_d = d.recip();
        let mut tr = 1.0f32;
        // In component order, not `order`: on the 200k room the smallest-first order made a
        // visibility ray test 50.2 surfels rather than 43.4 (rays leave surfaces, and the
        // background they mostly leave from blocks them sooner than an object does).
        for (inst, blas) in self.instances.iter().zip(&self.scene.blas) {
            let (Some(bounds), Some(bvh)) = (inst.bounds, blas.bvh.as_ref()) else {
                continue;
            };
            if !ray_box(o, inv_d, bounds, t_min, t_max) {
                continue;
            }
            tally.traversal();
            let (lo, ld) = inst.ray_to_local(o, d);
            // Returns from inside the traversal the moment the ray is blocked. (A `break` there,
            // which obvhs's `traverse!` doc suggests, only leaves its per-leaf loop: the
            // traversal goes on.) The far clip never shrinks: a visibility ray needs every hit,
            // not the closest.
            traverse_clipped!(bvh, lo, ld, t_min, t_max, tally, |base, bits| {
                for (slots, live) in LeafGroups::new(base, bits) {
                    let group = slots.map(|k| &blas.hit[k]);
                    let (kept, t, r2) = hit4(group, live, lo, ld, t_min, t_max);
                    for lane in 0..4 {
                        if live & (1 << lane) != 0 {
                            tally.leaf_test();
                        }
                        if kept & (1 << lane) == 0 || !(t[lane] > t_min && t[lane] < t_max) {
                            continue;
                        }
                        if let Some(r) = response(group[lane].alpha, r2[lane]) {
                            tally.hit();
                            tr *= 1.0 - r.alpha;
                            if tr < T_MIN {
                                return 0.0;
                            }
                        }
                    }
                }
            });
        }
        tr
    }
}

/// What a walk does with each composited hit: `hit(w, component, hit)`, front to back. A trait
/// rather than a closure so that the composite's per-hit work ([`Compositing`]) can be marked
/// `#[inline(always)]`: as a closure it was called out of line from the traversal's AVX2 twin
/// ([`Isa`]).
pub(super) trait Visit {
    fn hit(&mut self, w: f32, component: usize, hit: &Hit);
}

impl<F: FnMut(f32, usize, &Hit)> Visit for F {
    #[inline(always)]
    fn hit(&mut self, w: f32, component: usize, hit: &Hit) {
        self(w, component, hit)
    }
}

/// A composite's per-hit work: the hit added to the record (eq. surface-record), then handed to
/// `visit`.
struct Compositing<'p, 's, V> {
    placed: &'p Placed<'s>,
    o: Vec3,
    d: Vec3,
    record: SurfaceRecord,
    visit: V,
}

impl<V: FnMut(WeightedHit)> Visit for Compositing<'_, '_, V> {
    #[inline(always)]
    fn hit(&mut self, w: f32, c: usize, h: &Hit) {
        let blas = &self.placed.scene.blas[c];
        let slot = h.slot as usize;
        let surfel = &blas.hit[slot];
        let mut n = self.placed.instances[c].rotation * Vec3::from_array(surfel.n);
        if n.dot(self.d) > 0.0 {
            n = -n;
        }
        let x = self.o + h.t * self.d;
        self.record
            .add(w, h.t, x.to_array(), n.to_array(), &blas.material[slot]);
        (self.visit)(WeightedHit {
            component: c as u32,
            index: surfel.index,
            w,
        });
    }
}
