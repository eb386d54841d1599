//! The final gather of a record (§2.1, §4.1): M×N cosine-weighted strata whose jitter
//! depends on the record's id alone, so that a record shoots the same rays every frame, and
//! the method's resolver that turns the hits into strata and radiance.

use glam::Vec3;

use super::directional::stratum_direction;
use super::{CacheParams, HIT_BACK, HIT_DYNAMIC, Record, Stratum};
use crate::accel::{Hit, lanes4};
use crate::geom::{Motion, basis};
use crate::interaction::SurfacePoint;
use crate::sampling::Sampler;
use crate::scene::FrameScene;

/// Where a gather ray went, before its radiance is estimated: the surface point it met
/// (`None`: a miss). A batch holds millions of these, one part at a time ([`PART_HITS`]).
#[derive(Debug, Clone, Copy)]
pub struct GatherHit {
    pub sp: Option<SurfacePoint>,
}

impl GatherHit {
    /// A ray that leaves below the surface or meets nothing.
    pub const MISS: GatherHit = GatherHit { sp: None };

    /// The gather hit of the ray from `o` along `dir` that met `hit` (`None`: a miss).
    fn new(frame: &FrameScene, hit: Option<Hit>, o: Vec3, dir: Vec3) -> GatherHit {
        GatherHit {
            sp: hit.map(|h| SurfacePoint::new(frame, h, o, dir)),
        }
    }

    /// How far the ray went to its hit (infinity for a miss).
    pub fn distance(&self) -> f32 {
        self.sp.as_ref().map_or(f32::INFINITY, |sp| sp.hit.t)
    }

    /// The stratum flags of the hit: [`HIT_DYNAMIC`] for a dynamic prim, [`HIT_BACK`] for
    /// the back of a surface (none on a miss).
    pub fn flags(&self) -> u8 {
        match &self.sp {
            Some(sp) => {
                let dynamic = if sp.hit.motion == Motion::Dynamic {
                    HIT_DYNAMIC
                } else {
                    0
                };
                let back = if sp.front { 0 } else { HIT_BACK };
                dynamic | back
            }
            None => 0,
        }
    }
}

/// Each record's strata and the radiance the resolver keeps for them, in the order of its
/// strata: every stratum's (brute force), or only that of the strata whose rays met a
/// dynamic prim (`anchors`: a linked stratum's radiance is its anchor's, read when the
/// record is made, [`Resolve::radiance`], and a miss's is zero).
pub type Resolved = (Vec<Stratum>, Vec<Vec3>);

/// Turns a gather's hits into strata and their radiance: the method's part of a gather
/// (brute force estimates every hit; anchors link static hits to anchors). A batch of
/// records is gathered a part at a time ([`PART_HITS`]), so that its hits (over a hundred
/// bytes each) are held for one part only: [`Resolve::part`] for each part in record order,
/// then [`Resolve::finish`] once for the whole batch, then [`Resolve::radiance`] for each
/// record as it is made, so that every stratum's radiance is held for one record at a time.
pub trait Resolve: Sync {
    /// The strata of a part's records from their footprints (distance units) and their
    /// hits, in record order, with the radiance the resolver keeps ([`Resolved`]).
    fn part(&mut self, footprints: &[f32], hits: Vec<Vec<GatherHit>>) -> Vec<Resolved>;

    /// Completes the whole batch once every part is resolved (anchors: the new anchors
    /// made and their L_i estimated).
    fn finish(&mut self, resolved: &mut [Resolved]);

    /// The radiance of each of a finished record's `strata` from what [`Resolve::part`] and
    /// [`Resolve::finish`] kept (`kept`): by default, `kept` itself.
    fn radiance(&self, strata: &[Stratum], kept: Vec<Vec3>) -> Vec<Vec3> {
        let _ = strata;
        kept
    }

    /// What the method adds to a record made from a finished batch, from its strata's
    /// `radiance` (anchors: its dominant anchor); by default nothing.
    fn made(&self, record: &mut Record, radiance: &[Vec3]) {
        let _ = (record, radiance);
    }
}

/// A resolver that finds every stratum's radiance in its part (brute force).
impl<F: FnMut(&[f32], Vec<Vec<GatherHit>>) -> Vec<Resolved> + Sync> Resolve for F {
    fn part(&mut self, footprints: &[f32], hits: Vec<Vec<GatherHit>>) -> Vec<Resolved> {
        self(footprints, hits)
    }

    fn finish(&mut self, _: &mut [Resolved]) {}
}

/// The most gather hits a part of a batch holds at once ([`Resolve`]): 2^21, some 235 MB of
/// [`GatherHit`]s. Sponza's first frame at the final preset places up to 8 202 records of
/// 1 800 strata in one round (14.8 M hits, 1.65 GB when held at once).
pub const PART_HITS: usize = 1 << 21;

/// The records of a batch that one part gathers: as many as [`PART_HITS`] allows at
/// `strata` strata a record, at least one.
pub fn part_records(strata: [u32; 2]) -> usize {
    (PART_HITS / (strata[0] as usize * strata[1] as usize).max(1)).max(1)
}

/// The brute-force resolver: radiance at every hit from `radiance`, no links. The hits are
/// estimated in the photon tree's spatial order ([`crate::photon::knn::query_order`]).
pub fn estimate_all(
    footprints: &[f32],
    hits: Vec<Vec<GatherHit>>,
    radiance: &(dyn Fn(&SurfacePoint) -> Vec3 + Sync),
) -> Vec<Resolved> {
    let points: Vec<&SurfacePoint> = hits
        .iter()
        .flatten()
        .filter_map(|g| g.sp.as_ref())
        .collect();
    let positions: Vec<Vec3> = points.iter().map(|sp| sp.position).collect();
    let mut estimates =
        crate::photon::knn::map_in_query_order(&positions, |i| radiance(points[i])).into_iter();
    hits.iter()
        .zip(footprints)
        .map(|(h, &scale)| {
            let strata = h
                .iter()
                .map(|g| Stratum::new(None, g.flags(), g.distance(), scale))
                .collect();
            let rad = h
                .iter()
                .map(|g| match g.sp {
                    Some(_) => estimates.next().unwrap_or(Vec3::ZERO),
                    None => Vec3::ZERO,
                })
                .collect();
            (strata, rad)
        })
        .collect()
}

/// Seconds and rays spent updating the cache, split as in the paper's Table 1, with the
/// rows it has no name for (`placement`, `upkeep`).
#[derive(Debug, Clone, Copy, Default)]
pub struct GatherTimings {
    /// Tracing gather rays.
    pub final_gathering: f64,
    /// Estimating radiance at gather hits (photon lookups); `anchors`: the anchors' L_i.
    pub irradiance_estimation: f64,
    /// Integrating each record's strata into its irradiance, gradients and directional fit
    /// (`anchors`: and its dominant anchor). The paper's Table 1 would count it as final
    /// gathering, whose loop over a record's strata reads each one's L_i (Pseudocode 2);
    /// here it is kept apart from the rays, so that their rate is the tracing's.
    pub integration: f64,
    /// `anchors`: linking gather hits to anchors (Pseudocode 1's search and new anchors).
    pub attachment: f64,
    /// Deciding where new records go ([`crate::cache::IrradianceCache::place`]): the
    /// coverage tests at the pixel centres' grids and at the camera samples, and adding the
    /// records to the grids with their radii clamped by their neighbours'; not their
    /// gathers, which count in the rows above.
    pub placement: f64,
    /// The cache's bookkeeping between the stages: dropping expired records and, for
    /// `anchors`, counting the strata that link each anchor and collecting or rebalancing
    /// the anchors.
    pub upkeep: f64,
    pub rays: u64,
}

impl GatherTimings {
    /// Moves `seconds` of linking hits to anchors, timed inside a resolver that counted as
    /// irradiance estimation, to `attachment`.
    pub fn linked(&mut self, seconds: f64) {
        self.irradiance_estimation -= seconds;
        self.attachment += seconds;
    }

    /// The seconds counted so far in the rows a batch of records' gathers fall into (final
    /// gathering, irradiance estimation, attachment, integration): what a span that gathers
    /// takes off its own time to find its placement's.
    pub fn gathering(&self) -> f64 {
        self.final_gathering + self.irradiance_estimation + self.attachment + self.integration
    }

    /// Moves `seconds` of integrating records' strata, timed inside a phase that counted as
    /// irradiance estimation, to `integration`.
    pub fn integrated(&mut self, seconds: f64) {
        self.irradiance_estimation -= seconds;
        self.integration += seconds;
    }
}

/// A record's gather rays: where they leave from and the frame and jitter of their
/// directions, made once for all of its strata. The jitter inside a stratum depends on the
/// record's id only, so a record's rays are the same in every frame.
pub struct StratumRays {
    origin: Vec3,
    t: Vec3,
    b: Vec3,
    ns: Vec3,
    ng: Vec3,
    sampler: Sampler,
    strata: [u32; 2],
}

impl StratumRays {
    /// The rays of the record with id `id` at `sp`.
    pub fn new(sp: &SurfacePoint, id: u32, p: &CacheParams) -> Self {
        let (t, b) = basis(sp.ns);
        StratumRays {
            origin: sp.spawn(),
            t,
            b,
            ns: sp.ns,
            ng: sp.ng,
            sampler: Sampler::strata(id),
            strata: p.strata,
        }
    }

    /// Direction of stratum `s`.
    pub fn dir(&self, s: u32) -> Vec3 {
        let [m, n] = self.strata;
        let (j, k) = (s / n, s % n);
        let [u, v] = self.sampler.get2(s, 0);
        let (sin2, phi) = stratum_direction(m, n, j, k, u, v);
        let st = sin2.sqrt();
        (self.t * (st * phi.cos())
            + self.b * (st * phi.sin())
            + self.ns * (1.0 - sin2).max(0.0).sqrt())
        .normalize()
    }

    /// Stratum `s`'s ray (origin, direction), or `None` where it leaves below the surface
    /// (it is not traced: a miss).
    fn ray(&self, s: u32) -> Option<(Vec3, Vec3)> {
        let dir = self.dir(s);
        (dir.dot(self.ng) > 0.0).then_some((self.origin, dir))
    }

    /// Traces stratum `s`.
    pub fn trace(&self, frame: &FrameScene, s: u32) -> GatherHit {
        let Some((o, dir)) = self.ray(s) else {
            return GatherHit::MISS;
        };
        let hit = frame.accel.closest(
            &frame.static_geometry,
            &frame.dynamic_geometry,
            o,
            dir,
            f32::INFINITY,
        );
        GatherHit::new(frame, hit, o, dir)
    }

    /// Whether stratum `s`'s ray — the one [`StratumRays::trace`] traces — meets a dynamic
    /// prim nearer than `tmax` (this frame's dynamic prims only; the alpha test applies as
    /// it does to every ray).
    pub fn meets_dynamic(&self, frame: &FrameScene, s: u32, tmax: f32) -> bool {
        self.ray(s).is_some_and(|(o, dir)| {
            frame
                .accel
                .occluded_dynamic(&frame.dynamic_geometry, o, dir, tmax)
        })
    }
}

/// Traces every gather ray of a record at `sp`, four neighbouring strata at a time
/// ([`crate::accel::Accel::closest4`]): the hits [`StratumRays::trace`] finds one by one.
pub fn trace_strata(
    frame: &FrameScene,
    sp: &SurfacePoint,
    id: u32,
    p: &CacheParams,
) -> Vec<GatherHit> {
    let rays = StratumRays::new(sp, id, p);
    let [m, n] = p.strata;
    let mut out = vec![GatherHit::MISS; (m * n) as usize];
    // Four neighbouring strata at a time (two of a ring by two of the next), traced together.
    for j in (0..m).step_by(2) {
        for k in (0..n).step_by(2) {
            let strata: [Option<u32>; 4] = lanes4(|i| {
                let (dj, dk) = ((i / 2) as u32, (i % 2) as u32);
                (j + dj < m && k + dk < n).then_some((j + dj) * n + k + dk)
            });
            let dirs = lanes4(|i| strata[i].and_then(|s| rays.ray(s)).map(|r| r.1));
            let hits = frame.accel.closest4(
                &frame.static_geometry,
                &frame.dynamic_geometry,
                rays.origin,
                dirs,
            );
            for hit in hits.iter().flatten() {
                frame.geometry(hit.motion).prefetch(hit.triangle as usize);
            }
            for ((s, dir), hit) in strata.into_iter().zip(dirs).zip(hits) {
                if let (Some(s), Some(dir)) = (s, dir) {
                    out[s as usize] = GatherHit::new(frame, hit, rays.origin, dir);
                }
            }
        }
    }
    out
}

/// The id under which a pixel sample that no record covers gathers on the spot: apart from
/// every record's, so its rays are its own.
pub fn uncached_record_id(pixel: u32) -> u32 {
    pixel ^ 0x8000_0000
}
