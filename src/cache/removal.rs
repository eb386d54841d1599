//! Cache density control by the records' influence on the image (the paper's §4.3, third
//! category, Equation 1).
//!
//! Records added while a dynamic prim was near, or when the camera zoomed in, stay valid
//! after they are no longer needed: the pixels around them read more and more records, and
//! interpolation grows slower with no gain. After a frame, every pixel read from more than
//! N records (`weber_records`, the paper's N = 6) is *crowded*. For each record there, its
//! Weber fraction over every pixel it contributed to,
//!
//! δ_i = Σ_j |P_{j,i} − P̄_{j,i}| / P_{j,i},
//!
//! with P_{j,i} the pixel's interpolated irradiance (luminance) and P̄_{j,i} the same with
//! record i left out and the others' weights renormalised, measures how much of the image
//! it makes. Records with δ_i below `weber_threshold` are removed — lowest δ first, and only
//! while every pixel they contribute to keeps at least N records, so that thinning a crowded
//! region never opens a hole there (which the next frame's placement would fill with a new
//! record, gathered from scratch) and pixels outside crowded regions lose nothing.
//!
//! A "pixel" here is one cache read of the shading pass: a pixel's samples on one surface
//! share it. The paper keeps a use counter and a list of records with their weights per
//! pixel; [`WeberTally`] keeps the same, flattened, with each record's part of δ computed
//! at the read. No crate does this: it is the paper's own rule.

use crate::color::luminance;
use glam::Vec3;

/// One record's part in a cache read ([`super::IrradianceCache::interpolate`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contribution {
    pub record: u32,
    /// Ward's weight w_i at the read.
    pub weight: f32,
    /// The record's extrapolated irradiance there.
    pub value: Vec3,
}

/// The cache reads of a frame (or of a row of it), in order: for each, the records that
/// contributed and each one's term of Equation 1.
#[derive(Debug, Clone, Default)]
pub struct WeberTally {
    /// Per contribution: the record and |P − P̄| / P (infinite where leaving it out changes
    /// a black pixel, or leaves no record at all).
    parts: Vec<(u32, f32)>,
    /// Read j's contributions are `parts[ends[j − 1]..ends[j]]`.
    ends: Vec<u32>,
}

impl WeberTally {
    /// Notes one cache read and its contributions (all of them, weights as interpolated).
    pub fn read(&mut self, contributions: &[Contribution]) {
        let w: f32 = contributions.iter().map(|c| c.weight).sum();
        let sum: Vec3 = contributions.iter().map(|c| c.weight * c.value).sum();
        let p = luminance(sum / w);
        for c in contributions {
            let rest = w - c.weight;
            let fraction = if rest > 0.0 {
                let p_bar = luminance((sum - c.weight * c.value) / rest);
                let change = (p - p_bar).abs();
                if p > 0.0 {
                    change / p
                } else if change > 0.0 {
                    f32::INFINITY
                } else {
                    0.0
                }
            } else {
                f32::INFINITY
            };
            self.parts.push((c.record, fraction));
        }
        self.ends.push(self.parts.len() as u32);
    }

    /// Appends `other`'s reads after this one's.
    pub fn append(&mut self, other: &WeberTally) {
        let base = self.parts.len() as u32;
        self.parts.extend_from_slice(&other.parts);
        self.ends.extend(other.ends.iter().map(|e| base + e));
    }

    /// The records to remove (ascending), of `records` in all (module doc): those in a read
    /// with more than `crowded` contributors whose δ is below `threshold`, lowest δ first
    /// (ties by index), each only while every read it contributes to keeps `crowded`.
    pub fn removals(&self, records: usize, crowded: u32, threshold: f32) -> Vec<u32> {
        let reads = || {
            self.ends
                .iter()
                .scan(0usize, |start, &end| {
                    let r = *start..end as usize;
                    *start = end as usize;
                    Some(r)
                })
                .enumerate()
        };
        let mut delta = vec![0.0f64; records];
        let mut candidate = vec![false; records];
        // Reads per record, as a compressed sparse row table.
        let mut per_record = vec![0u32; records + 1];
        for (i, f) in &self.parts {
            delta[*i as usize] += *f as f64;
            per_record[*i as usize + 1] += 1;
        }
        for (_, r) in reads() {
            if r.len() > crowded as usize {
                for &(i, _) in &self.parts[r] {
                    candidate[i as usize] = true;
                }
            }
        }
        for i in 0..records {
            per_record[i + 1] += per_record[i];
        }
        let mut fill = per_record.clone();
        let mut read_of = vec![0u32; self.parts.len()];
        for (j, r) in reads() {
            for &(i, _) in &self.parts[r] {
                read_of[fill[i as usize] as usize] = j as u32;
                fill[i as usize] += 1;
            }
        }
        let mut order: Vec<u32> = (0..records as u32)
            .filter(|&i| candidate[i as usize] && delta[i as usize] < threshold as f64)
            .collect();
        order.sort_by(|&a, &b| {
            delta[a as usize]
                .total_cmp(&delta[b as usize])
                .then(a.cmp(&b))
        });
        let mut left: Vec<u32> = reads().map(|(_, r)| r.len() as u32).collect();
        let mut removed = Vec::new();
        for i in order {
            let mine =
                &read_of[per_record[i as usize] as usize..per_record[i as usize + 1] as usize];
            if mine.iter().all(|&j| left[j as usize] > crowded) {
                for &j in mine {
                    left[j as usize] -= 1;
                }
                removed.push(i);
            }
        }
        removed.sort_unstable();
        removed
    }

    /// Cache reads noted.
    pub fn len(&self) -> usize {
        self.ends.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn c(record: u32, weight: f32, value: f32) -> Contribution {
        Contribution {
            record,
            weight,
            value: Vec3::splat(value),
        }
    }

    #[test]
    fn the_weber_fraction_is_the_relative_change_without_the_record() {
        let mut t = WeberTally::default();
        // P = (1·1 + 1·3) / 2 = 2; without record 0: 3, without record 1: 1.
        t.read(&[c(0, 1.0, 1.0), c(1, 1.0, 3.0)]);
        assert_eq!(t.parts, vec![(0, 0.5), (1, 0.5)]);
        // A sole contributor cannot be left out.
        t.read(&[c(2, 1.0, 1.0)]);
        assert_eq!(t.parts[2], (2, f32::INFINITY));
    }

    #[test]
    fn crowded_reads_are_thinned_to_n_and_no_further() {
        // Eight records agree everywhere: each is redundant (δ = 0), but a read keeps six.
        let mut t = WeberTally::default();
        let same: Vec<Contribution> = (0..8).map(|i| c(i, 1.0 + i as f32, 1.0)).collect();
        for _ in 0..10 {
            t.read(&same);
        }
        assert_eq!(t.removals(8, 6, 0.1), vec![0, 1]);
        // A record that also serves an uncrowded read is kept there as well as here.
        t.read(&[c(0, 1.0, 1.0), c(9, 1.0, 1.0)]);
        assert_eq!(t.removals(10, 6, 0.1), vec![1, 2]);
    }

    #[test]
    fn influential_records_stay() {
        // Record 7 makes the pixels bright: its δ is large, the others' small.
        let mut t = WeberTally::default();
        let mut reads: Vec<Contribution> = (0..7).map(|i| c(i, 1.0, 1.0)).collect();
        reads.push(c(7, 4.0, 10.0));
        t.read(&reads);
        let removed = t.removals(8, 6, 0.5);
        assert!(!removed.contains(&7), "{removed:?}");
        assert_eq!(removed.len(), 2);
        // Nothing is crowded at N = 8: nothing goes.
        assert!(t.removals(8, 8, 0.5).is_empty());
    }
}
