//! Anchor bucketing (the paper's §5.1): the glossy lobe's indirect light at a camera hit C
//! gathered from the anchors that the neighbouring cache records' strata link, instead of
//! from new rays.
//!
//! The hemisphere at C is divided into M×N cosine-weighted cells (rows of equal sin²θ,
//! columns of equal φ, as the records' strata). Every anchor linked by a stratum of a record
//! valid at C is projected onto it; a cell's *bucket* holds the anchors in its direction that
//! are nearer than D_bucket = its depth × (1 + offset), the depth being the distance to the
//! nearest surface along the cell's centre direction (a hemisphere depth map of the scene
//! around C; anchors farther than that are hidden from C). The cell's incoming radiance is
//! the bucket's mean (each anchor's L_i × albedo / π, the radiance it leaves with); the BRDF
//! weights the cells. Only the cells that carry 99 % of the lobe's weight are mapped; the
//! tail is lit by the cache's irradiance, as a wide lobe is.
//!
//! The depth map here is traced on the CPU (one closest-hit ray per mapped cell, no shading);
//! the paper rasterises it on the GPU. A cell whose bucket is empty — no neighbouring record
//! saw that part of the scene — takes the photon estimate at its depth ray's hit, as a
//! final-gather hit would (counted in [`BucketStats::fallbacks`]).

use std::f32::consts::PI;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::anchor::AnchorSet;
use crate::bsdf::Bsdf;
use crate::cache::IrradianceCache;
use crate::geom::basis;
use crate::interaction::SurfacePoint;
use crate::scene::FrameScene;

/// Cells per side of a cell's BRDF average (2 × 2 directions).
const SUB: u32 = 2;

/// The cells that carry this share of the lobe's weight are mapped; the rest of the lobe
/// (its faint tail) is lit by the cache's irradiance as a wide lobe would be.
const LOBE_SHARE: f32 = 0.99;

/// Anchor-bucketing settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BucketParams {
    /// `[M, N]`: θ × φ cells of the hemisphere at the shading point.
    pub strata: [u32; 2],
    /// D_bucket = depth × (1 + offset).
    pub offset: f32,
}

impl Default for BucketParams {
    fn default() -> Self {
        BucketParams {
            strata: [12, 48],
            offset: 0.2,
        }
    }
}

/// What bucketing did at one shading point.
#[derive(Debug, Clone, Copy, Default)]
pub struct BucketStats {
    /// Depth-map rays traced.
    pub rays: u64,
    /// Anchors projected onto the hemisphere.
    pub anchors: u64,
    /// Cells with an empty bucket, lit by a photon estimate instead.
    pub fallbacks: u64,
}

/// The glossy lobe's indirect light at `at` towards `wo` (`bsdf` its BRDF about the shading
/// normal `ns`) from the anchors that the records valid at `at` (error threshold `a`) link,
/// the lobe's tail from the cache's `irradiance` there;
/// `None` where no record is valid there. `fallback` is the radiance estimate at a hit.
#[allow(clippy::too_many_arguments)]
pub fn glossy_indirect(
    frame: &FrameScene,
    cache: &IrradianceCache,
    anchors: &AnchorSet,
    at: &SurfacePoint,
    (wo, ns, bsdf): (Vec3, Vec3, &Bsdf),
    irradiance: Vec3,
    a: f32,
    p: &BucketParams,
    fallback: &dyn Fn(&SurfacePoint) -> Vec3,
    stats: &mut BucketStats,
) -> Option<Vec3> {
    let records = cache.valid_records(at.position, at.ns, a);
    if records.is_empty() {
        return None;
    }
    let [mm, nn] = p.strata;
    let cells = (mm * nn) as usize;
    let (t, b) = basis(ns);
    let dir = |u: f32, v: f32| {
        let sin2 = u.clamp(0.0, 1.0);
        let st = sin2.sqrt();
        let phi = 2.0 * PI * v;
        (t * (st * phi.cos()) + b * (st * phi.sin()) + ns * (1.0 - sin2).max(0.0).sqrt())
            .normalize()
    };
    // The BRDF's weight per cell: its mean over SUB² directions × the cell's cosine-weighted
    // measure π/(MN).
    let measure = PI / cells as f32;
    let mut weight = vec![Vec3::ZERO; cells];
    let mut peak = 0.0f32;
    for j in 0..mm {
        for k in 0..nn {
            let mut f = Vec3::ZERO;
            for q in 0..SUB * SUB {
                let u = (j as f32 + ((q / SUB) as f32 + 0.5) / SUB as f32) / mm as f32;
                let v = (k as f32 + ((q % SUB) as f32 + 0.5) / SUB as f32) / nn as f32;
                f += bsdf.eval(ns, wo, dir(u, v)).glossy;
            }
            let w = f * (measure / (SUB * SUB) as f32);
            peak = peak.max(w.max_element());
            weight[(j * nn + k) as usize] = w;
        }
    }
    if !(peak > 0.0) {
        return Some(Vec3::ZERO);
    }
    // The cells that carry LOBE_SHARE of the lobe's weight, heaviest first.
    let lum = |w: &Vec3| w.x + w.y + w.z;
    let total: f32 = weight.iter().map(lum).sum();
    let mut order: Vec<usize> = (0..cells).collect();
    order.sort_by(|&x, &y| lum(&weight[y]).total_cmp(&lum(&weight[x])).then(x.cmp(&y)));
    let mut active = vec![false; cells];
    let mut acc = 0.0;
    let mut tail = Vec3::ZERO;
    for c in order {
        if acc < LOBE_SHARE * total {
            active[c] = true;
            acc += lum(&weight[c]);
        } else {
            tail += weight[c];
        }
    }
    let o = at.spawn();
    let mut depth = vec![f32::INFINITY; cells];
    // Each mapped cell's depth-ray hit and direction: a surface point is made only for the
    // cells whose bucket turns out empty.
    let mut hits: Vec<Option<(crate::accel::Hit, Vec3)>> = vec![None; cells];
    for j in 0..mm {
        for k in 0..nn {
            let c = (j * nn + k) as usize;
            if !active[c] {
                continue;
            }
            let d = dir((j as f32 + 0.5) / mm as f32, (k as f32 + 0.5) / nn as f32);
            if d.dot(at.ng) <= 0.0 {
                continue;
            }
            stats.rays += 1;
            if let Some(h) = frame.accel.closest(
                &frame.static_geometry,
                &frame.dynamic_geometry,
                o,
                d,
                f32::INFINITY,
            ) {
                depth[c] = h.t;
                hits[c] = Some((h, d));
            }
        }
    }
    // The anchors the neighbouring records link, each once.
    let mut linked: Vec<u32> = records
        .iter()
        .flat_map(|&r| cache.records[r as usize].strata.iter())
        .filter_map(|s| s.link().map(|l| l.0))
        .collect();
    linked.sort_unstable();
    linked.dedup();
    let mut sum = vec![Vec3::ZERO; cells];
    let mut count = vec![0u32; cells];
    for id in linked {
        let anchor = anchors.anchor(crate::anchor::AnchorId(id));
        if !anchor.is_live() {
            continue;
        }
        let d = anchor.position(&anchors.quantizer) - at.position;
        let r = d.length();
        if !(r > 0.0) {
            continue;
        }
        let w = d / r;
        let cos = w.dot(ns);
        if cos <= 0.0 {
            continue;
        }
        let sin2 = (1.0 - cos * cos).max(0.0);
        let j = ((sin2 * mm as f32) as u32).min(mm - 1);
        let phi = w.dot(b).atan2(w.dot(t)).rem_euclid(2.0 * PI);
        let k = ((phi / (2.0 * PI) * nn as f32) as u32).min(nn - 1);
        let c = (j * nn + k) as usize;
        if !active[c] || r > depth[c] * (1.0 + p.offset) {
            continue;
        }
        stats.anchors += 1;
        sum[c] += anchor.radiance();
        count[c] += 1;
    }
    let mut out = tail * irradiance * std::f32::consts::FRAC_1_PI;
    for c in 0..cells {
        if !active[c] {
            continue;
        }
        let l = if count[c] > 0 {
            sum[c] / count[c] as f32
        } else if let Some((h, d)) = hits[c] {
            stats.fallbacks += 1;
            fallback(&SurfacePoint::new(frame, h, o, d))
        } else {
            Vec3::ZERO
        };
        out += weight[c] * l;
    }
    Some(out)
}
