//! The final gather of a record (§2.1, §4.1): M×N cosine-weighted strata whose jitter
//! depends on the record's id alone, so that a record shoots the same rays every frame, and
//! the method's resolver that turns the hits into strata and radiance.

use glam::Vec3;

use super::directional::stratum_direction;
use super::{CacheParams, HIT_BACK, HIT_DYNAMIC, Stratum};
use crate::geom::{Motion, basis};
use crate::interaction::SurfacePoint;
use crate::sampling::Sampler;
use crate::scene::FrameScene;

/// Where a gather ray went, before its radiance is estimated.
#[derive(Debug, Clone, Copy)]
pub struct GatherHit {
    pub sp: Option<SurfacePoint>,
    pub distance: f32,
}

impl GatherHit {
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

/// Turns one gather's hits into strata and their radiance: the method's part of a gather
/// (brute force estimates every hit; anchors link static hits to anchors). Arguments: the
/// records' footprints (distance units) and their hits, in record order.
pub type Resolve<'a> =
    dyn FnMut(&[f32], Vec<Vec<GatherHit>>) -> Vec<(Vec<Stratum>, Vec<Vec3>)> + 'a;

/// The brute-force resolver: radiance at every hit from `radiance`, no links. The hits are
/// estimated in the photon tree's spatial order ([`crate::photon::knn::query_order`]).
pub fn estimate_all(
    footprints: &[f32],
    hits: Vec<Vec<GatherHit>>,
    radiance: &(dyn Fn(&SurfacePoint) -> Vec3 + Sync),
) -> Vec<(Vec<Stratum>, Vec<Vec3>)> {
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
                .map(|g| Stratum::new(None, g.flags(), g.distance, scale))
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

/// Seconds and rays spent gathering, split as in the paper's Table 1.
#[derive(Debug, Clone, Copy, Default)]
pub struct GatherTimings {
    /// Tracing gather rays.
    pub final_gathering: f64,
    /// Estimating radiance at gather hits (photon lookups).
    pub irradiance_estimation: f64,
    pub rays: u64,
}

/// Direction of stratum `s` of a record with shading normal `ns` and id `id`: the jitter
/// inside the stratum depends on the id only, so a record's rays are the same in every
/// frame.
pub fn stratum_dir(ns: Vec3, id: u32, p: &CacheParams, s: u32) -> Vec3 {
    let [m, n] = p.strata;
    let (t, b) = basis(ns);
    let sampler = Sampler::strata(id);
    let (j, k) = (s / n, s % n);
    let [u, v] = sampler.get2(s, 0);
    let (sin2, phi) = stratum_direction(m, n, j, k, u, v);
    let st = sin2.sqrt();
    (t * (st * phi.cos()) + b * (st * phi.sin()) + ns * (1.0 - sin2).max(0.0).sqrt()).normalize()
}

/// Whether the ray of stratum `s` of the record at `sp` — the ray [`trace_stratum`]
/// traces — meets a dynamic prim nearer than `tmax` (this frame's dynamic prims only; the
/// alpha test applies as it does to every ray).
pub fn stratum_meets_dynamic(
    frame: &FrameScene,
    sp: &SurfacePoint,
    id: u32,
    p: &CacheParams,
    s: u32,
    tmax: f32,
) -> bool {
    let dir = stratum_dir(sp.ns, id, p, s);
    if dir.dot(sp.ng) <= 0.0 {
        return false;
    }
    frame
        .accel
        .occluded_dynamic(&frame.dynamic_geometry, sp.spawn(), dir, tmax)
}

/// Traces stratum `s` of the record at `sp`.
pub fn trace_stratum(
    frame: &FrameScene,
    sp: &SurfacePoint,
    id: u32,
    p: &CacheParams,
    s: u32,
) -> GatherHit {
    let dir = stratum_dir(sp.ns, id, p, s);
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
        .map(|s| trace_stratum(frame, sp, id, p, s))
        .collect()
}

/// The id under which a pixel sample that no record covers gathers on the spot: apart from
/// every record's, so its rays are its own.
pub fn uncached_record_id(pixel: u32) -> u32 {
    pixel ^ 0x8000_0000
}
