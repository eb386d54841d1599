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
//! Attachment searches the anchors for all of a gather's hits in parallel and creates the
//! missing anchors sequentially in record and stratum order
//! ([`crate::anchor::attach`]), so anchors are created in the same order for any thread
//! count; ray tracing and estimates run in parallel.

use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use super::{FrameContext, GiParams};
use crate::anchor::attach::{Attacher, Linking, SEARCH_SHARE, SearchBuffers};
use crate::anchor::importons::Importons;
use crate::anchor::{AnchorId, AnchorSet, Density, Quantizer};
use crate::cache::gather::{self, GatherHit, GatherTimings, Resolve, Resolved};
use crate::cache::{CacheParams, HIT_DYNAMIC, IrradianceCache, Record, Stratum};
use crate::color::luminance;
use crate::geom::Motion;
use crate::interaction::{PixelCentres, SurfacePoint};
use crate::photon::PhotonMap;
use crate::scene::FrameScene;
use crate::visibility::{self, DynamicSet, StrataBits, Visibility};

/// Anchor statistics of one frame.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct AnchorStats {
    pub anchors: u64,
    pub anchors_created: u64,
    /// Anchors whose L_i was estimated again (the others kept theirs: no photon within
    /// their estimate's reach changed).
    pub anchors_reestimated: u64,
    pub rays_reshot: u64,
    /// Strata the visibility test flagged (§3.2), before their own rays were tested.
    pub strata_flagged: u64,
    pub visibility_s: f64,
    /// Anchors by how many strata link them (the paper's Figure 8): 1, 2–10, 11–100,
    /// 101–1000, more.
    pub reuse_histogram: [u64; 5],
    pub rebalanced: bool,
}

/// The anchor method's resolver ([`Resolve`]) for a batch of gather hits, a part at a
/// time: dynamic hits by the photon map, static hits by attachment (searched in parallel,
/// new anchors made in record and stratum order across the parts; [`Attacher::link_part`]),
/// and once the batch is linked, its new anchors' L_i estimated. It keeps the radiance of
/// the strata whose rays met a dynamic prim only; a linked stratum's is read from its anchor
/// as its record is made ([`Resolve::radiance`]) and a miss's is zero, so that a batch holds
/// about 6 bytes a stratum, not 18.
/// Adds the seconds spent linking hits to anchors (searching and making them) to `seconds`.
struct AnchorResolver<'a, 'b> {
    att: &'a Attacher<'a>,
    set: &'a mut AnchorSet,
    /// The strata that re-shot hits replace (`None` for new records): a re-shot ray that
    /// lands on static geometry at the distance it had before (its stratum was flagged, but
    /// nothing dynamic was in the way) keeps its anchor, as an unflagged stratum would;
    /// re-attaching it could pick another anchor and add flicker. By record of the batch.
    previous: Option<&'a [Vec<Stratum>]>,
    /// The batch's attachment so far (`None` before its first part and after it finishes).
    linking: Option<Linking>,
    /// Attachment's buffers between batches.
    buffers: SearchBuffers,
    /// Records of the batch resolved so far (where the next part's `previous` start).
    done: usize,
    seconds: &'b mut f64,
}

impl<'a, 'b> AnchorResolver<'a, 'b> {
    fn new(
        att: &'a Attacher<'a>,
        set: &'a mut AnchorSet,
        previous: Option<&'a [Vec<Stratum>]>,
        seconds: &'b mut f64,
    ) -> Self {
        AnchorResolver {
            att,
            set,
            previous,
            linking: None,
            buffers: SearchBuffers::default(),
            done: 0,
            seconds,
        }
    }

    /// Resolves one batch as a single part: each record's strata and every stratum's
    /// radiance.
    fn all(
        &mut self,
        footprints: &[f32],
        hits: Vec<Vec<GatherHit>>,
    ) -> Vec<(Vec<Stratum>, Vec<Vec3>)> {
        let mut resolved = self.part(footprints, hits);
        self.finish(&mut resolved);
        resolved
            .into_iter()
            .map(|(strata, kept)| {
                let rad = self.radiance(&strata, kept);
                (strata, rad)
            })
            .collect()
    }
}

impl Resolve for AnchorResolver<'_, '_> {
    fn part(&mut self, footprints: &[f32], hits: Vec<Vec<GatherHit>>) -> Vec<Resolved> {
        let att = self.att;
        let previous = self.previous.map(|p| &p[self.done..self.done + hits.len()]);
        self.done += hits.len();
        let buffers = &mut self.buffers;
        let linking = self
            .linking
            .get_or_insert_with(|| att.begin(self.set, std::mem::take(buffers)));
        resolve_part(
            att,
            self.set,
            linking,
            footprints,
            hits,
            previous,
            self.seconds,
        )
    }

    fn finish(&mut self, _: &mut [Resolved]) {
        let t = Instant::now();
        let created = match self.linking.take() {
            Some(linking) => {
                let (created, buffers) = self.att.end(self.set, linking);
                self.buffers = buffers;
                created
            }
            None => Vec::new(),
        };
        *self.seconds += t.elapsed().as_secs_f64();
        self.done = 0;
        self.att.estimate_created(self.set, &created);
    }

    fn radiance(&self, strata: &[Stratum], kept: Vec<Vec3>) -> Vec<Vec3> {
        linked_radiance(strata, &kept, |id| self.set.anchor(id).radiance())
    }

    fn made(&self, record: &mut Record, radiance: &[Vec3]) {
        record.dominant_anchor = dominant(&record.strata, radiance);
    }
}

/// The radiance of each of `strata`: a linked stratum's from its anchor (`anchor`), that
/// of a stratum whose ray met a dynamic prim in turn from `dynamic` ([`AnchorResolver`]
/// keeps theirs only), zero for the others (misses).
fn linked_radiance(
    strata: &[Stratum],
    dynamic: &[Vec3],
    anchor: impl Fn(AnchorId) -> Vec3,
) -> Vec<Vec3> {
    let mut dynamic = dynamic.iter();
    strata
        .iter()
        .map(|s| match s.link() {
            Some(id) => anchor(id),
            None if s.flags() & HIT_DYNAMIC != 0 => dynamic.next().copied().unwrap_or(Vec3::ZERO),
            None => Vec3::ZERO,
        })
        .collect()
}

/// [`AnchorResolver`]'s part: the strata of `hits`, each static hit linked to its anchor,
/// each dynamic hit's radiance estimated; the radiance kept is that of the dynamic hits, in
/// order (a linked stratum's is its anchor's, once the batch is finished; a miss's zero).
fn resolve_part(
    att: &Attacher,
    set: &AnchorSet,
    linking: &mut Linking,
    footprints: &[f32],
    hits: Vec<Vec<GatherHit>>,
    previous: Option<&[Vec<Stratum>]>,
    seconds: &mut f64,
) -> Vec<Resolved> {
    // A batch holds up to millions of hits: every pass over them runs per record, in
    // parallel, and finds its place in the batch's flat lists (dynamic hits, attaching
    // hits) by its offsets there.
    let is = |g: &GatherHit, m: Motion| g.sp.as_ref().is_some_and(|sp| sp.hit.motion == m);
    // Per hit, the anchor a re-shot stratum keeps (its ray landed where it did before).
    let kept: Vec<Vec<Option<AnchorId>>> = hits
        .par_iter()
        .enumerate()
        .map(|(ri, h)| {
            let scale = footprints[ri];
            (0..h.len())
                .map(|si| {
                    previous
                        .map(|p| p[ri][si])
                        .filter(|old| {
                            old.flags() & HIT_DYNAMIC == 0
                                && Stratum::new(None, 0, h[si].distance(), scale).distance(scale)
                                    == old.distance(scale)
                        })
                        .and_then(|old| old.link())
                })
                .collect()
        })
        .collect();
    // A static hit attaches unless it keeps its anchor.
    let attaches = |g: &GatherHit, k: &Option<AnchorId>| k.is_none() && is(g, Motion::Static);
    // Each record's first place among the dynamic hits and the attaching hits.
    let mut offsets: Vec<(usize, usize)> = hits
        .par_iter()
        .zip(&kept)
        .map(|(h, k)| {
            let dynamic = h.iter().filter(|g| is(g, Motion::Dynamic)).count();
            let attaching = h.iter().zip(k).filter(|(g, k)| attaches(g, k)).count();
            (dynamic, attaching)
        })
        .collect();
    let mut total = (0, 0);
    for o in offsets.iter_mut() {
        let count = *o;
        *o = total;
        total = (total.0 + count.0, total.1 + count.1);
    }
    // Dynamic hits by the photon map, estimated in the photon tree's spatial order
    // (knn::query_order).
    let at_dynamic: Vec<&crate::interaction::SurfacePoint> = hits
        .par_iter()
        .flat_map_iter(|h| {
            h.iter()
                .filter(|g| is(g, Motion::Dynamic))
                .filter_map(|g| g.sp.as_ref())
        })
        .collect();
    let positions: Vec<Vec3> = at_dynamic.par_iter().map(|sp| sp.position).collect();
    let dynamic = crate::photon::knn::map_in_query_order(&positions, |i| {
        let sp = at_dynamic[i];
        sp.albedo(att.m)
            * std::f32::consts::FRAC_1_PI
            * (att.pm.irradiance(sp.position, sp.ng, att.k) + att.pm.direct_at_hit(att.frame, sp))
    });
    // The static hits that attach, in record and stratum order.
    let attaching: Vec<&crate::interaction::SurfacePoint> = hits
        .par_iter()
        .zip(&kept)
        .flat_map_iter(|(h, k)| {
            h.iter()
                .zip(k)
                .filter(|(g, k)| attaches(g, k))
                .filter_map(|(g, _)| g.sp.as_ref())
        })
        .collect();
    let t = Instant::now();
    let attached = att.link_part(set, linking, &attaching, SEARCH_SHARE);
    *seconds += t.elapsed().as_secs_f64();
    hits.par_iter()
        .zip(&kept)
        .zip(&offsets)
        .enumerate()
        .map(
            |(ri, ((h, kept), &(mut next_dynamic, mut next_attached)))| {
                let scale = footprints[ri];
                let mut strata = Vec::with_capacity(h.len());
                let mut at_dynamic = Vec::new();
                for (g, k) in h.iter().zip(kept) {
                    let stratum = match &g.sp {
                        Some(sp) if sp.hit.motion == Motion::Dynamic => {
                            at_dynamic.push(dynamic[next_dynamic]);
                            next_dynamic += 1;
                            Stratum::new(None, g.flags(), g.distance(), scale)
                        }
                        Some(_) => {
                            let id = k.unwrap_or_else(|| {
                                next_attached += 1;
                                attached[next_attached - 1]
                            });
                            Stratum::new(Some(id), g.flags(), g.distance(), scale)
                        }
                        None => Stratum::new(None, 0, f32::INFINITY, scale),
                    };
                    strata.push(stratum);
                }
                (strata, at_dynamic)
            },
        )
        .collect()
}

/// One frame of the anchor method's cache work (Pseudocode 2): everything up to shading,
/// phase by phase. With `albedo` (a material edit in watch mode), every anchor first reads
/// its albedo again ([`refresh_albedo`]), and no record is kept unchanged.
#[allow(clippy::too_many_arguments)] // the frame, its state and photons, placement's points, a material edit
pub fn update(
    ctx: &FrameContext,
    cache: &mut IrradianceCache,
    anchors: &mut Option<AnchorSet>,
    pm: &PhotonMap,
    params: &GiParams,
    vis: &dyn Visibility,
    samples: &[(u32, SurfacePoint)],
    centres: &PixelCentres,
    albedo: bool,
    timings: &mut GatherTimings,
) -> Result<AnchorStats, visibility::Error> {
    let (cp, ap, k) = (&params.cache, &params.anchors, params.k as usize);
    let mut st = AnchorStats::default();
    let (set, changed) = reestimate(ctx, anchors, pm, params, albedo, &mut st, timings);

    let t = Instant::now();
    let before = cache.len();
    cache.expire(ctx.frame, cp.max_age);
    let removed = cache.len() < before;
    timings.upkeep += t.elapsed().as_secs_f64();

    let t = Instant::now();
    let flags = flag_strata(ctx.scene, cache, cp.strata, vis)?;
    st.strata_flagged = flags.iter().map(|f| f.count() as u64).sum();
    let todo = strata_to_reshoot(ctx.scene, cache, &flags, cp);
    st.visibility_s = t.elapsed().as_secs_f64();

    let importons = (ap.density == Density::Importance).then(|| {
        Importons::trace(
            ctx.scene,
            ctx.width,
            ctx.height,
            ap.importons_per_pixel,
            ctx.seed,
        )
    });
    let att = Attacher {
        frame: ctx.scene,
        m: ctx.materials,
        pm,
        k,
        params: *ap,
        scale: ctx.scene.static_radius(),
        importance: importons.as_ref(),
    };

    st.rays_reshot = reshoot_and_update(ctx, &att, set, cache, todo, &changed, cp, false, timings);

    place_records(ctx, &att, set, cache, cp, samples, centres, timings);

    let t = Instant::now();
    let refs = anchor_references(set, cache);
    if removed {
        let referenced: Vec<bool> = refs.iter().map(|&c| c > 0).collect();
        set.collect(&referenced);
    } else {
        st.rebalanced = set.rebalance_if_needed(ap.rebalance as f64);
    }
    st.reuse_histogram = reuse_histogram(&refs);
    timings.upkeep += t.elapsed().as_secs_f64();
    st.anchors = set.live_count() as u64;
    st.anchors_created = set.take_created();
    Ok(st)
}

/// The phase every frame's cache work opens with (Pseudocode 2, §3.3.2): the anchor set
/// (made on the first frame, over the static scene's box), each anchor's albedo read again
/// with `albedo` ([`refresh_albedo`]), L_i re-estimated at every anchor whose photons
/// changed, and the photons linked again to their nearest anchors; timed as irradiance
/// estimation. The set, and which anchors changed (with `albedo`, all of them: each may
/// reflect another colour).
fn reestimate<'a>(
    ctx: &FrameContext,
    anchors: &'a mut Option<AnchorSet>,
    pm: &PhotonMap,
    params: &GiParams,
    albedo: bool,
    st: &mut AnchorStats,
    timings: &mut GatherTimings,
) -> (&'a mut AnchorSet, Vec<bool>) {
    let set = anchors.get_or_insert_with(|| {
        let (lo, hi) = ctx.scene.static_box();
        AnchorSet::new(Quantizer::new(lo, hi))
    });
    let t = Instant::now();
    let at = AnchorPlaces::of(set);
    if albedo {
        refresh_albedo(ctx, set, &at);
    }
    let k = params.anchors.anchor_k(params.k as usize, pm.direct);
    let (count, mut changed, nearest) = reestimate_anchors(ctx.scene, set, pm, k, &at);
    st.anchors_reestimated = count;
    if albedo {
        changed.fill(true);
    }
    relink_photons(set, pm, &at, &nearest);
    timings.irradiance_estimation += t.elapsed().as_secs_f64();
    (set, changed)
}

/// Watch mode's relight (a light or a material changed; geometry and camera are as when the
/// cache was made for this very frame): Pseudocode 2 without visibility detection or record
/// placement. Every record, stratum link and anchor is kept; L_i is re-estimated at every
/// anchor whose photons changed (§3.3.2, as every frame does) and, with `albedo`, every
/// anchor reads its albedo again from the surface it lies on (a material edit changes the
/// radiance an anchor reflects, albedo × L_i / π, and its reuse test). The only gather rays
/// are those of strata that hit a dynamic prim: no anchor holds their light, so they are
/// estimated from the photons again at the hits the frame's render kept
/// ([`IrradianceCache::dynamic_hits`]; traced again — the same directions, so the same hits
/// — only where a state came without them).
pub fn relight(
    ctx: &FrameContext,
    cache: &mut IrradianceCache,
    anchors: &mut Option<AnchorSet>,
    pm: &PhotonMap,
    params: &GiParams,
    albedo: bool,
    timings: &mut GatherTimings,
) -> AnchorStats {
    let (cp, ap, k) = (&params.cache, &params.anchors, params.k as usize);
    let mut st = AnchorStats::default();
    let (set, changed) = reestimate(ctx, anchors, pm, params, albedo, &mut st, timings);

    let att = Attacher {
        frame: ctx.scene,
        m: ctx.materials,
        pm,
        k,
        params: *ap,
        scale: ctx.scene.static_radius(),
        importance: None,
    };
    let none: Vec<StrataBits> = cache
        .records
        .iter()
        .map(|r| StrataBits::new(r.strata.len()))
        .collect();
    let todo = strata_to_reshoot(ctx.scene, cache, &none, cp);
    st.rays_reshot = reshoot_and_update(ctx, &att, set, cache, todo, &changed, cp, true, timings);

    let t = Instant::now();
    let refs = anchor_references(set, cache);
    st.rebalanced = set.rebalance_if_needed(ap.rebalance as f64);
    st.reuse_histogram = reuse_histogram(&refs);
    timings.upkeep += t.elapsed().as_secs_f64();
    st.anchors = set.live_count() as u64;
    st.anchors_created = set.take_created();
    st
}

/// Reads every live anchor's albedo again from the static surface it lies on: a short ray
/// from just above the anchor back along its normal finds that surface (the anchor keeps
/// no prim index, §3's 18 bytes). An anchor whose surface the ray does not find again
/// (its quantised position fell past a triangle's edge) keeps its albedo.
pub fn refresh_albedo(ctx: &FrameContext, set: &mut AnchorSet, at: &AnchorPlaces) {
    let lift = set.lift(ctx.scene.static_radius());
    // Traced along a Morton curve: neighbouring rays visit the same BVH nodes.
    let positions = &at.positions;
    let fresh: Vec<Option<Vec3>> = crate::photon::knn::map_in_order(&at.order, |i| {
        let a = &set.anchors[i];
        if !a.is_live() {
            return None;
        }
        let (x, n) = (positions[i], a.normal());
        let sp = crate::interaction::trace(ctx.scene, x + lift * n, -n)?;
        let back = (sp.position - x).length();
        (sp.hit.motion == Motion::Static && back <= 2.0 * lift).then(|| sp.albedo(ctx.materials))
    });
    for (i, al) in fresh.into_iter().enumerate() {
        if let Some(al) = al {
            set.anchor_mut(AnchorId(i as u32)).set_albedo(al);
        }
    }
}

/// Re-estimates L_i at the anchors from this frame's photons (§3.3.2); returns how many
/// were estimated. The photons follow the same paths wherever nothing moved, so an anchor
/// whose last estimate reached no photon that changed (gone, new or different) would get
/// the same photons and the same value: it keeps it, and only the others are estimated
/// again (the lazy recomputation the paper's §6 points to). Returns how many were estimated;
/// per anchor, whether its L_i may differ from the last frame's (estimated again, or a free
/// slot that a new anchor may fill); and per anchor, what the search found of its nearest
/// photon. With [`crate::photon::GatherDirect::ShadowRays`] an anchor estimated again adds
/// its punctual lights' direct light by shadow rays; one whose photons did not change keeps
/// that too (a moving occluder's shadow changes the first hits of the photons there).
fn reestimate_anchors(
    frame: &FrameScene,
    set: &mut AnchorSet,
    pm: &PhotonMap,
    anchor_k: usize,
    at: &AnchorPlaces,
) -> (u64, Vec<bool>, Vec<NearestPhoton>) {
    let changed = pm.changed_since(&set.previous_photons);
    // Where most photons changed (a light or a material edited, a first frame), nearly
    // every anchor is reached by one: each is estimated again without the test.
    let all = changed.len() >= pm.photons.len() / 2;
    // The search within an anchor's last reach first finds its k photons there where they
    // lie as densely as before; where most of them moved (a material edit: Russian roulette
    // follows the albedo), most anchors find fewer there and search again unbounded, so
    // those search unbounded at once (the same estimates either way). Where every photon
    // lies where it did (a light's intensity or colour edited), the reach holds exactly k.
    let near = !all || pm.same_places_as(&set.previous_photons);
    // An anchor is untouched where no changed photon lies within its reach: a search
    // bounded by the reach, which stops at the first it finds.
    let changed_tree =
        (!changed.is_empty() && !all).then(|| crate::photon::knn::PointTree::new(&changed));
    let set_ref = &*set;
    let positions = &at.positions;
    let lift = set.lift(frame.static_radius());
    let fresh: Vec<Option<(Vec3, f32, Option<usize>)>> =
        crate::photon::knn::map_in_order_prefetched(
            &at.order,
            |i| at.prefetch(set_ref, i),
            |i| {
                let a = &set_ref.anchors[i];
                if !a.is_live() {
                    return None;
                }
                let x = positions[i];
                let r2 = set_ref.reach2(AnchorId(i as u32));
                let untouched = r2.is_finite()
                    && !all
                    && changed_tree.as_ref().is_none_or(|t| !t.any_within(x, r2));
                let r2_near = if near { r2 } else { f32::INFINITY };
                (!untouched).then(|| {
                    let n = a.normal();
                    let (e, r2, ph) =
                        pm.irradiance_radius_and_nearest_near(x, n, anchor_k, r2_near);
                    (e + pm.direct_from(frame, x + lift * n, n), r2, ph)
                })
            },
        );
    let mut changed: Vec<bool> = set.anchors.iter().map(|a| !a.is_live()).collect();
    let mut nearest = vec![NearestPhoton::Unknown; set.anchors.len()];
    let mut count = 0;
    for (i, e) in fresh.into_iter().enumerate() {
        if let Some((e, r2, ph)) = e {
            let id = AnchorId(i as u32);
            set.anchor_mut(id).set_irradiance(e);
            set.set_reach(id, r2);
            changed[i] = true;
            nearest[i] = NearestPhoton::Searched(ph.map(|ph| ph as u32));
            count += 1;
        }
    }
    (count, changed, nearest)
}

/// An anchor's nearest photon (§3.3.2), as this frame's re-estimate of L_i left it.
#[derive(Debug, Clone, Copy)]
enum NearestPhoton {
    /// Not estimated again: still to be searched for.
    Unknown,
    /// Found by the estimate's search (`None`: no photon within the photon map's maximum
    /// radius).
    Searched(Option<u32>),
}

/// The anchors' decoded positions and their Morton order ([`crate::photon::knn::query_order`]),
/// shared by the frame's batches over every anchor (albedo, L_i, photon links).
pub struct AnchorPlaces {
    positions: Vec<Vec3>,
    order: crate::photon::knn::QueryOrder,
}

impl AnchorPlaces {
    /// Asks the cache for anchor `i`, its reach and its position.
    fn prefetch(&self, set: &AnchorSet, i: usize) {
        set.prefetch(AnchorId(i as u32));
        if let Some(p) = self.positions.get(i) {
            crate::geom::prefetch_value(p);
        }
    }

    fn of(set: &AnchorSet) -> AnchorPlaces {
        let q = set.quantizer;
        let positions: Vec<Vec3> = set.anchors.iter().map(|a| a.position(&q)).collect();
        let order = crate::photon::knn::query_order(&positions);
        AnchorPlaces { positions, order }
    }
}

/// Keeps this frame's photon paths for the next frame's comparison, and links each anchor's
/// nearest photon to it (§3.3.2: the first anchor claiming a photon keeps it). `known` holds
/// the nearest photon of the anchors whose L_i was estimated again this frame
/// ([`reestimate_anchors`]); the others' is searched for.
fn relink_photons(set: &mut AnchorSet, pm: &PhotonMap, at: &AnchorPlaces, known: &[NearestPhoton]) {
    set.previous_photons = pm.paths();
    set.photon_links = vec![None; pm.photons.len()];
    let positions = &at.positions;
    let nearest: Vec<Option<usize>> = crate::photon::knn::map_in_order_prefetched(
        &at.order,
        |i| {
            crate::geom::prefetch_value(&set.anchors[i]);
            crate::geom::prefetch_line(&known[i]);
            crate::geom::prefetch_line(&positions[i]);
        },
        |i| {
            if !set.anchors[i].is_live() {
                return None;
            }
            match known[i] {
                NearestPhoton::Searched(ph) => ph.map(|ph| ph as usize),
                NearestPhoton::Unknown => pm.nearest(positions[i]),
            }
        },
    );
    for (i, ph) in nearest.into_iter().enumerate() {
        if let Some(ph) = ph
            && set.photon_links[ph].is_none()
        {
            set.photon_links[ph] = Some(AnchorId(i as u32));
        }
    }
}

/// Visibility of dynamic prims from every static record (§3.2): the strata that may see one.
fn flag_strata(
    frame: &FrameScene,
    cache: &IrradianceCache,
    strata: [u32; 2],
    vis: &dyn Visibility,
) -> Result<Vec<StrataBits>, visibility::Error> {
    let dynamic = DynamicSet::new(&frame.dynamic_geometry);
    let points: Vec<(Vec3, Vec3)> = cache
        .records
        .iter()
        .map(|r| (r.position, r.normal))
        .collect();
    vis.flag(&points, strata, &dynamic)
}

/// Updates the records from this frame's re-shoot (Pseudocode 2): re-traces the strata
/// `todo` lists per record ([`strata_to_reshoot`]; with `stored`, those the cache kept the
/// hits of are read back instead), then updates the records from the new hits and the
/// anchors `changed` marks ([`update_records`]); the timings of both, and the rays traced.
/// The hits that met a dynamic prim are kept in the cache ([`IrradianceCache::dynamic_hits`]).
#[allow(clippy::too_many_arguments)] // the frame, its anchors and cache, and what changed
fn reshoot_and_update(
    ctx: &FrameContext,
    att: &Attacher,
    set: &mut AnchorSet,
    cache: &mut IrradianceCache,
    todo: Vec<Vec<u32>>,
    changed: &[bool],
    cp: &CacheParams,
    stored: bool,
    timings: &mut GatherTimings,
) -> u64 {
    let t = Instant::now();
    let (hits, rays) = reshoot(ctx.scene, cache, &todo, cp, stored);
    timings.final_gathering += t.elapsed().as_secs_f64();
    timings.rays += rays;
    // The hits that met a dynamic prim, for a relight of this frame (placement adds those
    // of new records).
    cache.dynamic_hits.clear();
    let ids: Vec<u32> = cache.records.iter().map(|r| r.id).collect();
    for ((&id, list), h) in ids.iter().zip(&todo).zip(&hits) {
        cache.keep_dynamic_hits(id, list.iter().copied().zip(h));
    }
    let t = Instant::now();
    let mut linking = 0.0;
    let integrating = update_records(
        att,
        set,
        cache,
        &todo,
        hits,
        changed,
        cp,
        ctx.frame,
        &mut linking,
    );
    timings.irradiance_estimation += t.elapsed().as_secs_f64();
    timings.linked(linking);
    timings.integrated(integrating);
    rays
}

/// The strata of each record that this frame re-shoots (Pseudocode 2): those whose ray hit a
/// dynamic prim last frame, and those that `flags` marks (§3.2: the stratum may see a
/// dynamic prim) and whose own ray meets one nearer than its static hit. A record shoots
/// the same ray in a stratum every frame ([`gather::StratumRays`]), and static geometry does
/// not change within a shot, so a flagged stratum whose ray meets no dynamic prim before
/// the surface it hit would hit that surface again; tracing its ray against the few dynamic
/// prims alone tells them apart. The flags' rule is conservative (a stratum's whole solid
/// angle, occluders ignored): on Sponza nine in ten flagged strata are left out this way, in
/// the example room, whose cube fills much of many hemispheres, about half.
fn strata_to_reshoot(
    frame: &FrameScene,
    cache: &IrradianceCache,
    flags: &[StrataBits],
    cp: &CacheParams,
) -> Vec<Vec<u32>> {
    cache
        .records
        .par_iter()
        .zip(flags)
        .map(|(r, f)| {
            // Set up only for a record with a flagged stratum (most have none).
            let rays =
                (f.count() > 0).then(|| gather::StratumRays::new(&r.surface_point(), r.id, cp));
            (0..r.strata.len() as u32)
                .filter(|&s| {
                    let st = r.strata[s as usize];
                    st.flags() & HIT_DYNAMIC != 0
                        || f.get(s as usize)
                            && rays.as_ref().is_some_and(|rays| {
                                rays.meets_dynamic(frame, s, st.distance_bound(r.footprint))
                            })
                })
                .collect()
        })
        .collect()
}

/// The hits of the strata `todo` lists, per record, and how many rays were traced for them.
fn reshoot(
    frame: &FrameScene,
    cache: &IrradianceCache,
    todo: &[Vec<u32>],
    cp: &CacheParams,
    stored: bool,
) -> (Vec<Vec<GatherHit>>, u64) {
    let traced = std::sync::atomic::AtomicU64::new(0);
    let hits = cache
        .records
        .par_iter()
        .zip(todo)
        .map(|(r, list)| {
            if list.is_empty() {
                return Vec::new();
            }
            let rays = gather::StratumRays::new(&r.surface_point(), r.id, cp);
            let kept = cache
                .dynamic_hits
                .get(&r.id)
                .filter(|_| stored)
                .map_or(&[][..], Vec::as_slice);
            list.iter()
                .map(|&s| match kept.binary_search_by_key(&s, |&(t, _)| t) {
                    Ok(i) => kept[i].1,
                    Err(_) => {
                        traced.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        rays.trace(frame, s)
                    }
                })
                .collect()
        })
        .collect();
    (hits, traced.into_inner())
}

/// Re-makes every existing record from its strata: the re-shot ones resolved anew, the
/// others reading their anchors' current L_i. A record with no stratum re-shot whose anchors
/// all keep their L_i (`changed`, by anchor index, says which were estimated again) would
/// come out the same, and is kept as it is. Returns the seconds spent integrating the
/// records' strata (irradiance, gradients, directional fit, dominant anchor).
#[allow(clippy::too_many_arguments)] // the anchors, the cache and this frame's changes to both
fn update_records(
    att: &Attacher,
    set: &mut AnchorSet,
    cache: &mut IrradianceCache,
    todo: &[Vec<u32>],
    hits: Vec<Vec<GatherHit>>,
    changed: &[bool],
    cp: &CacheParams,
    frame: i32,
    linking: &mut f64,
) -> f64 {
    let footprints: Vec<f32> = cache.records.iter().map(|r| r.footprint).collect();
    let previous: Vec<Vec<Stratum>> = cache
        .records
        .iter()
        .zip(todo)
        .map(|(r, list)| list.iter().map(|&s| r.strata[s as usize]).collect())
        .collect();
    let resolved = AnchorResolver::new(att, set, Some(&previous), linking).all(&footprints, hits);
    // Each anchor's radiance, decoded once for the many strata that read it.
    let radiance: Vec<Vec3> = set.anchors.par_iter().map(|a| a.radiance()).collect();
    let with: Vec<_> = resolved.into_iter().zip(todo).collect();
    let t = Instant::now();
    cache.update_each(with, |r, ((new_strata, new_rad), list)| {
        let same = list.is_empty()
            && r.strata.iter().all(|s| {
                s.link()
                    .is_none_or(|a| !changed.get(a.index()).copied().unwrap_or(true))
            });
        if same {
            r.reshot = 0.0;
            return;
        }
        let mut strata = std::mem::take(&mut r.strata);
        let mut rad = linked_radiance(&strata, &[], |a| radiance[a.index()]);
        for ((&s, ns), nr) in list.iter().zip(new_strata).zip(new_rad) {
            strata[s as usize] = ns;
            rad[s as usize] = nr;
        }
        let count = strata.len();
        let mut new = r.with_strata(strata, &rad, cp, frame);
        new.reshot = list.len() as f32 / count.max(1) as f32;
        new.dominant_anchor = dominant(&new.strata, &rad);
        *r = new;
    });
    t.elapsed().as_secs_f64()
}

/// New records where the image needs them (at the camera samples' lookup `samples` too;
/// the pixel centres' hits in `centres`); all their strata attach, and each record takes its
/// dominant anchor as it is made ([`Resolve::made`]).
#[allow(clippy::too_many_arguments)] // the frame, its anchors and cache, where to look
fn place_records(
    ctx: &FrameContext,
    att: &Attacher,
    set: &mut AnchorSet,
    cache: &mut IrradianceCache,
    cp: &CacheParams,
    samples: &[(u32, SurfacePoint)],
    centres: &PixelCentres,
    timings: &mut GatherTimings,
) {
    let mut linking = 0.0;
    {
        let mut resolver = AnchorResolver::new(att, set, None, &mut linking);
        cache.place(
            ctx.scene,
            ctx.width,
            ctx.height,
            cp,
            ctx.frame,
            samples,
            centres,
            true,
            &mut resolver,
            timings,
        );
    }
    timings.linked(linking);
}

/// The most shares [`anchor_references`] counts in at once: 4 bytes per anchor each, for
/// as long as the count takes (an anchor itself takes 20).
const REFERENCE_SHARES: usize = 4;

/// How many strata link each anchor: counted over one share of the records per thread
/// (tens of millions of strata at the final preset), then added. Each share counts into an
/// array over all anchors, so there are at most [`REFERENCE_SHARES`] of them.
fn anchor_references(set: &AnchorSet, cache: &IrradianceCache) -> Vec<u32> {
    let n = set.anchors.len();
    let shares = rayon::current_num_threads().clamp(1, REFERENCE_SHARES);
    let share = cache.records.len().div_ceil(shares).max(1);
    let count = |records: &[Record]| {
        let mut refs = vec![0u32; n];
        for s in records.iter().flat_map(|r| &r.strata) {
            if let Some(a) = s.link() {
                refs[a.index()] += 1;
            }
        }
        refs
    };
    let add = |mut a: Vec<u32>, b: Vec<u32>| {
        a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        a
    };
    cache
        .records
        .par_chunks(share)
        .map(count)
        .reduce_with(add)
        .unwrap_or_else(|| vec![0; n])
}

/// Anchors by how many strata link them (the paper's Figure 8).
fn reuse_histogram(refs: &[u32]) -> [u64; 5] {
    let mut h = [0; 5];
    for &c in refs.iter().filter(|&&c| c > 0) {
        let bin = match c {
            1 => 0,
            2..=10 => 1,
            11..=100 => 2,
            101..=1000 => 3,
            _ => 4,
        };
        h[bin] += 1;
    }
    h
}

/// The anchor whose strata carry most of a record's irradiance (luminance; ties go to the
/// lower id). Each anchor's strata are summed in stratum order, into a per-thread
/// open-addressing table keyed by anchor (a record's few hundred links, one probe each
/// on average: sorting them by anchor was half the cost of re-making a record).
fn dominant(strata: &[Stratum], rad: &[Vec3]) -> Option<AnchorId> {
    /// An empty slot (no anchor has this id: links are 30 bits).
    const EMPTY: u32 = u32::MAX;
    /// (anchor id, summed luminance) per slot, and the slots in use.
    type Table = (Vec<(u32, f32)>, Vec<u32>);
    thread_local! {
        /// Each thread's table.
        static TABLE: std::cell::RefCell<Table> =
            const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
    }
    TABLE.with_borrow_mut(|(table, used)| {
        // At most half full.
        let size = (2 * strata.len()).next_power_of_two().max(16);
        if table.len() < size {
            *table = vec![(EMPTY, 0.0); size];
        }
        let mask = table.len() - 1;
        for (s, l) in strata.iter().zip(rad) {
            let Some(a) = s.link() else {
                continue;
            };
            // Fibonacci hashing: neighbouring ids spread over the table.
            let mut i = (a.0.wrapping_mul(0x9E37_79B9) >> 7) as usize & mask;
            loop {
                let slot = &mut table[i];
                if slot.0 == a.0 {
                    slot.1 += luminance(*l);
                    break;
                }
                if slot.0 == EMPTY {
                    *slot = (a.0, 0.0 + luminance(*l));
                    used.push(i as u32);
                    break;
                }
                i = (i + 1) & mask;
            }
        }
        let mut best: (Option<u32>, f32) = (None, f32::MIN);
        for &i in used.iter() {
            let (id, l) = table[i as usize];
            if l > best.1 || (l == best.1 && best.0.is_some_and(|b| id < b)) {
                best = (Some(id), l);
            }
            table[i as usize] = (EMPTY, 0.0);
        }
        used.clear();
        best.0.map(AnchorId)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dominant anchor by its definition: strata sorted by anchor (each anchor's in
    /// stratum order), summed, the first largest sum in id order.
    fn dominant_by_sorting(strata: &[Stratum], rad: &[Vec3]) -> Option<AnchorId> {
        let mut links: Vec<(AnchorId, u32)> = strata
            .iter()
            .enumerate()
            .filter_map(|(i, s)| s.link().map(|a| (a, i as u32)))
            .collect();
        links.sort_unstable();
        let mut best: (Option<AnchorId>, f32) = (None, f32::MIN);
        for run in links.chunk_by(|x, y| x.0 == y.0) {
            let l = run
                .iter()
                .fold(0.0, |sum, &(_, i)| sum + luminance(rad[i as usize]));
            if l > best.1 {
                best = (Some(run[0].0), l);
            }
        }
        best.0
    }

    /// Records of 0 to 1 800 strata linking few or many anchors (spread ids, near ids, ties
    /// of equal radiance, unlinked strata), against the definition.
    #[test]
    fn the_dominant_anchor_is_the_one_whose_strata_sum_most() {
        let mut state = 7u32;
        let mut below = |n: u32| {
            state = crate::sampling::hash(&[state]);
            state % n
        };
        for case in 0..400 {
            let n = [0, 1, 7, 432, 1800][case % 5];
            let anchors = 1 + below(if case % 3 == 0 { 4 } else { 600 });
            let base = below(1 << 29);
            let strata: Vec<Stratum> = (0..n)
                .map(|_| {
                    let link = (below(8) != 0).then(|| AnchorId(base + below(anchors)));
                    Stratum::new(link, 0, 1.0, 1.0)
                })
                .collect();
            // Few distinct values, so that sums tie.
            let rad: Vec<Vec3> = (0..n)
                .map(|_| Vec3::splat([0.0, 0.25, 0.5, 1.0][below(4) as usize]))
                .collect();
            assert_eq!(
                dominant(&strata, &rad),
                dominant_by_sorting(&strata, &rad),
                "case {case}"
            );
        }
    }
}
