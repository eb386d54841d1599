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

use glam::{Vec2, Vec3};

use crate::scene::material::srgb_to_linear;

/// A compact anchor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(C)]
pub struct Anchor {
    /// Quantised position: 3 × 21 bits in a u64, stored as four u16 (alignment 2).
    position: [u16; 4],
    normal: [u8; 2],
    /// L_i in RGBE.
    irradiance: [u8; 4],
    /// Albedo, sRGB-encoded.
    albedo: [u8; 3],
    /// Liveness: 0 = free slot (ids of live anchors are stable).
    live: u8,
}

/// Maps positions inside the static scene's box to 21-bit integers and back.
#[derive(Debug, Clone, Copy)]
pub struct Quantizer {
    lo: Vec3,
    step: Vec3,
}

const QMAX: f32 = ((1u32 << 21) - 1) as f32;

impl Quantizer {
    pub fn new(lo: Vec3, hi: Vec3) -> Self {
        let extent = (hi - lo).max(Vec3::splat(f32::MIN_POSITIVE));
        // Pad by a step so that points on the box's faces stay inside.
        let lo = lo - extent / QMAX;
        let step = extent * (1.0 + 2.0 / QMAX) / QMAX;
        Quantizer { lo, step }
    }

    fn encode(&self, p: Vec3) -> u64 {
        let q = ((p - self.lo) / self.step)
            .round()
            .clamp(Vec3::ZERO, Vec3::splat(QMAX));
        (q.x as u64) | (q.y as u64) << 21 | (q.z as u64) << 42
    }

    fn decode(&self, v: u64) -> Vec3 {
        let m = (1u64 << 21) - 1;
        let q = Vec3::new((v & m) as f32, (v >> 21 & m) as f32, (v >> 42 & m) as f32);
        self.lo + q * self.step
    }

    /// Largest distance between a point and its decoded position.
    pub fn max_error(&self) -> f32 {
        0.5 * self.step.length()
    }
}

/// Ward's RGBE: a shared 8-bit exponent and three 8-bit mantissas.
pub fn rgbe_encode(c: Vec3) -> [u8; 4] {
    let c = c.max(Vec3::ZERO);
    let m = c.max_element();
    if !(m > 1e-38) || !m.is_finite() {
        return [0; 4];
    }
    let e = m.log2().floor() as i32 + 1; // m < 2^e
    let e = e.clamp(-127, 128);
    let scale = 256.0 / 2f32.powi(e);
    let q = |v: f32| (v * scale).floor().min(255.0) as u8;
    [q(c.x), q(c.y), q(c.z), (e + 127) as u8]
}

pub fn rgbe_decode(v: [u8; 4]) -> Vec3 {
    if v == [0; 4] {
        return Vec3::ZERO;
    }
    let f = 2f32.powi(v[3] as i32 - 127 - 8);
    Vec3::new(v[0] as f32 + 0.5, v[1] as f32 + 0.5, v[2] as f32 + 0.5) * f
}

/// Octahedral normal encoding in two bytes.
fn oct_encode(n: Vec3) -> [u8; 2] {
    let n = n / (n.x.abs() + n.y.abs() + n.z.abs()).max(f32::MIN_POSITIVE);
    let p = if n.z >= 0.0 {
        Vec2::new(n.x, n.y)
    } else {
        Vec2::new(
            (1.0 - n.y.abs()) * n.x.signum(),
            (1.0 - n.x.abs()) * n.y.signum(),
        )
    };
    let q = |v: f32| ((v * 0.5 + 0.5) * 255.0).round().clamp(0.0, 255.0) as u8;
    [q(p.x), q(p.y)]
}

fn oct_decode(e: [u8; 2]) -> Vec3 {
    let p = Vec2::new(
        e[0] as f32 / 255.0 * 2.0 - 1.0,
        e[1] as f32 / 255.0 * 2.0 - 1.0,
    );
    let z = 1.0 - p.x.abs() - p.y.abs();
    let (x, y) = if z >= 0.0 {
        (p.x, p.y)
    } else {
        (
            (1.0 - p.y.abs()) * p.x.signum(),
            (1.0 - p.x.abs()) * p.y.signum(),
        )
    };
    Vec3::new(x, y, z).normalize_or_zero()
}

fn srgb_encode(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

impl Anchor {
    pub fn new(
        q: &Quantizer,
        position: Vec3,
        normal: Vec3,
        albedo: Vec3,
        irradiance: Vec3,
    ) -> Self {
        let p = q.encode(position);
        Anchor {
            position: [
                p as u16,
                (p >> 16) as u16,
                (p >> 32) as u16,
                (p >> 48) as u16,
            ],
            normal: oct_encode(normal),
            irradiance: rgbe_encode(irradiance),
            albedo: [
                srgb_encode(albedo.x),
                srgb_encode(albedo.y),
                srgb_encode(albedo.z),
            ],
            live: 1,
        }
    }

    pub fn position(&self, q: &Quantizer) -> Vec3 {
        let p = self.position;
        q.decode(p[0] as u64 | (p[1] as u64) << 16 | (p[2] as u64) << 32 | (p[3] as u64) << 48)
    }

    pub fn normal(&self) -> Vec3 {
        oct_decode(self.normal)
    }

    pub fn albedo(&self) -> Vec3 {
        Vec3::new(
            srgb_to_linear(self.albedo[0] as f32 / 255.0),
            srgb_to_linear(self.albedo[1] as f32 / 255.0),
            srgb_to_linear(self.albedo[2] as f32 / 255.0),
        )
    }

    pub fn irradiance(&self) -> Vec3 {
        rgbe_decode(self.irradiance)
    }

    pub fn set_irradiance(&mut self, e: Vec3) {
        self.irradiance = rgbe_encode(e);
    }

    /// Radiance leaving the anchor: albedo × L_i / π.
    pub fn radiance(&self) -> Vec3 {
        self.albedo() * self.irradiance() * std::f32::consts::FRAC_1_PI
    }

    pub fn is_live(&self) -> bool {
        self.live != 0
    }
}

/// A point kd-tree with incremental insertion (the anchor kd-tree of §3).
#[derive(Debug, Clone, Default)]
pub struct KdTree {
    nodes: Vec<KdNode>,
    root: u32,
    /// Nodes visited by searches since the last reset.
    pub visited: u64,
    pub searches: u64,
}

#[derive(Debug, Clone, Copy)]
struct KdNode {
    point: Vec3,
    item: u32,
    axis: u8,
    left: u32,
    right: u32,
}

const NIL: u32 = u32::MAX;

impl KdTree {
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Inserts at the leaf the point descends to (unbalanced, as anchors arrive).
    pub fn insert(&mut self, point: Vec3, item: u32) {
        let id = self.nodes.len() as u32;
        if self.nodes.is_empty() {
            self.nodes.push(KdNode {
                point,
                item,
                axis: 0,
                left: NIL,
                right: NIL,
            });
            self.root = 0;
            return;
        }
        let mut at = self.root;
        loop {
            let n = self.nodes[at as usize];
            let go_left = point[n.axis as usize] < n.point[n.axis as usize];
            let next = if go_left { n.left } else { n.right };
            if next == NIL {
                self.nodes.push(KdNode {
                    point,
                    item,
                    axis: (n.axis + 1) % 3,
                    left: NIL,
                    right: NIL,
                });
                let n = &mut self.nodes[at as usize];
                if go_left {
                    n.left = id;
                } else {
                    n.right = id;
                }
                return;
            }
            at = next;
        }
    }

    /// A balanced tree over `points` (median splits on the widest axis).
    pub fn balanced(points: &[(Vec3, u32)]) -> KdTree {
        let mut t = KdTree {
            nodes: Vec::with_capacity(points.len()),
            root: NIL,
            visited: 0,
            searches: 0,
        };
        let mut pts = points.to_vec();
        t.root = t.build(&mut pts);
        t
    }

    fn build(&mut self, pts: &mut [(Vec3, u32)]) -> u32 {
        if pts.is_empty() {
            return NIL;
        }
        let (lo, hi) = pts.iter().fold(
            (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
            |(l, h), p| (l.min(p.0), h.max(p.0)),
        );
        let e = hi - lo;
        let axis = if e.x >= e.y && e.x >= e.z {
            0
        } else if e.y >= e.z {
            1
        } else {
            2
        };
        let mid = pts.len() / 2;
        pts.select_nth_unstable_by(mid, |a, b| {
            a.0[axis].total_cmp(&b.0[axis]).then(a.1.cmp(&b.1))
        });
        let id = self.nodes.len() as u32;
        self.nodes.push(KdNode {
            point: pts[mid].0,
            item: pts[mid].1,
            axis: axis as u8,
            left: NIL,
            right: NIL,
        });
        let (l, r) = pts.split_at_mut(mid);
        let left = self.build(l);
        let right = self.build(&mut r[1..]);
        self.nodes[id as usize].left = left;
        self.nodes[id as usize].right = right;
        id
    }

    /// Up to `k` nearest items within `radius` of `p` passing `accept`, nearest first, as
    /// (squared distance, item). Ties break by item, so results never depend on layout.
    pub fn nearest(
        &mut self,
        p: Vec3,
        radius: f32,
        k: usize,
        accept: impl Fn(u32) -> bool,
    ) -> Vec<(f32, u32)> {
        let mut best: Vec<(f32, u32)> = Vec::with_capacity(k + 1);
        if self.nodes.is_empty() || k == 0 {
            return best;
        }
        self.searches += 1;
        let mut r2 = radius * radius;
        let mut stack = vec![self.root];
        while let Some(i) = stack.pop() {
            if i == NIL {
                continue;
            }
            self.visited += 1;
            let n = self.nodes[i as usize];
            let d2 = (n.point - p).length_squared();
            if d2 <= r2 && accept(n.item) {
                let pos = best.partition_point(|&(d, it)| (d, it) < (d2, n.item));
                best.insert(pos, (d2, n.item));
                if best.len() > k {
                    best.pop();
                }
                if best.len() == k {
                    r2 = best[k - 1].0;
                }
            }
            let delta = p[n.axis as usize] - n.point[n.axis as usize];
            let (near, far) = if delta < 0.0 {
                (n.left, n.right)
            } else {
                (n.right, n.left)
            };
            if delta * delta <= r2 {
                stack.push(far);
            }
            stack.push(near);
        }
        best
    }

    /// Average nodes visited per search since the last reset.
    pub fn mean_visited(&self) -> f64 {
        if self.searches == 0 {
            0.0
        } else {
            self.visited as f64 / self.searches as f64
        }
    }
}

/// Anchor density control (§3.3.1).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Density {
    /// One radius D_max everywhere.
    Constant,
    /// D_max inversely proportional to the local density of global importons (Suykens 2002).
    Importance,
}

/// All anchors of a render, with their kd-tree and the photon links of the current frame.
pub struct AnchorSet {
    pub anchors: Vec<Anchor>,
    free: Vec<u32>,
    pub tree: KdTree,
    pub quantizer: Quantizer,
    /// For each photon of the current frame, the anchor it links to (§3.3.2).
    pub photon_links: Vec<u32>,
    /// Anchors created since the last call to [`AnchorSet::take_created`].
    created: u64,
    /// Per anchor, 2 bytes: how far its last estimate reached (the k-th photon), as an f16
    /// in units of 16 quantisation steps, rounded up; infinite when unknown. An anchor whose
    /// reach no changed photon enters keeps its estimate ([`super::coherent`]).
    reach: Vec<u16>,
    /// The photons of the previous frame, to tell which ones changed.
    pub previous_photons: super::photons::PhotonPaths,
}

/// Memory per anchor: the [`Anchor`] and its estimate's reach in [`AnchorSet`].
pub const BYTES_PER_ANCHOR: usize = size_of::<Anchor>() + size_of::<u16>();

/// "No anchor" in links.
pub const NONE: u32 = (1 << 30) - 1;

impl AnchorSet {
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
        16.0 * self.quantizer.step.max_element()
    }

    /// Records that anchor `id`'s estimate depends on no photon farther than √`r2`.
    pub fn set_reach(&mut self, id: u32, r2: f32) {
        let r = r2.sqrt() / self.reach_unit();
        let mut h = half::f16::from_f32(r);
        if h.to_f32() < r {
            h = half::f16::from_bits(h.to_bits() + 1);
        }
        self.reach[id as usize] = if r.is_finite() {
            h.to_bits()
        } else {
            half::f16::INFINITY.to_bits()
        };
    }

    /// The squared reach of anchor `id`'s estimate (at least the true one).
    pub fn reach2(&self, id: u32) -> f32 {
        let r = half::f16::from_bits(self.reach[id as usize]).to_f32() * self.reach_unit();
        r * r * (1.0 + 1e-5)
    }

    pub fn live_count(&self) -> usize {
        self.anchors.len() - self.free.len()
    }

    pub fn take_created(&mut self) -> u64 {
        std::mem::take(&mut self.created)
    }

    /// Adds an anchor; returns its id (a free slot's id is reused).
    pub fn add(&mut self, a: Anchor) -> u32 {
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
        id
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
                a.live = 0;
                self.free.push(i as u32);
            }
        }
        // Reuse the lowest free ids first, so that ids stay small and the order is fixed.
        self.free.sort_unstable_by(|a, b| b.cmp(a));
        self.free.dedup();
        self.tree = KdTree::balanced(&pts);
    }

    /// Rebuilds a balanced tree when searches visit more than `factor` × log2(n) nodes on
    /// average (§3); returns whether it did.
    pub fn rebalance_if_needed(&mut self, factor: f64) -> bool {
        let n = self.live_count().max(2) as f64;
        let needed = self.tree.searches > 0 && self.tree.mean_visited() > factor * n.log2();
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
    fn anchors_fit_in_twenty_bytes() {
        assert!(size_of::<Anchor>() <= 20, "{}", size_of::<Anchor>());
    }

    #[test]
    fn rgbe_round_trips_from_tiny_to_huge() {
        for v in [1e-30f32, 1e-6, 0.3, 1.0, 7.5, 1e6, 1e30] {
            let c = Vec3::new(v, 0.5 * v, 0.25 * v);
            let d = rgbe_decode(rgbe_encode(c));
            assert!(
                ((d - c).abs() / c.max_element()).max_element() < 1.0 / 128.0,
                "{c} -> {d}"
            );
        }
        assert_eq!(rgbe_decode(rgbe_encode(Vec3::ZERO)), Vec3::ZERO);
    }

    #[test]
    fn positions_keep_relative_precision_at_any_scale() {
        for s in [1e-3f32, 1.0, 1e4] {
            let q = Quantizer::new(Vec3::splat(-10.0 * s), Vec3::splat(30.0 * s));
            let p = Vec3::new(1.234, -5.678, 29.9) * s;
            let a = Anchor::new(&q, p, Vec3::Y, Vec3::splat(0.5), Vec3::ONE);
            assert!(
                (a.position(&q) - p).length() <= q.max_error() * 1.01,
                "scale {s}"
            );
            assert!(q.max_error() < 40.0 * s * 1e-6);
        }
    }

    #[test]
    fn normals_and_albedo_survive_encoding() {
        for n in [
            Vec3::X,
            -Vec3::Y,
            Vec3::new(0.3, -0.5, 0.8).normalize(),
            Vec3::new(-0.6, 0.1, -0.79).normalize(),
        ] {
            let q = Quantizer::new(Vec3::ZERO, Vec3::ONE);
            let a = Anchor::new(&q, Vec3::ZERO, n, Vec3::new(0.73, 0.05, 0.5), Vec3::ONE);
            assert!(a.normal().dot(n) > 0.9995, "{n} -> {}", a.normal());
            assert!(
                (a.albedo() - Vec3::new(0.73, 0.05, 0.5))
                    .abs()
                    .max_element()
                    < 0.004
            );
        }
    }

    #[test]
    fn kd_tree_finds_the_same_neighbours_balanced_or_not() {
        let pts: Vec<(Vec3, u32)> = (0..500u32)
            .map(|i| {
                let h = crate::sampling::hash(&[i]);
                (
                    Vec3::new(
                        (h & 1023) as f32,
                        (h >> 10 & 1023) as f32,
                        (h >> 20 & 1023) as f32,
                    ) * 0.01,
                    i,
                )
            })
            .collect();
        let mut inc = KdTree::default();
        for &(p, i) in &pts {
            inc.insert(p, i);
        }
        let mut bal = KdTree::balanced(&pts);
        for q in [Vec3::splat(5.0), Vec3::new(1.0, 9.0, 3.0)] {
            let a = inc.nearest(q, 2.0, 3, |_| true);
            let b = bal.nearest(q, 2.0, 3, |_| true);
            let mut brute: Vec<(f32, u32)> = pts
                .iter()
                .map(|&(p, i)| ((p - q).length_squared(), i))
                .filter(|x| x.0 <= 4.0)
                .collect();
            brute.sort_by(|x, y| x.partial_cmp(y).unwrap());
            brute.truncate(3);
            assert_eq!(a, brute);
            assert_eq!(b, brute);
        }
        assert!(bal.mean_visited() < inc.mean_visited() * 2.0 + 50.0);
    }
}
