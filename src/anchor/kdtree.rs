//! The anchor kd-tree of §3. Our own: the paper inserts anchors one by one as gather rays
//! find no suitable neighbour and rebalances when the average number of nodes a search
//! visits grows past a threshold, which needs a point kd-tree with incremental insertion
//! and visit counts — kiddo's bucketed trees expose neither.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// A point kd-tree with incremental insertion (the anchor kd-tree of §3).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct KdTree {
    nodes: Vec<KdNode>,
    root: u32,
    /// Nodes visited by searches since the last reset.
    pub visited: u64,
    pub searches: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct KdNode {
    point: Vec3,
    item: u32,
    axis: u8,
    left: u32,
    right: u32,
}

const NIL: u32 = u32::MAX;

/// What a search found: (squared distance, item), nearest first; on the stack for the few
/// neighbours attachment asks for (§3.3.1: three).
pub type Neighbours = smallvec::SmallVec<[(f32, u32); 4]>;

impl KdTree {
    /// Checks a tree read from disk over `items` items: the root is node 0, every child comes
    /// after its parent (as [`KdTree::insert`] and [`KdTree::balanced`] build them, so that a
    /// search ends), axes are 0..3 and items in range.
    pub fn check(&self, items: usize) -> Result<(), String> {
        if self.nodes.is_empty() {
            return Ok(());
        }
        if self.root != 0 {
            return Err(format!("anchor kd-tree root {} is not node 0", self.root));
        }
        for (i, n) in self.nodes.iter().enumerate() {
            let child_ok = |c: u32| c == NIL || (c as usize > i && (c as usize) < self.nodes.len());
            if !child_ok(n.left) || !child_ok(n.right) || n.axis > 2 || n.item as usize >= items {
                return Err(format!("anchor kd-tree node {i} is malformed"));
            }
        }
        Ok(())
    }

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
    /// Counts the search and the nodes it visited (§3's rebalancing rule).
    pub fn nearest(
        &mut self,
        p: Vec3,
        radius: f32,
        k: usize,
        accept: impl Fn(u32) -> bool,
    ) -> Neighbours {
        let (best, visited) = self.search(p, radius, k, accept);
        if visited > 0 {
            self.count(1, visited);
        }
        best
    }

    /// Adds `searches` searches that visited `visited` nodes in all to the counts
    /// [`KdTree::mean_visited`] reads (searches made by [`KdTree::search`], e.g. in
    /// parallel).
    pub fn count(&mut self, searches: u64, visited: u64) {
        self.searches += searches;
        self.visited += visited;
    }

    /// [`KdTree::nearest`] without counting: the items and how many nodes the search
    /// visited (0 when the tree is empty or `k` is 0: no search was made). Read-only, so
    /// searches can run in parallel; the caller adds them up with [`KdTree::count`].
    pub fn search(
        &self,
        p: Vec3,
        radius: f32,
        k: usize,
        accept: impl Fn(u32) -> bool,
    ) -> (Neighbours, u64) {
        let mut best = Neighbours::new();
        let mut visited = 0;
        if self.nodes.is_empty() || k == 0 {
            return (best, visited);
        }
        let mut r2 = radius * radius;
        // Each pending subtree with the squared distance to its splitting plane, so that a
        // far side is skipped if the search radius shrank below it since it was pushed.
        let mut stack: smallvec::SmallVec<[(u32, f32); 64]> = smallvec::smallvec![(self.root, 0.0)];
        while let Some((i, plane2)) = stack.pop() {
            if i == NIL || plane2 > r2 {
                continue;
            }
            visited += 1;
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
                stack.push((far, delta * delta));
            }
            stack.push((near, 0.0));
        }
        (best, visited)
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

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

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
            assert_eq!(a.to_vec(), brute);
            assert_eq!(b.to_vec(), brute);
        }
        assert!(bal.mean_visited() < inc.mean_visited() * 2.0 + 50.0);
    }
}
