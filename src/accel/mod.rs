//! Ray tracing against two BVH2s built with obvhs (PLOC with reinsertion): one over the
//! static geometry, built once per render with obvhs's `slow_build` preset (Sponza's 188 k
//! triangles: 0.21 s on two cores against 0.08 s for `medium_build`, for gather rays 4–6 %
//! faster, `cargo bench --bench rays`), and one over the dynamic geometry, rebuilt every
//! frame with the fastest preset. They are traversed by our own loop over a copy laid out
//! for it (`pairs.rs`); a hit does not depend on the BVH's shape. (obvhs 0.4's compressed
//! wide BVH traverses faster but misses rays in millimetre-sized scenes — a closed 2 mm room
//! lost 3 % of its photons through it — so it is not used.) Every hit says which set it came
//! from: the anchor method (paper §3.2, Pseudocode 2) re-traces only strata whose rays meet
//! dynamic geometry.
//!
//! Ray offsets come from floating-point error bounds, as in pbrt-v4 (Pharr, Jakob &
//! Humphreys, "Physically Based Rendering", 4th ed., §6.8): a hit point is interpolated from
//! its barycentrics with a per-component bound on its error ([`hit_point`]), and rays leave
//! from just beyond that bound along the geometric normal ([`offset_ray_origin`]). The bound
//! follows each coordinate's own magnitude, so offsets hold from 1e-9 to 1e9 in scale and
//! stay tiny on an axis-aligned ground of any size (the former fixed 2^-17 of the largest
//! coordinate lifted rays 7.6 units off a ±1e6 ground, over every small object's shadow).
//!
//! The other half of pbrt-v4's scheme is the intersection test's own error: a hit whose `t`
//! is within the rounding error of the f32 test (§6.8.7's conservative `t > δt`) is not
//! dropped, as pbrt does, but decided again in f64 ([`ShearedRay::intersect`]). Dropping it
//! loses true hits within ~γ·|v| of large triangles (half a unit near a ±1e6 ground at
//! grazing angles); in f64 the undecided band shrinks by 2^29.
//!
//! Triangles are intersected with the watertight test of Woop, Benthin & Wald, "Watertight
//! Ray/Triangle Intersection" (JCGT 2013), as in pbrt-v3: obvhs's Möller–Trumbore test lets
//! rays through shared edges, and light leaks out of closed rooms through them.

use std::sync::Arc;
use std::time::Duration;

use glam::{Vec2, Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::aabb::Aabb;
use obvhs::bvh2::Bvh2;
use obvhs::ray::Ray;
use obvhs::triangle::Triangle;

use crate::geom::{Geometry, Motion};

mod pairs;

use pairs::PairTree;

/// Relative padding of each triangle's bounding box: 2^-17 of its largest coordinate (only
/// the BVH's boxes; ray offsets come from [`hit_point`]'s error bounds).
const BOX_PAD: f32 = 1.0 / 131_072.0;

/// Shadow rays towards a sampled point of a surface stop this fraction short (pbrt-v4's
/// `ShadowEpsilon`): room for the rounding of the test's `t` beyond the target's own error
/// bound, at any scale.
pub const SHADOW_EPSILON: f32 = 1e-4;

/// γ(n) = nε / (1 − nε) with ε = 2^-24, f32's unit roundoff (pbrt-v4 eq. 6.36): bounds the
/// relative error that n successive f32 roundings can accumulate.
pub fn gamma(n: u32) -> f32 {
    let ne = n as f32 * (0.5 * f32::EPSILON);
    ne / (1.0 - ne)
}

/// γ(n) for f64 arithmetic (ε = 2^-53).
pub fn gamma64(n: u32) -> f64 {
    let ne = n as f64 * (0.5 * f64::EPSILON);
    ne / (1.0 - ne)
}

/// A triangle whose bounding box is padded by a relative epsilon. Axis-aligned triangles
/// (walls, floors) have boxes of zero thickness, which the slab test of a ray travelling
/// along that axis can miss; obvhs builds from the padded boxes.
struct PaddedTriangle(Triangle);

impl obvhs::Boundable for PaddedTriangle {
    fn aabb(&self) -> Aabb {
        let b = self.0.aabb();
        let pad = b
            .min
            .abs()
            .max(b.max.abs())
            .max_element()
            .max(f32::MIN_POSITIVE)
            * BOX_PAD;
        Aabb {
            min: b.min - Vec3A::splat(pad),
            max: b.max + Vec3A::splat(pad),
        }
    }
}

fn padded(g: &Geometry) -> Vec<PaddedTriangle> {
    g.triangles.iter().map(|t| PaddedTriangle(*t)).collect()
}

/// The static BVH, shared by every frame of a render.
pub struct StaticBvh {
    bvh: Option<Bvh2>,
    tree: PairTree,
    /// Unique within the process: what a GPU copy of this BVH is cached under.
    id: u64,
}

/// Ids of [`StaticBvh`]s.
static NEXT_STATIC_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

impl StaticBvh {
    pub fn build(g: &Geometry) -> Self {
        Self::build_with(g, BvhBuildParams::slow_build())
    }

    /// [`StaticBvh::build`] with another of obvhs's presets (benchmarks, tests).
    pub fn build_with(g: &Geometry, params: BvhBuildParams) -> Self {
        let bvh = (!g.is_empty()).then(|| {
            obvhs::bvh2::builder::build_bvh2(&padded(g), params, &mut Duration::default())
        });
        let id = NEXT_STATIC_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tree = PairTree::new(bvh.as_ref(), g);
        StaticBvh { bvh, tree, id }
    }

    /// Unique among the static BVHs built in this process (a rebuilt static set gets a new
    /// one), so that a copy on the GPU can be reused across frames.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// The BVH itself (`None` without static geometry), for uploading to a GPU.
    pub fn bvh2(&self) -> Option<&Bvh2> {
        self.bvh.as_ref()
    }

    pub fn bytes(&self) -> usize {
        self.tree.bytes(self.bvh.as_ref())
    }
}

/// A ray prepared for the watertight test: origin, axis permutation and shear.
#[derive(Debug, Clone, Copy)]
pub struct ShearedRay {
    origin: Vec3A,
    dir: Vec3,
    /// The axis of the direction's largest component, which becomes z; x and y follow it
    /// cyclically.
    kz: usize,
    shear: Vec3A,
}

impl ShearedRay {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        let a = dir.abs();
        let kz = if a.x > a.y {
            if a.x > a.z { 0 } else { 2 }
        } else if a.y > a.z {
            1
        } else {
            2
        };
        let kx = (kz + 1) % 3;
        let ky = (kx + 1) % 3;
        let d = [dir[kx], dir[ky], dir[kz]];
        ShearedRay {
            origin: origin.into(),
            dir,
            kz,
            shear: Vec3A::new(-d[0] / d[2], -d[1] / d[2], 1.0 / d[2]),
        }
    }

    /// Distance to `tri` along the ray within `(0, tmax]`, or infinity.
    ///
    /// Inside or outside is decided by the f32 edge functions alone (that is what makes the
    /// test watertight). `t` is trusted when it exceeds its own error bound δt (pbrt-v4
    /// §6.8.7, `IntersectTriangle`); a `t` within ±δt of zero — a ray leaving the surface it
    /// starts on, or a true hit very close to its origin — is decided again in f64
    /// (`Self::plane_t64`) instead of being dropped.
    #[inline]
    pub fn intersect(&self, tri: &Triangle, tmax: f32) -> f32 {
        self.intersect_barycentric(tri, tmax).0
    }

    /// [`ShearedRay::intersect`] with the hit's barycentrics (weights of `v1` and `v2`), which
    /// the alpha test of masked triangles needs.
    #[inline]
    pub fn intersect_barycentric(&self, tri: &Triangle, tmax: f32) -> (f32, Vec2) {
        let s = self.shear;
        // The permutation by cases rather than by index: a `Vec3A` indexed at run time goes
        // through memory.
        let tr = |v: Vec3A| {
            let p = v - self.origin;
            let (x, y, z) = match self.kz {
                0 => (p.y, p.z, p.x),
                1 => (p.z, p.x, p.y),
                _ => (p.x, p.y, p.z),
            };
            (x + s.x * z, y + s.y * z, z * s.z)
        };
        let (p0, p1, p2) = (tr(tri.v0), tr(tri.v1), tr(tri.v2));
        let mut e0 = p1.0 * p2.1 - p1.1 * p2.0;
        let mut e1 = p2.0 * p0.1 - p2.1 * p0.0;
        let mut e2 = p0.0 * p1.1 - p0.1 * p1.0;
        if e0 == 0.0 || e1 == 0.0 || e2 == 0.0 {
            // Exactly on an edge in f32: decide in f64.
            let f = |a: (f32, f32, f32), b: (f32, f32, f32)| {
                (a.0 as f64 * b.1 as f64 - a.1 as f64 * b.0 as f64) as f32
            };
            e0 = f(p1, p2);
            e1 = f(p2, p0);
            e2 = f(p0, p1);
        }
        if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
            return (f32::INFINITY, Vec2::ZERO);
        }
        let det = e0 + e1 + e2;
        if det == 0.0 {
            return (f32::INFINITY, Vec2::ZERO);
        }
        // Barycentrics first, then t: Σ e_i·z_i would be a cube of the coordinates, which
        // overflows f32 beyond ~1e12 and underflows below ~1e-13; this form only squares them.
        let inv_det = 1.0 / det;
        let (b0, b1, b2) = (e0 * inv_det, e1 * inv_det, e2 * inv_det);
        let t = b0 * p0.2 + b1 * p1.2 + b2 * p2.2;
        if !(t <= tmax) {
            return (f32::INFINITY, Vec2::ZERO);
        }
        let delta_t = t_error([p0, p1, p2], [b0, b1, b2], inv_det);
        if t > delta_t {
            return (t, Vec2::new(b1, b2));
        }
        if t < -delta_t {
            return (f32::INFINITY, Vec2::ZERO);
        }
        match self.plane_t64(tri) {
            // The smallest positive f32 if the f64 distance rounds to zero.
            Some(t64) if t64 <= tmax as f64 => {
                ((t64 as f32).max(f32::from_bits(1)), Vec2::new(b1, b2))
            }
            _ => (f32::INFINITY, Vec2::ZERO),
        }
    }

    /// [`ShearedRay::intersect`], where a `masked` triangle also needs `opaque_at` of the
    /// hit's barycentrics to stop the ray; opaque ones skip the alpha look-up.
    #[inline]
    pub(crate) fn cut_distance(
        &self,
        tri: &Triangle,
        masked: bool,
        tmax: f32,
        opaque_at: impl FnOnce(Vec2) -> bool,
    ) -> f32 {
        if !masked {
            return self.intersect(tri, tmax);
        }
        match self.intersect_barycentric(tri, tmax) {
            (t, b) if t.is_finite() && opaque_at(b) => t,
            _ => f32::INFINITY,
        }
    }

    /// Where the ray's line meets the plane of `tri`, solved in f64 from the exact f32
    /// inputs, if that `t` is positive beyond its own (f64) error bound; `None` otherwise
    /// (behind the origin, at it within rounding, or a ray in the plane).
    fn plane_t64(&self, tri: &Triangle) -> Option<f64> {
        let o = Vec3::from(self.origin).as_dvec3();
        let d = self.dir.as_dvec3();
        let v = |p: Vec3A| Vec3::from(p).as_dvec3();
        let (v0, v1, v2) = (v(tri.v0), v(tri.v1), v(tri.v2));
        let (a, b, w) = (v1 - v0, v2 - v0, v0 - o);
        let n = a.cross(b);
        let num = n.dot(w);
        let den = n.dot(d);
        if den == 0.0 || !den.is_finite() {
            return None;
        }
        let t = num / den;
        // First-order bound: each product of differences of f32 values carries a few f64
        // roundings; |a|×|b| bounds the normal's error even where the cross product cancels.
        let (aa, ba) = (a.abs(), b.abs());
        let n_abs = glam::DVec3::new(
            aa.y * ba.z + aa.z * ba.y,
            aa.z * ba.x + aa.x * ba.z,
            aa.x * ba.y + aa.y * ba.x,
        );
        let err = gamma64(16) * (n_abs.dot(w.abs()) + t.abs() * n_abs.dot(d.abs())) / den.abs();
        (t > err && t.is_finite()).then_some(t)
    }
}

/// What [`t_error`] computes with: one triangle's values (`f32`) or four triangles' in SIMD
/// lanes (`Vec4`, the traversal's block test), by the same operations in the same order.
pub(crate) trait Lanes:
    Copy
    + std::ops::Add<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Mul<f32, Output = Self>
{
    fn abs(self) -> Self;
    fn max(self, other: Self) -> Self;
}

impl Lanes for f32 {
    fn abs(self) -> Self {
        f32::abs(self)
    }
    fn max(self, other: Self) -> Self {
        f32::max(self, other)
    }
}

impl Lanes for glam::Vec4 {
    fn abs(self) -> Self {
        glam::Vec4::abs(self)
    }
    fn max(self, other: Self) -> Self {
        glam::Vec4::max(self, other)
    }
}

/// δt, pbrt-v4's bound on the error of the watertight test's `t` (§6.8.7), from the sheared
/// vertices `p` (x, y, z), the barycentrics `b` and 1/det: every product of three coordinates
/// divided by det first (the same range argument as `t`'s), and γ(5) for the two extra
/// roundings of the divisions. (`f32::max` and SIMD `max` agree where no value is NaN.)
#[inline(always)]
pub(crate) fn t_error<V: Lanes>(p: [(V, V, V); 3], b: [V; 3], inv_det: V) -> V {
    let max_z = p[0].2.abs().max(p[1].2.abs()).max(p[2].2.abs());
    let max_x = p[0].0.abs().max(p[1].0.abs()).max(p[2].0.abs());
    let max_y = p[0].1.abs().max(p[1].1.abs()).max(p[2].1.abs());
    let delta_z = max_z * gamma(3);
    let delta_x = (max_x + max_z) * gamma(5);
    let delta_y = (max_y + max_z) * gamma(5);
    let delta_e = (max_x * gamma(2) * max_y + delta_y * max_x + delta_x * max_y) * 2.0;
    let max_b = b[0].abs().max(b[1].abs()).max(b[2].abs());
    (max_b * gamma(5) * max_z + delta_e * inv_det.abs() * max_z + delta_z * max_b) * 3.0
}

/// Triangle `i` of `g`'s distance along `sr` within `(0, tmax]`, or infinity when the ray
/// misses it or passes through a cut-out (glTF alpha `MASK`) part of it: what the traversals
/// ask of every candidate triangle (they read a copy of the triangle and its flag), and what
/// the GPU's depth maps ask of the triangles they leave to the CPU's f64 test.
#[inline]
pub fn hit_distance(sr: &ShearedRay, g: &Geometry, i: usize, tmax: f32) -> f32 {
    sr.cut_distance(&g.triangles[i], g.shading[i].masked, tmax, |b| {
        g.alpha_passes(i, b)
    })
}

/// A ray–surface hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub motion: Motion,
    /// Index into the geometry of `motion`.
    pub triangle: u32,
}

/// Both BVHs of one frame.
pub struct Accel {
    statics: Arc<StaticBvh>,
    dynamic: Option<Bvh2>,
    dynamic_tree: PairTree,
}

impl Accel {
    /// Builds both BVHs (tests and single frames).
    pub fn build(static_geometry: &Geometry, dynamic_geometry: &Geometry) -> Self {
        Self::with_static(
            Arc::new(StaticBvh::build(static_geometry)),
            dynamic_geometry,
        )
    }

    /// Reuses a static BVH and builds the dynamic one.
    pub fn with_static(statics: Arc<StaticBvh>, dynamic_geometry: &Geometry) -> Self {
        let dynamic = (!dynamic_geometry.is_empty()).then(|| {
            obvhs::bvh2::builder::build_bvh2(
                &padded(dynamic_geometry),
                BvhBuildParams::fastest_build(),
                &mut Duration::default(),
            )
        });
        let dynamic_tree = PairTree::new(dynamic.as_ref(), dynamic_geometry);
        Accel {
            statics,
            dynamic,
            dynamic_tree,
        }
    }

    /// The static BVH (shared by every frame).
    pub fn statics(&self) -> &StaticBvh {
        &self.statics
    }

    /// This frame's dynamic BVH (`None` without dynamic geometry).
    pub fn dynamic_bvh2(&self) -> Option<&Bvh2> {
        self.dynamic.as_ref()
    }

    pub fn dynamic_bytes(&self) -> usize {
        self.dynamic_tree.bytes(self.dynamic.as_ref())
    }

    /// [`Accel::closest`] (with no limit on `t`) for four rays from `origin`, traced together
    /// through the static set ([`Accel::closest4_rays`]); a `None` direction is not traced.
    pub fn closest4(
        &self,
        s: &Geometry,
        d: &Geometry,
        origin: Vec3,
        dirs: [Option<Vec3>; 4],
    ) -> [Option<Hit>; 4] {
        self.closest4_rays(
            s,
            d,
            lanes4(|i| dirs[i].map(|d| (origin, d, f32::INFINITY))),
        )
    }

    /// [`Accel::closest`] for four rays, each `(origin, direction, tmax)`, traced together
    /// through the static set (`PairTree::closest4`: one walk of the tree for the four); a
    /// `None` ray is not traced. The hits are those `closest` finds for each ray alone. For
    /// rays that run close together: a record's gather rays through neighbouring strata, the
    /// camera samples of one pixel.
    pub fn closest4_rays(
        &self,
        s: &Geometry,
        d: &Geometry,
        rays: [Option<(Vec3, Vec3, f32)>; 4],
    ) -> [Option<Hit>; 4] {
        let active = (0..4)
            .filter(|&i| rays[i].is_some())
            .fold(0u32, |m, i| m | 1 << i);
        // A lane left out carries the first ray's origin, so that rays from one point keep
        // the walk's one-origin arithmetic (`PairTree::closest4`).
        let from = rays.iter().flatten().next().map_or(Vec3::ZERO, |r| r.0);
        let lanes = lanes4(|i| {
            let (o, dir, tmax) = rays[i].unwrap_or((from, Vec3::Z, f32::INFINITY));
            (o, canonical(dir), tmax)
        });
        let srs = lanes4(|i| ShearedRay::new(lanes[i].0, lanes[i].1));
        let rays = lanes4(|i| {
            let (o, dir, tmax) = lanes[i];
            Ray::new(o.into(), dir.into(), 0.0, tmax)
        });
        let statics = self.statics.tree.closest4(s, &rays, &srs, active);
        lanes4(|i| {
            (active & (1 << i) != 0).then(|| self.with_dynamic(d, statics[i], &rays[i], &srs[i]))?
        })
    }

    /// The hit of a ray whose static hit is `statics` (distance, triangle): that one, or the
    /// dynamic set's if nearer (the dynamic set is traced only up to the static hit, so a tie
    /// keeps the static one).
    fn with_dynamic(
        &self,
        d: &Geometry,
        statics: Option<(f32, u32)>,
        ray: &Ray,
        sr: &ShearedRay,
    ) -> Option<Hit> {
        let ray = Ray {
            tmax: statics.map_or(ray.tmax, |h| h.0),
            ..*ray
        };
        match self.dynamic_tree.closest(d, &ray, sr) {
            Some((t, triangle)) => Some(Hit {
                t,
                motion: Motion::Dynamic,
                triangle,
            }),
            None => statics.map(|(t, triangle)| Hit {
                t,
                motion: Motion::Static,
                triangle,
            }),
        }
    }

    /// Closest hit along `origin + t·dir` for `t` in `(0, tmax)`.
    pub fn closest(
        &self,
        s: &Geometry,
        d: &Geometry,
        origin: Vec3,
        dir: Vec3,
        tmax: f32,
    ) -> Option<Hit> {
        let dir = canonical(dir);
        let sr = ShearedRay::new(origin, dir);
        let ray = Ray::new(origin.into(), dir.into(), 0.0, tmax);
        let statics = self.statics.tree.closest(s, &ray, &sr);
        self.with_dynamic(d, statics, &ray, &sr)
    }

    /// True if a dynamic prim (of `d`, this frame's dynamic geometry) meets
    /// `origin + t·dir` for `t` in `(0, tmax)`; the static prims are not looked at.
    pub fn occluded_dynamic(&self, d: &Geometry, origin: Vec3, dir: Vec3, tmax: f32) -> bool {
        let dir = canonical(dir);
        let ray = Ray::new(origin.into(), dir.into(), 0.0, tmax);
        self.meets_dynamic(d, ray, &ShearedRay::new(origin, dir))
    }

    fn meets_dynamic(&self, d: &Geometry, ray: Ray, sr: &ShearedRay) -> bool {
        self.dynamic_tree.occluded(d, &ray, sr)
    }

    /// True if anything blocks `origin + t·dir` for `t` in `(0, tmax)` (shadow rays).
    pub fn occluded(&self, s: &Geometry, d: &Geometry, origin: Vec3, dir: Vec3, tmax: f32) -> bool {
        let dir = canonical(dir);
        let ray = Ray::new(origin.into(), dir.into(), 0.0, tmax);
        let sr = ShearedRay::new(origin, dir);
        if self.meets_dynamic(d, ray, &sr) {
            return true;
        }
        self.statics.tree.occluded(s, &ray, &sr)
    }
}

/// Turns negative zeros in a direction into positive ones: obvhs 0.4's CWBVH traversal
/// misses axis-aligned rays whose zero components are negative (e.g. `-Vec3::Z`).
pub fn canonical(dir: Vec3) -> Vec3 {
    dir + Vec3::ZERO
}

/// Barycentric coordinates `(b1, b2)` of `p` in triangle `t` (weights of `v1` and `v2`).
pub fn barycentric(t: &Triangle, p: Vec3) -> Vec2 {
    let (e1, e2, ep) = (t.v1 - t.v0, t.v2 - t.v0, Vec3A::from(p) - t.v0);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (dp1, dp2) = (ep.dot(e1), ep.dot(e2));
    let den = d11 * d22 - d12 * d12;
    if den == 0.0 {
        return Vec2::ZERO;
    }
    let b1 = (d22 * dp1 - d12 * dp2) / den;
    let b2 = (d11 * dp2 - d12 * dp1) / den;
    Vec2::new(b1, b2).clamp(Vec2::ZERO, Vec2::ONE)
}

/// A point on a triangle and a per-component bound on its distance from the true point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HitPoint {
    pub position: Vec3,
    pub error: Vec3,
    /// Barycentric weights of `v0`, `v1`, `v2` (non-negative, summing to 1).
    pub b: Vec3,
}

/// `[f(0), f(1), f(2), f(3)]`: the four lanes of a four-ray query, each built in place.
/// `[T; 4]::map` and `std::array::from_fn` moved such lanes (a ray and its shear, some
/// hundred bytes) through the stack one at a time: in a profile of Sponza's frame 1 at the
/// final preset, 6 % of the gather's samples went to that around [`Accel::closest4_rays`].
#[inline(always)]
pub(crate) fn lanes4<T>(mut f: impl FnMut(usize) -> T) -> [T; 4] {
    [f(0), f(1), f(2), f(3)]
}

/// The point where the ray `o + t·dir` meets `t`, interpolated from its barycentrics, with
/// the bound on its error of pbrt-v4's `Triangle::InteractionFromIntersection`
/// (γ(7)·Σ|b_i·p_i|, §6.8.5) — not `o + t·dir`, whose error grows with `t`.
///
/// The barycentrics and the interpolation are evaluated in f64 from the exact f32 vertices
/// and rounded to f32 once: in f32, barycentrics of a ±1e6 triangle are off by ~γ·|v|,
/// which puts the point 0.1 units away from where the ray met the ground (on the plane,
/// so harmless for self-intersection, but visible in the lighting). The bound is then half
/// an f32 ulp of the result plus f64's γ(7)·Σ|b_i·p_i|. `None` for a ray in the plane.
pub fn hit_point(t: &Triangle, o: Vec3, dir: Vec3) -> Option<HitPoint> {
    let v = |p: Vec3A| Vec3::from(p).as_dvec3();
    let (v0, v1, v2) = (v(t.v0), v(t.v1), v(t.v2));
    let (o, d) = (o.as_dvec3(), dir.as_dvec3());
    // The watertight test's permutation and shear (Woop et al. 2013), in f64.
    let a = d.abs();
    let kz = if a.x > a.y {
        if a.x > a.z { 0 } else { 2 }
    } else if a.y > a.z {
        1
    } else {
        2
    };
    let (kx, ky) = ((kz + 1) % 3, (kz + 2) % 3);
    let (sx, sy) = (-d[kx] / d[kz], -d[ky] / d[kz]);
    let tr = |p: glam::DVec3| {
        let q = p - o;
        (q[kx] + sx * q[kz], q[ky] + sy * q[kz])
    };
    let (p0, p1, p2) = (tr(v0), tr(v1), tr(v2));
    let e = glam::DVec3::new(
        p1.0 * p2.1 - p1.1 * p2.0,
        p2.0 * p0.1 - p2.1 * p0.0,
        p0.0 * p1.1 - p0.1 * p1.0,
    );
    let det = e.x + e.y + e.z;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    // The f32 test said inside; a point the f64 edges put a hair outside is clamped back
    // onto the triangle.
    let b = (e / det).max(glam::DVec3::ZERO);
    let sum = b.x + b.y + b.z;
    if !(sum > 0.0) {
        return None;
    }
    let b = b / sum;
    let (q0, q1, q2) = (v0 * b.x, v1 * b.y, v2 * b.z);
    let p64 = q0 + q1 + q2;
    let position = p64.as_vec3();
    let interp = ((q0.abs() + q1.abs() + q2.abs()) * gamma64(7)).as_vec3();
    // Half an ulp from the rounding to f32 (γ(1) covers it), and the f64 interpolation's
    // own error rounded up.
    let error = position.abs() * gamma(1) + interp * (1.0 + gamma(2));
    Some(HitPoint {
        position,
        error,
        b: b.as_vec3(),
    })
}

/// The point of `t` at barycentrics `b` (weights of `v0`, `v1`, `v2`), interpolated in f32,
/// and pbrt-v4's per-component bound on its error, γ(7)·(|b0·v0| + |b1·v1| + |b2·v2|)
/// (§6.8.5): for points sampled on emitters.
pub fn interpolate(t: &Triangle, b: Vec3) -> (Vec3, Vec3) {
    let (q0, q1, q2) = (t.v0 * b.x, t.v1 * b.y, t.v2 * b.z);
    (
        Vec3::from(q0 + q1 + q2),
        Vec3::from(q0.abs() + q1.abs() + q2.abs()) * gamma(7),
    )
}

/// A ray origin for leaving point `p` (with per-component error bound `error`) of a surface
/// with geometric normal `n` in direction `w` (pbrt-v4 §6.8.6, `OffsetRayOrigin`): moved
/// along `n`, to the side `w` leaves by, until outside the error box (d = |n|·error), then
/// rounded one more f32 step away from the surface per component.
pub fn offset_ray_origin(p: Vec3, error: Vec3, n: Vec3, w: Vec3) -> Vec3 {
    let d = n.abs().dot(error);
    let offset = if w.dot(n) < 0.0 { -d * n } else { d * n };
    let po = p + offset;
    Vec3::from_array(std::array::from_fn(|i| {
        if offset[i] > 0.0 {
            po[i].next_up()
        } else if offset[i] < 0.0 {
            po[i].next_down()
        } else {
            po[i]
        }
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{Geometry, TriangleShading, triangle};

    fn geometry(tris: &[Triangle]) -> Geometry {
        Geometry {
            triangles: tris.to_vec(),
            shading: vec![
                TriangleShading {
                    normals: [Vec3::Z; 3],
                    uvs: [Vec2::ZERO; 3],
                    material: 0,
                    prim: 0,
                    masked: false,
                    attributes: crate::geom::NO_ATTRIBUTES,
                };
                tris.len()
            ],
            ..Geometry::default()
        }
    }

    #[test]
    fn hits_report_their_set_and_the_nearest_wins() {
        let far = triangle(
            Vec3::new(-1.0, -1.0, -5.0),
            Vec3::new(1.0, -1.0, -5.0),
            Vec3::new(0.0, 1.0, -5.0),
        );
        let near = triangle(
            Vec3::new(-1.0, -1.0, -2.0),
            Vec3::new(1.0, -1.0, -2.0),
            Vec3::new(0.0, 1.0, -2.0),
        );
        let (s, d) = (geometry(&[far]), geometry(&[near]));
        let a = Accel::build(&s, &d);
        let h = a
            .closest(&s, &d, Vec3::ZERO, -Vec3::Z, f32::INFINITY)
            .unwrap();
        assert_eq!(h.motion, Motion::Dynamic);
        assert!((h.t - 2.0).abs() < 1e-5);
        let h = a
            .closest(&s, &d, Vec3::new(0.0, 0.0, -3.0), -Vec3::Z, f32::INFINITY)
            .unwrap();
        assert_eq!(h.motion, Motion::Static);
        assert!(a.occluded(&s, &d, Vec3::ZERO, -Vec3::Z, 3.0));
        assert!(!a.occluded(&s, &d, Vec3::ZERO, -Vec3::Z, 1.9));
        assert!(!a.occluded(&s, &d, Vec3::ZERO, Vec3::Z, 100.0));
    }

    /// The closest hit does not depend on the BVH: of two triangles hit at the same distance
    /// (here every triangle of a tiled floor twice, the copies listed in reverse after the
    /// originals) the one with the lower index wins, whichever preset built the tree.
    #[test]
    fn ties_go_to_the_lowest_index_whatever_the_bvh() {
        let mut tiles = Vec::new();
        for i in 0..16 {
            for j in 0..16 {
                let p = |x: f32, y: f32| Vec3::new(i as f32 + x, j as f32 + y, 0.0);
                tiles.push(triangle(p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0)));
                tiles.push(triangle(p(0.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)));
            }
        }
        let n = tiles.len();
        let all: Vec<Triangle> = tiles.iter().chain(tiles.iter().rev()).copied().collect();
        let (g, e) = (geometry(&all), Geometry::default());
        let presets = [
            BvhBuildParams::fastest_build(),
            BvhBuildParams::very_fast_build(),
            BvhBuildParams::medium_build(),
            BvhBuildParams::slow_build(),
            BvhBuildParams::very_slow_build(),
        ];
        for params in presets {
            let a = Accel::with_static(Arc::new(StaticBvh::build_with(&g, params)), &e);
            for (k, t) in tiles.iter().enumerate() {
                // A point inside triangle k, seen from above and at a slant.
                let c = (Vec3::from(t.v0) + Vec3::from(t.v1) + Vec3::from(t.v2)) / 3.0;
                for dir in [-Vec3::Z, Vec3::new(0.3, -0.2, -1.0).normalize()] {
                    let h = a
                        .closest(&g, &e, c - dir * 2.0, dir, f32::INFINITY)
                        .unwrap();
                    assert_eq!(
                        h.triangle as usize,
                        k,
                        "triangle {k} or its copy {}",
                        2 * n - 1 - k
                    );
                }
            }
        }
    }

    /// Regression: axis-aligned rays with negative-zero components (`-Vec3::Z` is
    /// `(-0, -0, -1)`) missed every triangle of a CWBVH.
    #[test]
    fn negative_zero_directions_hit() {
        let t = triangle(
            Vec3::new(-1.0, -1.0, -5.0),
            Vec3::new(1.0, -1.0, -5.0),
            Vec3::new(0.0, 1.0, -5.0),
        );
        let (g, e) = (geometry(&[t]), Geometry::default());
        let a = Accel::build(&g, &e);
        for dir in [
            -Vec3::Z,
            Vec3::new(-0.0, -0.0, -1.0),
            Vec3::new(0.0, 0.0, -1.0),
        ] {
            assert!(
                a.closest(&g, &e, Vec3::ZERO, dir, f32::INFINITY).is_some(),
                "{dir:?}"
            );
            assert!(a.occluded(&g, &e, Vec3::ZERO, dir, 10.0), "{dir:?}");
        }
    }

    /// Rays through the shared edge or vertex of two triangles hit one of them (a quad's
    /// diagonal and its corners), at every scale.
    #[test]
    fn intersection_is_watertight() {
        for scale in [1e-3f32, 1.0, 1e4] {
            let q = |x: f32, y: f32| Vec3::new(x, y, -1.0) * scale;
            let tris = [
                triangle(q(-1.0, -1.0), q(1.0, -1.0), q(1.0, 1.0)),
                triangle(q(-1.0, -1.0), q(1.0, 1.0), q(-1.0, 1.0)),
            ];
            let (g, e) = (geometry(&tris), Geometry::default());
            let a = Accel::build(&g, &e);
            for i in 0..2000 {
                let t = i as f32 / 2000.0 * 1.8 - 0.9;
                // Along the diagonal x = y, from an origin off the plane's normal.
                let o = Vec3::new(0.3, -0.1, 0.5) * scale;
                let dir = (q(t, t) - o).normalize();
                assert!(
                    a.closest(&g, &e, o, dir, f32::INFINITY).is_some(),
                    "scale {scale}, t {t}"
                );
            }
        }
    }

    /// An alpha test that cuts out the half of every triangle nearer its second vertex.
    #[derive(Debug)]
    struct HalfCut;

    impl crate::geom::AlphaTest for HalfCut {
        fn opaque(&self, _: &Geometry, _: usize, b: Vec2) -> bool {
            b.x < 0.5
        }
    }

    /// Masked triangles let rays through where their alpha test fails, in both sets and for
    /// both closest-hit and shadow rays; the same triangle unmasked stops them.
    #[test]
    fn masked_triangles_are_cut_out_for_every_query() {
        let t = triangle(
            Vec3::new(0.0, 0.0, -2.0),
            Vec3::new(4.0, 0.0, -2.0),
            Vec3::new(0.0, 4.0, -2.0),
        );
        let mut masked = geometry(&[t]);
        masked.shading[0].masked = true;
        masked.alpha = Some(Arc::new(HalfCut));
        let opaque = Geometry {
            alpha: Some(Arc::new(HalfCut)),
            ..geometry(&[t])
        };
        let e = Geometry::default();
        // (3, 0.5) has b.x = 0.75: cut out; (0.5, 0.5) has b.x = 0.125: opaque.
        let (cut, kept) = (Vec3::new(3.0, 0.5, 0.0), Vec3::new(0.5, 0.5, 0.0));
        for (s, d) in [(&masked, &e), (&e, &masked)] {
            let a = Accel::build(s, d);
            assert!(a.closest(s, d, cut, -Vec3::Z, f32::INFINITY).is_none());
            assert!(!a.occluded(s, d, cut, -Vec3::Z, 10.0));
            assert!(a.closest(s, d, kept, -Vec3::Z, f32::INFINITY).is_some());
            assert!(a.occluded(s, d, kept, -Vec3::Z, 10.0));
        }
        let a = Accel::build(&opaque, &e);
        assert!(
            a.closest(&opaque, &e, cut, -Vec3::Z, f32::INFINITY)
                .is_some()
        );
        assert!(a.occluded(&opaque, &e, cut, -Vec3::Z, 10.0));
    }

    /// The traversal's four-lane triangle test (`pairs`) finds what each triangle's own test
    /// ([`hit_distance`]) finds: for every ray the same closest distance and triangle (the
    /// lowest index on a tie), and the same answer for shadow rays. Rays aim at the vertices
    /// and edge midpoints of integer grids, where edge functions come out exactly zero and
    /// the test decides in f64, and at points scattered between; every third triangle is
    /// alpha-masked, so that rays pass through the cut-outs of the front grid to the one
    /// behind it. Traced four at a time ([`Accel::closest4`] from one origin,
    /// [`Accel::closest4_rays`] from four, some rays cut short), each ray finds what it finds
    /// alone.
    #[test]
    fn four_lane_test_agrees_with_each_triangles_own() {
        let mut tris = Vec::new();
        for (z0, slope) in [(-2.0f32, 0.0f32), (-3.0, -0.25)] {
            let v = |x: f32, y: f32| Vec3::new(x, y, z0 + slope * x);
            for y in 0..6 {
                for x in 0..6 {
                    let (x, y) = (x as f32, y as f32);
                    tris.push(triangle(v(x, y), v(x + 1.0, y), v(x + 1.0, y + 1.0)));
                    tris.push(triangle(v(x, y), v(x + 1.0, y + 1.0), v(x, y + 1.0)));
                }
            }
        }
        let mut g = geometry(&tris);
        for (i, s) in g.shading.iter_mut().enumerate() {
            s.masked = i % 3 == 0;
        }
        g.alpha = Some(Arc::new(HalfCut));
        let e = Geometry::default();
        let a = Accel::build(&g, &e);
        let half = |range: std::ops::Range<usize>| Geometry {
            triangles: g.triangles[range.clone()].to_vec(),
            shading: g.shading[range].to_vec(),
            ..g.clone()
        };
        let (front, back) = (half(0..72), half(72..144));
        let split = Accel::build(&front, &back);
        // The same trees with the walk of rays from one point in four lanes only, which
        // the others take only where the CPU lacks AVX2.
        let narrow = |s: &Geometry, d: &Geometry| {
            let mut statics = StaticBvh::build(s);
            statics.tree = statics.tree.four_lanes();
            Accel::with_static(Arc::new(statics), d)
        };
        let (a4, split4) = (narrow(&g, &e), narrow(&front, &back));
        assert!(!a4.statics.tree.wide());
        assert_eq!(a.statics.tree.wide(), pairs::has_avx2());
        let mut targets = Vec::new();
        for y in 0..13 {
            for x in 0..13 {
                targets.push(Vec3::new(x as f32 * 0.5, y as f32 * 0.5, -2.0));
            }
        }
        for i in 0..400u32 {
            let h = crate::sampling::hash(&[i]);
            let (u, v) = ((h & 0xffff) as f32 / 65536.0, (h >> 16) as f32 / 65536.0);
            targets.push(Vec3::new(u * 8.0 - 1.0, v * 8.0 - 1.0, -2.0));
        }
        let origins = [
            Vec3::new(3.0, 3.0, 1.0),
            Vec3::new(0.5, 2.0, 0.0),
            Vec3::new(6.0, 0.0, 2.0),
            Vec3::new(-1.0, 4.0, -1.0),
        ];
        let (mut hits, mut on_edge) = (0, 0);
        for o in origins {
            for &target in &targets {
                let dir = target - o;
                let sr = ShearedRay::new(o, canonical(dir));
                let own = (0..tris.len())
                    .map(|i| (hit_distance(&sr, &g, i, f32::INFINITY), i as u32))
                    .filter(|h| h.0 < f32::INFINITY)
                    .min_by(|x, y| x.partial_cmp(y).unwrap());
                let found = a.closest(&g, &e, o, dir, f32::INFINITY);
                assert_eq!(found.map(|h| (h.t, h.triangle)), own, "{o} → {target}");
                for tmax in [0.5, 1.0, 1.5] {
                    let blocked = own.is_some_and(|h| h.0 < tmax);
                    assert_eq!(a.occluded(&g, &e, o, dir, tmax), blocked, "{o} → {target}");
                }
                hits += usize::from(own.is_some());
                on_edge += usize::from(target.fract() == Vec3::new(0.0, 0.0, 0.0));
            }
            // Four rays at a time, as the gather traces them (a lane in five left out).
            for (n, four) in targets.chunks(4).enumerate() {
                let dirs: [Option<Vec3>; 4] = std::array::from_fn(|i| {
                    four.get(i)
                        .filter(|_| (4 * n + i) % 5 != 3)
                        .map(|&target| target - o)
                });
                // Both grids static, and the front one static with the back one dynamic.
                let sets = [(&a, &g, &e), (&split, &front, &back)];
                let four_lanes = [(&a4, &g, &e), (&split4, &front, &back)];
                for (a, s, d) in sets.into_iter().chain(four_lanes) {
                    let found = a.closest4(s, d, o, dirs);
                    for (dir, hit) in dirs.into_iter().zip(found) {
                        let alone = dir.and_then(|dir| a.closest(s, d, o, dir, f32::INFINITY));
                        assert_eq!(hit, alone, "{o} along {dir:?}");
                    }
                }
            }
        }
        // Four rays from four origins (camera rays from the near plane), some of them cut
        // short: each finds what it finds alone.
        for (n, four) in targets.chunks(4).enumerate() {
            let rays: [Option<(Vec3, Vec3, f32)>; 4] = std::array::from_fn(|i| {
                let o = origins[(n + i) % origins.len()];
                let tmax = [f32::INFINITY, 3.5, 2.0][(n + i) % 3];
                four.get(i)
                    .filter(|_| (4 * n + i) % 5 != 2)
                    .map(|&target| (o, target - o, tmax))
            });
            for (a, s, d) in [(&a, &g, &e), (&split, &front, &back)] {
                let found = a.closest4_rays(s, d, rays);
                for (ray, hit) in rays.into_iter().zip(found) {
                    let alone = ray.and_then(|(o, dir, tmax)| a.closest(s, d, o, dir, tmax));
                    assert_eq!(hit, alone, "{ray:?}");
                }
            }
        }
        assert!(
            hits > 1000 && on_edge > 100,
            "{hits} hits, {on_edge} rays at vertices"
        );
    }

    #[test]
    fn empty_sets_trace() {
        let e = Geometry::default();
        let a = Accel::build(&e, &e);
        assert!(
            a.closest(&e, &e, Vec3::ZERO, Vec3::X, f32::INFINITY)
                .is_none()
        );
        assert!(!a.occluded(&e, &e, Vec3::ZERO, Vec3::X, 1.0));
    }

    #[test]
    fn barycentrics_recover_the_point() {
        let t = triangle(Vec3::ZERO, Vec3::X, Vec3::Y);
        let b = barycentric(&t, Vec3::new(0.25, 0.5, 0.0));
        assert!((b - Vec2::new(0.25, 0.5)).length() < 1e-6);
    }

    /// Points on a tilted triangle — hit points ([`hit_point`]) and points interpolated in
    /// f32 as emitter samples are ([`interpolate`]) — spawn rays ([`offset_ray_origin`]) to
    /// either side, down to grazing angles, that never meet the triangle again: from 1e-9 to
    /// 1e9 in scale and 1e6 from the origin. Without the offset (or with it shrunk by 1e30)
    /// the interpolated points, whose error is several ulps, re-hit.
    #[test]
    fn offsets_escape_their_surface_at_any_scale() {
        let far = Vec3::new(1e6, -1e6, 1e6);
        let cases = [
            (1e-9f32, Vec3::ZERO),
            (1e-3, Vec3::ZERO),
            (1.0, Vec3::ZERO),
            (1e4, Vec3::ZERO),
            (1e9, Vec3::ZERO),
            (1.0, far),
            (1e-3, Vec3::new(1e3, 0.0, 0.0)),
        ];
        for (scale, at) in cases {
            let q = |v: Vec3| v * scale + at;
            let t = triangle(
                q(Vec3::new(-1.0, -0.3, -1.0)),
                q(Vec3::new(1.0, 0.2, -1.0)),
                q(Vec3::new(0.1, 0.05, 1.0)),
            );
            let (g, e) = (geometry(&[t]), Geometry::default());
            let a = Accel::build(&g, &e);
            let n = Vec3::from((t.v1 - t.v0).cross(t.v2 - t.v0)).normalize();
            let mut points = 0;
            for i in 0..300 {
                let (u, v) = (
                    (i as f32 * 0.618_034).fract(),
                    (i as f32 * 0.414_214).fract(),
                );
                let side = if i % 2 == 0 { 1.0 } else { -1.0 };
                // A hit point, from a ray arriving from `side`.
                let o = q(Vec3::new(0.3, 3.0, 0.2) * side);
                let dir = (q(Vec3::new(u - 0.5, 0.0, v - 0.5) * 0.8) - o).normalize();
                let mut starts = Vec::new();
                if a.closest(&g, &e, o, dir, f32::INFINITY).is_some() {
                    let hp = hit_point(&t, o, dir).unwrap();
                    starts.push((hp.position, hp.error));
                }
                // An emitter-style sample.
                let su = u.sqrt();
                starts.push(interpolate(&t, Vec3::new(1.0 - su, su * (1.0 - v), su * v)));
                for (p, error) in starts {
                    points += 1;
                    let ng = n * side;
                    let (tangent, _) = crate::geom::basis(ng);
                    for w in [
                        ng,
                        (ng + 3.0 * tangent).normalize(),
                        (0.01 * ng + tangent).normalize(),
                        (1e-4 * ng - tangent).normalize(),
                    ] {
                        for w in [w, -w] {
                            let po = offset_ray_origin(p, error, ng, w);
                            assert!(
                                a.closest(&g, &e, po, w, f32::INFINITY).is_none(),
                                "scale {scale} at {at}: point {i} ({p}) leaving along {w} re-hits"
                            );
                        }
                    }
                }
            }
            assert!(points > 500, "scale {scale} at {at}: {points} points");
        }
    }

    /// Near the middle of a ±1e6 ground the offset is the hit's own rounding error, far
    /// below the former 2^-17 of the largest coordinate (7.6 units): rays leave the ground,
    /// and a true hit on the ground 1e-3 away from a ray's origin is found.
    #[test]
    fn offsets_on_a_huge_ground_are_tiny_and_near_hits_survive() {
        for y in [0.0f32, 0.5, -3.0] {
            let c = |x: f32, z: f32| Vec3::new(x, y, z);
            let tris = [
                triangle(c(-1e6, -1e6), c(-1e6, 1e6), c(1e6, 1e6)),
                triangle(c(-1e6, -1e6), c(1e6, 1e6), c(1e6, -1e6)),
            ];
            let (g, e) = (geometry(&tris), Geometry::default());
            let a = Accel::build(&g, &e);
            for i in 0..100 {
                let x = (i as f32 * 0.618_034).fract() * 4.0 - 2.0;
                let o = Vec3::new(0.2, y + 2.0, 0.1);
                let dir = (c(x, -x * 0.7) - o).normalize();
                let h = a.closest(&g, &e, o, dir, f32::INFINITY).unwrap();
                let hp = hit_point(&tris[h.triangle as usize], o, dir).unwrap();
                let po = offset_ray_origin(hp.position, hp.error, Vec3::Y, Vec3::Y);
                let off = (po - hp.position).length();
                assert!(off < 1e-5, "y {y}: offset {off}");
                assert!(po.y >= y);
                let w = (Vec3::new(0.0, y + 2.0, 0.0) - po).normalize();
                assert!(!a.occluded(&g, &e, po, w, 1.9), "y {y}: sample {i}");
                // A grazing ray 1e-3 above the ground, going down at 1/100: its true hit
                // 0.1 away is well inside the f32 test's own error band there (~0.5).
                let o = c(x, -x * 0.7) + Vec3::Y * 1e-3;
                let dir = Vec3::new(1.0, -0.01, 0.3).normalize();
                let h = a.closest(&g, &e, o, dir, f32::INFINITY);
                let want = 1e-3 / 0.01 * Vec3::new(1.0, -0.01, 0.3).length();
                assert!(
                    h.is_some_and(|h| (h.t - want).abs() < 1e-3 * want),
                    "y {y}: grazing hit {h:?}, want t = {want}"
                );
            }
        }
    }
}
