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
    cells: rustc_hash::FxHashMap<(i32, i32, i32, i32), Vec<Entry>>,
    /// The levels in use, in order, with their cell sizes.
    levels: Vec<(i32, f32)>,
}

/// Lookups may relax Ward's threshold up to this factor (the shading fallback uses 2).
pub(super) const REACH: f32 = 2.0;

/// A record in a cell: its index and the sphere it was put there with (its position and
/// the radius given to [`RecordGrid::insert`]), so that a lookup passes over the records
/// whose sphere cannot hold its point without reading them. A cell holds every record whose
/// sphere, relaxed `REACH`-fold and at a level whose cells are up to twice its diameter,
/// overlaps it, and on a surface a lookup at Ward's a finds few of them valid: at Sponza's
/// pixels (640×360, production) an interpolation met some 170 candidates for 3 valid
/// records, each of them read from its whole `Record` to be rejected.
#[derive(Debug, Clone, Copy)]
pub(super) struct Entry {
    centre: Vec3,
    radius: f32,
    index: u32,
}

impl Entry {
    /// Whether `x` may lie within `factor` times the entry's radius of its centre. A
    /// superset: the squared bound has a relative margin of 10⁻³, far above the rounding of
    /// the tests the callers make (a distance under `factor` times a radius no larger than
    /// the entry's, computed in f32).
    #[inline(always)]
    fn may_hold(&self, x: Vec3, factor: f32) -> bool {
        let r = factor * self.radius;
        (x - self.centre).length_squared() <= r * r * (1.0 + 1e-3)
    }
}

impl RecordGrid {
    fn size(&self, level: i32) -> f32 {
        self.base * 2f32.powi(level)
    }

    fn cell_of_size(level: i32, size: f32, p: Vec3) -> (i32, i32, i32, i32) {
        let c = (p / size).floor();
        (level, c.x as i32, c.y as i32, c.z as i32)
    }

    fn cell(&self, level: i32, p: Vec3) -> (i32, i32, i32, i32) {
        Self::cell_of_size(level, self.size(level), p)
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
        let (lo, hi) = (
            self.cell(level, position - reach),
            self.cell(level, position + reach),
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
    /// `at` putting its entry in each cell's list, and its level to the ones lookups read.
    fn add(&mut self, i: u32, position: Vec3, radius: f32, at: impl Fn(&mut Vec<Entry>, Entry)) {
        let e = Entry {
            centre: position,
            radius,
            index: i,
        };
        let level = self.for_cells(position, radius, |g, c| {
            at(g.cells.entry(c).or_default(), e)
        });
        if let Err(at) = self.levels.binary_search_by_key(&level, |l| l.0) {
            self.levels.insert(at, (level, self.size(level)));
        }
    }

    /// Adds record `i` at `position` with validity radius `radius` (its R_i), after the
    /// records already in its cells (a grid filled in index order keeps each cell in it).
    pub(super) fn insert(&mut self, i: u32, position: Vec3, radius: f32) {
        self.add(i, position, radius, |list, e| list.push(e));
    }

    /// Adds record `i` like [`RecordGrid::insert`], at its place in index order in each
    /// cell.
    pub(super) fn insert_sorted(&mut self, i: u32, position: Vec3, radius: f32) {
        self.add(i, position, radius, |list, e| {
            let at = list.partition_point(|j| j.index < i);
            list.insert(at, e);
        });
    }

    /// Renumbers the records after some were removed: `map[i]` is record i's new index,
    /// or `u32::MAX` where it was removed (new indices in the order of the old ones, so
    /// cells stay in index order).
    pub(super) fn renumber(&mut self, map: &[u32]) {
        for list in self.cells.values_mut() {
            list.retain_mut(|e| {
                e.index = map[e.index as usize];
                e.index != u32::MAX
            });
        }
    }

    /// Removes record `i`, inserted at `position` with radius `radius`, from its cells.
    pub(super) fn remove(&mut self, i: u32, position: Vec3, radius: f32) {
        self.for_cells(position, radius, |g, c| {
            if let Some(list) = g.cells.get_mut(&c) {
                list.retain(|j| j.index != i);
            }
        });
    }

    /// The lists of the cells that hold `x`, one per level in use, in level order: the
    /// records whose sphere may contain `x` (a record sits at one level).
    fn lists_at(&self, x: Vec3) -> impl Iterator<Item = &Vec<Entry>> {
        self.levels
            .iter()
            .filter_map(move |&(l, size)| self.cells.get(&Self::cell_of_size(l, size, x)))
    }

    /// The records whose sphere, `factor` times the radius they were put in with, may
    /// contain `x` ([`Entry::may_hold`]): level by level, each level's in index order (a
    /// record sits at one level).
    fn candidates(&self, x: Vec3, factor: f32) -> impl Iterator<Item = u32> {
        self.lists_at(x)
            .flatten()
            .filter(move |e| e.may_hold(x, factor))
            .map(|e| e.index)
    }

    /// Whether `pred` holds for one of the records of [`RecordGrid::with_candidates`], in
    /// the same order, read in place and only up to the first that passes.
    pub(super) fn any_candidate(
        &self,
        x: Vec3,
        factor: f32,
        pred: impl FnMut(u32) -> bool,
    ) -> bool {
        self.candidates(x, factor).any(pred)
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
            out.extend(self.candidates(x, factor));
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
