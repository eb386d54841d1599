//! The cache's lookup structure: records by the space their validity spheres cover.

use glam::Vec3;

/// Records by the space their validity spheres cover: a multi-level hashed grid (in the
/// spirit of Ward's octree). A record of reach ρ = `REACH`·a·R_i sits at the level whose
/// cells are at least 2ρ wide, in the ≤ 8 cells its sphere overlaps, so a lookup reads one
/// cell per level and meets only records that can be valid there.
#[derive(Debug, Clone, Default)]
pub(super) struct RecordGrid {
    /// Cell size of level 0 (set from the first record: scale-free).
    base: f32,
    /// Ward's a the grid was built for.
    pub(super) error: f32,
    cells: rustc_hash::FxHashMap<(i32, i32, i32, i32), Cell>,
    /// The levels in use, in order, with the reciprocals of their cell sizes.
    levels: Vec<(i32, f32)>,
}

/// Lookups may relax Ward's threshold up to this factor (the shading fallback uses 2).
pub(super) const REACH: f32 = 2.0;

/// A record in a cell: its index and the sphere it was put there with (its position and
/// the radius given to [`RecordGrid::insert`]), so that a lookup passes over the records
/// whose sphere cannot hold its point without reading them. A cell holds every record whose
/// sphere, relaxed `REACH`-fold and at a level whose cells are up to twice its diameter,
/// overlaps it, and on a surface a lookup at Ward's a finds few of them valid: at Sponza's
/// pixels (640×360, production) an interpolation met some 200 entries for 10 candidates
/// and 3 valid records.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Entry {
    centre: Vec3,
    radius: f32,
    index: u32,
}

impl Entry {
    /// An empty lane's.
    const EMPTY: Entry = Entry {
        centre: Vec3::ZERO,
        radius: f32::NAN,
        index: u32::MAX,
    };
}

/// Bytes a cell spends on one of its records ([`Block`]'s share).
pub(super) const ENTRY_BYTES: usize = size_of::<Block>() / LANES;

/// Records a [`Block`] holds.
const LANES: usize = 4;

/// Up to [`LANES`] entries of a cell, coordinate by coordinate, so that a lookup tests
/// them together ([`Block::may_hold`]: the compiler makes SIMD lanes of it). An empty lane
/// has a NaN radius, which no test passes.
#[derive(Debug, Clone, Copy)]
struct Block {
    x: [f32; LANES],
    y: [f32; LANES],
    z: [f32; LANES],
    radius: [f32; LANES],
    index: [u32; LANES],
}

impl Block {
    const EMPTY: Block = Block {
        x: [Entry::EMPTY.centre.x; LANES],
        y: [Entry::EMPTY.centre.y; LANES],
        z: [Entry::EMPTY.centre.z; LANES],
        radius: [Entry::EMPTY.radius; LANES],
        index: [Entry::EMPTY.index; LANES],
    };

    fn get(&self, lane: usize) -> Entry {
        Entry {
            centre: Vec3::new(self.x[lane], self.y[lane], self.z[lane]),
            radius: self.radius[lane],
            index: self.index[lane],
        }
    }

    fn set(&mut self, lane: usize, e: Entry) {
        self.x[lane] = e.centre.x;
        self.y[lane] = e.centre.y;
        self.z[lane] = e.centre.z;
        self.radius[lane] = e.radius;
        self.index[lane] = e.index;
    }

    /// Bit `l` set where `x` may lie within `factor` times lane `l`'s radius of its centre.
    /// A superset: the squared bound has a relative margin of 10⁻³, far above the
    /// rounding of the tests the callers make (a distance under `factor` times a radius no
    /// larger than the entry's, computed in f32).
    #[inline(always)]
    fn may_hold(&self, x: Vec3, factor: f32) -> u32 {
        let mut bits = 0;
        for l in 0..LANES {
            let r = factor * self.radius[l];
            let (dx, dy, dz) = (x.x - self.x[l], x.y - self.y[l], x.z - self.z[l]);
            let held = dx * dx + dy * dy + dz * dz <= r * r * (1.0 + 1e-3);
            bits |= (held as u32) << l;
        }
        bits
    }
}

/// A cell's entries in index order (in blocks; only the last block may have empty lanes,
/// at its end).
#[derive(Debug, Clone, Default)]
struct Cell {
    blocks: Vec<Block>,
    len: usize,
}

impl Cell {
    fn push(&mut self, e: Entry) {
        let lane = self.len % LANES;
        if lane == 0 {
            // Grown by half, not doubled: most cells hold a few dozen entries.
            if self.blocks.len() == self.blocks.capacity() {
                self.blocks
                    .reserve_exact(self.blocks.len().div_ceil(2).max(1));
            }
            self.blocks.push(Block::EMPTY);
        }
        if let Some(b) = self.blocks.last_mut() {
            b.set(lane, e);
        }
        self.len += 1;
    }

    fn last_index(&self) -> Option<u32> {
        let k = self.len.checked_sub(1)?;
        Some(self.blocks[k / LANES].index[k % LANES])
    }

    fn entries(&self) -> impl Iterator<Item = Entry> + '_ {
        (0..self.len).map(|k| self.blocks[k / LANES].get(k % LANES))
    }

    /// Adds `e` at its place in index order.
    fn insert_sorted(&mut self, e: Entry) {
        if self.last_index().is_none_or(|last| last < e.index) {
            return self.push(e);
        }
        let mut entries: Vec<Entry> = self.entries().collect();
        let at = entries.partition_point(|j| j.index < e.index);
        entries.insert(at, e);
        *self = Cell::default();
        for e in entries {
            self.push(e);
        }
    }

    /// Keeps the entries whose index `keep` keeps (and may change), in order, in place.
    fn retain(&mut self, mut keep: impl FnMut(&mut u32) -> bool) {
        // The entries before the first dropped one stay where they are.
        let mut kept = 0;
        while kept < self.len && keep(&mut self.blocks[kept / LANES].index[kept % LANES]) {
            kept += 1;
        }
        for k in kept + 1..self.len {
            let mut e = self.blocks[k / LANES].get(k % LANES);
            if keep(&mut e.index) {
                self.blocks[kept / LANES].set(kept % LANES, e);
                kept += 1;
            }
        }
        self.len = kept;
        self.blocks.truncate(kept.div_ceil(LANES));
        if let Some(last) = self.blocks.last_mut()
            && kept % LANES != 0
        {
            for lane in kept % LANES..LANES {
                last.set(lane, Entry::EMPTY);
            }
        }
    }

    /// Calls `f` with the index of each entry that [`Block::may_hold`] `x`, in order, until
    /// `f` returns true; returns whether it did.
    #[inline(always)]
    fn find(&self, x: Vec3, factor: f32, f: &mut impl FnMut(u32) -> bool) -> bool {
        for b in &self.blocks {
            let mut bits = b.may_hold(x, factor);
            while bits != 0 {
                let l = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                if f(b.index[l]) {
                    return true;
                }
            }
        }
        false
    }
}

/// ⌊v⌋ as an i32, saturating (as `v.floor() as i32`, without a call to the C library's
/// `floorf` where the target has no rounding instruction).
#[inline(always)]
fn floor_i32(v: f32) -> i32 {
    let t = v as i32;
    if t as f32 > v { t.saturating_sub(1) } else { t }
}

impl RecordGrid {
    /// A level's cell size, at least the smallest normal float, whose reciprocal is finite.
    fn size(&self, level: i32) -> f32 {
        (self.base * 2f32.powi(level)).max(f32::MIN_POSITIVE)
    }

    /// The reciprocal of a level's cell size: a cell is ⌊p/size⌋ taken as ⌊p·(1/size)⌋,
    /// the same for a sphere's span and for a lookup, so the cells still cover every sphere
    /// (both are monotonic in p).
    fn inverse_size(&self, level: i32) -> f32 {
        1.0 / self.size(level)
    }

    #[inline(always)]
    fn cell_at(level: i32, inverse_size: f32, p: Vec3) -> (i32, i32, i32, i32) {
        let c = p * inverse_size;
        (level, floor_i32(c.x), floor_i32(c.y), floor_i32(c.z))
    }

    /// The level and the range of cells (inclusive) of a sphere at `position` of validity
    /// radius `radius`.
    fn span(&mut self, position: Vec3, radius: f32) -> (i32, [i32; 3], [i32; 3]) {
        let a = if self.error > 0.0 { self.error } else { 1.0 };
        let reach = REACH * a * radius;
        if self.base == 0.0 {
            self.base = (2.0 * reach).max(f32::MIN_POSITIVE);
        }
        let level = (2.0 * reach / self.base).log2().ceil().max(-60.0) as i32;
        let inverse = self.inverse_size(level);
        let (lo, hi) = (
            Self::cell_at(level, inverse, position - reach),
            Self::cell_at(level, inverse, position + reach),
        );
        (level, [lo.1, lo.2, lo.3], [hi.1, hi.2, hi.3])
    }

    /// Calls `f` with every cell of a sphere's span; returns the span's level.
    fn for_cells(
        &mut self,
        position: Vec3,
        radius: f32,
        mut f: impl FnMut(&mut Self, (i32, i32, i32, i32)),
    ) -> i32 {
        let (level, lo, hi) = self.span(position, radius);
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    f(self, (level, x, y, z));
                }
            }
        }
        level
    }

    /// Adds record `i` at `position` with validity radius `radius` (its R_i) to its cells,
    /// `at` putting its entry in each cell, and its level to the ones lookups read.
    fn add(&mut self, i: u32, position: Vec3, radius: f32, at: impl Fn(&mut Cell, Entry)) {
        let e = Entry {
            centre: position,
            radius,
            index: i,
        };
        let level = self.for_cells(position, radius, |g, c| {
            at(g.cells.entry(c).or_default(), e)
        });
        if let Err(at) = self.levels.binary_search_by_key(&level, |l| l.0) {
            self.levels.insert(at, (level, self.inverse_size(level)));
        }
    }

    /// Adds record `i` at `position` with validity radius `radius` (its R_i), after the
    /// records already in its cells (a grid filled in index order keeps each cell in it).
    pub(super) fn insert(&mut self, i: u32, position: Vec3, radius: f32) {
        self.add(i, position, radius, |cell, e| cell.push(e));
    }

    /// Adds record `i` like [`RecordGrid::insert`], at its place in index order in each
    /// cell.
    pub(super) fn insert_sorted(&mut self, i: u32, position: Vec3, radius: f32) {
        self.add(i, position, radius, |cell, e| cell.insert_sorted(e));
    }

    /// Renumbers the records after some were removed: `map[i]` is record i's new index,
    /// or `u32::MAX` where it was removed (new indices in the order of the old ones, so
    /// cells stay in index order).
    pub(super) fn renumber(&mut self, map: &[u32]) {
        for cell in self.cells.values_mut() {
            cell.retain(|index| {
                *index = map[*index as usize];
                *index != u32::MAX
            });
        }
    }

    /// Removes record `i`, inserted at `position` with radius `radius`, from its cells.
    pub(super) fn remove(&mut self, i: u32, position: Vec3, radius: f32) {
        self.for_cells(position, radius, |g, c| {
            if let Some(cell) = g.cells.get_mut(&c) {
                cell.retain(|j| *j != i);
            }
        });
    }

    /// Calls `pred` with the records of [`RecordGrid::with_candidates`] ([`Block::may_hold`]),
    /// in the same order, read in place, until it returns true; returns whether it did. A
    /// lookup reads one cell per level in use.
    #[inline]
    pub(super) fn any_candidate(
        &self,
        x: Vec3,
        factor: f32,
        mut pred: impl FnMut(u32) -> bool,
    ) -> bool {
        self.levels.iter().any(|&(level, inverse)| {
            self.cells
                .get(&Self::cell_at(level, inverse, x))
                .is_some_and(|cell| cell.find(x, factor, &mut pred))
        })
    }

    /// Calls `f` with the records whose sphere, `factor` times the radius they were put in
    /// with, may contain `x` (a test of a distance under `factor` times a radius no larger
    /// than that one passes only those: the lookup grid's clamped radii, which shrink in
    /// place and move when they grow; the Ward radii of the clamping grids, put in again
    /// when they change), level by level, each level's in index order, in a per-thread
    /// buffer that is not freed between calls.
    pub(super) fn with_candidates<R>(
        &self,
        x: Vec3,
        factor: f32,
        f: impl FnOnce(&[u32]) -> R,
    ) -> R {
        thread_local! {
            static BUFFER: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        let fill = |out: &mut Vec<u32>| {
            out.clear();
            self.any_candidate(x, factor, |i| {
                out.push(i);
                false
            });
        };
        BUFFER.with(|cell| match cell.try_borrow_mut() {
            Ok(mut out) => {
                fill(&mut out);
                f(&out)
            }
            Err(_) => {
                let mut out = Vec::new();
                fill(&mut out);
                f(&out)
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_is_the_floor_at_every_magnitude() {
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            -1.0 + f32::EPSILON,
            -(1 << 24) as f32 - 2.0,
            2147483520.0,
            -2147483648.0,
            -2147483904.0,
            3e9,
            -3e9,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
        ];
        let mut s = 0x2545_f491_u32;
        for _ in 0..100_000 {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            let v = f32::from_bits(s);
            values.extend([v, v.fract(), v * 1e-30]);
        }
        for v in values {
            assert_eq!(floor_i32(v), v.floor() as i32, "{v:e}");
        }
    }

    /// Spheres far below the first record's scale, whose levels' cells would be
    /// subnormal, still take a few cells each and are found (a cell size whose reciprocal
    /// overflowed would span every i32 cell).
    #[test]
    fn tiny_spheres_take_few_cells() {
        let mut grid = RecordGrid {
            error: 1.0,
            ..RecordGrid::default()
        };
        grid.insert(0, Vec3::ZERO, 0.0);
        for (i, r) in [1e-41, 1e-44, 1e-30].into_iter().enumerate() {
            let at = Vec3::new(r, 0.0, -r);
            let (_, lo, hi) = grid.span(at, r);
            assert!(
                (0..3).all(|k| i64::from(hi[k]) - i64::from(lo[k]) <= 2),
                "radius {r:e}: cells {lo:?} to {hi:?}"
            );
            grid.insert(i as u32 + 1, at, r);
        }
        assert!(grid.cells.len() <= 4 * 8, "{} cells", grid.cells.len());
        let mut found = Vec::new();
        grid.any_candidate(Vec3::ZERO, 1.0, |i| {
            found.push(i);
            false
        });
        found.sort_unstable();
        assert_eq!(found, [0, 1, 2, 3]);
    }

    /// A cell's blocks hold what a list of its entries would, in the same order, through
    /// pushes, sorted inserts, removals and renumbering, with every empty lane failing the
    /// test; its lookups are the list's entries that hold the point.
    #[test]
    fn cells_keep_their_entries_in_order() {
        let entry = |i: u32| Entry {
            centre: Vec3::new(i as f32 * 0.1, (i % 7) as f32, -(i as f32) * 0.3),
            radius: 0.5 + (i % 5) as f32,
            index: i,
        };
        let mut cell = Cell::default();
        let mut list: Vec<Entry> = Vec::new();
        let check = |cell: &Cell, list: &[Entry]| {
            assert_eq!(cell.entries().collect::<Vec<_>>(), list);
            assert_eq!(cell.blocks.len(), list.len().div_ceil(LANES));
            for k in list.len()..cell.blocks.len() * LANES {
                let e = cell.blocks[k / LANES].get(k % LANES);
                assert!(
                    e.index == u32::MAX && e.radius.is_nan(),
                    "lane {k} not empty"
                );
            }
            for x in [Vec3::ZERO, Vec3::new(1.0, 3.0, -2.0), Vec3::splat(-4.0)] {
                for factor in [0.5, 1.0, 2.0] {
                    let mut found = Vec::new();
                    cell.find(x, factor, &mut |i| {
                        found.push(i);
                        false
                    });
                    let held: Vec<u32> = list
                        .iter()
                        .filter(|e| {
                            let r = factor * e.radius;
                            (x - e.centre).length_squared() <= r * r * (1.0 + 1e-3)
                        })
                        .map(|e| e.index)
                        .collect();
                    assert_eq!(found, held);
                }
            }
        };
        for i in (0..40).map(|i| 2 * i) {
            cell.push(entry(i));
            list.push(entry(i));
            check(&cell, &list);
        }
        for i in [31, 7, 79, 0, 81] {
            let at = list.partition_point(|e| e.index < i);
            list.insert(at, entry(i));
            cell.insert_sorted(entry(i));
            check(&cell, &list);
        }
        for drop in [0, 81, 79, 31, 40, 2] {
            cell.retain(|j| *j != drop);
            list.retain(|e| e.index != drop);
            check(&cell, &list);
        }
        cell.retain(|j| {
            *j /= 2;
            *j % 3 != 0
        });
        list.retain_mut(|e| {
            e.index /= 2;
            e.index % 3 != 0
        });
        check(&cell, &list);
        cell.retain(|_| false);
        check(&cell, &[]);
    }
}
