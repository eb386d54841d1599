//! `anchorage compare`: measures the speed/accuracy trade of methods and presets on one job
//! (DESIGN.md, Speed versus accuracy). Every method renders the same frames with the same
//! seeds; each is scored against a reference method by
//!
//! - seconds per frame (median of the frames' totals),
//! - RMS relative error in %: `100·sqrt(Σ(m − r)² / Σ r²)` over the beauty's RGB, averaged
//!   over frames,
//! - temporal flicker in %: the mean absolute frame-to-frame change of the method's beauty
//!   over pixels where the reference does not change (coverage equal, depth within 1 % in
//!   both frames), relative to the reference's mean there. A moving camera leaves few such
//!   pixels: the report says how many were compared.
//!
//! Output: a table on stdout, `compare.json`, and `compare.png` (error against time).

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::error::{Error, Result};
use crate::integrator::FrameImage;
use crate::integrator::Preset;
use crate::job::{Job, Method, VisibilityChoice};
use crate::output;
use crate::pipeline;
use crate::scene::Scene;
use crate::session::FrameState;
use crate::stats::FrameStats;

/// One method at one preset, optionally with one setting changed.
#[derive(Debug, Clone, PartialEq)]
pub struct Variant {
    pub method: Method,
    pub preset: Preset,
    pub setting: Option<Setting>,
}

/// A method setting swept by `compare --vary`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Setting {
    Photons(u32),
    K(u32),
    Strata([u32; 2]),
    Error(f32),
    /// Where visibility detection runs (a render setting, not a method's).
    Visibility(VisibilityChoice),
    /// Photons per anchor estimate as a multiple of `k`.
    AnchorK(f32),
}

impl Setting {
    /// Parses `KEY=V1,V2,...` into one setting per value.
    pub fn parse_list(s: &str) -> Option<Vec<Setting>> {
        let (key, values) = s.split_once('=')?;
        values
            .split(',')
            .map(|v| {
                let v = v.trim();
                Some(match key.trim() {
                    "photons" => Setting::Photons(v.parse().ok()?),
                    "k" => Setting::K(v.parse().ok()?),
                    "strata" => {
                        let (m, n) = v.split_once('x')?;
                        Setting::Strata([m.parse().ok()?, n.parse().ok()?])
                    }
                    "error" => Setting::Error(v.parse().ok()?),
                    "anchor_k" => Setting::AnchorK(v.parse().ok()?),
                    "visibility" => Setting::Visibility(match v {
                        "auto" => VisibilityChoice::Auto,
                        "gpu" => VisibilityChoice::Gpu,
                        "cpu" => VisibilityChoice::Cpu,
                        _ => return None,
                    }),
                    _ => return None,
                })
            })
            .collect()
    }

    pub fn apply(&self, job: &mut Job) {
        let m = &mut job.method;
        match *self {
            Setting::Photons(v) => m.photons = Some(v),
            Setting::K(v) => m.k = Some(v),
            Setting::Strata(v) => m.strata = Some(v),
            Setting::Error(v) => m.error = Some(v),
            Setting::Visibility(v) => job.render.visibility = v,
            Setting::AnchorK(v) => m.anchors.get_or_insert_default().k_scale = v,
        }
    }

    fn label(&self) -> String {
        match self {
            Setting::Photons(v) => format!("photons={v}"),
            Setting::K(v) => format!("k={v}"),
            Setting::Strata([m, n]) => format!("strata={m}x{n}"),
            Setting::Error(v) => format!("error={v}"),
            Setting::Visibility(v) => format!("visibility={}", format!("{v:?}").to_lowercase()),
            Setting::AnchorK(v) => format!("anchor_k={v}"),
        }
    }
}

impl Variant {
    pub fn label(&self) -> String {
        let base = format!("{}/{}", self.method.name(), preset_name(self.preset));
        match &self.setting {
            Some(s) => format!("{base} {}", s.label()),
            None => base,
        }
    }
}

pub fn preset_name(p: Preset) -> &'static str {
    match p {
        Preset::Draft => "draft",
        Preset::Production => "production",
        Preset::Final => "final",
    }
}

pub fn parse_preset(s: &str) -> Option<Preset> {
    [Preset::Draft, Preset::Production, Preset::Final]
        .into_iter()
        .find(|p| preset_name(*p) == s)
}

/// Scores of one variant.
#[derive(Debug, Clone, Serialize)]
pub struct Score {
    pub label: String,
    pub method: String,
    pub preset: &'static str,
    pub seconds_per_frame_median: f64,
    pub rms_error_pct: f64,
    pub rms_error_pct_per_frame: Vec<f64>,
    /// `None` when no pixel stays unchanged in the reference (or one frame only).
    pub flicker_pct: Option<f64>,
    pub flicker_pixels: u64,
    /// The same two scores on the `indirect` AOV alone, where the methods differ.
    pub indirect_rms_error_pct: f64,
    pub indirect_flicker_pct: Option<f64>,
    pub rays_shot_per_frame: f64,
    /// Final-gather rays traced per second of final-gathering time, per worker thread.
    pub gather_rays_per_s_per_core: Option<f64>,
    /// Median per-stage seconds (the paper's Table 1 rows).
    pub table1_s: Table1,
    pub caches_per_frame: f64,
    pub photons_per_frame: f64,
    /// `anchors` after its first frame: median share of all strata re-traced, in %.
    pub reshot_pct: Option<f64>,
    /// `anchors` after its first frame: median visibility seconds per 10 000 records.
    pub visibility_s_per_10k_caches: Option<f64>,
}

/// Median seconds per stage.
#[derive(Debug, Clone, Serialize)]
pub struct Table1 {
    pub photon_tracing: f64,
    pub irradiance_estimation: f64,
    pub final_gathering: f64,
    pub cache_interpolation: f64,
    pub direct_lighting: f64,
    pub visibility: f64,
    pub total: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub job: String,
    pub frames: [i32; 2],
    pub resolution: [u32; 2],
    pub reference: String,
    pub reference_seconds_per_frame_median: f64,
    /// The reference's own flicker (its noise) on the same pixels.
    pub reference_flicker_pct: Option<f64>,
    pub reference_indirect_flicker_pct: Option<f64>,
    pub results: Vec<Score>,
}

struct Run {
    images: Vec<FrameImage>,
    stats: Vec<FrameStats>,
    strata_per_record: f64,
}

fn run(job: &Job, scene: &Scene, v: &Variant) -> Result<Run> {
    let mut job = job.clone();
    job.method.name = v.method;
    job.method.preset = v.preset;
    if let Some(s) = &v.setting {
        s.apply(&mut job);
    }
    let resources = pipeline::new_resources(&job, scene)?;
    let mut state = FrameState::default();
    let mut images = Vec::new();
    let mut stats = Vec::new();
    for f in job.frames.start..=job.frames.end {
        let t = Instant::now();
        let mut s = pipeline::new_stats(&job, f);
        let img = pipeline::render_frame(&job, scene, &resources, &mut state, f, &mut s)?;
        s.timings_s.total = t.elapsed().as_secs_f64();
        images.push(img);
        stats.push(s);
    }
    let [m, n] = job.method.params().cache.strata;
    Ok(Run {
        images,
        stats,
        strata_per_record: (m * n) as f64,
    })
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Which AOV a score reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Aov {
    Beauty,
    Indirect,
}

fn rgb(img: &FrameImage, aov: Aov, i: usize) -> [f32; 3] {
    match aov {
        Aov::Beauty => [img.beauty[i][0], img.beauty[i][1], img.beauty[i][2]],
        Aov::Indirect => img.indirect[i],
    }
}

/// `100·sqrt(Σ(a − r)² / Σ r²)` over the RGB of `aov`.
pub fn rms_error_pct(a: &FrameImage, r: &FrameImage, aov: Aov) -> f64 {
    let (mut d, mut n) = (0.0f64, 0.0f64);
    for i in 0..r.beauty.len() {
        let (p, q) = (rgb(a, aov, i), rgb(r, aov, i));
        for k in 0..3 {
            d += (p[k] as f64 - q[k] as f64).powi(2);
            n += (q[k] as f64).powi(2);
        }
    }
    if n > 0.0 { 100.0 * (d / n).sqrt() } else { 0.0 }
}

/// Flicker of `run` over pixels where the reference keeps its depth and coverage between
/// consecutive frames: (flicker %, pixels compared).
pub fn flicker_pct(run: &[FrameImage], reference: &[FrameImage], aov: Aov) -> (Option<f64>, u64) {
    let (mut change, mut level, mut count) = (0.0f64, 0.0f64, 0u64);
    for f in 1..run.len().min(reference.len()) {
        let (r0, r1) = (&reference[f - 1], &reference[f]);
        for i in 0..r1.beauty.len() {
            // Depth is the nearest of the pixel's jittered samples, which move from frame to
            // frame: 1 % tells an unchanged surface from a moving object.
            let same_z = (r0.depth[i] - r1.depth[i]).abs() <= 1e-2 * r1.depth[i].abs().max(1e-30);
            if !same_z || r0.beauty[i][3] != r1.beauty[i][3] || r1.beauty[i][3] == 0.0 {
                continue;
            }
            let (m0, m1, r) = (
                rgb(&run[f - 1], aov, i),
                rgb(&run[f], aov, i),
                rgb(r1, aov, i),
            );
            for k in 0..3 {
                change += (m1[k] as f64 - m0[k] as f64).abs();
                level += r[k] as f64;
            }
            count += 1;
        }
    }
    (
        (count > 0 && level > 0.0).then(|| 100.0 * change / level),
        count,
    )
}

/// Renders the reference and every variant over the job's frames and scores them.
pub fn compare(
    job: &Job,
    scene: &Scene,
    variants: &[Variant],
    reference: &Variant,
) -> Result<Report> {
    let reference_run = run(job, scene, reference)?;
    let (ref_flicker, _) = flicker_pct(&reference_run.images, &reference_run.images, Aov::Beauty);
    let (ref_ind_flicker, _) =
        flicker_pct(&reference_run.images, &reference_run.images, Aov::Indirect);
    let mut results = Vec::new();
    for v in variants {
        let r = run(job, scene, v)?;
        let per_frame: Vec<f64> = r
            .images
            .iter()
            .zip(&reference_run.images)
            .map(|(a, b)| rms_error_pct(a, b, Aov::Beauty))
            .collect();
        let indirect: Vec<f64> = r
            .images
            .iter()
            .zip(&reference_run.images)
            .map(|(a, b)| rms_error_pct(a, b, Aov::Indirect))
            .collect();
        let (flicker, pixels) = flicker_pct(&r.images, &reference_run.images, Aov::Beauty);
        let (ind_flicker, _) = flicker_pct(&r.images, &reference_run.images, Aov::Indirect);
        let n = r.stats.len().max(1) as f64;
        let med = |f: &dyn Fn(&FrameStats) -> f64| median(r.stats.iter().map(f).collect());
        let strata_per_record = r.strata_per_record;
        // Anchors in steady state: every frame after the first.
        let steady = |f: &dyn Fn(&FrameStats) -> f64| {
            (v.method == Method::Anchors && r.stats.len() > 1)
                .then(|| median(r.stats[1..].iter().map(f).collect()))
        };
        results.push(Score {
            label: v.label(),
            method: v.method.name(),
            preset: preset_name(v.preset),
            seconds_per_frame_median: median(r.stats.iter().map(|s| s.timings_s.total).collect()),
            rms_error_pct: per_frame.iter().sum::<f64>() / per_frame.len().max(1) as f64,
            rms_error_pct_per_frame: per_frame,
            flicker_pct: flicker,
            flicker_pixels: pixels,
            indirect_rms_error_pct: indirect.iter().sum::<f64>() / indirect.len().max(1) as f64,
            indirect_flicker_pct: ind_flicker,
            rays_shot_per_frame: r
                .stats
                .iter()
                .map(|s| s.counts.rays_shot as f64)
                .sum::<f64>()
                / n,
            gather_rays_per_s_per_core: {
                let (rays, secs) = r.stats.iter().fold((0.0, 0.0), |(a, b), s| {
                    (
                        a + s.counts.rays_shot as f64,
                        b + s.timings_s.final_gathering,
                    )
                });
                (secs > 0.0).then(|| rays / secs / rayon::current_num_threads() as f64)
            },
            table1_s: Table1 {
                photon_tracing: med(&|s| s.timings_s.photon_tracing),
                irradiance_estimation: med(&|s| s.timings_s.irradiance_estimation),
                final_gathering: med(&|s| s.timings_s.final_gathering),
                cache_interpolation: med(&|s| s.timings_s.cache_interpolation),
                direct_lighting: med(&|s| s.timings_s.direct_lighting),
                visibility: med(&|s| s.timings_s.visibility),
                total: med(&|s| s.timings_s.total),
            },
            reshot_pct: steady(&|s| {
                let strata = s.counts.caches as f64 * strata_per_record;
                100.0 * s.counts.rays_reshot as f64 / strata.max(1.0)
            }),
            visibility_s_per_10k_caches: steady(&|s| {
                s.timings_s.visibility / (s.counts.caches as f64).max(1.0) * 1e4
            }),
            caches_per_frame: r.stats.iter().map(|s| s.counts.caches as f64).sum::<f64>() / n,
            photons_per_frame: r.stats.iter().map(|s| s.counts.photons as f64).sum::<f64>() / n,
        });
    }
    Ok(Report {
        job: job.path.display().to_string(),
        frames: [job.frames.start, job.frames.end],
        resolution: [job.width, job.height],
        reference: reference.label(),
        reference_seconds_per_frame_median: median(
            reference_run
                .stats
                .iter()
                .map(|s| s.timings_s.total)
                .collect(),
        ),
        reference_flicker_pct: ref_flicker,
        reference_indirect_flicker_pct: ref_ind_flicker,
        results,
    })
}

/// The table printed on stdout.
pub fn table(r: &Report) -> String {
    let mut s = format!(
        "reference {} ({:.2} s/frame, own flicker {} beauty, {} indirect), frames {}..{}, {}x{}\n",
        r.reference,
        r.reference_seconds_per_frame_median,
        fmt_opt(r.reference_flicker_pct),
        fmt_opt(r.reference_indirect_flicker_pct),
        r.frames[0],
        r.frames[1],
        r.resolution[0],
        r.resolution[1]
    );
    s += &format!(
        "{:<40} {:>9} {:>9} {:>9} {:>9} {:>9} {:>12} {:>8} {:>9}\n",
        "method/preset",
        "s/frame",
        "RMS err%",
        "flicker%",
        "ind.err%",
        "ind.flk%",
        "gather rays",
        "caches",
        "photons"
    );
    for x in &r.results {
        s += &format!(
            "{:<40} {:>9.3} {:>9.2} {:>9} {:>9.2} {:>9} {:>12.0} {:>8.0} {:>9.0}\n",
            x.label,
            x.seconds_per_frame_median,
            x.rms_error_pct,
            fmt_opt(x.flicker_pct),
            x.indirect_rms_error_pct,
            fmt_opt(x.indirect_flicker_pct),
            x.rays_shot_per_frame,
            x.caches_per_frame,
            x.photons_per_frame
        );
    }
    s += &format!(
        "\nmedian seconds per stage (paper Table 1), {} worker threads\n{:<40} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>14} {:>8} {:>8}\n",
        rayon::current_num_threads(),
        "method/preset",
        "photons",
        "irr.est",
        "gather",
        "interp",
        "direct",
        "visib.",
        "total",
        "gather rays/s/core",
        "reshot%",
        "vis/10k"
    );
    for x in &r.results {
        let t = &x.table1_s;
        s += &format!(
            "{:<40} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>14} {:>8} {:>8}\n",
            x.label,
            t.photon_tracing,
            t.irradiance_estimation,
            t.final_gathering,
            t.cache_interpolation,
            t.direct_lighting,
            t.visibility,
            t.total,
            x.gather_rays_per_s_per_core
                .map_or("n/a".into(), |v| format!("{:.2} M", v / 1e6)),
            x.reshot_pct.map_or("n/a".into(), |v| format!("{v:.2}")),
            x.visibility_s_per_10k_caches
                .map_or("n/a".into(), |v| format!("{v:.3}"))
        );
    }
    s
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or("n/a".into(), |v| format!("{v:.3}"))
}

/// Writes `compare.json` and `compare.png` into `dir`.
pub fn write(dir: &Path, r: &Report) -> Result<()> {
    output::check_output_dir(dir)?;
    output::write_json(&dir.join("compare.json"), r)?;
    let png = plot(r);
    output::write_atomic(&dir.join("compare.png"), |tmp| {
        png.save_with_format(tmp, image::ImageFormat::Png)
            .map_err(|e| e.to_string())
    })
    .map_err(|e| Error::Render(e.to_string()))
}

const COLOURS: [[u8; 3]; 6] = [
    [220, 50, 47],
    [38, 139, 210],
    [133, 153, 0],
    [211, 54, 130],
    [181, 137, 0],
    [42, 161, 152],
];

fn text(img: &mut image::RgbImage, x: i32, y: i32, s: &str, c: [u8; 3]) {
    for (i, ch) in s.chars().enumerate() {
        let glyph = font8x8::legacy::BASIC_LEGACY[(ch as usize).min(127)];
        for (row, bits) in glyph.iter().enumerate() {
            for col in 0..8 {
                if bits >> col & 1 == 1 {
                    let (px, py) = (x + 8 * i as i32 + col, y + row as i32);
                    if px >= 0 && py >= 0 && (px as u32) < img.width() && (py as u32) < img.height()
                    {
                        img.put_pixel(px as u32, py as u32, image::Rgb(c));
                    }
                }
            }
        }
    }
}

/// Error (%, linear) against seconds per frame (log axis), one labelled point per variant.
pub fn plot(r: &Report) -> image::RgbImage {
    let (w, h) = (720u32, 480u32);
    let (left, right, top, bottom) = (70i32, 20i32, 30i32, 50i32);
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let xs: Vec<f64> = r
        .results
        .iter()
        .map(|x| x.seconds_per_frame_median.max(1e-6).log10())
        .collect();
    let ys: Vec<f64> = r.results.iter().map(|x| x.rms_error_pct).collect();
    let (x0, x1) = xs
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let (x0, x1) = if x0 >= x1 {
        (x0 - 0.5, x0 + 0.5)
    } else {
        (x0 - 0.1 * (x1 - x0), x1 + 0.1 * (x1 - x0))
    };
    let y1 = ys.iter().fold(0.0f64, |a, &v| a.max(v)).max(1e-3) * 1.15;
    let px = |x: f64| left + ((x - x0) / (x1 - x0) * (w as i32 - left - right) as f64) as i32;
    let py = |y: f64| h as i32 - bottom - (y / y1 * (h as i32 - top - bottom) as f64) as i32;
    let grey = image::Rgb([60, 60, 60]);
    for x in left..w as i32 - right {
        img.put_pixel(x as u32, (h as i32 - bottom) as u32, grey);
    }
    for y in top..h as i32 - bottom {
        img.put_pixel(left as u32, y as u32, grey);
    }
    text(
        &mut img,
        left,
        8,
        &format!(
            "RMS error % vs {} (y) against seconds per frame (x, log)",
            r.reference
        ),
        [0, 0, 0],
    );
    for t in 0..=4 {
        let y = y1 * t as f64 / 4.0;
        text(&mut img, 4, py(y) - 4, &format!("{y:.2}"), [0, 0, 0]);
    }
    for t in 0..=3 {
        let x = x0 + (x1 - x0) * t as f64 / 3.0;
        text(
            &mut img,
            px(x) - 16,
            h as i32 - bottom + 8,
            &format!("{:.3}", 10f64.powf(x)),
            [0, 0, 0],
        );
    }
    for (i, s) in r.results.iter().enumerate() {
        let c = COLOURS[i % COLOURS.len()];
        let (cx, cy) = (px(xs[i]), py(ys[i]));
        for dy in -3..=3 {
            for dx in -3..=3 {
                let (x, y) = (cx + dx, cy + dy);
                if x >= 0 && y >= 0 && (x as u32) < w && (y as u32) < h {
                    img.put_pixel(x as u32, y as u32, image::Rgb(c));
                }
            }
        }
        // Legend, top right: colour, label, error.
        let ly = top + 6 + 12 * i as i32;
        let lx = w as i32 - right - 8 * 44;
        for dy in 0..7 {
            for dx in 0..7 {
                img.put_pixel((lx + dx) as u32, (ly + dy) as u32, image::Rgb(c));
            }
        }
        text(
            &mut img,
            lx + 10,
            ly,
            &format!("{} {:.2}%", s.label, s.rms_error_pct),
            c,
        );
    }
    img
}
