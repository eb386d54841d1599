//! Photon tracing and the photon map (Jensen, "Realistic Image Synthesis Using Photon
//! Mapping", 2001; the paper's §1, §3 and §4.2).
//!
//! Photons leave the lights in proportion to their power and are traced with a quasi-Monte
//! Carlo sequence indexed by photon number, seeded by the job's seed but *not* by the frame:
//! photon `i` follows the same path in every frame where the geometry it meets did not
//! change, which the anchors rely on (§4.2, \[Chr02\]). Every diffuse hit stores the photon
//! (the first hit included: final-gather hits need the direct illumination there too),
//! weighted by how the hit's shading normal sees it (Veach 1997, §5.3), as the path tracer
//! and the direct light do; Russian roulette by albedo decides whether it bounces on.
//!
//! The kd-tree is our own ([`knn`]): a bounded k-nearest query that does not allocate.
//!
//! Every look-up is bounded: no photon farther than [`PhotonMap::max_radius`] from the
//! query point counts (DESIGN.md, Numerics), so light sealed behind closed geometry cannot
//! leak through it into an estimate, and a query far from every photon costs little. Where
//! fewer than k photons lie within the bound, the estimate is the density over the
//! maximum disc. Estimates gather over a disc, not a sphere (Jensen 2001, §7.2): a photon
//! off the query's tangent plane by more than [`DISC_THICKNESS`] of the radius lies on
//! another surface — a lamp 0.9 units under a ceiling must not count the dense photons
//! its back side leaves on the ceiling as light arriving at its front. Near a crease the
//! disc reaches past the end of its surface; the estimate divides by the part of the disc
//! that lies on it, which the photons on the other surface delimit (`SurfaceClip`).

pub mod knn;
pub mod precomputed;

use std::f32::consts::PI;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use glam::{Vec2, Vec3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::accel::{interpolate, offset_ray_origin};
use crate::color::luminance;
use crate::geom::{basis, cosine_direction, face_normal_area, uniform_sphere};
use crate::interaction::{Materials, ShadowRays, SurfacePoint, punctual_incident_from};
use crate::sampling::Sampler;
use crate::scene::{FrameScene, LightKind};

/// Where a gather hit's direct light from punctual lights comes from (`method.gather_direct`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum GatherDirect {
    /// The paper's (§1, §3.3.2): the photon map's estimate, first hits included. Its disc
    /// estimates read low where light changes over the disc — at the edges of surfaces, in
    /// corners, across shadow edges — and a gather reads that bias at every hit.
    Photons,
    /// A shadow ray to each punctual light from each gather hit and each anchor, as at a
    /// camera hit ([`PhotonMap::direct_at_hit`], [`PhotonMap::direct_from`]); the photon
    /// estimates count only light that has bounced at least once (and the first hits of
    /// emissive triangles' photons, which no shadow ray stands in for). The photons' first
    /// hits stay in the map with no power: the k-nearest radius, the anchors' nearest
    /// photons and the frame-to-frame comparison of paths (§4.2) see every photon as before.
    /// The default: the first bounce is most of a sunlit interior's indirect light, and the
    /// photons' estimate of it reads 25–30 % low on Sponza (README, "Against Cycles and our
    /// own path tracer").
    #[default]
    ShadowRays,
}

/// One stored photon.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Photon {
    pub position: Vec3,
    /// Normal of the surface it landed on, on the side it arrived from.
    pub normal: Vec3,
    /// Flux carried (scene light units × area), as the surface's shading normal sees it:
    /// the flux that crossed the surface × cos θ_s / cos θ_g (see `trace_path`).
    pub power: Vec3,
}

/// The photons of a map, path by path, kept to tell the next frame's changes.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PhotonPaths {
    pub photons: Vec<Photon>,
    pub path_start: Vec<u32>,
    /// The kd-tree the map built over these photons' positions: the next map whose
    /// photons lie where these did (a light's intensity or colour edited, nothing moved)
    /// uses it instead of building its own. Not saved (a resumed render builds it).
    #[serde(skip)]
    pub tree: KeptTree,
}

/// How much farther a k-nearest search looks again, in squared radius, where fewer than k
/// photons lie within the reach it was first given
/// ([`PhotonMap::irradiance_and_radius_near`]): an anchor whose reach lost a photon
/// or two finds its k-th just beyond it, and a search bounded there visits less of the tree
/// than an unbounded one.
pub const RETRY_REACH2: f32 = 1.5;

/// A kd-tree kept beside the photons it was built over ([`PhotonPaths::tree`]): derived
/// data, so two are always equal (the photons they index decide).
#[derive(Debug, Clone, Default)]
pub struct KeptTree(pub Option<Arc<knn::PointTree>>);

impl PartialEq for KeptTree {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl KeptTree {
    /// Bytes the tree holds on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.0.as_ref().map_or(0, |t| t.heap_bytes())
    }
}

impl PhotonPaths {
    /// Checks paths read from disk: the path starts rise and stay within the photons.
    pub fn check(&self) -> Result<(), String> {
        let ok = self.path_start.windows(2).all(|w| w[0] <= w[1])
            && self
                .path_start
                .last()
                .is_none_or(|&e| e as usize <= self.photons.len());
        if ok {
            Ok(())
        } else {
            Err("the previous frame's photon paths are malformed".into())
        }
    }
}

/// Photon map with its kd-tree.
pub struct PhotonMap {
    pub photons: Vec<Photon>,
    /// Where each emitted photon's path starts in `photons` (one more entry than paths):
    /// path `i` stored `photons[path_start[i]..path_start[i + 1]]`.
    pub path_start: Vec<u32>,
    tree: Arc<knn::PointTree>,
    /// `photons` in the tree's order, which look-ups read (the knn module doc).
    ordered: Vec<Photon>,
    /// Photons emitted (the divisor of every photon's power).
    pub emitted: u32,
    /// Total flux emitted by all lights (luminance-weighted sum is what selection uses).
    pub emitted_power: Vec3,
    /// No look-up reaches farther than this (scene units; see the module doc).
    pub max_radius: f32,
    /// Whether the estimates hold the first hits of punctual lights' photons:
    /// [`GatherDirect::ShadowRays`] only where it was asked for and the frame has a punctual
    /// light; without one there is nothing for shadow rays to stand in for, and the map is
    /// the one [`GatherDirect::Photons`] gives.
    pub direct: GatherDirect,
    /// The shadow rays cast for [`PhotonMap::direct_at_hit`] and [`PhotonMap::direct_from`].
    shadow_rays: Tally,
}

/// A count that the threads of a parallel loop add to, each in a cache line of its own, so
/// that counting every gather hit's shadow rays costs no contention. The sum does not depend
/// on which thread added what.
struct Tally(Box<[PaddedCount]>);

#[repr(align(128))]
#[derive(Default)]
struct PaddedCount(AtomicU64);

impl Tally {
    fn new() -> Tally {
        Tally(
            (0..=rayon::current_num_threads())
                .map(|_| PaddedCount::default())
                .collect(),
        )
    }

    fn add(&self, n: u64) {
        // A thread outside the pool (or of a larger pool) shares the last slot.
        let last = self.0.len() - 1;
        let i = rayon::current_thread_index().map_or(last, |i| i.min(last));
        self.0[i].0.fetch_add(n, Ordering::Relaxed);
    }

    fn sum(&self) -> u64 {
        self.0.iter().map(|c| c.0.load(Ordering::Relaxed)).sum()
    }
}

/// Half the thickness of the disc an estimate gathers over, as a fraction of its radius: a
/// photon farther than this from the query's tangent plane lies on another surface (on a
/// curved one, only beyond ~30° of arc). Jensen 2001, §7.2 compresses the sphere likewise.
pub const DISC_THICKNESS: f32 = 0.25;

/// The part of an estimate's disc that lies on the query's surface (boundary bias,
/// Jensen 2001, §7.2). A disc centred near a crease — a ceiling meeting a wall — reaches
/// past the end of its surface: dividing the photons on it by the whole disc's area πr²
/// halves the estimate at the crease (measured at the example room's back-wall/ceiling
/// seam: 0.32 against a path-traced 0.74), and a final-gather ray that lands close to the
/// crease reads that. The other surface tells where the disc's surface ends: a photon that
/// does not count (its normal disagrees) but whose surface faces the query point lies on
/// a surface that bounds this one, and the plane it lies on cuts the disc along a line. The
/// estimate divides by the area of the disc on the query's side of every such line, and
/// counts only photons there: where a line cuts away surface that is really there (the
/// floor beside a box's corner continues past the plane of its side), both sides of the
/// quotient lose the same region, so the estimate stays unbiased and only its variance
/// grows. A surface that ends with no photons beyond it (a convex edge, an unlit wall)
/// cuts nothing.
struct SurfaceClip {
    /// Each cutting line in the disc's plane: unit direction `a` (in the tangent basis)
    /// pointing into the kept side, and its distance `h ≥ 0` from the centre; the disc keeps
    /// the points `q` with `a·q ≥ −h`.
    lines: Vec<(Vec2, f32)>,
    x: Vec3,
    t: Vec3,
    b: Vec3,
    r: f32,
}

/// Buffers [`PhotonMap::estimate`] reuses from query to query on a thread: the clip's
/// lines and the photons on the disc (position, power), which the clip then tests.
#[derive(Default)]
struct EstimateScratch {
    lines: Vec<(Vec2, f32)>,
    on_disc: Vec<(Vec3, Vec3)>,
}

thread_local! {
    static ESTIMATE_SCRATCH: std::cell::RefCell<EstimateScratch> =
        std::cell::RefCell::new(EstimateScratch::default());
}

/// The least share of its disc an estimate divides by: a corner of three walls leaves a
/// quarter of it; only a wedge sharper than 45° reaches this floor, which keeps a photon or
/// two in a sliver of disc from dividing by almost nothing.
const CLIP_MIN_SHARE: f32 = 0.125;

impl SurfaceClip {
    /// A disc that nothing cuts yet, its lines kept in `lines` (emptied; a buffer reused
    /// from estimate to estimate); [`SurfaceClip::cut_by`] adds the photons off it.
    fn new(x: Vec3, n: Vec3, r: f32, mut lines: Vec<(Vec2, f32)>) -> Self {
        let (t, b) = basis(n);
        lines.clear();
        SurfaceClip { lines, x, t, b, r }
    }

    /// Adds the line that photon `p`, which lies off the disc at height `above_by` over its
    /// plane (`(p − x)·n`), cuts it along, if any. The tests run cheapest first: most
    /// photons off a disc lie below it or face away.
    fn cut_by(&mut self, p: &Photon, above_by: f32) {
        let (x, r) = (self.x, self.r);
        // A photon above the disc whose surface faces the query point: that surface
        // bounds the disc's (a concave crease; the query point may lie on it, at the
        // crease itself). One below the disc or facing away — a convex edge's side,
        // the back of a thin wall — does not.
        if !(above_by > 0.0) {
            return;
        }
        let c = (x - p.position).dot(p.normal);
        if !(c >= 0.0) {
            return;
        }
        let a = Vec2::new(self.t.dot(p.normal), self.b.dot(p.normal));
        let len = a.length();
        if len < 1e-3 || c >= r * len {
            return; // parallel to the disc, or cutting beyond its rim
        }
        let (a, h) = (a / len, c / len);
        // Photons on one plane all give this line: keep one of them. They come in the
        // search's order, plane by plane, so the latest line is the likeliest match.
        if !self
            .lines
            .iter()
            .rev()
            .any(|&(a2, h2)| a2.dot(a) > 0.9999 && (h2 - h).abs() <= 1e-3 * r)
        {
            self.lines.push((a, h));
        }
    }

    /// The power of the photons `on_disc` (position, power) that lie on the kept side of
    /// every line, summed in their order, and the area there (`SurfaceClip::area`).
    fn kept(&self, on_disc: &[(Vec3, Vec3)]) -> (Vec3, f32) {
        self.with_lanes(|lanes| {
            let sum = on_disc
                .iter()
                .filter(|(y, _)| self.contains_in(lanes, *y))
                .map(|(_, power)| *power)
                .sum();
            (sum, self.area_in(lanes))
        })
    }

    /// `f` of the lines laid out four to a [`ClipLanes`]: on the stack up to 32 lines, on the
    /// heap beyond.
    fn with_lanes<R>(&self, f: impl FnOnce(&[ClipLanes]) -> R) -> R {
        const ON_STACK: usize = 8;
        let lanes = self.lines.len().div_ceil(4);
        let fill = |soa: &mut [ClipLanes]| {
            for (k, &(a, h)) in self.lines.iter().enumerate() {
                let lane = &mut soa[k / 4];
                lane.ux[k % 4] = -a.x;
                lane.uy[k % 4] = -a.y;
                lane.h[k % 4] = h;
            }
        };
        if lanes <= ON_STACK {
            let mut soa = [ClipLanes::EMPTY; ON_STACK];
            fill(&mut soa[..lanes]);
            f(&soa[..lanes])
        } else {
            let mut soa = vec![ClipLanes::EMPTY; lanes];
            fill(&mut soa);
            f(&soa)
        }
    }

    /// Whether `y` (a photon on the disc) lies on the kept side of every line, tested four
    /// lines at a time in `lanes` ([`SurfaceClip::with_lanes`]): `a·q ≥ −h` as `u·q ≤ h`
    /// with `u = −a`, the same comparison to the bit (negation is exact).
    fn contains_in(&self, lanes: &[ClipLanes], y: Vec3) -> bool {
        let d = y - self.x;
        let q = Vec2::new(d.dot(self.t), d.dot(self.b));
        let (qx, qy) = (glam::Vec4::splat(q.x), glam::Vec4::splat(q.y));
        lanes
            .iter()
            .all(|o| (o.ux * qx + o.uy * qy).cmple(o.h).all())
    }

    /// Whether `y` lies on the kept side of every line.
    #[cfg(test)]
    fn contains(&self, y: Vec3) -> bool {
        self.with_lanes(|lanes| self.contains_in(lanes, y))
    }

    /// Area of the disc on the kept side of every line (πr² where nothing cuts it), never
    /// below [`CLIP_MIN_SHARE`] of the disc.
    #[cfg(test)]
    fn area(&self) -> f32 {
        self.with_lanes(|lanes| self.area_in(lanes))
    }

    /// `SurfaceClip::area`, the lines laid out in `lanes` ([`SurfaceClip::with_lanes`]).
    fn area_in(&self, lanes: &[ClipLanes]) -> f32 {
        let full = PI * self.r * self.r;
        let area = match self.lines[..] {
            [] => return full,
            // The circular segment past the line, r² acos(h/r) − h √(r² − h²), cut off.
            [(_, h)] => {
                let h = h.min(self.r);
                full - (self.r * self.r * (h / self.r).acos()
                    - h * (self.r * self.r - h * h).max(0.0).sqrt())
            }
            _ => self.cut_area(lanes),
        };
        area.max(CLIP_MIN_SHARE * full)
    }

    /// `SurfaceClip::area` where two or more lines cut the disc, exactly (up to rounding).
    ///
    /// The kept region is convex and holds the centre, so its boundary, seen from the
    /// centre, is a sequence of pieces of the lines and arcs of the rim that together turn
    /// once around it. A line at distance h whose piece runs from `lo` to `hi` along it adds
    /// the triangle that piece makes with the centre, ½·h·(hi − lo), and turns by the angle
    /// it subtends; the arcs make up the rest of the turn, each a sector ½r² per radian. A
    /// line's piece is its chord of the disc, shortened by every other line.
    ///
    /// This needs the centre strictly inside, so a line through it (a query point on
    /// another surface's plane) is moved off it by a millionth of the radius, which changes
    /// the area by about as much; and each point of the boundary must lie on one piece
    /// only, which holds because [`SurfaceClip::cut_by`] keeps no two lines that (nearly)
    /// coincide, and of two exactly parallel ones facing the same way only the nearer
    /// counts. Each line is tested against the others four at a time (`lanes`), branch-free:
    /// estimates near creases of curved or finely tessellated surfaces meet ten lines on
    /// average. (Integrating ½ρ(θ)² over 256 directions, as this did before, took three
    /// times as long and was off by up to 0.5 % of the disc.)
    fn cut_area(&self, lanes: &[ClipLanes]) -> f32 {
        use glam::Vec4;
        let r = self.r;
        let floor = 1e-6 * r;
        let floor4 = Vec4::splat(floor);
        let mut triangles = 0.0f32;
        let mut turned = 0.0f32;
        for (i, &(a, h)) in self.lines.iter().enumerate() {
            let (u, h) = (-a, h.max(floor));
            // The line's points are u·h + s·v, v along it with the kept side on its left.
            let v = u.perp();
            let w = (r * r - h * h).max(0.0).sqrt();
            let (mut lo, mut hi) = (Vec4::splat(-w), Vec4::splat(w));
            let mut behind = glam::BVec4A::FALSE;
            let (vx, vy) = (Vec4::splat(v.x), Vec4::splat(v.y));
            let (ux, uy, h4) = (Vec4::splat(u.x), Vec4::splat(u.y), Vec4::splat(h));
            let i4 = Vec4::splat(i as f32);
            for (l, o) in lanes.iter().enumerate() {
                // Line j keeps uj·(u·h + s·v) ≤ hj: s·(uj·v) ≤ hj − h·(uj·u).
                let hj = o.h.max(floor4);
                let along = o.ux * vx + o.uy * vy;
                let toward = o.ux * ux + o.uy * uy;
                let s = (hj - h4 * toward) / along;
                hi = hi.min(Vec4::select(along.cmpgt(Vec4::ZERO), s, Vec4::INFINITY));
                lo = lo.max(Vec4::select(along.cmplt(Vec4::ZERO), s, Vec4::NEG_INFINITY));
                // Parallel, facing the same way and nearer (ties: the earlier line).
                let j = Vec4::new(0.0, 1.0, 2.0, 3.0) + Vec4::splat(4.0 * l as f32);
                let nearer = hj.cmplt(h4) | (hj.cmpeq(h4) & j.cmplt(i4));
                behind |= along.cmpeq(Vec4::ZERO) & toward.cmpgt(Vec4::ZERO) & nearer;
            }
            let (lo, hi) = (lo.max_element(), hi.min_element());
            if !behind.any() && hi > lo {
                triangles += h * (hi - lo);
                turned += (h * (hi - lo)).atan2(h * h + lo * hi);
            }
        }
        0.5 * triangles + 0.5 * r * r * (2.0 * PI - turned).max(0.0)
    }
}

/// Four of a [`SurfaceClip`]'s lines, lane by lane: each as u·p ≤ h (u = −a, the unit
/// normal pointing away from the kept side). An unused lane is parallel to every line and
/// infinitely far: it bounds none and keeps every point.
#[derive(Clone, Copy)]
struct ClipLanes {
    ux: glam::Vec4,
    uy: glam::Vec4,
    h: glam::Vec4,
}

impl ClipLanes {
    const EMPTY: ClipLanes = ClipLanes {
        ux: glam::Vec4::ZERO,
        uy: glam::Vec4::ZERO,
        h: glam::Vec4::INFINITY,
    };
}

/// An emitting light as photon tracing sees it.
enum Source {
    Punctual(usize),
    Emitter(usize),
}

/// Photon `index`'s samples: dimension `d` of the photons' sequence ([`Sampler::photons`]).
/// Dimensions: [`DIM_LIGHT`] picks the light, four from [`DIM_EMIT`] place the photon on it,
/// and each bounce takes four from [`DIM_BOUNCES`] (roulette, then the BRDF sample).
struct PhotonSamples {
    sampler: Sampler,
    index: u32,
}

const DIM_LIGHT: u32 = 0;
const DIM_EMIT: u32 = 1;
const DIM_BOUNCES: u32 = 5;

impl PhotonSamples {
    fn get(&self, d: u32) -> f32 {
        self.sampler.get(self.index, d)
    }
}

/// The disc directional lights emit photons over: the cross-section of the sphere around the
/// static set ([`FrameScene::static_box`]), the same in every frame, so a prop driving off the
/// set neither thins the photons landing on it nor changes their power. Dynamic geometry
/// outside that sphere gets direct sunlight (shadow rays) but no sun photons. A scene with no
/// static geometry uses the bounds of all of it.
pub fn sun_sphere(frame: &FrameScene) -> (Vec3, f32) {
    let (mut lo, mut hi) = frame.static_box();
    if frame.static_geometry.is_empty() {
        (lo, hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for t in &frame.dynamic_geometry.triangles {
            for v in [t.v0, t.v1, t.v2] {
                lo = lo.min(v.into());
                hi = hi.max(v.into());
            }
        }
    }
    if lo.x > hi.x {
        return (Vec3::ZERO, 1.0);
    }
    let c = 0.5 * (lo + hi);
    (c, (0.5 * (hi - lo).length()).max(f32::MIN_POSITIVE))
}

/// What a photon map is traced with ([`PhotonMap::trace`]).
#[derive(Debug, Clone, Copy)]
pub struct Emission {
    /// Photons emitted from all lights together.
    pub count: u32,
    /// Selects the photons' sequence; it must not depend on the frame, for temporal
    /// coherence.
    pub seed: u32,
    /// Bounces a photon path takes at most.
    pub max_bounces: u32,
    /// Look-ups reach this fraction of the static geometry's bounding radius at most
    /// ([`FrameScene::static_radius`]: the same in every frame).
    pub max_radius: f32,
    /// With [`GatherDirect::ShadowRays`] the first hit of each punctual light's photon counts
    /// for nothing in the estimates.
    pub direct: GatherDirect,
}

impl PhotonMap {
    /// Traces `e.count` photons from every light of `frame` (see [`Emission`]). `previous`
    /// are the last map's photons, if any: where every photon lies where its predecessor
    /// did, the map uses their kd-tree ([`PhotonPaths::tree`]) instead of building one.
    pub fn trace(
        frame: &FrameScene,
        m: Materials,
        e: &Emission,
        previous: Option<&PhotonPaths>,
    ) -> PhotonMap {
        let Emission {
            count,
            seed,
            max_bounces,
            max_radius,
            direct,
        } = *e;
        let (centre, radius) = sun_sphere(frame);
        // Emitted flux per light.
        let mut sources = Vec::new();
        let mut power = Vec::new();
        for (i, l) in frame.lights.iter().enumerate() {
            let phi = match l.kind {
                LightKind::Point => 4.0 * PI * l.intensity,
                LightKind::Spot { outer, .. } => 2.0 * PI * (1.0 - outer.cos()) * l.intensity,
                LightKind::Directional => PI * radius * radius * l.intensity,
            };
            sources.push(Source::Punctual(i));
            power.push(phi);
        }
        for (i, e) in frame.emitters.list.iter().enumerate() {
            let sides = if e.double_sided { 2.0 } else { 1.0 };
            sources.push(Source::Emitter(i));
            power.push(PI * e.radiance * e.area * sides);
        }
        let weights: Vec<f64> = power
            .iter()
            .map(|p| luminance(*p).max(0.0) as f64)
            .collect();
        let total: f64 = weights.iter().sum();
        let emitted_power = power.iter().copied().sum();
        let mut map = PhotonMap {
            photons: Vec::new(),
            path_start: Vec::new(),
            tree: Arc::default(),
            ordered: Vec::new(),
            emitted: count,
            emitted_power,
            max_radius: max_radius * frame.static_radius(),
            direct: if frame.lights.is_empty() {
                GatherDirect::Photons
            } else {
                direct
            },
            shadow_rays: Tally::new(),
        };
        if total <= 0.0 || count == 0 {
            return map;
        }
        let mut cdf = Vec::with_capacity(weights.len());
        let mut acc = 0.0;
        for w in &weights {
            acc += w;
            cdf.push((acc / total) as f32);
        }
        let sampler = Sampler::photons(seed);
        use rayon::prelude::*;
        let chunks: Vec<(Vec<Photon>, Vec<u32>, Vec<u32>)> = (0..count.div_ceil(4096))
            .into_par_iter()
            .map(|c| {
                let mut out = Vec::new();
                let mut ends = Vec::new();
                // The first hits of punctual lights' photons, which shadow rays stand in for.
                let mut firsts = Vec::new();
                for i in c * 4096..((c + 1) * 4096).min(count) {
                    if i > c * 4096 {
                        ends.push(out.len() as u32);
                    }
                    let s = PhotonSamples { sampler, index: i };
                    let k = cdf
                        .partition_point(|&x| x <= s.get(DIM_LIGHT))
                        .min(sources.len() - 1);
                    let p_pick = (weights[k] / total) as f32;
                    let Some((o, dir, flux, reach)) = emit(frame, &sources[k], &s, centre, radius)
                    else {
                        continue;
                    };
                    let flux = flux / (p_pick * count as f32);
                    let first = out.len();
                    let ray = (o, dir, reach);
                    trace_path(frame, m, ray, flux, &s, max_bounces, &mut out);
                    if direct == GatherDirect::ShadowRays
                        && matches!(sources[k], Source::Punctual(_))
                        && out.len() > first
                    {
                        firsts.push(first as u32);
                    }
                }
                ends.push(out.len() as u32);
                (out, ends, firsts)
            })
            .collect();
        map.path_start.push(0);
        let mut firsts = Vec::new();
        for (photons, ends, first) in chunks {
            let base = map.photons.len() as u32;
            map.path_start.extend(ends.iter().map(|e| base + e));
            firsts.extend(first.iter().map(|f| base + f));
            map.photons.extend(photons);
        }
        let same_places = |p: &PhotonPaths| {
            p.photons.len() == map.photons.len()
                && p.photons.iter().zip(&map.photons).all(|(a, b)| {
                    a.position.to_array().map(f32::to_bits)
                        == b.position.to_array().map(f32::to_bits)
                })
        };
        map.tree = match previous.and_then(|p| p.tree.0.as_ref().filter(|_| same_places(p))) {
            Some(tree) => tree.clone(),
            None => {
                let pts: Vec<Vec3> = map.photons.iter().map(|p| p.position).collect();
                Arc::new(knn::PointTree::new(&pts))
            }
        };
        map.ordered = map.tree.in_tree_order(&map.photons);
        if !firsts.is_empty() {
            // The estimates read the ordered copy: the first hits lose their power there.
            let mut first = vec![false; map.photons.len()];
            for &i in &firsts {
                first[i as usize] = true;
            }
            let tree = &map.tree;
            map.ordered
                .par_iter_mut()
                .enumerate()
                .filter(|(pos, _)| first[tree.item(*pos as u32) as usize])
                .for_each(|(_, p)| p.power = Vec3::ZERO);
        }
        map
    }

    /// The irradiance the punctual lights give gather hit `sp` by shadow rays, where the
    /// estimates leave their first hits out ([`GatherDirect::ShadowRays`]); zero where the
    /// estimates hold them.
    pub fn direct_at_hit(&self, frame: &FrameScene, sp: &SurfacePoint) -> Vec3 {
        // Called at every gather hit: with the photons' estimate, not even the ray's origin.
        if self.direct == GatherDirect::Photons {
            return Vec3::ZERO;
        }
        self.direct_toward(frame, sp.spawn(), sp.ns, sp.ng)
    }

    /// [`Self::direct_at_hit`] at a point known only by its normal `n` and the origin `o` of
    /// its shadow rays, already off its surface (an anchor's decoded position lifted along
    /// its normal, `crate::integrator::anchors`).
    pub fn direct_from(&self, frame: &FrameScene, o: Vec3, n: Vec3) -> Vec3 {
        if self.direct == GatherDirect::Photons {
            return Vec3::ZERO;
        }
        self.direct_toward(frame, o, n, n)
    }

    /// The punctual lights' irradiance by shadow rays from `o`, at a point with shading
    /// normal `ns` and geometric normal `ng`, counted by the shading normal as a photon
    /// arriving from each light would be (cos θ_s / cos θ_g, as the photons are stored).
    /// The rays count in [`PhotonMap::shadow_rays_cast`].
    fn direct_toward(&self, frame: &FrameScene, o: Vec3, ns: Vec3, ng: Vec3) -> Vec3 {
        let mut cast = 0;
        let mut shadow = ShadowRays::traced(&mut cast);
        let mut e = Vec3::ZERO;
        for l in &frame.lights {
            if let Some((wi, el)) = punctual_incident_from(frame, o, ns, ng, l, &mut shadow) {
                e += el * (ng.dot(wi) * shading_normal_factor(ng, ns, wi));
            }
        }
        if cast > 0 {
            self.shadow_rays.add(cast);
        }
        e
    }

    /// The shadow rays cast so far from gather hits and anchors to the punctual lights
    /// ([`GatherDirect::ShadowRays`]); none with the photons' estimate.
    pub fn shadow_rays_cast(&self) -> u64 {
        self.shadow_rays.sum()
    }

    /// Irradiance at `x` (normal `n`) from the `k` nearest photons whose surface normal
    /// agrees with `n` (Jensen's estimate E = ΣΦ / πr², r the distance to the k-th photon;
    /// near a crease, ΣΦ / A with A the part of that disc on the surface).
    pub fn irradiance(&self, x: Vec3, n: Vec3, k: usize) -> Vec3 {
        self.irradiance_and_radius(x, n, k).0
    }

    /// The photons, path by path, with the kd-tree over them (what the next frame's map
    /// compares with and may reuse).
    pub fn paths(&self) -> PhotonPaths {
        PhotonPaths {
            photons: self.photons.clone(),
            path_start: self.path_start.clone(),
            tree: KeptTree(Some(self.tree.clone())),
        }
    }

    /// True if this map's photons lie where `previous`'s did, every one (the map reuses that
    /// map's kd-tree: [`PhotonMap::trace`]); false where that is unknown (a map read from a
    /// checkpoint keeps no tree).
    pub fn same_places_as(&self, previous: &PhotonPaths) -> bool {
        previous
            .tree
            .0
            .as_ref()
            .is_some_and(|t| Arc::ptr_eq(t, &self.tree))
    }

    /// [`PhotonMap::irradiance`] and the squared radius of the disc it gathered over: the
    /// estimate depends on no photon farther away. The disc reaches the k-th nearest photon
    /// within [`PhotonMap::max_radius`], or that radius where fewer lie within it; the
    /// estimate divides by the part of it on the query's surface (`SurfaceClip`).
    pub fn irradiance_and_radius(&self, x: Vec3, n: Vec3, k: usize) -> (Vec3, f32) {
        let r2_max = self.max_radius * self.max_radius;
        let k = k.max(1);
        self.tree
            .nearest_within(x, r2_max, k, |found| self.estimate(x, n, k, r2_max, found))
    }

    /// [`PhotonMap::irradiance_and_radius`] searched first within `r2_near` (an earlier
    /// estimate's reach at the same point, or a bound that should hold `k` photons;
    /// infinite: none). Where at least `k` photons lie within `r2_near`, they are the `k`
    /// nearest, found without the unbounded search's first visits; where fewer do (photons
    /// moved away since), the search looks again within [`RETRY_REACH2`] times `r2_near`,
    /// and only then unbounded.
    pub fn irradiance_and_radius_near(
        &self,
        x: Vec3,
        n: Vec3,
        k: usize,
        r2_near: f32,
    ) -> (Vec3, f32) {
        let r2_max = self.max_radius * self.max_radius;
        let k = k.max(1);
        self.search_near(x, k, r2_near, |found| self.estimate(x, n, k, r2_max, found))
    }

    /// [`PhotonMap::irradiance_and_radius_near`] with the index of the photon nearest to
    /// `x` ([`PhotonMap::nearest`]'s answer): the nearest of the `k` found
    /// ([`knn::PointTree::nearest_of`]), so an anchor's re-estimate also tells which photon
    /// it links (§3.3.2) without a search of its own.
    pub fn irradiance_radius_and_nearest_near(
        &self,
        x: Vec3,
        n: Vec3,
        k: usize,
        r2_near: f32,
    ) -> (Vec3, f32, Option<usize>) {
        let r2_max = self.max_radius * self.max_radius;
        let k = k.max(1);
        self.search_near(x, k, r2_near, |found| {
            let (e, r2) = self.estimate(x, n, k, r2_max, found);
            (e, r2, self.tree.nearest_of(found).map(|i| i as usize))
        })
    }

    /// `answer` for the `k` photons nearest to `x` (`k` ≥ 1), searched first within
    /// `r2_near`, then within [`RETRY_REACH2`] times it, then unbounded (up to
    /// [`PhotonMap::max_radius`]); a bounded search counts only where it found `k`.
    fn search_near<R>(
        &self,
        x: Vec3,
        k: usize,
        r2_near: f32,
        answer: impl Fn(&[knn::Neighbour]) -> R,
    ) -> R {
        let r2_max = self.max_radius * self.max_radius;
        for bound in [r2_near, r2_near * RETRY_REACH2] {
            if bound < r2_max {
                let near = self.tree.nearest_within(x, bound, k, |found| {
                    (found.len() >= k).then(|| answer(found))
                });
                if let Some(e) = near {
                    return e;
                }
            }
        }
        self.tree.nearest_within(x, r2_max, k, answer)
    }

    /// The estimate at `x` from the `found` photons (the k nearest within `r2_max`).
    fn estimate(
        &self,
        x: Vec3,
        n: Vec3,
        k: usize,
        r2_max: f32,
        found: &[knn::Neighbour],
    ) -> (Vec3, f32) {
        let r2 = if found.len() < k {
            r2_max
        } else {
            found.iter().map(|nb| nb.0).fold(0.0, f32::max)
        };
        if !(r2 > 0.0) {
            return (Vec3::ZERO, r2_max);
        }
        // Photons on surfaces facing elsewhere (across a corner) or off the disc (on a
        // parallel surface close by) do not count, but the disc still reaches the k-th
        // photon: a radius set by the few accepted ones would be unstable where almost none
        // are (Jensen 2001, §7.2).
        let r = r2.sqrt();
        let thickness = DISC_THICKNESS * r;
        ESTIMATE_SCRATCH.with(|cell| {
            let mut scratch = cell.take(); // empty where a query inside this one holds it
            let mut clip = SurfaceClip::new(x, n, r, std::mem::take(&mut scratch.lines));
            let on_disc = &mut scratch.on_disc;
            on_disc.clear();
            // One pass sums the photons on the disc, keeps them for the clip's test, and
            // lets the others cut it. Where none cuts it (a disc away from creases), that
            // sum is the estimate's.
            let mut sum = Vec3::ZERO;
            for nb in found {
                let p = &self.ordered[nb.1 as usize];
                let above_by = (p.position - x).dot(n);
                if p.normal.dot(n) > 0.5 && above_by.abs() <= thickness {
                    sum += p.power;
                    on_disc.push((p.position, p.power));
                } else {
                    clip.cut_by(p, above_by);
                }
            }
            let estimate = if clip.lines.is_empty() {
                sum / (PI * r2)
            } else {
                let (sum, area) = clip.kept(on_disc);
                sum / area
            };
            scratch.lines = clip.lines;
            cell.replace(scratch);
            (estimate, r2)
        })
    }

    /// Positions of the photons that differ from those of `previous`, path by path: where
    /// a path stored other photons (position, normal or power differ in any bit), both its
    /// old and its new photons count.
    pub fn changed_since(&self, previous: &PhotonPaths) -> Vec<Vec3> {
        use rayon::prelude::*;
        let paths = self.path_start.len().saturating_sub(1);
        if paths != previous.path_start.len().saturating_sub(1) {
            return self
                .photons
                .iter()
                .chain(&previous.photons)
                .map(|p| p.position)
                .collect();
        }
        let bits =
            |p: &Photon| [p.position, p.normal, p.power].map(|v| v.to_array().map(f32::to_bits));
        fn slice<'a>(photons: &'a [Photon], start: &[u32], i: usize) -> &'a [Photon] {
            &photons[start[i] as usize..start[i + 1] as usize]
        }
        (0..paths)
            .into_par_iter()
            .flat_map_iter(|i| {
                let a = slice(&self.photons, &self.path_start, i);
                let b = slice(&previous.photons, &previous.path_start, i);
                let same = a.len() == b.len() && a.iter().zip(b).all(|(x, y)| bits(x) == bits(y));
                let moved = if same { &[][..] } else { a };
                let was = if same { &[][..] } else { b };
                moved.iter().chain(was).map(|p| p.position)
            })
            .collect()
    }

    /// Index of the photon nearest to `x` within `radius` (and [`PhotonMap::max_radius`]),
    /// if any — [`PhotonMap::nearest`]'s answer where that lies within `radius`, found
    /// without searching farther — and its distance, `(position − x).length()` to the bit
    /// (the tree's squared distance sums the same products in the same order).
    pub fn nearest_within(&self, x: Vec3, radius: f32) -> Option<(usize, f32)> {
        let r = radius.min(self.max_radius);
        self.tree
            .nearest_one(x, r * r)
            .map(|(d2, i)| (i as usize, d2.sqrt()))
    }

    /// Index of the photon nearest to `x` within [`PhotonMap::max_radius`], if any.
    pub fn nearest(&self, x: Vec3) -> Option<usize> {
        let r2_max = self.max_radius * self.max_radius;
        self.tree.nearest_one(x, r2_max).map(|nb| nb.1 as usize)
    }

    /// Total flux stored in the map.
    pub fn stored_power(&self) -> Vec3 {
        self.photons.iter().map(|p| p.power).sum()
    }
}

/// Origin, direction and flux of a photon leaving `source`, and how far its light reaches:
/// a point or spot light's `range` (`KHR_lights_punctual`: beyond it the light is zero, as
/// direct light has it), else infinity.
fn emit(
    frame: &FrameScene,
    source: &Source,
    s: &PhotonSamples,
    centre: Vec3,
    radius: f32,
) -> Option<(Vec3, Vec3, Vec3, f32)> {
    match *source {
        Source::Punctual(i) => {
            let l = &frame.lights[i];
            let reach = l.range.unwrap_or(f32::INFINITY);
            match l.kind {
                LightKind::Point => Some((
                    l.position,
                    uniform_sphere(s.get(DIM_EMIT + 2), s.get(DIM_EMIT + 3)),
                    4.0 * PI * l.intensity,
                    reach,
                )),
                LightKind::Spot { inner, outer } => {
                    // Uniform in the outer cone, weighted by the smooth falloff.
                    let (co, ci) = (outer.cos(), inner.cos());
                    let z = 1.0 - s.get(DIM_EMIT + 2) * (1.0 - co);
                    let r = (1.0 - z * z).max(0.0).sqrt();
                    let phi = 2.0 * PI * s.get(DIM_EMIT + 3);
                    let (t, b) = basis(l.direction);
                    let d =
                        (t * (r * phi.cos()) + b * (r * phi.sin()) + l.direction * z).normalize();
                    let f = ((z - co) / (ci - co).max(1e-4)).clamp(0.0, 1.0);
                    Some((
                        l.position,
                        d,
                        2.0 * PI * (1.0 - co) * l.intensity * f * f,
                        reach,
                    ))
                }
                LightKind::Directional => {
                    let (t, b) = basis(l.direction);
                    let r = radius * s.get(DIM_EMIT).sqrt();
                    let phi = 2.0 * PI * s.get(DIM_EMIT + 1);
                    let o = centre - l.direction * (2.0 * radius)
                        + t * (r * phi.cos())
                        + b * (r * phi.sin());
                    Some((
                        o,
                        l.direction,
                        PI * radius * radius * l.intensity,
                        f32::INFINITY,
                    ))
                }
            }
        }
        Source::Emitter(i) => {
            let e = &frame.emitters.list[i];
            let g = frame.geometry(e.motion);
            let tri = &g.triangles[e.triangle as usize];
            let su = s.get(DIM_EMIT).sqrt();
            let u2 = s.get(DIM_EMIT + 1);
            // The point and its interpolation error bound (pbrt-v4 §6.8.5).
            let (y, y_error) = interpolate(tri, Vec3::new(1.0 - su, su * (1.0 - u2), su * u2));
            let (mut n, _) = face_normal_area(tri);
            let mut u3 = s.get(DIM_EMIT + 2);
            let mut sides = 1.0;
            if e.double_sided {
                sides = 2.0;
                if u3 < 0.5 {
                    n = -n;
                    u3 *= 2.0;
                } else {
                    u3 = 2.0 * u3 - 1.0;
                }
            }
            let d = cosine_direction(n, u3.min(0.999_999_9), s.get(DIM_EMIT + 3));
            // The radiance where the photon leaves (an emissive texture read there): chosen
            // by the triangle's mean power, each photon carries its own point's.
            let l_e = frame.emitted_radiance(e, Vec2::new(su * (1.0 - u2), su * u2));
            Some((
                offset_ray_origin(y, y_error, n, d),
                d,
                PI * l_e * e.area * sides,
                f32::INFINITY,
            ))
        }
    }
}

/// Follows one photon leaving along `ray` (origin, direction, and how far its light reaches
/// to its first hit), storing it at every diffuse hit.
fn trace_path(
    frame: &FrameScene,
    m: Materials,
    ray: (Vec3, Vec3, f32),
    mut flux: Vec3,
    s: &PhotonSamples,
    max_bounces: u32,
    out: &mut Vec<Photon>,
) {
    let (mut o, mut dir, reach) = ray;
    for bounce in 0..=max_bounces {
        let Some(hit) = frame.accel.closest(
            &frame.static_geometry,
            &frame.dynamic_geometry,
            o,
            dir,
            if bounce == 0 { reach } else { f32::INFINITY },
        ) else {
            return;
        };
        let sp = SurfacePoint::new(frame, hit, o, dir);
        let wo = -dir;
        let ns = sp.shading_normal(wo);
        // Shading normals (Veach 1997, §5.3): the photon's flux crossed the geometric
        // surface, at cos θ_g, but the surface reflects light arriving from `wo` by the
        // shading normal's cos θ_s, as the path tracer and the direct light evaluate it.
        // The stored power is the flux the shading normal sees — what E in ρE/π stands
        // for at a gather hit — and a bounce carries it on (the adjoint BSDF's correction,
        // which turns the outgoing cos θ_s into cos θ_g). A box whose corner vertices share
        // one averaged normal tilts its faces' shading normals by up to 55°: photons
        // counted by the geometric cosine read its faces about twice as bright as the path
        // tracer (the cornell-box.glb of cornellbox_wgpu_renderer).
        let shading = shading_normal_factor(sp.ng, sp.ns, wo);
        let flux_seen = flux * shading;
        out.push(Photon {
            position: sp.position,
            normal: sp.ng,
            power: flux_seen,
        });
        if flux_seen.max_element() <= 0.0 {
            return;
        }
        // Russian roulette by the directional albedo (Jensen §5.3): survive with p = its
        // mean, then scatter by sampling the BRDF (glossy bounces included).
        let bsdf = sp.bsdf(m);
        let albedo = bsdf.albedo(ns.dot(wo)).sum();
        let p = ((albedo.x + albedo.y + albedo.z) / 3.0).clamp(0.0, 1.0);
        let d = DIM_BOUNCES + 4 * bounce;
        if s.get(d) >= p || p <= 0.0 {
            return;
        }
        let Some(x) = bsdf.sample(ns, wo, [s.get(d + 1), s.get(d + 2), s.get(d + 3)]) else {
            return;
        };
        if x.wi.dot(sp.ng) <= 0.0 {
            return;
        }
        flux = flux_seen * x.f.sum() * (sp.ng.dot(x.wi) / (x.pdf * p));
        if !flux.is_finite() || flux.max_element() <= 0.0 {
            return;
        }
        dir = x.wi;
        o = sp.spawn();
    }
}

/// cos θ_s / cos θ_g of light arriving from `wo` (both normals on its side): the share of
/// a flux that crossed the geometric surface which the shading normal `ns` reflects
/// (Veach 1997, §5.3). 0 where `ns` faces away from `wo`; at most [`SHADING_MAX`], so a
/// photon grazing the geometric surface does not become a splotch.
fn shading_normal_factor(ng: Vec3, ns: Vec3, wo: Vec3) -> f32 {
    let cos_g = ng.dot(wo).abs();
    let cos_s = ns.dot(wo).max(0.0);
    if cos_s >= SHADING_MAX * cos_g {
        SHADING_MAX
    } else {
        cos_s / cos_g
    }
}

/// The most [`shading_normal_factor`] scales a photon by.
const SHADING_MAX: f32 = 4.0;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Geometry;
    use crate::scene::{FrameCamera, Material, PunctualLight, StaticSet, Surfaces};
    use glam::Vec4;

    use crate::geom::push_quad as quad;

    /// The square y = 0, |x|, |z| ≤ `l`, facing +y.
    fn floor_quad(g: &mut Geometry, l: f32) {
        quad(
            g,
            Vec3::new(-l, 0.0, -l),
            Vec3::new(-l, 0.0, l),
            Vec3::new(l, 0.0, l),
            Vec3::new(l, 0.0, -l),
        );
    }

    /// The photon map of `g`, every surface black, under a sun of irradiance 1 shining along
    /// `direction`: `photons` photons, none of which bounces.
    fn black_under_a_sun(g: Geometry, direction: Vec3, photons: u32) -> PhotonMap {
        sun_map(g, direction, 1.0, photons, None)
    }

    /// [`black_under_a_sun`] with the sun's irradiance `intensity`, traced after `previous`.
    fn sun_map(
        g: Geometry,
        direction: Vec3,
        intensity: f32,
        photons: u32,
        previous: Option<&PhotonPaths>,
    ) -> PhotonMap {
        let black = Material {
            base_color: Vec4::new(0.0, 0.0, 0.0, 1.0),
            ..Material::default()
        };
        let surfaces = Surfaces {
            materials: vec![black].into(),
            textures: Vec::new().into(),
        };
        let sun = PunctualLight {
            kind: LightKind::Directional,
            position: Vec3::ZERO,
            direction,
            intensity: Vec3::splat(intensity),
            range: None,
        };
        let camera = FrameCamera::look_at(Vec3::new(3.0, 2.0, 3.0), Vec3::ZERO, Vec3::Y, 1.0, 1.0);
        let frame = FrameScene::new(
            &StaticSet::new(g),
            Geometry::default(),
            vec![sun],
            camera,
            &surfaces,
        );
        let m = Materials {
            materials: &surfaces.materials,
            textures: &surfaces.textures,
        };
        let e = Emission {
            count: photons,
            seed: 3,
            max_bounces: 8,
            max_radius: 0.05,
            direct: GatherDirect::Photons,
        };
        PhotonMap::trace(&frame, m, &e, previous)
    }

    /// A map whose photons lie where the last map's did (the sun brighter) uses that map's
    /// kd-tree, and estimates what a map with its own tree does; one whose photons moved
    /// (the sun turned) builds its own.
    #[test]
    fn a_map_whose_photons_did_not_move_reuses_the_last_ones_tree() {
        let floor = || {
            let mut g = Geometry::default();
            floor_quad(&mut g, 1.0);
            g
        };
        let sun = Vec3::new(-0.6, -0.8, 0.0);
        let first = sun_map(floor(), sun, 1.0, 20_000, None);
        let paths = first.paths();
        let brighter = sun_map(floor(), sun, 2.0, 20_000, Some(&paths));
        assert!(Arc::ptr_eq(&brighter.tree, &first.tree));
        let own = sun_map(floor(), sun, 2.0, 20_000, None);
        assert!(!Arc::ptr_eq(&own.tree, &first.tree));
        for i in 0..50 {
            let x = Vec3::new(-0.9 + 0.036 * i as f32, 0.0, 0.3 - 0.01 * i as f32);
            let (a, b) = (
                brighter.irradiance_and_radius(x, Vec3::Y, 16),
                own.irradiance_and_radius(x, Vec3::Y, 16),
            );
            assert_eq!((a.0.to_array(), a.1), (b.0.to_array(), b.1), "at {x}");
            assert!(a.0.y > 0.0);
        }
        let turned = sun_map(
            floor(),
            Vec3::new(-0.5, -0.8, 0.1),
            1.0,
            20_000,
            Some(&paths),
        );
        assert!(!Arc::ptr_eq(&turned.tree, &first.tree));
    }

    /// The example room's dashed seam, reduced: a floor (y = 0, x ≥ 0) meeting a wall (x = 0, facing +x),
    /// both black, under a sun shining along (−0.6, −0.8, 0) with irradiance 1 at normal
    /// incidence: the floor's irradiance is 0.8 and the wall's 0.6 everywhere, right up to
    /// the crease, and no photon bounces. Averaged along the crease, estimates next to it
    /// read about half that when divided by the whole disc (the part past the crease lies
    /// on no surface); divided by the part of the disc on the surface, they read it. Measured
    /// (400 000 photons, k = 64): 0.40 on the floor and 0.31 on the wall at the crease
    /// before, 0.81 and 0.63 after; within 1.5 % elsewhere. The bound, 8 %, is about three
    /// times the noise of an 81-point mean.
    #[test]
    fn estimates_at_a_crease_read_the_irradiance_there() {
        let mut g = Geometry::default();
        let l = 1.0;
        quad(
            &mut g,
            Vec3::new(0.0, 0.0, -l),
            Vec3::new(0.0, 0.0, l),
            Vec3::new(l, 0.0, l),
            Vec3::new(l, 0.0, -l),
        );
        quad(
            &mut g,
            Vec3::new(0.0, 0.0, -l),
            Vec3::new(0.0, l, -l),
            Vec3::new(0.0, l, l),
            Vec3::new(0.0, 0.0, l),
        );
        let pm = black_under_a_sun(g, Vec3::new(-0.6, -0.8, 0.0), 400_000);
        let k = 64;
        // Mean estimate at distance d from the crease, over 81 points along it.
        let along = |d: f32, on_wall: bool| {
            let mut sum = 0.0;
            let mut r = 0.0;
            for i in 0..81 {
                let z = -0.8 + 0.02 * i as f32;
                let (x, n) = if on_wall {
                    (Vec3::new(0.0, d, z), Vec3::X)
                } else {
                    (Vec3::new(d, 0.0, z), Vec3::Y)
                };
                let (e, r2) = pm.irradiance_and_radius(x, n, k);
                sum += e.y / 81.0;
                r += r2.sqrt() / 81.0;
            }
            (sum, r)
        };
        let (_, r) = along(0.5, false);
        assert!(r < 0.1 * pm.max_radius.max(0.2), "k-nearest radius {r}");
        for (on_wall, want) in [(false, 0.8f32), (true, 0.6)] {
            for d in [0.5, 0.0, 0.2 * r, 0.5 * r, r, 2.0 * r] {
                let (e, _) = along(d, on_wall);
                let surface = if on_wall { "wall" } else { "floor" };
                assert!(
                    (e - want).abs() < 0.08 * want,
                    "{surface} at {d:.4} from the crease (k-nearest radius {r:.4}): {e:.4}, \
                     irradiance {want}"
                );
            }
        }
    }

    /// Which photons off a disc cut it: one above it on a surface facing the query point (a
    /// wall rising from the floor), once per plane; not one below it (a step down), one
    /// facing away (a convex edge's far side), one parallel to it, or one beyond its rim.
    #[test]
    fn only_surfaces_facing_the_disc_from_above_cut_it() {
        let photon = |position: Vec3, normal: Vec3| Photon {
            position,
            normal,
            power: Vec3::ONE,
        };
        let lines = |photons: &[Photon]| {
            let mut clip = SurfaceClip::new(Vec3::ZERO, Vec3::Y, 1.0, Vec::new());
            for p in photons {
                clip.cut_by(p, p.position.dot(Vec3::Y));
            }
            clip.lines
        };
        let wall = [
            photon(Vec3::new(0.5, 0.1, 0.0), -Vec3::X),
            photon(Vec3::new(0.5, 0.3, 0.2), -Vec3::X),
        ];
        let cut = lines(&wall);
        assert_eq!(cut.len(), 1, "one wall, one line: {cut:?}");
        assert!(
            (cut[0].1 - 0.5).abs() < 1e-6,
            "the wall stands 0.5 away: {cut:?}"
        );
        for (what, p) in [
            (
                "below the disc",
                photon(Vec3::new(0.5, -0.1, 0.0), -Vec3::X),
            ),
            ("facing away", photon(Vec3::new(0.5, 0.1, 0.0), Vec3::X)),
            // Almost level with the disc, and tilted too little to tell its direction.
            (
                "parallel",
                photon(
                    Vec3::new(0.5, 2e-4, 0.0),
                    Vec3::new(-9e-4, -1.0, 0.0).normalize(),
                ),
            ),
            ("beyond the rim", photon(Vec3::new(1.5, 0.1, 0.0), -Vec3::X)),
        ] {
            assert!(lines(&[p]).is_empty(), "a photon {what} cut the disc");
        }
    }

    /// A disc of radius `r` at the origin of the tangent plane (x, z), cut by `lines`.
    fn clip_of(r: f32, lines: Vec<(Vec2, f32)>) -> SurfaceClip {
        SurfaceClip {
            lines,
            x: Vec3::ZERO,
            t: Vec3::X,
            b: Vec3::Z,
            r,
        }
    }

    /// Values spread over [0, 1), one per call (any spread will do).
    fn draws() -> impl FnMut() -> f32 {
        let mut drawn = 0u32;
        move || {
            drawn += 1;
            (crate::sampling::hash(&[drawn]) >> 8) as f32 / (1u32 << 24) as f32
        }
    }

    /// `n` lines in directions and at distances (below `r`) drawn from `next`, a share
    /// `centre` of them through the centre.
    fn random_lines(
        n: usize,
        r: f32,
        centre: f32,
        next: &mut impl FnMut() -> f32,
    ) -> Vec<(Vec2, f32)> {
        (0..n)
            .map(|_| {
                let phi = 2.0 * PI * next();
                let h = if next() < centre { 0.0 } else { r * next() };
                (Vec2::new(phi.cos(), phi.sin()), h)
            })
            .collect()
    }

    /// The kept area by integrating ½ρ(θ)² in double precision over 2¹⁶ directions (ρ the
    /// distance to the nearest line along each, or the rim): within a millionth of the
    /// disc of the true area for these tests' few lines.
    fn area_by_directions(c: &SurfaceClip) -> f64 {
        let n = 1 << 16;
        let step = 2.0 * std::f64::consts::PI / n as f64;
        let sum: f64 = (0..n)
            .map(|i| {
                let (sin, cos) = ((i as f64 + 0.5) * step).sin_cos();
                let rho = c.lines.iter().fold(c.r as f64, |rho, &(a, h)| {
                    let ad = a.x as f64 * cos + a.y as f64 * sin;
                    if ad < 0.0 {
                        rho.min(h as f64 / -ad)
                    } else {
                        rho
                    }
                });
                rho * rho
            })
            .sum();
        0.5 * step * sum
    }

    /// The clipped disc's area: exact for one line; for a quarter disc (two lines through
    /// the centre), a half disc less a strip (two parallel lines facing the same way: only
    /// the nearer counts), and a square inside the disc (no rim left); never below
    /// [`CLIP_MIN_SHARE`].
    #[test]
    fn clipped_disc_areas() {
        let r = 2.0f32;
        let full = PI * r * r;
        for h in [0.0f32, 0.5, 1.0, 1.9] {
            let one = clip_of(r, vec![(Vec2::X, h)]);
            let segment = r * r * (h / r).acos() - h * (r * r - h * h).sqrt();
            assert!((one.area() - (full - segment)).abs() < 1e-4 * full);
            // The same line twice over, facing the same way a hair apart, is one line.
            let twice = clip_of(r, vec![(Vec2::X, h), (Vec2::X, h + 1e-6)]);
            assert!((twice.area() - one.area()).abs() < 1e-5 * full, "h {h}");
        }
        let quarter = clip_of(r, vec![(Vec2::X, 0.0), (Vec2::Y, 0.0)]);
        assert!((quarter.area() - full / 4.0).abs() < 1e-5 * full);
        // A line at 0.5 and a parallel one behind it at 1.2: the segment past 0.5 only.
        let parallel = clip_of(r, vec![(Vec2::X, 1.2), (Vec2::X, 0.5), (Vec2::Y, 1.9)]);
        let by_directions = area_by_directions(&parallel);
        assert!(
            (parallel.area() as f64 - by_directions).abs() < 1e-5 * full as f64,
            "{} against {by_directions}",
            parallel.area()
        );
        let side = 1.2f32; // the square's half-side; its corners lie 1.7 from the centre
        let square = clip_of(
            r,
            [Vec2::X, Vec2::Y, -Vec2::X, -Vec2::Y]
                .map(|a| (a, side))
                .to_vec(),
        );
        let inside = 4.0 * side * side;
        assert!(
            (square.area() - inside).abs() < 1e-5 * inside,
            "{}",
            square.area()
        );
        let sliver = clip_of(
            r,
            vec![(Vec2::X, 0.0), (Vec2::new(-1.0, 0.05).normalize(), 0.0)],
        );
        assert_eq!(sliver.area(), CLIP_MIN_SHARE * full);
        assert!(quarter.contains(Vec3::new(0.5, 0.0, 0.5)));
        assert!(!quarter.contains(Vec3::new(-0.5, 0.0, 0.5)));
    }

    /// The area of a disc cut by 2 to 80 lines in any directions (some through the centre)
    /// at any radius is the area integrated direction by direction, within 10⁻⁵ of the
    /// disc: on the stack (up to 32 lines) and on the heap.
    #[test]
    fn the_clipped_area_is_the_area_within_every_line() {
        let mut next = draws();
        for n in (2..=24).chain([31, 32, 33, 47, 80]) {
            for _ in 0..6 {
                let r = 1e-3 + 1e3 * next() * next();
                let c = clip_of(r, random_lines(n, r, 0.1, &mut next));
                let full = (PI * r * r) as f64;
                let by_directions = area_by_directions(&c);
                let area = c.with_lanes(|lanes| c.cut_area(lanes));
                assert!(
                    (area as f64 - by_directions).abs() < 1e-5 * full,
                    "{n} lines, r {r}: {area} against {by_directions}"
                );
            }
        }
    }

    /// The lines' test four at a time keeps exactly the points that `a·q ≥ −h` keeps for
    /// every line (the comparison as it reads, one line after another), including points on
    /// a line and lines through the centre: for 1 to 40 lines, on the stack and the heap.
    #[test]
    fn the_lanes_keep_the_points_every_line_keeps() {
        let mut next = draws();
        for n in 1..=40 {
            let r = 0.01 + 10.0 * next();
            let c = clip_of(r, random_lines(n, r, 0.2, &mut next));
            for i in 0..200 {
                // Points anywhere on the disc, and points exactly on the first line.
                let q = if i % 4 == 0 {
                    let (a, h) = c.lines[0];
                    -h * a + (2.0 * next() - 1.0) * r * a.perp()
                } else {
                    r * Vec2::new(2.0 * next() - 1.0, 2.0 * next() - 1.0)
                };
                let y = Vec3::new(q.x, 0.0, q.y);
                let d = y - c.x;
                let q = Vec2::new(d.dot(c.t), d.dot(c.b));
                let by_lines = c.lines.iter().all(|&(a, h)| a.dot(q) >= -h);
                assert_eq!(c.contains(y), by_lines, "{n} lines, point {q}");
            }
        }
    }

    /// A black floor (y = 0) whose vertex normals all lean 50° off its geometric normal —
    /// as on a box whose corners share one averaged normal — under a sun shining straight
    /// down with irradiance 1. Flux crosses the floor at cos θ_g = 1, but the floor reflects
    /// light by its shading normal, as the path tracer and the direct light evaluate it: the
    /// irradiance it reflects is cos 50° ≈ 0.643 (Veach 1997, §5.3). Measured (200 000
    /// photons, k = 64, mean of 81 estimates): 1.017 counting photons by the geometric
    /// cosine, 0.654 by the shading normal's. In cornell-box.glb (cornellbox_wgpu_renderer)
    /// the geometric count read the indirect light about twice the path tracer's.
    #[test]
    fn photons_are_counted_by_the_shading_normal() {
        let mut g = Geometry::default();
        floor_quad(&mut g, 2.0);
        let tilt = 50f32.to_radians();
        let ns = Vec3::new(tilt.sin(), tilt.cos(), 0.0);
        for s in &mut g.shading {
            s.normals = [ns; 3];
        }
        let pm = black_under_a_sun(g, Vec3::NEG_Y, 200_000);
        let mut e = 0.0;
        for i in 0..81 {
            let x = Vec3::new(
                -1.0 + 0.25 * (i % 9) as f32,
                0.0,
                -1.0 + 0.25 * (i / 9) as f32,
            );
            e += pm.irradiance(x, Vec3::Y, 64).y / 81.0;
        }
        let want = tilt.cos();
        assert!(
            (e - want).abs() < 0.05 * want,
            "irradiance the shading normal sees {e:.4}, want cos 50° = {want:.4}"
        );
    }
}
