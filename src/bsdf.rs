//! The glTF 2.0 metallic-roughness BRDF (glTF 2.0 specification, Appendix B), the one
//! reflection model every method shades with.
//!
//! ```text
//! f = (1 − m)·(1 − F_d)·c/π + [(1 − m)·F_d + m·F_m] · D·V
//! F_d = s·(0.04 + 0.96·(1 − |v·h|)⁵)          dielectric Fresnel (ior 1.5)
//! F_m = c + (1 − c)·(1 − |v·h|)⁵               conductor Fresnel, F0 = base colour
//! D   = α² / (π·((n·h)²(α² − 1) + 1)²)         Trowbridge-Reitz (GGX), α = roughness²
//! V   = ½ / (n·l·√((n·v)²(1 − α²) + α²) + n·v·√((n·l)²(1 − α²) + α²))   Smith, height-correlated
//! ```
//!
//! with `c` the base colour, `m` metallic and `s` the dielectric specular factor of
//! `KHR_materials_specular` (1 without it; 0 makes the dielectric a pure Lambertian). The
//! specular Fresnel terms merge into one Schlick term `F = f0 + (f90 − f0)(1 − |v·h|)⁵`
//! with `f0 = (1 − m)·0.04·s + m·c` and `f90 = (1 − m)·s + m`; [`Lobes`] keeps the diffuse
//! and glossy parts apart because the renderer routes them differently (paper §5, §7: the
//! diffuse part through the irradiance cache, the glossy part by gathering at the pixel).
//!
//! Sampling picks the diffuse lobe (cosine-weighted) or the glossy one (the GGX distribution
//! of visible normals, Heitz 2018) in proportion to their directional albedos, read from
//! tables this module integrates once ([`Tables`]). The same tables give the directional
//! albedo used where the irradiance cache stands in for the incident light: that is exact
//! for uniform incident light and an approximation otherwise.
//!
//! Single-scattering GGX loses energy at high roughness (light that would bounce between
//! microfacets is dropped): a white metal at roughness 1 reflects 1 − ln 2 ≈ 0.31 of the
//! light at normal incidence, 0.99 at roughness 0.1. The diffuse layer of a dielectric takes
//! the light its glossy layer does not reflect by albedo scaling (Kelemen & Szirmay-Kalos
//! 2001): `f_d = c_diff/π · (1 − s·E(n·wo))(1 − s·E(n·wi)) / (1 − s·Ē)` with `E` the
//! directional albedo of the dielectric's glossy layer and `Ē` its cosine-weighted mean.
//! This replaces the Appendix's per-half-vector `(1 − F(v·h))` weight, which is not
//! reciprocal-energy-safe: a white dielectric at roughness 0.05 reflects 1.016 of the light
//! at 57° with it. With the scaling a white dielectric reflects exactly what arrives, and it
//! stays reciprocal.
//! Roughness is clamped below at [`MIN_ROUGHNESS`]: a perfect mirror is rendered as a very
//! sharp GGX lobe, which keeps every term finite in f32.

use std::f32::consts::{FRAC_1_PI, PI};
use std::sync::OnceLock;

use glam::Vec3;

use crate::color::luminance;
use crate::geom::basis;

/// Smallest roughness (glTF `roughnessFactor`) rendered: α = 1e-3.
pub const MIN_ROUGHNESS: f32 = 0.031_622_78;

/// The roughness from which the cached methods light a glossy lobe from the irradiance
/// cache through its directional albedo, by default (`method.glossy_max_roughness`).
pub const CACHE_LIT_ROUGHNESS: f32 = 0.6;

/// Reflectance of a dielectric of ior 1.5 at normal incidence, the glTF default.
const DIELECTRIC_F0: f32 = 0.04;

/// A BRDF value (or a reflectance) split into its diffuse and glossy lobes.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Lobes {
    pub diffuse: Vec3,
    pub glossy: Vec3,
}

impl Lobes {
    pub const ZERO: Lobes = Lobes {
        diffuse: Vec3::ZERO,
        glossy: Vec3::ZERO,
    };

    pub fn sum(&self) -> Vec3 {
        self.diffuse + self.glossy
    }

    pub fn scale(self, s: Vec3) -> Lobes {
        Lobes {
            diffuse: self.diffuse * s,
            glossy: self.glossy * s,
        }
    }
}

impl std::ops::Add for Lobes {
    type Output = Lobes;
    fn add(self, o: Lobes) -> Lobes {
        Lobes {
            diffuse: self.diffuse + o.diffuse,
            glossy: self.glossy + o.glossy,
        }
    }
}

impl std::ops::AddAssign for Lobes {
    fn add_assign(&mut self, o: Lobes) {
        *self = *self + o;
    }
}

/// A direction sampled from the BRDF.
#[derive(Debug, Clone, Copy)]
pub struct BsdfSample {
    pub wi: Vec3,
    /// The BRDF at `wi`, both lobes.
    pub f: Lobes,
    /// Probability density of `wi` (solid angle) under the mixture of both lobes.
    pub pdf: f32,
    /// Whether the glossy lobe drew it.
    pub glossy: bool,
}

/// The BRDF at one surface point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bsdf {
    /// `(1 − metallic) × base colour`: the Lambertian layer's colour before Fresnel.
    pub c_diff: Vec3,
    /// Dielectric specular factor (`KHR_materials_specular.specularFactor`).
    pub specular: f32,
    pub f0: Vec3,
    pub f90: Vec3,
    /// GGX α = roughness².
    pub alpha: f32,
    pub roughness: f32,
}

impl Bsdf {
    /// The BRDF of base colour `base` (linear, clamped to [0, 1]), `metallic`, `roughness`
    /// and dielectric specular factor `specular`, as glTF defines them (all clamped to
    /// [0, 1]).
    pub fn new(base: Vec3, metallic: f32, roughness: f32, specular: f32) -> Self {
        let c = base.clamp(Vec3::ZERO, Vec3::ONE);
        let m = if metallic.is_finite() {
            metallic.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let s = if specular.is_finite() {
            specular.clamp(0.0, 1.0)
        } else {
            1.0
        };
        let r = if roughness.is_finite() {
            roughness.clamp(MIN_ROUGHNESS, 1.0)
        } else {
            1.0
        };
        Bsdf {
            c_diff: c * (1.0 - m),
            specular: s,
            f0: Vec3::splat((1.0 - m) * DIELECTRIC_F0 * s) + c * m,
            f90: Vec3::splat((1.0 - m) * s + m),
            alpha: r * r,
            roughness: r,
        }
    }

    /// A pure Lambertian of albedo `c` (specular factor 0).
    pub fn lambertian(c: Vec3) -> Self {
        Bsdf::new(c, 0.0, 1.0, 0.0)
    }

    /// Whether the glossy lobe reflects anything.
    pub fn has_glossy(&self) -> bool {
        self.f90.max_element() > 0.0
    }

    /// The BRDF for light arriving from `wi` and leaving towards `wo`, both unit vectors on
    /// the side of the shading normal `n` (zero otherwise).
    pub fn eval(&self, n: Vec3, wo: Vec3, wi: Vec3) -> Lobes {
        let (no, ni) = (n.dot(wo), n.dot(wi));
        if !(no > 0.0 && ni > 0.0) {
            return Lobes::ZERO;
        }
        let h = (wo + wi).normalize_or_zero();
        if h == Vec3::ZERO {
            return Lobes::ZERO;
        }
        let x = schlick_weight(wo.dot(h));
        let diffuse = if self.c_diff == Vec3::ZERO {
            Vec3::ZERO
        } else if self.specular == 0.0 {
            // A pure Lambertian: no glossy layer takes any light.
            self.c_diff * FRAC_1_PI
        } else {
            let t = tables();
            let lost = |mu: f32| 1.0 - self.specular * t.dielectric(mu, self.roughness);
            let mean = 1.0 - self.specular * t.mean_dielectric(self.roughness);
            self.c_diff * (lost(no) * lost(ni) / mean * FRAC_1_PI)
        };
        let glossy = if self.has_glossy() {
            let f = self.f0 + (self.f90 - self.f0) * x;
            f * (ggx_d(n.dot(h), self.alpha) * smith_v(no, ni, self.alpha))
        } else {
            Vec3::ZERO
        };
        Lobes { diffuse, glossy }
    }

    /// Probability of choosing the glossy lobe when sampling towards `wo` with `n·wo = cos_o`.
    fn glossy_probability(&self, cos_o: f32) -> f32 {
        let a = self.albedo(cos_o);
        let (d, g) = (luminance(a.diffuse), luminance(a.glossy));
        if !(d + g > 0.0) {
            return 0.0;
        }
        g / (d + g)
    }

    /// Density of sampling `wi` given `wo` ([`Bsdf::sample`]).
    pub fn pdf(&self, n: Vec3, wo: Vec3, wi: Vec3) -> f32 {
        let (no, ni) = (n.dot(wo), n.dot(wi));
        if !(no > 0.0 && ni > 0.0) {
            return 0.0;
        }
        let pg = self.glossy_probability(no);
        let mut pdf = (1.0 - pg) * ni * FRAC_1_PI;
        if pg > 0.0 {
            pdf += pg * self.vndf_pdf(n, wo, wi, no);
        }
        pdf
    }

    /// Density of the visible-normal sampling of the glossy lobe: D(h)·G1(wo)/(4 n·wo).
    fn vndf_pdf(&self, n: Vec3, wo: Vec3, wi: Vec3, no: f32) -> f32 {
        let h = (wo + wi).normalize_or_zero();
        if h == Vec3::ZERO {
            return 0.0;
        }
        ggx_d(n.dot(h), self.alpha) * smith_g1(no, self.alpha) / (4.0 * no)
    }

    /// Samples an incident direction for light leaving towards `wo` from three uniform
    /// numbers (`u[0]` picks the lobe). `None` where nothing is reflected or the sampled
    /// direction falls below the surface.
    pub fn sample(&self, n: Vec3, wo: Vec3, u: [f32; 3]) -> Option<BsdfSample> {
        let no = n.dot(wo);
        if !(no > 0.0) {
            return None;
        }
        let pg = self.glossy_probability(no);
        let a = self.albedo(no);
        if a.sum().max_element() <= 0.0 {
            return None;
        }
        let glossy = u[0] < pg;
        let (t, b) = basis(n);
        let wi = if glossy {
            let local = Vec3::new(wo.dot(t), wo.dot(b), no);
            let m = sample_vndf(local, self.alpha, u[1], u[2]);
            let m = t * m.x + b * m.y + n * m.z;
            (m * (2.0 * wo.dot(m)) - wo).normalize_or_zero()
        } else {
            crate::geom::cosine_direction(n, u[1].min(0.999_999_9), u[2])
        };
        let pdf = self.pdf(n, wo, wi);
        if !(pdf > 0.0) || !pdf.is_finite() {
            return None;
        }
        Some(BsdfSample {
            wi,
            f: self.eval(n, wo, wi),
            pdf,
            glossy,
        })
    }

    /// Samples the glossy lobe alone (its visible normals): the direction, the glossy BRDF
    /// there and the density. `None` without a glossy lobe or below the surface.
    pub fn sample_glossy(&self, n: Vec3, wo: Vec3, u: [f32; 2]) -> Option<(Vec3, Vec3, f32)> {
        let no = n.dot(wo);
        if !(no > 0.0) || !self.has_glossy() {
            return None;
        }
        let (t, b) = basis(n);
        let local = Vec3::new(wo.dot(t), wo.dot(b), no);
        let m = sample_vndf(local, self.alpha, u[0], u[1]);
        let m = t * m.x + b * m.y + n * m.z;
        let wi = (m * (2.0 * wo.dot(m)) - wo).normalize_or_zero();
        if !(n.dot(wi) > 0.0) {
            return None;
        }
        let pdf = self.vndf_pdf(n, wo, wi, no);
        let f = self.eval(n, wo, wi).glossy;
        (pdf > 0.0 && pdf.is_finite()).then_some((wi, f, pdf))
    }

    /// Directional albedo for light leaving towards `wo` with `n·wo = cos_o`: the fraction
    /// of uniform incident radiance each lobe reflects (∫ f cos θi dωi).
    pub fn albedo(&self, cos_o: f32) -> Lobes {
        let t = tables();
        let mu = cos_o.clamp(0.0, 1.0);
        let (a, b) = t.specular(mu, self.roughness);
        Lobes {
            diffuse: self.c_diff * (1.0 - self.specular * (DIELECTRIC_F0 * a + b)),
            glossy: self.f0 * a + self.f90 * b,
        }
    }

    /// Hemispherical albedo: [`Bsdf::albedo`] averaged over cosine-weighted outgoing
    /// directions, the reflectance the photon map and the gather hits use.
    pub fn hemispherical_albedo(&self) -> Lobes {
        let t = tables();
        let (a, b) = t.mean_specular(self.roughness);
        Lobes {
            diffuse: self.c_diff * (1.0 - self.specular * (DIELECTRIC_F0 * a + b)),
            glossy: self.f0 * a + self.f90 * b,
        }
    }
}

/// `(1 − |cos|)⁵`, the Schlick weight.
#[inline]
fn schlick_weight(cos: f32) -> f32 {
    let m = (1.0 - cos.abs()).clamp(0.0, 1.0);
    let m2 = m * m;
    m2 * m2 * m
}

/// The Trowbridge-Reitz (GGX) distribution at `n·h = cos_h`.
#[inline]
pub fn ggx_d(cos_h: f32, alpha: f32) -> f32 {
    if !(cos_h > 0.0) {
        return 0.0;
    }
    let a2 = alpha * alpha;
    // (n·h)²(α² − 1) + 1 written as 1 − (n·h)² + (n·h)²α² so that it does not cancel for
    // tiny α at n·h ≈ 1.
    let c2 = cos_h * cos_h;
    let s2 = (1.0 - c2).max(0.0);
    let d = s2 + c2 * a2;
    a2 / (PI * d * d)
}

/// Smith's height-correlated visibility `G₂ / (4 n·l n·v)`.
#[inline]
pub fn smith_v(no: f32, ni: f32, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    let go = ni * (no * no * (1.0 - a2) + a2).sqrt();
    let gi = no * (ni * ni * (1.0 - a2) + a2).sqrt();
    let d = go + gi;
    if d > 0.0 { 0.5 / d } else { 0.0 }
}

/// Smith's masking term for one direction.
#[inline]
fn smith_g1(cos: f32, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    2.0 * cos / (cos + (a2 + (1.0 - a2) * cos * cos).sqrt())
}

/// A GGX visible normal for the local outgoing direction `v` (z up), Heitz 2018, "Sampling
/// the GGX Distribution of Visible Normals".
fn sample_vndf(v: Vec3, alpha: f32, u1: f32, u2: f32) -> Vec3 {
    let vh = Vec3::new(alpha * v.x, alpha * v.y, v.z).normalize();
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 0.0 {
        Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt()
    } else {
        Vec3::X
    };
    let t2 = vh.cross(t1);
    let r = u1.sqrt();
    let phi = 2.0 * PI * u2;
    let p1 = r * phi.cos();
    let s = 0.5 * (1.0 + vh.z);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * phi.sin();
    let nh = t1 * p1 + t2 * p2 + vh * (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(1e-7)).normalize()
}

/// Nodes per axis of the albedo tables.
const TABLE: usize = 48;
/// Stratified samples per axis in each node's integral.
const TABLE_SAMPLES: usize = 32;

/// Directional-albedo tables, integrated once per process (deterministically: stratified
/// midpoints, no random numbers): `A(μ, r) = ∫ (1 − x)·D·V cos θi dωi` and
/// `B(μ, r) = ∫ x·D·V cos θi dωi` (x the Schlick weight) give the glossy lobe's albedo as
/// `f0·A + f90·B` (the split-sum tables of Karis 2013). Rows are `μ = n·wo`, columns
/// roughness, both at `i/(TABLE − 1)` (μ = 0 integrated at a grazing 0.01); look-ups
/// interpolate bilinearly.
pub struct Tables {
    spec: Vec<[f32; 2]>,
    mean_spec: [[f32; 2]; TABLE],
    /// Per node, the glossy lobe's moments ([`Tables::glossy_moments`]) for A and B.
    moments: Vec<[[f32; 7]; 2]>,
}

fn node(i: usize) -> f32 {
    i as f32 / (TABLE - 1) as f32
}

/// Linear interpolation position of `x ∈ [0, 1]` among the nodes: (index, weight).
fn locate(x: f32) -> (usize, f32) {
    let f = (x * (TABLE - 1) as f32).clamp(0.0, (TABLE - 1) as f32);
    let i = (f.floor() as usize).min(TABLE - 2);
    (i, f - i as f32)
}

impl Tables {
    fn build() -> Tables {
        let n = TABLE_SAMPLES;
        let mut spec = vec![[0.0f32; 2]; TABLE * TABLE];
        let mut moments = vec![[[0.0f32; 7]; 2]; TABLE * TABLE];
        for i in 0..TABLE {
            let mu = node(i).max(0.01);
            let wo = Vec3::new((1.0 - mu * mu).sqrt(), 0.0, mu);
            for j in 0..TABLE {
                let r = node(j).max(MIN_ROUGHNESS);
                let alpha = r * r;
                let (mut sa, mut sb) = (0.0f64, 0.0f64);
                let (mut ma, mut mb) = ([0.0f64; 7], [0.0f64; 7]);
                for a in 0..n {
                    for b in 0..n {
                        let (u1, u2) = ((a as f32 + 0.5) / n as f32, (b as f32 + 0.5) / n as f32);
                        let m = sample_vndf(wo, alpha, u1, u2);
                        let wi = m * (2.0 * wo.dot(m)) - wo;
                        if wi.z <= 0.0 {
                            continue;
                        }
                        // f·cos/pdf with pdf = D·G1(wo)/(4 n·wo): the D cancels.
                        let w = smith_v(mu, wi.z, alpha) * wi.z * 4.0 * mu / smith_g1(mu, alpha);
                        let x = schlick_weight(wo.dot(m));
                        sa += ((1.0 - x) * w) as f64;
                        sb += (x * w) as f64;
                        let (dx, dy, dz) = (wi.x as f64, wi.y as f64, wi.z as f64);
                        let p = [1.0, dx, dz, dx * dz, dx * dx, dy * dy, dz * dz];
                        for (k, p) in p.iter().enumerate() {
                            ma[k] += ((1.0 - x) * w) as f64 * p;
                            mb[k] += (x * w) as f64 * p;
                        }
                    }
                }
                let k = (n * n) as f64;
                spec[i * TABLE + j] = [(sa / k) as f32, (sb / k) as f32];
                moments[i * TABLE + j] = [ma.map(|v| (v / k) as f32), mb.map(|v| (v / k) as f32)];
            }
        }
        // Cosine-weighted means over μ: 2∫ g(μ) μ dμ by the trapezoidal rule.
        let h = 1.0 / (TABLE - 1) as f32;
        let weight = |i: usize| {
            let end = if i == 0 || i == TABLE - 1 { 0.5 } else { 1.0 };
            2.0 * node(i) * h * end
        };
        let mut mean_spec = [[0.0; 2]; TABLE];
        for (j, m) in mean_spec.iter_mut().enumerate() {
            for i in 0..TABLE {
                let [a, b] = spec[i * TABLE + j];
                m[0] += a * weight(i);
                m[1] += b * weight(i);
            }
        }
        Tables {
            spec,
            mean_spec,
            moments,
        }
    }

    /// The glossy lobe's moments at `μ`, roughness `r`, in the frame of the outgoing
    /// direction (normal z, `wo` in the xz-plane towards +x): `∫ w·cos θi·p(ωi) dωi` for
    /// `p` in `[1, x, z, xz, x², y², z²]`, with `w = (1 − x_s)·D·V` for A and `x_s·D·V` for B
    /// (`x_s` the Schlick weight), so that the lobe of f0, f90 reflects `f0·(A·c) + f90·(B·c)`
    /// of a radiance `c·p` ([`crate::cache::directional`]). The moments of y, xy and yz
    /// vanish by symmetry. The first entries are `Tables::specular`'s A and B.
    pub fn glossy_moments(&self, mu: f32, roughness: f32) -> [[f32; 7]; 2] {
        let (i, s) = locate(mu);
        let (j, t) = locate(roughness);
        let at = |i: usize, j: usize| &self.moments[i * TABLE + j];
        let w = [
            (at(i, j), (1.0 - s) * (1.0 - t)),
            (at(i, j + 1), (1.0 - s) * t),
            (at(i + 1, j), s * (1.0 - t)),
            (at(i + 1, j + 1), s * t),
        ];
        std::array::from_fn(|l| {
            std::array::from_fn(|k| w.iter().map(|(m, w)| m[l][k] * w).sum::<f32>())
        })
    }

    /// `(A, B)` at `μ`, roughness `r`.
    fn specular(&self, mu: f32, roughness: f32) -> (f32, f32) {
        let (i, s) = locate(mu);
        let (j, t) = locate(roughness);
        let at = |i: usize, j: usize| self.spec[i * TABLE + j];
        let lerp =
            |a: [f32; 2], b: [f32; 2], w: f32| [a[0] + (b[0] - a[0]) * w, a[1] + (b[1] - a[1]) * w];
        let top = lerp(at(i, j), at(i, j + 1), t);
        let bottom = lerp(at(i + 1, j), at(i + 1, j + 1), t);
        let v = lerp(top, bottom, s);
        (v[0], v[1])
    }

    /// `(Ā, B̄)`: the cosine-weighted means over μ at roughness `r`.
    fn mean_specular(&self, roughness: f32) -> (f32, f32) {
        let (j, t) = locate(roughness);
        let (a, b) = (self.mean_spec[j], self.mean_spec[j + 1]);
        (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t)
    }

    /// Directional albedo of a white dielectric's specular layer (f0 0.04, f90 1).
    fn dielectric(&self, mu: f32, roughness: f32) -> f32 {
        let (a, b) = self.specular(mu, roughness);
        DIELECTRIC_F0 * a + b
    }

    /// [`Tables::dielectric`] averaged over cosine-weighted directions.
    fn mean_dielectric(&self, roughness: f32) -> f32 {
        let (a, b) = self.mean_specular(roughness);
        DIELECTRIC_F0 * a + b
    }
}

/// The process's albedo tables.
pub fn tables() -> &'static Tables {
    static T: OnceLock<Tables> = OnceLock::new();
    T.get_or_init(Tables::build)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::Sampler;

    fn dir(theta: f32, phi: f32) -> Vec3 {
        Vec3::new(
            theta.sin() * phi.cos(),
            theta.sin() * phi.sin(),
            theta.cos(),
        )
    }

    /// ∫ f cos θi dωi by BRDF sampling with `n` samples.
    fn sampled_albedo(b: &Bsdf, wo: Vec3, n: u32) -> Lobes {
        let s = Sampler::strata(7);
        let mut sum = Lobes::ZERO;
        for i in 0..n {
            let u = [s.get(i, 0), s.get(i, 1), s.get(i, 2)];
            if let Some(x) = b.sample(Vec3::Z, wo, u) {
                sum += x.f.scale(Vec3::splat(x.wi.z / x.pdf));
            }
        }
        sum.scale(Vec3::splat(1.0 / n as f32))
    }

    /// ∫ f cos θi dωi by uniform hemisphere sampling, independent of the BRDF's sampler.
    fn uniform_albedo(b: &Bsdf, wo: Vec3, n: u32) -> Lobes {
        let s = Sampler::strata(11);
        let mut sum = Lobes::ZERO;
        for i in 0..n {
            let [u1, u2] = s.get2(i, 0);
            let z = u1;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let wi = Vec3::new(r * (2.0 * PI * u2).cos(), r * (2.0 * PI * u2).sin(), z);
            sum += b.eval(Vec3::Z, wo, wi).scale(Vec3::splat(wi.z * 2.0 * PI));
        }
        sum.scale(Vec3::splat(1.0 / n as f32))
    }

    /// White furnace: no roughness, metallic value or angle reflects more than it receives.
    /// The known loss of single-scattering GGX is stated: a white metal reflects 0.99 at
    /// roughness 0.1 and normal incidence, 1 − ln 2 ≈ 0.31 at roughness 1.
    #[test]
    fn white_furnace_reflects_at_most_what_arrives() {
        for &r in &[0.05f32, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0] {
            for &m in &[0.0f32, 0.5, 1.0] {
                let b = Bsdf::new(Vec3::ONE, m, r, 1.0);
                for &theta in &[0.0f32, 0.5, 1.0, 1.3, 1.5] {
                    let wo = dir(theta, 0.3);
                    let a = sampled_albedo(&b, wo, 1 << 15).sum();
                    assert!(
                        a.max_element() <= 1.0 + 0.01,
                        "roughness {r} metallic {m} θ {theta}: albedo {a}"
                    );
                    let t = b.albedo(wo.z).sum();
                    assert!(t.max_element() <= 1.0 + 0.01, "table albedo {t}");
                }
            }
        }
        let metal = |r: f32, theta: f32| {
            sampled_albedo(&Bsdf::new(Vec3::ONE, 1.0, r, 1.0), dir(theta, 0.0), 1 << 15)
                .sum()
                .x
        };
        assert!(
            (metal(0.1, 0.0) - 0.99).abs() < 0.015,
            "{}",
            metal(0.1, 0.0)
        );
        // α = 1: D = 1/π and V = ½/(n·l + n·v), so at normal incidence
        // ∫ f cos = ∫₀¹ μ/(1 + μ) dμ = 1 − ln 2.
        let closed = 1.0 - std::f32::consts::LN_2;
        assert!(
            (metal(1.0, 0.0) - closed).abs() < 0.005,
            "{}",
            metal(1.0, 0.0)
        );
        // A white dielectric loses nothing: its diffuse layer takes what the glossy one does
        // not reflect, at every roughness and angle.
        for &r in &[0.05f32, 0.5, 1.0] {
            for &theta in &[0.0f32, 0.8, 1.4] {
                let a =
                    sampled_albedo(&Bsdf::new(Vec3::ONE, 0.0, r, 1.0), dir(theta, 0.0), 1 << 15);
                assert!((a.sum().x - 1.0).abs() < 0.01, "r {r} θ {theta}: {a:?}");
            }
        }
        // The Lambertian limit is exactly the base colour.
        let l = sampled_albedo(&Bsdf::lambertian(Vec3::splat(0.7)), dir(0.7, 0.0), 1 << 12);
        assert!(
            (l.diffuse.x - 0.7).abs() < 1e-3 && l.glossy == Vec3::ZERO,
            "{l:?}"
        );
    }

    #[test]
    fn reciprocity() {
        let s = Sampler::strata(3);
        for i in 0..2000 {
            let r = s.get(i, 0);
            let b = Bsdf::new(Vec3::new(0.9, 0.5, 0.2), s.get(i, 1), r, 1.0);
            let a = dir(s.get(i, 2) * 1.5, s.get(i, 3) * std::f32::consts::TAU);
            let c = dir(s.get(i, 4) * 1.5, s.get(i, 5) * std::f32::consts::TAU);
            let (x, y) = (b.eval(Vec3::Z, a, c).sum(), b.eval(Vec3::Z, c, a).sum());
            assert!(
                (x - y).abs().max_element() <= 1e-4 * x.max_element().max(1.0),
                "{x} vs {y}"
            );
        }
    }

    /// The tables agree with the albedo integrated by sampling and by uniform directions:
    /// a wrong pdf (or a wrong table) shows as a difference.
    #[test]
    fn sampling_weights_match_evaluation_and_tables() {
        for &r in &[0.1f32, 0.3, 0.6, 1.0] {
            for &m in &[0.0f32, 1.0] {
                let b = Bsdf::new(Vec3::new(0.8, 0.6, 0.3), m, r, 1.0);
                for &theta in &[0.2f32, 0.9, 1.3] {
                    let wo = dir(theta, 1.0);
                    let sampled = sampled_albedo(&b, wo, 1 << 16).sum();
                    let table = b.albedo(wo.z).sum();
                    assert!(
                        (sampled - table).abs().max_element() < 0.01,
                        "r {r} m {m} θ {theta}: sampled {sampled} table {table}"
                    );
                    if r >= 0.3 {
                        let uniform = uniform_albedo(&b, wo, 1 << 18).sum();
                        assert!(
                            (uniform - table).abs().max_element() < 0.02,
                            "r {r} m {m} θ {theta}: uniform {uniform} table {table}"
                        );
                    }
                }
            }
        }
    }

    /// Pearson's χ² test of the sampled directions against the pdf integrated over a
    /// (cos θ, φ) grid, as pbrt-v4's `chi2test` does: bins with fewer than 5 expected samples
    /// are pooled; the p-value must pass a 1 % significance level with a Šidák correction
    /// over all cases.
    #[test]
    fn sampled_directions_follow_the_pdf() {
        use statrs::distribution::{ChiSquared, ContinuousCDF};
        let (nt, np) = (16usize, 32usize);
        let samples = 200_000u32;
        let cases: Vec<(f32, f32, f32)> = vec![
            (0.15, 1.0, 0.3),
            (0.3, 0.0, 0.8),
            (0.5, 0.5, 1.2),
            (1.0, 0.0, 0.1),
            (0.25, 1.0, 1.45),
        ];
        let alpha = 1.0 - (1.0 - 0.01f64).powf(1.0 / cases.len() as f64);
        for (ci, &(r, m, theta)) in cases.iter().enumerate() {
            let b = Bsdf::new(Vec3::new(0.7, 0.7, 0.7), m, r, 1.0);
            let wo = dir(theta, 0.4);
            let bin = |w: Vec3| {
                let t = ((w.z.clamp(0.0, 1.0)) * nt as f32).min(nt as f32 - 1.0) as usize;
                let p = (w.y.atan2(w.x) + PI) / (2.0 * PI);
                let p = ((p * np as f32) as usize).min(np - 1);
                t * np + p
            };
            let mut observed = vec![0f64; nt * np];
            let s = Sampler::strata(100 + ci as u32);
            for i in 0..samples {
                let u = [s.get(i, 0), s.get(i, 1), s.get(i, 2)];
                if let Some(x) = b.sample(Vec3::Z, wo, u) {
                    observed[bin(x.wi)] += 1.0;
                }
            }
            // Expected counts: the pdf integrated over each bin (uniform in cos θ and φ,
            // so dω = d(cos θ)·dφ) by a 24×24 midpoint rule.
            let sub = 24;
            let mut expected = vec![0f64; nt * np];
            for t in 0..nt {
                for p in 0..np {
                    let mut sum = 0.0f64;
                    for a in 0..sub {
                        for c in 0..sub {
                            let z = (t as f32 + (a as f32 + 0.5) / sub as f32) / nt as f32;
                            let phi =
                                (p as f32 + (c as f32 + 0.5) / sub as f32) / np as f32 * 2.0 * PI
                                    - PI;
                            let rr = (1.0 - z * z).max(0.0).sqrt();
                            let w = Vec3::new(rr * phi.cos(), rr * phi.sin(), z);
                            sum += b.pdf(Vec3::Z, wo, w) as f64;
                        }
                    }
                    let area = (1.0 / nt as f64) * (2.0 * PI as f64 / np as f64);
                    expected[t * np + p] = sum / (sub * sub) as f64 * area * samples as f64;
                }
            }
            // Pool small bins (pbrt's rule), then Pearson's statistic.
            let mut order: Vec<usize> = (0..expected.len()).collect();
            order.sort_by(|&a, &b| expected[a].total_cmp(&expected[b]));
            let (mut chi2, mut dof) = (0.0f64, 0i64);
            let (mut pool_e, mut pool_o) = (0.0, 0.0);
            for &i in &order {
                if expected[i] < 5.0 {
                    pool_e += expected[i];
                    pool_o += observed[i];
                    assert!(
                        expected[i] > 0.0 || observed[i] == 0.0,
                        "case {ci}: samples where the pdf is 0 (bin {i})"
                    );
                } else {
                    let d = observed[i] - expected[i];
                    chi2 += d * d / expected[i];
                    dof += 1;
                }
            }
            if pool_e > 5.0 {
                let d = pool_o - pool_e;
                chi2 += d * d / pool_e;
                dof += 1;
            }
            let dist = ChiSquared::new((dof - 1) as f64).unwrap();
            let p_value = 1.0 - dist.cdf(chi2);
            assert!(
                p_value > alpha,
                "case {ci} (roughness {r}, metallic {m}, θ {theta}): χ² {chi2:.1} dof {dof} p {p_value:.2e}"
            );
        }
    }

    #[test]
    fn the_lambertian_limit_is_exact() {
        let b = Bsdf::lambertian(Vec3::splat(0.5));
        let f = b.eval(Vec3::Z, dir(0.3, 0.0), dir(1.1, 2.0));
        assert_eq!(f.glossy, Vec3::ZERO);
        assert!((f.diffuse.x - 0.5 * FRAC_1_PI).abs() < 1e-7);
        let a = b.hemispherical_albedo();
        assert!((a.diffuse.x - 0.5).abs() < 1e-6 && a.glossy == Vec3::ZERO);
    }
}
