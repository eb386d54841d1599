//! Ray-tracing throughput on a job's scene, on one thread: final-gather rays (1 800 a point,
//! in the cosine-distributed strata a cache record shoots) from the camera's first hits on a
//! 40 × 24 grid of the job's first frame, traced to their closest hit, then the same rays
//! cut to a tenth of the scene's radius and traced as shadow rays. For each of obvhs's
//! static-BVH presets, the closest hits are traced twice over the same BVH: through obvhs's
//! own `Bvh2::ray_traverse` (anchorage's traversal before `accel::pairs`, the watertight test
//! and the alpha test as `Accel::closest` runs them) and through `Accel::closest`, then a
//! third time four at a time, as the gather traces them: `Accel::closest4` over 2 × 2
//! neighbouring strata of a point. A digest of every hit (triangle and distance) shows which
//! agree; where the first two differ, the bench counts the ties (the same distance,
//! `Accel::closest` keeping the lower triangle index).
//!
//! `cargo bench --bench rays -- benches/sponza/job.json`
//!
//! Last, the gather's whole per-record work on the tree renders use: `gather::trace_strata`
//! from each of the grid's points (directions, the four-ray trace and every hit's surface
//! point) at the production preset's 12 × 36 strata and the final preset's 30 × 60, with a
//! digest of every hit's point, so that the stage's cost beside the trace is measured too.
//! `--gather` runs this part alone.
//!
//! With `--dump DIR` it also writes the scene's triangles, the gather rays, their 2 × 2
//! packets and `Accel::closest`'s hits to `DIR` (little-endian raw arrays; layout in
//! `benches/embree_trace.c`), for that program to trace the same rays with Embree.

use std::sync::Arc;
use std::time::Instant;

use anchorage::accel::{Accel, ShearedRay, StaticBvh, canonical, hit_distance};
use anchorage::cache::CacheParams;
use anchorage::cache::gather::{StratumRays, trace_strata};
use anchorage::geom::{Geometry, Motion};
use anchorage::scene::FrameScene;
use glam::Vec3;
use obvhs::BvhBuildParams;
use obvhs::bvh2::Bvh2;
use obvhs::ray::{Ray, RayHit};

/// The closest hit through obvhs's traversal of one set: (distance, triangle).
fn obvhs_set(bvh: &Bvh2, g: &Geometry, o: Vec3, d: Vec3, tmax: f32) -> Option<(f32, u32)> {
    let sr = ShearedRay::new(o, d);
    let mut hit = RayHit::none();
    let found = bvh.ray_traverse(
        Ray::new(o.into(), d.into(), 0.0, tmax),
        &mut hit,
        |r, id| hit_distance(&sr, g, bvh.primitive_indices[id] as usize, r.tmax),
    );
    found.then(|| (hit.t, bvh.primitive_indices[hit.primitive_id as usize]))
}

/// `Accel::closest` as it was: the static set, then the dynamic one up to the static hit.
fn obvhs_closest(fs: &FrameScene, o: Vec3, d: Vec3) -> Option<(f32, Motion, u32)> {
    let d = canonical(d);
    let mut best = None;
    if let Some(bvh) = fs.accel.statics().bvh2() {
        best = obvhs_set(bvh, &fs.static_geometry, o, d, f32::INFINITY)
            .map(|(t, i)| (t, Motion::Static, i));
    }
    if let Some(bvh) = fs.accel.dynamic_bvh2() {
        let tmax = best.map_or(f32::INFINITY, |h| h.0);
        if let Some((t, i)) = obvhs_set(bvh, &fs.dynamic_geometry, o, d, tmax) {
            best = Some((t, Motion::Dynamic, i));
        }
    }
    best
}

fn digest(h: Option<(f32, Motion, u32)>, acc: u64) -> u64 {
    let v = h.map_or(0, |(t, m, i)| {
        (u64::from(t.to_bits()) << 32 | u64::from(i)) ^ (m == Motion::Dynamic) as u64
    });
    mix(acc, v)
}

/// `acc` with the word `v` folded in (the digests' step).
fn mix(acc: u64, v: u64) -> u64 {
    acc.wrapping_mul(0x100_0000_01b3).wrapping_add(v)
}

/// The camera's first hits through the centres of a 40 × 24 grid over the image, each with
/// its grid index (the id its record's rays are jittered by).
fn camera_points(fs: &FrameScene) -> Vec<(u32, anchorage::interaction::SurfacePoint)> {
    (0..24 * 40u32)
        .filter_map(|i| {
            let (px, py) = ((i % 40) as f32 + 0.5, (i / 40) as f32 + 0.5);
            let sp = anchorage::interaction::trace_camera(fs, px / 40.0, py / 24.0).1?;
            Some((i, sp))
        })
        .collect()
}

fn rate(n: usize, seconds: f64) -> f64 {
    n as f64 / seconds / 1e6
}

/// Writes `values` to `dir/name` as little-endian 32-bit words.
fn dump(dir: &std::path::Path, name: &str, values: impl Iterator<Item = [u8; 4]>) {
    let bytes: Vec<u8> = values.flatten().collect();
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

/// The triangles of `g` as nine f32 each.
fn triangle_words(g: &Geometry) -> impl Iterator<Item = [u8; 4]> + '_ {
    g.triangles
        .iter()
        .flat_map(|t| [t.v0, t.v1, t.v2])
        .flat_map(|v| v.to_array())
        .map(f32::to_le_bytes)
}

fn main() {
    let mut path = "benches/sponza/job.json".to_string();
    let mut dump_dir = None;
    let mut gather_only = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        if a == "--dump" {
            dump_dir = args.next().map(std::path::PathBuf::from);
        } else if a == "--gather" {
            gather_only = true;
        } else if !a.starts_with("--") {
            path = a;
        }
    }
    let job = anchorage::job::Job::load(std::path::Path::new(&path), &Default::default())
        .unwrap_or_else(|e| panic!("{e}"));
    let scene = job.load_scene().unwrap_or_else(|e| panic!("{e}"));
    let base = scene.statics();
    let aspect = job.width as f32 / job.height as f32;
    let time = job.time_of(job.frames.start);
    let cp = CacheParams {
        strata: [30, 60],
        ..CacheParams::default()
    };
    println!(
        "{path}: {} static triangles, 1 thread",
        base.geometry.triangles.len()
    );
    let presets = [
        ("medium_build", BvhBuildParams::medium_build()),
        ("slow_build", BvhBuildParams::slow_build()),
        ("very_slow_build", BvhBuildParams::very_slow_build()),
    ];
    for (name, params) in presets {
        if gather_only {
            break;
        }
        let start = Instant::now();
        let bvh = StaticBvh::build_with(&base.geometry, params);
        let build = start.elapsed().as_secs_f64();
        let statics = anchorage::scene::StaticSet {
            bvh: Arc::new(bvh),
            ..base.clone()
        };
        let (fs, _) = scene.evaluate(time, aspect, &statics);
        let mut rays = Vec::new();
        // Each point's rays as `Accel::closest4` takes them in the gather: 2 × 2 strata,
        // each lane the ray's index in `rays` (`None`: below the surface or past the grid).
        let mut packets: Vec<(Vec3, [Option<usize>; 4])> = Vec::new();
        for (id, sp) in camera_points(&fs) {
            let strata = StratumRays::new(&sp, id, &cp);
            let o = sp.spawn();
            let first = rays.len();
            let mut index = [None; 1800];
            for s in 0..1800 {
                let d = strata.dir(s);
                if d.dot(sp.ng) > 0.0 {
                    index[s as usize] = Some(rays.len());
                    rays.push((o, d));
                }
            }
            let [m, n] = cp.strata;
            for j in (0..m).step_by(2) {
                for k in (0..n).step_by(2) {
                    let lane = |dj: u32, dk: u32| {
                        (j + dj < m && k + dk < n)
                            .then(|| index[((j + dj) * n + k + dk) as usize])
                            .flatten()
                    };
                    packets.push((o, [lane(0, 0), lane(0, 1), lane(1, 0), lane(1, 1)]));
                }
            }
            debug_assert!(rays[first..].iter().all(|r| r.0 == o));
        }
        let short = 0.1 * fs.static_radius();
        if let Some(dir) = dump_dir.take() {
            std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
            dump(&dir, "static.bin", triangle_words(&fs.static_geometry));
            dump(&dir, "dynamic.bin", triangle_words(&fs.dynamic_geometry));
            let words = rays.iter().flat_map(|(o, d)| [o.to_array(), d.to_array()]);
            dump(&dir, "rays.bin", words.flatten().map(f32::to_le_bytes));
            let lanes = packets
                .iter()
                .flat_map(|(_, l)| l.map(|i| i.map_or(-1, |i| i as i32)));
            dump(&dir, "packets.bin", lanes.map(i32::to_le_bytes));
            // Per ray: distance (infinite on a miss), set (0 static, 1 dynamic, -1 none) and
            // triangle (-1 on a miss).
            let hits = rays.iter().flat_map(|&(o, d)| {
                let h = Accel::closest(
                    &fs.accel,
                    &fs.static_geometry,
                    &fs.dynamic_geometry,
                    o,
                    d,
                    f32::INFINITY,
                );
                let (t, set, i) = h.map_or((f32::INFINITY, -1, -1), |h| {
                    (
                        h.t,
                        i32::from(h.motion == Motion::Dynamic),
                        h.triangle as i32,
                    )
                });
                [t.to_le_bytes(), set.to_le_bytes(), i.to_le_bytes()]
            });
            dump(&dir, "hits.bin", hits);
            dump(&dir, "short.bin", std::iter::once(short.to_le_bytes()));
            println!("wrote {} rays to {}", rays.len(), dir.display());
        }
        let (mut ours, mut theirs, mut occluded) = (f64::MAX, f64::MAX, f64::MAX);
        let (mut d_ours, mut d_theirs, mut blocked) = (0, 0, 0);
        let (mut fours, mut d_fours) = (f64::MAX, 0);
        let (mut differ, mut ties) = (0, 0);
        for _ in 0..3 {
            let start = Instant::now();
            let a: Vec<_> = rays
                .iter()
                .map(|&(o, d)| obvhs_closest(&fs, o, d))
                .collect();
            theirs = theirs.min(start.elapsed().as_secs_f64());
            let start = Instant::now();
            let b: Vec<_> = rays
                .iter()
                .map(|&(o, d)| {
                    Accel::closest(
                        &fs.accel,
                        &fs.static_geometry,
                        &fs.dynamic_geometry,
                        o,
                        d,
                        f32::INFINITY,
                    )
                    .map(|h| (h.t, h.motion, h.triangle))
                })
                .collect();
            ours = ours.min(start.elapsed().as_secs_f64());
            let start = Instant::now();
            let mut c = vec![None; rays.len()];
            for (o, lanes) in &packets {
                let dirs = lanes.map(|l| l.map(|i| rays[i].1));
                let hits = fs
                    .accel
                    .closest4(&fs.static_geometry, &fs.dynamic_geometry, *o, dirs);
                for (l, h) in lanes.iter().zip(hits) {
                    if let Some(i) = l {
                        c[*i] = h.map(|h| (h.t, h.motion, h.triangle));
                    }
                }
            }
            fours = fours.min(start.elapsed().as_secs_f64());
            d_fours = c.iter().fold(0, |acc, &h| digest(h, acc));
            let start = Instant::now();
            blocked = rays
                .iter()
                .filter(|&&(o, d)| {
                    fs.accel
                        .occluded(&fs.static_geometry, &fs.dynamic_geometry, o, d, short)
                })
                .count();
            occluded = occluded.min(start.elapsed().as_secs_f64());
            d_theirs = a.iter().fold(0, |acc, &h| digest(h, acc));
            d_ours = b.iter().fold(0, |acc, &h| digest(h, acc));
            differ = a.iter().zip(&b).filter(|(a, b)| a != b).count();
            // Hits at the same distance where ours is the triangle of lower index.
            ties = a
                .iter()
                .zip(&b)
                .filter(|(a, b)| match (a, b) {
                    (Some(a), Some(b)) => a != b && a.0 == b.0 && a.1 == b.1 && b.2 < a.2,
                    _ => false,
                })
                .count();
        }
        println!(
            "{name:<16} build {build:.2} s | {} gather rays, closest hit: obvhs's traversal \
             {:.3} M/s (digest {d_theirs:016x}), Accel::closest {:.3} M/s (digest \
             {d_ours:016x}), {differ} hits differ, {ties} of them ties won by the lower index; \
             Accel::closest4 over 2×2 strata {:.3} M/s (digest {d_fours:016x}) | shadow rays of \
             {short:.3}: {:.3} M/s, {blocked} blocked",
            rays.len(),
            rate(rays.len(), theirs),
            rate(rays.len(), ours),
            rate(rays.len(), fours),
            rate(rays.len(), occluded),
        );
    }
    gather_stage(&scene, time, aspect, &base);
}

/// `trace_strata` from the camera's first hits on the grid, at each preset's strata, best
/// of three, with a digest of every hit's point and shading normal (module doc). Each
/// point's hits are dropped once digested, as a render drops a part's.
fn gather_stage(
    scene: &anchorage::scene::Scene,
    time: f32,
    aspect: f32,
    statics: &anchorage::scene::StaticSet,
) {
    let (fs, _) = scene.evaluate(time, aspect, statics);
    let points = camera_points(&fs);
    for strata in [[12, 36], [30, 60]] {
        let cp = CacheParams {
            strata,
            ..CacheParams::default()
        };
        let (mut best, mut rays, mut d) = (f64::MAX, 0, 0u64);
        for _ in 0..3 {
            (rays, d) = (0, 0);
            let start = Instant::now();
            for (id, sp) in &points {
                let hits = trace_strata(&fs, sp, *id, &cp);
                rays += hits.len();
                d = hits.iter().fold(d, |acc, h| {
                    let v = h.sp.as_ref().map_or(0, |sp| {
                        let p = sp.position.to_array().map(f32::to_bits);
                        let n = sp.ns.to_array().map(f32::to_bits);
                        (u64::from(p[0] ^ p[1].rotate_left(11) ^ p[2].rotate_left(22)) << 32)
                            | u64::from(n[0] ^ n[1].rotate_left(11) ^ n[2].rotate_left(22))
                    });
                    mix(acc, v)
                });
            }
            best = best.min(start.elapsed().as_secs_f64());
        }
        println!(
            "gather::trace_strata, {}×{} strata from {} points: {rays} rays, {:.3} M/s \
             (digest {d:016x})",
            strata[0],
            strata[1],
            points.len(),
            rate(rays, best),
        );
    }
}
