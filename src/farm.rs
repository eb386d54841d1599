//! Farm jobs: a shot split into frame chunks that an existing farm engine runs, described as
//! an Open Job Description template (the open job specification AWS Deadline Cloud runs;
//! `openjd run` runs it locally). DESIGN.md, Shot state.
//!
//! Two ways to split, because the state anchors carry from frame to frame (§3) makes a chunk
//! that starts cold differ from the same frames of a run that rendered through:
//!
//! - **warm-up** (parallel): one step whose tasks are the chunks; each renders `--warmup N`
//!   frames before its range without writing them. Every chunk runs at once; the chunk's
//!   first frame differs from the full run's by a seam error that falls with N (measured in
//!   the README), at the cost of N extra frames per chunk.
//! - **chained** (exact): one step per chunk, each depending on the one before; a chunk
//!   writes its last frame's checkpoint (`--state-out`) and the next resumes from it
//!   (`--resume`), so the frames are byte for byte those of one render. Chunks then run one
//!   after the other, on whichever machine the farm picks (the checkpoint travels through
//!   the shared state directory).
//!
//! The template's parameters — the job file, the output and state directories, the
//! anchorage executable — default to this machine's paths and are overridden at submission
//! (`-p Job=...`), so the same template serves the farm's path mapping.

use std::path::{Path, PathBuf};

use serde::Serialize;
use serde_json::{Value, json};

use crate::compare::score::{Aov, rms_error_pct};
use crate::error::{Error, Result};
use crate::job::{FrameRange, Job};
use crate::pipeline;
use crate::scene::Scene;
use crate::session::FrameState;

/// How the chunks of a farm job get their state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    /// Parallel chunks, each warmed up by this many unwritten frames.
    Warmup(u32),
    /// Chunks run in order, each resuming the previous one's last state.
    Chained,
}

/// The most chunks a template holds (one task, or one step, each).
pub const MAX_CHUNKS: usize = 10_000;

/// The frame ranges of `frames` in chunks of `size`.
pub fn chunks(frames: FrameRange, size: u32) -> Vec<FrameRange> {
    let size = i64::from(size.max(1));
    let (start, end) = (i64::from(frames.start), i64::from(frames.end));
    (0..)
        .map(|k| start + k * size)
        .take_while(|&a| a <= end)
        .map(|a| FrameRange {
            start: a as i32,
            end: (a + size - 1).min(end) as i32,
        })
        .collect()
}

fn range_arg(r: FrameRange) -> String {
    format!("{}-{}", r.start, r.end)
}

/// The Open Job Description template (`jobtemplate-2023-09`) that renders `job`'s frames in
/// chunks of `chunk_size` split as `split` says. `exe` is the anchorage executable the
/// template runs by default; `dir` is where the template is written: the specification
/// makes default paths relative to it.
pub fn template(job: &Job, chunk_size: u32, split: Split, exe: &Path, dir: &Path) -> Result<Value> {
    if chunk_size == 0 {
        return Err(Error::input("--chunk-size", "0", "must be at least 1"));
    }
    let chunks = chunks(job.frames, chunk_size);
    if chunks.len() > MAX_CHUNKS {
        return Err(Error::input(
            "--chunk-size",
            chunk_size.to_string(),
            format!(
                "makes {} chunks; at most {MAX_CHUNKS} (choose larger chunks)",
                chunks.len()
            ),
        ));
    }
    let dir = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
    // A PATH parameter's default is relative to the template's directory and may not leave
    // it; a path outside it has no default and is given at submission (`-p Job=...`).
    let path_param = |name: &str, p: &Path, object: &str, flow: &str, about: &str| {
        let mut v = json!({"name": name, "type": "PATH", "objectType": object,
                           "dataFlow": flow, "description": about});
        let p = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
        if let Some(rel) = relative_to(&p, &dir) {
            v["default"] = json!(rel.display().to_string());
        }
        v
    };
    let mut params = vec![
        path_param("Job", &job.path, "FILE", "IN", "The anchorage job file."),
        path_param(
            "OutDir",
            &job.out_dir,
            "DIRECTORY",
            "OUT",
            "Where the frames are written.",
        ),
        json!({"name": "Anchorage", "type": "STRING", "default": exe.display().to_string(),
               "description": "The anchorage executable on the workers."}),
    ];
    let render = |frames: FrameRange, extra: Vec<String>| {
        let mut args = vec![
            "render".to_string(),
            "{{Param.Job}}".into(),
            "--frames".into(),
            range_arg(frames),
            "--out".into(),
            "{{Param.OutDir}}".into(),
        ];
        args.extend(extra);
        json!({"actions": {"onRun": {"command": "{{Param.Anchorage}}", "args": args}}})
    };
    let steps: Vec<Value> = match split {
        Split::Warmup(n) => {
            let ranges: Vec<String> = chunks.iter().map(|&c| range_arg(c)).collect();
            let mut args = vec![
                "render".to_string(),
                "{{Param.Job}}".into(),
                "--frames".into(),
                "{{Task.Param.Frames}}".into(),
                "--out".into(),
                "{{Param.OutDir}}".into(),
            ];
            if n > 0 {
                args.extend(["--warmup".into(), n.to_string()]);
            }
            vec![json!({
                "name": "Render",
                "description": format!("Frames {} in chunks of {chunk_size}, each warmed up by {n} frames", range_arg(job.frames)),
                "parameterSpace": {"taskParameterDefinitions": [
                    {"name": "Frames", "type": "STRING", "range": ranges}
                ]},
                "script": {"actions": {"onRun": {"command": "{{Param.Anchorage}}", "args": args}}}
            })]
        }
        Split::Chained => {
            params.push(path_param(
                "StateDir",
                &job.out_dir.join("state"),
                "DIRECTORY",
                "INOUT",
                "Where each chunk leaves its last frame's state for the next.",
            ));
            let mut steps = Vec::new();
            let mut previous: Option<String> = None;
            for &c in &chunks {
                let name = format!("Frames {}", range_arg(c));
                let mut extra = vec![
                    "--state-out".to_string(),
                    "{{Param.StateDir}}".into(),
                    "--state-every".into(),
                    chunk_size.to_string(),
                ];
                if previous.is_some() {
                    let before = i64::from(c.start) - 1;
                    extra.extend([
                        "--resume".into(),
                        format!("{{{{Param.StateDir}}}}/{}.{before:04}.state", job.name),
                    ]);
                }
                let mut step = json!({"name": name, "script": render(c, extra)});
                if let Some(p) = &previous {
                    step["dependencies"] = json!([{"dependsOn": p}]);
                }
                steps.push(step);
                previous = Some(name);
            }
            steps
        }
    };
    let how = match split {
        Split::Warmup(n) => format!("warm-up {n}"),
        Split::Chained => "chained".into(),
    };
    // Job names are at most 128 characters.
    let name: String = format!("anchorage {} {} ({how})", job.name, range_arg(job.frames))
        .chars()
        .take(128)
        .collect();
    Ok(json!({
        "specificationVersion": "jobtemplate-2023-09",
        "name": name,
        "parameterDefinitions": params,
        "steps": steps,
    }))
}

/// What warming up a chunk by `warmup` frames buys, averaged over a shot's chunk seams.
#[derive(Debug, Clone, Serialize)]
pub struct SeamRow {
    pub warmup: u32,
    /// Mean over the seams of the RMS error (% of the full run's RMS) of the chunk's first
    /// frame against the same frame of the run that rendered through, beauty and indirect.
    pub beauty_rms_pct: f64,
    pub indirect_rms_pct: f64,
    /// The largest of the seams' indirect errors.
    pub indirect_rms_max_pct: f64,
    /// The step the viewer sees at the seam: the chunk's first frame against the full run's
    /// frame before it (indirect, RMS %), beside the full run's own step between those two
    /// frames (the same for every row).
    pub indirect_step_pct: f64,
    pub full_run_indirect_step_pct: f64,
    /// The chunk's first frame's gather rays against the full run's at that frame.
    pub gather_rays: u64,
    pub full_run_gather_rays: u64,
    /// Frames rendered and thrown away per chunk (fewer for a chunk near the animation's
    /// start), and their share of the shot's frames.
    pub extra_frames_per_chunk: f64,
    pub extra_frames_pct: f64,
    /// Seconds to render the warm-up and the first frame, mean over the seams.
    pub seconds_per_seam: f64,
}

/// Measures [`Split::Warmup`] on `job`: renders its frames through once, then every chunk
/// seam (each chunk's first frame but the first chunk's) again with each of `warmups`,
/// and scores the seam frame against the run that rendered through.
pub fn measure_seams(
    job: &Job,
    scene: &Scene,
    chunk_size: u32,
    warmups: &[u32],
    mut progress: impl FnMut(&str),
) -> Result<Vec<SeamRow>> {
    let resources = pipeline::new_resources(job, scene)?;
    let seams: Vec<i32> = chunks(job.frames, chunk_size)
        .iter()
        .skip(1)
        .map(|c| c.start)
        .collect();
    if seams.is_empty() {
        return Err(Error::input(
            "--chunk-size",
            chunk_size.to_string(),
            format!(
                "frames {} make one chunk: no seam to measure",
                range_arg(job.frames)
            ),
        ));
    }
    let (mut full, mut before) = (Vec::new(), Vec::new());
    let mut state = FrameState::default();
    for f in job.frames.start..=job.frames.end {
        let mut stats = pipeline::new_stats(job, f);
        let img = pipeline::render_frame(job, scene, &resources, &mut state, f, &mut stats)?;
        if seams.contains(&(f + 1)) {
            before.push(img.clone());
        }
        if seams.contains(&f) {
            full.push((img, stats.counts.rays_shot));
        }
        progress(&format!("full run: frame {f}"));
    }
    let frames = f64::from(job.frames.end) - f64::from(job.frames.start) + 1.0;
    let mut rows = Vec::new();
    for &n in warmups {
        let (mut beauty, mut indirect, mut worst, mut rays, mut extra, mut secs) =
            (0.0, 0.0, 0.0f64, 0u64, 0.0, 0.0);
        let (mut step, mut own_step) = (0.0, 0.0);
        for ((&seam, (reference, _)), previous) in seams.iter().zip(&full).zip(&before) {
            let mut chunk = job.clone();
            chunk.frames = FrameRange {
                start: seam,
                end: seam,
            };
            let first = pipeline::first_frame(&chunk, scene, n);
            let t0 = std::time::Instant::now();
            let mut state = FrameState::default();
            let mut last = None;
            for f in first..=seam {
                let mut stats = pipeline::new_stats(job, f);
                let img =
                    pipeline::render_frame(job, scene, &resources, &mut state, f, &mut stats)?;
                last = Some((img, stats.counts.rays_shot));
            }
            secs += t0.elapsed().as_secs_f64();
            let (img, r) = last.expect("the seam frame is rendered");
            beauty += rms_error_pct(&img, reference, Aov::Beauty);
            let e = rms_error_pct(&img, reference, Aov::Indirect);
            indirect += e;
            worst = worst.max(e);
            step += rms_error_pct(&img, previous, Aov::Indirect);
            own_step += rms_error_pct(reference, previous, Aov::Indirect);
            rays += r;
            extra += f64::from(seam - first);
            progress(&format!("warm-up {n}: seam at frame {seam}"));
        }
        let k = seams.len() as f64;
        rows.push(SeamRow {
            warmup: n,
            beauty_rms_pct: beauty / k,
            indirect_rms_pct: indirect / k,
            indirect_rms_max_pct: worst,
            indirect_step_pct: step / k,
            full_run_indirect_step_pct: own_step / k,
            gather_rays: rays / seams.len() as u64,
            full_run_gather_rays: full.iter().map(|x| x.1).sum::<u64>() / seams.len() as u64,
            extra_frames_per_chunk: extra / k,
            // The first chunk needs no warm-up.
            extra_frames_pct: 100.0 * extra / frames,
            seconds_per_seam: secs / k,
        });
    }
    Ok(rows)
}

/// The rows of [`measure_seams`] as a table.
pub fn seam_table(rows: &[SeamRow]) -> String {
    let mut t = String::from(
        "warm-up  seam RMS beauty  seam RMS indirect (max)  indirect step (full run)  gather rays (full run)  extra frames/chunk  extra frames  s/seam\n",
    );
    for r in rows {
        t += &format!(
            "{:>7}  {:>14.2} %  {:>11.2} % ({:>6.2} %)  {:>10.2} % ({:>6.2} %)  {:>10} ({:>9})  {:>18.1}  {:>10.1} %  {:>6.2}\n",
            r.warmup,
            r.beauty_rms_pct,
            r.indirect_rms_pct,
            r.indirect_rms_max_pct,
            r.indirect_step_pct,
            r.full_run_indirect_step_pct,
            r.gather_rays,
            r.full_run_gather_rays,
            r.extra_frames_per_chunk,
            r.extra_frames_pct,
            r.seconds_per_seam
        );
    }
    t
}

/// `path` relative to the directory `base` (both absolute, normalised by
/// [`std::path::absolute`]), or `None` where `path` is not inside `base`.
fn relative_to(path: &Path, base: &Path) -> Option<PathBuf> {
    let rel = path.strip_prefix(base).ok()?;
    if rel
        .components()
        .any(|c| c == std::path::Component::ParentDir)
    {
        return None;
    }
    Some(if rel.as_os_str().is_empty() {
        PathBuf::from(".")
    } else {
        rel.to_path_buf()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunks_cover_the_range_once() {
        let r = |start, end| FrameRange { start, end };
        assert_eq!(chunks(r(0, 9), 4), vec![r(0, 3), r(4, 7), r(8, 9)]);
        assert_eq!(chunks(r(-3, -3), 10), vec![r(-3, -3)]);
        assert_eq!(chunks(r(i32::MAX - 1, i32::MAX), 1).len(), 2);
    }

    #[test]
    fn default_paths_are_relative_to_the_template() {
        let rel = |p: &str, b: &str| relative_to(Path::new(p), Path::new(b));
        assert_eq!(rel("/a/b/job.json", "/a/b").unwrap(), Path::new("job.json"));
        assert_eq!(
            rel("/a/b/c/job.json", "/a/b").unwrap(),
            Path::new("c/job.json")
        );
        assert_eq!(rel("/a/b/job.json", "/a/c"), None);
        assert_eq!(rel("/a/b/../c/job.json", "/a/b"), None);
        assert_eq!(rel("/a", "/a").unwrap(), Path::new("."));
    }
}
