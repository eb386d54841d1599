//! The anchor method: temporally coherent final gathering (the paper's §3–§4.3,
//! Pseudocode 1 and 2).
//!
//! Every frame: shoot the photons (the same QMC paths as before where nothing moved),
//! re-estimate L_i at every anchor and relink each anchor's nearest photon (§3.3.2); drop
//! dynamic and stale records (§4.3); flag the strata of every static record that may see a
//! dynamic prim ([`Visibility`], §3.2) and re-trace exactly those flagged now and those whose
//! ray hit a dynamic prim in the previous frame ("if dynamic object was hit in current or
//! previous frame", Pseudocode 2: the second set catches disocclusion) — a re-traced ray that
//! hits dynamic geometry gets its radiance the brute force way, one that hits static geometry
//! attaches to an anchor (Pseudocode 1) unless it lands where it did before; every other
//! stratum reads its anchor. A stratum flagged in the previous frame whose ray hit static
//! geometry and is not flagged now needs nothing: its direction is fixed and nothing dynamic
//! can be in its way. New records (camera motion, dynamic prims) gather all their
//! strata and attach them the same way.
//!
//! Attachment is sequential in record and stratum order, so anchors are created in the
//! same order for any thread count; ray tracing and estimates run in parallel.

use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use super::anchors::{Anchor, AnchorSet, Density, NONE, Quantizer};
use super::cache::{
    CacheParams, GatherHit, GatherTimings, HIT_DYNAMIC, IrradianceCache, NO_LINK, Stratum,
};
use super::photons::PhotonMap;
use super::visibility::{DynamicSet, Visibility};
use crate::render::{Materials, SurfacePoint};
use crate::scene::{FrameScene, Motion};

/// Anchor settings ([`AnchorParams::default`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AnchorParams {
    /// D_max (§3.3.1) as a fraction of the static scene's bounding-sphere radius. Default 0.01.
    pub d_max: f32,
    /// D_max in scene units instead; overrides `d_max` when set.
    pub d_max_absolute: Option<f32>,
    /// `constant` D_max, or `importance`-driven from global importons. Default constant.
    pub density: Density,
    /// Radius of the nearest-photon search of Pseudocode 1 (§3.3.2), as a fraction of the
    /// scene radius. Default 0.005.
    pub photon_radius: f32,
    /// Reuse heuristics (§3.1): cosine between normals at least this; default 0.9.
    pub normal_cos: f32,
    /// Reuse heuristics: largest albedo difference per channel; default 0.1.
    pub albedo_tolerance: f32,
    /// Rebalance the anchor kd-tree when searches visit more than this × log2(anchors)
    /// nodes on average (§3). Default 3.
    pub rebalance: f32,
    /// Importons for `importance` density, per pixel. Default 0.25.
    pub importons_per_pixel: f32,
    /// Photons per anchor estimate, as a multiple of the method's `k`. Default 2: anchors
    /// are far fewer than gather hits, so a wider estimate per anchor costs little and gives
    /// an indirect light both closer to the path-traced reference and steadier in time.
    pub k_scale: f32,
}

impl AnchorParams {
    /// Photons per anchor estimate for the method's `k`.
    pub fn anchor_k(&self, k: usize) -> usize {
        ((k as f32 * self.k_scale).round() as usize).max(1)
    }
}

impl Default for AnchorParams {
    fn default() -> Self {
        AnchorParams {
            d_max: 0.01,
            d_max_absolute: None,
            density: Density::Constant,
            photon_radius: 0.005,
            normal_cos: 0.9,
            albedo_tolerance: 0.1,
            rebalance: 3.0,
            importons_per_pixel: 0.25,
            k_scale: 2.0,
        }
    }
}

/// Anchor statistics of one frame.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct AnchorStats {
    pub anchors: u64,
    pub anchors_created: u64,
    /// Anchors whose L_i was estimated again (the others kept theirs: no photon within
    /// their estimate's reach changed).
    pub anchors_reestimated: u64,
    pub rays_reshot: u64,
    pub visibility_s: f64,
    /// Anchors by how many strata link them (the paper's Figure 8): 1, 2–10, 11–100,
    /// 101–1000, more.
    pub reuse_histogram: [u64; 5],
    pub rebalanced: bool,
}

/// Pseudocode 1 with the reuse heuristics of §3.1, for one frame.
pub struct Attacher<'a> {
    pub frame: &'a FrameScene,
    pub m: Materials<'a>,
    pub pm: &'a PhotonMap,
    pub k: usize,
    pub params: AnchorParams,
    /// The scene radius the relative distances refer to.
    pub scale: f32,
    /// Importance-driven D_max factor at a point (1 = the constant D_max).
    pub importance: Option<&'a Importons>,
}

impl Attacher<'_> {
    fn acceptable(&self, set: &AnchorSet, id: u32, sp: &SurfacePoint, albedo: Vec3) -> bool {
        let a = &set.anchors[id as usize];
        // Cheapest first (§3.1): normal, albedo, then visibility by a shadow ray.
        if a.normal().dot(sp.ng) < self.params.normal_cos {
            return false;
        }
        if (a.albedo() - albedo).abs().max_element() > self.params.albedo_tolerance {
            return false;
        }
        let p = a.position(&set.quantizer);
        let target = p + a.normal() * sp.offset.max(set.quantizer.max_error() * 2.0);
        let o = sp.spawn();
        let d = target - o;
        let dist = d.length();
        if !(dist > 0.0) {
            return true;
        }
        !self.frame.accel.occluded(
            &self.frame.static_geometry,
            &self.frame.dynamic_geometry,
            o,
            d / dist,
            dist,
        )
    }

    /// AttachToAnchor (Pseudocode 1): the anchor a static gather hit links to.
    pub fn attach(&self, set: &mut AnchorSet, sp: &SurfacePoint) -> u32 {
        let albedo = sp.albedo(self.m);
        let x = sp.position;
        // §3.3.2: the nearest photon's anchor, if it has one.
        let photon = self.pm.nearest(x).filter(|&i| {
            (self.pm.photons[i].position - x).length() <= self.params.photon_radius * self.scale
        });
        if let Some(ph) = photon {
            let a = set.photon_links[ph];
            if a != NONE && set.anchors[a as usize].is_live() && self.acceptable(set, a, sp, albedo)
            {
                return a;
            }
        }
        // §3.3.1: the nearest anchors within D_max; three rejections create a new one.
        let factor = self.importance.map_or(1.0, |imp| imp.factor(x));
        let d_max = self
            .params
            .d_max_absolute
            .unwrap_or(self.params.d_max * self.scale)
            * factor;
        let anchors = &set.anchors;
        let candidates = set
            .tree
            .nearest(x, d_max, 3, |i| anchors[i as usize].is_live());
        let found = candidates
            .iter()
            .map(|&(_, id)| id)
            .find(|&id| self.acceptable(set, id, sp, albedo));
        let id = match found {
            Some(id) => id,
            None => {
                // Estimated where the anchor is stored (quantised position and normal),
                // exactly as later frames re-estimate it: the normal test against photons
                // can tip on a fraction of a degree.
                let q = set.quantizer;
                let id = set.add(Anchor::new(&q, x, sp.ng, albedo, Vec3::ZERO));
                let a = set.anchors[id as usize];
                let (e, r2) = self.pm.irradiance_and_radius(
                    a.position(&q),
                    a.normal(),
                    self.params.anchor_k(self.k),
                );
                set.anchors[id as usize].set_irradiance(e);
                set.set_reach(id, r2);
                id
            }
        };
        if let Some(ph) = photon
            && set.photon_links[ph] == NONE
        {
            set.photon_links[ph] = id;
        }
        id
    }
}

/// Global importons (Suykens 2002): camera paths stored at their second diffuse hit; their
/// density sets D_max (§3.3.1).
pub struct Importons {
    tree: Option<kiddo::immutable::float::kdtree::ImmutableKdTree<f32, u32, 3, 32>>,
    mean_density: f32,
    k: usize,
}

impl Importons {
    pub fn trace(
        frame: &FrameScene,
        width: u32,
        height: u32,
        per_pixel: f32,
        seed: u32,
    ) -> Importons {
        use super::photons::cosine_direction;
        let count = ((width * height) as f32 * per_pixel).max(16.0) as u32;
        let pts: Vec<[f32; 3]> = (0..count)
            .into_par_iter()
            .filter_map(|i| {
                let s = crate::sampling::Sampler::new(seed, 0, 0x1a90_0001, i);
                let (o, d) = frame.camera.ray(s.get(0, 0), s.get(0, 1));
                let sp = crate::render::trace(frame, o, d)?;
                let d2 = cosine_direction(sp.ns, s.get(0, 2).min(0.999_999_9), s.get(0, 3));
                let h2 = frame.accel.closest(
                    &frame.static_geometry,
                    &frame.dynamic_geometry,
                    sp.spawn(),
                    d2,
                    f32::INFINITY,
                )?;
                Some((sp.spawn() + d2 * h2.t).to_array())
            })
            .collect();
        let k = 16;
        let tree = (pts.len() > k)
            .then(|| kiddo::immutable::float::kdtree::ImmutableKdTree::new_from_slice(&pts));
        let mut imp = Importons {
            tree,
            mean_density: 1.0,
            k,
        };
        // Mean density over the importons themselves (a sample of where gathers land).
        let sample: Vec<f32> = pts
            .iter()
            .step_by((pts.len() / 256).max(1))
            .map(|p| imp.density(Vec3::from(*p)))
            .collect();
        if !sample.is_empty() {
            imp.mean_density = sample.iter().sum::<f32>() / sample.len() as f32;
        }
        imp
    }

    fn density(&self, x: Vec3) -> f32 {
        let Some(t) = &self.tree else { return 1.0 };
        let nn = t.nearest_n::<kiddo::SquaredEuclidean>(
            &x.to_array(),
            std::num::NonZero::new(self.k).expect("k > 0"),
        );
        let r2 = nn.iter().map(|n| n.distance).fold(0.0f32, f32::max);
        self.k as f32 / (std::f32::consts::PI * r2.max(f32::MIN_POSITIVE))
    }

    /// D_max factor at `x`: inversely proportional to the local importon density, relative
    /// to the mean, clamped to [1/8, 8].
    pub fn factor(&self, x: Vec3) -> f32 {
        (self.mean_density / self.density(x).max(f32::MIN_POSITIVE)).clamp(0.125, 8.0)
    }
}

/// Resolves gather hits for the anchor method: dynamic hits by the photon map (parallel),
/// static hits by attachment (sequential, in order). `previous` are the strata that re-shot
/// hits replace: a re-shot ray that lands on static geometry at the distance it had before
/// (its stratum was flagged, but nothing dynamic was in the way) keeps its anchor, as an
/// unflagged stratum would; re-attaching it could pick another anchor and add flicker.
fn resolve(
    att: &Attacher,
    set: &mut AnchorSet,
    footprints: &[f32],
    hits: Vec<Vec<GatherHit>>,
    previous: Option<&[Vec<Stratum>]>,
) -> Vec<(Vec<Stratum>, Vec<Vec3>)> {
    let dynamic: Vec<Vec<Vec3>> = hits
        .par_iter()
        .map(|h| {
            h.iter()
                .map(|g| match &g.sp {
                    Some(sp) if sp.hit.motion == Motion::Dynamic => {
                        sp.albedo(att.m)
                            * std::f32::consts::FRAC_1_PI
                            * att.pm.irradiance(sp.position, sp.ng, att.k)
                    }
                    _ => Vec3::ZERO,
                })
                .collect()
        })
        .collect();
    let mut out = Vec::with_capacity(hits.len());
    for (ri, (h, dyn_rad)) in hits.into_iter().zip(dynamic).enumerate() {
        let mut strata = Vec::with_capacity(h.len());
        let mut rad = Vec::with_capacity(h.len());
        for (si, g) in h.iter().enumerate() {
            // The anchor of a re-shot stratum whose ray lands where it did before.
            let kept = previous
                .map(|p| p[ri][si])
                .filter(|old| {
                    old.flags() & HIT_DYNAMIC == 0
                        && Stratum::new(0, 0, g.distance, footprints[ri]).distance(footprints[ri])
                            == old.distance(footprints[ri])
                })
                .and_then(|old| old.link());
            if let (Some(sp), Some(id)) = (&g.sp, kept)
                && sp.hit.motion == Motion::Static
            {
                strata.push(Stratum::new(id, 0, g.distance, footprints[ri]));
                rad.push(set.anchors[id as usize].radiance());
                continue;
            }
            match &g.sp {
                Some(sp) if sp.hit.motion == Motion::Dynamic => {
                    strata.push(Stratum::new(
                        NO_LINK,
                        HIT_DYNAMIC,
                        g.distance,
                        footprints[ri],
                    ));
                    rad.push(dyn_rad[si]);
                }
                Some(sp) => {
                    let id = att.attach(set, sp);
                    strata.push(Stratum::new(id, 0, g.distance, footprints[ri]));
                    rad.push(set.anchors[id as usize].radiance());
                }
                None => {
                    strata.push(Stratum::new(NO_LINK, 0, f32::INFINITY, footprints[ri]));
                    rad.push(Vec3::ZERO);
                }
            }
        }
        out.push((strata, rad));
    }
    out
}

/// One frame of the anchor method's cache work (Pseudocode 2): everything up to shading.
#[allow(clippy::too_many_arguments)] // the frame's whole context
pub fn update(
    frame: &FrameScene,
    m: Materials,
    cache: &mut IrradianceCache,
    anchors: &mut Option<AnchorSet>,
    pm: &PhotonMap,
    cp: &CacheParams,
    ap: &AnchorParams,
    k: usize,
    width: u32,
    height: u32,
    seed: u32,
    frame_number: i32,
    vis: &dyn Visibility,
    timings: &mut GatherTimings,
) -> Result<AnchorStats, String> {
    let mut st = AnchorStats::default();
    let radius = static_radius(frame);
    let set = anchors.get_or_insert_with(|| {
        let (lo, hi) = static_box(frame);
        AnchorSet::new(Quantizer::new(lo, hi))
    });
    // Re-estimate L_i at every anchor from this frame's photons, then relink (§3.3.2). The
    // photons follow the same paths wherever nothing moved, so an anchor whose last estimate
    // reached no photon that changed (gone, new or different) would get the same photons
    // and the same value: it keeps it, and only the others are estimated again (the lazy
    // recomputation the paper's §6 points to).
    let t = Instant::now();
    let q = set.quantizer;
    let changed = pm.changed_since(&set.previous_photons);
    let changed_tree = (!changed.is_empty()).then(|| {
        let pts: Vec<[f32; 3]> = changed.iter().map(|p| p.to_array()).collect();
        kiddo::immutable::float::kdtree::ImmutableKdTree::<f32, u32, 3, 32>::new_from_slice(&pts)
    });
    let set_ref = &*set;
    let fresh: Vec<Option<(Vec3, f32)>> = set
        .anchors
        .par_iter()
        .enumerate()
        .map(|(id, a)| {
            if !a.is_live() {
                return None;
            }
            let x = a.position(&q);
            let r2 = set_ref.reach2(id as u32);
            let untouched = r2.is_finite()
                && changed_tree.as_ref().is_none_or(|t| {
                    t.nearest_one::<kiddo::SquaredEuclidean>(&x.to_array())
                        .distance
                        > r2
                });
            (!untouched).then(|| pm.irradiance_and_radius(x, a.normal(), ap.anchor_k(k)))
        })
        .collect();
    for (id, e) in fresh.into_iter().enumerate() {
        if let Some((e, r2)) = e {
            set.anchors[id].set_irradiance(e);
            set.set_reach(id as u32, r2);
            st.anchors_reestimated += 1;
        }
    }
    set.previous_photons = super::photons::PhotonPaths {
        photons: pm.photons.clone(),
        path_start: pm.path_start.clone(),
    };
    set.photon_links = vec![NONE; pm.photons.len()];
    let nearest: Vec<Option<usize>> = set
        .anchors
        .par_iter()
        .map(|a| {
            if a.is_live() {
                pm.nearest(a.position(&q))
            } else {
                None
            }
        })
        .collect();
    for (id, ph) in nearest.into_iter().enumerate() {
        if let Some(ph) = ph
            && set.photon_links[ph] == NONE
        {
            set.photon_links[ph] = id as u32;
        }
    }
    timings.irradiance_estimation += t.elapsed().as_secs_f64();

    let before = cache.len();
    cache.expire(frame_number, cp.max_age);
    let removed = cache.len() < before;

    // Visibility of dynamic prims from every static record (§3.2).
    let t = Instant::now();
    let dynamic = DynamicSet::new(&frame.dynamic_geometry);
    let points: Vec<(Vec3, Vec3)> = cache
        .records
        .iter()
        .map(|r| (r.position, r.normal))
        .collect();
    let flags = vis.flag(&points, cp.strata, &dynamic)?;
    st.visibility_s = t.elapsed().as_secs_f64();

    let importons = (ap.density == Density::Importance)
        .then(|| Importons::trace(frame, width, height, ap.importons_per_pixel, seed));
    let att = Attacher {
        frame,
        m,
        pm,
        k,
        params: *ap,
        scale: radius,
        importance: importons.as_ref(),
    };

    // Re-shoot the strata flagged now or whose ray hit a dynamic prim last frame (Pseudocode 2).
    let t = Instant::now();
    let todo: Vec<Vec<u32>> = cache
        .records
        .iter()
        .zip(&flags)
        .map(|(r, f)| {
            (0..r.strata.len() as u32)
                .filter(|&s| f.get(s as usize) || r.strata[s as usize].flags() & HIT_DYNAMIC != 0)
                .collect()
        })
        .collect();
    let hits: Vec<Vec<GatherHit>> = cache
        .records
        .par_iter()
        .zip(&todo)
        .map(|(r, list)| {
            let sp = r.surface_point();
            list.iter()
                .map(|&s| IrradianceCache::trace_stratum(frame, &sp, r.id, cp, s))
                .collect()
        })
        .collect();
    timings.final_gathering += t.elapsed().as_secs_f64();
    st.rays_reshot = todo.iter().map(|l| l.len() as u64).sum();
    timings.rays += st.rays_reshot;
    let t = Instant::now();
    let footprints: Vec<f32> = cache.records.iter().map(|r| r.footprint).collect();
    let previous: Vec<Vec<Stratum>> = cache
        .records
        .iter()
        .zip(&todo)
        .map(|(r, list)| list.iter().map(|&s| r.strata[s as usize]).collect())
        .collect();
    let resolved = resolve(&att, set, &footprints, hits, Some(&previous));
    let anchors_ref = &*set;
    let updated: Vec<_> = cache
        .records
        .par_iter()
        .zip(resolved)
        .zip(&todo)
        .map(|((r, (new_strata, new_rad)), list)| {
            let mut strata = r.strata.clone();
            let mut rad: Vec<Vec3> = strata
                .iter()
                .map(|s| {
                    s.link()
                        .map_or(Vec3::ZERO, |a| anchors_ref.anchors[a as usize].radiance())
                })
                .collect();
            for ((&s, ns), nr) in list.iter().zip(new_strata).zip(new_rad) {
                strata[s as usize] = ns;
                rad[s as usize] = nr;
            }
            let mut new = r.with_strata(strata, &rad, cp, frame_number);
            new.reshot = list.len() as f32 / r.strata.len().max(1) as f32;
            new.dominant_anchor = dominant(&new.strata, &rad);
            new
        })
        .collect();
    cache.replace_records(updated);
    timings.irradiance_estimation += t.elapsed().as_secs_f64();

    // New records where the image needs them; all their strata attach.
    let first_new = cache.len();
    {
        let mut resolver =
            |fp: &[f32], hits: Vec<Vec<GatherHit>>| resolve(&att, set, fp, hits, None);
        cache.place(
            frame,
            width,
            height,
            cp,
            frame_number,
            &mut resolver,
            timings,
        );
    }
    for r in &mut cache.records[first_new..] {
        let rad: Vec<Vec3> = r
            .strata
            .iter()
            .map(|s| {
                s.link()
                    .map_or(Vec3::ZERO, |a| set.anchors[a as usize].radiance())
            })
            .collect();
        r.dominant_anchor = dominant(&r.strata, &rad);
    }

    // Anchors no stratum links any more are freed (§3); otherwise rebalance if searches
    // have grown slow.
    let mut refs = vec![0u32; set.anchors.len()];
    for r in &cache.records {
        for s in &r.strata {
            if let Some(a) = s.link() {
                refs[a as usize] += 1;
            }
        }
    }
    if removed {
        let referenced: Vec<bool> = refs.iter().map(|&c| c > 0).collect();
        set.collect(&referenced);
    } else {
        st.rebalanced = set.rebalance_if_needed(ap.rebalance as f64);
    }
    for &c in refs.iter().filter(|&&c| c > 0) {
        let bin = match c {
            1 => 0,
            2..=10 => 1,
            11..=100 => 2,
            101..=1000 => 3,
            _ => 4,
        };
        st.reuse_histogram[bin] += 1;
    }
    st.anchors = set.live_count() as u64;
    st.anchors_created = set.take_created();
    Ok(st)
}

/// The anchor whose strata carry most of a record's irradiance (luminance).
fn dominant(strata: &[Stratum], rad: &[Vec3]) -> u32 {
    let mut sums: Vec<(u32, f32)> = Vec::new();
    for (s, r) in strata.iter().zip(rad) {
        if let Some(a) = s.link() {
            let l = r.dot(Vec3::new(0.2126, 0.7152, 0.0722));
            match sums.iter_mut().find(|(id, _)| *id == a) {
                Some(e) => e.1 += l,
                None => sums.push((a, l)),
            }
        }
    }
    sums.iter()
        .fold((NO_LINK, f32::MIN), |best, &(a, l)| {
            if l > best.1 || (l == best.1 && a < best.0) {
                (a, l)
            } else {
                best
            }
        })
        .0
}

fn static_box(frame: &FrameScene) -> (Vec3, Vec3) {
    let mut lo = Vec3::splat(f32::MAX);
    let mut hi = Vec3::splat(f32::MIN);
    for t in &frame.static_geometry.triangles {
        for v in [t.v0, t.v1, t.v2] {
            lo = lo.min(v.into());
            hi = hi.max(v.into());
        }
    }
    if lo.x > hi.x {
        (Vec3::ZERO, Vec3::ONE)
    } else {
        (lo, hi)
    }
}

/// Radius of the sphere around the static geometry's box: the unit of relative distances.
fn static_radius(frame: &FrameScene) -> f32 {
    let (lo, hi) = static_box(frame);
    (0.5 * (hi - lo).length()).max(f32::MIN_POSITIVE)
}
