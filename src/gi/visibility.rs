//! Which strata of a static cache record may see a dynamic prim this frame (the paper's
//! §3.2). The paper rasterises dynamic objects onto a hemisphere map per cache on the GPU;
//! [`Visibility`] is the interface such an implementation fills, and [`CpuVisibility`] is
//! the reference implementation on the CPU.
//!
//! The contract is conservative: a stratum is flagged if any direction inside it (not only
//! its centre) may meet a dynamic prim. The CPU version bounds each dynamic prim by a sphere
//! and each stratum by a cone around its centre direction, and flags the stratum when the
//! two cones overlap: no stratum that meets a dynamic prim can be missed (tested).

use glam::Vec3;

use super::photons::basis;
use crate::scene::Geometry;

/// A bounding sphere of one dynamic prim.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bound {
    pub centre: Vec3,
    pub radius: f32,
}

/// Bounding spheres of the dynamic prims (one per glTF node) of a frame.
pub fn dynamic_bounds(g: &Geometry) -> Vec<Bound> {
    let mut boxes: std::collections::BTreeMap<u32, (Vec3, Vec3)> =
        std::collections::BTreeMap::new();
    for (t, s) in g.triangles.iter().zip(&g.shading) {
        let e = boxes
            .entry(s.prim)
            .or_insert((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)));
        for v in [t.v0, t.v1, t.v2] {
            e.0 = e.0.min(v.into());
            e.1 = e.1.max(v.into());
        }
    }
    boxes
        .values()
        .map(|&(lo, hi)| {
            let centre = 0.5 * (lo + hi);
            // Pad by a relative epsilon so that rounding cannot shrink the sphere.
            let radius =
                0.5 * (hi - lo).length() * (1.0 + 1e-5) + centre.abs().max_element() * 1e-6;
            Bound { centre, radius }
        })
        .collect()
}

/// One bit per stratum, index `j·N + k` (θ row j, φ column k), as the gather lays them out.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct StrataBits(pub Vec<u64>);

impl StrataBits {
    pub fn new(n: usize) -> Self {
        StrataBits(vec![0; n.div_ceil(64)])
    }

    pub fn set(&mut self, i: usize) {
        self.0[i / 64] |= 1 << (i % 64);
    }

    pub fn get(&self, i: usize) -> bool {
        self.0.get(i / 64).is_some_and(|w| w >> (i % 64) & 1 == 1)
    }

    pub fn count(&self) -> usize {
        self.0.iter().map(|w| w.count_ones() as usize).sum()
    }
}

/// Flags strata that may see dynamic prims. Implementations must be conservative (module
/// doc) and lay strata out as [`super::cache::stratum_direction`] does.
pub trait Visibility: Sync {
    fn name(&self) -> &'static str;

    /// For each record (position, normal), the strata whose directions may meet a bound.
    fn flag(&self, records: &[(Vec3, Vec3)], strata: [u32; 2], bounds: &[Bound])
    -> Vec<StrataBits>;
}

/// The CPU implementation: cone–cone overlap tests.
pub struct CpuVisibility;

/// θ limits of row j of M cosine-weighted strata: sin²θ from j/M to (j+1)/M.
fn theta_limits(j: u32, m: u32) -> (f32, f32) {
    (
        (j as f32 / m as f32).sqrt().asin(),
        ((j + 1) as f32 / m as f32).min(1.0).sqrt().asin(),
    )
}

impl Visibility for CpuVisibility {
    fn name(&self) -> &'static str {
        "cpu"
    }

    fn flag(
        &self,
        records: &[(Vec3, Vec3)],
        [m, n]: [u32; 2],
        bounds: &[Bound],
    ) -> Vec<StrataBits> {
        use rayon::prelude::*;
        let dphi = 2.0 * std::f32::consts::PI / n as f32;
        // Per row: centre θ and the cone half-angle bounding any cell of the row:
        // |θ − θc| ≤ Δθ/2 along the meridian, then ≤ sin θ+ · Δφ/2 along the parallel.
        let rows: Vec<(f32, f32)> = (0..m)
            .map(|j| {
                let (t0, t1) = theta_limits(j, m);
                (0.5 * (t0 + t1), 0.5 * (t1 - t0) + t1.sin() * 0.5 * dphi)
            })
            .collect();
        records
            .par_iter()
            .map(|&(x, normal)| {
                let mut bits = StrataBits::new((m * n) as usize);
                let (t, b) = basis(normal);
                for bound in bounds {
                    let v = bound.centre - x;
                    let d = v.length();
                    if d <= bound.radius {
                        for i in 0..(m * n) as usize {
                            bits.set(i);
                        }
                        continue;
                    }
                    let axis = v / d;
                    let alpha = (bound.radius / d).min(1.0).asin();
                    // Entirely below the horizon: no stratum can see it.
                    if axis.dot(normal) < -alpha.sin() {
                        continue;
                    }
                    for (j, &(theta, beta)) in rows.iter().enumerate() {
                        let (st, ct) = theta.sin_cos();
                        for k in 0..n {
                            let phi = (k as f32 + 0.5) * dphi;
                            let dir = t * (st * phi.cos()) + b * (st * phi.sin()) + normal * ct;
                            let angle = dir.dot(axis).clamp(-1.0, 1.0).acos();
                            if angle <= alpha + beta + 1e-4 {
                                bits.set(j * n as usize + k as usize);
                            }
                        }
                    }
                }
                bits
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::Accel;
    use crate::scene::TriangleShading;
    use crate::scene::frame::triangle;
    use glam::Vec2;

    /// Random dynamic triangles around random records: every direction inside a stratum
    /// that hits a triangle lies in a flagged stratum.
    #[test]
    fn cpu_visibility_is_conservative() {
        let [m, n] = [8u32, 24u32];
        let r = |i: u32, d: u32| crate::sampling::hash(&[i, d]) as f32 / u32::MAX as f32;
        let mut g = Geometry::default();
        for i in 0..6u32 {
            let c = Vec3::new(
                r(i, 0) * 4.0 - 2.0,
                r(i, 1) * 2.0 + 0.2,
                r(i, 2) * 4.0 - 2.0,
            );
            let s = 0.2 + r(i, 3);
            let v = |k: u32| {
                c + Vec3::new(r(i, 10 + k) - 0.5, r(i, 20 + k) - 0.5, r(i, 30 + k) - 0.5) * s
            };
            g.triangles.push(triangle(v(0), v(1), v(2)));
            g.shading.push(TriangleShading {
                normals: [Vec3::Y; 3],
                uvs: [Vec2::ZERO; 3],
                material: 0,
                prim: i,
            });
        }
        let empty = Geometry::default();
        let accel = Accel::build(&empty, &g);
        let bounds = dynamic_bounds(&g);
        let records: Vec<(Vec3, Vec3)> = (0..20u32)
            .map(|i| {
                let nrm = Vec3::new(r(i, 40) - 0.5, 1.0, r(i, 41) - 0.5).normalize();
                (
                    Vec3::new(r(i, 42) * 4.0 - 2.0, 0.0, r(i, 43) * 4.0 - 2.0),
                    nrm,
                )
            })
            .collect();
        let flags = CpuVisibility.flag(&records, [m, n], &bounds);
        let mut hits = 0;
        for (ri, &(x, nrm)) in records.iter().enumerate() {
            let (t, b) = basis(nrm);
            for j in 0..m {
                let (t0, t1) = theta_limits(j, m);
                for k in 0..n {
                    for s in 0..64u32 {
                        // Anywhere in the cell, corners included.
                        let u = if s < 4 {
                            (s & 1) as f32
                        } else {
                            r(s, 50 + j * n + k)
                        };
                        let v = if s < 4 {
                            (s >> 1) as f32
                        } else {
                            r(s, 90_000 + j * n + k)
                        };
                        let theta = t0 + (t1 - t0) * u;
                        let phi = (k as f32 + v) / n as f32 * 2.0 * std::f32::consts::PI;
                        let dir = t * (theta.sin() * phi.cos())
                            + b * (theta.sin() * phi.sin())
                            + nrm * theta.cos();
                        if accel.closest(&empty, &g, x, dir, f32::INFINITY).is_some() {
                            hits += 1;
                            assert!(
                                flags[ri].get((j * n + k) as usize),
                                "record {ri}, stratum ({j},{k}) sees a dynamic triangle but is not flagged"
                            );
                        }
                    }
                }
            }
        }
        assert!(hits > 100, "the test must exercise hits ({hits})");
        // And it is not trivially conservative: most strata stay unflagged.
        let flagged: usize = flags.iter().map(StrataBits::count).sum();
        assert!(
            flagged < records.len() * (m * n) as usize / 2,
            "{flagged} flagged"
        );
    }
}
