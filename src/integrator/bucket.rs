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
//! The depth map is one closest-hit query per mapped cell (its centre direction, from the
//! point's offset origin); the paper rasterises it on the GPU. Bucketing runs in two steps so
//! that the queries can be answered in batches: [`plan`] weighs the cells and lists the
//! queries of one shading point, the cached shading collects the plans of a band of pixels
//! and answers all their queries in one call to [`crate::visibility::depth::DepthMaps`] —
//! on the GPU or the CPU, wherever visibility runs — and [`finish`] fills the buckets from
//! the answers. With the CPU implementation the result is the one per-point tracing gives,
//! bit for bit; the GPU's bounded difference is stated in [`crate::visibility::depth`]. A
//! cell whose bucket is empty — no neighbouring record saw that part of the scene — takes
//! the photon estimate at its depth query's hit, as a final-gather hit would (counted in
//! [`BucketStats::fallbacks`]).

use std::f32::consts::PI;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::accel::Hit;
use crate::anchor::AnchorSet;
use crate::bsdf::Bsdf;
use crate::cache::IrradianceCache;
use crate::geom::basis;
use crate::interaction::SurfacePoint;
use crate::scene::FrameScene;
use crate::visibility::depth::DepthQuery;

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
    /// Depth-map queries answered.
    pub rays: u64,
    /// Anchors projected onto the hemisphere.
    pub anchors: u64,
    /// Cells with an empty bucket, lit by a photon estimate instead.
    pub fallbacks: u64,
}

/// One shading point's bucketing before its depth map is known: the lobe's mapped cells
/// with their BRDF weights, and the depth queries of those above the geometric horizon.
#[derive(Debug, Clone)]
pub struct BucketPlan {
    /// The records valid at the point.
    records: Vec<u32>,
    position: Vec3,
    /// The depth queries' origin (offset off the surface).
    origin: Vec3,
    ns: Vec3,
    /// The lobe reflects nothing here: the result is zero.
    black: bool,
    /// Mapped cells in index order: cell, BRDF weight, and its query's index in `dirs`
    /// (`None` below the geometric horizon: no depth, no fallback).
    cells: Vec<(u32, Vec3, Option<u32>)>,
    /// The depth queries' directions.
    dirs: Vec<Vec3>,
    /// The weight of the unmapped cells (lit by the cache's irradiance).
    tail: Vec3,
}

impl BucketPlan {
    /// The depth queries, in the order [`finish`] expects their answers.
    pub fn queries(&self) -> impl Iterator<Item = DepthQuery> + '_ {
        self.dirs.iter().map(|&dir| DepthQuery {
            origin: self.origin,
            dir,
        })
    }

    pub fn query_count(&self) -> usize {
        self.dirs.len()
    }
}

/// Plans the glossy lobe's bucketing at `at` towards `wo` (`bsdf` its BRDF about the shading
/// normal `ns`) from the records valid there (error threshold `a`): the BRDF's weight per cell,
/// the cells that carry `LOBE_SHARE` of it, and one depth query per mapped cell above the
/// geometric horizon. `None` where no record is valid.
pub fn plan(
    cache: &IrradianceCache,
    at: &SurfacePoint,
    (wo, ns, bsdf): (Vec3, Vec3, &Bsdf),
    a: f32,
    p: &BucketParams,
) -> Option<BucketPlan> {
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
    let mut plan = BucketPlan {
        records,
        position: at.position,
        origin: at.spawn(),
        ns,
        black: false,
        cells: Vec::new(),
        dirs: Vec::new(),
        tail: Vec3::ZERO,
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
        plan.black = true;
        return Some(plan);
    }
    // The cells that carry LOBE_SHARE of the lobe's weight, heaviest first.
    let lum = |w: &Vec3| w.x + w.y + w.z;
    let total: f32 = weight.iter().map(lum).sum();
    let mut order: Vec<usize> = (0..cells).collect();
    order.sort_by(|&x, &y| lum(&weight[y]).total_cmp(&lum(&weight[x])).then(x.cmp(&y)));
    let mut active = vec![false; cells];
    let mut acc = 0.0;
    for c in order {
        if acc < LOBE_SHARE * total {
            active[c] = true;
            acc += lum(&weight[c]);
        } else {
            plan.tail += weight[c];
        }
    }
    for j in 0..mm {
        for k in 0..nn {
            let c = (j * nn + k) as usize;
            if !active[c] {
                continue;
            }
            let d = dir((j as f32 + 0.5) / mm as f32, (k as f32 + 0.5) / nn as f32);
            let query = (d.dot(at.ng) > 0.0).then(|| {
                plan.dirs.push(d);
                (plan.dirs.len() - 1) as u32
            });
            plan.cells.push((c as u32, weight[c], query));
        }
    }
    Some(plan)
}

/// The glossy lobe's indirect light of a [`plan`] given the answers to its depth queries
/// (`depth`, in the order of [`BucketPlan::queries`]): the anchors the valid records link,
/// bucketed by cell and kept where nearer than D_bucket; each mapped cell's bucket mean
/// weighted by the BRDF, an empty bucket's cell lit by `fallback` (the radiance estimate at
/// its depth query's hit), and the lobe's tail by the cache's `irradiance`.
#[allow(clippy::too_many_arguments)]
pub fn finish(
    frame: &FrameScene,
    cache: &IrradianceCache,
    anchors: &AnchorSet,
    plan: &BucketPlan,
    depth: &[Option<Hit>],
    irradiance: Vec3,
    p: &BucketParams,
    fallback: &dyn Fn(&SurfacePoint) -> Vec3,
    stats: &mut BucketStats,
) -> Vec3 {
    if plan.black {
        return Vec3::ZERO;
    }
    stats.rays += plan.dirs.len() as u64;
    let [mm, nn] = p.strata;
    let cells = (mm * nn) as usize;
    let ns = plan.ns;
    let (t, b) = basis(ns);
    // Per cell: its index in `plan.cells` (mapped cells only) and its depth.
    let mut slot = vec![u32::MAX; cells];
    let mut cell_depth = vec![f32::INFINITY; cells];
    for (i, &(c, _, q)) in plan.cells.iter().enumerate() {
        slot[c as usize] = i as u32;
        if let Some(Some(h)) = q.and_then(|q| depth.get(q as usize)) {
            cell_depth[c as usize] = h.t;
        }
    }
    // The anchors the neighbouring records link, each once.
    let mut linked: Vec<u32> = plan
        .records
        .iter()
        .flat_map(|&r| cache.records[r as usize].strata.iter())
        .filter_map(|s| s.link().map(|l| l.0))
        .collect();
    linked.sort_unstable();
    linked.dedup();
    let mut sum = vec![Vec3::ZERO; plan.cells.len()];
    let mut count = vec![0u32; plan.cells.len()];
    for id in linked {
        let anchor = anchors.anchor(crate::anchor::AnchorId(id));
        if !anchor.is_live() {
            continue;
        }
        let d = anchor.position(&anchors.quantizer) - plan.position;
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
        let i = slot[c];
        if i == u32::MAX || r > cell_depth[c] * (1.0 + p.offset) {
            continue;
        }
        stats.anchors += 1;
        sum[i as usize] += anchor.radiance();
        count[i as usize] += 1;
    }
    let mut out = plan.tail * irradiance * std::f32::consts::FRAC_1_PI;
    for (i, &(_, weight, q)) in plan.cells.iter().enumerate() {
        let l = if count[i] > 0 {
            sum[i] / count[i] as f32
        } else if let Some(q) = q
            && let Some(Some(h)) = depth.get(q as usize)
        {
            stats.fallbacks += 1;
            fallback(&SurfacePoint::new(
                frame,
                *h,
                plan.origin,
                plan.dirs[q as usize],
            ))
        } else {
            Vec3::ZERO
        };
        out += weight * l;
    }
    out
}
