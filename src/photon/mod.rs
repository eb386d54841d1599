//! Photon tracing and the photon map (Jensen, "Realistic Image Synthesis Using Photon
//! Mapping", 2001; the paper's §1, §3 and §4.2).
//!
//! Photons leave the lights in proportion to their power and are traced with a quasi-Monte
//! Carlo sequence indexed by photon number, seeded by the job's seed but *not* by the frame:
//! photon `i` follows the same path in every frame where the geometry it meets did not
//! change, which the anchors rely on (§4.2, [Chr02]). Every diffuse hit stores the photon
//! (the first hit included: final-gather hits need the direct illumination there too);
//! Russian roulette by albedo decides whether it bounces on.
//!
//! The kd-tree is kiddo's immutable tree: a maintained crate doing exactly the k-nearest
//! query the estimate needs.
//!
//! Every look-up is bounded: no photon farther than [`PhotonMap::max_radius`] from the
//! query point counts (DESIGN.md, Numerics), so light sealed behind closed geometry cannot
//! leak through it into an estimate, and a query far from every photon costs little. Where
//! fewer than k photons lie within the bound, the estimate is the density over the
//! maximum disc. Estimates gather over a disc, not a sphere (Jensen 2001, §7.2): a photon
//! off the query's tangent plane by more than [`DISC_THICKNESS`] of the radius lies on
//! another surface — a lamp 0.9 units under a ceiling must not count the dense photons
//! its back side leaves on the ceiling as light arriving at its front.

pub mod precomputed;

use std::f32::consts::PI;
use std::num::NonZero;

use glam::{Vec2, Vec3};
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use serde::{Deserialize, Serialize};

use crate::accel::{interpolate, offset_ray_origin};
use crate::color::luminance;
use crate::geom::{basis, cosine_direction, face_normal_area, uniform_sphere};
use crate::interaction::{Materials, SurfacePoint};
use crate::sampling::Sampler;
use crate::scene::{FrameScene, LightKind};

/// One stored photon.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Photon {
    pub position: Vec3,
    /// Normal of the surface it landed on, on the side it arrived from.
    pub normal: Vec3,
    /// Flux carried (scene light units × area).
    pub power: Vec3,
}

/// The photons of a map, path by path, kept to tell the next frame's changes.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PhotonPaths {
    pub photons: Vec<Photon>,
    pub path_start: Vec<u32>,
}

/// Photon map with its kd-tree.
pub struct PhotonMap {
    pub photons: Vec<Photon>,
    /// Where each emitted photon's path starts in `photons` (one more entry than paths):
    /// path `i` stored `photons[path_start[i]..path_start[i + 1]]`.
    pub path_start: Vec<u32>,
    tree: Option<ImmutableKdTree<f32, u32, 3, 32>>,
    /// Photons emitted (the divisor of every photon's power).
    pub emitted: u32,
    /// Total flux emitted by all lights (luminance-weighted sum is what selection uses).
    pub emitted_power: Vec3,
    /// No look-up reaches farther than this (scene units; see the module doc).
    pub max_radius: f32,
}

/// Half the thickness of the disc an estimate gathers over, as a fraction of its radius: a
/// photon farther than this from the query's tangent plane lies on another surface (on a
/// curved one, only beyond ~30° of arc). Jensen 2001, §7.2 compresses the sphere likewise.
pub const DISC_THICKNESS: f32 = 0.25;

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

impl PhotonMap {
    /// Traces `count` photons from every light of `frame`. `seed` selects the sequence;
    /// it must not depend on the frame for temporal coherence. Look-ups reach
    /// `max_radius` × the static geometry's bounding radius at most
    /// ([`FrameScene::static_radius`]: the same in every frame).
    pub fn trace(
        frame: &FrameScene,
        m: Materials,
        count: u32,
        seed: u32,
        max_bounces: u32,
        max_radius: f32,
    ) -> PhotonMap {
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
            tree: None,
            emitted: count,
            emitted_power,
            max_radius: max_radius * frame.static_radius(),
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
        let chunks: Vec<(Vec<Photon>, Vec<u32>)> = (0..count.div_ceil(4096))
            .into_par_iter()
            .map(|c| {
                let mut out = Vec::new();
                let mut ends = Vec::new();
                for i in c * 4096..((c + 1) * 4096).min(count) {
                    if i > c * 4096 {
                        ends.push(out.len() as u32);
                    }
                    let s = PhotonSamples { sampler, index: i };
                    let k = cdf
                        .partition_point(|&x| x <= s.get(DIM_LIGHT))
                        .min(sources.len() - 1);
                    let p_pick = (weights[k] / total) as f32;
                    let Some((o, dir, flux)) = emit(frame, &sources[k], &s, centre, radius) else {
                        continue;
                    };
                    let flux = flux / (p_pick * count as f32);
                    trace_path(frame, m, o, dir, flux, &s, max_bounces, &mut out);
                }
                ends.push(out.len() as u32);
                (out, ends)
            })
            .collect();
        map.path_start.push(0);
        for (photons, ends) in chunks {
            let base = map.photons.len() as u32;
            map.path_start.extend(ends.iter().map(|e| base + e));
            map.photons.extend(photons);
        }
        if !map.photons.is_empty() {
            let pts: Vec<[f32; 3]> = map.photons.iter().map(|p| p.position.to_array()).collect();
            map.tree = Some(ImmutableKdTree::new_from_slice(&pts));
        }
        map
    }

    /// Irradiance at `x` (normal `n`) from the `k` nearest photons whose surface normal
    /// agrees with `n` (Jensen's estimate E = ΣΦ / πr², r the distance to the k-th photon).
    pub fn irradiance(&self, x: Vec3, n: Vec3, k: usize) -> Vec3 {
        self.irradiance_and_radius(x, n, k).0
    }

    /// [`PhotonMap::irradiance`] and the squared radius of the disc it gathered over: the
    /// estimate depends on no photon farther away. The disc reaches the k-th nearest photon
    /// within [`PhotonMap::max_radius`], or that radius where fewer lie within it.
    pub fn irradiance_and_radius(&self, x: Vec3, n: Vec3, k: usize) -> (Vec3, f32) {
        let r2_max = self.max_radius * self.max_radius;
        let Some(tree) = &self.tree else {
            return (Vec3::ZERO, r2_max);
        };
        let k = k.max(1);
        let found = tree.nearest_n_within::<SquaredEuclidean>(
            &x.to_array(),
            r2_max,
            NonZero::new(k).expect("k >= 1"),
            false,
        );
        let r2 = if found.len() < k {
            r2_max
        } else {
            found.iter().map(|nb| nb.distance).fold(0.0, f32::max)
        };
        if !(r2 > 0.0) {
            return (Vec3::ZERO, r2_max);
        }
        // Photons on surfaces facing elsewhere (across a corner) or off the disc (on a
        // parallel surface close by) do not count, but the disc still reaches the k-th
        // photon: a radius set by the few accepted ones would be unstable where almost none
        // are (Jensen 2001, §7.2).
        let thickness = DISC_THICKNESS * r2.sqrt();
        let sum: Vec3 = found
            .iter()
            .map(|nb| &self.photons[nb.item as usize])
            .filter(|p| p.normal.dot(n) > 0.5 && (p.position - x).dot(n).abs() <= thickness)
            .map(|p| p.power)
            .sum();
        (sum / (PI * r2), r2)
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
                let moved: Vec<Vec3> = if same {
                    Vec::new()
                } else {
                    a.iter().chain(b).map(|p| p.position).collect()
                };
                moved
            })
            .collect()
    }

    /// Index of the photon nearest to `x` within [`PhotonMap::max_radius`], if any.
    pub fn nearest(&self, x: Vec3) -> Option<usize> {
        let t = self.tree.as_ref()?;
        let r2_max = self.max_radius * self.max_radius;
        t.nearest_n_within::<SquaredEuclidean>(&x.to_array(), r2_max, NonZero::<usize>::MIN, false)
            .first()
            .map(|nb| nb.item as usize)
    }

    /// Total flux stored in the map.
    pub fn stored_power(&self) -> Vec3 {
        self.photons.iter().map(|p| p.power).sum()
    }
}

/// Origin, direction and flux of a photon leaving `source`.
fn emit(
    frame: &FrameScene,
    source: &Source,
    s: &PhotonSamples,
    centre: Vec3,
    radius: f32,
) -> Option<(Vec3, Vec3, Vec3)> {
    match *source {
        Source::Punctual(i) => {
            let l = &frame.lights[i];
            match l.kind {
                LightKind::Point => Some((
                    l.position,
                    uniform_sphere(s.get(DIM_EMIT + 2), s.get(DIM_EMIT + 3)),
                    4.0 * PI * l.intensity,
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
                    Some((l.position, d, 2.0 * PI * (1.0 - co) * l.intensity * f * f))
                }
                LightKind::Directional => {
                    let (t, b) = basis(l.direction);
                    let r = radius * s.get(DIM_EMIT).sqrt();
                    let phi = 2.0 * PI * s.get(DIM_EMIT + 1);
                    let o = centre - l.direction * (2.0 * radius)
                        + t * (r * phi.cos())
                        + b * (r * phi.sin());
                    Some((o, l.direction, PI * radius * radius * l.intensity))
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
            ))
        }
    }
}

/// Follows one photon, storing it at every diffuse hit.
#[allow(clippy::too_many_arguments)] // the photon's state, spelled out
fn trace_path(
    frame: &FrameScene,
    m: Materials,
    mut o: Vec3,
    mut dir: Vec3,
    mut flux: Vec3,
    s: &PhotonSamples,
    max_bounces: u32,
    out: &mut Vec<Photon>,
) {
    for bounce in 0..=max_bounces {
        let Some(hit) = frame.accel.closest(
            &frame.static_geometry,
            &frame.dynamic_geometry,
            o,
            dir,
            f32::INFINITY,
        ) else {
            return;
        };
        let sp = SurfacePoint::new(frame, hit, o, dir);
        out.push(Photon {
            position: sp.position,
            normal: sp.ng,
            power: flux,
        });
        // Russian roulette by the directional albedo (Jensen §5.3): survive with p = its
        // mean, then scatter by sampling the BRDF (glossy bounces included).
        let wo = -dir;
        let bsdf = sp.bsdf(m);
        let ns = sp.shading_normal(wo);
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
        flux *= x.f.sum() * (ns.dot(x.wi) / (x.pdf * p));
        if !flux.is_finite() || flux.max_element() <= 0.0 {
            return;
        }
        dir = x.wi;
        o = sp.spawn();
    }
}
