//! The traversal of a BVH2 that obvhs built, over a copy laid out for it: every pair of
//! siblings in one 64-byte line, their two boxes stored axis by axis so that one SIMD step
//! measures both, and every leaf's triangles side by side in leaf order, with each one's
//! alpha flag as a bit.
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

use glam::{Vec4, Vec4Swizzles};
use obvhs::aabb::Aabb;
use obvhs::bvh2::Bvh2;
use obvhs::faststack::FastStack;
use obvhs::ray::Ray;
use obvhs::triangle::Triangle;

use super::ShearedRay;
use crate::geom::Geometry;

/// A node's link: a leaf's triangles `index..index + count` in leaf order (`count` > 0),
/// or the pair that holds an interior node's two children (`count` 0).
#[derive(Debug, Clone, Copy, Default)]
struct Link {
    index: u32,
    count: u32,
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
    /// The geometry's triangles in leaf order, and the index of each in the geometry.
    triangles: Vec<Triangle>,
    order: Vec<u32>,
    /// Bit `i` set where triangle `i` (leaf order) is alpha-masked.
    masked: Vec<u64>,
    max_depth: usize,
}

impl PairTree {
    /// The layout of `bvh` (`None`: no geometry), built over `g`.
    pub(super) fn new(bvh: Option<&Bvh2>, g: &Geometry) -> PairTree {
        let Some(bvh) = bvh.filter(|b| !b.nodes.is_empty()) else {
            return PairTree {
                root: None,
                pairs: Vec::new(),
                triangles: Vec::new(),
                order: Vec::new(),
                masked: Vec::new(),
                max_depth: 0,
            };
        };
        let order = bvh.primitive_indices.clone();
        let mut masked = vec![0u64; order.len().div_ceil(64)];
        for (j, &i) in order.iter().enumerate() {
            if g.shading[i as usize].masked {
                masked[j / 64] |= 1 << (j % 64);
            }
        }
        let triangles = order.iter().map(|&i| g.triangles[i as usize]).collect();
        // Pairs in depth-first order: a node's children, then their subtrees.
        let mut pairs: Vec<Pair> = Vec::new();
        let mut todo: Vec<(usize, usize)> = Vec::new();
        let link = |n: usize, pairs: &mut Vec<Pair>, todo: &mut Vec<(usize, usize)>| {
            let node = &bvh.nodes[n];
            if node.is_leaf() {
                Link {
                    index: node.first_index,
                    count: node.prim_count,
                }
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
        PairTree {
            root: Some((*bvh.nodes[0].aabb(), root)),
            pairs,
            triangles,
            order,
            masked,
            max_depth: bvh.max_depth,
        }
    }

    /// Bytes on the heap: `bvh`'s (the tree this one was laid out from) and this copy's.
    pub(super) fn bytes(&self, bvh: Option<&Bvh2>) -> usize {
        bvh.map_or(0, |b| {
            b.nodes.len() * size_of_val(&b.nodes[0]) + b.primitive_indices.len() * 4
        }) + self.pairs.len() * size_of::<Pair>()
            + self.triangles.len() * (size_of::<Triangle>() + 4)
            + self.masked.len() * 8
    }

    /// [`super::hit_distance`] for the triangle at `id` in leaf order, from the copy.
    #[inline]
    fn distance(&self, sr: &ShearedRay, g: &Geometry, id: usize, tmax: f32) -> f32 {
        let masked = self.masked[id / 64] & (1 << (id % 64)) != 0;
        sr.cut_distance(&self.triangles[id], masked, tmax, |b| {
            g.alpha_passes(self.order[id] as usize, b)
        })
    }

    /// The nearest hit within `ray.tmax` (of `g`, the geometry the tree was built over):
    /// its distance and the triangle's index in `g`.
    pub(super) fn closest(&self, g: &Geometry, ray: &Ray, sr: &ShearedRay) -> Option<(f32, u32)> {
        // The hit so far: its distance and its triangle's index in `g`.
        let mut best: Option<(f32, u32)> = None;
        obvhs::fast_stack!(u32, (96, 192), self.max_depth, stack, {
            self.traverse(&mut stack, ray, |leaf, tmax| {
                for id in leaf.index..leaf.index + leaf.count {
                    let t = self.distance(sr, g, id as usize, *tmax);
                    // (The geometry's index is read only for a hit.)
                    let nearer = match best {
                        None => t < *tmax,
                        Some((b, bt)) => t < b || (t == b && self.order[id as usize] < bt),
                    };
                    if nearer {
                        *tmax = t;
                        best = Some((t, self.order[id as usize]));
                    }
                }
                true
            })
        });
        best
    }

    /// Whether any triangle of `g` meets the ray within `ray.tmax`.
    pub(super) fn occluded(&self, g: &Geometry, ray: &Ray, sr: &ShearedRay) -> bool {
        let mut hit = false;
        obvhs::fast_stack!(u32, (96, 192), self.max_depth, stack, {
            self.traverse(&mut stack, ray, |leaf, tmax| {
                hit = (leaf.index..leaf.index + leaf.count)
                    .any(|id| self.distance(sr, g, id as usize, *tmax) < *tmax);
                !hit
            })
        });
        hit
    }

    /// obvhs's `Bvh2::ray_traverse_dynamic` over the pairs: `leaf` tests a leaf's triangles,
    /// may shorten the ray and returns false to stop.
    #[inline(always)]
    fn traverse<S: FastStack<u32>>(
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
            if a.0 > b.0 {
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
