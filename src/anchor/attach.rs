//! AttachToAnchor (Pseudocode 1, §3.1, §3.3): the anchor a static gather hit links to —
//! the nearest photon's anchor, else one of the nearest anchors within D_max that passes
//! the reuse tests, else a new anchor at the hit.
//!
//! A gather's hits attach together ([`Attacher::link_all`] for steps 1, 2 and the photon
//! claims of step 3, then [`Attacher::estimate_created`] for the new anchors' L_i), in
//! three steps that give the same anchors for any thread count:
//!
//! 1. *Search*, in parallel, read-only: every hit looks for its nearest photon and for an
//!    acceptable anchor among those that existed before this batch (the photon's anchor,
//!    then the three nearest within D_max). On a steady frame almost every hit finds one
//!    here, and this is where the time goes (k-d searches and the shadow rays of §3.1).
//! 2. *Create*, sequentially in hit order (record, then stratum), only for the hits that
//!    found none: the search is repeated against what this batch has added so far — the
//!    anchor its photon links to since, then the three nearest within D_max among the
//!    anchors step 1 tried and those this batch created — and a new anchor is made where
//!    none is acceptable, so that two nearby hits of one batch share an anchor as they
//!    would one by one. The batch is searched a share at a time, and a share's step 2 runs
//!    beside the next share's step 1, as a task of its own; what it makes and links is
//!    kept aside until every share is searched, so that step 1 reads the anchors as they
//!    were before the batch.
//! 3. *Resolve*: each hit's nearest photon, in hit order, links to the hit's anchor unless
//!    it links one already (§3.3.2: the first claim keeps it); the new anchors' L_i are
//!    estimated in parallel.
//!
//! A batch too large to hold at once is gathered a part at a time
//! ([`crate::cache::gather::PART_HITS`]) and attaches part by part between
//! [`Attacher::begin`] and [`Attacher::end`] ([`Attacher::link_part`]): the searches of every
//! part read the anchors as they were before the batch and step 2 runs on in hit order, so
//! the anchors are those of the whole batch at once.
//!
//! One by one, a hit could also reuse an anchor that an earlier hit of its batch created
//! or linked, where step 1 finds an older one first: the choice may differ, not its
//! quality (every anchor chosen passes the same tests).

use std::collections::HashMap;

use glam::Vec3;

use super::importons::Importons;
use super::kdtree::Neighbours;
use super::{Anchor, AnchorId, AnchorParams, AnchorSet, KdTree, Quantizer};
use crate::accel::{gamma, offset_ray_origin};
use crate::geom::{prefetch_line, prefetch_value};
use crate::interaction::{Materials, Segment, SurfacePoint};
use crate::photon::PhotonMap;
use crate::photon::knn::QueryOrder;
use crate::scene::FrameScene;

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
    fn acceptable(&self, q: &Quantizer, a: &Anchor, hit: &AttachPoint) -> bool {
        // Cheapest first (§3.1): normal, albedo, then visibility by a shadow ray.
        let n = a.normal();
        if n.dot(hit.ng) < self.params.normal_cos {
            return false;
        }
        if (a.albedo() - hit.albedo).abs().max_element() > self.params.albedo_tolerance {
            return false;
        }
        // The decoded position is off the anchor's surface by at most the quantiser's
        // half step per axis (twice that for margin), plus the rounding of the hit it came
        // from; the shadow ray runs between the two error boxes (pbrt-v4's `SpawnRayTo`),
        // leaving the anchor on the side its normal faces.
        let p = a.position(q);
        let p_error = 2.0 * q.error() + p.abs() * gamma(7);
        let target = offset_ray_origin(p, p_error, n, n);
        let from = (hit.position, hit.error, hit.ng);
        let Some(s) = Segment::to_exact(from, target) else {
            return true;
        };
        !self.frame.accel.occluded(
            &self.frame.static_geometry,
            &self.frame.dynamic_geometry,
            s.origin,
            s.dir,
            s.tmax,
        )
    }

    /// The nearest photon to `x` within the photon radius (§3.3.2), if any.
    fn nearest_photon(&self, x: Vec3) -> Option<usize> {
        // (The search radius has a margin over the test's, which decides, so that the
        // photon found is the one an unbounded search would find and test.)
        let radius = self.params.photon_radius * self.scale;
        self.pm
            .nearest_within(x, radius * (1.0 + 1e-5))
            .filter(|&(_, d)| d <= radius)
            .map(|(i, _)| i)
    }

    /// Step 1 (module doc) for one hit whose nearest photon ([`Attacher::nearest_photon`])
    /// is `photon`: read-only, against the anchors and photon links as they are.
    fn search(&self, set: &AnchorSet, hit: &AttachPoint, photon: Option<usize>) -> Search {
        let x = hit.position;
        // §3.3.2: the nearest photon's anchor, if it has one.
        let linked = photon.and_then(|ph| set.photon_links[ph]);
        // §3.3.1: D_max, constant or scaled by the importons.
        let factor = self.importance.map_or(1.0, |imp| imp.factor(x));
        let d_max = self
            .params
            .d_max_absolute
            .unwrap_or(self.params.d_max * self.scale)
            * factor;
        let mut search = Search {
            hit: *hit,
            photon,
            linked,
            d_max,
            found: None,
            near: Neighbours::new(),
            visited: 0,
        };
        if let Some(a) = linked
            && set.anchor(a).is_live()
            && self.acceptable(&set.quantizer, set.anchor(a), hit)
        {
            search.found = Some(a);
            return search;
        }
        // §3.3.1: the nearest anchors within D_max; three rejections create a new one.
        // The tree holds live anchors only (they die only in `AnchorSet::collect`, which
        // rebuilds it from the live ones).
        let (candidates, visited) = set.tree.search(x, d_max, 3, |_| true);
        search.visited = visited;
        for &(_, id) in candidates.iter() {
            prefetch_line(set.anchor(AnchorId(id)));
        }
        // The photon's anchor, if it is among them, failed the tests already.
        search.found = candidates
            .iter()
            .map(|&(_, id)| AnchorId(id))
            .filter(|&id| Some(id) != linked)
            .find(|&id| self.acceptable(&set.quantizer, set.anchor(id), hit));
        search.near = candidates;
        search
    }

    /// The anchor an attachment of `sp` would link to among the existing anchors (step 1,
    /// read-only: nothing is made or linked), if one is acceptable.
    pub fn find(&self, set: &AnchorSet, sp: &SurfacePoint) -> Option<AnchorId> {
        let hit = AttachPoint::of(sp, self.m);
        self.search(set, &hit, self.nearest_photon(hit.position))
            .found
    }

    /// Step 2 (module doc) for a hit whose search found no anchor: the anchor its photon
    /// links to since the search, else an acceptable one among the three nearest within
    /// D_max of the anchors before this batch (all rejected in step 1) and those this batch
    /// made (`made.fresh`, a tree of their places in `made.anchors`), as one by one; else a
    /// new anchor (its L_i estimated later, in step 3), which goes into `made`.
    fn create(&self, set: &AnchorSet, made: &mut Made, s: &Search) -> AnchorId {
        let hit = &s.hit;
        let q = &set.quantizer;
        let now = s.photon.and_then(|ph| made.links[ph]);
        if let Some(a) = now
            && now != s.linked
        {
            let anchor = match made.place.get(&a.0) {
                Some(&i) => &made.anchors[i as usize].1,
                None => set.anchor(a),
            };
            if anchor.is_live() && self.acceptable(q, anchor, hit) {
                return a;
            }
        }
        let (created, _) = made.fresh.search(hit.position, s.d_max, 3, |_| true);
        // (squared distance, id, place in `made.anchors` for one this batch made)
        let mut nearest: Vec<(f32, u32, Option<u32>)> = s
            .near
            .iter()
            .map(|&(d2, id)| (d2, id, None))
            .chain(
                created
                    .iter()
                    .map(|&(d2, i)| (d2, made.anchors[i as usize].0.0, Some(i))),
            )
            .collect();
        nearest.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        nearest.truncate(3);
        if let Some(id) = nearest
            .iter()
            .filter_map(|&(_, _, i)| i)
            .map(|i| &made.anchors[i as usize])
            .find(|(_, a, _)| self.acceptable(q, a, hit))
            .map(|&(id, _, _)| id)
        {
            return id;
        }
        let anchor = Anchor::new(q, hit.position, hit.ng, hit.albedo, Vec3::ZERO);
        // Where its L_i is searched first (step 3): a nearby anchor's reach, widened by the
        // distance between the two (and the new one's quantisation), takes in that anchor's
        // whole disc, which held k photons when it was estimated.
        let near = s.near.iter().map(|&(d2, other)| {
            let r = set.reach2(AnchorId(other)).sqrt() + d2.sqrt() + q.max_error();
            r * r
        });
        let reach2 = near.fold(f32::INFINITY, f32::min);
        let id = made.ids.next().expect("anchor ids run on without end");
        let i = made.anchors.len() as u32;
        made.place.insert(id.0, i);
        made.fresh.insert(anchor.position(q), i);
        made.anchors.push((id, anchor, reach2));
        id
    }

    /// AttachToAnchor (Pseudocode 1) for a batch of static gather hits, in order (record,
    /// then stratum) — steps 1 and 2 and the photon claims of step 3 (module doc): the
    /// anchor each hit links to, the same for any thread count, and the anchors made, whose
    /// L_i [`Attacher::estimate_created`] estimates.
    ///
    /// The hits are searched a share of [`SEARCH_SHARE`] at a time
    /// ([`Attacher::link_all_in_shares`]).
    pub fn link_all(
        &self,
        set: &mut AnchorSet,
        hits: &[&SurfacePoint],
    ) -> (Vec<AnchorId>, Vec<AnchorId>) {
        self.link_all_in_shares(set, hits, SEARCH_SHARE)
    }

    /// [`Attacher::link_all`], the hits searched `share` at a time (at least one), each
    /// share's step 2 beside the next share's search: step 2 runs on one thread, and would
    /// otherwise leave the others idle. So that every search still reads the anchors and
    /// links as they were before the batch, step 2 and the claims write to `Made`, which
    /// goes into the set once the last share is searched. The result does not depend on
    /// `share`.
    pub fn link_all_in_shares(
        &self,
        set: &mut AnchorSet,
        hits: &[&SurfacePoint],
        share: usize,
    ) -> (Vec<AnchorId>, Vec<AnchorId>) {
        let mut linking = self.begin(set, SearchBuffers::default());
        let ids = self.link_part(set, &mut linking, hits, share);
        (ids, self.end(set, linking).0)
    }

    /// A batch attached a part at a time ([`Attacher::link_part`]): what steps 2 and 3 have
    /// made so far, kept apart from `set` until [`Attacher::end`]. Its searches fill
    /// `buffers` (which [`Attacher::end`] hands back for the next batch).
    pub fn begin(&self, set: &AnchorSet, buffers: SearchBuffers) -> Linking {
        Linking {
            made: Made {
                links: set.photon_links.clone(),
                ids: Box::new(set.next_ids()),
                anchors: Vec::new(),
                place: HashMap::new(),
                fresh: KdTree::default(),
            },
            searched: 0,
            visited: 0,
            buffers,
        }
    }

    /// [`Attacher::link_all_in_shares`] for the next part of a batch begun with
    /// [`Attacher::begin`] (`set` as it was then): the anchor each of `hits` links to. The
    /// parts together link as the whole batch would at once: every search reads the set as
    /// it was before the batch, and step 2 goes on in hit order across the parts.
    pub fn link_part(
        &self,
        set: &AnchorSet,
        linking: &mut Linking,
        hits: &[&SurfacePoint],
        share: usize,
    ) -> Vec<AnchorId> {
        let Linking {
            made,
            searched,
            visited,
            buffers: SearchBuffers([now, later]),
        } = linking;
        let (mut now, mut later) = (now, later);
        let mut ids = Vec::with_capacity(hits.len());
        let mut shares = hits.chunks(share.max(1));
        let mut current = shares.next();
        if let Some(share) = current {
            self.search_share(set, share, now);
        }
        while current.is_some() {
            let next = shares.next();
            let searches = &now.searched;
            let step2 = || {
                for s in searches {
                    *searched += u64::from(s.visited > 0);
                    *visited += u64::from(s.visited);
                    let id = match &s.found {
                        Ok(id) => *id,
                        Err(search) => self.create(set, made, search),
                    };
                    // Step 3: the first claim on a photon keeps it (§3.3.2).
                    if let Some(ph) = s.photon.map(|ph| ph as usize)
                        && made.links[ph].is_none()
                    {
                        made.links[ph] = Some(id);
                    }
                    ids.push(id);
                }
            };
            let search_next = || {
                if let Some(share) = next {
                    self.search_share(set, share, later);
                }
            };
            rayon::join(search_next, step2);
            std::mem::swap(&mut now, &mut later);
            current = next;
        }
        ids
    }

    /// Ends a batch begun with [`Attacher::begin`]: the anchors and photon links its parts
    /// made go into `set`. Returns the anchors made, whose L_i
    /// [`Attacher::estimate_created`] estimates, and the searches' buffers.
    pub fn end(&self, set: &mut AnchorSet, linking: Linking) -> (Vec<AnchorId>, SearchBuffers) {
        set.tree.count(linking.searched, linking.visited);
        set.photon_links = linking.made.links;
        let mut created = Vec::with_capacity(linking.made.anchors.len());
        for (id, anchor, reach2) in linking.made.anchors {
            let added = set.add(anchor);
            debug_assert_eq!(
                added, id,
                "anchor ids are given in the order they are added"
            );
            set.set_reach(added, reach2);
            created.push(added);
        }
        (created, linking.buffers)
    }

    /// Step 1 (module doc) for a share of a batch's hits, into `buffers.searched`. A hit's
    /// whole search is kept only where it found no anchor (step 2 reads it): most find one,
    /// and the batch holds millions. What the search reads of each hit is gathered first,
    /// in the hits' order: the search visits the hits in spatial order, and a whole surface
    /// point spans two cache lines.
    fn search_share(&self, set: &AnchorSet, share: &[&SurfacePoint], buffers: &mut ShareBuffers) {
        use rayon::prelude::*;
        let ShareBuffers {
            points,
            positions,
            keys,
            order,
            searched,
        } = buffers;
        share
            .par_iter()
            .map(|sp| AttachPoint::of(sp, self.m))
            .collect_into_vec(points);
        positions.clear();
        positions.extend(points.iter().map(|p| p.position));
        crate::photon::knn::query_order_into(positions, keys, order);
        let points = &*points;
        // A group of hits at a time, each step's reads asked of the cache for the whole
        // group before the step makes them: the next group's points (read in the search's
        // order, not the hits'), the photons' links, the linked anchors.
        let search = |group: &[u32], next: &[u32], put: &mut dyn FnMut(Searched)| {
            for &i in next {
                prefetch_value(&points[i as usize]);
            }
            let mut photons = [None; SEARCH_GROUP];
            for (ph, &i) in photons.iter_mut().zip(group) {
                *ph = self.nearest_photon(points[i as usize].position);
                if let Some(ph) = *ph {
                    prefetch_line(&set.photon_links[ph]);
                }
            }
            for &ph in &photons {
                if let Some(a) = ph.and_then(|ph| set.photon_links[ph]) {
                    prefetch_line(set.anchor(a));
                }
            }
            for (&ph, &i) in photons.iter().zip(group) {
                let s = self.search(set, &points[i as usize], ph);
                put(Searched {
                    // A photon linked already keeps its anchor (step 3).
                    photon: s.photon.filter(|_| s.linked.is_none()).map(|ph| ph as u32),
                    visited: s.visited as u32,
                    found: match s.found {
                        Some(id) => Ok(id),
                        None => Err(Box::new(s)),
                    },
                });
            }
        };
        crate::photon::knn::map_in_order_grouped_into(order, SEARCH_GROUP, search, searched);
    }

    /// Step 3 (module doc) for the anchors `created`: their L_i, estimated
    /// where each anchor is stored (quantised position and normal), exactly as later frames
    /// re-estimate it: the normal test against photons can tip on a fraction of a degree.
    /// The search looks first within the reach step 2 set from a nearby anchor's
    /// ([`PhotonMap::irradiance_and_radius_near`]; unbounded where none was near).
    pub fn estimate_created(&self, set: &mut AnchorSet, created: &[AnchorId]) {
        let q = set.quantizer;
        let lift = set.lift(self.frame.static_radius());
        let k = self.params.anchor_k(self.k, self.pm.direct);
        let estimates: Vec<(Vec3, f32)> = {
            let set = &*set;
            let positions: Vec<Vec3> = created
                .iter()
                .map(|&id| set.anchor(id).position(&q))
                .collect();
            crate::photon::knn::map_in_query_order(&positions, |i| {
                let (a, x) = (set.anchor(created[i]), positions[i]);
                let reach = set.reach2(created[i]);
                let n = a.normal();
                let (e, r2) = self.pm.irradiance_and_radius_near(x, n, k, reach);
                (e + self.pm.direct_from(self.frame, x + lift * n, n), r2)
            })
        };
        for (&id, (e, r2)) in created.iter().zip(estimates) {
            set.anchor_mut(id).set_irradiance(e);
            set.set_reach(id, r2);
        }
    }
}

/// What step 1 keeps of a hit's [`Search`]: the anchor found, or the whole search for
/// step 2; the nearest photon if it had no anchor then, for step 3 (a linked one keeps
/// its anchor, and links are not removed while a batch attaches); the nodes it visited.
struct Searched {
    photon: Option<u32>,
    visited: u32,
    found: Result<AnchorId, Box<Search>>,
}

/// A batch of attachment under way ([`Attacher::begin`]).
pub struct Linking {
    made: Made,
    /// Anchor-tree searches made and the nodes they visited (§3's rebalancing rule).
    searched: u64,
    visited: u64,
    buffers: SearchBuffers,
}

/// The buffers of step 1 (module doc): those of the share being searched and of the one
/// step 2 reads. They pass from share to share, part to part and batch to batch
/// ([`Attacher::begin`], [`Attacher::end`]): fresh buffers, 27 MB a share, cost the kernel
/// a fault and a zeroed page at each first touch of 4 KiB, and a frame attaches one batch
/// for each round of placement.
#[derive(Default)]
pub struct SearchBuffers([ShareBuffers; 2]);

/// What step 1 holds for a share of hits ([`Attacher::search_share`]): what it reads of
/// each hit, their positions and spatial order, and what it found.
#[derive(Default)]
struct ShareBuffers {
    points: Vec<AttachPoint>,
    positions: Vec<Vec3>,
    keys: Vec<(u32, u32)>,
    order: QueryOrder,
    searched: Vec<Searched>,
}

/// What step 2 and the claims of step 3 change while a batch attaches (module doc), kept
/// apart from the set until every share of every part is searched.
struct Made {
    /// The photons' links as the claims leave them (a copy of the set's).
    links: Vec<Option<AnchorId>>,
    /// The ids [`AnchorSet::add`] will give the anchors made, in order.
    ids: Box<dyn Iterator<Item = AnchorId> + Send + Sync>,
    /// The anchors made, in order: id, anchor, and the squared reach its L_i is searched
    /// within first.
    anchors: Vec<(AnchorId, Anchor, f32)>,
    /// Each made anchor's place in `anchors`, by id.
    place: HashMap<u32, u32>,
    /// The made anchors' positions, with their places in `anchors`.
    fresh: KdTree,
}

/// What attachment reads of a static gather hit: where it lies (with the error bound of
/// its position), which way its surface faces, and its albedo.
#[derive(Clone, Copy)]
struct AttachPoint {
    position: Vec3,
    error: Vec3,
    ng: Vec3,
    albedo: Vec3,
}

impl AttachPoint {
    fn of(sp: &SurfacePoint, m: Materials) -> AttachPoint {
        AttachPoint {
            position: sp.position,
            error: sp.error,
            ng: sp.ng,
            albedo: sp.albedo(m),
        }
    }
}

/// Hits that step 1 searches together, in their spatial order ([`Attacher::link_all`]):
/// what it reads of each hit is gathered for a share at once (48 bytes a hit, 12.6 MB), a
/// batch at the final preset holds millions, and a share's step 2 runs beside the next
/// share's search. (Shares of an eighth of the batch, for more of step 2 beside the
/// searches, made Sponza's frame 1 slower: the searches lose locality.)
pub const SEARCH_SHARE: usize = 1 << 18;

/// Hits of a share that step 1 searches as a group ([`Attacher::search_share`]): their
/// photons first, then their links and anchors, each step's reads asked of the cache for
/// the whole group before the next step makes them. (Groups of 4 and 16 were no
/// different on Sponza, nor were the steps run a few hits apart, as a pipeline.)
const SEARCH_GROUP: usize = 8;

/// Bytes step 1 holds for a share of hits ([`SEARCH_SHARE`], [`SearchBuffers`]): what it
/// reads of each hit, the hit's position, sort key and place in the order, and what it
/// found; two shares are held at once (one searched beside the last one's step 2), 55 MB.
pub const SHARE_BYTES: usize = SEARCH_SHARE
    * (size_of::<AttachPoint>()
        + size_of::<Vec3>()
        + size_of::<(u32, u32)>()
        + size_of::<u32>()
        + size_of::<Searched>());

/// What step 1 (module doc) found for one hit.
struct Search {
    /// What the search read of the hit (step 2 reads it again).
    hit: AttachPoint,
    /// The nearest photon within the photon radius, and the anchor it linked to then.
    photon: Option<usize>,
    linked: Option<AnchorId>,
    /// D_max at the hit.
    d_max: f32,
    /// The anchor found, if any, and the nearest anchors within D_max the search tried
    /// (squared distance, id).
    found: Option<AnchorId>,
    near: Neighbours,
    /// Nodes of the anchor kd-tree the search visited (0: it made none).
    visited: u64,
}
