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
//! to a range of pixel footprints (Tabellion & Lamorlette 2004), so density follows the image,
//! and by the neighbouring records' radii (Křivánek et al. 2006), so that records stop short
//! of a contact where their neighbours' radii are small
//! (`IrradianceCache::clamp_to_neighbours`). No crate offers an irradiance cache; the
//! grid, the clamping and the placement follow the papers cited at each.
//!

mod clamp;
pub mod directional;
pub mod gather;
mod grid;
pub mod record;
pub mod removal;

use glam::Vec3;
use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use clamp::Placed;
pub use gather::{GatherHit, GatherTimings, Resolve, Resolved};
use grid::{REACH, RecordGrid};
pub use record::{ENCLOSED_SHARE, HIT_BACK, HIT_DYNAMIC, Record, Stratum, finish_record};
pub use removal::{Contribution, WeberTally};

use crate::geom::Motion;
use crate::interaction::{PixelCentres, SurfacePoint};
use crate::scene::{FrameCamera, FrameScene, Projection};

/// Irradiance-cache settings ([`CacheParams::default`] = the `production` preset).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
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
    /// §4.3's N: a pixel read from more than this many records is crowded, and records
    /// there may be removed by their Weber fraction ([`removal`]). Default 6.
    pub weber_records: u32,
    /// A record in a crowded pixel whose Weber fraction δ (Equation 1: the summed relative
    /// change of the pixels it contributes to when it is left out) is below this is removed
    /// after the frame; 0 turns the rule off. Default 0.5.
    pub weber_threshold: f32,
    /// Neighbour clamping's slope s: a record's radius is at most a neighbour's plus s times
    /// their distance (`IrradianceCache::clamp_to_neighbours`); 0 turns it off. Default 2.
    pub neighbour_clamp: f32,
    /// Placement counts a pixel centre as covered where a record made for an earlier frame,
    /// none of whose strata reach a dynamic prim, is valid to this multiple of a (its
    /// weight above 1/(slack·a)); other records cover to a. As the camera moves, this
    /// frame's pixel centres fall between the records placed for earlier ones; with 1 each
    /// such crack gets a record (a gather of every stratum, a pop in the image where it
    /// appears), above 1 the shading reads the records around it to its relaxed threshold
    /// ([`RELAXED`]·a), as it reads them for camera samples off the pixel centres. Records
    /// that see a dynamic prim keep the full density (§4.3: caches added as an object
    /// nears), so that its contact shadows stay as sharp. In [1, [`RELAXED`]]. Default 2.
    pub coverage_slack: f32,
}

impl Default for CacheParams {
    fn default() -> Self {
        CacheParams {
            strata: [12, 36],
            error: 0.25,
            min_spacing_px: 2.0,
            max_spacing_px: 24.0,
            max_age: 2,
            weber_records: 6,
            weber_threshold: 0.5,
            neighbour_clamp: 2.0,
            coverage_slack: RELAXED,
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

/// The cache with its lookup grid. Serialised as its records, the record id counter and
/// Ward's a; the grid is derived from them and rebuilt on reading (the same grid: records
/// enter it in index order either way).
#[derive(Debug, Clone, Default)]
pub struct IrradianceCache {
    pub records: Vec<Record>,
    /// Records by their clamped radii ([`Record::reach_radius`]), for lookups. A record
    /// sits in the cells of the radius it had when it was put there (`grid_radius`): radii
    /// that shrink since (clamped by more records) leave it in cells that hold at least its
    /// sphere, so a lookup still meets every record valid at its point; one that grows
    /// (a neighbour that clamped it went) moves it ([`IrradianceCache::clamp_again`]).
    grid: RecordGrid,
    /// Per record, the radius it sits in [`IrradianceCache::grid`] by (its
    /// [`Record::reach_radius`] when it was put there: at least the one it has now).
    grid_radius: Vec<f32>,
    /// Records by Ward's radii, for neighbour clamping ([`IrradianceCache::clamp_to_neighbours`]).
    ward: RecordGrid,
    next_id: u32,
    /// The hits of the strata whose rays met a dynamic prim in the frame the records were
    /// last brought up to date for, by record id: no anchor holds their light, and watch
    /// mode's relight of that same frame (nothing moved) estimates it there again instead
    /// of tracing the rays anew. Neither serialised nor compared: a state without them
    /// traces those rays and gets the same hits.
    pub dynamic_hits: DynamicHits,
    /// The slope of neighbour clamping the radii were clamped with
    /// ([`IrradianceCache::set_params`]).
    neighbour_clamp: f32,
    /// Records a part of a gather's batch traces at once (`None`: as many as
    /// [`gather::PART_HITS`] hits allow; a batch is gathered and resolved a part at a time,
    /// [`Resolve`]). The records do not depend on it, only the memory a batch holds:
    /// neither serialised nor compared.
    pub part_records: Option<usize>,
}

/// Bytes of the grid entries of one record: up to eight cells of each of the two grids
/// hold it.
const CELL_ENTRIES: usize = 2 * 8 * grid::ENTRY_BYTES;

/// The points of `uncovered` (each with the enclosed records valid there,
/// [`IrradianceCache::enclosed_at`]) that no enclosed record stands in for; the enclosed
/// records that do go into `blocking`, to be marked used.
fn unblocked<T>(uncovered: Vec<(T, Vec<u32>)>, blocking: &mut Vec<u32>) -> Vec<T> {
    let mut open = Vec::with_capacity(uncovered.len());
    for (point, enclosed) in uncovered {
        if enclosed.is_empty() {
            open.push(point);
        } else {
            blocking.extend(enclosed);
        }
    }
    open
}

/// The points of `pending` (pixel index, surface point; in order) to gather in one round of
/// [`IrradianceCache::place_at_samples`]: each with no point taken before it within
/// `reach` pixels.
fn spaced(
    pending: &[&(u32, SurfacePoint)],
    width: u32,
    height: u32,
    reach: i64,
) -> Vec<(u32, SurfacePoint)> {
    let mut taken = vec![false; (width as usize) * (height as usize)];
    let mut chosen = Vec::new();
    for &&(pixel, sp) in pending {
        let (x, y) = ((pixel % width) as i64, (pixel / width) as i64);
        let near = (-reach..=reach).any(|dy| {
            (-reach..=reach).any(|dx| {
                let (u, v) = (x + dx, y + dy);
                (0..width as i64).contains(&u)
                    && (0..height as i64).contains(&v)
                    && taken[(v * width as i64 + u) as usize]
            })
        });
        if !near {
            taken[pixel as usize] = true;
            chosen.push((pixel, sp));
        }
    }
    chosen
}

/// [`IrradianceCache::dynamic_hits`]: per record id, (stratum, hit) pairs.
pub type DynamicHits = rustc_hash::FxHashMap<u32, Vec<(u32, GatherHit)>>;

impl PartialEq for IrradianceCache {
    fn eq(&self, other: &Self) -> bool {
        self.records == other.records
            && self.next_id == other.next_id
            && self.grid.error == other.grid.error
            && self.neighbour_clamp == other.neighbour_clamp
    }
}

/// What [`IrradianceCache`] serialises (borrowed for writing).
#[derive(Serialize)]
struct CacheRef<'a> {
    records: &'a [Record],
    next_id: u32,
    error: f32,
    neighbour_clamp: f32,
}

/// What [`IrradianceCache`] deserialises: the fields of [`CacheRef`], owned.
#[derive(Deserialize)]
struct CacheData {
    records: Vec<Record>,
    next_id: u32,
    error: f32,
    neighbour_clamp: f32,
}

impl Serialize for IrradianceCache {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        CacheRef {
            records: &self.records,
            next_id: self.next_id,
            error: self.grid.error,
            neighbour_clamp: self.neighbour_clamp,
        }
        .serialize(s)
    }
}

impl<'de> Deserialize<'de> for IrradianceCache {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let data = CacheData::deserialize(d)?;
        let mut cache = IrradianceCache {
            records: data.records,
            grid: RecordGrid::default(),
            grid_radius: Vec::new(),
            ward: RecordGrid::default(),
            next_id: data.next_id,
            dynamic_hits: DynamicHits::default(),
            neighbour_clamp: data.neighbour_clamp,
            part_records: None,
        };
        cache.grid.error = data.error;
        cache.rebuild_tree();
        Ok(cache)
    }
}

/// The shading relaxes Ward's threshold to this multiple of a before it gathers on the spot
/// where no record is valid (`crate::integrator::cached`); placement covers camera samples
/// to the same threshold ([`IrradianceCache::place`]).
pub const RELAXED: f32 = REACH;

/// [`Record::last_used`] of a record [`IrradianceCache::retire`] marked.
const RETIRED: i32 = i32::MIN;

/// Rounds of `IrradianceCache::place_at_samples` at most.
pub const SAMPLE_ROUNDS: usize = 4;

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

impl IrradianceCache {
    /// Bytes the cache holds on the heap: records, their strata, and about eight cell
    /// entries per record in each grid.
    pub fn heap_bytes(&self) -> usize {
        self.records.len() * (size_of::<Record>() + CELL_ENTRIES)
            + self
                .records
                .iter()
                .map(|r| r.strata.len() * size_of::<Stratum>())
                .sum::<usize>()
            + self
                .dynamic_hits
                .values()
                .map(|h| h.len() * size_of::<(u32, GatherHit)>() + 32)
                .sum::<usize>()
    }

    pub fn len(&self) -> usize {
        self.records.len()
    }

    /// The id the next record made will have (ids only grow).
    pub fn next_id(&self) -> u32 {
        self.next_id
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// Rebuilds the lookup grid (after records were removed or changed).
    /// Checks a cache read from disk for a render with `strata` strata per record and
    /// `anchors` anchors: finite geometry, the stratum count, links in range.
    pub fn check(&self, strata: usize, anchors: usize) -> Result<(), String> {
        for (i, r) in self.records.iter().enumerate() {
            let finite = r.position.is_finite()
                && r.normal.is_finite()
                && r.irradiance.is_finite()
                && r.error.is_finite()
                && r.ng.is_finite()
                && r.radius.is_finite()
                && r.radius > 0.0
                && r.footprint.is_finite();
            if !finite {
                return Err(format!("cache record {i} has a non-finite value"));
            }
            if r.strata.len() != strata {
                return Err(format!(
                    "cache record {i} has {} strata; the job's settings make {strata}",
                    r.strata.len()
                ));
            }
            let link_ok =
                |a: Option<crate::anchor::AnchorId>| a.is_none_or(|a| a.index() < anchors);
            if !r.strata.iter().all(|s| link_ok(s.link())) || !link_ok(r.dominant_anchor) {
                return Err(format!(
                    "cache record {i} links an anchor that does not exist"
                ));
            }
        }
        Ok(())
    }

    /// Builds the grid of Ward's radii, clamps every record's radius by its neighbours'
    /// ([`IrradianceCache::clamp_to_neighbours`]), then builds the lookup grid of the
    /// clamped radii.
    fn rebuild_tree(&mut self) {
        let error = self.grid.error;
        self.ward = RecordGrid::default();
        self.ward.error = error;
        for (i, r) in self.records.iter().enumerate() {
            self.ward.insert(i as u32, r.position, r.radius);
        }
        self.clamp_to_neighbours(0);
        self.grid = RecordGrid::default();
        self.grid.error = error;
        for (i, r) in self.records.iter().enumerate() {
            self.grid.insert(i as u32, r.position, r.reach_radius);
        }
        self.grid_radius = self.records.iter().map(|r| r.reach_radius).collect();
    }

    /// Takes the settings of `p` the lookups depend on: Ward's a (lookups relax it at most
    /// `REACH`-fold) and the slope of neighbour clamping.
    pub fn set_params(&mut self, p: &CacheParams) {
        if (self.grid.error, self.neighbour_clamp) != (p.error, p.neighbour_clamp) {
            self.grid.error = p.error;
            self.neighbour_clamp = p.neighbour_clamp;
            self.rebuild_tree();
        }
    }

    /// Drops dynamic records, static ones unused for more than `max_age` frames, and those
    /// [`IrradianceCache::retire`] marked (§4.3).
    pub fn expire(&mut self, frame: i32, max_age: u32) {
        let keep: Vec<bool> = self
            .records
            .iter()
            .map(|r| {
                r.motion == Motion::Static
                    && r.last_used != RETIRED
                    && frame.saturating_sub(r.last_used) <= max_age as i32
            })
            .collect();
        self.remove_records(&keep);
    }

    /// Marks records for removal at the next [`IrradianceCache::expire`] (the Weber rule of
    /// §4.3 decides after a frame, and the next frame removes them with the stale ones, so
    /// that the anchors they alone referenced are collected then).
    pub fn retire(&mut self, records: &[u32]) {
        for &i in records {
            self.records[i as usize].last_used = RETIRED;
        }
    }

    /// Ward's weight of record `r` at (x, n), or 0 where it must not be used: behind x,
    /// facing away, enclosed ([`Record::enclosed`]) or a spot record ([`Record::spot`]).
    /// w = 1 / (|x − x_i|/R_i + sqrt(1 − n·n_i)).
    fn weight(r: &Record, x: Vec3, n: Vec3) -> f32 {
        if !r.is_open() {
            return 0.0;
        }
        Self::ward_weight(r, x, n)
    }

    /// [`IrradianceCache::weight`] whatever the record's kind.
    fn ward_weight(r: &Record, x: Vec3, n: Vec3) -> f32 {
        let ndot = n.dot(r.normal);
        if ndot <= 0.0 {
            return 0.0;
        }
        let d = x - r.position;
        // Ward's "in front" test: reject records in front of x.
        if d.dot(n + r.normal) * 0.5 < -0.05 * r.reach_radius {
            return 0.0;
        }
        // Capped at 1e4: at a record's own position the weight is infinite, and weighted sums
        // must stay finite (pixel centres land exactly on records placed there).
        let e = d.length() / r.reach_radius + (1.0 - ndot).max(0.0).sqrt();
        1.0 / e.max(1e-4)
    }

    /// Interpolated irradiance at (x, n) from records whose weight exceeds 1/a, with
    /// gradients; `None` where no record is valid. `parts` receives the contributing records
    /// with their weights and extrapolated values (it is cleared first).
    pub fn interpolate(
        &self,
        x: Vec3,
        n: Vec3,
        a: f32,
        parts: &mut Vec<Contribution>,
    ) -> Option<Interpolated> {
        self.interpolate_by(x, n, a, parts, Self::weight)
    }

    /// The blend of the records whose `weight` at (x, n) exceeds 1/a, found through the
    /// lookup grid (`parts` cleared first).
    fn interpolate_by(
        &self,
        x: Vec3,
        n: Vec3,
        a: f32,
        parts: &mut Vec<Contribution>,
        weight: impl Fn(&Record, Vec3, Vec3) -> f32,
    ) -> Option<Interpolated> {
        parts.clear();
        if self.records.is_empty() {
            return None;
        }
        debug_assert!(
            a <= REACH * self.grid.error * 1.0001,
            "lookup beyond the grid's reach"
        );
        // The valid records' weights and values, summed in index order (whatever order the
        // grid's cells hand them out in): sorting the few valid ones is cheaper than sorting
        // every candidate.
        self.grid.with_candidates(x, a, |idx| {
            for &i in idx {
                let r = &self.records[i as usize];
                let w = weight(r, x, n);
                if w <= 1.0 / a {
                    continue;
                }
                parts.push(Contribution {
                    record: i,
                    weight: w,
                    value: r.extrapolate(x, n).max(Vec3::ZERO),
                });
            }
        });
        parts.sort_unstable_by_key(|c| c.record);
        self.blend(parts)
    }

    /// [`IrradianceCache::interpolate`] among the spot records ([`Record::spot`]) alone:
    /// what a camera sample that no other record covers reads. A spot record is made for
    /// such a sample in the frame that first needs it ([`IrradianceCache::place`] with
    /// `spot`), at the sample, and kept as any record is (its strata linked to anchors,
    /// re-estimated and re-shot as theirs are, removed after `max_age` frames unused); later
    /// frames' samples read it where its Ward radius, not widened to the minimum spacing,
    /// makes it valid (the shading reads it to its relaxed threshold, as it reads the open
    /// records), instead of gathering on the spot.
    pub fn interpolate_spot(
        &self,
        x: Vec3,
        n: Vec3,
        a: f32,
        parts: &mut Vec<Contribution>,
    ) -> Option<Interpolated> {
        self.interpolate_by(x, n, a, parts, Self::spot_weight)
    }

    /// Ward's weight of a spot record at (x, n); 0 for any other record.
    fn spot_weight(r: &Record, x: Vec3, n: Vec3) -> f32 {
        if r.spot {
            Self::ward_weight(r, x, n)
        } else {
            0.0
        }
    }

    /// True if a spot record is valid at (x, n) to a.
    fn spot_covers(&self, x: Vec3, n: Vec3, a: f32) -> bool {
        !self.records.is_empty()
            && self.grid.any_candidate(x, a, |i| {
                Self::spot_weight(&self.records[i as usize], x, n) > 1.0 / a
            })
    }

    /// What [`IrradianceCache::interpolate`] at (x, n) gives where its valid records and
    /// their weights are known (`weights`, in index order, as it found them): the records'
    /// values read again (a relight changes them, not where they are valid). `parts` is
    /// filled as `interpolate` fills it.
    pub fn interpolate_known(
        &self,
        x: Vec3,
        n: Vec3,
        weights: &[(u32, f32)],
        parts: &mut Vec<Contribution>,
    ) -> Option<Interpolated> {
        parts.clear();
        parts.extend(weights.iter().map(|&(i, w)| Contribution {
            record: i,
            weight: w,
            value: self.records[i as usize].extrapolate(x, n).max(Vec3::ZERO),
        }));
        self.blend(parts)
    }

    /// A key of everything that decides which records are valid where, and with what
    /// weight: the records' positions, normals, reach radii and kinds, and the error
    /// thresholds `a`. Equal keys: [`IrradianceCache::interpolate`] finds the same records
    /// with the same weights at every point.
    pub fn interpolation_key(&self, a: &[f32]) -> u64 {
        use std::hash::Hasher;
        let mut h = std::hash::DefaultHasher::new();
        for v in a {
            h.write_u32(v.to_bits());
        }
        h.write_usize(self.records.len());
        for r in &self.records {
            for v in [r.position, r.normal] {
                for c in v.to_array() {
                    h.write_u32(c.to_bits());
                }
            }
            h.write_u32(r.reach_radius.to_bits());
            h.write_u8(u8::from(r.enclosed) | u8::from(r.spot) << 1);
        }
        h.finish()
    }

    /// The weighted blend of the contributions `parts` (in index order).
    fn blend(&self, parts: &[Contribution]) -> Option<Interpolated> {
        let mut sum = Vec3::ZERO;
        let mut wsum = 0.0f32;
        let mut reshot = 0.0f32;
        let mut dominant = (0.0f32, 0);
        for c in parts.iter() {
            let w = c.weight;
            sum += w * c.value;
            wsum += w;
            reshot += w * self.records[c.record as usize].reshot;
            if w > dominant.0 {
                dominant = (w, c.record);
            }
        }
        (wsum > 0.0).then(|| Interpolated {
            irradiance: sum / wsum,
            reshot: reshot / wsum,
            dominant_record: dominant.1,
        })
    }

    /// The records valid at (x, n) (weight above 1/a), in index order.
    pub fn valid_records(&self, x: Vec3, n: Vec3, a: f32) -> Vec<u32> {
        if self.records.is_empty() {
            return Vec::new();
        }
        let mut valid: Vec<u32> = self.grid.with_candidates(x, a, |idx| {
            idx.iter()
                .copied()
                .filter(|&i| Self::weight(&self.records[i as usize], x, n) > 1.0 / a)
                .collect()
        });
        valid.sort_unstable();
        valid
    }

    /// True if some record is valid at (x, n).
    pub fn covers(&self, x: Vec3, n: Vec3, a: f32) -> bool {
        self.covers_with_slack(x, n, a, 1.0, &[])
    }

    /// True if some record is valid at (x, n) to a, or one that `quiet` marks (by index) to
    /// `slack`·a ([`CacheParams::coverage_slack`]).
    fn covers_with_slack(&self, x: Vec3, n: Vec3, a: f32, slack: f32, quiet: &[bool]) -> bool {
        if self.records.is_empty() {
            return false;
        }
        let (strict, relaxed) = (1.0 / a, 1.0 / (slack * a));
        self.grid.any_candidate(x, a * slack.max(1.0), |i| {
            let w = Self::weight(&self.records[i as usize], x, n);
            w > strict || (w > relaxed && quiet.get(i as usize).copied().unwrap_or(false))
        })
    }

    /// Per record, whether none of its strata reach a dynamic prim: the records that cover to
    /// [`CacheParams::coverage_slack`] in [`IrradianceCache::place`] (none where the slack is
    /// 1, which relaxes nothing). Taken once before placement adds records (the new ones,
    /// past its end, cover only to a), so that a record's strata are read once a frame, not
    /// once for every point it is a candidate for.
    fn quiet_records(&self, slack: f32) -> Vec<bool> {
        if slack <= 1.0 {
            return Vec::new();
        }
        self.records
            .par_iter()
            .map(|r| !r.strata.iter().any(|s| s.flags() & HIT_DYNAMIC != 0))
            .collect()
    }

    /// The enclosed records ([`Record::enclosed`]; not spot records) that would be valid at
    /// (x, n) to a were they not enclosed.
    fn enclosed_at(&self, x: Vec3, n: Vec3, a: f32) -> Vec<u32> {
        if self.records.is_empty() {
            return Vec::new();
        }
        self.grid.with_candidates(x, a, |idx| {
            idx.iter()
                .copied()
                .filter(|&i| {
                    let r = &self.records[i as usize];
                    r.enclosed && !r.spot && Self::ward_weight(r, x, n) > 1.0 / a
                })
                .collect()
        })
    }

    /// Re-gathers every record (brute force: every frame, every stratum).
    pub fn regather(
        &mut self,
        frame: &FrameScene,
        p: &CacheParams,
        frame_number: i32,
        resolve: &mut dyn Resolve,
        timings: &mut GatherTimings,
    ) {
        let footprints: Vec<f32> = self.records.iter().map(|r| r.footprint).collect();
        let records = &self.records;
        let resolved = gather_in_parts(
            frame,
            p,
            &footprints,
            &|i| (records[i].surface_point(), records[i].id),
            resolve,
            timings,
            self.part_records.unwrap_or(gather::part_records(p.strata)),
            |_, _| {},
        );
        let t2 = std::time::Instant::now();
        let resolve: &dyn Resolve = resolve;
        let updated: Vec<Record> = self
            .records
            .par_iter()
            .zip(resolved)
            .map(|(r, (strata, kept))| {
                let rad = resolve.radiance(&strata, kept);
                let mut record = r.with_strata(strata, &rad, p, frame_number);
                resolve.made(&mut record, &rad);
                record
            })
            .collect();
        timings.integration += t2.elapsed().as_secs_f64();
        self.records = updated;
        self.rebuild_tree();
    }

    /// Places new records where the image needs them (module doc): levels of `2^l`-pixel
    /// grids from `coarsest` down to 1, then `IrradianceCache::place_at_samples` for
    /// `samples`, the points off the pixel centres where this frame's camera samples will
    /// read the cache (with spot records for those no other record covers, with `spot`). The
    /// grids' points are pixel centres, whose hits `centres` holds.
    ///
    /// A point where an enclosed record ([`Record::enclosed`]) is valid gets no record: its
    /// own would come out enclosed as well, never used. That record is marked used in this
    /// frame instead, so that it stays for as long as it stands in for one. (Before, each
    /// frame of a fixed camera placed the same enclosed records at the pixel centres again,
    /// and each expired unused after `max_age` frames: on Sponza at 320 × 180, production, a
    /// fifth of a steady frame's gather rays.)
    #[allow(clippy::too_many_arguments)] // placement needs the view and the method
    pub fn place(
        &mut self,
        frame: &FrameScene,
        width: u32,
        height: u32,
        p: &CacheParams,
        frame_number: i32,
        samples: &[(u32, SurfacePoint)],
        centres: &PixelCentres,
        spot: bool,
        resolve: &mut dyn Resolve,
        timings: &mut GatherTimings,
    ) {
        debug_assert_eq!(centres.size(), (width, height));
        // Placement's own time: the span less its records' gathers.
        let (start, gathered) = (std::time::Instant::now(), timings.gathering());
        let coarsest = 16u32;
        let mut spacing = coarsest;
        // The records of earlier frames that see no dynamic prim cover to the slack
        // threshold; the others, to a.
        let quiet = self.quiet_records(p.coverage_slack);
        // The enclosed records that kept a point from getting a record (to be kept).
        let mut blocking: Vec<u32> = Vec::new();
        loop {
            let level_first = spacing == coarsest;
            let candidates: Vec<(u32, u32)> = (0..height)
                .step_by(spacing as usize)
                .flat_map(|y| (0..width).step_by(spacing as usize).map(move |x| (x, y)))
                .filter(|&(x, y)| level_first || x % (2 * spacing) != 0 || y % (2 * spacing) != 0)
                .collect();
            let uncovered: Vec<_> = candidates
                .par_iter()
                .filter_map(|&(x, y)| {
                    let sp = centres.point(frame, x, y)?;
                    let covered = self.covers_with_slack(
                        sp.position,
                        sp.ns,
                        p.error,
                        p.coverage_slack,
                        &quiet,
                    );
                    let enclosed = || self.enclosed_at(sp.position, sp.ns, p.error);
                    (!covered).then(|| ((y * width + x, sp), enclosed()))
                })
                .collect();
            let needed = unblocked(uncovered, &mut blocking);
            self.add_records(
                frame,
                &needed,
                height,
                p,
                frame_number,
                false,
                resolve,
                timings,
            );
            if spacing == 1 {
                break;
            }
            spacing /= 2;
        }
        self.place_at_samples(
            frame,
            width,
            height,
            p,
            frame_number,
            samples,
            spot,
            resolve,
            timings,
            &mut blocking,
        );
        self.touch(&blocking, frame_number);
        timings.placement += start.elapsed().as_secs_f64() - (timings.gathering() - gathered);
    }

    /// Records for the `samples` (pixel index, surface point; in pixel order) that no record
    /// covers even at the shading's relaxed threshold ([`RELAXED`]·a): a camera sample whose
    /// surface differs from its pixel centre's (an edge, a thin prop) reads the cache at its
    /// own point, which the pixel-centre grids need not cover. In rounds: each takes, in
    /// order, the uncovered points with no point taken in the round within
    /// `min_spacing_px` pixels (a record is valid at least that far on its surface), gathers
    /// them together, and leaves the rest to be checked again against the new records.
    ///
    /// No record is placed for a point still uncovered after [`SAMPLE_ROUNDS`] rounds, nor
    /// for one where an enclosed record ([`Record::enclosed`], of this frame or an earlier
    /// one) would be valid to the relaxed threshold: its own record would come out enclosed
    /// as well (a contact, the inside of intersecting meshes), unused, and be placed again
    /// each round and each frame (on Sponza, ~300 such records a frame, a fifth of its new
    /// records). The enclosed records that stood in go into `blocking`. With
    /// `spot` (the anchor method), each such point that no spot record covers to the relaxed
    /// threshold gets one ([`IrradianceCache::interpolate_spot`]), in rounds the same way,
    /// the last round taking every point left; without, such points gather on the spot
    /// when shaded.
    #[allow(clippy::too_many_arguments)] // `place`'s
    fn place_at_samples(
        &mut self,
        frame: &FrameScene,
        width: u32,
        height: u32,
        p: &CacheParams,
        frame_number: i32,
        samples: &[(u32, SurfacePoint)],
        spot: bool,
        resolve: &mut dyn Resolve,
        timings: &mut GatherTimings,
        blocking: &mut Vec<u32>,
    ) {
        let reach = p.min_spacing_px.max(1.0) as i64;
        let relaxed = RELAXED * p.error;
        let mut pending: Vec<&(u32, SurfacePoint)> = samples.iter().collect();
        for _ in 0..SAMPLE_ROUNDS {
            let uncovered: Vec<_> = pending
                .into_par_iter()
                .filter(|(_, sp)| !self.covers(sp.position, sp.ns, relaxed))
                .map(|point| {
                    (
                        point,
                        self.enclosed_at(point.1.position, point.1.ns, relaxed),
                    )
                })
                .collect();
            pending = unblocked(uncovered, blocking);
            if pending.is_empty() {
                break;
            }
            let chosen = spaced(&pending, width, height, reach);
            self.add_records(
                frame,
                &chosen,
                height,
                p,
                frame_number,
                false,
                resolve,
                timings,
            );
        }
        if !spot {
            return;
        }
        let mut pending: Vec<&(u32, SurfacePoint)> = samples
            .par_iter()
            .filter(|(_, sp)| !self.covers(sp.position, sp.ns, relaxed))
            .collect();
        for round in 1..=SAMPLE_ROUNDS {
            pending = pending
                .into_par_iter()
                .filter(|(_, sp)| !self.spot_covers(sp.position, sp.ns, relaxed))
                .collect();
            if pending.is_empty() {
                break;
            }
            let chosen = if round < SAMPLE_ROUNDS {
                spaced(&pending, width, height, reach)
            } else {
                pending.iter().map(|&&c| c).collect()
            };
            self.add_records(
                frame,
                &chosen,
                height,
                p,
                frame_number,
                true,
                resolve,
                timings,
            );
        }
    }

    /// Gathers and inserts records at the given surface points (in order): spot records
    /// ([`Record::spot`]) with `spot`.
    #[allow(clippy::too_many_arguments)]
    pub fn add_records(
        &mut self,
        frame: &FrameScene,
        points: &[(u32, SurfacePoint)],
        height: u32,
        p: &CacheParams,
        frame_number: i32,
        spot: bool,
        resolve: &mut dyn Resolve,
        timings: &mut GatherTimings,
    ) {
        if points.is_empty() {
            return;
        }
        let first_id = self.next_id;
        self.next_id += points.len() as u32;
        let footprints: Vec<f32> = points
            .iter()
            .map(|(_, sp)| pixel_footprint(&frame.camera, sp.position, height))
            .collect();
        let part = self.part_records.unwrap_or(gather::part_records(p.strata));
        let resolved = gather_in_parts(
            frame,
            p,
            &footprints,
            &|i| (points[i].1, first_id + i as u32),
            resolve,
            timings,
            part,
            |i, h| {
                self.keep_dynamic_hits(
                    first_id + i as u32,
                    h.iter().enumerate().map(|(s, g)| (s as u32, g)),
                )
            },
        );
        let t2 = std::time::Instant::now();
        let resolve: &dyn Resolve = resolve;
        let records: Vec<Record> = points
            .par_iter()
            .zip(resolved)
            .enumerate()
            .map(|(i, ((_, sp), (strata, kept)))| {
                let rad = resolve.radiance(&strata, kept);
                let mut record = finish_record(
                    sp,
                    sp.hit.motion,
                    first_id + i as u32,
                    footprints[i],
                    strata,
                    &rad,
                    p,
                    frame_number,
                    spot,
                );
                resolve.made(&mut record, &rad);
                record
            })
            .collect();
        timings.integration += t2.elapsed().as_secs_f64();
        self.append(records);
    }

    /// Adds `records` at the end: to both grids, with their radii clamped.
    fn append(&mut self, records: Vec<Record>) {
        let first = self.records.len();
        for r in records {
            self.ward
                .insert(self.records.len() as u32, r.position, r.radius);
            self.records.push(r);
        }
        self.clamp_to_neighbours(first);
        for (i, r) in self.records.iter().enumerate().skip(first) {
            self.grid.insert(i as u32, r.position, r.reach_radius);
            self.grid_radius.push(r.reach_radius);
        }
    }

    /// Adds the hits among `hits` (stratum, hit) that met a dynamic prim to
    /// [`IrradianceCache::dynamic_hits`] for record `id`.
    pub fn keep_dynamic_hits<'a>(
        &mut self,
        id: u32,
        hits: impl Iterator<Item = (u32, &'a GatherHit)>,
    ) {
        for (s, g) in hits {
            if g.flags() & HIT_DYNAMIC != 0 {
                self.dynamic_hits.entry(id).or_default().push((s, *g));
            }
        }
    }

    /// Replaces every record. Records in the same places as before (count, order, positions
    /// and normals: the anchor method's update of each frame) keep both grids: where
    /// re-shot strata changed some Ward radii, the clamp is brought up to date around them
    /// (`IrradianceCache::reclamp`); anything else rebuilds the grids.
    pub fn replace_records(&mut self, records: Vec<Record>) {
        let old: Vec<Placed> = self.records.iter().map(Placed::of).collect();
        self.records = records;
        self.placed_again(&old);
    }

    /// Brings every record up to date in place, `f` with its item of `with` (in parallel),
    /// and the grids with them as [`IrradianceCache::replace_records`] does.
    pub fn update_each<T: Send>(&mut self, with: Vec<T>, f: impl Fn(&mut Record, T) + Sync) {
        let old: Vec<Placed> = self.records.iter().map(Placed::of).collect();
        self.records
            .par_iter_mut()
            .zip(with)
            .for_each(|(r, w)| f(r, w));
        self.placed_again(&old);
    }

    /// Marks records as used in `frame`.
    pub fn touch(&mut self, used: &[u32], frame: i32) {
        for &i in used {
            self.records[i as usize].last_used = frame;
        }
    }
}

/// Gathers the records of a batch `part` at a time (at least one; [`gather::part_records`],
/// so that at most [`gather::PART_HITS`] hits are held) and resolves each part as it is
/// traced, then finishes the batch ([`Resolve`]): record `i` of the batch leaves from
/// `origin(i)`'s surface point with that id, and `each(i, hits)` sees its hits once traced.
/// The records' strata and the radiance the resolver keeps come out in order
/// ([`Resolved`]); tracing counts as final gathering, resolving as irradiance estimation.
#[allow(clippy::too_many_arguments)] // the batch, its parts, and who resolves and sees them
fn gather_in_parts(
    frame: &FrameScene,
    p: &CacheParams,
    footprints: &[f32],
    origin: &(dyn Fn(usize) -> (SurfacePoint, u32) + Sync),
    resolve: &mut dyn Resolve,
    timings: &mut GatherTimings,
    part: usize,
    mut each: impl FnMut(usize, &[GatherHit]),
) -> Vec<Resolved> {
    let n = footprints.len();
    let part = part.max(1);
    let mut resolved = Vec::with_capacity(n);
    for start in (0..n).step_by(part) {
        let end = (start + part).min(n);
        let t0 = std::time::Instant::now();
        let hits: Vec<Vec<GatherHit>> = (start..end)
            .into_par_iter()
            .map(|i| {
                let (sp, id) = origin(i);
                gather::trace_strata(frame, &sp, id, p)
            })
            .collect();
        timings.final_gathering += t0.elapsed().as_secs_f64();
        timings.rays += hits.iter().map(|h| h.len() as u64).sum::<u64>();
        for (i, h) in (start..end).zip(&hits) {
            each(i, h);
        }
        let t1 = std::time::Instant::now();
        resolved.extend(resolve.part(&footprints[start..end], hits));
        timings.irradiance_estimation += t1.elapsed().as_secs_f64();
    }
    let t1 = std::time::Instant::now();
    resolve.finish(&mut resolved);
    timings.irradiance_estimation += t1.elapsed().as_secs_f64();
    resolved
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::anchor::AnchorId;
    use crate::cache::gather::estimate_all;
    use crate::geom::Geometry;

    #[test]
    fn strata_fit_in_six_bytes_and_round_trip() {
        assert_eq!(size_of::<Stratum>(), 6);
        for scale in [1e-3f32, 1.0, 1e4] {
            let s = Stratum::new(
                Some(AnchorId(123_456)),
                HIT_DYNAMIC,
                37.5 * scale,
                0.01 * scale,
            );
            assert_eq!(s.link(), Some(AnchorId(123_456)));
            assert_eq!(s.flags(), HIT_DYNAMIC);
            assert!((s.distance(0.01 * scale) - 37.5 * scale).abs() < 37.5 * scale * 1e-3);
            let miss = Stratum::new(None, 0, f32::INFINITY, scale);
            assert!(!miss.hit() && miss.link().is_none());
        }
    }
    use crate::scene::{FrameScene, StaticSet};

    use crate::geom::push_quad as quad;

    /// A floor (y = 0) and a wall (x = 0, height 1, long in z) whose face towards +x emits
    /// radiance 1 into the gather (the radiance estimate below). From the floor at distance
    /// d the wall's view factor is F = (1 − d/√(d² + 1))/2, so E = πF and
    /// dE/dd = −(π/2)/(d² + 1)^{3/2}.
    fn scene() -> FrameScene {
        let mut g = Geometry::default();
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
        frame_of(g, Vec3::new(3.0, 2.0, 0.0))
    }

    /// `g` as the static set, seen from `eye` looking at the origin.
    fn frame_of(g: Geometry, eye: Vec3) -> FrameScene {
        let statics = StaticSet::new(g);
        let camera = crate::scene::FrameCamera::look_at(eye, Vec3::ZERO, Vec3::Y, 1.0, 1.0);
        FrameScene::new(
            &statics,
            Geometry::default(),
            Vec::new(),
            camera,
            &crate::scene::Surfaces::default(),
        )
    }

    /// A floor (y = 0, 8 × 8) with a closed unit box standing on it (its bottom face on
    /// the floor's plane), every face wound counter-clockwise seen from outside.
    fn box_on_floor() -> FrameScene {
        let mut g = Geometry::default();
        let l = 4.0;
        quad(
            &mut g,
            Vec3::new(-l, 0.0, -l),
            Vec3::new(-l, 0.0, l),
            Vec3::new(l, 0.0, l),
            Vec3::new(l, 0.0, -l),
        );
        let c = |x: f32, y: f32, z: f32| Vec3::new(x - 0.5, y, z - 0.5);
        let faces = [
            [c(0., 1., 0.), c(0., 1., 1.), c(1., 1., 1.), c(1., 1., 0.)], // top
            [c(0., 0., 0.), c(1., 0., 0.), c(1., 0., 1.), c(0., 0., 1.)], // bottom
            [c(0., 0., 1.), c(1., 0., 1.), c(1., 1., 1.), c(0., 1., 1.)], // +z
            [c(0., 0., 0.), c(0., 1., 0.), c(1., 1., 0.), c(1., 0., 0.)], // -z
            [c(1., 0., 0.), c(1., 1., 0.), c(1., 1., 1.), c(1., 0., 1.)], // +x
            [c(0., 0., 0.), c(0., 0., 1.), c(0., 1., 1.), c(0., 1., 0.)], // -x
        ];
        for [a, b, cc, d] in faces {
            quad(&mut g, a, b, cc, d);
        }
        frame_of(g, Vec3::new(3.0, 2.0, 3.0))
    }

    /// A batch is gathered a part at a time, each part resolved as it is traced and the batch
    /// finished once ([`Resolve`]): the records' strata and radiance are those of one part,
    /// whatever the part's size, and no part holds more records than it may.
    #[test]
    fn a_batch_gathers_the_same_in_parts_of_any_size() {
        let frame = box_on_floor();
        let p = CacheParams {
            strata: [4, 8],
            ..CacheParams::default()
        };
        let points: Vec<(SurfacePoint, u32)> = (0..9)
            .map(|i| {
                let o = Vec3::new(-3.0 + 0.7 * i as f32, 0.5, 1.3);
                let sp = crate::interaction::trace(&frame, o, -Vec3::Y).unwrap();
                (sp, 100 + i)
            })
            .collect();
        let footprints = vec![0.1; points.len()];
        // Brute force's estimate in each part; finishing doubles every radiance, so that a
        // record the finish misses (or one finished twice) shows.
        struct Counting {
            parts: Vec<usize>,
            finished: usize,
        }
        impl Resolve for Counting {
            fn part(&mut self, fp: &[f32], hits: Vec<Vec<GatherHit>>) -> Vec<Resolved> {
                self.parts.push(hits.len());
                let lit = |sp: &SurfacePoint| if sp.front { Vec3::ONE } else { Vec3::ZERO };
                estimate_all(fp, hits, &lit)
            }
            fn finish(&mut self, resolved: &mut [Resolved]) {
                self.finished += 1;
                resolved
                    .iter_mut()
                    .flat_map(|r| r.1.iter_mut())
                    .for_each(|r| *r *= 2.0);
            }
        }
        let run = |part: usize| {
            let mut r = Counting {
                parts: Vec::new(),
                finished: 0,
            };
            let mut t = GatherTimings::default();
            let mut seen = Vec::new();
            let out = gather_in_parts(
                &frame,
                &p,
                &footprints,
                &|i| points[i],
                &mut r,
                &mut t,
                part,
                |i, h| seen.push((i, h.len())),
            );
            (out, r, seen, t.rays)
        };
        let (whole, r, ..) = run(points.len());
        assert_eq!((r.parts, r.finished), (vec![points.len()], 1));
        assert!(whole.iter().any(|(_, rad)| rad.contains(&Vec3::splat(2.0))));
        for part in [1, 2, 4] {
            let (out, r, seen, rays) = run(part);
            assert!(out == whole, "the records gathered {part} at a time");
            assert!(r.parts.iter().all(|&n| n <= part), "parts of {:?}", r.parts);
            assert_eq!(r.parts.iter().sum::<usize>(), points.len());
            assert_eq!(r.finished, 1, "the batch finished once");
            let each: Vec<_> = (0..points.len()).map(|i| (i, 32)).collect();
            assert_eq!(seen, each, "every record's hits seen once, in order");
            assert_eq!(rays, 32 * points.len() as u64);
        }
    }

    /// Contact regions: a static record on a floor that a prim now stands on gathers from
    /// inside the prim — every ray meets the back of a face, and the inside reflects nothing
    /// — so its irradiance is 0. Used at the visible floor beside the prim, it gave pixels
    /// of exactly zero indirect light that no statistic explained. Such a record is
    /// enclosed: no lookup or placement test uses it.
    #[test]
    fn a_record_under_a_box_on_the_floor_is_enclosed_and_never_used() {
        let frame = box_on_floor();
        let p = CacheParams::default();
        // From inside the box straight down: the floor point under it, its normal up.
        let o = Vec3::new(0.45, 0.5, 0.1);
        let sp = crate::interaction::trace(&frame, o, -Vec3::Y).unwrap();
        assert!(sp.ns.y > 0.99, "the floor's side facing the box");
        let hits = gather::trace_strata(&frame, &sp, 7, &p);
        // No photon reaches the inside of the box; the outside of everything is lit.
        let lit = |sp: &SurfacePoint| if sp.front { Vec3::ONE } else { Vec3::ZERO };
        let (strata, rad) = estimate_all(&[0.1], vec![hits.clone()], &lit).remove(0);
        let r = finish_record(&sp, Motion::Static, 7, 0.1, strata, &rad, &p, 0, false);
        assert!(
            r.enclosed,
            "every ray of a gather inside the box hits an unlit back face"
        );
        // The same gather where the back faces reflect light (a mesh wound the other way
        // from its neighbours, as Sponza's LOD is): nothing is enclosed there.
        let everywhere = |_: &SurfacePoint| Vec3::ONE;
        let (strata, rad) = estimate_all(&[0.1], vec![hits], &everywhere).remove(0);
        let lit_back = finish_record(&sp, Motion::Static, 7, 0.1, strata, &rad, &p, 0, false);
        assert!(!lit_back.enclosed, "lit back faces are no inside");
        let mut cache = IrradianceCache::default();
        cache.set_params(&p);
        cache.replace_records(vec![r.clone()]);
        // The visible floor just outside the box's +x face, well inside the record's reach.
        let x = Vec3::new(0.52, 0.0, 0.1);
        assert!((x - r.position).length() < 0.5 * p.error * r.radius);
        let mut used = Vec::new();
        assert!(
            cache
                .interpolate(x, Vec3::Y, 2.0 * p.error, &mut used)
                .is_none()
                && used.is_empty(),
            "an enclosed record interpolated beside the box"
        );
        assert!(
            !cache.covers(x, Vec3::Y, p.error),
            "placement must put a record there"
        );

        // A record on the open floor is not enclosed: its rays hit the front of the box.
        let o = Vec3::new(1.0, 0.5, 0.1);
        let sp = crate::interaction::trace(&frame, o, -Vec3::Y).unwrap();
        let hits = gather::trace_strata(&frame, &sp, 8, &p);
        let (strata, rad) = estimate_all(&[0.05], vec![hits], &lit).remove(0);
        let open = finish_record(&sp, Motion::Static, 8, 0.05, strata, &rad, &p, 0, false);
        assert!(!open.enclosed && open.irradiance.x > 0.0);
    }

    /// A spot record keeps its own Ward radius (not widened to the minimum spacing), serves
    /// [`IrradianceCache::interpolate_spot`] alone and only within that radius, and neither
    /// covers a point for placement nor clamps an open record's radius.
    #[test]
    fn a_spot_record_serves_only_uncovered_samples_within_its_own_radius() {
        let frame = box_on_floor();
        let p = CacheParams::default();
        // On the floor a hair outside the box's +x face: half the hemisphere is the box.
        let sp = crate::interaction::trace(&frame, Vec3::new(0.51, 0.5, 0.1), -Vec3::Y).unwrap();
        let hits = gather::trace_strata(&frame, &sp, 9, &p);
        let lit = |sp: &SurfacePoint| if sp.front { Vec3::ONE } else { Vec3::ZERO };
        let (strata, rad) = estimate_all(&[0.1], vec![hits], &lit).remove(0);
        let widened = finish_record(
            &sp,
            Motion::Static,
            9,
            0.1,
            strata.clone(),
            &rad,
            &p,
            0,
            false,
        );
        let spot = finish_record(&sp, Motion::Static, 9, 0.1, strata, &rad, &p, 0, true);
        let r_min = p.min_spacing_px * 0.1 / p.error;
        assert_eq!(widened.radius, r_min, "the box makes Ward's radius small");
        assert!(
            spot.spot && spot.radius < 0.5 * r_min,
            "{} against {r_min}",
            spot.radius
        );
        assert_eq!(spot.irradiance, widened.irradiance);
        // An open record 0.3 away on the floor, whose radius a neighbour at the spot
        // record's place with its radius would clamp (to 2 · 0.3 + R_spot).
        let mut open = Record::bare(sp.position + Vec3::new(0.3, 0.0, 0.0), Vec3::Y, 2.0);
        open.id = 1;
        let mut cache = IrradianceCache::default();
        cache.set_params(&p);
        cache.replace_records(vec![open.clone(), spot.clone()]);
        assert_eq!(
            cache.records[0].reach_radius, 2.0,
            "a spot record clamps no one"
        );
        let (x, n, a) = (spot.position, Vec3::Y, RELAXED * p.error);
        let mut parts = Vec::new();
        // Open lookups read the open record only, even at the spot record's own place.
        assert!(cache.interpolate(x, n, a, &mut parts).is_some());
        assert!(parts.iter().all(|c| c.record == 0));
        assert!(cache.valid_records(x, n, a).iter().all(|&i| i == 0));
        // Only spot lookups read it: at its place, not a·R_spot beyond it (where its radius
        // widened to the minimum spacing would still be valid).
        let found = cache.interpolate_spot(x, n, a, &mut parts).unwrap();
        assert_eq!(parts.iter().map(|c| c.record).collect::<Vec<_>>(), vec![1]);
        assert_eq!(found.irradiance, spot.irradiance);
        assert!(cache.spot_covers(x, n, a));
        let beyond = x + Vec3::new(0.0, 0.0, 1.25 * a * spot.radius);
        assert!(1.25 * a * spot.radius < a * r_min);
        assert!(cache.interpolate_spot(beyond, n, a, &mut parts).is_none());
        assert!(!cache.spot_covers(beyond, n, a));
        // A cache of the spot record alone covers nothing for placement.
        cache.replace_records(vec![spot]);
        assert!(!cache.covers(x, n, a));
        assert!(cache.interpolate(x, n, a, &mut parts).is_none());
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
        let hits = gather::trace_strata(frame, &sp, 3, p);
        let (strata, rad) = estimate_all(&[1e-3], vec![hits], &wall_radiance).remove(0);
        finish_record(&sp, Motion::Static, 3, 1e-3, strata, &rad, p, 0, false)
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
        let hits = gather::trace_strata(&frame, &sp, 3, &p);
        let (strata, rad) = estimate_all(&[1e-3], vec![hits], &wall_radiance).remove(0);
        let tilted = finish_record(&sp, Motion::Static, 3, 1e-3, strata, &rad, &p, 0, false);
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
