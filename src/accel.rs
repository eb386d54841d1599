//! Ray tracing against two BVH2s built with obvhs (PLOC with reinsertion): one over the
//! static geometry, built once per render with a higher-quality preset, and one over the
//! dynamic geometry, rebuilt every frame with the fastest preset. (obvhs 0.4's compressed
//! wide BVH traverses faster but misses rays in millimetre-sized scenes — a closed 2 mm room
//! lost 3 % of its photons through it — so it is not used.) Every hit
//! says which set it came from: the anchor method (paper §3.2, Pseudocode 2) re-traces only
//! strata whose rays meet dynamic geometry.
//!
//! Ray offsets are relative to the magnitude of the coordinates involved (float error of the
//! intersection grows with them), so they behave the same at any scene scale.
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
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;

use crate::geom::{Geometry, Motion};

/// Relative offset of ray origins from surfaces: 2^-17 of the largest vertex coordinate of
/// the triangle left behind (a few ulps of f32's 2^-24 relative precision, times margin for
/// the intersection's own error).
pub const OFFSET_SCALE: f32 = 1.0 / 131_072.0;

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
            * OFFSET_SCALE;
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
}

impl StaticBvh {
    pub fn build(g: &Geometry) -> Self {
        let bvh = (!g.is_empty()).then(|| {
            obvhs::bvh2::builder::build_bvh2(
                &padded(g),
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            )
        });
        StaticBvh { bvh }
    }

    pub fn bytes(&self) -> usize {
        self.bvh.as_ref().map_or(0, |b| {
            b.nodes.len() * size_of_val(&b.nodes[0]) + b.primitive_indices.len() * 4
        })
    }
}

/// A ray prepared for the watertight test: origin, axis permutation and shear.
#[derive(Debug, Clone, Copy)]
pub struct ShearedRay {
    origin: Vec3A,
    k: [usize; 3],
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
            k: [kx, ky, kz],
            shear: Vec3A::new(-d[0] / d[2], -d[1] / d[2], 1.0 / d[2]),
        }
    }

    /// Distance to `tri` along the ray within `(0, tmax]`, or infinity.
    #[inline]
    pub fn intersect(&self, tri: &Triangle, tmax: f32) -> f32 {
        match self.intersect_scaled(tri, tmax) {
            Some((t_scaled, det, _)) => t_scaled / det,
            None => f32::INFINITY,
        }
    }

    /// [`ShearedRay::intersect`] with the hit's barycentrics (weights of `v1` and `v2`), which
    /// the alpha test of masked triangles needs.
    #[inline]
    pub fn intersect_barycentric(&self, tri: &Triangle, tmax: f32) -> (f32, Vec2) {
        match self.intersect_scaled(tri, tmax) {
            Some((t_scaled, det, e)) => (t_scaled / det, e / det),
            None => (f32::INFINITY, Vec2::ZERO),
        }
    }

    /// The watertight test proper: for a hit within `(0, tmax]`, the distance times the
    /// determinant, the determinant, and the edge functions of `v1` and `v2` (barycentrics
    /// times the determinant). The division is left to the caller.
    #[inline]
    fn intersect_scaled(&self, tri: &Triangle, tmax: f32) -> Option<(f32, f32, Vec2)> {
        const MISS: Option<(f32, f32, Vec2)> = None;
        let [kx, ky, kz] = self.k;
        let s = self.shear;
        let tr = |v: Vec3A| {
            let p = v - self.origin;
            let (x, y, z) = (p[kx], p[ky], p[kz]);
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
            return MISS;
        }
        let det = e0 + e1 + e2;
        if det == 0.0 {
            return MISS;
        }
        let t_scaled = e0 * p0.2 + e1 * p1.2 + e2 * p2.2;
        if det < 0.0 && (t_scaled >= 0.0 || t_scaled < tmax * det) {
            return MISS;
        }
        if det > 0.0 && (t_scaled <= 0.0 || t_scaled > tmax * det) {
            return MISS;
        }
        Some((t_scaled, det, Vec2::new(e1, e2)))
    }
}

/// The closure the traversals call for candidate triangle `i` of `g`: its distance, or
/// infinity when the ray misses it or passes through a cut-out (glTF alpha `MASK`) part of it.
#[inline]
fn hit_distance(sr: &ShearedRay, g: &Geometry, i: usize, tmax: f32) -> f32 {
    match sr.intersect_scaled(&g.triangles[i], tmax) {
        None => f32::INFINITY,
        // Opaque triangles: one flag read, no barycentrics.
        Some((t_scaled, det, _)) if !g.shading[i].masked => t_scaled / det,
        Some((t_scaled, det, e)) if g.alpha_passes(i, e / det) => t_scaled / det,
        Some(_) => f32::INFINITY,
    }
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
        Accel { statics, dynamic }
    }

    pub fn dynamic_bytes(&self) -> usize {
        self.dynamic.as_ref().map_or(0, |b| {
            b.nodes.len() * size_of_val(&b.nodes[0]) + b.primitive_indices.len() * 4
        })
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
        let ray = Ray::new(origin.into(), dir.into(), 0.0, tmax);
        let sr = ShearedRay::new(origin, dir);
        let mut best: Option<Hit> = None;
        if let Some(bvh) = &self.statics.bvh {
            let mut hit = RayHit::none();
            if bvh.ray_traverse(ray, &mut hit, |r, id| {
                hit_distance(&sr, s, bvh.primitive_indices[id] as usize, r.tmax)
            }) {
                best = Some(Hit {
                    t: hit.t,
                    motion: Motion::Static,
                    triangle: bvh.primitive_indices[hit.primitive_id as usize],
                });
            }
        }
        if let Some(bvh) = &self.dynamic {
            let tmax = best.map_or(tmax, |h| h.t);
            let ray = Ray::new(origin.into(), dir.into(), 0.0, tmax);
            let mut hit = RayHit::none();
            if bvh.ray_traverse(ray, &mut hit, |r, id| {
                hit_distance(&sr, d, bvh.primitive_indices[id] as usize, r.tmax)
            }) {
                best = Some(Hit {
                    t: hit.t,
                    motion: Motion::Dynamic,
                    triangle: bvh.primitive_indices[hit.primitive_id as usize],
                });
            }
        }
        best
    }

    /// True if anything blocks `origin + t·dir` for `t` in `(0, tmax)` (shadow rays).
    pub fn occluded(&self, s: &Geometry, d: &Geometry, origin: Vec3, dir: Vec3, tmax: f32) -> bool {
        let dir = canonical(dir);
        let ray = Ray::new(origin.into(), dir.into(), 0.0, tmax);
        let sr = ShearedRay::new(origin, dir);
        if let Some(bvh) = &self.dynamic
            && !bvh.ray_traverse_miss(ray, |r, id| {
                hit_distance(&sr, d, bvh.primitive_indices[id] as usize, r.tmax)
            })
        {
            return true;
        }
        if let Some(bvh) = &self.statics.bvh
            && !bvh.ray_traverse_miss(ray, |r, id| {
                hit_distance(&sr, s, bvh.primitive_indices[id] as usize, r.tmax)
            })
        {
            return true;
        }
        false
    }
}

/// Turns negative zeros in a direction into positive ones: obvhs 0.4's CWBVH traversal
/// misses axis-aligned rays whose zero components are negative (e.g. `-Vec3::Z`).
fn canonical(dir: Vec3) -> Vec3 {
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

/// Distance to move a ray origin off triangle `t` along its normal (see the module doc).
pub fn offset_of(t: &Triangle) -> f32 {
    let m = t.v0.abs().max(t.v1.abs()).max(t.v2.abs()).max_element();
    m.max(f32::MIN_POSITIVE) * OFFSET_SCALE
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

    /// Offsets scale with the coordinates: a ray leaving a surface at 1e4 does not re-hit it.
    #[test]
    fn offsets_escape_their_surface_at_any_scale() {
        for scale in [1e-3f32, 1.0, 1e4] {
            let t = triangle(
                Vec3::new(-1.0, 0.0, -1.0) * scale,
                Vec3::new(1.0, 0.0, -1.0) * scale,
                Vec3::new(0.0, 0.0, 1.0) * scale + Vec3::new(7.0 * scale, 0.0, 0.0),
            );
            let g = geometry(&[t]);
            let e = Geometry::default();
            let a = Accel::build(&g, &e);
            for i in 0..200 {
                let x = (i as f32 / 200.0 - 0.5) * 0.3 * scale;
                let p = Vec3::new(x + 0.3 * scale, 0.0, 0.1 * scale);
                let o = p + Vec3::Y * offset_of(&t);
                let dir = Vec3::new(0.3, 1.0, -0.2).normalize();
                assert!(
                    a.closest(&g, &e, o, dir, f32::INFINITY).is_none(),
                    "scale {scale}, sample {i}"
                );
            }
        }
    }
}
