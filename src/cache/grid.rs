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
    cells: rustc_hash::FxHashMap<(i32, i32, i32, i32), Vec<u32>>,
    levels: std::collections::BTreeSet<i32>,
}

/// Lookups may relax Ward's threshold up to this factor (the shading fallback uses 2).
pub(super) const REACH: f32 = 2.0;

impl RecordGrid {
    fn cell(&self, level: i32, p: Vec3) -> (i32, i32, i32, i32) {
        let size = self.base * 2f32.powi(level);
        let c = (p / size).floor();
        (level, c.x as i32, c.y as i32, c.z as i32)
    }

    /// Adds record `i` at `position` with validity radius `radius` (its R_i).
    pub(super) fn insert(&mut self, i: u32, position: Vec3, radius: f32) {
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
        for x in lo.1..=hi.1 {
            for y in lo.2..=hi.2 {
                for z in lo.3..=hi.3 {
                    self.cells.entry((level, x, y, z)).or_default().push(i);
                }
            }
        }
        self.levels.insert(level);
    }

    /// Calls `f` with the records whose sphere may contain `x` (level by level, each
    /// level's in index order; a record sits at one level), in a per-thread buffer that is
    /// not freed between calls.
    pub(super) fn with_candidates<R>(&self, x: Vec3, f: impl FnOnce(&[u32]) -> R) -> R {
        thread_local! {
            static BUFFER: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        let fill = |out: &mut Vec<u32>| {
            out.clear();
            for &l in &self.levels {
                if let Some(c) = self.cells.get(&self.cell(l, x)) {
                    out.extend_from_slice(c);
                }
            }
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
