//! Neighbour clamping of record radii (Křivánek, Bouatouch, Pattanaik & Žára, "Making
//! Radiance and Irradiance Caching Practical", 2006), kept up to date as records are added,
//! changed and removed: the radius each lookup uses ([`Record::reach_radius`]) is Ward's
//! radius capped by its neighbours', always equal to a full pass over the records.

use glam::Vec3;
use rayon::prelude::*;

use super::grid::{REACH, RecordGrid};
use super::{IrradianceCache, Record};

/// Where a record lies and how far it reaches: what the grids hold it by.
pub(super) struct Placed {
    position: Vec3,
    normal: Vec3,
    radius: f32,
    reach_radius: f32,
    /// Clamps its neighbours ([`Record::is_open`]).
    open: bool,
}

impl Placed {
    pub(super) fn of(r: &Record) -> Placed {
        Placed {
            position: r.position,
            normal: r.normal,
            radius: r.radius,
            reach_radius: r.reach_radius,
            open: r.is_open(),
        }
    }
}

/// The cap record j puts on record i's radius under neighbour clamping (R_j + s·d), if j
/// is within i's reach on a surface facing the same way; each is (position, normal, Ward
/// radius).
#[inline]
fn clamp_cap(i: (Vec3, Vec3, f32), j: (Vec3, Vec3, f32), slope: f32, a: f32) -> Option<f32> {
    let ((xi, ni, ri), (xj, nj, rj)) = (i, j);
    if ni.dot(nj) <= 0.0 {
        return None;
    }
    let d = (xi - xj).length();
    (d < REACH * a * ri).then_some(rj + slope * d)
}

impl IrradianceCache {
    /// Neighbour clamping (Křivánek, Bouatouch, Pattanaik & Žára, "Making Radiance and
    /// Irradiance Caching Practical", 2006): R_i ≤ R_j + s·|x_i − x_j| for every record j
    /// within the reach of record i on a surface facing the same way, s the slope
    /// [`super::CacheParams::neighbour_clamp`] (0: off). Křivánek et al. use 1; 2, the
    /// default, keeps most of the effect at contacts with 40 % fewer records (the example's
    /// frame 36 at 320 × 240, brute force: the band above the sliding cube's base reads
    /// 2.5 % above a path-traced reference with 1, 4 % with 2, 7 % without clamping; 5 340,
    /// 3 210 and 2 085 records; 4.95, 3.21 and 2.32 s). Ward's
    /// harmonic-mean R_i sees only what the record's own rays hit: a record a little above
    /// a contact (a box's side above the floor) has a large R_i and is valid down into the
    /// contact, where irradiance falls off faster than its gradient says, while the records
    /// next to the contact have small ones. Clamped, the large record stops short of the
    /// small ones' region, and placement fills it with records of its own. Computed from
    /// Ward's radii in one pass, as the minimum of the caps, so the result depends on the
    /// records alone, not on their order, the grids' history or the thread count. Records
    /// from `first` on are new (the others were clamped among themselves before): only the
    /// pairs with a new record are looked at. Enclosed records (never used) clamp nothing.
    pub(super) fn clamp_to_neighbours(&mut self, first: usize) {
        let slope = self.neighbour_clamp;
        if slope <= 0.0 {
            for r in &mut self.records[first..] {
                r.reach_radius = r.radius;
            }
            return;
        }
        let points = self.clamp_points();
        // The records before `first` keep the radii the records before them gave them
        // (more records can only lower a radius); the pass adds the caps of the pairs
        // with a new record: new j (the grid of Ward's radii finds the records whose
        // sphere holds x_j), and old j in a new record's sphere (a grid of the new records
        // alone finds them, without a search of every old record's neighbours).
        let mut fresh = RecordGrid::default();
        if first > 0 {
            fresh.error = self.ward.error;
            for (i, p) in points.iter().enumerate().skip(first) {
                fresh.insert(i as u32, p.0, p.2);
            }
        }
        let start: Vec<f32> = self
            .records
            .iter()
            .enumerate()
            .map(|(i, r)| if i < first { r.reach_radius } else { r.radius })
            .collect();
        let reach = self.lowest_caps(
            &points,
            start,
            |j| if j >= first { &self.ward } else { &fresh },
            |i| Some(i as usize),
        );
        for (r, reach) in self.records.iter_mut().zip(reach) {
            r.reach_radius = reach;
        }
    }

    /// [`IrradianceCache::clamp_to_neighbours`] again after the Ward radii (or enclosure
    /// flags) of the records `changed` (in index order) changed from `old`'s, positions and
    /// normals unchanged, with the same radii as a full pass: the changed records are
    /// clamped again from all their neighbours; a record a changed one may clamp takes its
    /// new cap where that is lower ([`IrradianceCache::cap_changed`]), and is clamped again
    /// from all its neighbours only where the old cap was the one it had and the new one is
    /// higher or gone. Both grids are brought up to date in place.
    fn reclamp(&mut self, old: &[Placed], changed: &[usize]) {
        for &j in changed {
            self.ward.remove(j as u32, old[j].position, old[j].radius);
            let r = &self.records[j];
            self.ward.insert_sorted(j as u32, r.position, r.radius);
        }
        let mut affected: Vec<u32> = changed.iter().map(|&j| j as u32).collect();
        if self.neighbour_clamp > 0.0 {
            for &j in changed {
                let now = Placed::of(&self.records[j]);
                for i in self.within_reach_of(now.position) {
                    if i as usize != j
                        && changed.binary_search(&(i as usize)).is_err()
                        && self.cap_changed(i as usize, &old[j], Some(&now))
                    {
                        affected.push(i);
                    }
                }
            }
        }
        self.clamp_again(affected);
    }

    /// Record i's clamped radius after the cap a neighbour puts on it changed from what
    /// the neighbour `was` to what it is `now` (None: removed): lowered to the new cap
    /// where that is lower; true where the old cap was the radius i had and the new one is
    /// higher or gone, so that only a pass over all of i's neighbours can tell its radius.
    fn cap_changed(&mut self, i: usize, was: &Placed, now: Option<&Placed>) -> bool {
        let (slope, a) = (self.neighbour_clamp, self.clamp_error());
        let r = &self.records[i];
        let pi = (r.position, r.normal, r.radius);
        let cap = |j: &Placed| {
            if !j.open {
                None
            } else {
                clamp_cap(pi, (j.position, j.normal, j.radius), slope, a)
            }
        };
        let (before, after) = (cap(was), now.and_then(cap));
        let reach = &mut self.records[i].reach_radius;
        if let Some(c) = before
            && c == *reach
            && after.is_none_or(|n| n > c)
        {
            return true;
        }
        if let Some(n) = after
            && n < *reach
        {
            *reach = n;
        }
        false
    }

    /// Per slot, the lowest of `start` and the caps (`clamp_cap`) every open record j
    /// ([`Record::is_open`]) puts on the records `grid(j)` finds at x_j and `slot` gives a slot
    /// (`points`: each record's position, normal and Ward radius). The minimum does not
    /// depend on the order, so neither on the thread count.
    fn lowest_caps<'g>(
        &'g self,
        points: &[(Vec3, Vec3, f32)],
        start: Vec<f32>,
        grid: impl Fn(usize) -> &'g RecordGrid + Sync,
        slot: impl Fn(u32) -> Option<usize> + Sync,
    ) -> Vec<f32> {
        let (slope, a) = (self.neighbour_clamp, self.clamp_error());
        (0..points.len())
            .into_par_iter()
            .with_min_len(1024)
            .filter(|&j| self.records[j].is_open())
            .fold(
                || start.clone(),
                |mut reach, j| {
                    grid(j).with_candidates(points[j].0, REACH * a, |idx| {
                        for &i in idx {
                            if i as usize != j
                                && let Some(cap) =
                                    clamp_cap(points[i as usize], points[j], slope, a)
                                && let Some(k) = slot(i)
                            {
                                reach[k] = reach[k].min(cap);
                            }
                        }
                    });
                    reach
                },
            )
            .reduce(
                || start.clone(),
                |mut a, b| {
                    for (x, y) in a.iter_mut().zip(b) {
                        *x = x.min(y);
                    }
                    a
                },
            )
    }

    /// What clamping reads of each record, side by side in memory: position, normal and
    /// Ward's radius.
    fn clamp_points(&self) -> Vec<(Vec3, Vec3, f32)> {
        self.records
            .iter()
            .map(|r| (r.position, r.normal, r.radius))
            .collect()
    }

    /// Ward's a as the grids use it.
    fn clamp_error(&self) -> f32 {
        if self.ward.error > 0.0 {
            self.ward.error
        } else {
            1.0
        }
    }

    /// The records whose sphere (Ward's radius, relaxed `REACH`-fold) holds `x`: those a
    /// record at `x` may clamp.
    fn within_reach_of(&self, x: Vec3) -> Vec<u32> {
        let a = self.clamp_error();
        self.ward.with_candidates(x, REACH * a, |idx| {
            idx.iter()
                .copied()
                .filter(|&i| {
                    let r = &self.records[i as usize];
                    (r.position - x).length() < REACH * a * r.radius
                })
                .collect()
        })
    }

    /// Computes the clamped radius of the records `affected` again from all their
    /// neighbours, as [`IrradianceCache::clamp_to_neighbours`] does, and moves those whose
    /// reach grew past their cells of the lookup grid.
    fn clamp_again(&mut self, mut affected: Vec<u32>) {
        let slope = self.neighbour_clamp;
        affected.sort_unstable();
        affected.dedup();
        let points = self.clamp_points();
        let start: Vec<f32> = affected.iter().map(|&i| points[i as usize].2).collect();
        let reach = if slope <= 0.0 {
            start
        } else {
            // The affected records by their spheres, to meet them from every record j.
            let mut spheres = RecordGrid::default();
            spheres.error = self.ward.error;
            for &i in &affected {
                spheres.insert(i, points[i as usize].0, points[i as usize].2);
            }
            self.lowest_caps(
                &points,
                start,
                |_| &spheres,
                |i| affected.binary_search(&i).ok(),
            )
        };
        for (&i, reach) in affected.iter().zip(reach) {
            let i = i as usize;
            self.records[i].reach_radius = reach;
            // A record whose reach grew past the cells it sits in moves to larger ones.
            if reach > self.grid_radius[i] {
                let p = self.records[i].position;
                self.grid.remove(i as u32, p, self.grid_radius[i]);
                self.grid.insert_sorted(i as u32, p, reach);
                self.grid_radius[i] = reach;
            }
        }
    }

    /// Removes the records `keep` does not mark. Where they are few (an animation's frame
    /// retires a few), both grids are renumbered in place and the records the removed ones
    /// clamped are clamped again ([`IrradianceCache::clamp_again`]); else both are rebuilt.
    pub(super) fn remove_records(&mut self, keep: &[bool]) {
        let removed = keep.iter().filter(|&&k| !k).count();
        if removed == 0 {
            return;
        }
        if removed * 4 > keep.len() || self.grid_radius.len() != keep.len() {
            let mut k = keep.iter();
            self.records.retain(|_| *k.next().unwrap_or(&false));
            self.rebuild_tree();
            return;
        }
        // The records a removed one clamped to its cap are clamped again from all their
        // neighbours ([`IrradianceCache::cap_changed`]), by their old indices.
        let mut affected = Vec::new();
        if self.neighbour_clamp > 0.0 {
            for j in (0..keep.len()).filter(|&j| !keep[j]) {
                let was = Placed::of(&self.records[j]);
                for i in self.within_reach_of(was.position) {
                    if keep[i as usize] && self.cap_changed(i as usize, &was, None) {
                        affected.push(i);
                    }
                }
            }
        }
        let mut map = vec![u32::MAX; keep.len()];
        for (next, (m, _)) in map.iter_mut().zip(keep).filter(|(_, k)| **k).enumerate() {
            *m = next as u32;
        }
        self.ward.renumber(&map);
        self.grid.renumber(&map);
        let mut k = keep.iter();
        self.records.retain(|_| *k.next().unwrap_or(&false));
        let mut k = keep.iter();
        self.grid_radius.retain(|_| *k.next().unwrap_or(&false));
        let affected = affected
            .into_iter()
            .map(|i| map[i as usize])
            .filter(|&i| i != u32::MAX)
            .collect();
        self.clamp_again(affected);
    }

    /// The grids brought up to date after the records changed from `old`.
    pub(super) fn placed_again(&mut self, old: &[Placed]) {
        let same_places = old.len() == self.records.len()
            && self.grid_radius.len() == old.len()
            && old
                .iter()
                .zip(&self.records)
                .all(|(a, b)| a.position == b.position && a.normal == b.normal);
        if !same_places {
            self.rebuild_tree();
            return;
        }
        for (r, o) in self.records.iter_mut().zip(old) {
            r.reach_radius = o.reach_radius;
        }
        let changed: Vec<usize> = (0..old.len())
            .filter(|&i| {
                let (a, b) = (&old[i], &self.records[i]);
                a.radius.to_bits() != b.radius.to_bits() || a.open != b.is_open()
            })
            .collect();
        if changed.len() * 4 > old.len() {
            self.rebuild_tree();
        } else if !changed.is_empty() {
            self.reclamp(old, &changed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::CacheParams;

    #[test]
    fn radii_are_clamped_by_their_neighbours_whatever_their_order() {
        // On a floor: a large record and, 1 away, a small one next to a contact; a record
        // facing down at the small one's place, and an enclosed one there.
        let small = Record::bare(Vec3::new(1.0, 0.0, 0.0), Vec3::Y, 0.1);
        let mut enclosed = Record::bare(Vec3::new(0.5, 0.0, 0.0), Vec3::Y, 0.01);
        enclosed.enclosed = true;
        let records = vec![
            Record::bare(Vec3::ZERO, Vec3::Y, 10.0),
            small,
            Record::bare(Vec3::new(1.0, 0.0, 0.0), -Vec3::Y, 10.0),
            enclosed,
            Record::bare(Vec3::new(100.0, 0.0, 0.0), Vec3::Y, 10.0),
        ];
        let mut cache = IrradianceCache::default();
        cache.set_params(&CacheParams {
            error: 0.25,
            neighbour_clamp: 2.0,
            ..CacheParams::default()
        });
        cache.replace_records(records.clone());
        let reach: Vec<f32> = cache.records.iter().map(|r| r.reach_radius).collect();
        // R_0 ≤ R_1 + 2·1; the small one keeps its own; the one facing away and the far
        // one are not clamped; the enclosed record clamps nothing.
        assert!((reach[0] - (0.1 + 2.0)).abs() < 1e-5, "{reach:?}");
        assert_eq!(reach[1], 0.1);
        assert_eq!(reach[2], 10.0);
        assert_eq!(reach[4], 10.0);
        // Ward's radii are kept, and lookups use the clamped ones: 1.5 from the large
        // record is beyond a·R_0 now.
        assert_eq!(cache.records[0].radius, 10.0);
        let mut parts = Vec::new();
        let at = Vec3::new(-1.5, 0.0, 0.0);
        assert!(cache.interpolate(at, Vec3::Y, 0.25, &mut parts).is_none());
        // The same radii in any order, and added in two batches.
        let mut reversed = records.clone();
        reversed.reverse();
        cache.replace_records(reversed.clone());
        let mut again: Vec<f32> = cache.records.iter().map(|r| r.reach_radius).collect();
        again.reverse();
        assert_eq!(again, reach);
        // Both ways round: a new record clamped by an old one, and an old by a new one.
        for order in [records.clone(), reversed] {
            let full: Vec<f32> = {
                cache.replace_records(order.clone());
                cache.records.iter().map(|r| r.reach_radius).collect()
            };
            for split in 0..order.len() {
                cache.replace_records(order[..split].to_vec());
                cache.append(order[split..].to_vec());
                let batches: Vec<f32> = cache.records.iter().map(|r| r.reach_radius).collect();
                assert_eq!(batches, full, "added after record {split}");
            }
        }
    }

    /// The records valid at (x, n) to `a`, by a pass over all of them.
    fn valid_by_pass(cache: &IrradianceCache, x: Vec3, n: Vec3, a: f32) -> Vec<u32> {
        (0..cache.records.len() as u32)
            .filter(|&i| IrradianceCache::weight(&cache.records[i as usize], x, n) > 1.0 / a)
            .collect()
    }

    /// 10 bits of `h` from bit `shift` on, as a fraction in [0, 1].
    fn unit(h: u32, shift: u32) -> f32 {
        (h >> shift & 1023) as f32 / 1023.0
    }

    /// A point on a floor or on one of two walls that meet it (by `i % 3`), within `size` of
    /// their common corner by the hash of `i` and `salt`, and the surface's normal.
    fn on_floor_or_wall(i: u32, salt: u32, size: f32) -> (Vec3, Vec3) {
        let h = crate::sampling::hash(&[i, salt]);
        let (u, v) = (size * unit(h, 0), size * unit(h, 10));
        match i % 3 {
            0 => (Vec3::new(u, 0.0, v), Vec3::Y),
            1 => (Vec3::new(0.0, u, v), Vec3::X),
            _ => (Vec3::new(u, v, 0.0), Vec3::Z),
        }
    }

    /// `count` records placed by [`on_floor_or_wall`] with `salt` and `size`, their Ward
    /// radii from `radii.0` to `radii.0 + radii.1` by the hash of their index and `salt + 1`.
    fn floor_and_wall_records(count: u32, salt: u32, size: f32, radii: (f32, f32)) -> Vec<Record> {
        (0..count)
            .map(|i| {
                let (p, n) = on_floor_or_wall(i, salt, size);
                let h = crate::sampling::hash(&[i, salt + 1]);
                Record::bare(p, n, radii.0 + radii.1 * unit(h, 0))
            })
            .collect()
    }

    #[test]
    fn radii_brought_up_to_date_in_place_equal_a_full_pass() {
        // Records on a floor and two walls that meet it, some enclosed; then rounds in which
        // a few Ward radii grow or shrink and a few records turn enclosed or back, as re-shot
        // strata change them, and a few records are removed.
        use crate::sampling::hash;
        let place = |i: u32| on_floor_or_wall(i, 3, 4.0);
        let mut records = floor_and_wall_records(900, 3, 4.0, (0.02, 0.5));
        for (i, r) in records.iter_mut().enumerate() {
            r.enclosed = i % 37 == 0;
        }
        let params = CacheParams {
            error: 0.25,
            neighbour_clamp: 2.0,
            ..CacheParams::default()
        };
        let mut cache = IrradianceCache::default();
        cache.set_params(&params);
        cache.replace_records(records);
        let mut reclamped = 0;
        for round in 0..6u32 {
            let mut next = cache.records.clone();
            for (i, r) in next.iter_mut().enumerate() {
                let h = hash(&[i as u32, round, 9]);
                if h.is_multiple_of(16) {
                    r.radius *= 0.2 + 3.0 * unit(h, 8);
                }
                if h % 97 == 1 {
                    r.enclosed = !r.enclosed;
                }
            }
            let changed = next
                .iter()
                .zip(&cache.records)
                .filter(|(a, b)| a.radius != b.radius || a.enclosed != b.enclosed)
                .count();
            reclamped += usize::from(changed > 0 && changed * 4 <= next.len());
            cache.replace_records(next.clone());
            // A few records retire (§4.3's removal).
            let keep: Vec<bool> = (0..next.len())
                .map(|i| !hash(&[i as u32, round, 11]).is_multiple_of(29))
                .collect();
            cache.remove_records(&keep);
            let mut k = keep.iter();
            next.retain(|_| *k.next().unwrap());
            let mut full = IrradianceCache::default();
            full.set_params(&params);
            full.replace_records(next);
            let reach = |c: &IrradianceCache| -> Vec<u32> {
                c.records.iter().map(|r| r.reach_radius.to_bits()).collect()
            };
            assert_eq!(reach(&cache), reach(&full), "round {round}");
            for q in 0..300u32 {
                let (p, n) = place(10_000 + q);
                let valid = cache.valid_records(p, n, REACH * 0.25);
                assert_eq!(
                    valid,
                    full.valid_records(p, n, REACH * 0.25),
                    "round {round}, lookup {q}"
                );
                // Records moved and renumbered in place: the grids still find every one.
                assert_eq!(
                    valid,
                    valid_by_pass(&cache, p, n, REACH * 0.25),
                    "round {round}, lookup {q}"
                );
            }
        }
        assert_eq!(reclamped, 6, "every round is brought up to date in place");
    }

    /// The grids pass over the records whose spheres cannot hold a point without reading
    /// them (`grid::Block`): every clamped radius, every lookup and every coverage test
    /// equals a pass over all the records, at points on the edges of their spheres too.
    #[test]
    fn lookups_and_clamps_equal_a_pass_over_every_record() {
        let place = |i: u32| on_floor_or_wall(i, 5, 2.0);
        let mut records = floor_and_wall_records(400, 5, 2.0, (0.01, 0.4));
        for (i, r) in records.iter_mut().enumerate() {
            r.enclosed = i % 23 == 0;
            r.spot = i % 31 == 1;
        }
        let (a, slope) = (0.25, 2.0);
        let mut cache = IrradianceCache::default();
        cache.set_params(&CacheParams {
            error: a,
            neighbour_clamp: slope,
            ..CacheParams::default()
        });
        // Half the records at first, the rest added: both paths of the clamp.
        cache.replace_records(records[..200].to_vec());
        cache.append(records[200..].to_vec());
        let rs = &cache.records;
        for (i, r) in rs.iter().enumerate() {
            let lowest = rs
                .iter()
                .enumerate()
                .filter(|&(j, o)| j != i && o.is_open())
                .filter_map(|(_, o)| {
                    let at = |r: &Record| (r.position, r.normal, r.radius);
                    clamp_cap(at(r), at(o), slope, a)
                })
                .fold(r.radius, f32::min);
            assert_eq!(r.reach_radius, lowest, "record {i}");
        }
        let quiet: Vec<bool> = (0..rs.len()).map(|i| i % 2 == 0).collect();
        // Random points, and points on each record's surface at its sphere's edge.
        let mut points: Vec<(Vec3, Vec3)> = (0..300).map(|q| place(10_000 + q)).collect();
        for r in rs {
            let t = r.normal.any_orthonormal_vector();
            for f in [0.5, 0.999, 1.0 - 1e-6, 1.0, 1.0 + 1e-6, 1.001, 1.5] {
                for reach in [a * r.reach_radius, REACH * a * r.reach_radius] {
                    points.push((r.position + t * (reach * f), r.normal));
                }
            }
        }
        for (x, n) in points {
            for t in [a, REACH * a] {
                let valid = |i: usize| IrradianceCache::weight(&rs[i], x, n) > 1.0 / t;
                let all = valid_by_pass(&cache, x, n, t);
                assert_eq!(cache.valid_records(x, n, t), all, "at {x}, a {t}");
                // Placement's coverage: to a, or to the slack (at most `REACH`) for the quiet.
                if t == a {
                    let loose =
                        |i: usize| IrradianceCache::weight(&rs[i], x, n) > 1.0 / (REACH * t);
                    let covered = (0..rs.len()).any(|i| valid(i) || (quiet[i] && loose(i)));
                    assert_eq!(
                        cache.covers_with_slack(x, n, t, REACH, &quiet),
                        covered,
                        "at {x}"
                    );
                }
                let enclosed = rs.iter().any(|r| {
                    r.enclosed && !r.spot && IrradianceCache::ward_weight(r, x, n) > 1.0 / t
                });
                assert_eq!(
                    !cache.enclosed_at(x, n, t).is_empty(),
                    enclosed,
                    "at {x}, a {t}"
                );
                let spot =
                    (0..rs.len()).any(|i| IrradianceCache::spot_weight(&rs[i], x, n) > 1.0 / t);
                assert_eq!(cache.spot_covers(x, n, t), spot, "at {x}, a {t}");
            }
        }
    }
}
