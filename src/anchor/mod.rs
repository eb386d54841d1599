//! Anchors (the paper's §3, §3.1, §3.3, Pseudocode 1): final-gather hit points on static
//! geometry, linked permanently from cache strata, whose irradiance L_i is re-estimated from
//! each frame's photons so that strata need no ray tracing while nothing moves in front of
//! them.
//!
//! Storage is compact (§3: 22 bytes there, 18 here): the position quantised to 21 bits per
//! axis inside the static scene's bounding box (relative, so equally fine at any scene
//! scale: 36 m Sponza → 17 µm), the normal octahedron-encoded in two bytes, L_i in RGBE
//! (Ward's shared exponent: 2^−128..2^127, 8-bit mantissa relative to the brightest channel,
//! so intensities from 1e−6 to 1e6 and beyond survive) and the albedo as three sRGB-encoded
//! bytes.
//!
//! The anchor kd-tree is our own: the paper inserts anchors one by one as gather rays find
//! no suitable neighbour and rebalances when the average number of nodes a search visits
//! grows past a threshold, which needs a point kd-tree with incremental insertion and visit
//! counts — kiddo's bucketed trees expose neither.

pub mod attach;
pub mod importons;
pub mod kdtree;
pub mod packed;

use glam::Vec3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::photon::{GatherDirect, PhotonPaths};
pub use kdtree::KdTree;
pub use packed::{Anchor, Quantizer};

/// The id of an anchor: its slot in [`AnchorSet::anchors`], stable while the anchor lives.
/// Strata store it in 30 bits ([`AnchorId::MAX`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct AnchorId(pub u32);

impl AnchorId {
    /// The largest id a stratum can link.
    pub const MAX: u32 = (1 << 30) - 2;

    pub fn index(self) -> usize {
        self.0 as usize
    }

    /// The value of the `anchor_id` AOV: id + 1, and 0 for none.
    pub fn aov(id: Option<AnchorId>) -> u32 {
        id.map_or(0, |a| a.0 + 1)
    }
}

/// Anchor settings ([`AnchorParams::default`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct AnchorParams {
    /// D_max (§3.3.1) as a fraction of the static scene's bounding-sphere radius. Default 0.01.
    #[schemars(extend("exclusiveMinimum" = 0, "maximum" = 1))]
    pub d_max: f32,
    /// D_max in scene units instead; overrides `d_max` when set.
    #[schemars(extend("exclusiveMinimum" = 0))]
    pub d_max_absolute: Option<f32>,
    /// `constant` D_max, or `importance`-driven from global importons. Default constant.
    pub density: Density,
    /// Radius of the nearest-photon search of Pseudocode 1 (§3.3.2), as a fraction of the
    /// scene radius. Default 0.005.
    #[schemars(extend("exclusiveMinimum" = 0, "maximum" = 1))]
    pub photon_radius: f32,
    /// Reuse heuristics (§3.1): cosine between normals at least this; default 0.9.
    #[schemars(range(min = -1, max = 1))]
    pub normal_cos: f32,
    /// Reuse heuristics: largest albedo difference per channel; default 0.1.
    #[schemars(range(min = 0))]
    pub albedo_tolerance: f32,
    /// Rebalance the anchor kd-tree when searches visit more than this × log2(anchors)
    /// nodes on average (§3); it is rebuilt too after a frame that made more than a quarter
    /// of the live anchors (the first frame, which grows it from nothing). Default 1.75: on
    /// Sponza at the `final` preset, attachment's searches visit 1.6 × log2(anchors) nodes
    /// in a freshly balanced tree and 1.8–2 × in one grown by insertion, where attachment's
    /// first step takes about 7 % longer.
    #[schemars(range(min = 1))]
    pub rebalance: f32,
    /// Importons for `importance` density, per pixel. Default 0.25.
    #[schemars(extend("exclusiveMinimum" = 0, "maximum" = 16))]
    pub importons_per_pixel: f32,
    /// Photons per anchor estimate, as a multiple of the method's `k`. Default 2 where the
    /// photon estimates hold the first bounce (`gather_direct` `photons`), 1 where shadow
    /// rays stand in for it (`shadow-rays`, in a frame with a punctual light).
    #[schemars(extend("exclusiveMinimum" = 0, "maximum" = 64))]
    pub k_scale: Option<f32>,
}

impl AnchorParams {
    /// The default `k_scale` for where the gather hits' direct light comes from.
    ///
    /// With [`GatherDirect::Photons`], 2: anchors are far fewer than gather hits, so a wider
    /// estimate per anchor costs little, and it holds the first bounce's light, whose variance
    /// the wider estimate halves; on the example's fixed camera it reads nearer the
    /// path-traced reference than brute force does and flickers less. With
    /// [`GatherDirect::ShadowRays`], 1: the estimate then holds only light that has bounced
    /// at least once (and emissive triangles' first hits), smooth enough that the wider
    /// disc's bias outweighs its lower noise.
    /// On Sponza's frame 8 (160 × 90, production) the indirect light reads 10.3 % low at 1
    /// and 11.6 % low at 2 (brute force, at 1 by construction, 9.2 %), and with 64 times the
    /// photons 1.7 % and 3.3 % (brute force 1.0 %), each against the path tracer; over
    /// frames 0–8 the anchors still flicker less than brute force at 1 (README, "Photons per
    /// anchor estimate with shadow rays").
    pub fn default_k_scale(direct: GatherDirect) -> f32 {
        match direct {
            GatherDirect::Photons => 2.0,
            GatherDirect::ShadowRays => 1.0,
        }
    }

    /// Photons per anchor estimate for the method's `k`, where the photon map's estimates
    /// hold what `direct` says ([`crate::photon::PhotonMap::direct`]: a frame without
    /// punctual lights holds every first hit, whatever `gather_direct` asks).
    pub fn anchor_k(&self, k: usize, direct: GatherDirect) -> usize {
        let scale = self.k_scale.unwrap_or(Self::default_k_scale(direct));
        ((k as f32 * scale).round() as usize).max(1)
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
            rebalance: 1.75,
            importons_per_pixel: 0.25,
            k_scale: None,
        }
    }
}

/// Anchor density control (§3.3.1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum Density {
    /// One radius D_max everywhere.
    Constant,
    /// D_max inversely proportional to the local density of global importons (Suykens 2002).
    Importance,
}

/// All anchors of a render, with their kd-tree and the photon links of the current frame:
/// part of the frame state a render carries from frame to frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AnchorSet {
    pub anchors: Vec<Anchor>,
    free: Vec<u32>,
    pub tree: KdTree,
    pub quantizer: Quantizer,
    /// For each photon of the current frame, the anchor it links to (§3.3.2).
    pub photon_links: Vec<Option<AnchorId>>,
    /// Anchors created since the last call to [`AnchorSet::take_created`].
    created: u64,
    /// Per anchor, 2 bytes: how far its last estimate reached (the k-th photon), as an f16
    /// in units of 16 quantisation steps, rounded up; infinite when unknown. An anchor whose
    /// reach no changed photon enters keeps its estimate
    /// (`integrator::anchors`).
    reach: Vec<u16>,
    /// The photons of the previous frame, to tell which ones changed.
    pub previous_photons: PhotonPaths,
}

/// Memory per anchor: the [`Anchor`] and its estimate's reach in [`AnchorSet`].
pub const BYTES_PER_ANCHOR: usize = size_of::<Anchor>() + size_of::<u16>();

impl AnchorSet {
    /// Checks a set read from disk: every index it holds points into it.
    pub fn check(&self) -> Result<(), String> {
        let n = self.anchors.len();
        if self.reach.len() != n {
            return Err(format!("{} anchors but {} reaches", n, self.reach.len()));
        }
        if self.free.iter().any(|&f| f as usize >= n) {
            return Err("a free anchor slot is out of range".into());
        }
        if self.photon_links.iter().flatten().any(|a| a.index() >= n) {
            return Err("a photon links to an anchor that does not exist".into());
        }
        self.tree.check(n)?;
        // Searches take the tree's anchors as live (`attach`).
        if self
            .tree
            .items()
            .any(|i| !self.anchors[i as usize].is_live())
        {
            return Err("the anchor kd-tree holds a free anchor slot".into());
        }
        self.previous_photons.check()
    }

    pub fn new(quantizer: Quantizer) -> Self {
        AnchorSet {
            anchors: Vec::new(),
            free: Vec::new(),
            tree: KdTree::default(),
            quantizer,
            photon_links: Vec::new(),
            created: 0,
            reach: Vec::new(),
            previous_photons: Default::default(),
        }
    }

    fn reach_unit(&self) -> f32 {
        16.0 * self.quantizer.step().max_element()
    }

    /// Records that anchor `id`'s estimate depends on no photon farther than √`r2`.
    pub fn set_reach(&mut self, id: AnchorId, r2: f32) {
        let r = r2.sqrt() / self.reach_unit();
        let mut h = half::f16::from_f32(r);
        if h.to_f32() < r {
            h = half::f16::from_bits(h.to_bits() + 1);
        }
        self.reach[id.index()] = if r.is_finite() {
            h.to_bits()
        } else {
            half::f16::INFINITY.to_bits()
        };
    }

    /// How far above an anchor's decoded position the rays that leave it start (its
    /// surface found again, its shadow rays), in a scene of bounding radius `scene_radius`:
    /// far enough to clear the quantisation and the hit's rounding, near enough that no
    /// other surface fits in between.
    pub fn lift(&self, scene_radius: f32) -> f32 {
        16.0 * self.quantizer.max_error() + 1e-6 * scene_radius
    }

    /// The squared reach of anchor `id`'s estimate (at least the true one).
    pub fn reach2(&self, id: AnchorId) -> f32 {
        let r = half::f16::from_bits(self.reach[id.index()]).to_f32() * self.reach_unit();
        r * r * (1.0 + 1e-5)
    }

    /// Asks the CPU to bring anchor `id` and its reach into its cache, for a read soon.
    #[inline]
    pub fn prefetch(&self, id: AnchorId) {
        if let (Some(a), Some(r)) = (self.anchors.get(id.index()), self.reach.get(id.index())) {
            crate::geom::prefetch_value(a);
            crate::geom::prefetch_line(r);
        }
    }

    pub fn anchor(&self, id: AnchorId) -> &Anchor {
        &self.anchors[id.index()]
    }

    pub fn anchor_mut(&mut self, id: AnchorId) -> &mut Anchor {
        &mut self.anchors[id.index()]
    }

    /// Bytes the set holds on the heap: anchors, their tree, photon links and the previous
    /// frame's photons.
    pub fn heap_bytes(&self) -> usize {
        self.anchors.len() * BYTES_PER_ANCHOR
            + self.free.len() * size_of::<u32>()
            + self.tree.heap_bytes()
            + self.photon_links.len() * size_of::<Option<AnchorId>>()
            + self.previous_photons.photons.len() * size_of::<crate::photon::Photon>()
            + self.previous_photons.path_start.len() * size_of::<u32>()
            + self.previous_photons.tree.heap_bytes()
    }

    pub fn live_count(&self) -> usize {
        self.anchors.len() - self.free.len()
    }

    pub fn take_created(&mut self) -> u64 {
        std::mem::take(&mut self.created)
    }

    /// The ids that [`AnchorSet::add`] gives the anchors added next, in order: the free
    /// slots as it reuses them, then new ones. (Attachment names the anchors it makes
    /// before it adds them: see [`attach`].)
    pub fn next_ids(&self) -> impl Iterator<Item = AnchorId> + use<> {
        let free = self.free.clone().into_iter().rev();
        free.chain(self.anchors.len() as u32..).map(AnchorId)
    }

    /// Adds an anchor; returns its id (a free slot's id is reused).
    pub fn add(&mut self, a: Anchor) -> AnchorId {
        let id = match self.free.pop() {
            Some(id) => {
                self.anchors[id as usize] = a;
                self.reach[id as usize] = half::f16::INFINITY.to_bits();
                id
            }
            None => {
                self.anchors.push(a);
                self.reach.push(half::f16::INFINITY.to_bits());
                (self.anchors.len() - 1) as u32
            }
        };
        self.tree.insert(a.position(&self.quantizer), id);
        self.created += 1;
        AnchorId(id)
    }

    /// Frees every anchor `referenced` does not mark and rebuilds a balanced tree (§3: kept
    /// while any stratum links it). Ids of live anchors do not change.
    pub fn collect(&mut self, referenced: &[bool]) {
        let mut pts = Vec::new();
        for (i, a) in self.anchors.iter_mut().enumerate() {
            if !a.is_live() {
                continue;
            }
            if referenced.get(i).copied().unwrap_or(false) {
                pts.push((a.position(&self.quantizer), i as u32));
            } else {
                a.kill();
                self.free.push(i as u32);
            }
        }
        // Reuse the lowest free ids first, so that ids stay small and the order is fixed.
        self.free.sort_unstable_by(|a, b| b.cmp(a));
        self.free.dedup();
        self.tree = KdTree::balanced(&pts);
    }

    /// Rebuilds a balanced tree when searches visit more than `factor` × log2(n) nodes on
    /// average (§3), or when the anchors created since [`AnchorSet::take_created`] are more
    /// than a quarter of the live ones (the first frame grows the tree from nothing, one
    /// insertion at a time, and its searches average fewer visits than the next frame's
    /// will); returns whether it did.
    pub fn rebalance_if_needed(&mut self, factor: f64) -> bool {
        let live = self.live_count();
        let n = live.max(2) as f64;
        let grown = self.created.saturating_mul(4) > live as u64;
        let needed =
            grown || (self.tree.searches > 0 && self.tree.mean_visited() > factor * n.log2());
        if needed {
            let pts: Vec<(Vec3, u32)> = self
                .anchors
                .iter()
                .enumerate()
                .filter(|(_, a)| a.is_live())
                .map(|(i, a)| (a.position(&self.quantizer), i as u32))
                .collect();
            self.tree = KdTree::balanced(&pts);
        }
        self.tree.visited = 0;
        self.tree.searches = 0;
        needed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anchors_estimate_from_twice_the_photons_only_where_photons_hold_the_first_bounce() {
        let p = AnchorParams::default();
        assert_eq!(p.anchor_k(50, GatherDirect::Photons), 100);
        assert_eq!(p.anchor_k(50, GatherDirect::ShadowRays), 50);
        let set = AnchorParams {
            k_scale: Some(1.5),
            ..p
        };
        assert_eq!(set.anchor_k(50, GatherDirect::Photons), 75);
        assert_eq!(set.anchor_k(50, GatherDirect::ShadowRays), 75);
        let tiny = AnchorParams {
            k_scale: Some(1e-3),
            ..p
        };
        assert_eq!(tiny.anchor_k(50, GatherDirect::ShadowRays), 1);
    }

    #[test]
    fn a_frame_that_made_most_of_the_anchors_leaves_a_balanced_tree() {
        let q = Quantizer::new(Vec3::ZERO, Vec3::splat(100.0));
        let at = |i: u32| {
            let h = crate::sampling::hash(&[i, 11]);
            Vec3::new((h & 1023) as f32, (h >> 10 & 1023) as f32, 500.0) * 0.09
        };
        let anchor = |i: u32| Anchor::new(&q, at(i), Vec3::Z, Vec3::splat(0.5), Vec3::ONE);
        let mut set = AnchorSet::new(q);
        for i in 0..4000 {
            set.add(anchor(i));
        }
        // No search was made, and the factor is one no search reaches: the growth decides.
        let grown = set.tree.clone();
        assert!(set.rebalance_if_needed(1e9));
        assert_ne!(set.tree, grown);
        assert_eq!(set.tree.len(), 4000);
        set.tree.check(4000).unwrap();
        assert_eq!(set.take_created(), 4000);
        // A frame that adds less than a quarter keeps the tree it grew.
        for i in 4000..4500 {
            set.add(anchor(i));
        }
        let grown = set.tree.clone();
        assert!(!set.rebalance_if_needed(1e9));
        assert_eq!(set.tree, grown);
    }
}
