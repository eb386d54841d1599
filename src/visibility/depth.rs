//! Hemisphere depth maps for anchor bucketing (the paper's §5.1): for every mapped cell of a
//! glossy shading point's hemisphere, the distance to the nearest surface along the cell's
//! centre direction. A bucket keeps the anchors nearer than that distance (plus an offset);
//! farther ones are hidden from the point.
//!
//! The paper rasterises one depth map per shading point on the GPU. Here a map is a batch
//! of closest-hit queries — one ray per mapped cell, from the point's offset origin — and
//! [`DepthMaps`] answers a whole batch of them (every shading point of a band of pixels,
//! [`crate::integrator::bucket`]) against the frame's static and dynamic geometry at once.
//! Two implementations keep the same contract:
//!
//! - [`CpuDepthMaps`]: [`crate::accel::Accel::closest`] per query, in parallel. The
//!   reference: bucketing with it renders what the per-pixel tracing did before the queries
//!   were batched, byte for byte.
//! - [`super::depth_gpu::GpuDepthMaps`]: a compute shader (`shaders/depth.wgsl`) that
//!   traverses the same obvhs BVH2s, flattened and uploaded (the static one once per render,
//!   the dynamic one per frame), and intersects triangles with the same watertight test in
//!   f32. It runs on the device of [`super::gpu::GpuVisibility`]: depth maps run where
//!   visibility runs ([`super::Visibility::depth_maps`]).
//!
//! How far the two may differ, and why. The CPU test settles two cases in f64 that WGSL
//! cannot: an edge function exactly zero in f32 (a ray through an edge or a vertex) and a
//! `t` within its own rounding bound of zero — a hit at the ray's origin, which every ray
//! leaving a surface meets in the triangle it starts on (about half of a glossy floor's
//! depth queries). The shader does not guess there: it names such a triangle (two per query
//! at most), and the CPU tests that triangle alone with its own test and keeps the nearer of
//! its answer and the shader's. A query with more such triangles, with an alpha-tested
//! (glTF `MASK`) triangle in front of its nearest hit (the shader has no textures), or whose
//! traversal stack would overflow is answered *undecided* and traced whole on the CPU. What
//! remains is rounding: the shader's f32 arithmetic may be fused (multiply-add) where Rust's
//! is not, so (a) a hit's `t` may differ from the CPU's by some units in the last place of
//! the terms it is summed from — the triangle's vertices' distances along the ray, so
//! relative to `t` far more where `t` is small beside them (tested: the difference is below
//! [`T_TOLERANCE`] of the largest distance from the origin to the triangle's vertices; on an
//! NVIDIA H200 it was at most 1.0·10⁻⁶ of that, while a hit 1.6·10⁻⁴ from its origin came
//! back 1.5·10⁻⁵ of its own distance off), and (b) a ray within about an ulp of an edge
//! shared by two triangles may be given to the other triangle (the same `t`: both tests are
//! watertight, neither lets it through), or, at the silhouette edge of an object, a ray
//! grazing it within an ulp may hit or miss it on one side only (tested: at most one query
//! in [`GRAZING_SHARE`] hits a different triangle at a different distance, misses
//! included). In bucketing, (a) moves D_bucket by at most 10⁻⁵ of the hit triangle's reach
//! from the point and can only matter for an anchor that close to a bucket's edge; (b)
//! changes a cell's depth only for a ray that grazes a silhouette, where either depth is a
//! fair reading of the map. The images agree to the bound `tests/it/glossy.rs` states.

use glam::Vec3;
use rayon::prelude::*;

use super::Error;
use crate::accel::Hit;
use crate::scene::FrameScene;

/// Largest difference between the GPU's and the CPU's distance for the same hit, relative to
/// the larger of that distance and the hit triangle's farthest vertex from the ray's origin
/// (module doc, (a)).
pub const T_TOLERANCE: f32 = 1e-5;

/// At most one query in this many may differ in what it hits between the implementations
/// (module doc, (b)).
pub const GRAZING_SHARE: usize = 1000;

/// One depth query: a ray from `origin` (already offset off its surface) along the unit
/// vector `dir`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthQuery {
    pub origin: Vec3,
    pub dir: Vec3,
}

/// Answers batches of depth queries against a frame's geometry (module doc).
pub trait DepthMaps: Send + Sync {
    /// The implementation and, for the GPU, its adapter.
    fn name(&self) -> String;

    /// The closest hit of each query against `frame`'s static and dynamic geometry, alpha
    /// test included (`None` where nothing is hit), in the order of `queries`.
    fn closest(
        &self,
        frame: &FrameScene,
        queries: &[DepthQuery],
    ) -> Result<Vec<Option<Hit>>, Error>;
}

/// Queries per parallel task of [`CpuDepthMaps`]: large enough that the task's overhead does
/// not count, small enough to balance.
const CPU_CHUNK: usize = 256;

/// The CPU implementation: [`crate::accel::Accel::closest`] per query.
pub struct CpuDepthMaps;

/// Closest hit of one query on the CPU (both implementations fall back to it).
pub fn closest_on_cpu(frame: &FrameScene, q: &DepthQuery) -> Option<Hit> {
    frame.accel.closest(
        &frame.static_geometry,
        &frame.dynamic_geometry,
        q.origin,
        q.dir,
        f32::INFINITY,
    )
}

impl DepthMaps for CpuDepthMaps {
    fn name(&self) -> String {
        "cpu".into()
    }

    fn closest(
        &self,
        frame: &FrameScene,
        queries: &[DepthQuery],
    ) -> Result<Vec<Option<Hit>>, Error> {
        let mut out = vec![None; queries.len()];
        out.par_chunks_mut(CPU_CHUNK)
            .zip(queries.par_chunks(CPU_CHUNK))
            .for_each(|(o, q)| {
                for (o, q) in o.iter_mut().zip(q) {
                    *o = closest_on_cpu(frame, q);
                }
            });
        Ok(out)
    }
}

/// Random scenes and queries for the tests of both implementations.
#[cfg(test)]
pub(crate) mod testing {
    use super::*;
    use crate::geom::{Geometry, TriangleShading, triangle};
    use glam::Vec2;

    fn r(seed: u32, i: u32, d: u32) -> f32 {
        crate::sampling::hash(&[seed, i, d]) as f32 / u32::MAX as f32
    }

    /// A frame of `statics` (its BVH built here) and `dynamic`.
    pub fn frame(statics: Geometry, dynamic: Geometry) -> FrameScene {
        frame_with(&crate::scene::StaticSet::new(statics), dynamic)
    }

    /// A frame of a static set (its BVH shared) and `dynamic`.
    pub fn frame_with(statics: &crate::scene::StaticSet, dynamic: Geometry) -> FrameScene {
        let camera = crate::scene::FrameCamera::look_at(Vec3::Z, Vec3::ZERO, Vec3::Y, 1.0, 1.0);
        FrameScene::new(
            statics,
            dynamic,
            Vec::new(),
            camera,
            &crate::scene::Surfaces::default(),
        )
    }

    /// `n` random triangles of size about `size` around the origin (within `spread`), prim
    /// `i % 7`.
    pub fn soup(seed: u32, n: u32, spread: f32, size: f32) -> Geometry {
        let r = |i, d| r(seed, i, d);
        let mut g = Geometry::default();
        for i in 0..n {
            let c = Vec3::new(r(i, 0) - 0.5, r(i, 1) - 0.5, r(i, 2) - 0.5) * spread;
            let v = |k: u32| {
                c + Vec3::new(r(i, 10 + k) - 0.5, r(i, 20 + k) - 0.5, r(i, 30 + k) - 0.5) * size
            };
            g.triangles.push(triangle(v(0), v(1), v(2)));
            g.shading.push(TriangleShading {
                normals: [Vec3::Y; 3],
                uvs: [Vec2::ZERO; 3],
                material: 0,
                prim: i % 7,
                masked: false,
                attributes: crate::geom::NO_ATTRIBUTES,
            });
        }
        g
    }

    /// A closed axis-aligned box of 12 triangles around the soup (every ray hits something
    /// but for the ones that leave through a gap — there is none: the box is closed).
    pub fn closed_box(half: f32) -> Geometry {
        let mut g = Geometry::default();
        let h = half;
        let c = |x: f32, y: f32, z: f32| Vec3::new(x, y, z) * h;
        let quads = [
            [
                c(-1., -1., -1.),
                c(1., -1., -1.),
                c(1., 1., -1.),
                c(-1., 1., -1.),
            ],
            [
                c(-1., -1., 1.),
                c(-1., 1., 1.),
                c(1., 1., 1.),
                c(1., -1., 1.),
            ],
            [
                c(-1., -1., -1.),
                c(-1., 1., -1.),
                c(-1., 1., 1.),
                c(-1., -1., 1.),
            ],
            [
                c(1., -1., -1.),
                c(1., -1., 1.),
                c(1., 1., 1.),
                c(1., 1., -1.),
            ],
            [
                c(-1., -1., -1.),
                c(-1., -1., 1.),
                c(1., -1., 1.),
                c(1., -1., -1.),
            ],
            [
                c(-1., 1., -1.),
                c(1., 1., -1.),
                c(1., 1., 1.),
                c(-1., 1., 1.),
            ],
        ];
        for q in quads {
            for t in [[q[0], q[1], q[2]], [q[0], q[2], q[3]]] {
                g.triangles.push(triangle(t[0], t[1], t[2]));
                g.shading.push(TriangleShading {
                    normals: [Vec3::Y; 3],
                    uvs: [Vec2::ZERO; 3],
                    material: 0,
                    prim: 100,
                    masked: false,
                    attributes: crate::geom::NO_ATTRIBUTES,
                });
            }
        }
        g
    }

    /// `n` queries from random points inside the box towards random directions, a few of
    /// them along the axes (negative zeros included).
    pub fn queries(seed: u32, n: u32, spread: f32) -> Vec<DepthQuery> {
        let r = |i, d| r(seed ^ 0x5eed, i, d);
        (0..n)
            .map(|i| {
                let origin = Vec3::new(r(i, 0) - 0.5, r(i, 1) - 0.5, r(i, 2) - 0.5) * spread;
                let dir = if i % 97 == 0 {
                    [Vec3::X, -Vec3::Y, Vec3::new(-0.0, -0.0, -1.0)][(i / 97 % 3) as usize]
                } else {
                    let z = 2.0 * r(i, 3) - 1.0;
                    let phi = 2.0 * std::f32::consts::PI * r(i, 4);
                    let s = (1.0 - z * z).max(0.0).sqrt();
                    Vec3::new(s * phi.cos(), s * phi.sin(), z)
                };
                DepthQuery { origin, dir }
            })
            .collect()
    }

    /// `n` queries leaving the floor of `closed_box(half)` (y = −half) into the box, from
    /// random points offset off it as the renderer offsets its rays (with a hit point's
    /// error bound, γ(7) of each coordinate): the glossy floor's depth maps.
    pub fn queries_from_floor(seed: u32, n: u32, half: f32) -> Vec<DepthQuery> {
        let r = |i, d| r(seed ^ 0xf1002, i, d);
        (0..n)
            .map(|i| {
                let p = Vec3::new(
                    (2.0 * r(i, 0) - 1.0) * 0.9 * half,
                    -half,
                    (2.0 * r(i, 1) - 1.0) * 0.9 * half,
                );
                let y = r(i, 2).max(1e-3);
                let phi = 2.0 * std::f32::consts::PI * r(i, 3);
                let s = (1.0 - y * y).max(0.0).sqrt();
                let dir = Vec3::new(s * phi.cos(), y, s * phi.sin());
                let error = p.abs() * crate::accel::gamma(7);
                let origin = crate::accel::offset_ray_origin(p, error, Vec3::Y, dir);
                DepthQuery { origin, dir }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::testing::*;
    use super::*;
    use crate::accel::Accel;

    /// The CPU implementation is the per-query trace, in the queries' order, for any
    /// number of threads.
    #[test]
    fn cpu_depth_maps_are_the_closest_hits_in_order() {
        let statics = closed_box(4.0);
        let dynamic = soup(3, 300, 4.0, 0.8);
        let frame = frame(statics, dynamic);
        let qs = queries(3, 3000, 4.0);
        let out = CpuDepthMaps.closest(&frame, &qs).unwrap();
        let accel = Accel::build(&frame.static_geometry, &frame.dynamic_geometry);
        let mut hits = 0;
        for (q, h) in qs.iter().zip(&out) {
            let want = accel.closest(
                &frame.static_geometry,
                &frame.dynamic_geometry,
                q.origin,
                q.dir,
                f32::INFINITY,
            );
            assert_eq!(*h, want);
            hits += h.is_some() as usize;
        }
        // Inside a closed box every ray hits something.
        assert_eq!(hits, qs.len());
    }
}
