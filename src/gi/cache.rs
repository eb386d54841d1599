//! The irradiance cache (Ward, Rubinstein & Clear 1988; the paper's §2.1, §4.1, §4.3):
//! records placed on surfaces seen by the camera, each holding the irradiance from a
//! stratified final gather over its hemisphere, the harmonic-mean distance to what the
//! gather hit, translational and rotational gradients (Ward & Heckbert 1992), and its strata
//! — distance, flags and incoming radiance per direction — which the anchor method reuses
//! (§4.1 `RadianceSample`).
//!
//! Placement is deterministic and parallel: image-space grids from coarse to fine; at each
//! level every grid pixel whose surface point no record covers gets a record, all records of
//! a level are gathered in parallel and inserted in pixel order. Validity radii are clamped
//! to a range of pixel footprints (Tabellion & Lamorlette 2004), so density follows the image.
//!
//! Gradients follow the stratified formulation of Ward & Heckbert for cosine-weighted
//! strata (as given in Křivánek & Gautron, "Practical Global Illumination with Irradiance
//! Caching", 2009, §2.2).

use std::f32::consts::PI;

use glam::Vec3;
use rayon::prelude::*;

use super::photons::basis;
use crate::render::SurfacePoint;
use crate::sampling::hash;
use crate::scene::{FrameCamera, FrameScene, Motion, Projection};

/// Stratum flag: the gather ray hit a dynamic prim (its radiance was estimated directly).
pub const HIT_DYNAMIC: u8 = 1;

/// One gather direction of a record (the paper's `RadianceSample`, §4.1) in 6 bytes: a
/// 30-bit anchor link with two flag bits, and the hit distance as an f16 in units of the
/// record's pixel footprint (scale-free: the same bits at 1e−3 and 1e4; infinite on a miss).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[repr(C)]
pub struct Stratum([u16; 3]);

impl Stratum {
    pub fn new(link: u32, flags: u8, distance: f32, scale: f32) -> Self {
        let link = link.min(NO_LINK);
        let d = if distance.is_finite() {
            half::f16::from_f32((distance / scale).min(65504.0)).to_bits()
        } else {
            half::f16::INFINITY.to_bits()
        };
        Stratum([
            link as u16,
            (link >> 16) as u16 | (flags as u16 & 3) << 14,
            d,
        ])
    }

    /// The anchor the stratum's ray reaches, if it hit static geometry in the anchor method.
    pub fn link(&self) -> Option<u32> {
        let l = self.0[0] as u32 | ((self.0[1] as u32) & 0x3fff) << 16;
        (l != NO_LINK).then_some(l)
    }

    pub fn flags(&self) -> u8 {
        (self.0[1] >> 14) as u8
    }

    pub fn set_flags(&mut self, flags: u8) {
        self.0[1] = (self.0[1] & 0x3fff) | (flags as u16 & 3) << 14;
    }

    /// Hit distance given the record's footprint `scale`; infinite on a miss.
    pub fn distance(&self, scale: f32) -> f32 {
        half::f16::from_bits(self.0[2]).to_f32() * scale
    }

    pub fn hit(&self) -> bool {
        half::f16::from_bits(self.0[2]).is_finite()
    }
}

/// "No anchor" in a stratum's link.
pub const NO_LINK: u32 = (1 << 30) - 1;

/// An irradiance cache record.
#[derive(Debug, Clone)]
pub struct Record {
    pub position: Vec3,
    pub normal: Vec3,
    pub irradiance: Vec3,
    /// Ward's R_i: harmonic-mean hit distance, clamped so that a·R_i lies between the
    /// minimum and maximum spacing in pixel footprints.
    pub radius: f32,
    /// Rotational and translational gradients, per colour channel (R, G, B).
    pub grad_r: [Vec3; 3],
    pub grad_t: [Vec3; 3],
    pub motion: Motion,
    /// Seeds the record's stratum jitter: the same directions every frame.
    pub id: u32,
    /// Last frame in which the record contributed to a pixel (§4.3).
    pub last_used: i32,
    /// Pixel footprint at creation, for clamping the radius when re-gathered.
    pub footprint: f32,
    /// Ray-origin offset and geometric normal of the surface the record sits on.
    pub offset: f32,
    pub ng: Vec3,
    pub strata: Vec<Stratum>,
    /// Fraction of the strata traced this frame (1 for brute force and new records).
    pub reshot: f32,
    /// The anchor contributing most of the record's irradiance (`NO_LINK` if none).
    pub dominant_anchor: u32,
}

impl Record {
    /// First-order irradiance at (x, n) from the record's gradients (Ward & Heckbert 1992):
    /// E_i + (n × n_i)·∇_r E_i + (x − x_i)·∇_t E_i, with ∇_r as [`gradients`] computes it.
    pub fn extrapolate(&self, x: Vec3, n: Vec3) -> Vec3 {
        let rot = n.cross(self.normal);
        let dx = x - self.position;
        self.irradiance
            + Vec3::from_array(std::array::from_fn(|c| {
                rot.dot(self.grad_r[c]) + dx.dot(self.grad_t[c])
            }))
    }
}

/// Irradiance-cache settings ([`CacheParams::default`] = the `production` preset).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CacheParams {
    /// Strata in θ (M) and φ (N); M·N gather rays per record. Default 12×36 = 432.
    pub strata: [u32; 2],
    /// Ward's error threshold a: a record is used where its weight exceeds 1/a. Default 0.25.
    pub error: f32,
    /// A record is valid out to a·R_i; that distance is clamped to [min, max] pixel
    /// footprints. Defaults 2 and 24.
    pub min_spacing_px: f32,
    pub max_spacing_px: f32,
    /// Frames a record may go unused before it is removed (§4.3). Default 2.
    pub max_age: u32,
}

impl Default for CacheParams {
    fn default() -> Self {
        CacheParams {
            strata: [12, 36],
            error: 0.25,
            min_spacing_px: 2.0,
            max_spacing_px: 24.0,
            max_age: 2,
        }
    }
}

/// What [`IrradianceCache::interpolate`] found.
#[derive(Debug, Clone, Copy)]
pub struct Interpolated {
    pub irradiance: Vec3,
    /// Weighted fraction of the contributing records' strata traced this frame.
    pub reshot: f32,
    /// The record with the largest weight.
    pub dominant_record: u32,
}

/// Turns one gather's hits into strata and their radiance: the method's part of a gather
/// (brute force estimates every hit; anchors link static hits to anchors). Arguments: the
/// records' footprints (distance units) and their hits, in record order.
pub type Resolve<'a> =
    dyn FnMut(&[f32], Vec<Vec<GatherHit>>) -> Vec<(Vec<Stratum>, Vec<Vec3>)> + 'a;

/// The brute-force resolver: radiance at every hit from `radiance`, no links.
pub fn estimate_all(
    footprints: &[f32],
    hits: Vec<Vec<GatherHit>>,
    radiance: &(dyn Fn(&SurfacePoint) -> Vec3 + Sync),
) -> Vec<(Vec<Stratum>, Vec<Vec3>)> {
    hits.into_par_iter()
        .zip(footprints.par_iter())
        .map(|(h, &scale)| {
            let strata = h
                .iter()
                .map(|g| {
                    let flags = match &g.sp {
                        Some(sp) if sp.hit.motion == Motion::Dynamic => HIT_DYNAMIC,
                        _ => 0,
                    };
                    Stratum::new(NO_LINK, flags, g.distance, scale)
                })
                .collect();
            let rad = h
                .iter()
                .map(|g| g.sp.as_ref().map_or(Vec3::ZERO, radiance))
                .collect();
            (strata, rad)
        })
        .collect()
}

/// Where a gather ray went, before its radiance is estimated.
#[derive(Debug, Clone, Copy)]
pub struct GatherHit {
    pub sp: Option<SurfacePoint>,
    pub distance: f32,
}

/// Records by the space their validity spheres cover: a multi-level hashed grid (in the
/// spirit of Ward's octree). A record of reach ρ = `REACH`·a·R_i sits at the level whose
/// cells are at least 2ρ wide, in the ≤ 8 cells its sphere overlaps, so a lookup reads one
/// cell per level and meets only records that can be valid there.
#[derive(Default)]
struct RecordGrid {
    /// Cell size of level 0 (set from the first record: scale-free).
    base: f32,
    /// Ward's a the grid was built for.
    error: f32,
    cells: rustc_hash::FxHashMap<(i32, i32, i32, i32), Vec<u32>>,
    levels: std::collections::BTreeSet<i32>,
}

/// Lookups may relax Ward's threshold up to this factor (the shading fallback uses 2).
const REACH: f32 = 2.0;

impl RecordGrid {
    fn cell(&self, level: i32, p: Vec3) -> (i32, i32, i32, i32) {
        let size = self.base * 2f32.powi(level);
        let c = (p / size).floor();
        (level, c.x as i32, c.y as i32, c.z as i32)
    }

    fn insert(&mut self, i: u32, r: &Record) {
        let a = if self.error > 0.0 { self.error } else { 1.0 };
        let reach = REACH * a * r.radius;
        if self.base == 0.0 {
            self.base = (2.0 * reach).max(f32::MIN_POSITIVE);
        }
        let level = (2.0 * reach / self.base).log2().ceil().max(-60.0) as i32;
        let (lo, hi) = (
            self.cell(level, r.position - reach),
            self.cell(level, r.position + reach),
        );
        for x in lo.1..=hi.1 {
            for y in lo.2..=hi.2 {
                for z in lo.3..=hi.3 {
                    self.cells.entry((level, x, y, z)).or_default().push(i);
                }
            }
        }
        self.levels.insert(level);
    }

    /// Records whose sphere may contain `x`, in index order.
    fn candidates(&self, x: Vec3, out: &mut Vec<u32>) {
        out.clear();
        for &l in &self.levels {
            if let Some(c) = self.cells.get(&self.cell(l, x)) {
                out.extend_from_slice(c);
            }
        }
        out.sort_unstable();
    }
}

/// The cache with its lookup grid.
#[derive(Default)]
pub struct IrradianceCache {
    pub records: Vec<Record>,
    grid: RecordGrid,
    next_id: u32,
}

/// World size of one pixel at `x` as seen by `camera` for an image `height` pixels tall.
pub fn pixel_footprint(camera: &FrameCamera, x: Vec3, height: u32) -> f32 {
    match camera.projection {
        Projection::Perspective { yfov } => {
            let depth = (x - camera.origin)
                .dot(camera.forward)
                .abs()
                .max(f32::MIN_POSITIVE);
            depth * 2.0 * (0.5 * yfov).tan() / height as f32
        }
        Projection::Orthographic { ymag } => 2.0 * ymag / height as f32,
    }
}

/// Direction of stratum (j, k) with jitter (u, v): cosine-weighted, θ from j, φ from k.
fn stratum_direction(m: u32, n: u32, j: u32, k: u32, u: f32, v: f32) -> (f32, f32) {
    let sin2 = (j as f32 + u) / m as f32;
    let phi = 2.0 * PI * (k as f32 + v) / n as f32;
    (sin2, phi)
}

impl IrradianceCache {
    pub fn len(&self) -> usize {
        self.records.len()
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// Rebuilds the lookup grid (after records were removed or changed).
    fn rebuild_tree(&mut self) {
        let error = self.grid.error;
        self.grid = RecordGrid {
            error,
            ..Default::default()
        };
        for (i, r) in self.records.iter().enumerate() {
            self.grid.insert(i as u32, r);
        }
    }

    /// Sets Ward's a the lookups will use (at most `REACH` times it).
    pub fn set_error(&mut self, a: f32) {
        if self.grid.error != a {
            self.grid.error = a;
            self.rebuild_tree();
        }
    }

    /// Drops dynamic records, and static ones unused for more than `max_age` frames (§4.3).
    pub fn expire(&mut self, frame: i32, max_age: u32) {
        self.records
            .retain(|r| r.motion == Motion::Static && frame - r.last_used <= max_age as i32);
        self.rebuild_tree();
    }

    fn insert(&mut self, r: Record) {
        self.grid.insert(self.records.len() as u32, &r);
        self.records.push(r);
    }

    /// Ward's weight of record `r` at (x, n), or 0 where it must not be used: behind x, or
    /// facing away. w = 1 / (|x − x_i|/R_i + sqrt(1 − n·n_i)).
    fn weight(r: &Record, x: Vec3, n: Vec3) -> f32 {
        let ndot = n.dot(r.normal);
        if ndot <= 0.0 {
            return 0.0;
        }
        let d = x - r.position;
        // Ward's "in front" test: reject records in front of x.
        if d.dot(n + r.normal) * 0.5 < -0.05 * r.radius {
            return 0.0;
        }
        // Capped at 1e4: at a record's own position the weight is infinite, and weighted sums
        // must stay finite (pixel centres land exactly on records placed there).
        let e = d.length() / r.radius + (1.0 - ndot).max(0.0).sqrt();
        1.0 / e.max(1e-4)
    }

    /// Interpolated irradiance at (x, n) from records whose weight exceeds 1/a, with
    /// gradients; `None` where no record is valid. `used` receives contributing records.
    pub fn interpolate(
        &self,
        x: Vec3,
        n: Vec3,
        a: f32,
        used: &mut Vec<u32>,
    ) -> Option<Interpolated> {
        if self.records.is_empty() {
            return None;
        }
        debug_assert!(
            a <= REACH * self.grid.error * 1.0001,
            "lookup beyond the grid's reach"
        );
        let mut sum = Vec3::ZERO;
        let mut wsum = 0.0f32;
        let mut reshot = 0.0f32;
        let mut dominant = (0.0f32, NO_LINK);
        let mut idx = Vec::new();
        self.grid.candidates(x, &mut idx);
        for i in idx {
            let r = &self.records[i as usize];
            let w = Self::weight(r, x, n);
            if w <= 1.0 / a {
                continue;
            }
            sum += w * r.extrapolate(x, n).max(Vec3::ZERO);
            wsum += w;
            reshot += w * r.reshot;
            if w > dominant.0 {
                dominant = (w, i);
            }
            used.push(i);
        }
        (wsum > 0.0).then(|| Interpolated {
            irradiance: sum / wsum,
            reshot: reshot / wsum,
            dominant_record: dominant.1,
        })
    }

    /// True if some record is valid at (x, n).
    pub fn covers(&self, x: Vec3, n: Vec3, a: f32) -> bool {
        if self.records.is_empty() {
            return false;
        }
        let mut idx = Vec::new();
        self.grid.candidates(x, &mut idx);
        idx.iter()
            .any(|&i| Self::weight(&self.records[i as usize], x, n) > 1.0 / a)
    }

    /// Direction of stratum `s` of a record with shading normal `ns` and id `id`: the
    /// jitter inside the stratum depends on the id only, so a record's rays are the same in
    /// every frame.
    pub fn stratum_dir(ns: Vec3, id: u32, p: &CacheParams, s: u32) -> Vec3 {
        let [m, n] = p.strata;
        let (t, b) = basis(ns);
        let seed = hash(&[id, 0x6a7e_0001]);
        let (j, k) = (s / n, s % n);
        let u = sobol_burley::sample(s, 0, seed);
        let v = sobol_burley::sample(s, 1, seed);
        let (sin2, phi) = stratum_direction(m, n, j, k, u, v);
        let st = sin2.sqrt();
        (t * (st * phi.cos()) + b * (st * phi.sin()) + ns * (1.0 - sin2).max(0.0).sqrt())
            .normalize()
    }

    /// Traces stratum `s` of the record at `sp`.
    pub fn trace_stratum(
        frame: &FrameScene,
        sp: &SurfacePoint,
        id: u32,
        p: &CacheParams,
        s: u32,
    ) -> GatherHit {
        let dir = Self::stratum_dir(sp.ns, id, p, s);
        let miss = GatherHit {
            sp: None,
            distance: f32::INFINITY,
        };
        if dir.dot(sp.ng) <= 0.0 {
            return miss;
        }
        let o = sp.spawn();
        match frame.accel.closest(
            &frame.static_geometry,
            &frame.dynamic_geometry,
            o,
            dir,
            f32::INFINITY,
        ) {
            Some(h) => GatherHit {
                sp: Some(SurfacePoint::new(frame, h, o, dir)),
                distance: h.t,
            },
            None => miss,
        }
    }

    /// Traces every gather ray of a record at `sp`.
    pub fn trace_strata(
        frame: &FrameScene,
        sp: &SurfacePoint,
        id: u32,
        p: &CacheParams,
    ) -> Vec<GatherHit> {
        (0..p.strata[0] * p.strata[1])
            .map(|s| Self::trace_stratum(frame, sp, id, p, s))
            .collect()
    }

    /// Completes a record from its strata: irradiance E = π/(MN) Σ L, harmonic-mean radius
    /// clamped to [min, max] footprints, and gradients.
    #[allow(clippy::too_many_arguments)] // a record's every part
    pub fn finish_record(
        sp: &SurfacePoint,
        motion: Motion,
        id: u32,
        footprint: f32,
        strata: Vec<Stratum>,
        radiance: &[Vec3],
        p: &CacheParams,
        frame: i32,
    ) -> Record {
        let [m, n] = p.strata;
        let scale = PI / (m * n) as f32;
        let irradiance = radiance.iter().sum::<Vec3>() * scale;
        let inv: f32 = strata
            .iter()
            .filter(|s| s.hit())
            .map(|s| 1.0 / s.distance(footprint).max(f32::MIN_POSITIVE))
            .sum();
        let harmonic = if inv > 0.0 {
            (m * n) as f32 / inv
        } else {
            f32::INFINITY
        };
        // Clamp so that the region where the record is valid (distance < a·R) spans between
        // min and max pixel footprints (Tabellion & Lamorlette 2004).
        let radius = harmonic.clamp(
            p.min_spacing_px * footprint / p.error,
            p.max_spacing_px * footprint / p.error,
        );
        let r_min = p.min_spacing_px * footprint / p.error;
        let (grad_r, mut grad_t) = gradients(&strata, radiance, footprint, sp.ns, m, n, r_min);
        // Gradient limiting (Křivánek et al. 2006): extrapolation across the region where the
        // record is valid (a·R_i) may change each channel by at most its own value, so noisy
        // radiance next to a corner cannot turn into a large gradient.
        for c in 0..3 {
            let limit = irradiance[c] / (p.error * radius).max(f32::MIN_POSITIVE);
            let g = grad_t[c].length();
            if g > limit {
                grad_t[c] *= limit / g;
            }
        }
        Record {
            position: sp.position,
            normal: sp.ns,
            irradiance,
            radius,
            grad_r,
            grad_t,
            motion,
            id,
            last_used: frame,
            footprint,
            offset: sp.offset,
            ng: sp.ng,
            strata,
            reshot: 1.0,
            dominant_anchor: NO_LINK,
        }
    }

    /// Re-gathers every record (brute force: every frame, every stratum).
    pub fn regather(
        &mut self,
        frame: &FrameScene,
        p: &CacheParams,
        frame_number: i32,
        resolve: &mut Resolve,
        timings: &mut GatherTimings,
    ) {
        let t0 = std::time::Instant::now();
        let hits: Vec<Vec<GatherHit>> = self
            .records
            .par_iter()
            .map(|r| Self::trace_strata(frame, &r.surface_point(), r.id, p))
            .collect();
        timings.final_gathering += t0.elapsed().as_secs_f64();
        timings.rays += hits.iter().map(|h| h.len() as u64).sum::<u64>();
        let t1 = std::time::Instant::now();
        let footprints: Vec<f32> = self.records.iter().map(|r| r.footprint).collect();
        let resolved = resolve(&footprints, hits);
        let updated: Vec<Record> = self
            .records
            .par_iter()
            .zip(resolved)
            .map(|(r, (strata, rad))| r.with_strata(strata, &rad, p, frame_number))
            .collect();
        timings.irradiance_estimation += t1.elapsed().as_secs_f64();
        self.records = updated;
        self.rebuild_tree();
    }

    /// Places new records where the image needs them (module doc): levels of `2^l`-pixel
    /// grids from `coarsest` down to 1.
    #[allow(clippy::too_many_arguments)] // placement needs the view and the method
    pub fn place(
        &mut self,
        frame: &FrameScene,
        width: u32,
        height: u32,
        p: &CacheParams,
        frame_number: i32,
        resolve: &mut Resolve,
        timings: &mut GatherTimings,
    ) {
        let coarsest = 16u32;
        let mut spacing = coarsest;
        loop {
            let level_first = spacing == coarsest;
            let candidates: Vec<(u32, u32)> = (0..height)
                .step_by(spacing as usize)
                .flat_map(|y| (0..width).step_by(spacing as usize).map(move |x| (x, y)))
                .filter(|&(x, y)| level_first || x % (2 * spacing) != 0 || y % (2 * spacing) != 0)
                .collect();
            let needed: Vec<(u32, SurfacePoint)> = candidates
                .par_iter()
                .filter_map(|&(x, y)| {
                    let (o, d) = frame.camera.ray(
                        (x as f32 + 0.5) / width as f32,
                        (y as f32 + 0.5) / height as f32,
                    );
                    let sp = crate::render::trace(frame, o, d)?;
                    (!self.covers(sp.position, sp.ns, p.error)).then_some((y * width + x, sp))
                })
                .collect();
            self.add_records(frame, &needed, height, p, frame_number, resolve, timings);
            if spacing == 1 {
                break;
            }
            spacing /= 2;
        }
    }

    /// Gathers and inserts records at the given surface points (in order).
    #[allow(clippy::too_many_arguments)]
    pub fn add_records(
        &mut self,
        frame: &FrameScene,
        points: &[(u32, SurfacePoint)],
        height: u32,
        p: &CacheParams,
        frame_number: i32,
        resolve: &mut Resolve,
        timings: &mut GatherTimings,
    ) {
        if points.is_empty() {
            return;
        }
        let first_id = self.next_id;
        self.next_id += points.len() as u32;
        let t0 = std::time::Instant::now();
        let hits: Vec<Vec<GatherHit>> = points
            .par_iter()
            .enumerate()
            .map(|(i, (_, sp))| Self::trace_strata(frame, sp, first_id + i as u32, p))
            .collect();
        timings.final_gathering += t0.elapsed().as_secs_f64();
        timings.rays += hits.iter().map(|h| h.len() as u64).sum::<u64>();
        let t1 = std::time::Instant::now();
        let footprints: Vec<f32> = points
            .iter()
            .map(|(_, sp)| pixel_footprint(&frame.camera, sp.position, height))
            .collect();
        let resolved = resolve(&footprints, hits);
        let records: Vec<Record> = points
            .par_iter()
            .zip(resolved)
            .enumerate()
            .map(|(i, ((_, sp), (strata, rad)))| {
                Self::finish_record(
                    sp,
                    sp.hit.motion,
                    first_id + i as u32,
                    footprints[i],
                    strata,
                    &rad,
                    p,
                    frame_number,
                )
            })
            .collect();
        timings.irradiance_estimation += t1.elapsed().as_secs_f64();
        for r in records {
            self.insert(r);
        }
    }

    /// Replaces every record (same count, same order) and rebuilds the lookup tree.
    pub fn replace_records(&mut self, records: Vec<Record>) {
        self.records = records;
        self.rebuild_tree();
    }

    /// Marks records as used in `frame`.
    pub fn touch(&mut self, used: &[u32], frame: i32) {
        for &i in used {
            self.records[i as usize].last_used = frame;
        }
    }
}

/// Seconds and rays spent gathering, split as in the paper's Table 1.
#[derive(Debug, Clone, Copy, Default)]
pub struct GatherTimings {
    /// Tracing gather rays.
    pub final_gathering: f64,
    /// Estimating radiance at gather hits (photon lookups).
    pub irradiance_estimation: f64,
    pub rays: u64,
}

impl Record {
    /// The record re-made from new strata at its own position; id, footprint and last use
    /// are kept.
    pub fn with_strata(
        &self,
        strata: Vec<Stratum>,
        radiance: &[Vec3],
        p: &CacheParams,
        frame: i32,
    ) -> Record {
        let mut new = IrradianceCache::finish_record(
            &self.surface_point(),
            self.motion,
            self.id,
            self.footprint,
            strata,
            radiance,
            p,
            frame,
        );
        new.last_used = self.last_used;
        new
    }

    /// The surface point of the record, for re-gathering from its own position and normal.
    pub fn surface_point(&self) -> SurfacePoint {
        SurfacePoint {
            position: self.position,
            ng: self.ng,
            ns: self.normal,
            uv: glam::Vec2::ZERO,
            offset: self.offset,
            material: 0,
            front: true,
            hit: crate::accel::Hit {
                t: 0.0,
                motion: self.motion,
                triangle: 0,
            },
        }
    }
}

/// Rotational and translational irradiance gradients from cosine-weighted strata (Ward &
/// Heckbert 1992, in the form of Křivánek & Gautron 2009, eqs. 2.13–2.14):
///
/// ∇_r E = π/(MN) Σ_k v_k Σ_j −tan θ_j L_jk
/// ∇_t E = Σ_k [ u_k (2π/N) Σ_{j≥1} sin θ_j− cos² θ_j− / min(r_{j−1,k}, r_jk) (L_jk − L_{j−1,k})
///             + v_k− Σ_j (sin θ_j+ − sin θ_j−) / min(r_jk, r_{j,k−1}) (L_jk − L_{j,k−1}) ]
///
/// Distances below `r_min` (the record's smallest radius) count as `r_min`: a gather ray that
/// grazes a corner says little about how irradiance changes over the record's extent.
fn gradients(
    strata: &[Stratum],
    radiance: &[Vec3],
    scale: f32,
    n: Vec3,
    m: u32,
    nn: u32,
    r_min: f32,
) -> ([Vec3; 3], [Vec3; 3]) {
    let (t, b) = basis(n);
    let mut gr = [Vec3::ZERO; 3];
    let mut gt = [Vec3::ZERO; 3];
    let idx = |j: u32, k: u32| (j * nn + (k % nn)) as usize;
    let dist = |i: usize| strata[i].distance(scale);
    for k in 0..nn {
        let phi_c = 2.0 * PI * (k as f32 + 0.5) / nn as f32;
        let phi_m = 2.0 * PI * k as f32 / nn as f32;
        let u_k = t * phi_c.cos() + b * phi_c.sin();
        let v_k = -t * phi_c.sin() + b * phi_c.cos();
        let v_km = -t * phi_m.sin() + b * phi_m.cos();
        let mut rot = Vec3::ZERO;
        let mut theta_term = Vec3::ZERO;
        let mut phi_term = Vec3::ZERO;
        for j in 0..m {
            let s = idx(j, k);
            let sin_c = ((j as f32 + 0.5) / m as f32).sqrt();
            let tan_c = sin_c / (1.0 - sin_c * sin_c).max(1e-12).sqrt();
            rot -= tan_c * radiance[s];
            let sin_m = (j as f32 / m as f32).sqrt();
            let sin_p = ((j + 1) as f32 / m as f32).sqrt();
            if j > 0 {
                let prev = idx(j - 1, k);
                let r = dist(prev).min(dist(s)).max(r_min);
                if r.is_finite() && r > 0.0 {
                    let cos2 = 1.0 - sin_m * sin_m;
                    theta_term += (sin_m * cos2 / r) * (radiance[s] - radiance[prev]);
                }
            }
            let left = idx(j, k + nn - 1);
            let r = dist(left).min(dist(s)).max(r_min);
            if r.is_finite() && r > 0.0 {
                phi_term += ((sin_p - sin_m) / r) * (radiance[s] - radiance[left]);
            }
        }
        rot *= PI / (m * nn) as f32;
        theta_term *= 2.0 * PI / nn as f32;
        for c in 0..3 {
            gr[c] += v_k * rot[c];
            gt[c] += u_k * theta_term[c] + v_km * phi_term[c];
        }
    }
    (gr, gt)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::frame::triangle;

    #[test]
    fn strata_fit_in_six_bytes_and_round_trip() {
        assert_eq!(size_of::<Stratum>(), 6);
        for scale in [1e-3f32, 1.0, 1e4] {
            let s = Stratum::new(123_456, HIT_DYNAMIC, 37.5 * scale, 0.01 * scale);
            assert_eq!(s.link(), Some(123_456));
            assert_eq!(s.flags(), HIT_DYNAMIC);
            assert!((s.distance(0.01 * scale) - 37.5 * scale).abs() < 37.5 * scale * 1e-3);
            let miss = Stratum::new(NO_LINK, 0, f32::INFINITY, scale);
            assert!(!miss.hit() && miss.link().is_none());
        }
    }
    use crate::scene::{FrameScene, Geometry, Material, StaticSet, TriangleShading};
    use glam::Vec2;

    /// A floor (y = 0) and a wall (x = 0, height 1, long in z) whose face towards +x emits
    /// radiance 1 into the gather (the radiance estimate below). From the floor at distance
    /// d the wall's view factor is F = (1 − d/√(d² + 1))/2, so E = πF and
    /// dE/dd = −(π/2)/(d² + 1)^{3/2}.
    fn scene() -> FrameScene {
        let mut g = Geometry::default();
        let quad = |g: &mut Geometry, a: Vec3, b: Vec3, c: Vec3, d: Vec3| {
            for t in [triangle(a, b, c), triangle(a, c, d)] {
                let n = Vec3::from((t.v1 - t.v0).cross(t.v2 - t.v0)).normalize();
                g.triangles.push(t);
                g.shading.push(TriangleShading {
                    normals: [n; 3],
                    uvs: [Vec2::ZERO; 3],
                    material: 0,
                    prim: 0,
                });
            }
        };
        let l = 200.0;
        quad(
            &mut g,
            Vec3::new(-l, 0.0, -l),
            Vec3::new(-l, 0.0, l),
            Vec3::new(l, 0.0, l),
            Vec3::new(l, 0.0, -l),
        );
        quad(
            &mut g,
            Vec3::new(0.0, 0.0, -l),
            Vec3::new(0.0, 1.0, -l),
            Vec3::new(0.0, 1.0, l),
            Vec3::new(0.0, 0.0, l),
        );
        let statics = StaticSet::new(g);
        let camera = crate::scene::FrameCamera::look_at(
            Vec3::new(3.0, 2.0, 0.0),
            Vec3::ZERO,
            Vec3::Y,
            1.0,
            1.0,
        );
        FrameScene::new(
            &statics,
            Geometry::default(),
            Vec::new(),
            camera,
            &[Material::default()],
        )
    }

    fn wall_radiance(sp: &SurfacePoint) -> Vec3 {
        if sp.ng.x > 0.5 { Vec3::ONE } else { Vec3::ZERO }
    }

    fn record_at(frame: &FrameScene, d: f32, p: &CacheParams) -> Record {
        let o = Vec3::new(d, 0.5, 0.25);
        let hit = frame
            .accel
            .closest(
                &frame.static_geometry,
                &frame.dynamic_geometry,
                o,
                -Vec3::Y,
                f32::INFINITY,
            )
            .unwrap();
        let sp = SurfacePoint::new(frame, hit, o, -Vec3::Y);
        let hits = IrradianceCache::trace_strata(frame, &sp, 3, p);
        let (strata, rad) = estimate_all(&[1e-3], vec![hits], &wall_radiance).remove(0);
        IrradianceCache::finish_record(&sp, Motion::Static, 3, 1e-3, strata, &rad, p, 0)
    }

    #[test]
    fn irradiance_and_translational_gradient_match_the_view_factor() {
        let frame = scene();
        let p = CacheParams {
            strata: [40, 120],
            ..CacheParams::default()
        };
        for d in [0.5f32, 1.0, 2.0] {
            let r = record_at(&frame, d, &p);
            let e = std::f32::consts::FRAC_PI_2 * (1.0 - d / (d * d + 1.0).sqrt());
            let de = -std::f32::consts::FRAC_PI_2 / (d * d + 1.0).powf(1.5);
            assert!(
                (r.irradiance.x - e).abs() < 0.025 * e,
                "d {d}: E {} vs {e}",
                r.irradiance.x
            );
            let g = r.grad_t[0];
            assert!(
                (g.x - de).abs() < 0.1 * de.abs(),
                "d {d}: dE/dx {} vs {de}",
                g.x
            );
            assert!(
                g.y.abs() < 0.05 * de.abs() && g.z.abs() < 0.05 * de.abs(),
                "d {d}: gradient {g}"
            );
        }
    }

    /// Tilting the normal towards the wall by δ changes E by (n × n')·∇_r E to first order;
    /// compared with a second gather at the tilted normal.
    #[test]
    fn rotational_gradient_predicts_a_tilted_gather() {
        let frame = scene();
        let p = CacheParams {
            strata: [40, 120],
            ..CacheParams::default()
        };
        let r = record_at(&frame, 1.0, &p);
        let delta = 0.05f32;
        let n2 = Vec3::new(-delta.sin(), delta.cos(), 0.0);
        let o = Vec3::new(1.0, 0.5, 0.25);
        let hit = frame
            .accel
            .closest(
                &frame.static_geometry,
                &frame.dynamic_geometry,
                o,
                -Vec3::Y,
                f32::INFINITY,
            )
            .unwrap();
        let mut sp = SurfacePoint::new(&frame, hit, o, -Vec3::Y);
        sp.ns = n2;
        let hits = IrradianceCache::trace_strata(&frame, &sp, 3, &p);
        let (strata, rad) = estimate_all(&[1e-3], vec![hits], &wall_radiance).remove(0);
        let tilted =
            IrradianceCache::finish_record(&sp, Motion::Static, 3, 1e-3, strata, &rad, &p, 0);
        let predicted = r.extrapolate(r.position, n2).x;
        let actual = tilted.irradiance.x;
        let change = actual - r.irradiance.x;
        assert!(change > 0.0, "tilting towards the wall gathers more of it");
        assert!(
            (predicted - actual).abs() < 0.15 * change,
            "predicted {predicted}, gathered {actual} (from {})",
            r.irradiance.x
        );
    }
}
