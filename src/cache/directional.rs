//! The direction light arrives from at a record, for glossy lobes lit from the cache.
//!
//! A record's irradiance E lights a glossy lobe exactly only where the incident radiance is
//! uniform: shading multiplies E/π by the lobe's directional albedo ([`crate::bsdf`]). A
//! rough lobe (roughness at or above `glossy_max_roughness`, the cache's share of §5) still
//! reflects mostly what arrives around the mirror direction, so where the light is
//! one-sided — a coloured wall beside a brushed-metal floor — the albedo reads too much or
//! too little of it: on a metal sheet of roughness 0.7 beside a red panel, per-tile errors
//! of the indirect light against the path tracer up to 28–32 % (15 % with the fit; test
//! `glossy::a_rough_metal_sheet_reflects_the_side_its_light_comes_from`). At roughness 1
//! (α = 1, a GGX lobe that hardly depends on direction) the two agree within 1 %.
//!
//! Each record therefore also keeps a quadratic fit of its incident radiance over the
//! hemisphere, `L(ω) ≈ a + b·ω + ωᵀQω` per colour channel: the span of the spherical
//! harmonics up to band 2 (enough for a lobe this broad; Ramamoorthi & Hanrahan 2001 show it
//! holds irradiance to within a few per cent), a low-order radiance cache in the sense of
//! Křivánek et al. 2005 ("Radiance caching for efficient global illumination computation").
//! It is fitted by least squares, weighted by solid angle, to the strata's radiance, each
//! stratum at the centre of its cell — the strata are the record's hemisphere in every
//! method (brute force re-gathers them, anchors read them from their anchors), so the fit
//! follows the record whenever it changes. The weights depend only on the strata's layout,
//! so the fit is one matrix per layout and a product per record. Kept in world axes, fits
//! of neighbouring records blend with the interpolation's weights like their irradiance.
//!
//! Shading integrates the lobe against the fit through the lobe's moments
//! `∫ f cos θi · {1, x, z, xz, x², y², z²} dωi` in the frame of the outgoing direction
//! ([`crate::bsdf::Tables::glossy_moments`]): ten numbers per channel per record, a few dozen
//! multiplications per sample. Under uniform light the fit is its constant term and the
//! result is the directional albedo's, as before. No crate fits or evaluates this; it is
//! small enough to write here.

use std::cell::RefCell;
use std::f64::consts::PI;
use std::rc::Rc;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::bsdf::Bsdf;
use crate::geom::basis;

/// Basis functions of the fit in the record's frame (x, y along its tangents, z its normal):
/// `[1, x, y, z, xy, yz, xz, x², y²]` (z² = 1 − x² − y² on the sphere).
const TERMS: usize = 9;

/// A record's incident radiance as `a + b·ω + ωᵀQω` per channel, in world axes:
/// `[a, b.x, b.y, b.z, Q.xx, Q.yy, Q.zz, Q.xy, Q.xz, Q.yz]` for R, G and B.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Directional(pub [[f32; 10]; 3]);

/// The fit's weights: per stratum, its contribution to each local coefficient.
type FitMatrix = Vec<[f32; TERMS]>;

/// A strata layout and its fit matrix (`None`: too coarse to fit).
type LayoutFit = ([u32; 2], Rc<Option<FitMatrix>>);

thread_local! {
    /// The fit matrix of the last strata layout this thread fitted (a job has one).
    static FIT: RefCell<Option<LayoutFit>> = const { RefCell::new(None) };
}

fn terms(x: f64, y: f64, z: f64) -> [f64; TERMS] {
    [1.0, x, y, z, x * y, y * z, x * z, x * x, y * y]
}

/// Direction of stratum (j, k) with jitter (u, v): cosine-weighted, θ from j, φ from k.
pub(super) fn stratum_direction(m: u32, n: u32, j: u32, k: u32, u: f32, v: f32) -> (f32, f32) {
    let sin2 = (j as f32 + u) / m as f32;
    let phi = 2.0 * std::f32::consts::PI * (k as f32 + v) / n as f32;
    (sin2, phi)
}

/// The weighted least-squares fit matrix for `m × n` cosine-weighted strata, each at its
/// centre ([`stratum_direction`], in `cache::gather`'s order), or `None` where the strata are
/// too few to determine nine coefficients.
fn fit_matrix(m: u32, n: u32) -> Option<FitMatrix> {
    let cell = PI / (m as f64 * n as f64);
    let rows: Vec<([f64; TERMS], f64)> = (0..m * n)
        .map(|s| {
            let (sin2, phi) = stratum_direction(m, n, s / n, s % n, 0.5, 0.5);
            let (sin2, phi) = (sin2 as f64, phi as f64);
            let (st, z) = (sin2.sqrt(), (1.0 - sin2).sqrt());
            // A stratum's solid angle: its share of the cosine-weighted hemisphere over cos θ.
            (terms(st * phi.cos(), st * phi.sin(), z), cell / z)
        })
        .collect();
    let mut g = [[0.0f64; TERMS]; TERMS];
    for (p, w) in &rows {
        for i in 0..TERMS {
            for j in 0..TERMS {
                g[i][j] += w * p[i] * p[j];
            }
        }
    }
    let inv = invert(g)?;
    Some(
        rows.iter()
            .map(|(p, w)| {
                std::array::from_fn(|i| {
                    (0..TERMS).map(|j| inv[i][j] * p[j] * w).sum::<f64>() as f32
                })
            })
            .collect(),
    )
}

/// Gauss-Jordan inversion with partial pivoting; `None` if `g` is (nearly) singular.
fn invert(mut g: [[f64; TERMS]; TERMS]) -> Option<[[f64; TERMS]; TERMS]> {
    let mut inv = [[0.0f64; TERMS]; TERMS];
    for (i, row) in inv.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    let scale = (0..TERMS).map(|i| g[i][i].abs()).fold(0.0, f64::max);
    for c in 0..TERMS {
        let p = (c..TERMS).max_by(|&a, &b| g[a][c].abs().total_cmp(&g[b][c].abs()))?;
        if !(g[p][c].abs() > 1e-9 * scale) {
            return None;
        }
        g.swap(c, p);
        inv.swap(c, p);
        let d = g[c][c];
        for j in 0..TERMS {
            g[c][j] /= d;
            inv[c][j] /= d;
        }
        for r in 0..TERMS {
            if r != c {
                let f = g[r][c];
                for j in 0..TERMS {
                    g[r][j] -= f * g[c][j];
                    inv[r][j] -= f * inv[c][j];
                }
            }
        }
    }
    Some(inv)
}

fn with_fit_matrix<R>(strata: [u32; 2], f: impl FnOnce(Option<&FitMatrix>) -> R) -> R {
    let matrix = FIT.with(|cell| {
        let mut cell = cell.borrow_mut();
        match &*cell {
            Some((s, m)) if *s == strata => m.clone(),
            _ => {
                let m = Rc::new(fit_matrix(strata[0], strata[1]));
                *cell = Some((strata, m.clone()));
                m
            }
        }
    });
    f(matrix.as_ref().as_ref())
}

impl Directional {
    /// The fit to the radiance `radiance` of a record's strata (layout `strata`) around
    /// the shading normal `ns` they were traced about; `None` for layouts too coarse to fit.
    pub fn fit(ns: Vec3, radiance: &[Vec3], strata: [u32; 2]) -> Option<Directional> {
        with_fit_matrix(strata, |m| {
            let m = m?;
            if m.len() != radiance.len() {
                return None;
            }
            let mut c = [[0.0f32; TERMS]; 3];
            for (w, l) in m.iter().zip(radiance) {
                for (ch, cc) in c.iter_mut().enumerate() {
                    for (ci, wi) in cc.iter_mut().zip(w) {
                        *ci += wi * l[ch];
                    }
                }
            }
            let (t, b) = basis(ns);
            let n = ns;
            Some(Directional(c.map(|c| to_world(&c, t, b, n))))
        })
    }

    /// `self + w·other`.
    pub fn add_scaled(&mut self, other: &Directional, w: f32) {
        for (a, b) in self.0.iter_mut().zip(&other.0) {
            for (x, y) in a.iter_mut().zip(b) {
                *x += w * y;
            }
        }
    }

    pub fn scaled(mut self, s: f32) -> Directional {
        for c in &mut self.0 {
            for x in c {
                *x *= s;
            }
        }
        self
    }

    /// The radiance the glossy lobe of `bsdf` reflects towards `wo` (shading normal `ns`)
    /// under this incident light: ∫ f_glossy cos θi L(ωi) dωi, never negative.
    pub fn glossy(&self, bsdf: &Bsdf, ns: Vec3, wo: Vec3) -> Vec3 {
        let mu = ns.dot(wo);
        if !(mu > 0.0) || !bsdf.has_glossy() {
            return Vec3::ZERO;
        }
        let along = wo - ns * mu;
        let len = along.length();
        let x = if len > 1e-6 { along / len } else { basis(ns).0 };
        let y = ns.cross(x);
        let [ma, mb] = crate::bsdf::tables().glossy_moments(mu, bsdf.roughness);
        let out = Vec3::from_array(std::array::from_fn(|ch| {
            let c = &self.0[ch];
            let b = Vec3::new(c[1], c[2], c[3]);
            let q = |v: Vec3| {
                Vec3::new(
                    c[4] * v.x + c[7] * v.y + c[8] * v.z,
                    c[7] * v.x + c[5] * v.y + c[9] * v.z,
                    c[8] * v.x + c[9] * v.y + c[6] * v.z,
                )
            };
            let (qx, qy, qn) = (q(x), q(y), q(ns));
            let parts = [
                c[0],
                b.dot(x),
                b.dot(ns),
                2.0 * x.dot(qn),
                x.dot(qx),
                y.dot(qy),
                ns.dot(qn),
            ];
            let contract = |m: &[f32; 7]| m.iter().zip(&parts).map(|(m, p)| m * p).sum::<f32>();
            bsdf.f0[ch] * contract(&ma) + bsdf.f90[ch] * contract(&mb)
        }));
        out.max(Vec3::ZERO)
    }
}

/// Local coefficients (basis [`terms`] in the frame `t, b, n`) as world-axis
/// `[a, b, Q]` ([`Directional`]).
fn to_world(c: &[f32; TERMS], t: Vec3, b: Vec3, n: Vec3) -> [f32; 10] {
    let lin = t * c[1] + b * c[2] + n * c[3];
    // Q = c4·sym(t, b) + c5·sym(b, n) + c6·sym(t, n) + c7·t tᵀ + c8·b bᵀ, sym(u, v) =
    // (u vᵀ + v uᵀ)/2, so that ωᵀQω = c4·xy + c5·yz + c6·xz + c7·x² + c8·y².
    let q = |i: usize, j: usize| {
        0.5 * c[4] * (t[i] * b[j] + b[i] * t[j])
            + 0.5 * c[5] * (b[i] * n[j] + n[i] * b[j])
            + 0.5 * c[6] * (t[i] * n[j] + n[i] * t[j])
            + c[7] * t[i] * t[j]
            + c[8] * b[i] * b[j]
    };
    [
        c[0],
        lin.x,
        lin.y,
        lin.z,
        q(0, 0),
        q(1, 1),
        q(2, 2),
        q(0, 1),
        q(0, 2),
        q(1, 2),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::cosine_direction;

    /// Radiance of the strata of a record at normal `n` from `l(ω)`, at the strata centres.
    fn strata_radiance(n: Vec3, m: u32, k: u32, l: impl Fn(Vec3) -> Vec3) -> Vec<Vec3> {
        (0..m * k)
            .map(|s| {
                let (j, i) = (s / k, s % k);
                let u = (j as f32 + 0.5) / m as f32;
                let v = (i as f32 + 0.5) / k as f32;
                l(cosine_direction(n, u, v))
            })
            .collect()
    }

    /// A quadratic radiance is fitted exactly, whatever the normal.
    #[test]
    fn a_quadratic_radiance_is_fitted_exactly() {
        let f = |w: Vec3| {
            Vec3::new(
                1.0 + 0.5 * w.x - 0.3 * w.z + 0.7 * w.x * w.y,
                0.2 + w.y * w.y,
                2.0 - w.z * w.x + 0.4 * w.y,
            )
        };
        for n in [Vec3::Z, Vec3::NEG_Y, Vec3::new(0.3, -0.5, 0.8).normalize()] {
            let d = Directional::fit(n, &strata_radiance(n, 12, 36, f), [12, 36]).unwrap();
            for (u, v) in [(0.1, 0.2), (0.5, 0.9), (0.95, 0.4)] {
                let w = cosine_direction(n, u, v);
                let e = f(w);
                let got = Vec3::from_array(std::array::from_fn(|ch| {
                    let c = &d.0[ch];
                    let q = c[4] * w.x * w.x
                        + c[5] * w.y * w.y
                        + c[6] * w.z * w.z
                        + 2.0 * (c[7] * w.x * w.y + c[8] * w.x * w.z + c[9] * w.y * w.z);
                    c[0] + c[1] * w.x + c[2] * w.y + c[3] * w.z + q
                }));
                assert!(
                    (got - e).abs().max_element() < 1e-3,
                    "{n} {w}: {got} vs {e}"
                );
            }
        }
    }

    /// Under uniform radiance the lobe reflects its directional albedo times it; under light
    /// from one side it reflects more towards the other (the mirror direction), which the
    /// albedo cannot tell apart.
    #[test]
    fn the_lobe_reads_the_side_the_light_comes_from() {
        let n = Vec3::Y;
        let bsdf = Bsdf::new(Vec3::splat(0.9), 1.0, 0.7, 1.0);
        let uniform = Directional::fit(n, &vec![Vec3::ONE; 432], [12, 36]).unwrap();
        for mu in [0.2f32, 0.6, 0.95] {
            let wo = Vec3::new((1.0 - mu * mu).sqrt(), mu, 0.0);
            let got = uniform.glossy(&bsdf, n, wo);
            let want = bsdf.albedo(mu).glossy;
            assert!(
                (got - want).abs().max_element() < 0.01,
                "{mu}: {got} vs {want}"
            );
        }
        // Light from the −x half only: a view from +x (mirror direction towards −x) reads
        // more than the albedo's share, a view from −x less.
        let half = |w: Vec3| if w.x < 0.0 { Vec3::ONE } else { Vec3::ZERO };
        let d = Directional::fit(n, &strata_radiance(n, 12, 36, half), [12, 36]).unwrap();
        let mu = 0.4f32;
        let from = |s: f32| Vec3::new(s * (1.0 - mu * mu).sqrt(), mu, 0.0);
        let albedo = 0.5 * bsdf.albedo(mu).glossy.x;
        let (facing, away) = (
            d.glossy(&bsdf, n, from(1.0)).x,
            d.glossy(&bsdf, n, from(-1.0)).x,
        );
        assert!(
            facing > 1.2 * albedo && away < 0.8 * albedo,
            "{facing} {away} {albedo}"
        );
    }

    #[test]
    fn too_few_strata_give_no_fit() {
        assert!(Directional::fit(Vec3::Z, &[Vec3::ONE; 4], [2, 2]).is_none());
        assert!(Directional::fit(Vec3::Z, &[Vec3::ONE; 12], [2, 6]).is_none());
    }
}
