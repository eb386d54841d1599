//! Statistical image comparison, as Mitsuba 3's render tests do it: an image is compared
//! with a reference through a z-test over tiles, not by exact equality or a pinned RMS.
//!
//! Design:
//! - **Variance beside the mean.** Every rendered [`FrameImage`] carries the variance of each
//!   pixel's mean ([`FrameImage::variance`]: the sample variance of its camera samples over
//!   their number). The path-traced reference is rendered with many samples, so its variance
//!   is small but not zero; the tested image is itself stochastic (direct light by shadow
//!   rays, jittered camera samples), so its variance counts too: the test is Welch's, with
//!   both images' variances in the denominator.
//! - **Tiles.** Pixels are averaged over square tiles (`tile` × `tile`): a tile's variance
//!   is the sum of its pixels' variances over the number of pixels squared (pixels use
//!   independent sample streams). Tiles are the unit of the cached methods' error (a cache
//!   record spans several pixels), and averaging makes the tile means close to normal.
//! - **Multiple comparisons.** Every tile and channel (and every frame, when several are
//!   tested together) is one test; the whole comparison fails with probability `alpha` when
//!   the images agree in expectation, by Šidák's correction: each test is run at
//!   `1 − (1 − alpha)^(1/m)`, two-sided.
//! - **Bias allowance.** Photon mapping and irradiance caching are biased (density estimation
//!   blurs the irradiance over its k photons, the cache interpolates, anchors reuse L_i over
//!   D_max), and their error is correlated over many pixels, which no per-pixel variance
//!   sees. A biased method is therefore tested with a stated allowance `bias`, relative to
//!   the reference tile's value (with `floor` × the reference's image mean as the smallest
//!   value it is relative to, so that dark tiles do not demand an impossibly small absolute
//!   error). The allowance enters the denominator as a variance: a tile fails when
//!   `|test − ref| > sqrt((z·σ)² + (bias·max(|ref|, floor·mean))²)`, z the corrected
//!   critical value, σ² the sum of both tiles' variances. Noise-free, a tile fails exactly
//!   when its relative error exceeds `bias`; where noise dominates, the test is Welch's.
//!   For an unbiased method (the path tracer against itself at another seed) `bias` is 0.
//! - **Failure images.** On failure the reference, the tested image (EXR with every AOV, and
//!   PNG previews) and the z-map (`zmap.png`: per tile, blue where the image is darker than
//!   the reference, red where brighter, full intensity at the critical value; `zmap.exr` with
//!   the signed z of the worst channel per pixel) are written to `$ANCHORAGE_TEST_OUT/NAME`,
//!   or `target/test-out/NAME`, and the message names that directory.
//!
//! Everything is deterministic: renders are pure functions of the seed and frame, so a test
//! that passes passes every time; `alpha` bounds how likely a correct renderer at another
//! seed would be to fail it.

use std::path::PathBuf;

use anchorage::compare::Aov;
use anchorage::integrator::FrameImage;

/// The settings of one comparison.
#[derive(Debug, Clone, Copy)]
pub struct Welch {
    /// Tile side in pixels (1: per-pixel test).
    pub tile: u32,
    /// Probability that the whole comparison fails for images that agree in expectation.
    pub alpha: f64,
    /// Bias allowance relative to the reference tile (0 for an unbiased method).
    pub bias: f64,
    /// The smallest value `bias` is relative to, as a fraction of the reference's mean over
    /// the image and channels.
    pub floor: f64,
}

impl Welch {
    /// An unbiased comparison, per tile.
    pub fn unbiased(tile: u32) -> Welch {
        Welch {
            tile,
            alpha: 0.01,
            bias: 0.0,
            floor: 0.0,
        }
    }

    /// A comparison with a bias allowance relative to the reference tile, at least relative
    /// to a fifth of the image's mean.
    pub fn biased(tile: u32, bias: f64) -> Welch {
        Welch {
            tile,
            alpha: 0.01,
            bias,
            floor: 0.2,
        }
    }
}

/// One tile's result.
#[derive(Debug, Clone, Copy)]
pub struct TileZ {
    pub tx: u32,
    pub ty: u32,
    pub channel: usize,
    pub test: f64,
    pub reference: f64,
    /// (test − reference) over the denominator (noise and allowance).
    pub z: f64,
}

/// The outcome of a comparison over one or more frames.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The corrected critical value.
    pub z_crit: f64,
    /// The smallest bias allowance with which every tile would pass (for the messages: how
    /// far a comparison is from its allowance).
    pub needed_bias: f64,
    /// Per frame, every tile and channel.
    pub tiles: Vec<Vec<TileZ>>,
}

impl Outcome {
    /// The tiles over the critical value.
    pub fn failures(&self) -> Vec<(usize, TileZ)> {
        self.tiles
            .iter()
            .enumerate()
            .flat_map(|(f, t)| t.iter().map(move |z| (f, *z)))
            .filter(|(_, t)| t.z.abs() > self.z_crit)
            .collect()
    }

    /// The largest |z| relative to the critical value (< 1: passes).
    pub fn worst(&self) -> f64 {
        self.tiles
            .iter()
            .flatten()
            .map(|t| t.z.abs() / self.z_crit)
            .fold(0.0, f64::max)
    }
}

fn values(img: &FrameImage, aov: Aov, i: usize) -> ([f64; 3], [f64; 3]) {
    let (v, var) = match aov {
        Aov::Beauty => (
            [img.beauty[i][0], img.beauty[i][1], img.beauty[i][2]],
            img.variance.beauty[i],
        ),
        Aov::Indirect => (img.indirect[i], img.variance.indirect[i]),
    };
    (v.map(f64::from), var.map(f64::from))
}

/// Tile means and variances of the means, per channel: `(tiles_x, tiles_y, [(mean, var)])`.
fn tiles(img: &FrameImage, aov: Aov, tile: u32) -> (u32, u32, Vec<[(f64, f64); 3]>) {
    let (tx, ty) = (img.width.div_ceil(tile), img.height.div_ceil(tile));
    let mut out = vec![[(0.0, 0.0); 3]; (tx * ty) as usize];
    let mut count = vec![0.0f64; out.len()];
    for y in 0..img.height {
        for x in 0..img.width {
            let t = ((y / tile) * tx + x / tile) as usize;
            let (v, var) = values(img, aov, (y * img.width + x) as usize);
            for c in 0..3 {
                out[t][c].0 += v[c];
                out[t][c].1 += var[c];
            }
            count[t] += 1.0;
        }
    }
    for (o, n) in out.iter_mut().zip(count) {
        for c in o.iter_mut() {
            *c = (c.0 / n, c.1 / (n * n));
        }
    }
    (tx, ty, out)
}

/// Compares `test[f]` with `reference[f]` for every frame `f` on `aov`, with the Šidák
/// correction over all frames, tiles and channels.
pub fn compare(test: &[&FrameImage], reference: &[&FrameImage], aov: Aov, w: Welch) -> Outcome {
    assert_eq!(test.len(), reference.len());
    // Per frame, per tile and channel: the tile, both means, the noise variance of their
    // difference and the bias allowance.
    let mut all: Vec<Vec<(TileZ, f64, f64)>> = Vec::new();
    for (a, r) in test.iter().zip(reference) {
        assert_eq!(
            (a.width, a.height),
            (r.width, r.height),
            "image sizes differ"
        );
        let (tx, _, ta) = tiles(a, aov, w.tile);
        let (_, _, tr) = tiles(r, aov, w.tile);
        let mean = tr.iter().flatten().map(|c| c.0.abs()).sum::<f64>() / (3 * tr.len()) as f64;
        let mut frame = Vec::with_capacity(3 * ta.len());
        for (t, (ca, cr)) in ta.iter().zip(&tr).enumerate() {
            for c in 0..3 {
                let tile = TileZ {
                    tx: t as u32 % tx,
                    ty: t as u32 / tx,
                    channel: c,
                    test: ca[c].0,
                    reference: cr[c].0,
                    z: 0.0,
                };
                let allowance = w.bias * cr[c].0.abs().max(w.floor * mean);
                frame.push((tile, ca[c].1 + cr[c].1, allowance));
            }
        }
        all.push(frame);
    }
    let z_crit = sidak_z(w.alpha, all.iter().map(Vec::len).sum());
    let needed_bias = all
        .iter()
        .flatten()
        .map(|(t, var, allowance)| {
            let excess = ((t.test - t.reference).powi(2) - z_crit * z_crit * var).max(0.0);
            let base = if w.bias > 0.0 {
                allowance / w.bias
            } else {
                t.reference.abs()
            };
            excess.sqrt() / base.max(1e-300)
        })
        .fold(0.0, f64::max);
    let tiles = all
        .into_iter()
        .map(|frame| {
            frame
                .into_iter()
                .map(|(mut t, var, allowance)| {
                    let denom = (var + (allowance / z_crit).powi(2)).sqrt();
                    let d = t.test - t.reference;
                    t.z = if denom > 0.0 {
                        d / denom
                    } else if d == 0.0 {
                        0.0
                    } else {
                        f64::INFINITY.copysign(d)
                    };
                    t
                })
                .collect()
        })
        .collect();
    Outcome {
        z_crit,
        needed_bias,
        tiles,
    }
}

/// Asserts that `test` agrees with `reference` on `aov` (see the module doc); on failure
/// writes the failure images under [`failure_dir`]`(name)` and names it.
pub fn assert_agrees(
    name: &str,
    test: &[&FrameImage],
    reference: &[&FrameImage],
    aov: Aov,
    w: Welch,
) -> Outcome {
    let out = compare(test, reference, aov, w);
    eprintln!(
        "{name}: worst tile at {:.2} of the critical z {:.2} ({} tests; passes with a bias \
         allowance of {:.3} or more)",
        out.worst(),
        out.z_crit,
        out.tiles.iter().map(Vec::len).sum::<usize>(),
        out.needed_bias
    );
    let failures = out.failures();
    if !failures.is_empty() {
        let dir = write_failure(name, test, reference, &out, w.tile);
        let mut shown: Vec<String> = failures
            .iter()
            .take(8)
            .map(|(f, t)| {
                format!(
                    "frame #{f} tile ({}, {}) channel {}: {:.5} vs reference {:.5}, z {:.1}",
                    t.tx, t.ty, t.channel, t.test, t.reference, t.z
                )
            })
            .collect();
        if failures.len() > 8 {
            shown.push(format!("… {} more", failures.len() - 8));
        }
        panic!(
            "{name}: {} of {} tile tests beyond z = {:.2} (alpha {}, Šidák; bias allowance {}, \
             tile {} px) on {aov:?}:\n  {}\nreference, test and z-map written to {}",
            failures.len(),
            out.tiles.iter().map(Vec::len).sum::<usize>(),
            out.z_crit,
            w.alpha,
            w.bias,
            w.tile,
            shown.join("\n  "),
            dir.display()
        );
    }
    out
}

/// Where a failing comparison writes its images: `$ANCHORAGE_TEST_OUT/NAME`, else
/// `target/test-out/NAME`.
pub fn failure_dir(name: &str) -> PathBuf {
    let base = std::env::var_os("ANCHORAGE_TEST_OUT")
        .map(PathBuf::from)
        .unwrap_or_else(|| super::common::root().join("target/test-out"));
    base.join(name)
}

fn write_failure(
    name: &str,
    test: &[&FrameImage],
    reference: &[&FrameImage],
    out: &Outcome,
    tile: u32,
) -> PathBuf {
    use anchorage::output::{write_exr, write_png};
    let dir = failure_dir(name);
    let _ = std::fs::create_dir_all(&dir);
    for (f, ((a, r), tz)) in test.iter().zip(reference).zip(&out.tiles).enumerate() {
        let _ = write_exr(&dir.join(format!("reference.{f}.exr")), r);
        let _ = write_exr(&dir.join(format!("test.{f}.exr")), a);
        let _ = write_png(&dir.join(format!("reference.{f}.png")), r);
        let _ = write_png(&dir.join(format!("test.{f}.png")), a);
        // Signed z of the worst channel per tile, spread over its pixels.
        let tx = a.width.div_ceil(tile);
        let mut worst = vec![0.0f64; (tx * a.height.div_ceil(tile)) as usize];
        for t in tz {
            let i = (t.ty * tx + t.tx) as usize;
            if t.z.abs() > worst[i].abs() {
                worst[i] = t.z;
            }
        }
        let at = |x: u32, y: u32| worst[((y / tile) * tx + x / tile) as usize];
        let mut png = image::RgbImage::new(a.width, a.height);
        for (x, y, p) in png.enumerate_pixels_mut() {
            let z = (at(x, y) / out.z_crit).clamp(-1.0, 1.0);
            let v = (z.abs() * 255.0).round() as u8;
            *p = if z >= 0.0 {
                image::Rgb([v, 0, 0])
            } else {
                image::Rgb([0, 0, v])
            };
        }
        let _ = png.save(dir.join(format!("zmap.{f}.png")));
        let zmap = FrameImage {
            width: a.width,
            height: a.height,
            beauty: (0..a.height)
                .flat_map(|y| (0..a.width).map(move |x| (x, y)))
                .map(|(x, y)| {
                    let z = at(x, y) as f32;
                    [z, z, z, 1.0]
                })
                .collect(),
            direct: vec![[0.0; 3]; (a.width * a.height) as usize],
            indirect: vec![[0.0; 3]; (a.width * a.height) as usize],
            depth: vec![0.0; (a.width * a.height) as usize],
            ..FrameImage::default()
        };
        let _ = write_exr(&dir.join(format!("zmap.{f}.exr")), &zmap);
    }
    dir
}

/// The two-sided critical value of the standard normal for `m` tests whose union has
/// probability `alpha` (Šidák: each at `1 − (1 − alpha)^(1/m)`).
pub fn sidak_z(alpha: f64, m: usize) -> f64 {
    let per_test = -f64::exp_m1(f64::ln_1p(-alpha) / m.max(1) as f64);
    // Solve erfc(z / √2) = per_test by bisection; erfc is monotone.
    let (mut lo, mut hi) = (0.0f64, 40.0f64);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if erfc(mid / std::f64::consts::SQRT_2) > per_test {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The complementary error function (Numerical Recipes' Chebyshev fit, relative error below
/// 1.2e-7 everywhere).
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let r = t
        * (-z * z - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87
                                        + t * (-0.822_152_23 + t * 0.170_872_77)))))))))
            .exp();
    if x >= 0.0 { r } else { 2.0 - r }
}

/// The machinery itself: the critical values are right, a copy of an image passes, a
/// brightened tile fails and writes its failure images, and noise within the variance
/// passes.
#[test]
fn statistical_comparison_machinery() {
    // Φ⁻¹(0.975) = 1.95996; Šidák for 1000 tests at 0.01: per test 1.005e-5 → 4.417.
    assert!(
        (sidak_z(0.05, 1) - 1.959_96).abs() < 1e-3,
        "{}",
        sidak_z(0.05, 1)
    );
    assert!(
        (sidak_z(0.01, 1000) - 4.417).abs() < 2e-3,
        "{}",
        sidak_z(0.01, 1000)
    );
    let n = 16 * 16;
    let img = |v: f32, var: f32| FrameImage {
        width: 16,
        height: 16,
        beauty: vec![[v, v, v, 1.0]; n],
        direct: vec![[0.0; 3]; n],
        indirect: vec![[v; 3]; n],
        depth: vec![1.0; n],
        variance: anchorage::integrator::PixelVariance {
            beauty: vec![[var; 3]; n],
            indirect: vec![[var; 3]; n],
        },
        ..FrameImage::default()
    };
    let r = img(1.0, 0.01);
    // A tile mean of 64 pixels has variance 2·0.01/64: σ = 0.0177; z_crit for 48 tests ≈ 3.5.
    assert!(
        compare(
            &[&img(1.05, 0.01)],
            &[&r],
            Aov::Indirect,
            Welch::unbiased(8)
        )
        .worst()
            < 1.0
    );
    assert!(compare(&[&img(1.1, 0.01)], &[&r], Aov::Indirect, Welch::unbiased(8)).worst() > 1.0);
    // The allowance: noise-free, a tile fails when its relative error exceeds it.
    let (r0, a0) = (img(1.0, 0.0), img(1.04, 0.0));
    assert!(compare(&[&a0], &[&r0], Aov::Indirect, Welch::biased(8, 0.05)).worst() < 1.0);
    assert!(compare(&[&a0], &[&r0], Aov::Indirect, Welch::biased(8, 0.03)).worst() > 1.0);
    // One bright tile fails, with the failure images written.
    let mut bad = img(1.0, 0.01);
    for y in 8..16 {
        for x in 0..8 {
            bad.indirect[y * 16 + x] = [1.5; 3];
        }
    }
    let o = compare(&[&bad], &[&r], Aov::Indirect, Welch::unbiased(8));
    let f = o.failures();
    assert_eq!(f.len(), 3, "one tile, three channels");
    assert_eq!((f[0].1.tx, f[0].1.ty), (0, 1));
    let out = write_failure("machinery-self-test", &[&bad], &[&r], &o, 8);
    for file in ["reference.0.exr", "test.0.exr", "zmap.0.png", "zmap.0.exr"] {
        assert!(
            out.join(file).is_file(),
            "{file} written to {}",
            out.display()
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// The variance the film accumulates is the right size: the path tracer at another seed
/// agrees with itself per pixel and per tile (no bias allowance), and the same image 10 %
/// brighter fails per tile.
#[test]
fn path_tracer_agrees_with_itself_at_another_seed() {
    let job = |seed: u32| {
        super::common::job_from_json(
            &super::common::example_job(),
            &format!(
                r#"{{"scene":[{{"path":"room.gltf"}}],"camera":{{"position":[0,1.5,6.5],"look_at":[0,1.3,0],"yfov_deg":38}},
                "resolution":[32,24],"frames":{{"start":0,"end":48}},"seed":{seed},
                "method":{{"name":"path-trace","path_samples":64}}}}"#
            ),
        )
        .unwrap()
    };
    let a = super::common::render(&job(0), 12);
    let b = super::common::render(&job(1), 12);
    assert!(a.beauty != b.beauty, "another seed, another image");
    for aov in [Aov::Beauty, Aov::Indirect] {
        assert_agrees("pt-seeds-per-pixel", &[&a], &[&b], aov, Welch::unbiased(1));
        assert_agrees("pt-seeds-per-tile", &[&a], &[&b], aov, Welch::unbiased(4));
    }
    let mut brighter = a.clone();
    for p in &mut brighter.beauty {
        for c in &mut p[..3] {
            *c *= 1.1;
        }
    }
    let out = compare(&[&brighter], &[&b], Aov::Beauty, Welch::unbiased(4));
    assert!(out.worst() > 1.0, "10 % brighter passes: {}", out.worst());
}
