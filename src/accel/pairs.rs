//! The traversal of a BVH2 that obvhs built, over a copy laid out for it: every pair of
//! siblings in one 64-byte line, their two boxes stored axis by axis so that one SIMD step
//! measures both, and every leaf's triangles in blocks of four stored coordinate by
//! coordinate, so that one set of SIMD steps tests four, with each one's alpha flag as a bit.
//!
//! A leaf's triangles are tested four at a time ([`block_test`]): the watertight test of
//! `ShearedRay::intersect_barycentric` with the same f32 arithmetic lane by lane, so that
//! each lane finds the distance the one-triangle test finds. The lanes that test would
//! decide by another path (an edge function exactly zero or a distance within its error
//! bound of zero, both redone in f64; a value that is not finite; an alpha-masked
//! triangle) go to it one at a time. On Sponza's gather rays this traces 1.3× as many
//! closest-hit rays a second as testing one triangle at a time, and shadow rays 1.2× as many
//! (`cargo bench --bench rays`).
//!
//! A record's gather rays leave one point in neighbouring directions, so the gather traces
//! them four at a time ([`PairTree::closest4`], 2 × 2 neighbouring strata): one walk of the
//! tree for the four, each pair's two boxes tested against the four rays in SIMD lanes, a
//! subtree entered with the lanes that enter its box, a leaf tested for each of them. On
//! Sponza's gather rays that traces 1.20–1.23× as many a second as one ray at a time, with the
//! same hits (`cargo bench --bench rays`).
//!
//! Where the CPU has AVX2, rays from one point take [`wide`]'s tests instead: a pair's two
//! boxes against the four rays in eight lanes, and a leaf's blocks against two rays at once,
//! with the same arithmetic lane by lane, and so the same hits.
//!
//! A four-wide tree (obvhs's BVH2 collapsed, each node taking in the children of its largest
//! interior children, the entered children sorted by entry distance) traced 17 % fewer
//! closest-hit rays a second than these pairs and 40 % fewer shadow rays, and so is not used.
//!
//! Written here rather than calling obvhs's `Bvh2::ray_traverse`: its nodes are 32 bytes
//! each, so that half the sibling pairs straddle two cache lines; it tests the two boxes one
//! after the other; and a leaf's triangles are reached through `primitive_indices` into the
//! geometry, with the triangle's 80-byte shading record read to learn that it is opaque. On
//! Sponza's final-gather rays a traversal meets some 41 box pairs and 14 triangles.
//!
//! The order is obvhs's (the nearer child first, a leaf child's triangles tested as soon as
//! its box is hit, the same box and triangle arithmetic), and the closest hit does not
//! depend on it: of two triangles hit at the same `t` (a ray through a shared edge, faces
//! that coincide) the one with the lower index in the geometry wins. (Every box is padded
//! beyond its triangles, so the ray enters it before it meets them, and a box that holds a
//! tie is opened.) So the hits, and the images, do not depend on how the BVH was built: its
//! preset, its thread count.

use glam::{Vec3A, Vec4, Vec4Swizzles};
use obvhs::aabb::Aabb;
use obvhs::bvh2::Bvh2;
use obvhs::faststack::FastStack;
use obvhs::ray::Ray;
use obvhs::triangle::Triangle;

use super::{Lanes, ShearedRay, lanes4, t_error};
use crate::geom::Geometry;

#[cfg(target_arch = "x86_64")]
mod wide;
#[cfg(target_arch = "x86_64")]
use wide::Wide;

/// A node's link: a leaf's triangles in slots `index..index + count` (`count` > 0),
/// or the pair that holds an interior node's two children (`count` 0).
#[derive(Debug, Clone, Copy, Default)]
struct Link {
    index: u32,
    count: u32,
}

/// A block of four triangles of one leaf: `v[k][a]` holds coordinate `a` of vertex `k`, lane
/// `i` for the block's triangle `i`. A leaf's last block is padded with zeros: a slot takes
/// 36 bytes here and 4 in `order`, and Sponza's triangles fill 72 % of their slots.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C)]
struct Quad {
    v: [[Vec4; 3]; 3],
}

/// Two siblings: per axis, the lanes hold the left box's minimum, the right's minimum, the
/// left's maximum and the right's maximum.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(64))]
struct Pair {
    x: Vec4,
    y: Vec4,
    z: Vec4,
    link: [Link; 2],
}

/// A BVH2 laid out for traversal (module doc), with the triangles of its leaves.
pub(super) struct PairTree {
    /// The root's box and link; `None` for an empty tree.
    root: Option<(Aabb, Link)>,
    pairs: Vec<Pair>,
    /// The geometry's triangles in leaf order, each leaf starting a block; triangle (slot)
    /// `i` is lane `i % 4` of block `i / 4`.
    quads: Vec<Quad>,
    /// The index in the geometry of the triangle in each slot (`u32::MAX`: padding).
    order: Vec<u32>,
    /// Bit `i` set where the triangle in slot `i` is alpha-masked.
    masked: Vec<u64>,
    max_depth: usize,
    /// Whether [`PairTree::closest4`] tests rays from one point in AVX2's eight lanes
    /// ([`Wide`]): where the CPU has it.
    wide: bool,
}

impl PairTree {
    /// The layout of `bvh` (`None`: no geometry), built over `g`.
    pub(super) fn new(bvh: Option<&Bvh2>, g: &Geometry) -> PairTree {
        let Some(bvh) = bvh.filter(|b| !b.nodes.is_empty()) else {
            return PairTree {
                root: None,
                pairs: Vec::new(),
                quads: Vec::new(),
                order: Vec::new(),
                masked: Vec::new(),
                max_depth: 0,
                wide: false,
            };
        };
        let mut quads: Vec<Quad> = Vec::new();
        let mut order: Vec<u32> = Vec::new();
        // A leaf's triangles into blocks of their own: its link's index is its first slot.
        let mut place = |first: u32, count: u32| {
            let index = order.len() as u32;
            let tris = &bvh.primitive_indices[first as usize..(first + count) as usize];
            for four in tris.chunks(4) {
                let mut q = Quad::default();
                for (lane, &i) in four.iter().enumerate() {
                    let t = &g.triangles[i as usize];
                    for (k, v) in [t.v0, t.v1, t.v2].into_iter().enumerate() {
                        for a in 0..3 {
                            q.v[k][a][lane] = v[a];
                        }
                    }
                }
                quads.push(q);
                order.extend(four);
                order.resize(quads.len() * 4, u32::MAX);
            }
            Link { index, count }
        };
        // Pairs in depth-first order: a node's children, then their subtrees.
        let mut pairs: Vec<Pair> = Vec::new();
        let mut todo: Vec<(usize, usize)> = Vec::new();
        let mut link = |n: usize, pairs: &mut Vec<Pair>, todo: &mut Vec<(usize, usize)>| {
            let node = &bvh.nodes[n];
            if node.is_leaf() {
                place(node.first_index, node.prim_count)
            } else {
                pairs.push(Pair::default());
                todo.push((n, pairs.len() - 1));
                Link {
                    index: (pairs.len() - 1) as u32,
                    count: 0,
                }
            }
        };
        let root = link(0, &mut pairs, &mut todo);
        while let Some((n, slot)) = todo.pop() {
            let first = bvh.nodes[n].first_index as usize;
            let (l, r) = (bvh.nodes[first].aabb(), bvh.nodes[first + 1].aabb());
            let links = [
                link(first, &mut pairs, &mut todo),
                link(first + 1, &mut pairs, &mut todo),
            ];
            pairs[slot] = Pair {
                x: Vec4::new(l.min.x, r.min.x, l.max.x, r.max.x),
                y: Vec4::new(l.min.y, r.min.y, l.max.y, r.max.y),
                z: Vec4::new(l.min.z, r.min.z, l.max.z, r.max.z),
                link: links,
            };
        }
        let mut masked = vec![0u64; order.len().div_ceil(64)];
        for (j, &i) in order.iter().enumerate() {
            if i != u32::MAX && g.shading[i as usize].masked {
                masked[j / 64] |= 1 << (j % 64);
            }
        }
        PairTree {
            root: Some((*bvh.nodes[0].aabb(), root)),
            pairs,
            quads,
            order,
            masked,
            max_depth: bvh.max_depth,
            wide: has_avx2(),
        }
    }

    /// Whether [`PairTree::closest4`] runs in AVX2's eight lanes ([`Wide`]) for rays from one
    /// point.
    #[cfg(test)]
    pub(super) fn wide(&self) -> bool {
        self.wide
    }

    /// The same tree, [`PairTree::closest4`] in four lanes only.
    #[cfg(test)]
    pub(super) fn four_lanes(mut self) -> PairTree {
        self.wide = false;
        self
    }

    /// Bytes on the heap: `bvh`'s (the tree this one was laid out from) and this copy's.
    pub(super) fn bytes(&self, bvh: Option<&Bvh2>) -> usize {
        bvh.map_or(0, |b| {
            b.nodes.len() * size_of_val(&b.nodes[0]) + b.primitive_indices.len() * 4
        }) + self.pairs.len() * size_of::<Pair>()
            + self.quads.len() * size_of::<Quad>()
            + self.order.len() * 4
            + self.masked.len() * 8
    }

    /// [`super::hit_distance`] for the triangle in slot `id`, from the copy.
    #[inline]
    fn distance(&self, sr: &ShearedRay, g: &Geometry, id: usize, tmax: f32) -> f32 {
        let masked = self.masked[id / 64] & (1 << (id % 64)) != 0;
        let q = &self.quads[id / 4];
        let lane = id % 4;
        let vertex = |k: usize| Vec3A::new(q.v[k][0][lane], q.v[k][1][lane], q.v[k][2][lane]);
        let tri = Triangle {
            v0: vertex(0),
            v1: vertex(1),
            v2: vertex(2),
        };
        sr.cut_distance(&tri, masked, tmax, |b| {
            g.alpha_passes(self.order[id] as usize, b)
        })
    }

    /// The distances along `sr` (within `tmax`, infinity for a miss) of `leaf`'s triangles
    /// that may be hit, in slot order: `visit(slot, t, tmax)` may shorten the ray and
    /// returns false to stop.
    #[inline(always)]
    fn leaf_hits(
        &self,
        sr: &ShearedRay,
        g: &Geometry,
        leaf: Link,
        tmax: &mut f32,
        mut visit: impl FnMut(usize, f32, &mut f32) -> bool,
    ) -> bool {
        let first = leaf.index as usize;
        for b in 0..leaf.count.div_ceil(4) as usize {
            let base = first + 4 * b;
            let lanes = (leaf.count as usize - 4 * b).min(4);
            let masked = (self.masked[base / 64] >> (base % 64)) as u32 & 0xf;
            let found = block_test(sr, &self.quads[base / 4], *tmax, masked);
            // (A padding lane holds a triangle of three equal points, which no ray meets; left
            // out, it costs no one-triangle test.)
            for lane in set_bits((found.hit | found.rest) & ((1 << lanes) - 1)) {
                let t = if found.rest & (1 << lane) != 0 {
                    self.distance(sr, g, base + lane, *tmax)
                } else {
                    found.t[lane]
                };
                if !visit(base + lane, t, tmax) {
                    return false;
                }
            }
        }
        true
    }

    /// The nearest hit within `ray.tmax` (of `g`, the geometry the tree was built over):
    /// its distance and the triangle's index in `g`.
    pub(super) fn closest(&self, g: &Geometry, ray: &Ray, sr: &ShearedRay) -> Option<(f32, u32)> {
        // The hit so far: its distance and its triangle's index in `g`.
        let mut best: Option<(f32, u32)> = None;
        obvhs::fast_stack!(u32, (96, 192), self.max_depth, stack, {
            self.traverse::<_, true>(&mut stack, ray, |leaf, tmax| {
                self.leaf_hits(sr, g, leaf, tmax, |id, t, tmax| {
                    self.keep_nearer(&mut best, id, t, tmax);
                    true
                })
            })
        });
        best
    }

    /// Keeps the hit of slot `id` at `t` in `best` (the hit so far: distance, triangle index
    /// in the geometry) if it is nearer, or as near with a lower index, and shortens the ray.
    #[inline(always)]
    fn keep_nearer(&self, best: &mut Option<(f32, u32)>, id: usize, t: f32, tmax: &mut f32) {
        // (The geometry's index is read only for a hit.)
        let nearer = match *best {
            None => t < *tmax,
            Some((b, bt)) => t < b || (t == b && self.order[id] < bt),
        };
        if nearer {
            *tmax = t;
            *best = Some((t, self.order[id]));
        }
    }

    /// [`PairTree::closest`] for the rays of the lanes set in `active`, four neighbouring
    /// rays (a record's gather rays through neighbouring strata, one pixel's camera
    /// samples): the tree is walked once for all of them, each pair's two boxes tested
    /// against the four rays in SIMD lanes, a subtree entered with the lanes that enter its
    /// box, a leaf tested for each of them. Rays from one point (every lane's origin the
    /// same) take the slab arithmetic with that origin subtracted once per plane. A
    /// lane's hit is the one [`PairTree::closest`] finds: every triangle its ray can meet
    /// lies in a box it enters, and the nearest hit does not depend on the order.
    pub(super) fn closest4(
        &self,
        g: &Geometry,
        rays: &[Ray; 4],
        srs: &[ShearedRay; 4],
        active: u32,
    ) -> [Option<(f32, u32)>; 4] {
        let inv = |a: usize| Vec4::from_array(lanes4(|i| rays[i].inv_direction[a]));
        let inv = [inv(0), inv(1), inv(2)];
        let o = rays[0].origin;
        if rays.iter().all(|r| r.origin == o) {
            #[cfg(target_arch = "x86_64")]
            if self.wide {
                // SAFETY: `wide` is set only where the CPU has AVX2 (`PairTree::new`).
                return unsafe { self.closest4_wide(g, rays, srs, active, o, inv) };
            }
            self.closest4_from(g, rays, srs, active, Narrow { origins: o, inv })
        } else {
            let lanes = |a: usize| Vec4::from_array(lanes4(|i| rays[i].origin[a]));
            let origins = [lanes(0), lanes(1), lanes(2)];
            self.closest4_from(g, rays, srs, active, Narrow { origins, inv })
        }
    }

    /// [`PairTree::closest4`] for rays from one point, its boxes and leaves tested in the
    /// eight lanes of AVX2 ([`Wide`]).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn closest4_wide(
        &self,
        g: &Geometry,
        rays: &[Ray; 4],
        srs: &[ShearedRay; 4],
        active: u32,
        o: Vec3A,
        inv: [Vec4; 3],
    ) -> [Option<(f32, u32)>; 4] {
        self.closest4_from(g, rays, srs, active, Wide::new(o, inv))
    }

    /// [`PairTree::closest4`], each pair's boxes and each leaf's triangles tested by `walk`.
    #[inline(always)]
    fn closest4_from(
        &self,
        g: &Geometry,
        rays: &[Ray; 4],
        srs: &[ShearedRay; 4],
        active: u32,
        walk: impl FourRays,
    ) -> [Option<(f32, u32)>; 4] {
        let Some((root_box, root)) = &self.root else {
            return [None; 4];
        };
        let mut found = Found4 {
            tree: self,
            g,
            srs,
            tmax: lanes4(|i| rays[i].tmax),
            best: [None; 4],
        };
        let active = (0..4)
            .filter(|&i| active & (1 << i) != 0 && root_box.intersect_ray(&rays[i]) < found.tmax[i])
            .fold(0u32, |m, i| m | 1 << i);
        if active == 0 {
            return found.best;
        }
        if root.count > 0 {
            walk.leaf(&mut found, *root, active);
            return found.best;
        }
        obvhs::fast_stack!(u64, (96, 192), self.max_depth, stack, {
            // The pair to open and the lanes that entered its parent's box.
            let (mut current, mut lanes) = (root.index, active);
            loop {
                let p = &self.pairs[current as usize];
                self.prefetch_children(p);
                let e = walk.enter(p, Vec4::from_array(found.tmax), lanes);
                let (mut a, mut b) = ((e.lanes[0], p.link[0]), (e.lanes[1], p.link[1]));
                // The nearer first, for the first lane that enters both.
                let both = a.0 & b.0;
                if both != 0 && e.second_nearer & (1 << both.trailing_zeros()) != 0 {
                    std::mem::swap(&mut a, &mut b);
                }
                // Leaves are tested now; pairs are opened, the nearer first.
                let first = visit(walk, &mut found, a);
                let second = visit(walk, &mut found, b);
                let pack = |(index, lanes): (u32, u32)| u64::from(lanes) << 32 | u64::from(index);
                (current, lanes) = match (first, second) {
                    (Some(open), Some(later)) => {
                        stack.push(pack(later));
                        open
                    }
                    (Some(open), None) | (None, Some(open)) => open,
                    (None, None) => match stack.pop() {
                        Some(next) => (next as u32, (next >> 32) as u32),
                        None => break,
                    },
                };
            }
        });
        found.best
    }

    /// Whether any triangle of `g` meets the ray within `ray.tmax`.
    pub(super) fn occluded(&self, g: &Geometry, ray: &Ray, sr: &ShearedRay) -> bool {
        let mut hit = false;
        obvhs::fast_stack!(u32, (96, 192), self.max_depth, stack, {
            self.traverse::<_, false>(&mut stack, ray, |leaf, tmax| {
                hit = !self.leaf_hits(sr, g, leaf, tmax, |_, t, tmax| !(t < *tmax));
                !hit
            })
        });
        hit
    }

    /// Asks the CPU's cache for both children of `p` while its boxes are tested: a pair's
    /// line, or a leaf's first block. ([`PairTree::closest4`]'s walk, where the next pair's
    /// arrival was its largest wait: 5 % more rays a second in the rays bench. A single ray's
    /// walk, with less to do between pairs, was no faster for it.)
    #[inline(always)]
    fn prefetch_children(&self, p: &Pair) {
        for link in p.link {
            if link.count == 0 {
                crate::geom::prefetch_line(self.pairs.as_ptr().wrapping_add(link.index as usize));
            } else {
                let block = link.index as usize / 4;
                crate::geom::prefetch_line(self.quads.as_ptr().wrapping_add(block));
            }
        }
    }

    /// obvhs's `Bvh2::ray_traverse_dynamic` over the pairs: `leaf` tests a leaf's triangles,
    /// may shorten the ray and returns false to stop. `NEAR_FIRST`: a pair's nearer child
    /// first (a closest hit shortens the ray sooner); an occlusion test, whose answer is the
    /// same in any order, takes them as they lie.
    #[inline(always)]
    fn traverse<S: FastStack<u32>, const NEAR_FIRST: bool>(
        &self,
        stack: &mut S,
        ray: &Ray,
        mut leaf: impl FnMut(Link, &mut f32) -> bool,
    ) {
        let Some((root_box, root)) = &self.root else {
            return;
        };
        let mut tmax = ray.tmax;
        if !(root_box.intersect_ray(ray) < tmax) {
            return;
        }
        if root.count > 0 {
            leaf(*root, &mut tmax);
            return;
        }
        let (o, inv) = (ray.origin, ray.inv_direction);
        let (ox, oy, oz) = (Vec4::splat(o.x), Vec4::splat(o.y), Vec4::splat(o.z));
        let (ix, iy, iz) = (Vec4::splat(inv.x), Vec4::splat(inv.y), Vec4::splat(inv.z));
        let mut current = root.index;
        loop {
            let p = &self.pairs[current as usize];
            // Both slab tests at once (obvhs's `Aabb::intersect_ray`, lane by lane).
            let (tx, ty, tz) = ((p.x - ox) * ix, (p.y - oy) * iy, (p.z - oz) * iz);
            let (sx, sy, sz) = (tx.zwxy(), ty.zwxy(), tz.zwxy());
            let near = tx.min(sx).max(ty.min(sy)).max(tz.min(sz));
            let far = tx.max(sx).min(ty.max(sy)).min(tz.max(sz));
            let entry = |i: usize| {
                if far[i] >= near[i] && far[i] >= 0.0 {
                    near[i]
                } else {
                    f32::INFINITY
                }
            };
            let (mut a, mut b) = ((entry(0), p.link[0]), (entry(1), p.link[1]));
            if NEAR_FIRST && a.0 > b.0 {
                std::mem::swap(&mut a, &mut b);
            }
            // Whether to descend into a child: a leaf hit is tested now (`None`: stop).
            let mut open = |(entry, link): (f32, Link), tmax: &mut f32| {
                if !(entry < *tmax) {
                    Some(false)
                } else if link.count == 0 {
                    Some(true)
                } else {
                    leaf(link, tmax).then_some(false)
                }
            };
            let Some(go_a) = open(a, &mut tmax) else {
                return;
            };
            let Some(go_b) = open(b, &mut tmax) else {
                return;
            };
            current = match (go_a, go_b) {
                (true, true) => {
                    stack.push(b.1.index);
                    a.1.index
                }
                (true, false) => a.1.index,
                (false, true) => b.1.index,
                (false, false) => match stack.pop() {
                    Some(next) => next,
                    None => return,
                },
            };
        }
    }
}

/// A child of a pair that [`PairTree::closest4`]'s walk reached (the lanes whose rays
/// entered its box, and its link): a leaf's triangles are tested at once; a pair is
/// returned, to be opened (its index and the lanes).
#[inline(always)]
fn visit(
    walk: impl FourRays,
    found: &mut Found4,
    (lanes, link): (u32, Link),
) -> Option<(u32, u32)> {
    if lanes == 0 {
        None
    } else if link.count > 0 {
        walk.leaf(found, link, lanes);
        None
    } else {
        Some((link.index, lanes))
    }
}

/// What [`FourRays::enter`] finds of a pair's two children.
struct Entered {
    /// For each child, the lanes whose rays enter its box.
    lanes: [u32; 2],
    /// The lanes whose rays enter the second child's box nearer than the first's (their
    /// entry distances compared as f32s, `<`).
    second_nearer: u32,
}

/// How [`PairTree::closest4`] tests its four rays against a pair's boxes and a leaf's
/// triangles.
trait FourRays: Copy {
    /// The test of a pair's two boxes (obvhs's `Aabb::intersect_ray`, lane by lane): for
    /// each child, the lanes of `lanes` whose rays enter it before their `far_limit`, and
    /// which child each ray enters first.
    fn enter(self, p: &Pair, far_limit: Vec4, lanes: u32) -> Entered;

    /// The rays of `lanes` against `leaf`'s triangles ([`Found4`]).
    fn leaf(self, found: &mut Found4, leaf: Link, lanes: u32);
}

/// What [`PairTree::closest4`]'s leaf tests read and keep: the tree, its geometry and the
/// four rays; each lane's `tmax`, shortened to its nearest hit so far, and that hit in
/// `best` ([`PairTree::keep_nearer`]).
struct Found4<'a> {
    tree: &'a PairTree,
    g: &'a Geometry,
    srs: &'a [ShearedRay; 4],
    tmax: [f32; 4],
    best: [Option<(f32, u32)>; 4],
}

impl Found4<'_> {
    /// Lane `i`'s ray alone against `leaf`'s triangles, four at a time.
    #[inline(always)]
    fn one(&mut self, i: usize, leaf: Link) {
        let (tree, best) = (self.tree, &mut self.best[i]);
        tree.leaf_hits(
            &self.srs[i],
            self.g,
            leaf,
            &mut self.tmax[i],
            |id, t, tmax| {
                tree.keep_nearer(best, id, t, tmax);
                true
            },
        );
    }
}

/// The test in four SIMD lanes, a child at a time.
#[derive(Clone, Copy)]
struct Narrow<O> {
    origins: O,
    /// Each axis's reciprocal direction components, a ray a lane.
    inv: [Vec4; 3],
}

impl<O: Origins> FourRays for Narrow<O> {
    #[inline(always)]
    fn enter(self, p: &Pair, far_limit: Vec4, lanes: u32) -> Entered {
        let [ix, iy, iz] = self.inv;
        // One axis's slab for the four rays: the distances to its two planes.
        let slab = |lo: f32, hi: f32, axis: usize, inv: Vec4| {
            (
                self.origins.to_plane(lo, axis) * inv,
                self.origins.to_plane(hi, axis) * inv,
            )
        };
        let enter = |c: usize| {
            let (x0, x1) = slab(p.x[c], p.x[c + 2], 0, ix);
            let (y0, y1) = slab(p.y[c], p.y[c + 2], 1, iy);
            let (z0, z1) = slab(p.z[c], p.z[c + 2], 2, iz);
            let near = x0.min(x1).max(y0.min(y1)).max(z0.min(z1));
            let far = x0.max(x1).min(y0.max(y1)).min(z0.max(z1));
            let hit = far.cmpge(near) & far.cmpge(Vec4::ZERO) & near.cmplt(far_limit);
            (near, hit.bitmask() & lanes)
        };
        let ((near0, lanes0), (near1, lanes1)) = (enter(0), enter(1));
        Entered {
            lanes: [lanes0, lanes1],
            second_nearer: near1.cmplt(near0).bitmask(),
        }
    }

    #[inline(always)]
    fn leaf(self, found: &mut Found4, leaf: Link, lanes: u32) {
        for i in set_bits(lanes) {
            found.one(i, leaf);
        }
    }
}

/// Whether the CPU has AVX2, which [`Wide`] needs.
pub(super) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Where the four rays of [`PairTree::closest4`] leave from: one point for all of them (a
/// record's gather rays), or one for each lane (camera rays from the near plane).
trait Origins: Copy {
    /// Each lane's distance from its origin to `plane` along `axis` (`plane − o[axis]`).
    fn to_plane(self, plane: f32, axis: usize) -> Vec4;
}

impl Origins for Vec3A {
    #[inline(always)]
    fn to_plane(self, plane: f32, axis: usize) -> Vec4 {
        Vec4::splat(plane - self[axis])
    }
}

impl Origins for [Vec4; 3] {
    #[inline(always)]
    fn to_plane(self, plane: f32, axis: usize) -> Vec4 {
        Vec4::splat(plane) - self[axis]
    }
}

/// What [`block_test`] finds of a block's four triangles: `hit` holds the lanes hit at `t`,
/// `rest` those the one-triangle test must decide (module doc); as bits.
struct BlockHits<L = Vec4> {
    t: L,
    hit: u32,
    rest: u32,
}

/// The lanes a block test computes in: a block's four triangles against one ray (`Vec4`), or
/// against two rays from one point (`wide::W8`, lanes 0–3 the first ray's, 4–7 the
/// second's). Each operation is the same IEEE operation in every lane, so every lane rounds
/// as [`Vec4`]'s does.
trait BlockLanes:
    Lanes + std::ops::Sub<Output = Self> + std::ops::Div<Output = Self> + std::ops::Neg<Output = Self>
{
    type Mask: Copy + std::ops::BitOr<Output = Self::Mask> + std::ops::BitAnd<Output = Self::Mask>;
    /// Every lane's bit.
    const ALL: u32;
    fn splat(x: f32) -> Self;
    /// A coordinate of a block's four triangles, in each ray's lanes.
    fn block(v: Vec4) -> Self;
    fn lt(self, other: Self) -> Self::Mask;
    fn gt(self, other: Self) -> Self::Mask;
    fn le(self, other: Self) -> Self::Mask;
    fn eq(self, other: Self) -> Self::Mask;
    fn ne(self, other: Self) -> Self::Mask;
    fn finite(self) -> Self::Mask;
    fn bits(m: Self::Mask) -> u32;
}

/// [`BlockLanes`]' comparison `$name` by `Vec4`'s `$cmp`.
macro_rules! compare {
    ($name:ident, $cmp:ident) => {
        #[inline(always)]
        fn $name(self, other: Self) -> Self::Mask {
            self.$cmp(other)
        }
    };
}

impl BlockLanes for Vec4 {
    type Mask = glam::BVec4A;
    const ALL: u32 = 0xf;
    #[inline(always)]
    fn splat(x: f32) -> Self {
        Vec4::splat(x)
    }
    #[inline(always)]
    fn block(v: Vec4) -> Self {
        v
    }
    compare!(lt, cmplt);
    compare!(gt, cmpgt);
    compare!(le, cmple);
    compare!(eq, cmpeq);
    compare!(ne, cmpne);
    #[inline(always)]
    fn finite(self) -> Self::Mask {
        self.is_finite_mask()
    }
    #[inline(always)]
    fn bits(m: Self::Mask) -> u32 {
        m.bitmask()
    }
}

/// The lanes set in `bits`, lowest first.
#[inline(always)]
fn set_bits(mut bits: u32) -> impl Iterator<Item = usize> {
    std::iter::from_fn(move || {
        (bits != 0).then(|| {
            let lane = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            lane
        })
    })
}

/// Block `q`'s four triangles tested against `sr` within `tmax`, lane by lane with the
/// arithmetic of `ShearedRay::intersect_barycentric` (no fused operations, so each lane
/// rounds as the one-triangle test does); `masked` has bit `i` set where lane `i`'s triangle
/// is alpha-masked.
#[inline(always)]
fn block_test(sr: &ShearedRay, q: &Quad, tmax: f32, masked: u32) -> BlockHits {
    let s = sr.shear;
    let shear = [Vec4::splat(s.x), Vec4::splat(s.y), Vec4::splat(s.z)];
    block_test_in(sr.origin, sr.kz, shear, q, Vec4::splat(tmax), masked)
}

/// A vertex of a block's four triangles (`v`: x, y, z) relative to the rays' origin `o`,
/// permuted so that axis `kz` becomes z, and sheared by `[sx, sy, sz]`. (A function, not a
/// closure: a closure is not inlined for certain, and `wide`'s lanes need it inlined.)
#[inline(always)]
fn sheared<L: BlockLanes>(v: &[Vec4; 3], o: Vec3A, kz: usize, [sx, sy, sz]: [L; 3]) -> (L, L, L) {
    let p = [
        L::block(v[0]) - L::splat(o.x),
        L::block(v[1]) - L::splat(o.y),
        L::block(v[2]) - L::splat(o.z),
    ];
    let (x, y, z) = match kz {
        0 => (p[1], p[2], p[0]),
        1 => (p[2], p[0], p[1]),
        _ => (p[0], p[1], p[2]),
    };
    (x + sx * z, y + sy * z, z * sz)
}

/// [`block_test`] in lanes `L`, for rays from `o` whose largest direction component is
/// along axis `kz`, with each lane's shear and `tmax`; `masked` has a bit for each lane.
#[inline(always)]
fn block_test_in<L: BlockLanes>(
    o: Vec3A,
    kz: usize,
    [sx, sy, sz]: [L; 3],
    q: &Quad,
    tmax: L,
    masked: u32,
) -> BlockHits<L> {
    let s = [sx, sy, sz];
    let (p0, p1, p2) = (
        sheared(&q.v[0], o, kz, s),
        sheared(&q.v[1], o, kz, s),
        sheared(&q.v[2], o, kz, s),
    );
    let e0 = p1.0 * p2.1 - p1.1 * p2.0;
    let e1 = p2.0 * p0.1 - p2.1 * p0.0;
    let e2 = p0.0 * p1.1 - p0.1 * p1.0;
    let zero = L::splat(0.0);
    let negative = e0.lt(zero) | e1.lt(zero) | e2.lt(zero);
    let positive = e0.gt(zero) | e1.gt(zero) | e2.gt(zero);
    let on_edge = L::bits(e0.eq(zero) | e1.eq(zero) | e2.eq(zero));
    let inside = !L::bits(negative & positive) & L::ALL;
    let det = e0 + e1 + e2;
    let inv_det = L::splat(1.0) / det;
    let (b0, b1, b2) = (e0 * inv_det, e1 * inv_det, e2 * inv_det);
    let t = b0 * p0.2 + b1 * p1.2 + b2 * p2.2;
    let delta_t = t_error([p0, p1, p2], [b0, b1, b2], inv_det);
    // Lanes whose values are all finite: there `max` and the comparisons agree with the
    // scalar test's; the others go to it.
    let finite = L::bits(t.finite() & delta_t.finite());
    let live = L::bits(det.ne(zero)) & L::bits(t.le(tmax));
    let near_zero = !L::bits(t.gt(delta_t) | t.lt(-delta_t));
    let rest = on_edge | (inside & (masked | ((!finite | near_zero) & live)));
    let hit = inside & !rest & live & L::bits(t.gt(delta_t));
    BlockHits { t, hit, rest }
}
