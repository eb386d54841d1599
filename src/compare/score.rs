//! Scores a variant's run against the reference's: RMS relative error and temporal flicker,
//! on the beauty and on the `indirect` AOV alone (where the methods differ), and the
//! per-stage seconds of the paper's Table 1.

use serde::Serialize;

use super::Variant;
use super::run::Run;
use crate::integrator::FrameImage;
use crate::job::{Job, Method};
use crate::stats::FrameStats;

/// Scores of one variant.
#[derive(Debug, Clone, Serialize)]
pub struct Score {
    pub label: String,
    pub method: String,
    pub preset: String,
    pub seconds_per_frame_median: f64,
    pub rms_error_pct: f64,
    pub rms_error_pct_per_frame: Vec<f64>,
    /// `None` when no pixel stays unchanged in the reference (or one frame only).
    pub flicker_pct: Option<f64>,
    pub flicker_pixels: u64,
    /// The same two scores on the `indirect` AOV alone, where the methods differ.
    pub indirect_rms_error_pct: f64,
    pub indirect_flicker_pct: Option<f64>,
    /// The two RMS errors less the reference's own noise ([`rms_error_pct_denoised`]): the
    /// error against the image the reference converges to. `None` where the reference kept
    /// no per-pixel variance.
    pub rms_error_pct_denoised: Option<f64>,
    pub indirect_rms_error_pct_denoised: Option<f64>,
    pub rays_shot_per_frame: f64,
    /// Final-gather rays traced per second of final-gathering time, per worker thread.
    pub gather_rays_per_s_per_core: Option<f64>,
    /// Median per-stage seconds (the paper's Table 1 rows).
    pub table1_s: Table1,
    pub caches_per_frame: f64,
    pub photons_per_frame: f64,
    /// `anchors` after its first frame: median share of all strata re-traced, in %.
    pub reshot_pct: Option<f64>,
    /// `anchors` after its first frame: median share of all strata the visibility test
    /// flagged (§3.2), in %: the re-shot ones are those of them whose own ray meets a
    /// dynamic prim, and those whose ray met one last frame.
    pub flagged_pct: Option<f64>,
    /// `anchors` after its first frame: median visibility seconds per 10 000 records.
    pub visibility_s_per_10k_caches: Option<f64>,
}

/// Median seconds per stage (each a median over frames, of the stats' `timings_s`).
#[derive(Debug, Clone, Serialize)]
pub struct Table1 {
    pub photon_tracing: f64,
    pub irradiance_estimation: f64,
    /// `anchors`: linking gather hits to anchors (the stats' `attachment`).
    pub attachment: f64,
    /// Integrating records' strata (the stats' `integration`).
    pub integration: f64,
    pub final_gathering: f64,
    pub cache_interpolation: f64,
    pub direct_lighting: f64,
    pub visibility: f64,
    /// Deciding where records go and the cache's bookkeeping (the stats' `placement` and
    /// `upkeep`).
    pub placement: f64,
    pub upkeep: f64,
    /// Everything else of a frame: `total` less the rows above (scene evaluation, BVHs,
    /// depth maps, the shading pass's camera rays (`camera_rays`), output, what little lies
    /// between the timed spans).
    pub other: f64,
    pub total: f64,
}

/// Everything `compare` measured: the tables print it, `compare.json` is it.
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

/// [`rms_error_pct`] against the image the reference `r` converges to, estimated from `r` and
/// its per-pixel variance of the mean σ²: E[(a − r)²] = (a − E r)² + σ² for a reference
/// independent of `a`, so `100·sqrt((Σ(a − r)² − Σσ²) / (Σr² − Σσ²))` (each sum clamped at
/// zero). The variance is that of independent samples, an upper bound in practice for the
/// reference's scrambled-QMC ones, so this reads at most the true error against the converged
/// image, and close to it when the variant's error is not far below the reference's noise.
/// `None` when the reference kept no variance.
pub fn rms_error_pct_denoised(a: &FrameImage, r: &FrameImage, aov: Aov) -> Option<f64> {
    let var = match aov {
        Aov::Beauty => &r.variance.beauty,
        Aov::Indirect => &r.variance.indirect,
    };
    if var.len() != r.beauty.len() {
        return None;
    }
    let (mut d, mut n, mut v) = (0.0f64, 0.0f64, 0.0f64);
    for (i, s2) in var.iter().enumerate() {
        let (p, q) = (rgb(a, aov, i), rgb(r, aov, i));
        for k in 0..3 {
            d += (p[k] as f64 - q[k] as f64).powi(2);
            n += (q[k] as f64).powi(2);
            v += s2[k] as f64;
        }
    }
    let n = n - v;
    Some(if n > 0.0 {
        100.0 * ((d - v).max(0.0) / n).sqrt()
    } else {
        0.0
    })
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

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Scores `r`, the run of variant `v`, against the reference's run.
pub(super) fn score(v: &Variant, r: &Run, reference: &Run) -> Score {
    let error = |aov| -> Vec<f64> {
        r.images
            .iter()
            .zip(&reference.images)
            .map(|(a, b)| rms_error_pct(a, b, aov))
            .collect()
    };
    let (per_frame, indirect) = (error(Aov::Beauty), error(Aov::Indirect));
    let denoised = |aov| -> Option<f64> {
        let e: Option<Vec<f64>> = r
            .images
            .iter()
            .zip(&reference.images)
            .map(|(a, b)| rms_error_pct_denoised(a, b, aov))
            .collect();
        e.map(|e| mean(&e))
    };
    let (flicker, pixels) = flicker_pct(&r.images, &reference.images, Aov::Beauty);
    let (ind_flicker, _) = flicker_pct(&r.images, &reference.images, Aov::Indirect);
    let n = r.stats.len().max(1) as f64;
    let med = |f: &dyn Fn(&FrameStats) -> f64| median(r.stats.iter().map(f).collect());
    let per_frame_mean = |f: &dyn Fn(&FrameStats) -> f64| r.stats.iter().map(f).sum::<f64>() / n;
    let strata_per_record = r.strata_per_record;
    // Anchors in steady state: every frame after the first.
    let steady = |f: &dyn Fn(&FrameStats) -> f64| {
        (v.method == Method::Anchors && r.stats.len() > 1)
            .then(|| median(r.stats[1..].iter().map(f).collect()))
    };
    Score {
        label: v.label(),
        method: v.method.name(),
        preset: v.preset.name(),
        seconds_per_frame_median: med(&|s| s.timings_s.total),
        rms_error_pct: mean(&per_frame),
        rms_error_pct_per_frame: per_frame,
        flicker_pct: flicker,
        flicker_pixels: pixels,
        indirect_rms_error_pct: mean(&indirect),
        indirect_flicker_pct: ind_flicker,
        rms_error_pct_denoised: denoised(Aov::Beauty),
        indirect_rms_error_pct_denoised: denoised(Aov::Indirect),
        rays_shot_per_frame: per_frame_mean(&|s| s.counts.rays_shot as f64),
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
            attachment: med(&|s| s.timings_s.attachment),
            integration: med(&|s| s.timings_s.integration),
            final_gathering: med(&|s| s.timings_s.final_gathering),
            cache_interpolation: med(&|s| s.timings_s.cache_interpolation),
            direct_lighting: med(&|s| s.timings_s.direct_lighting),
            visibility: med(&|s| s.timings_s.visibility),
            placement: med(&|s| s.timings_s.placement),
            upkeep: med(&|s| s.timings_s.upkeep),
            other: med(&|s| {
                let t = &s.timings_s;
                t.total
                    - (t.photon_tracing
                        + t.irradiance_estimation
                        + t.attachment
                        + t.integration
                        + t.final_gathering
                        + t.cache_interpolation
                        + t.direct_lighting
                        + t.visibility
                        + t.placement
                        + t.upkeep)
            }),
            total: med(&|s| s.timings_s.total),
        },
        reshot_pct: steady(&|s| {
            let strata = s.counts.caches as f64 * strata_per_record;
            100.0 * s.counts.rays_reshot as f64 / strata.max(1.0)
        }),
        flagged_pct: steady(&|s| {
            let strata = s.counts.caches as f64 * strata_per_record;
            100.0 * s.counts.strata_flagged as f64 / strata.max(1.0)
        }),
        visibility_s_per_10k_caches: steady(&|s| {
            s.timings_s.visibility / (s.counts.caches as f64).max(1.0) * 1e4
        }),
        caches_per_frame: per_frame_mean(&|s| s.counts.caches as f64),
        photons_per_frame: per_frame_mean(&|s| s.counts.photons as f64),
    }
}

/// The report of `job`: the reference's own numbers, then `results` in plan order.
pub(super) fn report(job: &Job, reference: &Variant, run: &Run, results: Vec<Score>) -> Report {
    let (ref_flicker, _) = flicker_pct(&run.images, &run.images, Aov::Beauty);
    let (ref_ind_flicker, _) = flicker_pct(&run.images, &run.images, Aov::Indirect);
    Report {
        job: job.path.display().to_string(),
        frames: [job.frames.start, job.frames.end],
        resolution: [job.width, job.height],
        reference: reference.label(),
        reference_seconds_per_frame_median: median(
            run.stats.iter().map(|s| s.timings_s.total).collect(),
        ),
        reference_flicker_pct: ref_flicker,
        reference_indirect_flicker_pct: ref_ind_flicker,
        results,
    }
}

/// A report of `n` made-up variants: three methods swept over `n / 3` photon counts.
#[cfg(test)]
pub(super) fn sample(n: usize) -> Report {
    let methods = ["anchors", "brute-force", "precomputed"];
    let results = (0..n)
        .map(|i| {
            let (method, step) = (methods[i % 3], (i / 3) as f64);
            let label = format!("{method}/production photons={}", 10_000 * (i / 3 + 1));
            Score {
                label,
                method: method.into(),
                preset: "production".into(),
                seconds_per_frame_median: 0.2 * (1.0 + step) * (1.0 + (i % 3) as f64),
                rms_error_pct: 1.9 + 0.01 * (i % 3) as f64 - 0.01 * step,
                rms_error_pct_per_frame: vec![1.9; 3],
                flicker_pct: Some(0.5),
                flicker_pixels: 700,
                indirect_rms_error_pct: 5.1 + 0.4 * (i % 3) as f64 - 0.05 * step,
                indirect_flicker_pct: None,
                rms_error_pct_denoised: Some(1.5),
                indirect_rms_error_pct_denoised: None,
                rays_shot_per_frame: 1e6,
                gather_rays_per_s_per_core: Some(2e6),
                table1_s: Table1 {
                    photon_tracing: 0.01,
                    irradiance_estimation: 0.02,
                    attachment: 0.03,
                    integration: 0.005,
                    final_gathering: 0.1,
                    cache_interpolation: 0.01,
                    direct_lighting: 0.02,
                    visibility: 0.0,
                    placement: 0.015,
                    upkeep: 0.005,
                    other: 0.02,
                    total: 0.2,
                },
                caches_per_frame: 800.0,
                photons_per_frame: 5e4,
                reshot_pct: None,
                flagged_pct: None,
                visibility_s_per_10k_caches: None,
            }
        })
        .collect();
    Report {
        job: "examples/room/compare.json".into(),
        frames: [0, 2],
        resolution: [128, 96],
        reference: "path-trace/final".into(),
        reference_seconds_per_frame_median: 12.0,
        reference_flicker_pct: Some(0.1),
        reference_indirect_flicker_pct: None,
        results,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Normal deviates from a fixed splitmix64 sequence (Box–Muller).
    fn normals(seed: u64, n: usize) -> Vec<f64> {
        let mut s = seed;
        let mut uniform = move || {
            s = s.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let (u, v) = (uniform().max(1e-300), uniform());
                (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
            })
            .collect()
    }

    fn image(values: &[f64], variance: Option<f64>) -> FrameImage {
        FrameImage {
            beauty: values.iter().map(|&v| [v as f32; 4]).collect(),
            variance: crate::integrator::film::PixelVariance {
                beauty: variance.map_or(Vec::new(), |s2| vec![[s2 as f32; 3]; values.len()]),
                indirect: Vec::new(),
            },
            ..Default::default()
        }
    }

    /// A variant 3 % off the truth with a little noise, against a reference whose noise is
    /// ten times its error: the plain RMS error reads the reference's noise, the denoised
    /// one the variant's own error against the converged image.
    #[test]
    fn the_denoised_error_reads_the_error_against_the_converged_image() {
        let n = 40_000;
        let truth: Vec<f64> = (0..n)
            .map(|i| 1.0 + 0.5 * (i as f64 * 0.01).sin())
            .collect();
        let (na, nr) = (normals(1, n), normals(2, n));
        let a: Vec<f64> = (0..n).map(|i| truth[i] * 1.03 + 0.01 * na[i]).collect();
        let sigma = 0.3;
        let r: Vec<f64> = (0..n).map(|i| truth[i] + sigma * nr[i]).collect();
        let t = image(&truth, None);
        let (ia, ir) = (image(&a, None), image(&r, Some(sigma * sigma)));
        let true_error = rms_error_pct(&ia, &t, Aov::Beauty);
        let plain = rms_error_pct(&ia, &ir, Aov::Beauty);
        let denoised = rms_error_pct_denoised(&ia, &ir, Aov::Beauty).unwrap();
        assert!(plain > 5.0 * true_error, "plain {plain} true {true_error}");
        assert!(
            (denoised - true_error).abs() < 0.1 * true_error,
            "denoised {denoised} against the converged image {true_error}"
        );
        // Without a variance there is nothing to subtract.
        assert_eq!(rms_error_pct_denoised(&ia, &t, Aov::Beauty), None);
    }
}
