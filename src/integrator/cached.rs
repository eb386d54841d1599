//! The methods that shade from the irradiance cache: `brute-force`, `precomputed` and
//! `anchors`. Each frame has two phases. *Prepare*: trace the photons (§4.2), then bring
//! the cache up to date — brute force and precomputed re-gather every stratum of every
//! record and place new records (`prepare_brute_force`), anchors run Pseudocode 2
//! ([`super::anchors::update`]). *Shade*: direct light by shadow rays at each camera hit, and
//! the indirect light interpolated from the cache ([`CachedShading`]).
//!
//! With anchor bucketing (§5.1) the shade phase goes band by band (about [`BAND_PIXELS`]
//! pixels each): a planning pass over the band's camera samples makes the same choices the
//! shading will make and plans each bucketed shading point ([`super::bucket::plan`]); one
//! call to the visibility implementation's [`DepthMaps`] answers all the band's depth
//! queries (on the GPU where visibility runs there); then the band is shaded, each shading
//! point finishing its plan in the same order. The planning pass costs a second camera ray
//! per sample; the image is the one per-point tracing gives, bit for bit, with the CPU.

use std::f32::consts::{FRAC_1_PI, PI};
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use super::anchors::AnchorStats;
use super::bucket::{BucketParams, BucketPlan};
use super::replay::{DirectKeys, Replay, RowLog, ShadingLog};
use super::{Accumulator, CameraHit, FrameContext, FrameImage, GiParams, RenderCounts, Shade};
use crate::accel::Hit;
use crate::anchor::attach::Attacher;
use crate::anchor::{AnchorId, AnchorSet};
use crate::bsdf::Lobes;
use crate::cache::directional::Directional;
use crate::cache::{
    CacheParams, Contribution, GatherHit, GatherTimings, IrradianceCache, RELAXED, Record,
    WeberTally, gather,
};
use crate::geom::Motion;
use crate::interaction::{Materials, PixelCentres, SurfacePoint, camera_hit};
use crate::photon::PhotonMap;
use crate::photon::precomputed::PrecomputedIrradiance;
use crate::scene::FrameScene;
use crate::visibility::Visibility;
use crate::visibility::depth::{CpuDepthMaps, DepthMaps, DepthQuery};
use serde::{Deserialize, Serialize};

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
    /// Christensen's irradiance at the photons, and the map it was computed from.
    Precomputed(&'a PrecomputedIrradiance, &'a PhotonMap),
    /// `anchors`, for the gathers of pixel samples no record covers: a static hit reflects
    /// the light of the anchor Pseudocode 1 would link it to (§3.1's reuse tests, the same
    /// search as a record's hit; no anchor is made or linked), as a record's stratum would;
    /// a dynamic hit, or one no existing anchor is acceptable for, the photons' estimate.
    Anchors(&'a Attacher<'a>, &'a AnchorSet),
}

impl GatherEstimate<'_> {
    /// Reflected radiance leaving a gather hit: albedo × E / π (emission excluded: direct
    /// light is computed separately at the camera hit). E adds the punctual lights' direct
    /// light by shadow rays where the photon map leaves it out
    /// ([`crate::photon::GatherDirect::ShadowRays`]).
    pub fn radiance(&self, frame: &FrameScene, sp: &SurfacePoint, m: Materials) -> Vec3 {
        let e = match *self {
            GatherEstimate::PhotonMap(pm, k) => {
                pm.irradiance(sp.position, sp.ng, k) + pm.direct_at_hit(frame, sp)
            }
            GatherEstimate::Precomputed(pc, pm) => {
                pc.lookup(sp.position, sp.ng) + pm.direct_at_hit(frame, sp)
            }
            GatherEstimate::Anchors(att, set) => {
                let anchor = (sp.hit.motion == Motion::Static)
                    .then(|| att.find(set, sp))
                    .flatten();
                if let Some(id) = anchor {
                    return set.anchor(id).radiance();
                }
                att.pm.irradiance(sp.position, sp.ng, att.k) + att.pm.direct_at_hit(frame, sp)
            }
        };
        sp.albedo(m) * FRAC_1_PI * e
    }
}

/// Timings and counts of one frame's global illumination (the paper's Table 1 rows), in
/// seconds of the frame's wall time. Each phase is attributed where its work happens: the
/// prepare phase's parallel loops by wall-clock spans around each (photon tracing, gather
/// rays, estimates and attachment); the parallel shading pass by thread seconds accumulated
/// per row at each work site, its wall time split among the rows in their proportion —
/// direct light to `direct_lighting`, interpolation (with bucketing and glossy rays) to
/// `cache_interpolation`, the fallback for samples no record covers (a final gather on
/// the spot) to `final_gathering` (its rays) and `irradiance_estimation` (their photon
/// look-ups), and the rest of a pixel's work, its camera rays and the film's bookkeeping,
/// to `camera_rays`. So the rows add up to the frame's time, less scene evaluation, BVHs,
/// output and the bookkeeping between phases.
#[derive(Debug, Clone, Default)]
pub struct CachedStats {
    pub photon_tracing: f64,
    pub irradiance_estimation: f64,
    /// `anchors`: linking gather hits to anchors ([`crate::anchor::attach`]).
    pub attachment: f64,
    /// Integrating records' strata ([`crate::cache::GatherTimings::integration`]).
    pub integration: f64,
    /// Deciding where new records go: tracing the pixel centres and the camera samples'
    /// lookup points, and [`crate::cache::GatherTimings::placement`].
    pub placement: f64,
    /// [`crate::cache::GatherTimings::upkeep`], and after the shading pass: assembling the
    /// film from its rows (and watch mode's log of its rays), marking the records it read
    /// as used, and the Weber rule's tally and removals (§4.3).
    pub upkeep: f64,
    pub final_gathering: f64,
    pub cache_interpolation: f64,
    /// Answering anchor bucketing's depth queries (§5.1), wherever visibility runs.
    pub depth_maps: f64,
    pub direct_lighting: f64,
    /// The shading pass's camera rays and film bookkeeping (`ShadeRow::t_camera`).
    pub camera_rays: f64,
    pub photons: u64,
    pub caches: u64,
    /// Spot records ([`crate::cache::Record::spot`]) among `caches`, and those made this
    /// frame.
    pub caches_spot: u64,
    pub caches_spot_made: u64,
    /// Records the Weber rule (§4.3) removes after this frame.
    pub caches_retired: u64,
    /// Final-gather rays: the prepare phase's and the uncached fallback's.
    pub rays_shot: u64,
    /// Pixel samples no record covered, gathered on the spot, and the rays they traced
    /// (part of `rays_shot`).
    pub uncached_samples: u64,
    pub uncached_rays: u64,
    /// Shadow rays from gather hits and anchors to the punctual lights
    /// ([`PhotonMap::shadow_rays_cast`]).
    pub gather_shadow_rays: u64,
    /// The anchor method's statistics.
    pub anchors: Option<AnchorStats>,
}

/// What a cached method carries from frame to frame: the cache and, for `anchors`, the
/// anchors (owned by the session's frame state); and where watch mode keeps the shading
/// pass's rays ([`ShadingLog`]): the render logs its own there, after replaying the one
/// there if it is a relight ([`Refresh::relight_only`]).
pub struct CachedState<'a> {
    pub cache: &'a mut IrradianceCache,
    pub anchors: &'a mut Option<AnchorSet>,
    pub log: Option<&'a mut ShadingLog>,
    /// What this render's direct light depends on ([`DirectKeys`]), logged with it so
    /// that a relight may reuse it; `None`: never reused.
    pub keys: Option<&'a DirectKeys>,
}

/// What watch mode knows about the state the anchor method carries into a frame
/// (`crate::watch`). The default, for a render's frame after frame, knows nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Refresh {
    /// The state was left by this same frame and only lights or materials changed since:
    /// [`super::anchors::relight`] instead of Pseudocode 2.
    pub relight_only: bool,
    /// Materials changed since the state was made: anchors read their albedo again
    /// ([`super::anchors::refresh_albedo`]).
    pub albedo: bool,
}

/// Renders a frame with a cached method: prepare (photons, cache update and placement),
/// then shade.
#[allow(clippy::too_many_arguments)] // a frame's every input
pub fn render(
    ctx: &FrameContext,
    state: CachedState,
    params: &GiParams,
    method: CachedMethod,
    visibility: &dyn Visibility,
    spp: u32,
    light_samples: u32,
    refresh: Refresh,
) -> Result<(FrameImage, RenderCounts, CachedStats), crate::visibility::Error> {
    render_in_bands(
        ctx,
        state,
        params,
        method,
        visibility,
        (spp, light_samples),
        Some(BAND_PIXELS),
        refresh,
    )
}

/// [`render`] with bucketing's bands of `band_pixels` pixels, or (`None`) without bands:
/// each shading point plans and answers its own depth queries on the CPU, as before the
/// queries were batched. Public for the test that the two give the same bytes.
#[doc(hidden)]
#[allow(clippy::too_many_arguments)] // `render`'s, plus the band size
pub fn render_in_bands(
    ctx: &FrameContext,
    state: CachedState,
    params: &GiParams,
    method: CachedMethod,
    visibility: &dyn Visibility,
    (spp, light_samples): (u32, u32),
    band_pixels: Option<u32>,
    refresh: Refresh,
) -> Result<(FrameImage, RenderCounts, CachedStats), crate::visibility::Error> {
    let mut st = CachedStats::default();
    let mut log_slot = state.log;
    let known = log_slot.as_deref_mut().map(std::mem::take).filter(|l| {
        method == CachedMethod::Anchors
            && refresh.relight_only
            && l.fits(ctx.width, ctx.height, spp)
    });
    let t = Instant::now();
    let emission = crate::photon::Emission {
        count: params.photons,
        seed: ctx.seed,
        max_bounces: params.photon_bounces,
        max_radius: params.max_photon_radius,
        direct: params.gather_direct,
    };
    let pm = PhotonMap::trace(
        ctx.scene,
        ctx.materials,
        &emission,
        state.anchors.as_ref().map(|a| &a.previous_photons),
    );
    st.photon_tracing = t.elapsed().as_secs_f64();
    st.photons = pm.photons.len() as u64;
    let t = Instant::now();
    let pc = (method == CachedMethod::Precomputed)
        .then(|| PrecomputedIrradiance::new(&pm, params.k as usize));
    st.irradiance_estimation = t.elapsed().as_secs_f64();
    let estimate = match &pc {
        Some(pc) => GatherEstimate::Precomputed(pc, &pm),
        None => GatherEstimate::PhotonMap(&pm, params.k as usize),
    };
    let mut gt = GatherTimings::default();
    let cache = state.cache;
    cache.set_params(&params.cache);
    let first_id = cache.next_id();
    // What the camera sees at the pixel centres, traced once for placement, the lookup
    // points and the shading pass; a relight reads the hits its log keeps instead.
    let relight = method == CachedMethod::Anchors && refresh.relight_only;
    let t = Instant::now();
    let centres = (!relight).then(|| PixelCentres::trace(ctx.scene, ctx.width, ctx.height));
    st.placement = t.elapsed().as_secs_f64();
    match &centres {
        None => {
            st.anchors = Some(super::anchors::relight(
                ctx,
                cache,
                state.anchors,
                &pm,
                params,
                refresh.albedo,
                &mut gt,
            ));
        }
        Some(centres) if method == CachedMethod::Anchors => {
            let t = Instant::now();
            let samples = lookup_points(ctx, spp, centres);
            st.placement += t.elapsed().as_secs_f64();
            st.anchors = Some(super::anchors::update(
                ctx,
                cache,
                state.anchors,
                &pm,
                params,
                visibility,
                &samples,
                centres,
                refresh.albedo,
                &mut gt,
            )?);
        }
        Some(centres) => {
            let t = Instant::now();
            let samples = lookup_points(ctx, spp, centres);
            st.placement += t.elapsed().as_secs_f64();
            prepare_brute_force(
                ctx,
                cache,
                &params.cache,
                estimate,
                &samples,
                centres,
                &mut gt,
            );
        }
    }
    st.final_gathering = gt.final_gathering;
    st.irradiance_estimation += gt.irradiance_estimation;
    st.attachment = gt.attachment;
    st.integration = gt.integration;
    st.placement += gt.placement;
    st.upkeep = gt.upkeep;
    st.rays_shot = gt.rays;
    st.caches = cache.len() as u64;
    st.caches_spot = cache.records.iter().filter(|r| r.spot).count() as u64;
    st.caches_spot_made = cache
        .records
        .iter()
        .filter(|r| r.spot && r.id >= first_id)
        .count() as u64;

    // Only the anchor method's state survives a light or material edit to be relit. The
    // keys are those of the cache as it is shaded, after this frame's update.
    let log = log_slot.is_some() && method == CachedMethod::Anchors;
    let keyed = log || known.is_some();
    let replay = Replay {
        known: known.as_ref(),
        log,
        keys: state.keys,
        spp,
        interpolation: keyed.then(|| {
            let a = params.cache.error;
            cache.interpolation_key(&[a, RELAXED * a])
        }),
        emitters: keyed.then(|| super::replay::emitters_key(ctx.scene)),
    };
    // Pixel samples no record covers read the anchors at their gathers' hits, within the
    // constant D_max (importance-driven density's importons are the update's, not kept).
    let attacher = (method == CachedMethod::Anchors).then(|| Attacher {
        frame: ctx.scene,
        m: ctx.materials,
        pm: &pm,
        k: params.k as usize,
        params: params.anchors,
        scale: ctx.scene.static_radius(),
        importance: None,
    });
    let uncached = match (&attacher, state.anchors.as_ref()) {
        (Some(att), Some(set)) => GatherEstimate::Anchors(att, set),
        _ => estimate,
    };
    let shading = CachedShading {
        cache,
        anchors: state.anchors.as_ref(),
        estimate,
        uncached,
        params: &params.cache,
        light_samples,
        glossy: params.glossy,
        pass: BucketPass::Shade(None),
        replay,
        centres: centres.as_ref(),
    };
    let mut wall = 0.0;
    let mut planning = 0.0;
    let bands = band_pixels.filter(|_| {
        shading.anchors.is_some()
            && params.glossy.mode == GlossyMode::Bucketing
            && params.glossy.may_bucket(ctx.materials.materials)
    });
    let rows = if let Some(band_pixels) = bands {
        let band_rows = (band_pixels / ctx.width.max(1)).max(1);
        let mut rows = Vec::with_capacity(ctx.height as usize);
        for y0 in (0..ctx.height).step_by(band_rows as usize) {
            let band = y0..(y0 + band_rows).min(ctx.height);
            let t = Instant::now();
            let planner = CachedShading {
                pass: BucketPass::Plan,
                replay: Replay {
                    log: false,
                    ..shading.replay
                },
                ..shading
            };
            let planned = super::render_pixel_rows(ctx, spp, &planner, band.clone());
            let first_pixel = band.start * ctx.width;
            let plans = BandPlans::new(
                first_pixel,
                (band.len() as u32 * ctx.width) as usize,
                planned.into_iter().flat_map(|(_, row)| row.plans),
            );
            planning += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let answers = visibility
                .depth_maps()
                .closest(ctx.scene, &plans.queries())?;
            st.depth_maps += t.elapsed().as_secs_f64();
            let plans = BandPlans { answers, ..plans };
            let t = Instant::now();
            let shader = CachedShading {
                pass: BucketPass::Shade(Some(&plans)),
                ..shading
            };
            rows.extend(super::render_pixel_rows(ctx, spp, &shader, band));
            wall += t.elapsed().as_secs_f64();
        }
        rows
    } else {
        let t = Instant::now();
        let rows = super::render_pixel_rows(ctx, spp, &shading, 0..ctx.height);
        wall += t.elapsed().as_secs_f64();
        rows
    };
    let t = Instant::now();
    let (img, mut rows) = super::film::assemble(ctx.width, ctx.height, rows);
    if let Some(slot) = log_slot.filter(|_| replay.log) {
        let logs = rows.iter_mut().map(|r| std::mem::take(&mut r.log));
        let (keys, interpolation) = (replay.keys.cloned(), replay.interpolation);
        let emitters = replay.emitters;
        *slot = ShadingLog::join(ctx.width, ctx.height, spp, logs, keys, known)
            .map(|l| {
                l.with_interpolation_key(interpolation)
                    .with_emitters_key(emitters)
            })
            .unwrap_or_default();
    }
    let mut used: Vec<u32> = rows.iter().flat_map(|r| r.used.iter().copied()).collect();
    used.sort_unstable();
    used.dedup();
    cache.touch(&used, ctx.frame);
    if params.cache.weber_threshold > 0.0 {
        let mut tally = WeberTally::default();
        for r in &rows {
            tally.append(&r.weber);
        }
        let removed = tally.removals(
            cache.len(),
            params.cache.weber_records,
            params.cache.weber_threshold,
        );
        cache.retire(&removed);
        st.caches_retired = removed.len() as u64;
    }
    st.upkeep += t.elapsed().as_secs_f64();
    st.uncached_samples = rows.iter().map(|r| r.uncached).sum();
    st.uncached_rays = rows.iter().map(|r| r.uncached_rays).sum();
    st.rays_shot += st.uncached_rays;
    // The shading pass's wall time, split in proportion to the thread seconds measured at
    // each work site (CachedStats), camera rays and the film's bookkeeping among them.
    let sum = |f: fn(&ShadeRow) -> f64| rows.iter().map(f).sum::<f64>();
    // Direct light and interpolation were timed at a sample of the shaded samples, camera
    // rays at a sample of the pixels.
    let sampled = sum(|r| r.shaded as f64) / sum(|r| r.timed as f64).max(1.0);
    let pixels = sum(|r| r.pixels as f64) / sum(|r| r.pixels_timed as f64).max(1.0);
    let site = [
        sampled * sum(|r| r.t_direct),
        sampled * sum(|r| r.t_interp),
        sum(|r| r.t_gather),
        sum(|r| r.t_estimate),
        pixels * sum(|r| r.t_camera),
    ];
    let threads: f64 = site.iter().sum();
    let share = |i: usize| {
        if threads > 0.0 {
            wall * site[i] / threads
        } else if i == 0 {
            wall
        } else {
            0.0
        }
    };
    st.direct_lighting = share(0);
    st.cache_interpolation = share(1) + planning;
    st.final_gathering += share(2);
    st.irradiance_estimation += share(3);
    st.camera_rays = share(4);
    let counts = RenderCounts::sum(rows.iter().map(|r| &r.counts));
    st.gather_shadow_rays = pm.shadow_rays_cast();
    Ok((img, counts, st))
}

/// The prepare phase of `brute-force` and `precomputed`: stale records dropped, every
/// stratum of every record re-gathered, new records placed (at the camera samples' lookup
/// `samples` too); every gather hit estimated.
fn prepare_brute_force(
    ctx: &FrameContext,
    cache: &mut IrradianceCache,
    cp: &CacheParams,
    estimate: GatherEstimate,
    samples: &[(u32, SurfacePoint)],
    centres: &PixelCentres,
    gt: &mut GatherTimings,
) {
    let m = ctx.materials;
    let radiance = |sp: &SurfacePoint| estimate.radiance(ctx.scene, sp, m);
    let mut brute =
        |fp: &[f32], hits: Vec<Vec<GatherHit>>| gather::estimate_all(fp, hits, &radiance);
    // Brute force re-gathers every stratum every frame: no hit is worth keeping.
    let t = Instant::now();
    cache.dynamic_hits.clear();
    cache.expire(ctx.frame, cp.max_age);
    gt.upkeep += t.elapsed().as_secs_f64();
    cache.regather(ctx.scene, cp, ctx.frame, &mut brute, gt);
    // Samples no record covers gather on the spot in every frame, as brute force does
    // everywhere: no spot records.
    cache.place(
        ctx.scene, ctx.width, ctx.height, cp, ctx.frame, samples, centres, false, &mut brute, gt,
    );
}

/// Pixels per band of the bucketing passes (module doc): enough depth queries per call to
/// keep a GPU busy (tens of thousands of shading points' worth), few enough plans to keep
/// in memory (a few kilobytes each).
pub const BAND_PIXELS: u32 = 8192;

/// The shading pass times direct light, interpolation and the pixels' camera rays in one
/// pixel column of this many ([`ShadeRow`]).
const TIMED_COLUMNS: u32 = 8;

/// Which pass of the shade phase runs (module doc).
#[derive(Clone, Copy)]
enum BucketPass<'a> {
    /// Plans bucketing at every shading point that will bucket; shades nothing.
    Plan,
    /// Shades, finishing each bucketed shading point's plan from the band's answers (`None`:
    /// plans and answers on the spot, on the CPU).
    Shade(Option<&'a BandPlans>),
}

/// A band's bucketing plans in the order the shading meets them, and their depth answers.
struct BandPlans {
    /// Index of the band's first pixel.
    first_pixel: u32,
    /// The plans of the band's pixel i are `starts[i]..starts[i + 1]`.
    starts: Vec<usize>,
    /// Each plan (`None` where no record was valid) and its answers' range.
    plans: Vec<(Option<BucketPlan>, std::ops::Range<usize>)>,
    answers: Vec<Option<Hit>>,
}

impl BandPlans {
    /// Gathers the plans of a band of `pixels` pixels from `first_pixel`, given per plan its
    /// pixel index, in pixel order.
    fn new(
        first_pixel: u32,
        pixels: usize,
        plans: impl Iterator<Item = (u32, Option<BucketPlan>)>,
    ) -> Self {
        let mut band = BandPlans {
            first_pixel,
            starts: vec![0; pixels + 1],
            plans: Vec::new(),
            answers: Vec::new(),
        };
        let mut queries = 0;
        for (pixel, plan) in plans {
            let i = (pixel - first_pixel) as usize;
            if i < pixels {
                band.starts[i + 1] += 1;
            }
            let n = plan.as_ref().map_or(0, BucketPlan::query_count);
            band.plans.push((plan, queries..queries + n));
            queries += n;
        }
        for i in 0..pixels {
            band.starts[i + 1] += band.starts[i];
        }
        band
    }

    /// Every plan's depth queries, in order: each plan fills its own range, in parallel.
    fn queries(&self) -> Vec<DepthQuery> {
        let total = self.plans.last().map_or(0, |(_, r)| r.end);
        let blank = DepthQuery {
            origin: Vec3::ZERO,
            dir: Vec3::ZERO,
        };
        let mut out = vec![blank; total];
        let mut rest = out.as_mut_slice();
        let mut parts = Vec::with_capacity(self.plans.len());
        for (plan, range) in &self.plans {
            let (part, tail) = std::mem::take(&mut rest).split_at_mut(range.len());
            parts.push((plan, part));
            rest = tail;
        }
        parts.into_par_iter().for_each(|(plan, part)| {
            if let Some(plan) = plan {
                for (q, p) in part.iter_mut().zip(plan.queries()) {
                    *q = p;
                }
            }
        });
        out
    }

    /// The plans of pixel `index` (empty outside the band).
    fn of_pixel(&self, index: u32) -> std::ops::Range<usize> {
        match index.checked_sub(self.first_pixel) {
            Some(i) if (i as usize) + 1 < self.starts.len() => {
                self.starts[i as usize]..self.starts[i as usize + 1]
            }
            _ => 0..0,
        }
    }
}

/// The shade phase of the cached methods: direct light by shadow rays, indirect light
/// interpolated from the cache at the pixel centre's surface.
#[derive(Clone, Copy)]
pub struct CachedShading<'a> {
    pub cache: &'a IrradianceCache,
    /// `anchors`: the anchors, for bucketing.
    pub anchors: Option<&'a AnchorSet>,
    /// The estimate at glossy rays' hits.
    pub estimate: GatherEstimate<'a>,
    /// The estimate at the hits of the gathers of pixel samples no record covers.
    pub uncached: GatherEstimate<'a>,
    pub params: &'a CacheParams,
    pub light_samples: u32,
    pub glossy: GlossyParams,
    pass: BucketPass<'a>,
    /// The rays the pass replays and whether it logs its own ([`super::replay`]).
    replay: Replay<'a>,
    /// What the pixel centres' rays hit, where this frame traced them already (a pixel
    /// centre the replay holds reads it from there).
    centres: Option<&'a PixelCentres>,
}

/// How the glossy lobe's indirect light is shaded at camera hits (paper §5, §7). Lobes
/// narrower than `specular_max_roughness` (highly glossy) get `rays` importance-sampled
/// reflection rays per camera sample, each ending in the photon estimate at its hit; lobes up
/// to `max_roughness` (moderately glossy) are gathered by `mode`: anchor bucketing (§5.1,
/// [`super::bucket`]; `anchors` only, the other methods sample) or the same reflection
/// rays; wider lobes are lit from the cache's irradiance through their directional albedo,
/// like the diffuse lobe (exact for uniform incident light).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GlossyParams {
    pub mode: GlossyMode,
    pub rays: u32,
    pub specular_max_roughness: f32,
    pub max_roughness: f32,
    pub bucket: BucketParams,
}

/// How moderately glossy lobes gather their indirect light.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
pub enum GlossyMode {
    /// Anchor bucketing (§5.1).
    #[default]
    Bucketing,
    /// Importance-sampled reflection rays.
    Importance,
}

impl GlossyParams {
    /// Whether some surface of `materials` may be moderately glossy, so bucketed (§5.1): its
    /// roughness (the factor, times a texture's value in [0, 1] where there is one, clamped
    /// as the BRDF clamps it) may lie at or above `specular_max_roughness` and below
    /// `max_roughness`. Where none may, shading needs no planning pass.
    pub fn may_bucket(&self, materials: &[crate::scene::Material]) -> bool {
        materials.iter().any(|m| {
            let hi = m.roughness.clamp(crate::bsdf::MIN_ROUGHNESS, 1.0);
            let lo = if m.metallic_roughness_texture.is_some() {
                crate::bsdf::MIN_ROUGHNESS
            } else {
                hi
            };
            lo < self.max_roughness && hi >= self.specular_max_roughness
        })
    }
}

impl Default for GlossyParams {
    fn default() -> Self {
        GlossyParams {
            mode: GlossyMode::Bucketing,
            rays: 2,
            specular_max_roughness: 0.35,
            max_roughness: crate::bsdf::CACHE_LIT_ROUGHNESS,
            bucket: BucketParams::default(),
        }
    }
}

/// How a camera hit's glossy lobe gets its indirect light.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum GlossyPath {
    Rays,
    Bucket,
    Cache,
}

/// Per-row state of the cached shading pass.
#[derive(Default)]
pub struct ShadeRow {
    counts: RenderCounts,
    /// Records that contributed to a pixel (§4.3: they stay alive).
    used: Vec<u32>,
    /// The last cache read's contributions, and every read's for the Weber rule (§4.3).
    parts: Vec<Contribution>,
    weber: WeberTally,
    /// Thread seconds at the work sites (the rows of [`CachedStats`]): direct light and
    /// interpolation (bucketing and glossy rays included) at the `timed` samples of the
    /// `shaded` ones (a clock read per sample costs a few per cent of the pass: one pixel
    /// column in [`TIMED_COLUMNS`] is timed, a sample of every part of the image), and the
    /// uncached fallback's gather rays and photon look-ups, each timed (they are rare and
    /// long).
    t_direct: f64,
    t_interp: f64,
    t_gather: f64,
    t_estimate: f64,
    /// The timed column's pixels' own work besides the sites above: their camera rays
    /// (the pixel centre's and every sample's, with their surface points) and the film's
    /// bookkeeping — each such pixel's thread seconds from its start to the next pixel's,
    /// less the sites' seconds within it, over `pixels_timed` of the row's `pixels` (a
    /// row's last pixel, with no next one, is left out).
    t_camera: f64,
    pixels: u64,
    pixels_timed: u64,
    /// The timed pixel under way: when it began, and the sites' seconds then.
    pixel_clock: Option<(Instant, f64)>,
    timed: u64,
    shaded: u64,
    uncached: u64,
    /// Gather rays the uncached fallback traced.
    uncached_rays: u64,
    /// The planning pass's bucketing plans, with their pixel's index.
    plans: Vec<(u32, Option<BucketPlan>)>,
    /// The row's camera hits and shadow answers, where the pass logs them.
    log: RowLog,
    /// Cache reads so far in the row (where a relight's next one is in the log).
    reads: usize,
}

impl AsMut<RenderCounts> for ShadeRow {
    fn as_mut(&mut self) -> &mut RenderCounts {
        &mut self.counts
    }
}

/// The surface a pixel's samples are grouped by: one prim, facing one way.
type SurfaceKey = (Motion, u32);

/// What the cache gave a surface of the pixel: irradiance, `anchor_id` AOV value, and the
/// share of its strata re-traced this frame.
#[derive(Clone, Copy)]
struct CacheValue {
    irradiance: Vec3,
    anchor_id: u32,
    reshot: f32,
    /// The incident light's direction, blended from the records like the irradiance (or
    /// fitted to the gather on the spot): what a cache-lit glossy lobe reflects.
    directional: Option<Directional>,
}

impl CacheValue {
    /// What a glossy lobe lit from the cache reflects towards `wo`: the lobe integrated
    /// against the directional fit, or, without one, its directional albedo `albedo` times
    /// the irradiance `e` (already divided by π).
    fn glossy(&self, bsdf: &crate::bsdf::Bsdf, ns: Vec3, wo: Vec3, albedo: Vec3, e: Vec3) -> Vec3 {
        self.directional
            .map_or(albedo * e, |d| d.glossy(bsdf, ns, wo))
    }
}

/// What a cache-lit glossy lobe's light depends on besides the surface: the BRDF's
/// roughness and Fresnel terms (bit patterns: a texture may vary them within a prim).
type GlossyKey = [u32; 7];

fn glossy_key(b: &crate::bsdf::Bsdf) -> GlossyKey {
    [
        b.roughness.to_bits(),
        b.f0.x.to_bits(),
        b.f0.y.to_bits(),
        b.f0.z.to_bits(),
        b.f90.x.to_bits(),
        b.f90.y.to_bits(),
        b.f90.z.to_bits(),
    ]
}

/// The contributing records' directional fits blended with their interpolation weights;
/// `None` if one of them has none.
fn blend_directional(parts: &[Contribution], records: &[Record]) -> Option<Directional> {
    let mut sum = Directional::default();
    let mut wsum = 0.0f32;
    for c in parts {
        sum.add_scaled(records[c.record as usize].directional.as_ref()?, c.weight);
        wsum += c.weight;
    }
    (wsum > 0.0).then(|| sum.scaled(1.0 / wsum))
}

/// Per-pixel state: the pixel centre's surface and the last interpolation.
pub struct CachedPixel {
    index: u32,
    centre: Option<SurfacePoint>,
    last: Option<(SurfaceKey, Vec3, CacheValue)>,
    /// The last bucketed glossy light, by surface.
    bucketed: Option<(SurfaceKey, Vec3, Option<Vec3>)>,
    /// The last cache-lit glossy light, by surface and BRDF: the pixel's other samples on
    /// that surface reuse it, as they reuse the interpolation (their outgoing directions
    /// differ by a fraction of the pixel; the lobe lit this way is rough).
    glossy: Option<(SurfaceKey, Vec3, GlossyKey, Vec3)>,
    /// Shading: the pixel's bucketing plans not yet used, in the band's plans.
    plans: std::ops::Range<usize>,
}

/// Two surface points face the same way for the cache when their shading normals' cosine
/// exceeds this: a pixel's samples share one cache read (and one bucketing) only then.
const SAME_FACING: f32 = 0.999;

/// The pixel centre's camera hit and surface point ([`camera_hit`]: `known` is a logged hit).
fn centre_hit(
    ctx: &FrameContext,
    x: u32,
    y: u32,
    known: Option<Option<Hit>>,
) -> (Option<Hit>, Option<SurfacePoint>) {
    let (_, hit, sp) = camera_hit(
        ctx.scene,
        (x as f32 + 0.5) / ctx.width as f32,
        (y as f32 + 0.5) / ctx.height as f32,
        known,
    );
    (hit, sp)
}

impl CachedPixel {
    /// Pixel `index` with its centre's surface `centre` (module doc of [`CachedShading`]),
    /// and `plans`.
    fn new(index: u32, centre: Option<SurfacePoint>, plans: std::ops::Range<usize>) -> Self {
        CachedPixel {
            index,
            centre,
            last: None,
            bucketed: None,
            glossy: None,
            plans,
        }
    }

    /// Where the pixel's samples on surface `key` read the cache: the pixel centre's surface
    /// point when the sample `sp` lies on that surface, facing the same way, else `sp`.
    fn shading_point<'p>(
        &'p self,
        ctx: &FrameContext,
        key: SurfaceKey,
        sp: &'p SurfacePoint,
    ) -> &'p SurfacePoint {
        match &self.centre {
            Some(c) if CachedShading::key(ctx, c) == key && c.ns.dot(sp.ns) > SAME_FACING => c,
            _ => sp,
        }
    }

    /// Whether sample `sp` (on surface `key`) reads the cache where the pixel's previous
    /// read serves it: the same prim, facing the same way.
    fn reuses_last(&self, key: SurfaceKey, sp: &SurfacePoint) -> Option<CacheValue> {
        match self.last {
            Some((k, n, v)) if k == key && n.dot(sp.ns) > SAME_FACING => Some(v),
            _ => None,
        }
    }
}

/// The points off the pixel centres where this frame's camera samples will read the cache,
/// found by the shading's own choices (`CachedPixel::shading_point`,
/// `CachedPixel::reuses_last`) without shading: the cache places records for those no
/// record covers ([`IrradianceCache::place`]), so that the shading rarely has to gather on
/// the spot. In pixel order. Only pixels whose centre sees another surface than a
/// neighbouring centre (another prim, a normal turned past `SAME_FACING`, or nothing
/// beside something) have their samples traced: inside a surface every sample reads the
/// cache at its pixel centre, and inside the empty background none reads it. A feature
/// smaller than a pixel that no centre sees is missed, and its samples gather on the spot
/// when shaded.
pub fn lookup_points(
    ctx: &FrameContext,
    spp: u32,
    centres: &PixelCentres,
) -> Vec<(u32, SurfacePoint)> {
    use rayon::prelude::*;
    let (w, h) = (ctx.width, ctx.height);
    let centre_points: Vec<Option<SurfacePoint>> = (0..w * h)
        .into_par_iter()
        .map(|i| centres.point(ctx.scene, i % w, i / w))
        .collect();
    let alike = |a: &Option<SurfacePoint>, b: &Option<SurfacePoint>| match (a, b) {
        (Some(a), Some(b)) => {
            CachedShading::key(ctx, a) == CachedShading::key(ctx, b) && a.ns.dot(b.ns) > SAME_FACING
        }
        (None, None) => true,
        _ => false,
    };
    let uniform = |x: u32, y: u32| {
        let c = &centre_points[(y * w + x) as usize];
        [(-1, 0), (1, 0), (0, -1), (0, 1)].iter().all(|&(dx, dy)| {
            let (u, v) = (x as i64 + dx, y as i64 + dy);
            !(0..w as i64).contains(&u)
                || !(0..h as i64).contains(&v)
                || alike(c, &centre_points[(v * w as i64 + u) as usize])
        })
    };
    (0..h)
        .into_par_iter()
        .flat_map_iter(|y| {
            let mut points = Vec::new();
            for x in (0..w).filter(|&x| !uniform(x, y)) {
                let index = y * w + x;
                let mut pixel = CachedPixel::new(index, centre_points[index as usize], 0..0);
                let sampler = super::pixel_sampler(ctx, x, y);
                let cameras = super::pixel_camera_hits(ctx, &sampler, (x, y), spp, |_| None);
                for (ray, hit) in cameras {
                    let Some(sp) =
                        hit.map(|h| SurfacePoint::new(ctx.scene, h, ray.origin, ray.dir))
                    else {
                        continue;
                    };
                    let key = CachedShading::key(ctx, &sp);
                    if pixel.reuses_last(key, &sp).is_some() {
                        continue;
                    }
                    // The pixel centre needs nothing: the finest placement grid covered it.
                    if std::ptr::eq(pixel.shading_point(ctx, key, &sp), &sp) {
                        points.push((index, sp));
                    }
                    let none = CacheValue {
                        irradiance: Vec3::ZERO,
                        anchor_id: 0,
                        reshot: 0.0,
                        directional: None,
                    };
                    pixel.last = Some((key, sp.ns, none));
                }
            }
            points
        })
        .collect()
}

impl CachedShading<'_> {
    fn key(ctx: &FrameContext, sp: &SurfacePoint) -> SurfaceKey {
        (
            sp.hit.motion,
            ctx.scene.geometry(sp.hit.motion).shading[sp.hit.triangle as usize].prim,
        )
    }

    /// Interpolates the cache at `at`. A sample off the placement grid may fall just outside
    /// every record: the threshold is relaxed, then the spot records are read
    /// ([`IrradianceCache::interpolate_spot`]), before gathering on the spot.
    fn lookup(
        &self,
        ctx: &FrameContext,
        at: &SurfacePoint,
        pixel: u32,
        row: &mut ShadeRow,
    ) -> CacheValue {
        let a = self.params.error;
        let parts = &mut row.parts;
        // A relight reads the records the logged read found valid, with their weights.
        let known = self.replay.interpolation(pixel, row.reads);
        row.reads += 1;
        let found = match known {
            Some([]) => None,
            Some(weights) => self
                .cache
                .interpolate_known(at.position, at.ns, weights, parts),
            None => self
                .cache
                .interpolate(at.position, at.ns, a, parts)
                .or_else(|| {
                    self.cache
                        .interpolate(at.position, at.ns, RELAXED * a, parts)
                })
                .or_else(|| {
                    self.cache
                        .interpolate_spot(at.position, at.ns, RELAXED * a, parts)
                }),
        };
        if self.replay.log {
            row.log.interpolation(parts);
        }
        row.used.extend(parts.iter().map(|c| c.record));
        // The Weber rule (§4.3) weighs the open records a pixel reads, not spot records.
        let open = parts
            .first()
            .is_some_and(|c| !self.cache.records[c.record as usize].spot);
        if found.is_some() && open && self.params.weber_threshold > 0.0 {
            row.weber.read(parts);
        }
        match found {
            Some(i) => CacheValue {
                irradiance: i.irradiance,
                anchor_id: AnchorId::aov(
                    self.cache.records[i.dominant_record as usize].dominant_anchor,
                ),
                reshot: i.reshot,
                directional: blend_directional(parts, &self.cache.records),
            },
            None => {
                // Timed apart from interpolation: a final gather and its photon look-ups.
                row.uncached += 1;
                let t0 = Instant::now();
                let hits = gather::trace_strata(
                    ctx.scene,
                    at,
                    gather::uncached_record_id(pixel),
                    self.params,
                );
                let t1 = Instant::now();
                row.uncached_rays += hits.len() as u64;
                let strata = (self.params.strata[0] * self.params.strata[1]) as f32;
                let radiance: Vec<Vec3> = hits
                    .iter()
                    .map(|h| {
                        h.sp.as_ref().map_or(Vec3::ZERO, |sp| {
                            self.uncached.radiance(ctx.scene, sp, ctx.materials)
                        })
                    })
                    .collect();
                let e = radiance.iter().sum::<Vec3>() * (PI / strata);
                let directional = Directional::fit(at.ns, &radiance, self.params.strata);
                row.t_gather += (t1 - t0).as_secs_f64();
                row.t_estimate += t1.elapsed().as_secs_f64();
                CacheValue {
                    irradiance: e,
                    anchor_id: 0,
                    reshot: 1.0,
                    directional,
                }
            }
        }
    }
}

impl Shade for CachedShading<'_> {
    type Row = ShadeRow;
    type Pixel = CachedPixel;

    /// The pixel centre's surface: interpolation for the pixel's samples on that surface
    /// happens there, which does not move with the per-frame sample jitter.
    fn begin_pixel(&self, ctx: &FrameContext, row: &mut ShadeRow, x: u32, y: u32) -> CachedPixel {
        // The timed pixel before this one ends here (ShadeRow::t_camera).
        let timed = x.is_multiple_of(TIMED_COLUMNS);
        if timed || row.pixel_clock.is_some() {
            let now = Instant::now();
            let sites = row.t_direct + row.t_interp + row.t_gather + row.t_estimate;
            if let Some((t0, sites0)) = row.pixel_clock.take() {
                row.t_camera += ((now - t0).as_secs_f64() - (sites - sites0)).max(0.0);
                row.pixels_timed += 1;
            }
            row.pixel_clock = timed.then_some((now, sites));
        }
        row.pixels += 1;
        let index = y * ctx.width + x;
        let plans = match self.pass {
            BucketPass::Shade(Some(band)) => band.of_pixel(index),
            _ => 0..0,
        };
        let known = self
            .replay
            .centre(index)
            .or_else(|| self.centres.map(|c| c.hit(x, y)));
        let (hit, centre) = centre_hit(ctx, x, y, known);
        if self.replay.log && x == 0 {
            let samples = (ctx.width * self.replay.spp * self.light_samples) as usize;
            let lengths = self
                .replay
                .known
                .map_or((samples, samples), |l| l.row_lengths(y));
            row.log.reserve(
                ctx.width,
                self.replay.spp,
                lengths,
                self.replay.logs_camera(),
            );
        }
        if self.replay.logs_camera() {
            row.log.centre(hit);
        }
        CachedPixel::new(index, centre, plans)
    }

    fn known_camera_hit(
        &self,
        ctx: &FrameContext,
        (x, y, s): (u32, u32, u32),
    ) -> Option<Option<crate::accel::Hit>> {
        self.replay.sample(y * ctx.width + x, s)
    }

    fn log_camera_hit(&self, row: &mut ShadeRow, hit: Option<crate::accel::Hit>) {
        if self.replay.log {
            row.log.sample(self.replay.logs_camera().then_some(hit));
        }
    }

    fn sample(
        &self,
        ctx: &FrameContext,
        pixel: &mut CachedPixel,
        row: &mut ShadeRow,
        hit: &CameraHit,
        acc: &mut Accumulator,
    ) {
        if let BucketPass::Plan = self.pass {
            self.plan_sample(ctx, pixel, row, hit);
            return;
        }
        let sp = &hit.sp;
        // Timed in one pixel column of every TIMED_COLUMNS (ShadeRow::t_direct).
        row.shaded += 1;
        let timed = (pixel.index % ctx.width.max(1)).is_multiple_of(TIMED_COLUMNS);
        row.timed += u64::from(timed);
        let t0 = timed.then(Instant::now);
        let bsdf = hit.bsdf(ctx);
        let cast = &mut row.counts.shadow_rays;
        let reused = self
            .replay
            .direct(pixel.index, hit.sample, sp.material, cast, &mut row.log);
        let l_direct = reused.unwrap_or_else(|| {
            let mut shadow =
                self.replay
                    .shadow_rays(pixel.index, hit.sample, sp.material, cast, &mut row.log);
            hit.direct_light(ctx, &bsdf, self.light_samples, &mut shadow)
        });
        if self.replay.log {
            row.log.direct(l_direct);
        }
        let t1 = timed.then(Instant::now);
        let fallback_before = row.t_gather + row.t_estimate;
        // One interpolation per pixel and surface: the pixel's other samples on the same
        // prim, facing the same way, reuse it (records are valid over several pixels).
        let key = Self::key(ctx, sp);
        let value = match pixel.reuses_last(key, sp) {
            Some(v) => v,
            None => {
                let at = pixel.shading_point(ctx, key, sp);
                let v = self.lookup(ctx, at, pixel.index, row);
                pixel.last = Some((key, sp.ns, v));
                v
            }
        };
        acc.note_cache(value.anchor_id, value.reshot);
        let wo = hit.wo();
        let ns = sp.shading_normal(wo);
        let a = bsdf.albedo(ns.dot(wo));
        let e = value.irradiance * FRAC_1_PI;
        let glossy = match self.glossy_path(&bsdf) {
            GlossyPath::Cache => {
                let gk = glossy_key(&bsdf);
                match pixel.glossy {
                    Some((k, n, g, v)) if k == key && g == gk && n.dot(sp.ns) > SAME_FACING => v,
                    _ => {
                        let v = value.glossy(&bsdf, ns, wo, a.glossy, e);
                        pixel.glossy = Some((key, sp.ns, gk, v));
                        v
                    }
                }
            }
            GlossyPath::Rays => self.glossy_indirect(ctx, hit, &bsdf, ns, &mut row.counts),
            GlossyPath::Bucket => {
                let b = match pixel.bucketed {
                    Some((k, n, v)) if k == key && n.dot(sp.ns) > SAME_FACING => v,
                    _ => {
                        let planned = (!pixel.plans.is_empty()).then(|| {
                            pixel.plans.start += 1;
                            pixel.plans.start - 1
                        });
                        let at = pixel.shading_point(ctx, key, sp);
                        let v =
                            self.bucketed(ctx, at, wo, value.irradiance, planned, &mut row.counts);
                        pixel.bucketed = Some((key, sp.ns, v));
                        v
                    }
                };
                match b {
                    Some(v) => v,
                    // No record is valid here: reflection rays, or the cache if there are none.
                    None if self.glossy.rays > 0 => {
                        self.glossy_indirect(ctx, hit, &bsdf, ns, &mut row.counts)
                    }
                    None => value.glossy(&bsdf, ns, wo, a.glossy, e),
                }
            }
        };
        if let (Some(t0), Some(t1)) = (t0, t1) {
            row.t_direct += (t1 - t0).as_secs_f64();
            // Interpolation's share: the sample's time after direct light, less the
            // fallback's.
            let fallback = row.t_gather + row.t_estimate - fallback_before;
            row.t_interp += (t1.elapsed().as_secs_f64() - fallback).max(0.0);
        }
        acc.hit(
            hit.depth(ctx),
            sp.emission(ctx.materials),
            l_direct,
            Lobes {
                diffuse: a.diffuse * e,
                glossy,
            },
        );
    }
}

impl CachedShading<'_> {
    /// Which way a BRDF's glossy lobe is lit ([`GlossyParams`]).
    fn glossy_path(&self, bsdf: &crate::bsdf::Bsdf) -> GlossyPath {
        let g = &self.glossy;
        if !bsdf.has_glossy() || bsdf.roughness >= g.max_roughness {
            return GlossyPath::Cache;
        }
        let bucket = bsdf.roughness >= g.specular_max_roughness
            && g.mode == GlossyMode::Bucketing
            && self.anchors.is_some();
        if bucket {
            GlossyPath::Bucket
        } else if g.rays > 0 {
            GlossyPath::Rays
        } else {
            GlossyPath::Cache
        }
    }

    /// The planning pass at one camera hit: the choices [`Shade::sample`] makes up to
    /// bucketing, and the plan where it buckets a new surface.
    fn plan_sample(
        &self,
        ctx: &FrameContext,
        pixel: &mut CachedPixel,
        row: &mut ShadeRow,
        hit: &CameraHit,
    ) {
        let sp = &hit.sp;
        if self.glossy_path(&hit.bsdf(ctx)) != GlossyPath::Bucket {
            return;
        }
        let key = Self::key(ctx, sp);
        if matches!(pixel.bucketed, Some((k, n, _)) if k == key && n.dot(sp.ns) > SAME_FACING) {
            return;
        }
        let at = pixel.shading_point(ctx, key, sp);
        let plan = self.plan(ctx, at, hit.wo());
        row.plans.push((pixel.index, plan));
        pixel.bucketed = Some((key, sp.ns, None));
    }

    /// Bucketing's plan at `at` for light leaving towards `wo` ([`super::bucket::plan`]).
    fn plan(&self, ctx: &FrameContext, at: &SurfacePoint, wo: Vec3) -> Option<BucketPlan> {
        let bsdf = at.bsdf(ctx.materials);
        let ns = at.shading_normal(wo);
        super::bucket::plan(
            self.cache,
            at,
            (wo, ns, &bsdf),
            self.params.error,
            &self.glossy.bucket,
        )
    }

    /// Anchor bucketing at `at` for light leaving towards `wo` ([`super::bucket`]): the
    /// band's plan `planned` with its answers, or (without one) planned and answered here on
    /// the CPU; `None` where no record is valid there.
    fn bucketed(
        &self,
        ctx: &FrameContext,
        at: &SurfacePoint,
        wo: Vec3,
        irradiance: Vec3,
        planned: Option<usize>,
        counts: &mut RenderCounts,
    ) -> Option<Vec3> {
        let anchors = self.anchors?;
        let band = match self.pass {
            BucketPass::Shade(Some(band)) => Some(band),
            _ => None,
        };
        let here;
        let (plan, depth) = match (band, planned) {
            (Some(band), Some(i)) => {
                let (plan, range) = band.plans.get(i)?;
                (plan.as_ref()?, band.answers.get(range.clone())?)
            }
            _ => {
                let plan = self.plan(ctx, at, wo)?;
                let queries: Vec<DepthQuery> = plan.queries().collect();
                let depth = CpuDepthMaps.closest(ctx.scene, &queries).ok()?;
                here = (plan, depth);
                (&here.0, &here.1[..])
            }
        };
        let mut st = super::bucket::BucketStats::default();
        let fallback = |y: &SurfacePoint| self.estimate.radiance(ctx.scene, y, ctx.materials);
        let v = super::bucket::finish(
            ctx.scene,
            self.cache,
            anchors,
            plan,
            depth,
            irradiance,
            &self.glossy.bucket,
            &fallback,
            &mut st,
        );
        counts.glossy_rays += st.rays;
        Some(v)
    }

    /// The glossy lobe's indirect light at a camera hit by importance-sampled reflection
    /// rays ([`GlossyParams`]): at each ray's hit, the photon estimate reflected by its
    /// albedo, as at a final-gather hit. Emission the rays find is not counted: the direct
    /// light's BRDF sample has it.
    fn glossy_indirect(
        &self,
        ctx: &FrameContext,
        hit: &CameraHit,
        bsdf: &crate::bsdf::Bsdf,
        ns: Vec3,
        counts: &mut RenderCounts,
    ) -> Vec3 {
        let (sampler, s) = (hit.sampler, hit.sample);
        let mut dims = super::shading_dims();
        dims.take(super::DIRECT_DIMS);
        let n = self.glossy.rays;
        let mut sum = Vec3::ZERO;
        for _ in 0..n {
            let dim_dir = dims.take(2);
            let u = [sampler.get(s, dim_dir), sampler.get(s, dim_dir + 1)];
            let Some((wi, f, pdf)) = bsdf.sample_glossy(ns, hit.wo(), u) else {
                continue;
            };
            if wi.dot(hit.sp.ng) <= 0.0 {
                continue;
            }
            counts.glossy_rays += 1;
            let Some(y) = crate::interaction::trace(ctx.scene, hit.sp.spawn(), wi) else {
                continue;
            };
            // The photon estimate at the hit, as at a final-gather hit: it holds the direct
            // light there too.
            let l = self.estimate.radiance(ctx.scene, &y, ctx.materials);
            sum += f * l * (ns.dot(wi) / pdf);
        }
        sum / n as f32
    }
}

#[cfg(test)]
mod tests {
    use super::GlossyParams;
    use crate::scene::Material;
    use crate::scene::material::{TextureRef, UvTransform, Wrap};

    #[test]
    fn only_materials_that_can_be_moderately_glossy_need_bucketing() {
        let g = GlossyParams::default();
        let (lo, hi) = (g.specular_max_roughness, g.max_roughness);
        let with = |roughness: f32, textured: bool| Material {
            roughness,
            metallic_roughness_texture: textured.then_some(TextureRef {
                texture: 0,
                wrap: [Wrap::Repeat; 2],
                transform: UvTransform::IDENTITY,
            }),
            ..Material::default()
        };
        let may = |m: Material| g.may_bucket(&[Material::default(), m]);
        assert!(
            !g.may_bucket(&[Material::default()]),
            "glTF's default is fully rough"
        );
        assert!(may(with(0.5 * (lo + hi), false)));
        assert!(may(with(lo, false)));
        assert!(!may(with(hi, false)), "as rough as the cache takes");
        assert!(
            !may(with(0.5 * lo, false)),
            "highly glossy: reflection rays"
        );
        // A texture scales the factor by [0, 1]: a rough factor may become glossy, a highly
        // glossy one stays so.
        assert!(may(with(1.0, true)));
        assert!(!may(with(0.5 * lo, true)));
        assert!(!g.may_bucket(&[]));
    }
}
