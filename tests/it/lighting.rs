//! Direct lighting against analytic answers, scale invariance, and numerical extremes.

use super::common::*;
use super::scenes::base64_encode;
use anchorage::integrator::FrameImage;
use glam::Vec3;

const ALBEDO: f32 = 0.5;

/// A 20 m white-ish plane at y = 0, a light from `light` (KHR_lights_punctual JSON) at
/// `light_pos`, scaled by `scale`; camera 5 m above, looking down.
fn plane_job(
    dir: &std::path::Path,
    light: &str,
    light_pos: [f32; 3],
    rotation: [f32; 4],
    scale: f32,
    size: u32,
) -> anchorage::job::Job {
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    let bin = floats(&[
        -10.0, 0.0, -10.0, -10.0, 0.0, 10.0, 10.0, 0.0, 10.0, 10.0, 0.0, -10.0,
    ]);
    let idx: Vec<u8> = [0u32, 1, 2, 0, 2, 3]
        .iter()
        .flat_map(|i| i.to_le_bytes())
        .collect();
    let mut all = bin.clone();
    all.extend(idx);
    let gltf = format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_lights_punctual"],
        "extensions":{{"KHR_lights_punctual":{{"lights":[{light}]}}}},
        "scenes":[{{"nodes":[0,1]}}],
        "nodes":[{{"name":"plane","mesh":0}},{{"name":"light","translation":{light_pos:?},"rotation":{rotation:?},"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[{ALBEDO},{ALBEDO},{ALBEDO},1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1,"material":0}}]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-10,0,-10],"max":[10,0,10]}},
                     {{"bufferView":0,"byteOffset":48,"componentType":5125,"count":6,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteLength":72}}],
        "buffers":[{{"byteLength":72,"uri":"data:application/octet-stream;base64,{}"}}]}}"#,
        base64_encode(&all)
    );
    std::fs::write(dir.join("plane.gltf"), gltf).unwrap();
    job_from_json(
        &dir.join("j.json"),
        &format!(
            r#"{{"scene":[{{"path":"plane.gltf","transform":{{"scale":{scale}}}}}],
            "camera":{{"position":[0,{},0],"look_at":[0,0,0],"up":[0,0,-1],"yfov_deg":60}},
            "resolution":[{size},{size}],"render":{{"samples_per_pixel":16}}}}"#,
            5.0 * scale
        ),
    )
    .unwrap()
}

/// Radiance expected at the plane point seen through each pixel centre.
fn check_against(
    img: &FrameImage,
    job: &anchorage::job::Job,
    expect: impl Fn(Vec3) -> f32,
    tol: f32,
) {
    let scene = job.load_scene().unwrap();
    let cam = scene.camera_at(0.0, 1.0);
    let mut worst = 0.0f32;
    for y in 0..img.height {
        for x in 0..img.width {
            let r = cam.ray(
                (x as f32 + 0.5) / img.width as f32,
                (y as f32 + 0.5) / img.height as f32,
            );
            let p = r.origin + r.dir * (-r.origin.y / r.dir.y);
            let want = expect(p);
            let got = img.beauty[(y * img.width + x) as usize][0];
            let err = (got - want).abs() / want;
            worst = worst.max(err);
            assert!(
                err < tol,
                "pixel ({x},{y}) at {p}: {got} vs analytic {want}"
            );
        }
    }
    eprintln!("worst relative error {worst:.2e}");
}

/// A point light of intensity I at height h over a Lambertian plane of albedo ρ:
/// E = I cosθ / r², L = ρ E / π (KHR_lights_punctual: intensity in candela).
#[test]
fn point_light_over_a_plane_matches_i_cos_over_r2() {
    let dir = tempdir();
    let (i, h) = (100.0f32, 2.0f32);
    let job = plane_job(
        dir.path(),
        &format!(r#"{{"type":"point","intensity":{i}}}"#),
        [0.0, h, 0.0],
        [0.0, 0.0, 0.0, 1.0],
        1.0,
        48,
    );
    let img = render(&job, 0);
    check_against(
        &img,
        &job,
        |p| {
            let r2 = (Vec3::new(0.0, h, 0.0) - p).length_squared();
            let cos = h / r2.sqrt();
            ALBEDO / std::f32::consts::PI * i * cos / r2
        },
        0.01,
    );
    // The direct AOV is the same light (no emission here), and alpha is full coverage.
    assert_eq!(img.direct[100][0], img.beauty[100][0]);
    assert_eq!(img.beauty[100][3], 1.0);
}

/// A directional light of E lux at 60° from the normal: E cos 60° everywhere.
#[test]
fn directional_light_gives_e_cos_theta() {
    let dir = tempdir();
    // Rotating −Z by −30° about X gives (0, −sin 30°, −cos 30°): 60° from the plane's normal.
    let a = (-30.0f32).to_radians() / 2.0;
    let q = [a.sin(), 0.0, 0.0, a.cos()];
    let job = plane_job(
        dir.path(),
        r#"{"type":"directional","intensity":3}"#,
        [0.0, 3.0, 0.0],
        q,
        1.0,
        16,
    );
    let img = render(&job, 0);
    let want = ALBEDO / std::f32::consts::PI * 3.0 * 60f32.to_radians().cos();
    check_against(&img, &job, |_| want, 1e-4);
}

/// A spot light: full intensity inside the inner cone, none outside the outer.
#[test]
fn spot_light_cone() {
    let dir = tempdir();
    let a = (-90.0f32).to_radians() / 2.0; // point straight down
    let job = plane_job(
        dir.path(),
        r#"{"type":"spot","intensity":50,"spot":{"innerConeAngle":0.3,"outerConeAngle":0.5}}"#,
        [0.0, 2.0, 0.0],
        [a.sin(), 0.0, 0.0, a.cos()],
        1.0,
        32,
    );
    let img = render(&job, 0);
    let c = img.beauty[(16 * 32 + 16) as usize][0];
    let r2 = 4.0 + 2.0 * (2.0 * 5.0 * (30f32.to_radians()).tan() / 32.0f32).powi(2) / 4.0;
    assert!(
        (c - ALBEDO / std::f32::consts::PI * 50.0 / r2).abs() / c < 0.01,
        "{c}"
    );
    assert_eq!(img.beauty[0][0], 0.0, "corner is outside the outer cone");
}

/// Light intensities from 1e-6 to 1e6 give finite AOVs that scale linearly.
#[test]
fn extreme_intensities_stay_finite_and_linear() {
    let dir = tempdir();
    let mut images = Vec::new();
    for i in [1e-6f32, 1.0, 1e6] {
        let job = plane_job(
            dir.path(),
            &format!(r#"{{"type":"point","intensity":{i:e}}}"#),
            [0.0, 2.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            1.0,
            16,
        );
        let img = render(&job, 0);
        assert!(
            img.beauty
                .iter()
                .flatten()
                .chain(img.direct.iter().flatten())
                .chain(&img.depth)
                .all(|v| v.is_finite())
        );
        images.push(img);
    }
    for (img, s) in [(&images[0], 1e-6f32), (&images[2], 1e6)] {
        for (a, b) in img.beauty.iter().zip(&images[1].beauty) {
            assert!(
                (a[0] / s - b[0]).abs() <= 1e-5 * b[0],
                "{} vs {}",
                a[0] / s,
                b[0]
            );
        }
    }
}

/// A point-lit scene scaled by s: distances grow by s, so radiance falls by 1/s².
#[test]
fn point_lit_scene_scales_as_inverse_square() {
    let dir = tempdir();
    let light = r#"{"type":"point","intensity":100}"#;
    let base = render(
        &plane_job(
            dir.path(),
            light,
            [0.0, 2.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            1.0,
            16,
        ),
        0,
    );
    for s in [1e-9f32, 1e-3, 1e4, 1e9] {
        let img = render(
            &plane_job(
                dir.path(),
                light,
                [0.0, 2.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                s,
                16,
            ),
            0,
        );
        for (a, b) in img.beauty.iter().zip(&base.beauty) {
            assert!(
                (a[0] * s * s - b[0]).abs() <= 1e-3 * b[0],
                "scale {s}: {} vs {}",
                a[0] * s * s,
                b[0]
            );
        }
    }
}

/// The example (area-lit) rendered at scene scales from 1e-9 to 1e9 gives the same image.
#[test]
fn example_is_the_same_image_at_any_scene_scale() {
    let job_at = |s: f32| {
        job_from_json(
            &example_job(),
            &format!(
                r#"{{"scene":[{{"path":"room.gltf","transform":{{"scale":{s:e}}}}}],"resolution":[96,72],"frames":{{"start":0,"end":48}},
                "render":{{"samples_per_pixel":4}}}}"#
            ),
        )
        .unwrap()
    };
    let base = render(&job_at(1.0), 12);
    for s in [1e-9f32, 1e-6, 1e-3, 1e4, 1e6, 1e9] {
        let img = render(&job_at(s), 12);
        let rms = relative_rms(&img, &base);
        eprintln!("scale {s:e}: relative RMS difference {rms:.2e}");
        assert!(rms < 2e-3, "scale {s}: relative RMS difference {rms}");
        let alpha_diff = img
            .beauty
            .iter()
            .zip(&base.beauty)
            .filter(|(a, b)| a[3] != b[3])
            .count();
        assert!(alpha_diff <= 2, "{alpha_diff} pixels change coverage");
    }
}
