//! Memory estimate of a render, checked against a limit before the big allocations (image
//! and AOV buffers, photons, the irradiance cache and its strata), so that a job too big for
//! the machine stops with exit 2 and the estimate instead of an abort halfway through.
//!
//! The estimate is an upper bound of the largest items, not an accounting of every byte:
//! per pixel the AOVs, the render's pixel accumulators and the EXR encoder's channel copies;
//! per photon its record and its share of the kd-tree, for the longest expected paths; per
//! cache record its strata, for records as dense as the minimum spacing allows (Sponza
//! places 31–87 % of that); while a batch of records is gathered, the strata and radiance
//! it resolves (`anchors`: the strata alone) and the hits of one part of it
//! ([`crate::cache::gather::PART_HITS`]) with what resolving them holds; with
//! checkpoints, the buffers a checkpoint holds while it is written or read (a batch of its
//! chunks: it is encoded and decoded as it streams); the scene's own
//! geometry and textures as loaded.

use std::path::Path;

use crate::error::{Error, Result};
use crate::job::{Job, Method};
use crate::scene::Scene;

/// Bytes per pixel: AOVs (beauty 16, direct and indirect 24, their diffuse and glossy parts
/// 48, depth, anchor id and reshoot 12), the accumulators they are collected from (about as
/// many), and the EXR encoder's per-channel copies with its compression buffers.
const BYTES_PER_PIXEL: u64 = 100 + 112 + 216;
/// Bytes per stored photon (position, normal, power; the kd-tree's copy and index) times the
/// photons one emitted photon leaves in bright scenes.
const BYTES_PER_PHOTON: u64 = (36 + 24) * 6;
/// Bytes per stratum of a cache record (`cache::record::Stratum`) with its anchor's share.
const BYTES_PER_STRATUM: u64 = 6 + 4;
/// Bytes per stratum of a batch of records being gathered: its stratum and radiance as the
/// batch resolves them ([`crate::cache::Resolved`]), held until the batch's records are made.
/// A frame's largest batch (the finest grid of its pixel centres) holds up to about half its
/// new records (45–54 % on Sponza's first frame); counted here for all of them.
const RESOLVED_BYTES_PER_STRATUM: u64 = 6 + 12;
/// [`RESOLVED_BYTES_PER_STRATUM`] for `anchors`, which keeps the stratum alone: a linked
/// stratum's radiance is its anchor's, read as its record is made, and only the few strata
/// whose rays met a dynamic prim keep theirs.
const ANCHOR_RESOLVED_BYTES_PER_STRATUM: u64 = 6;
/// Bytes per hit of the part of a batch being gathered: the hit
/// ([`crate::cache::GatherHit`]) and what resolving it holds beside (for `anchors`: the
/// re-shot stratum's kept anchor, the attaching hits' list and their anchors, 24 bytes).
const PART_BYTES_PER_HIT: u64 = size_of::<crate::cache::GatherHit>() as u64 + 24;
/// What `anchors` holds beside a part while its hits attach: two shares of the search
/// ([`crate::anchor::attach::SHARE_BYTES`]).
const ANCHOR_SEARCH_BYTES: u64 = 2 * crate::anchor::attach::SHARE_BYTES as u64;
/// Bytes per triangle: its vertices (48) and shading record (80), and its share of the BVH
/// with the traversal's copy of it (`accel::pairs`: 101 a triangle on Sponza).
const BYTES_PER_TRIANGLE: u64 = 48 + 80 + 104;

/// What a render is estimated to hold at its peak, by part.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Estimate {
    pub image: u64,
    pub photons: u64,
    pub cache: u64,
    /// A batch of records being gathered: one part's hits and the batch's resolved strata.
    pub gather: u64,
    /// The buffers of a checkpoint being written or read (0 without checkpoints).
    pub checkpoint: u64,
    pub scene: u64,
}

impl Estimate {
    pub fn total(&self) -> u64 {
        self.image + self.photons + self.cache + self.gather + self.checkpoint + self.scene
    }

    /// Estimates the peak memory of rendering `job` on `scene`, writing or reading
    /// checkpoints where `checkpoints` says so (`render --state-out` or `--resume`).
    pub fn of(job: &Job, scene: &Scene, checkpoints: bool) -> Estimate {
        let pixels = u64::from(job.width) * u64::from(job.height);
        let p = job.method.params();
        let cached = !matches!(job.method.name, Method::Direct | Method::PathTrace);
        let (photons, cache, gather, checkpoint) = if cached {
            // One record per square of the minimum spacing: Sponza's first frame places 70 %
            // of that at the final preset (1.5 pixels) at 320×180 (18 050 records), 48 % at
            // 640×360 (49 285) and 31 % at 1280×720 (125 191), and 81 % at production
            // (2 pixels) at 320×180 (11 610).
            let spacing = f64::from(p.cache.min_spacing_px.max(1.0));
            let records = (pixels as f64 / (spacing * spacing)).ceil() as u64;
            let strata = u64::from(p.cache.strata[0]) * u64::from(p.cache.strata[1]);
            let part = (crate::cache::gather::part_records(p.cache.strata) as u64).min(records);
            let (resolved, search) = match job.method.name {
                Method::Anchors => (ANCHOR_RESOLVED_BYTES_PER_STRATUM, ANCHOR_SEARCH_BYTES),
                _ => (RESOLVED_BYTES_PER_STRATUM, 0),
            };
            (
                u64::from(p.photons) * BYTES_PER_PHOTON,
                records * strata * BYTES_PER_STRATUM,
                records * strata * resolved + part * strata * PART_BYTES_PER_HIT + search,
                if checkpoints {
                    crate::checkpoint::BUFFER_BYTES
                } else {
                    0
                },
            )
        } else {
            (0, 0, 0, 0)
        };
        // Every instance of a mesh is its own world-space copy.
        let triangles: u64 = scene
            .layers
            .iter()
            .flat_map(|l| l.nodes.iter().filter_map(|n| n.mesh).map(|m| &l.meshes[m]))
            .flat_map(|m| &m.primitives)
            .map(|p| p.indices.len() as u64 / 3)
            .sum();
        let texels: u64 = scene
            .textures
            .iter()
            .map(|t| u64::from(t.width) * u64::from(t.height) * 16)
            .sum();
        Estimate {
            image: pixels * BYTES_PER_PIXEL,
            photons,
            cache,
            gather,
            checkpoint,
            scene: triangles * BYTES_PER_TRIANGLE + texels,
        }
    }

    /// The job key to change first: the one behind the largest part.
    fn culprit(&self) -> &'static str {
        let parts = [
            (self.image, "resolution"),
            (self.photons, "method.photons"),
            (self.cache, "method.strata"),
            (self.gather, "method.strata"),
            (self.checkpoint, "method.strata"),
            (self.scene, "scene"),
        ];
        parts
            .iter()
            .max_by_key(|(b, _)| *b)
            .map_or("resolution", |(_, k)| k)
    }
}

/// The memory a render may use: `--memory-limit`, or by default 80 % of the machine's (or
/// the control group's, where lower) memory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limit {
    pub bytes: u64,
    /// Whether the user gave it (else it is the machine's share).
    pub explicit: bool,
}

impl Limit {
    pub fn of_machine() -> Option<Limit> {
        let total = machine_memory()?;
        Some(Limit {
            bytes: total / 5 * 4,
            explicit: false,
        })
    }

    /// Parses `--memory-limit`: bytes, or a number with K, M, G or T (powers of 1024).
    pub fn parse(s: &str) -> Result<Limit> {
        Limit::parse_option("--memory-limit", s)
    }

    /// Parses a size given to the command-line option `option`, as [`Limit::parse`].
    pub fn parse_option(option: &str, s: &str) -> Result<Limit> {
        let t = s.trim();
        let (num, unit) = match t.char_indices().find(|(_, c)| c.is_ascii_alphabetic()) {
            Some((i, _)) => (&t[..i], t[i..].to_ascii_uppercase()),
            None => (t, String::new()),
        };
        let scale: u64 = match unit.trim_end_matches(['B', 'I']) {
            "" => 1,
            "K" => 1 << 10,
            "M" => 1 << 20,
            "G" => 1 << 30,
            "T" => 1 << 40,
            _ => 0,
        };
        let v: f64 = num.trim().parse().unwrap_or(f64::NAN);
        let bytes = v * scale as f64;
        if scale == 0 || !(bytes >= 1.0 && bytes < 2f64.powi(63)) {
            return Err(Error::input(
                option,
                s,
                "expected a size such as 8G, 512M or 1073741824",
            ));
        }
        Ok(Limit {
            bytes: bytes as u64,
            explicit: true,
        })
    }
}

/// Physical memory, or the control group's limit where one is set and lower.
fn machine_memory() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let total = meminfo
        .lines()
        .find_map(|l| l.strip_prefix("MemTotal:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())?
        * 1024;
    let cgroup = std::fs::read_to_string("/sys/fs/cgroup/memory.max")
        .ok()
        .and_then(|s| s.trim().parse::<u64>().ok());
    Some(cgroup.map_or(total, |c| c.min(total)))
}

fn gib(b: u64) -> String {
    format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64)
}

/// Checks the job's estimate against `limit` (the machine's share when `None` and it can be
/// read); over it, an input error naming the job key behind the largest part.
pub fn check(job: &Job, scene: &Scene, limit: Option<Limit>) -> Result<Estimate> {
    check_with_checkpoints(job, scene, limit, false)
}

/// [`check`] for a render that writes or reads checkpoints where `checkpoints` says so.
pub fn check_with_checkpoints(
    job: &Job,
    scene: &Scene,
    limit: Option<Limit>,
    checkpoints: bool,
) -> Result<Estimate> {
    let e = Estimate::of(job, scene, checkpoints);
    let Some(limit) = limit.or_else(Limit::of_machine) else {
        return Ok(e);
    };
    if e.total() > limit.bytes {
        let whose = if limit.explicit {
            "--memory-limit".to_string()
        } else {
            "80 % of this machine's memory; --memory-limit changes it".to_string()
        };
        return Err(Error::input(
            Path::new(&job.path),
            e.culprit(),
            format!(
                "the render needs about {} (images {} at {}×{}, photons {}, cache {}, gathering {}{}, \
                 scene {}), more than the limit of {} ({whose})",
                gib(e.total()),
                gib(e.image),
                job.width,
                job.height,
                gib(e.photons),
                gib(e.cache),
                gib(e.gather),
                if e.checkpoint > 0 {
                    format!(", checkpoints {}", gib(e.checkpoint))
                } else {
                    String::new()
                },
                gib(e.scene),
                gib(limit.bytes),
            ),
        ));
    }
    Ok(e)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_binary_units() {
        assert_eq!(Limit::parse("8G").unwrap().bytes, 8 << 30);
        assert_eq!(Limit::parse("512M").unwrap().bytes, 512 << 20);
        assert_eq!(Limit::parse("1.5GiB").unwrap().bytes, 3 << 29);
        assert_eq!(Limit::parse("1000").unwrap().bytes, 1000);
        for bad in ["", "G", "-1G", "8Q", "nan", "1e30T"] {
            assert!(Limit::parse(bad).is_err(), "{bad}");
        }
    }
}
