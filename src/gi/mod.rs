//! Global illumination: the baselines the paper measures its anchors against (§1, §2.1,
//! §4, §6) and an unbiased reference.
//!
//! - `brute-force`: photon map + irradiance cache; every frame every record re-gathers every
//!   stratum, and radiance at a gather hit is albedo × photon-map irradiance / π from the k
//!   nearest photons (the paper's Table 1, left column).
//! - `precomputed`: as brute force, but gather hits read irradiance precomputed at a quarter
//!   of the photons (Christensen 1999, the paper's Figure 7 comparison).
//! - `path-trace`: a path tracer with next-event estimation, the ground truth.
//!
//! All share seeds, the photon sequence and the cache placement, so they compare like for
//! like. Cache records persist between frames (positions and ids, hence gather directions):
//! static records are re-gathered each frame, dynamic ones are re-placed (§4.2, §4.3).

pub mod anchors;
pub mod cache;
pub mod coherent;
pub mod gpu;
pub mod photons;
pub mod visibility;

use std::f32::consts::FRAC_1_PI;
use std::num::NonZero;
use std::time::Instant;

use glam::Vec3;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::render::{
    Accumulator, FrameImage, Materials, RenderCounts, SurfacePoint, direct_irradiance, render_rows,
};
use crate::sampling::Sampler;
use crate::scene::FrameScene;
use cache::{CacheParams, GatherTimings, IrradianceCache};
use coherent::{AnchorParams, AnchorStats};
use photons::{PhotonMap, cosine_direction};

/// Settings of the photon-mapping methods ([`GiParams::preset`] gives the presets).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GiParams {
    /// Photons emitted per frame.
    pub photons: u32,
    /// Photons in each irradiance estimate.
    pub k: u32,
    /// Photon bounces at most.
    pub max_bounces: u32,
    pub cache: CacheParams,
    /// `anchors`: anchor density and reuse heuristics.
    pub anchors: AnchorParams,
    /// `path-trace`: samples per pixel and maximum path length.
    pub path_samples: u32,
    pub path_depth: u32,
}

/// Named speed/accuracy presets.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    Draft,
    #[default]
    Production,
    Final,
}

impl GiParams {
    pub fn preset(p: Preset) -> Self {
        let cache = CacheParams::default();
        match p {
            Preset::Draft => GiParams {
                photons: 50_000,
                k: 32,
                max_bounces: 8,
                cache: CacheParams {
                    strata: [8, 24],
                    error: 0.4,
                    min_spacing_px: 3.0,
                    max_spacing_px: 32.0,
                    ..cache
                },
                anchors: AnchorParams::default(),
                path_samples: 64,
                path_depth: 8,
            },
            Preset::Production => GiParams {
                photons: 200_000,
                k: 64,
                max_bounces: 12,
                cache,
                anchors: AnchorParams::default(),
                path_samples: 256,
                path_depth: 12,
            },
            Preset::Final => GiParams {
                photons: 800_000,
                k: 100,
                max_bounces: 16,
                cache: CacheParams {
                    strata: [30, 60],
                    error: 0.15,
                    min_spacing_px: 1.5,
                    max_spacing_px: 16.0,
                    ..cache
                },
                anchors: AnchorParams::default(),
                path_samples: 1024,
                path_depth: 16,
            },
        }
    }
}

/// Irradiance precomputed at every fourth photon (Christensen 1999).
pub struct PrecomputedIrradiance {
    points: Vec<(Vec3, Vec3, Vec3)>, // position, normal, irradiance
    tree: Option<ImmutableKdTree<f32, u32, 3, 32>>,
}

impl PrecomputedIrradiance {
    pub fn new(pm: &PhotonMap, k: usize) -> Self {
        let points: Vec<(Vec3, Vec3, Vec3)> = pm
            .photons
            .par_iter()
            .step_by(4)
            .map(|p| (p.position, p.normal, pm.irradiance(p.position, p.normal, k)))
            .collect();
        let tree = (!points.is_empty()).then(|| {
            let pts: Vec<[f32; 3]> = points.iter().map(|p| p.0.to_array()).collect();
            ImmutableKdTree::new_from_slice(&pts)
        });
        PrecomputedIrradiance { points, tree }
    }

    /// Irradiance of the nearest precomputed point whose normal agrees with `n`.
    pub fn lookup(&self, x: Vec3, n: Vec3) -> Vec3 {
        let Some(t) = &self.tree else {
            return Vec3::ZERO;
        };
        for nb in t.nearest_n::<SquaredEuclidean>(&x.to_array(), NonZero::new(8).expect("8 > 0")) {
            let p = &self.points[nb.item as usize];
            if p.1.dot(n) > 0.5 {
                return p.2;
            }
        }
        Vec3::ZERO
    }
}

/// State kept between the frames of one render (DESIGN.md: one owner of what survives).
#[derive(Default)]
pub struct Session {
    pub cache: IrradianceCache,
    /// The anchor method's anchors, kept from frame to frame.
    pub anchors: Option<anchors::AnchorSet>,
    /// Visibility detection for the anchor method; `None` is the CPU implementation.
    pub visibility: Option<Box<dyn visibility::Visibility>>,
}

/// Timings and counts of one frame's global illumination (the paper's Table 1 rows).
#[derive(Debug, Clone, Default)]
pub struct GiStats {
    pub photon_tracing: f64,
    pub irradiance_estimation: f64,
    pub final_gathering: f64,
    pub cache_interpolation: f64,
    pub direct_lighting: f64,
    pub photons: u64,
    pub caches: u64,
    pub rays_shot: u64,
    /// Pixel samples no record covered, gathered on the spot.
    pub uncached_samples: u64,
    /// The anchor method's statistics.
    pub anchors: Option<AnchorStats>,
}

/// The photon-mapping methods that shade from the irradiance cache.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CachedMethod {
    BruteForce,
    Precomputed,
    Anchors,
}

/// Which estimate a gather hit uses.
#[derive(Clone, Copy)]
pub enum GatherEstimate<'a> {
    PhotonMap(&'a PhotonMap, usize),
    Precomputed(&'a PrecomputedIrradiance),
}

impl GatherEstimate<'_> {
    /// Reflected radiance leaving a gather hit: albedo × E / π (emission excluded: direct
    /// light is computed separately at the camera hit).
    pub fn radiance(&self, sp: &SurfacePoint, m: Materials) -> Vec3 {
        let e = match *self {
            GatherEstimate::PhotonMap(pm, k) => pm.irradiance(sp.position, sp.ng, k),
            GatherEstimate::Precomputed(pc) => pc.lookup(sp.position, sp.ng),
        };
        sp.albedo(m) * FRAC_1_PI * e
    }
}

/// Renders a frame with a cached method: photons, cache update and placement, then shading.
#[allow(clippy::too_many_arguments)] // the frame's whole context
pub fn render_cached(
    frame: &FrameScene,
    m: Materials,
    session: &mut Session,
    params: &GiParams,
    method: CachedMethod,
    spp: u32,
    light_samples: u32,
    width: u32,
    height: u32,
    seed: u32,
    frame_number: i32,
) -> Result<(FrameImage, RenderCounts, GiStats), String> {
    let mut st = GiStats::default();
    let t = Instant::now();
    let pm = PhotonMap::trace(frame, m, params.photons, seed, params.max_bounces);
    st.photon_tracing = t.elapsed().as_secs_f64();
    st.photons = pm.photons.len() as u64;
    let t = Instant::now();
    let pc = (method == CachedMethod::Precomputed)
        .then(|| PrecomputedIrradiance::new(&pm, params.k as usize));
    st.irradiance_estimation = t.elapsed().as_secs_f64();
    let est = match &pc {
        Some(pc) => GatherEstimate::Precomputed(pc),
        None => GatherEstimate::PhotonMap(&pm, params.k as usize),
    };
    let radiance = |sp: &SurfacePoint| est.radiance(sp, m);
    let mut gt = GatherTimings::default();
    let cache = &mut session.cache;
    cache.set_error(params.cache.error);
    if method == CachedMethod::Anchors {
        let vis = session
            .visibility
            .as_deref()
            .unwrap_or(&visibility::CpuVisibility);
        st.anchors = Some(coherent::update(
            frame,
            m,
            cache,
            &mut session.anchors,
            &pm,
            &params.cache,
            &params.anchors,
            params.k as usize,
            width,
            height,
            seed,
            frame_number,
            vis,
            &mut gt,
        )?);
    } else {
        let mut brute =
            |fp: &[f32], hits: Vec<Vec<cache::GatherHit>>| cache::estimate_all(fp, hits, &radiance);
        cache.expire(frame_number, params.cache.max_age);
        cache.regather(frame, &params.cache, frame_number, &mut brute, &mut gt);
        cache.place(
            frame,
            width,
            height,
            &params.cache,
            frame_number,
            &mut brute,
            &mut gt,
        );
    }
    st.final_gathering = gt.final_gathering;
    st.irradiance_estimation += gt.irradiance_estimation;
    st.rays_shot = gt.rays;
    st.caches = cache.len() as u64;

    // Shading: direct light by shadow rays, indirect from the cache.
    let t = Instant::now();
    let cache_ref = &*cache;
    let a = params.cache.error;
    let (img, rows) = render_rows(width, height, |x, y, row: &mut ShadeRow| {
        let pixel = y * width + x;
        let sampler = Sampler::new(seed, frame_number, 0, pixel);
        let mut acc = Accumulator::default();
        type Last = ((crate::scene::Motion, u32), Vec3, Vec3, (u32, f32));
        let mut last: Option<Last> = None;
        // The pixel centre's surface: interpolation for the pixel's samples on that surface
        // happens there, which does not move with the per-frame sample jitter.
        let (co, cd) = frame.camera.ray(
            (x as f32 + 0.5) / width as f32,
            (y as f32 + 0.5) / height as f32,
        );
        let centre = frame
            .accel
            .closest(
                &frame.static_geometry,
                &frame.dynamic_geometry,
                co,
                cd,
                f32::INFINITY,
            )
            .map(|h| SurfacePoint::new(frame, h, co, cd));
        let key = |sp: &SurfacePoint| {
            (
                sp.hit.motion,
                frame.geometry(sp.hit.motion).shading[sp.hit.triangle as usize].prim,
            )
        };
        for s in 0..spp {
            let [jx, jy] = sampler.get2(s, 0);
            let (o, d) = frame.camera.ray(
                (x as f32 + jx) / width as f32,
                (y as f32 + jy) / height as f32,
            );
            row.counts.camera_rays += 1;
            let Some(sp) = crate::render::trace(frame, o, d) else {
                continue;
            };
            let hit = sp.hit;
            let t0 = Instant::now();
            let albedo = sp.albedo(m) * FRAC_1_PI;
            let l_direct = albedo
                * direct_irradiance(
                    frame,
                    &sp,
                    &sampler,
                    s,
                    light_samples,
                    2,
                    &mut row.counts.shadow_rays,
                );
            let t1 = Instant::now();
            // One interpolation per pixel and surface: the pixel's other samples on the same
            // prim, facing the same way, reuse it (records are valid over several pixels).
            let reuse = last.filter(|(prim, n, _, _)| *prim == key(&sp) && n.dot(sp.ns) > 0.999);
            let (e, anchor_id, reshot) = match reuse {
                Some((_, _, e, (id, r))) => (e, id, r),
                None => {
                    let at = match &centre {
                        Some(c) if key(c) == key(&sp) && c.ns.dot(sp.ns) > 0.999 => c,
                        _ => &sp,
                    };
                    // A sample off the placement grid may fall just outside every record:
                    // relax the threshold twice before gathering on the spot.
                    let found = cache_ref
                        .interpolate(at.position, at.ns, a, &mut row.used)
                        .or_else(|| {
                            cache_ref.interpolate(at.position, at.ns, 2.0 * a, &mut row.used)
                        });
                    let r = match found {
                        Some(i) => {
                            let anchor =
                                cache_ref.records[i.dominant_record as usize].dominant_anchor;
                            (
                                i.irradiance,
                                if anchor == cache::NO_LINK {
                                    0
                                } else {
                                    anchor + 1
                                },
                                i.reshot,
                            )
                        }
                        None => {
                            row.uncached += 1;
                            let hits = IrradianceCache::trace_strata(
                                frame,
                                at,
                                pixel ^ 0x8000_0000,
                                &params.cache,
                            );
                            let strata = (params.cache.strata[0] * params.cache.strata[1]) as f32;
                            let e = hits
                                .iter()
                                .filter_map(|h| h.sp.as_ref())
                                .map(&radiance)
                                .sum::<Vec3>()
                                * (std::f32::consts::PI / strata);
                            (e, 0, 1.0)
                        }
                    };
                    last = Some((key(&sp), sp.ns, r.0, (r.1, r.2)));
                    r
                }
            };
            acc.note_cache(anchor_id, reshot);
            row.t_direct += (t1 - t0).as_secs_f64();
            row.t_interp += t1.elapsed().as_secs_f64();
            acc.hit(
                hit.t * d.dot(frame.camera.forward),
                sp.emission(m),
                l_direct,
                albedo * e,
            );
        }
        acc.finish(spp)
    });
    let wall = t.elapsed().as_secs_f64();
    let mut used: Vec<u32> = rows.iter().flat_map(|r| r.used.iter().copied()).collect();
    used.sort_unstable();
    used.dedup();
    cache.touch(&used, frame_number);
    let (td, ti): (f64, f64) = rows
        .iter()
        .fold((0.0, 0.0), |(a, b), r| (a + r.t_direct, b + r.t_interp));
    st.uncached_samples = rows.iter().map(|r| r.uncached).sum();
    let frac = if td + ti > 0.0 { ti / (td + ti) } else { 0.0 };
    st.cache_interpolation = wall * frac;
    st.direct_lighting = wall * (1.0 - frac);
    let counts = RenderCounts::sum(rows.iter().map(|r| &r.counts));
    Ok((img, counts, st))
}

/// Per-row state of the cached shading pass.
#[derive(Default)]
struct ShadeRow {
    counts: RenderCounts,
    used: Vec<u32>,
    t_direct: f64,
    t_interp: f64,
    uncached: u64,
}

/// Unbiased path tracing with next-event estimation: emission is counted at the camera hit
/// only; every diffuse vertex samples the lights with shadow rays and continues by cosine
/// sampling; Russian roulette after three bounces.
#[allow(clippy::too_many_arguments)]
pub fn path_trace(
    frame: &FrameScene,
    m: Materials,
    spp: u32,
    depth: u32,
    light_samples: u32,
    width: u32,
    height: u32,
    seed: u32,
    frame_number: i32,
) -> (FrameImage, RenderCounts) {
    let (img, rows) = render_rows(width, height, |x, y, counts: &mut RenderCounts| {
        let sampler = Sampler::new(seed, frame_number, 0, y * width + x);
        let mut acc = Accumulator::default();
        for s in 0..spp {
            let [jx, jy] = sampler.get2(s, 0);
            let (mut o, mut d) = frame.camera.ray(
                (x as f32 + jx) / width as f32,
                (y as f32 + jy) / height as f32,
            );
            counts.camera_rays += 1;
            let mut beta = Vec3::ONE;
            for bounce in 0..depth {
                let Some(sp) = crate::render::trace(frame, o, d) else {
                    break;
                };
                let hit = sp.hit;
                let dim = 2 + bounce * 6;
                let albedo = sp.albedo(m);
                let l = beta
                    * albedo
                    * FRAC_1_PI
                    * direct_irradiance(
                        frame,
                        &sp,
                        &sampler,
                        s,
                        light_samples,
                        dim,
                        &mut counts.shadow_rays,
                    );
                if bounce == 0 {
                    acc.hit(
                        hit.t * d.dot(frame.camera.forward),
                        sp.emission(m),
                        l,
                        Vec3::ZERO,
                    );
                } else {
                    acc.add(Vec3::ZERO, l);
                }
                beta *= albedo;
                if bounce >= 3 {
                    let p = beta.max_element().clamp(0.05, 1.0);
                    if sampler.get(s, dim + 3) >= p {
                        break;
                    }
                    beta /= p;
                }
                let nd = cosine_direction(
                    sp.ns,
                    sampler.get(s, dim + 4).min(0.999_999_9),
                    sampler.get(s, dim + 5),
                );
                if nd.dot(sp.ng) <= 0.0 {
                    break;
                }
                o = sp.spawn();
                d = nd;
            }
        }
        acc.finish(spp)
    });
    let mut img = img;
    img.drop_cache_aovs();
    (img, RenderCounts::sum(&rows))
}
