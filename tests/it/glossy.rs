//! Glossy surfaces (glTF metallic-roughness; paper §5): direct light on a metal plane against
//! the closed form, the path tracer's sampling strategies against each other, and the cached
//! methods against the path tracer on a scene with a glossy floor.

use super::common::*;
use super::sets::{Prim, gltf_with, room_quads};
use super::stat::{Welch, assert_agrees};
use anchorage::compare::Aov;
use anchorage::integrator::FrameImage;
use anchorage::job::Job;
use glam::Vec3;

/// The glTF 2.0 Appendix B specular BRDF of a metal, written out independently of
/// `anchorage::bsdf`: Schlick F with F0 = base colour, GGX D, height-correlated Smith V.
fn metal_brdf(n: Vec3, v: Vec3, l: Vec3, base: f32, roughness: f32) -> f32 {
    let a = roughness * roughness;
    let h = (v + l).normalize();
    let (nh, nv, nl, vh) = (n.dot(h), n.dot(v), n.dot(l), v.dot(h));
    if nv <= 0.0 || nl <= 0.0 {
        return 0.0;
    }
    let d = a * a / (std::f32::consts::PI * (nh * nh * (a * a - 1.0) + 1.0).powi(2));
    let vis = 0.5
        / (nl * (nv * nv * (1.0 - a * a) + a * a).sqrt()
            + nv * (nl * nl * (1.0 - a * a) + a * a).sqrt());
    let f = base + (1.0 - base) * (1.0 - vh).powi(5);
    f * d * vis
}

fn quad_y(y: f32, lo: [f32; 2], hi: [f32; 2]) -> [[f32; 3]; 4] {
    [
        [lo[0], y, lo[1]],
        [lo[0], y, hi[1]],
        [hi[0], y, hi[1]],
        [hi[0], y, lo[1]],
    ]
}

fn prim(name: &'static str, quads: Vec<[[f32; 3]; 4]>, albedo: f32) -> Prim {
    Prim {
        name,
        quads,
        albedo,
        motion: "static",
        keys: vec![],
    }
}

fn metal(base: f32, roughness: f32) -> String {
    format!(
        r#"{{"pbrMetallicRoughness":{{"baseColorFactor":[{base},{base},{base},1],"metallicFactor":1,"roughnessFactor":{roughness}}}}}"#
    )
}

fn job(dir: &std::path::Path, text: &str, camera: &str, size: [u32; 2], method: &str) -> Job {
    std::fs::write(dir.join("scene.gltf"), text).unwrap();
    job_from_json(
        &dir.join(format!("{}.json", method.len())),
        &format!(
            r#"{{"scene":[{{"path":"scene.gltf"}}],"camera":{camera},"resolution":[{},{}],
            "render":{{"samples_per_pixel":16}},"method":{method}}}"#,
            size[0], size[1]
        ),
    )
    .unwrap()
}

/// A metal plane (base colour 0.9, roughness 0.4) under a point light of I = 100 cd at 2 m:
/// every pixel's direct light is f(v, l)·I·cos θ/r² with f the Appendix B BRDF, averaged
/// over the pixel (16 sub-pixel positions against the renderer's 64 jittered samples),
/// within 3 % where the highlight is not negligible. A metal has no diffuse part, so the
/// `glossy_direct` AOV carries all of it.
#[test]
fn a_metal_plane_under_a_point_light_matches_the_closed_form() {
    let dir = tempdir();
    let (base, roughness, intensity) = (0.9f32, 0.4f32, 100.0f32);
    let light = Vec3::new(0.0, 2.0, 0.0);
    let text = gltf_with(
        &[prim(
            "plane",
            vec![quad_y(0.0, [-10.0, -10.0], [10.0, 10.0])],
            base,
        )],
        &[super::sets::Light {
            intensity,
            keys: vec![(0.0, light.to_array())],
        }],
        |_| metal(base, roughness),
    );
    let camera = r#"{"position":[0,2.5,4],"look_at":[0,0,0],"yfov_deg":50}"#;
    let mut j = job(dir.path(), &text, camera, [40, 30], r#"{"name":"direct"}"#);
    j.render.samples_per_pixel = 64;
    let img = render(&j, 0);
    let scene = j.load_scene().unwrap();
    let cam = scene.camera_at(0.0, img.width as f32 / img.height as f32);
    let expect = |fx: f32, fy: f32| {
        let r = cam.ray(fx, fy);
        if r.dir.y >= 0.0 {
            return 0.0;
        }
        let p = r.origin + r.dir * (-r.origin.y / r.dir.y);
        let to_l = light - p;
        let (r2, l) = (to_l.length_squared(), to_l.normalize());
        metal_brdf(Vec3::Y, -r.dir, l, base, roughness) * intensity * l.y / r2
    };
    let mut want = vec![0.0f32; (img.width * img.height) as usize];
    for y in 0..img.height {
        for x in 0..img.width {
            let mut sum = 0.0;
            for k in 0..16 {
                let (sx, sy) = ((k % 4) as f32 + 0.5, (k / 4) as f32 + 0.5);
                sum += expect(
                    (x as f32 + sx / 4.0) / img.width as f32,
                    (y as f32 + sy / 4.0) / img.height as f32,
                );
            }
            want[(y * img.width + x) as usize] = sum / 16.0;
        }
    }
    let peak = want.iter().cloned().fold(0.0f32, f32::max);
    assert!(peak > 1.0, "the highlight is in view: peak {peak}");
    let mut worst = 0.0f32;
    for (i, &w) in want.iter().enumerate() {
        if w < 0.02 * peak {
            continue;
        }
        let got = img.beauty[i][0];
        let err = (got - w).abs() / w;
        worst = worst.max(err);
        assert!(
            err < 0.03,
            "pixel {i}: {got} vs closed form {w} (peak {peak})"
        );
        assert!(img.diffuse_direct[i][0].abs() < 1e-6 * w);
        assert_eq!(img.glossy_direct[i], img.direct[i]);
    }
    eprintln!("worst relative error {worst:.3}");
}

/// A grey room lit by a small emissive ceiling quad, with a metal sheet of `roughness` on
/// the floor, and its emitter in view.
fn glossy_room(roughness: f32) -> String {
    glossy_room_with(roughness, None)
}

/// [`glossy_room`], with a black fin 0.5 high standing on the sheet at `x = fin`, between
/// the sheet and the panel, if given.
fn glossy_room_with(roughness: f32, fin: Option<f32>) -> String {
    let room = prim("room", room_quads([-2.0, 0.0, -2.0], [2.0, 2.5, 2.0]), 0.6);
    let sheet = prim("sheet", vec![quad_y(0.01, [-1.2, -1.5], [1.2, 0.5])], 0.9);
    let lamp = prim("lamp", vec![quad_y(2.45, [-0.4, -0.8], [0.4, 0.0])], 0.0);
    // A red panel on the left: the sheet reflects it on one side only.
    let panel = prim(
        "panel",
        vec![[
            [-1.9, 0.0, -1.5],
            [-1.9, 0.0, 0.5],
            [-1.9, 1.5, 0.5],
            [-1.9, 1.5, -1.5],
        ]],
        0.8,
    );
    let mut prims = vec![room, sheet, lamp, panel];
    if let Some(x) = fin {
        prims.push(prim(
            "fin",
            vec![[[x, 0.0, -1.5], [x, 0.0, 0.5], [x, 0.5, 0.5], [x, 0.5, -1.5]]],
            0.0,
        ));
    }
    gltf_with(&prims, &[], |p| {
        match p.name {
        "fin" => r#"{"pbrMetallicRoughness":{"baseColorFactor":[0,0,0,1],"metallicFactor":0},"extensions":{"KHR_materials_specular":{"specularFactor":0}},"doubleSided":true}"#.to_string(),
        "panel" => r#"{"pbrMetallicRoughness":{"baseColorFactor":[0.8,0.1,0.1,1],"metallicFactor":0},"extensions":{"KHR_materials_specular":{"specularFactor":0}},"doubleSided":true}"#.to_string(),
        "sheet" => metal(0.9, roughness),
        "lamp" => r#"{"pbrMetallicRoughness":{"baseColorFactor":[0,0,0,1],"metallicFactor":0},"emissiveFactor":[1,1,1],"extensions":{"KHR_materials_emissive_strength":{"emissiveStrength":20}},"doubleSided":true}"#.to_string(),
        _ => r#"{"pbrMetallicRoughness":{"baseColorFactor":[0.6,0.6,0.6,1],"metallicFactor":0},"extensions":{"KHR_materials_specular":{"specularFactor":0}},"doubleSided":true}"#.to_string(),
    }
    })
}

/// Looking down at the sheet, towards the red panel it reflects.
const SHEET_CAMERA: &str = r#"{"position":[0.6,0.9,0.3],"look_at":[-0.5,0,-0.7],"yfov_deg":50}"#;

const ROOM_CAMERA: &str = r#"{"position":[0,1.3,1.9],"look_at":[0,0.4,-0.8],"yfov_deg":70}"#;

fn path_traced(dir: &std::path::Path, roughness: f32, sampling: &str, samples: u32) -> FrameImage {
    let j = job(
        dir,
        &glossy_room(roughness),
        ROOM_CAMERA,
        [24, 18],
        &format!(
            r#"{{"name":"path-trace","path_samples":{samples},"path_sampling":"{sampling}"}}"#
        ),
    );
    render(&j, 0)
}

/// Emitter sampling alone, BRDF sampling alone and their combination by multiple importance
/// sampling estimate the same image (per-tile Welch tests, no bias allowed): a wrong MIS
/// weight, BRDF pdf or emitter pdf shows as a difference. The highlight of the lamp in the
/// metal sheet is where BRDF sampling wins and emitter sampling is noisy.
#[test]
fn path_tracer_strategies_converge_to_the_same_image() {
    let dir = tempdir();
    let mis = path_traced(dir.path(), 0.3, "mis", 256);
    let lights = path_traced(dir.path(), 0.3, "lights", 256);
    let brdf = path_traced(dir.path(), 0.3, "brdf", 512);
    let glossy: f32 = mis.glossy_direct.iter().map(|p| p[0]).sum();
    assert!(glossy > 0.0, "the sheet reflects the lamp");
    assert_agrees(
        "strategies-lights-vs-mis",
        &[&lights],
        &[&mis],
        Aov::Beauty,
        Welch::unbiased(4),
    );
    assert_agrees(
        "strategies-brdf-vs-mis",
        &[&brdf],
        &[&mis],
        Aov::Beauty,
        Welch::unbiased(4),
    );
}

/// The cached methods on the glossy room against the path tracer: the glossy floor's
/// indirect light by importance-sampled reflection rays (roughness 0.3 is below the default
/// `glossy_max_roughness`), the rest from the cache. Bias allowance 20 % per 4-pixel tile
/// (measured: both pass from 11.3 %; with the direct light counted twice at the rays' hits
/// they need 29.7 %; without the glossy rays the sheet has no glossy indirect light and the
/// test fails).
#[test]
fn cached_methods_on_a_glossy_floor_agree_with_the_path_tracer() {
    let dir = tempdir();
    let pt = path_traced(dir.path(), 0.3, "mis", 512);
    for method in ["brute-force", "anchors"] {
        let j = job(
            dir.path(),
            &glossy_room(0.3),
            ROOM_CAMERA,
            [24, 18],
            &format!(r#"{{"name":"{method}","preset":"draft","photons":200000}}"#),
        );
        let img = render(&j, 0);
        let g: f32 = img.glossy_indirect.iter().map(|p| p[0]).sum();
        assert!(g > 0.0, "{method}: the sheet reflects indirect light");
        assert_agrees(
            &format!("glossy-room-{method}-vs-path-trace"),
            &[&img],
            &[&pt],
            Aov::Beauty,
            Welch::biased(4, 0.2),
        );
    }
}

/// A moderately glossy sheet (roughness 0.5) reflecting a red panel, seen from above, rendered
/// by `anchors` with anchor bucketing (§5.1) and with importance-sampled reflection rays on
/// the same caches: the two agree on the indirect light per 4-pixel tile within 10 %, and
/// each agrees with the path tracer within 30 % on the beauty (the photon estimates' bias in
/// the panel's corner). Bucketing must reach anchors (not only its fallback).
#[test]
fn anchor_bucketing_agrees_with_importance_sampling_on_a_moderately_glossy_sheet() {
    let dir = tempdir();
    let pt = render(
        &job(
            dir.path(),
            &glossy_room(0.5),
            SHEET_CAMERA,
            [24, 18],
            r#"{"name":"path-trace","path_samples":512}"#,
        ),
        0,
    );
    let img = |mode: &str| {
        render(
            &job(
                dir.path(),
                &glossy_room(0.5),
                SHEET_CAMERA,
                [24, 18],
                &format!(
                    r#"{{"name":"anchors","preset":"draft","photons":200000,"glossy_mode":"{mode}"}}"#
                ),
            ),
            0,
        )
    };
    let (bucketing, importance) = (img("bucketing"), img("importance"));
    let g: f32 = bucketing.glossy_indirect.iter().map(|p| p[0]).sum();
    assert!(g > 0.0, "the sheet reflects indirect light");
    assert_agrees(
        "bucketing-vs-importance",
        &[&bucketing],
        &[&importance],
        Aov::Indirect,
        Welch::biased(4, 0.1),
    );
    for (name, im) in [("bucketing", &bucketing), ("importance", &importance)] {
        assert_agrees(
            &format!("sheet-{name}-vs-path-trace"),
            &[im],
            &[&pt],
            Aov::Beauty,
            Welch::biased(4, 0.3),
        );
    }
}

/// The glossy example room (a polished floor, a gold cube) renders the same bytes on one and
/// two threads with every glossy path: bucketing, reflection rays, and the cache.
#[test]
fn glossy_room_gives_the_same_bytes_with_one_and_two_threads() {
    let dir = tempdir();
    let job = dir.path().join("job.json");
    for mode in ["bucketing", "importance"] {
        std::fs::write(
            &job,
            format!(
                r#"{{"scene":[{{"path":"{}"}}],"resolution":[48,36],"frames":{{"start":0,"end":48}},"render":{{"samples_per_pixel":2}},
                "method":{{"name":"anchors","preset":"draft","glossy_mode":"{mode}"}}}}"#,
                root().join("examples/room/room_glossy.gltf").display()
            ),
        )
        .unwrap();
        let names: Vec<String> = (4..=6).map(|f| format!("job.{f:04}.exr")).collect();
        assert_same_bytes_with_1_and_2_threads(&job, &["--frames", "4-6"], &names);
    }
}

/// Anchor bucketing keeps only the anchors nearer than the depth map (§5.1): a black fin
/// (0.5 high) stands on the sheet between the pixels and the red panel, and records valid at
/// pixels next to the fin see the panel over it. Bucketing must agree with reflection rays
/// (which meet the fin) per 4-pixel tile within 10 % on the indirect light (measured: no
/// allowance needed); without the depth test the panel's red shows through the fin and it
/// needs 37 %.
#[test]
fn anchor_bucketing_does_not_see_through_an_occluder() {
    let dir = tempdir();
    let camera = r#"{"position":[0.3,0.35,0.0],"look_at":[-0.4,0,-0.6],"yfov_deg":45}"#;
    let img = |mode: &str| {
        render(
            &job(
                dir.path(),
                &glossy_room_with(0.5, Some(-0.5)),
                camera,
                [24, 18],
                &format!(
                    r#"{{"name":"anchors","preset":"draft","photons":200000,"glossy_mode":"{mode}"}}"#
                ),
            ),
            0,
        )
    };
    let (bucketing, importance) = (img("bucketing"), img("importance"));
    assert_agrees(
        "fin-bucketing-vs-importance",
        &[&bucketing],
        &[&importance],
        Aov::Indirect,
        Welch::biased(4, 0.1),
    );
}

/// Out-of-range glossy settings are input errors naming the key.
#[test]
fn glossy_settings_out_of_range_name_their_key() {
    let dir = tempdir();
    std::fs::write(dir.path().join("scene.gltf"), glossy_room(0.5)).unwrap();
    for (extra, key) in [
        (r#""glossy_bucket_strata":[0,8]"#, "glossy_bucket_strata"),
        (r#""glossy_bucket_offset":-1"#, "glossy_bucket_offset"),
        (r#""glossy_rays":33"#, "glossy_rays"),
        (r#""glossy_max_roughness":0.9"#, "glossy_max_roughness"),
        (
            r#""glossy_specular_max_roughness":0.7,"glossy_max_roughness":0.5"#,
            "glossy_specular_max_roughness",
        ),
    ] {
        let e = job_from_json(
            &dir.path().join("j.json"),
            &format!(r#"{{"scene":[{{"path":"scene.gltf"}}],"method":{{{extra}}}}}"#),
        )
        .err()
        .unwrap_or_else(|| panic!("{extra} accepted"));
        assert!(e.to_string().contains(key), "{extra}: {e}");
    }
}

/// How two renders of the same frame differ in one AOV: pixels that differ at all, and the
/// RMS and largest difference relative to the mean of the first.
fn aov_difference(a: &[[f32; 3]], b: &[[f32; 3]]) -> (usize, f64, f64) {
    let mean = a.iter().flatten().map(|&v| v as f64).sum::<f64>() / (3 * a.len()).max(1) as f64;
    let (mut differ, mut sq, mut max) = (0, 0.0f64, 0.0f64);
    for (p, q) in a.iter().zip(b) {
        differ += (p != q) as usize;
        for k in 0..3 {
            let d = (p[k] - q[k]).abs() as f64;
            sq += d * d;
            max = max.max(d);
        }
    }
    let rms = (sq / (3 * a.len()).max(1) as f64).sqrt();
    (differ, rms / mean.max(1e-30), max / mean.max(1e-30))
}

/// Anchor bucketing's depth maps (§5.1) run where visibility runs: the glossy example room
/// (a polished floor reflecting a moving gold cube, bucketed) rendered with `visibility: gpu`
/// (Mesa's lavapipe here) and `cpu` over three frames. The direct light does not involve
/// depth maps and must match to the bit; in `glossy_indirect` the GPU's depths may differ by
/// rounding (module doc of `anchorage::visibility::depth`: 10⁻⁵ of a depth, or a grazing ray
/// given to the other side of a silhouette), which moves an anchor across a bucket's D_bucket
/// or changes a cell's fallback: at most 0.2 % of the pixels may differ and the difference's
/// RMS must stay below 5·10⁻⁶ of the mean (measured on lavapipe: no pixel differs; with every
/// GPU depth 10⁻³ too long, 100 times the stated rounding, 0.7 % of the pixels differ by a
/// relative RMS of 1.8·10⁻⁵ and the test fails). Leaving the dynamic cube out of the GPU's
/// depth maps fails it too.
#[test]
fn glossy_room_renders_alike_with_depth_maps_on_the_gpu_and_the_cpu() {
    if anchorage::visibility::gpu::adapter_for_tests().is_none() {
        return;
    }
    let dir = tempdir();
    let text = format!(
        r#"{{"scene":[{{"path":"{}"}}],"resolution":[64,48],"frames":{{"start":0,"end":48}},
        "render":{{"samples_per_pixel":2}},"method":{{"name":"anchors","preset":"draft"}}}}"#,
        root().join("examples/room/room_glossy.gltf").display()
    );
    let on = |v| {
        let mut job = job_from_json(&dir.path().join("job.json"), &text).unwrap();
        job.render.visibility = v;
        render_frames(&job, &[0, 6, 12])
    };
    let cpu = on(anchorage::job::VisibilityChoice::Cpu);
    let gpu = on(anchorage::job::VisibilityChoice::Gpu);
    let mut bucketed = 0.0;
    for (f, (c, g)) in cpu.iter().zip(&gpu).enumerate() {
        assert_eq!(c.direct, g.direct, "frame {f}: direct light");
        let (differ, rms, max) = aov_difference(&c.glossy_indirect, &g.glossy_indirect);
        let (beauty_differ, ..) = aov_difference(
            &c.beauty
                .iter()
                .map(|p| [p[0], p[1], p[2]])
                .collect::<Vec<_>>(),
            &g.beauty
                .iter()
                .map(|p| [p[0], p[1], p[2]])
                .collect::<Vec<_>>(),
        );
        eprintln!(
            "frame {f}: glossy_indirect differs in {differ} of {} pixels (beauty {beauty_differ}), \
             relative RMS {rms:.2e}, largest {max:.2e}",
            c.glossy_indirect.len()
        );
        assert!(
            differ * 500 <= c.glossy_indirect.len(),
            "frame {f}: {differ} pixels differ"
        );
        assert!(rms <= 5e-6, "frame {f}: relative RMS {rms:e}");
        bucketed += c
            .glossy_indirect
            .iter()
            .flatten()
            .map(|&v| v as f64)
            .sum::<f64>();
    }
    assert!(bucketed > 0.0, "the room must have bucketed glossy light");
}

/// Batching bucketing's depth queries by bands of pixels changes no byte: frame 3 of the
/// glossy example room, rendered from the same state (frames 0–2 first) in bands of 480
/// pixels (five rows), in the default bands (one here), and without bands — each shading
/// point tracing its own depth map, as bucketing did before the batching — gives the same
/// AOVs to the bit.
#[test]
fn bucketing_in_bands_gives_the_same_bytes_as_per_point_depth_maps() {
    use anchorage::integrator::FrameContext;
    use anchorage::integrator::cached::{self, BAND_PIXELS, CachedMethod, CachedState};
    use anchorage::interaction::Materials;
    use anchorage::pipeline;
    use anchorage::session::FrameState;
    let dir = tempdir();
    let text = format!(
        r#"{{"scene":[{{"path":"{}"}}],"resolution":[96,40],"frames":{{"start":0,"end":48}},
        "render":{{"samples_per_pixel":2,"visibility":"cpu"}},
        "method":{{"name":"anchors","preset":"draft"}}}}"#,
        root().join("examples/room/room_glossy.gltf").display()
    );
    let job = job_from_json(&dir.path().join("job.json"), &text).unwrap();
    let scene = job.load_scene().unwrap();
    let resources = pipeline::new_resources(&job, &scene).unwrap();
    let mut state = FrameState::default();
    for f in 0..3 {
        let mut stats = pipeline::new_stats(&job, f);
        pipeline::render_frame(&job, &scene, &resources, &mut state, f, &mut stats).unwrap();
    }
    let frame = 3;
    let aspect = job.width as f32 / job.height as f32;
    let (fs, _) = scene.evaluate(job.time_of(frame), aspect, &resources.statics);
    let ctx = FrameContext {
        scene: &fs,
        materials: Materials {
            materials: &scene.materials,
            textures: &scene.textures,
        },
        width: job.width,
        height: job.height,
        seed: job.seed,
        frame,
    };
    let params = job.method.params();
    let run = |bands: Option<u32>| {
        let mut s = state.clone();
        let (img, counts, _) = cached::render_in_bands(
            &ctx,
            CachedState {
                cache: &mut s.cache,
                anchors: &mut s.anchors,
                log: None,
                keys: None,
            },
            &params,
            CachedMethod::Anchors,
            resources.visibility.as_ref(),
            (job.render.samples_per_pixel, job.render.light_samples),
            bands,
            cached::Refresh::default(),
        )
        .unwrap();
        (img, counts.glossy_rays)
    };
    let (per_point, rays) = run(None);
    assert!(rays > 10_000, "the frame must bucket ({rays} depth rays)");
    for bands in [Some(480), Some(BAND_PIXELS)] {
        let (img, r) = run(bands);
        assert_eq!(r, rays, "{bands:?}: depth rays");
        let differ =
            |a: &[[f32; 3]], b: &[[f32; 3]]| a.iter().zip(b).filter(|(p, q)| p != q).count();
        let beauty = |i: &FrameImage| {
            i.beauty
                .iter()
                .map(|p| [p[0], p[1], p[2]])
                .collect::<Vec<_>>()
        };
        for (aov, n) in [
            ("beauty", differ(&beauty(&img), &beauty(&per_point))),
            (
                "glossy_indirect",
                differ(&img.glossy_indirect, &per_point.glossy_indirect),
            ),
            ("indirect", differ(&img.indirect, &per_point.indirect)),
        ] {
            assert_eq!(n, 0, "{bands:?}: {aov} differs in {n} pixels");
        }
        assert!(img.anchor_id == per_point.anchor_id, "{bands:?}: anchor_id");
    }
}

/// A rough metal sheet (roughness 0.7, lit from the cache: above `glossy_max_roughness`)
/// reflecting the red panel on one side of it, seen from above: the cached methods agree
/// with the path tracer on the indirect light per 4-pixel tile within 20 %. The lobe reads
/// the records' directional fit of their incident light; lit by their irradiance through
/// its directional albedo instead (the fit ignored), the worst tiles need 28 % (anchors) and
/// 32 % (brute force), and the test fails. Measured: 13.8 % and 15.0 % with the fit.
#[test]
fn a_rough_metal_sheet_reflects_the_side_its_light_comes_from() {
    let dir = tempdir();
    let pt = render(
        &job(
            dir.path(),
            &glossy_room(0.7),
            SHEET_CAMERA,
            [24, 18],
            r#"{"name":"path-trace","path_samples":1024}"#,
        ),
        0,
    );
    for method in ["brute-force", "anchors"] {
        let img = render(
            &job(
                dir.path(),
                &glossy_room(0.7),
                SHEET_CAMERA,
                [24, 18],
                &format!(r#"{{"name":"{method}","preset":"draft","photons":400000}}"#),
            ),
            0,
        );
        assert_agrees(
            &format!("rough-sheet-{method}-vs-path-trace"),
            &[&img],
            &[&pt],
            Aov::Indirect,
            Welch::biased(4, 0.2),
        );
    }
}
