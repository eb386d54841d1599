//! The photon map's kd-tree and its bounded k-nearest query (Jensen 2001, §6.3: a balanced
//! kd-tree, the k nearest photons within a maximum radius).
//!
//! Our own, because the estimate asks for up to k = 128 photons (the anchors' `k_scale`
//! × k) at every anchor and gather hit: kiddo's `nearest_n_within` allocates a binary heap
//! per query and sifts it at every closer candidate, which profiles showed as most of a
//! look-up's time. Here a query collects candidates into a per-thread buffer that is never
//! freed; when it holds 2k of them, a selection (`select_nth_unstable`, linear) keeps the k
//! nearest and tightens the search radius to the k-th — amortised O(1) per candidate, no
//! allocation once the buffer has grown.
//!
//! The tree is implicit: points sorted so that every range `lo..hi` longer than a leaf is
//! split at its middle `mid` by the median on the range's widest axis (`lo..mid` at or
//! below, `mid..hi` at or above). Building it needs no nodes and splits disjoint ranges in
//! parallel; the splits are then laid out as a binary heap (`Split`), whose top levels a
//! query finds in cache. Results are the k points nearest by (squared distance, index),
//! ties going to the lower index, so they do not depend on how the points were ordered in
//! the tree.
//!
//! [`PointTree::nearest_within`] names the points it finds by their position in the tree's
//! order ([`PointTree::item`] gives their index): neighbours lie close together in that
//! order, so data the caller keeps in it ([`PointTree::in_tree_order`]) is read from a few
//! cache lines instead of from all over memory — the photon estimate's first read of each
//! photon was most of its time.

use std::cell::RefCell;

use glam::Vec3;

/// Points a range holds at most before it is split.
const LEAF: usize = 12;

/// Ranges this long or longer are split on two threads.
const PARALLEL: usize = 1 << 14;

/// A balanced point kd-tree over fixed points (one frame's photons).
#[derive(Debug, Clone, Default)]
pub struct PointTree {
    /// The points, in tree order.
    points: Vec<[f32; 3]>,
    /// Each tree-order point's index in the slice the tree was built from.
    items: Vec<u32>,
    /// The splits, as an implicit binary heap: the root's at 0, the children of the split
    /// at `i` at `2i + 1` (its range's lower half) and `2i + 2` (the upper half).
    splits: Vec<Split>,
}

/// A range's split: its axis (0..3) and value (the median's coordinate; the points at its
/// `mid` and after are reordered by the splits below it).
///
/// Kept in heap order rather than at each range's `mid`: a query reads one split per level,
/// and the top levels then share a few cache lines instead of each taking one (or two, for
/// an axis and a value apart) of the point-sized arrays.
#[derive(Debug, Clone, Copy, Default)]
struct Split {
    value: f32,
    axis: u32,
}

/// One neighbour found: squared distance and position in the tree's order (for
/// [`PointTree::nearest_within`]) or index (for [`PointTree::nearest_one`]).
pub type Neighbour = (f32, u32);

thread_local! {
    /// Each thread's candidate buffer for [`PointTree::nearest_within`].
    static CANDIDATES: RefCell<Vec<Neighbour>> = const { RefCell::new(Vec::new()) };
}

impl PointTree {
    /// The tree of `points` (indices into it are what queries return).
    pub fn new(points: &[Vec3]) -> PointTree {
        let n = points.len();
        assert!(n <= u32::MAX as usize, "at most 2^32 points");
        let mut order: Vec<([f32; 3], u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (p.to_array(), i as u32))
            .collect();
        let mut axes = vec![0u8; n];
        let mut values = vec![0.0f32; n];
        split(&mut order, &mut axes, &mut values);
        let mut splits = Vec::new();
        in_heap_order(0, n, 0, &axes, &values, &mut splits);
        PointTree {
            points: order.iter().map(|e| e.0).collect(),
            items: order.iter().map(|e| e.1).collect(),
            splits,
        }
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Bytes the tree holds on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.points.capacity() * size_of::<[f32; 3]>()
            + self.items.capacity() * size_of::<u32>()
            + self.splits.capacity() * size_of::<Split>()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The index (in the slice the tree was built from) of the point at tree position `pos`.
    pub fn item(&self, pos: u32) -> u32 {
        self.items[pos as usize]
    }

    /// `data` (one element per point, by index) in the tree's order: element `pos` is
    /// `data[item(pos)]`.
    pub fn in_tree_order<T: Copy>(&self, data: &[T]) -> Vec<T> {
        self.items.iter().map(|&i| data[i as usize]).collect()
    }

    /// The point nearest to `x` at squared distance at most `r2_max` (ties: the lower
    /// index), as (squared distance, index).
    pub fn nearest_one(&self, x: Vec3, r2_max: f32) -> Option<Neighbour> {
        let mut best: Option<Neighbour> = None;
        self.search(x, r2_max, |d2, pos| {
            let i = self.items[pos as usize];
            if best.is_none_or(|b| (d2, i) < b) {
                best = Some((d2, i));
            }
            Some(d2)
        });
        best
    }

    /// The index of the nearest of `found` (as [`PointTree::nearest_within`] gives them),
    /// ranked as every query here ranks points: by squared distance, then index. It is
    /// [`PointTree::nearest_one`]'s answer wherever `found` holds the point nearest to the
    /// query, as the k nearest within any bound that holds one do.
    pub fn nearest_of(&self, found: &[Neighbour]) -> Option<u32> {
        // The least squared distance first; indices only break its ties.
        let mut nearest: Option<Neighbour> = None;
        for &(d2, pos) in found {
            if nearest.is_none_or(|(b2, b)| d2 < b2 || (d2 == b2 && self.item(pos) < self.item(b)))
            {
                nearest = Some((d2, pos));
            }
        }
        nearest.map(|(_, pos)| self.item(pos))
    }

    /// Whether a point lies at squared distance at most `r2_max` from `x` (the answer of
    /// [`PointTree::nearest_one`]`.is_some()`; the search stops at the first it finds).
    pub fn any_within(&self, x: Vec3, r2_max: f32) -> bool {
        let mut found = false;
        self.search(x, r2_max, |_, _| {
            found = true;
            Some(f32::NEG_INFINITY) // nothing is nearer: every other branch is skipped
        });
        found
    }

    /// Calls `f` with the up to `k` points nearest to `x` at squared distance at most
    /// `r2_max` (by squared distance, then index), in no particular order, each as (squared
    /// distance, position in the tree's order).
    pub fn nearest_within<R>(
        &self,
        x: Vec3,
        r2_max: f32,
        k: usize,
        f: impl FnOnce(&[Neighbour]) -> R,
    ) -> R {
        let k = k.max(1);
        CANDIDATES.with(|cell| match cell.try_borrow_mut() {
            Ok(mut buf) => {
                self.collect(x, r2_max, k, &mut buf);
                f(&buf)
            }
            // A query from inside `f` (none today) gets a buffer of its own.
            Err(_) => {
                let mut buf = Vec::new();
                self.collect(x, r2_max, k, &mut buf);
                f(&buf)
            }
        })
    }

    fn collect(&self, x: Vec3, r2_max: f32, k: usize, buf: &mut Vec<Neighbour>) {
        buf.clear();
        let cap = 2 * k;
        self.search(x, r2_max, |d2, i| {
            buf.push((d2, i));
            if buf.len() < cap {
                return None;
            }
            keep_nearest(buf, k, &self.items);
            Some(buf.iter().fold(0.0f32, |m, e| m.max(e.0)))
        });
        if buf.len() > k {
            keep_nearest(buf, k, &self.items);
        }
    }

    /// Visits the points within `r2_max` of `x`, the nearer side of each split first:
    /// `found(d2, position)` may return a tighter bound.
    ///
    /// A loop, with the ranges still to visit on a stack in the frame, rather than a
    /// recursion, and inlined into each query: the queries come by the million a frame (an
    /// estimate at every gather hit and anchor, the nearest photon at every attaching hit,
    /// Pseudocode 1).
    #[inline(always)]
    fn search<F: FnMut(f32, u32) -> Option<f32>>(&self, x: Vec3, r2_max: f32, mut found: F) {
        let q = x.to_array();
        let mut bound = r2_max;
        // Ranges to visit (lo, hi, split) with the squared distance to the plane that split
        // them off: at most one per level, and a tree of 2^32 points has fewer than 32.
        let mut pending = [(0u32, 0u32, 0u32, 0.0f32); 32];
        pending[0] = (0, self.points.len() as u32, 0, 0.0);
        let mut top = usize::from(!self.points.is_empty());
        while top > 0 {
            top -= 1;
            let (mut lo, mut hi, mut node, plane2) = pending[top];
            if plane2 > bound {
                continue;
            }
            while (hi - lo) as usize > LEAF {
                let mid = lo + (hi - lo) / 2;
                let split = self.splits[node as usize];
                let diff = q[split.axis as usize] - split.value;
                let (lower, upper) = ((lo, mid, 2 * node + 1), (mid, hi, 2 * node + 2));
                let (near, far) = if diff < 0.0 {
                    (lower, upper)
                } else {
                    (upper, lower)
                };
                if diff * diff <= bound {
                    pending[top] = (far.0, far.1, far.2, diff * diff);
                    top += 1;
                }
                (lo, hi, node) = near;
            }
            for (p, pos) in self.points[lo as usize..hi as usize].iter().zip(lo..) {
                let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
                let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                if d2 <= bound
                    && let Some(b) = found(d2, pos)
                {
                    bound = b;
                }
            }
        }
    }
}

/// An order of a batch's points, each index once: made only by [`query_order`] (or
/// [`query_order_into`]; the default orders no points), so that [`map_in_order`] can write
/// each answer to its own slot from any thread.
#[derive(Default)]
pub struct QueryOrder(Vec<u32>);

/// An order in which to query the tree at `points` (indices into it): along a Morton curve
/// over their bounding box (10 bits per axis; points not finite first), so that consecutive
/// queries visit the same nodes and points and find them in cache. The answers do not
/// depend on the order.
pub fn query_order(points: &[Vec3]) -> QueryOrder {
    let mut order = QueryOrder::default();
    query_order_into(points, &mut Vec::new(), &mut order);
    order
}

/// [`query_order`] into `order`, sorting in `keys`: both keep their buffers, for batches
/// ordered one after another.
pub fn query_order_into(points: &[Vec3], keys: &mut Vec<(u32, u32)>, order: &mut QueryOrder) {
    assert!(points.len() <= u32::MAX as usize, "at most 2^32 points");
    let (lo, hi) = points
        .iter()
        .filter(|p| p.is_finite())
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(*p), hi.max(*p))
        });
    let scale = 1023.0 / (hi - lo).max_element().max(f32::MIN_POSITIVE);
    // Spreads the 10 low bits of `v` to every third bit.
    fn spread(v: u32) -> u32 {
        let mut v = v & 0x3ff;
        v = (v | (v << 16)) & 0x0300_00ff;
        v = (v | (v << 8)) & 0x0300_f00f;
        v = (v | (v << 4)) & 0x030c_30c3;
        (v | (v << 2)) & 0x0924_9249
    }
    let key = |p: &Vec3| {
        let c = ((*p - lo) * scale).clamp(Vec3::ZERO, Vec3::splat(1023.0));
        spread(c.x as u32) | spread(c.y as u32) << 1 | spread(c.z as u32) << 2
    };
    use rayon::prelude::*;
    points
        .par_iter()
        .enumerate()
        .map(|(i, p)| (if p.is_finite() { key(p) } else { 0 }, i as u32))
        .collect_into_vec(keys);
    // Keys with their index are distinct: the order is the same however the sort splits.
    keys.par_sort_unstable();
    keys.par_iter()
        .map(|&(_, i)| i)
        .collect_into_vec(&mut order.0);
}

/// `f(i)` for every point `i` of `points`, computed in parallel in [`query_order`] and
/// returned in the points' order: for a batch of look-ups at scattered points (gather hits
/// in record order, anchors in the order they were made).
pub fn map_in_query_order<T: Send>(points: &[Vec3], f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    map_in_order(&query_order(points), f)
}

/// [`map_in_query_order`] with the points' [`query_order`] computed already (several
/// batches at the same points).
///
/// Each answer is written straight to its point's slot by the thread that computed it. A
/// batch holds up to millions of answers (a frame's gather hits), and putting them back in
/// order on one thread — a scatter into optional slots, then a pass that unwraps them —
/// took 0.13–0.15 s of a Sponza frame at the final preset. That needs `unsafe`: the slots
/// are written in parallel through one pointer, which is sound because a [`QueryOrder`] is
/// a permutation (each slot written once, by one thread).
pub fn map_in_order<T: Send>(order: &QueryOrder, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    use rayon::prelude::*;
    let order = &order.0;
    // SAFETY: `order` is a permutation of 0..len ([`query_order`]): each slot is written
    // once, by the one iteration that meets its index.
    unsafe {
        in_slots(order.len(), |slots| {
            order
                .par_iter()
                .for_each(|&i| slots.write(i, f(i as usize)));
        })
    }
}

/// [`map_in_order`] a group of `group` consecutive points of the order at a time (at least
/// one): `f` is given a group's indices and the next group's (empty after the last), and
/// calls `put` with its answers in the group's order. For look-ups that read memory at
/// addresses that earlier reads give (a photon, then its link, then an anchor): `f` can ask
/// the cache for the next group's inputs, and for each step's reads across its group
/// before it makes them, so that one point's wait overlaps the others' work. The answers
/// do not depend on `group`.
///
/// # Panics
/// If `f` puts other than one answer for each index of its group.
pub fn map_in_order_grouped<T: Send>(
    order: &QueryOrder,
    group: usize,
    f: impl Fn(&[u32], &[u32], &mut dyn FnMut(T)) + Sync,
) -> Vec<T> {
    let mut out = Vec::new();
    map_in_order_grouped_into(order, group, f, &mut out);
    out
}

/// [`map_in_order_grouped`] into `out` (its answers replaced), which keeps its buffer: for
/// batches mapped one after another.
///
/// # Panics
/// If `f` puts other than one answer for each index of its group.
pub fn map_in_order_grouped_into<T: Send>(
    order: &QueryOrder,
    group: usize,
    f: impl Fn(&[u32], &[u32], &mut dyn FnMut(T)) + Sync,
    out: &mut Vec<T>,
) {
    use rayon::prelude::*;
    let order = &order.0;
    let group = group.max(1);
    let end = |at: usize| at.min(order.len());
    // SAFETY: the groups split the permutation `order` ([`query_order`]), and each group
    // writes the slots of its own indices, one answer each (checked as they come and at
    // its end): each slot is written once.
    unsafe {
        in_slots_into(out, order.len(), |slots| {
            (0..order.len().div_ceil(group))
                .into_par_iter()
                .for_each(|g| {
                    let this = &order[g * group..end((g + 1) * group)];
                    let next = &order[end((g + 1) * group)..end((g + 2) * group)];
                    let mut at = this.iter();
                    f(this, next, &mut |answer| {
                        slots.write(*at.next().expect("no more answers than points"), answer);
                    });
                    assert!(at.next().is_none(), "an answer for each point");
                });
        })
    }
}

/// [`map_in_order`] that asks the cache for what `f` reads at a point ahead of it, by
/// `ahead(i)` for point `i` a group of [`PREFETCH_GROUP`] points before `f(i)`: for maps
/// over arrays indexed by the points' order (anchors and their reaches, visited in
/// [`query_order`]), which the Morton order reads at scattered places.
pub fn map_in_order_prefetched<T: Send>(
    order: &QueryOrder,
    ahead: impl Fn(usize) + Sync,
    f: impl Fn(usize) -> T + Sync,
) -> Vec<T> {
    map_in_order_grouped(order, PREFETCH_GROUP, |group, next, put| {
        for &i in next {
            ahead(i as usize);
        }
        for &i in group {
            put(f(i as usize));
        }
    })
}

/// The points [`map_in_order_prefetched`] asks the cache for at once.
pub const PREFETCH_GROUP: usize = 8;

/// `len` answers that `fill` writes into their slots from any thread, as a vector.
///
/// # Safety
/// As [`in_slots_into`]'s.
unsafe fn in_slots<T: Send>(len: usize, fill: impl FnOnce(&Slots<T>)) -> Vec<T> {
    let mut out = Vec::new();
    // SAFETY: the caller's contract.
    unsafe { in_slots_into(&mut out, len, fill) };
    out
}

/// [`in_slots`] into `out`, whose answers are replaced and whose buffer is kept.
///
/// # Safety
/// `fill` writes each of the slots `0..len` exactly once ([`Slots::write`]), or panics
/// (then `out` is left empty and the answers written leak).
unsafe fn in_slots_into<T: Send>(out: &mut Vec<T>, len: usize, fill: impl FnOnce(&Slots<T>)) {
    out.clear();
    out.reserve(len);
    fill(&Slots(out.spare_capacity_mut().as_mut_ptr(), len));
    // SAFETY: the buffer holds at least `len` slots (reserved), and every one of the first
    // `len` was written once (the caller's contract).
    unsafe { out.set_len(len) };
}

/// The slots [`in_slots`] fills from several threads at once: a vector's buffer and its
/// length.
struct Slots<T>(*mut std::mem::MaybeUninit<T>, usize);

// SAFETY: the threads write distinct slots only ([`in_slots`]'s contract), each a `T: Send`.
unsafe impl<T: Send> Send for Slots<T> {}
unsafe impl<T: Send> Sync for Slots<T> {}

impl<T> Slots<T> {
    /// Writes slot `i`.
    ///
    /// # Safety
    /// No other write of slot `i` happens, before or at the same time.
    ///
    /// # Panics
    /// If `i` lies past the slots.
    unsafe fn write(&self, i: u32, answer: T) {
        let i = i as usize;
        assert!(i < self.1, "slot {i} of {}", self.1);
        // SAFETY: slot `i` lies within the buffer (asserted), which outlives `self`, and
        // nothing else writes it (the caller's contract).
        unsafe { self.0.add(i).write(std::mem::MaybeUninit::new(answer)) };
    }
}

/// Keeps the `k` least of `buf` (squared distance, tree position) by squared distance, then
/// index (`items` maps positions to indices).
fn keep_nearest(buf: &mut Vec<Neighbour>, k: usize, items: &[u32]) {
    buf.select_nth_unstable_by(k - 1, |a, b| {
        a.0.total_cmp(&b.0)
            .then_with(|| items[a.1 as usize].cmp(&items[b.1 as usize]))
    });
    buf.truncate(k);
}

/// The splits `split` wrote at each range's `mid` (`axes`, `values`), for the range
/// `lo..hi` and those below it, into `heap` from index `node` (`PointTree::splits`).
fn in_heap_order(
    lo: usize,
    hi: usize,
    node: usize,
    axes: &[u8],
    values: &[f32],
    heap: &mut Vec<Split>,
) {
    if hi - lo <= LEAF {
        return;
    }
    let mid = lo + (hi - lo) / 2;
    if heap.len() <= node {
        heap.resize(node + 1, Split::default());
    }
    heap[node] = Split {
        value: values[mid],
        axis: u32::from(axes[mid]),
    };
    in_heap_order(lo, mid, 2 * node + 1, axes, values, heap);
    in_heap_order(mid, hi, 2 * node + 2, axes, values, heap);
}

/// Orders `pts` into the implicit tree, writing each split's axis and value at its `mid`.
fn split(pts: &mut [([f32; 3], u32)], axes: &mut [u8], splits: &mut [f32]) {
    let n = pts.len();
    if n <= LEAF {
        return;
    }
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for (p, _) in pts.iter() {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let axis = (0..3)
        .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])).then(b.cmp(&a)))
        .unwrap_or(0);
    let mid = n / 2;
    // Index breaks ties so that the order is a function of the points alone.
    pts.select_nth_unstable_by(mid, |a, b| {
        a.0[axis].total_cmp(&b.0[axis]).then(a.1.cmp(&b.1))
    });
    axes[mid] = axis as u8;
    splits[mid] = pts[mid].0[axis];
    let (pl, pr) = pts.split_at_mut(mid);
    let (al, ar) = axes.split_at_mut(mid);
    let (sl, sr) = splits.split_at_mut(mid);
    if n >= PARALLEL {
        rayon::join(|| split(pl, al, sl), || split(pr, ar, sr));
    } else {
        split(pl, al, sl);
        split(pr, ar, sr);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The k nearest by (squared distance, index) within r2_max, by brute force.
    fn brute(points: &[Vec3], x: Vec3, r2_max: f32, k: usize) -> Vec<Neighbour> {
        let mut all: Vec<Neighbour> = points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let d = *p - x;
                let d = [d.x, d.y, d.z];
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2], i as u32)
            })
            .filter(|e| e.0 <= r2_max)
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.truncate(k);
        all
    }

    /// Found neighbours with their indices, sorted.
    fn indexed(tree: &PointTree, found: &[Neighbour]) -> Vec<Neighbour> {
        let mut v: Vec<Neighbour> = found.iter().map(|&(d2, p)| (d2, tree.item(p))).collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        v
    }

    #[test]
    fn finds_the_same_neighbours_as_brute_force() {
        // A plane of points on a grid (many equal distances), a random cloud, and 50
        // coincident points: ties must go to the lower index.
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut points = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                points.push(Vec3::new(i as f32 * 0.1, 0.0, j as f32 * 0.1));
            }
        }
        for _ in 0..3000 {
            points.push(Vec3::new(next() * 4.0, next() * 2.0 - 1.0, next() * 4.0));
        }
        points.extend(std::iter::repeat_n(Vec3::new(1.0, 0.0, 1.0), 50));
        let tree = PointTree::new(&points);
        assert_eq!(tree.len(), points.len());
        for q in 0..300 {
            let x = if q % 3 == 0 {
                points[(q * 37) % points.len()]
            } else {
                Vec3::new(next() * 4.4 - 0.2, next() * 2.2 - 1.1, next() * 4.4 - 0.2)
            };
            for &k in &[1, 4, 16, 64, 128] {
                for &r2 in &[0.01f32, 0.25, f32::INFINITY] {
                    let want = brute(&points, x, r2, k);
                    let got = tree.nearest_within(x, r2, k, |f| indexed(&tree, f));
                    assert_eq!(got, want, "query {q} at {x}, k {k}, r2 {r2}");
                    let nearest = tree.nearest_within(x, r2, k, |f| tree.nearest_of(f));
                    assert_eq!(nearest, want.first().map(|e| e.1), "query {q} at {x}");
                }
            }
            let r2 = 0.04;
            assert_eq!(
                tree.nearest_one(x, r2),
                brute(&points, x, r2, 1).first().copied()
            );
            for r2 in [0.0001f32, 0.01, 0.25] {
                let want = !brute(&points, x, r2, 1).is_empty();
                assert_eq!(tree.any_within(x, r2), want, "query {q} at {x}, r2 {r2}");
            }
            // The nearest point's own squared distance counts; the next float below does not.
            let nearest = brute(&points, x, f32::INFINITY, 1)[0].0;
            let below = match nearest > 0.0 {
                true => f32::from_bits(nearest.to_bits() - 1),
                false => -1.0,
            };
            assert!(tree.any_within(x, nearest), "query {q} at {x}");
            assert!(!tree.any_within(x, below), "query {q} at {x}");
        }
    }

    #[test]
    fn batches_in_query_order_answer_in_the_points_order() {
        let points: Vec<Vec3> = (0..1000)
            .map(|i| {
                let t = i as f32 * 0.37;
                Vec3::new(t.sin() * 5.0, (t * 1.3).cos(), t % 2.0)
            })
            .chain([Vec3::NAN, Vec3::splat(f32::INFINITY)])
            .collect();
        let mut order = query_order(&points).0;
        // Neighbours along the curve are near in space: its steps are short on average.
        let step: f32 = order
            .windows(2)
            .take(999)
            .filter(|w| w.iter().all(|&i| (i as usize) < 1000))
            .map(|w| points[w[0] as usize].distance(points[w[1] as usize]))
            .sum::<f32>()
            / 999.0;
        let raw: f32 = (0..999)
            .map(|i| points[i].distance(points[i + 1]))
            .sum::<f32>()
            / 999.0;
        assert!(step < 0.5 * raw, "{step} {raw}");
        order.sort_unstable();
        assert!(
            order.iter().copied().eq(0..points.len() as u32),
            "a permutation"
        );
        let back = map_in_query_order(&points, |i| i);
        assert!(back.into_iter().eq(0..points.len()));
        assert!(map_in_query_order(&[], |i| i).is_empty());
        // Answers that own heap memory come back whole, in the points' order.
        let order = query_order(&points);
        let named = map_in_order(&order, |i| format!("point {i}"));
        assert!(
            named
                .iter()
                .enumerate()
                .all(|(i, s)| *s == format!("point {i}"))
        );
    }

    #[test]
    fn grouped_maps_answer_every_point_in_its_slot() {
        let points: Vec<Vec3> = (0..1000)
            .map(|i| {
                let f = i as f32;
                Vec3::new((f * 0.37).sin(), (f * 1.91).cos(), (f * 0.13).fract())
            })
            .collect();
        let order = query_order(&points);
        // Groups that divide the points and groups that leave a short last one; answers
        // that own heap memory.
        for group in [0, 1, 3, 8, 999, 1000, 4096] {
            let seen = std::sync::Mutex::new(Vec::<u32>::new());
            let named = map_in_order_grouped(&order, group, |this, next, put| {
                assert!(this.len() <= group.max(1) && next.len() <= group.max(1));
                seen.lock().unwrap().extend(next);
                for &i in this {
                    put(format!("point {i}"));
                }
            });
            assert!(
                named
                    .iter()
                    .enumerate()
                    .all(|(i, s)| *s == format!("point {i}")),
                "groups of {group}"
            );
            // Every point but the first group's is announced, once, a group ahead.
            let mut seen = seen.into_inner().unwrap();
            seen.sort_unstable();
            let first = group.clamp(1, points.len());
            assert_eq!(seen.len(), points.len() - first, "groups of {group}");
            seen.dedup();
            assert_eq!(seen.len(), points.len() - first, "groups of {group}");
        }
        let ahead = std::sync::atomic::AtomicUsize::new(0);
        let back = map_in_order_prefetched(
            &order,
            |_| {
                ahead.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            },
            |i| i,
        );
        assert!(back.into_iter().eq(0..points.len()));
        assert_eq!(ahead.into_inner(), points.len() - PREFETCH_GROUP);
        assert!(map_in_order_grouped(&query_order(&[]), 8, |_, _, put| put(0u8)).is_empty());
    }

    #[test]
    #[should_panic(expected = "an answer for each point")]
    fn a_group_that_answers_too_few_points_panics() {
        let points = vec![Vec3::ZERO; 20];
        map_in_order_grouped(&query_order(&points), 8, |this, _, put| {
            for &i in &this[1..] {
                put(i);
            }
        });
    }

    #[test]
    fn the_nearest_of_equally_near_points_is_the_lowest_index() {
        // Six points around each centre at the same distance, their indices in an order the
        // tree's coordinate order does not follow: the first one a walk meets is often not
        // the lowest.
        let offsets = [Vec3::X, -Vec3::Y, Vec3::Z, -Vec3::X, Vec3::Y, -Vec3::Z];
        let centres: Vec<Vec3> = (0..200)
            .map(|c| Vec3::new(c as f32 * 10.0, (c % 7) as f32 * 10.0, 0.0))
            .collect();
        let mut points = vec![Vec3::ZERO; centres.len() * offsets.len()];
        for (c, &centre) in centres.iter().enumerate() {
            for (j, &o) in offsets.iter().enumerate() {
                // Cluster c's point j at index j' (a rotation by c) of the cluster's six.
                points[c * offsets.len() + (j + c) % offsets.len()] = centre + o;
            }
        }
        let tree = PointTree::new(&points);
        for &centre in &centres {
            let want = brute(&points, centre, f32::INFINITY, 1);
            assert_eq!(
                tree.nearest_one(centre, f32::INFINITY).map(|n| vec![n]),
                Some(want),
                "at {centre}"
            );
        }
    }

    #[test]
    fn empty_and_tiny_trees_answer() {
        let tree = PointTree::new(&[]);
        assert!(tree.is_empty());
        assert_eq!(tree.nearest_one(Vec3::ZERO, f32::INFINITY), None);
        assert!(!tree.any_within(Vec3::ZERO, f32::INFINITY));
        assert!(tree.nearest_within(Vec3::ZERO, 1.0, 8, |f| f.is_empty()));
        let tree = PointTree::new(&[Vec3::X, Vec3::Y]);
        let got = tree.nearest_within(Vec3::ZERO, 4.0, 8, |f| indexed(&tree, f));
        assert_eq!(got, vec![(1.0, 0), (1.0, 1)]);
    }
}
