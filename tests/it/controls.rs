//! What a job controls beyond the method: camera clip planes, which animation clips play,
//! and the previews' exposure.

use super::common::*;
use super::scenes::base64_encode;

/// Two squares facing +Z: a dark one (half-size 1) at z = −1 and an emissive one (half-size
/// 20, radiance 4) at z = −5, seen by a glTF camera at the origin (`camera` is its JSON).
/// Animations (JSON array) may move node 0, the dark square.
fn clip_scene(dir: &std::path::Path, camera: &str, animations: &str) -> std::path::PathBuf {
    let quad = |h: f32, z: f32| [-h, -h, z, h, -h, z, h, h, z, -h, h, z];
    let mut pos: Vec<f32> = quad(1.0, -1.0).to_vec();
    pos.extend(quad(20.0, -5.0));
    let idx: [u32; 6] = [0, 1, 2, 0, 2, 3];
    let mut bin: Vec<u8> = pos.iter().flat_map(|v| v.to_le_bytes()).collect();
    bin.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    // Animation data: times [0, 1], translations of clip A (to x = 3) and clip B (to y = 3).
    let anim: [f32; 14] = [
        0.0, 1.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, 0.0,
    ];
    bin.extend(anim.iter().flat_map(|v| v.to_le_bytes()));
    let gltf = format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_materials_emissive_strength"],
        "scenes":[{{"nodes":[0,1,2]}}],
        "nodes":[{{"name":"near","mesh":0}},{{"name":"far","mesh":1}},{{"name":"cam","camera":0}}],
        "cameras":[{camera}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}},
                     {{"pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1],"metallicFactor":0}},"emissiveFactor":[1,1,1],
                       "extensions":{{"KHR_materials_emissive_strength":{{"emissiveStrength":4}}}}}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":2,"material":0}}]}},
                  {{"primitives":[{{"attributes":{{"POSITION":1}},"indices":2,"material":1}}]}}],
        "animations":{animations},
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-1,-1,-1],"max":[1,1,-1]}},
                     {{"bufferView":0,"byteOffset":48,"componentType":5126,"count":4,"type":"VEC3","min":[-20,-20,-5],"max":[20,20,-5]}},
                     {{"bufferView":0,"byteOffset":96,"componentType":5125,"count":6,"type":"SCALAR"}},
                     {{"bufferView":0,"byteOffset":120,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
                     {{"bufferView":0,"byteOffset":128,"componentType":5126,"count":2,"type":"VEC3"}},
                     {{"bufferView":0,"byteOffset":152,"componentType":5126,"count":2,"type":"VEC3"}}],
        "bufferViews":[{{"buffer":0,"byteLength":{}}}],
        "buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}]}}"#,
        bin.len(),
        bin.len(),
        base64_encode(&bin)
    );
    let path = dir.join("clip.gltf");
    std::fs::write(&path, gltf).unwrap();
    path
}

fn perspective(znear: f32, zfar: Option<f32>) -> String {
    let far = zfar.map(|f| format!(r#","zfar":{f}"#)).unwrap_or_default();
    format!(r#"{{"type":"perspective","perspective":{{"yfov":0.5,"znear":{znear}{far}}}}}"#)
}

fn clip_job(dir: &std::path::Path, camera: &str, scale: f32) -> anchorage::job::Job {
    clip_scene(dir, camera, "[]");
    job_from_json(
        &dir.join("job.json"),
        &format!(
            r#"{{"scene":[{{"path":"clip.gltf","transform":{{"scale":{scale}}}}}],"camera":{{"node":"cam"}},
            "resolution":[8,8],"render":{{"samples_per_pixel":1}},"method":{{"name":"direct"}}}}"#
        ),
    )
    .unwrap()
}

/// Mean beauty (green) and mean depth over the image.
fn means(img: &anchorage::integrator::FrameImage) -> (f32, f32) {
    let n = img.beauty.len() as f32;
    (
        img.beauty.iter().map(|p| p[1]).sum::<f32>() / n,
        img.depth.iter().sum::<f32>() / n,
    )
}

/// glTF 2.0 §3.10: nothing nearer than `znear` or farther than `zfar` is seen. The clip depths
/// are in the camera node's units, so they scale with the layer like the rest of the scene.
#[test]
fn camera_clip_planes_hide_what_lies_outside_them() {
    let dir = tempdir();
    for scale in [1.0f32, 1e-3, 1e4] {
        // znear 0.5: the dark square at depth 1 fills the view.
        let (l, z) = means(&render(
            &clip_job(dir.path(), &perspective(0.5, None), scale),
            0,
        ));
        assert_eq!(l, 0.0, "scale {scale}: the near square hides the emitter");
        assert!((z / scale - 1.0).abs() < 1e-4, "scale {scale}: depth {z}");
        // znear 2: the camera sees through it to the emitter at depth 5.
        let (l, z) = means(&render(
            &clip_job(dir.path(), &perspective(2.0, None), scale),
            0,
        ));
        assert!(
            (l - 4.0).abs() < 1e-4,
            "scale {scale}: emitter radiance {l}"
        );
        assert!((z / scale - 5.0).abs() < 1e-3, "scale {scale}: depth {z}");
        // zfar 4 as well: nothing left to see.
        let img = render(
            &clip_job(dir.path(), &perspective(2.0, Some(4.0)), scale),
            0,
        );
        assert_eq!(means(&img).0, 0.0, "scale {scale}: beyond zfar");
        assert!(
            img.beauty.iter().all(|p| p[3] == 0.0),
            "alpha 0 where nothing is seen"
        );
    }
}

/// Cameras no projection can have are errors naming the camera and key, not black frames
/// or panics.
#[test]
fn impossible_cameras_are_refused() {
    let dir = tempdir();
    for (camera, key) in [
        (
            r#"{"type":"perspective","perspective":{"yfov":0,"znear":0.1}}"#,
            "perspective.yfov",
        ),
        (
            r#"{"type":"perspective","perspective":{"yfov":4,"znear":0.1}}"#,
            "perspective.yfov",
        ),
        (
            r#"{"type":"perspective","perspective":{"yfov":1,"znear":1,"zfar":0.5}}"#,
            "perspective.zfar",
        ),
        (
            r#"{"type":"orthographic","orthographic":{"xmag":1,"ymag":0,"znear":0,"zfar":9}}"#,
            "orthographic.ymag",
        ),
    ] {
        let err = clip_job(dir.path(), camera, 1.0).load_scene().unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("clip.gltf") && msg.contains(key), "{msg}");
        assert_eq!(err.exit_code(), 2);
    }
}

const TWO_CLIPS: &str = r#"[
    {"name":"A","samplers":[{"input":3,"output":4}],"channels":[{"sampler":0,"target":{"node":0,"path":"translation"}}]},
    {"name":"B","samplers":[{"input":3,"output":5}],"channels":[{"sampler":0,"target":{"node":0,"path":"translation"}}]}]"#;

fn clips_job(dir: &std::path::Path, animations: &str) -> anchorage::Result<anchorage::job::Job> {
    clip_scene(dir, &perspective(0.1, None), TWO_CLIPS);
    job_from_json(
        &dir.join("job.json"),
        &format!(
            r#"{{"scene":[{{"path":"clip.gltf"{animations}}}],"camera":{{"node":"cam"}},
            "resolution":[8,8],"render":{{"samples_per_pixel":1}},"method":{{"name":"direct"}}}}"#
        ),
    )
}

/// Where the `near` square is at t = 1 with the job's choice of clips.
fn near_at_1(dir: &std::path::Path, animations: &str) -> (glam::Vec3, Vec<String>) {
    let scene = clips_job(dir, animations).unwrap().load_scene().unwrap();
    let world = scene.layers[0].world_matrices(1.0);
    (world[0].w_axis.truncate(), scene.warnings())
}

/// Clips that drive the same channel: all play by default (the first in the file wins, with
/// a warning naming them), and the job picks the ones that play per layer, by name or index.
#[test]
fn animation_clips_are_chosen_per_layer() {
    let dir = tempdir();
    let (p, warnings) = near_at_1(dir.path(), "");
    assert_eq!(
        p,
        glam::Vec3::new(3.0, 0.0, 0.0),
        "A comes first in the file"
    );
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("\"A\", \"B\"") && w.contains("scene[0].animations")),
        "{warnings:?}"
    );
    let (p, warnings) = near_at_1(dir.path(), r#","animations":["B"]"#);
    assert_eq!(p, glam::Vec3::new(0.0, 3.0, 0.0), "B chosen");
    assert!(warnings.is_empty(), "{warnings:?}");
    let (p, _) = near_at_1(dir.path(), r#","animations":["animations[1]"]"#);
    assert_eq!(p, glam::Vec3::new(0.0, 3.0, 0.0), "B chosen by index");
    let (p, _) = near_at_1(dir.path(), r#","animations":[]"#);
    assert_eq!(p, glam::Vec3::ZERO, "no clip plays");
    let err = clips_job(dir.path(), r#","animations":["Run"]"#)
        .unwrap()
        .load_scene()
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("scene[0].animations[0]") && err.contains("\"Run\"") && err.contains("A, B"),
        "{err}"
    );
}

/// Previews scale by 2^exposure before the sRGB curve; the EXR keeps scene radiance; a
/// mostly clipped preview gets a warning with an exposure that fits.
#[test]
fn preview_exposure_scales_the_png_only() {
    let dir = tempdir();
    clip_scene(dir.path(), &perspective(2.0, None), "[]");
    let jp = dir.path().join("job.json");
    std::fs::write(
        &jp,
        r#"{"scene":[{"path":"clip.gltf"}],"camera":{"node":"cam"},"resolution":[8,8],
        "render":{"samples_per_pixel":1},"method":{"name":"direct"}}"#,
    )
    .unwrap();
    let render_png = |extra: &[&str]| {
        let out = dir.path().join("out");
        let _ = std::fs::remove_dir_all(&out);
        let mut args = vec![
            "render",
            jp.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.push("--preview");
        args.extend(extra);
        let o = run(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        let png = image::open(out.join("job.0000.png")).unwrap().to_rgb8();
        let exr = exr::prelude::read_first_rgba_layer_from_file(
            out.join("job.0000.exr"),
            |r, _| vec![0.0f32; r.width() * r.height()],
            |v: &mut Vec<f32>, p, (_, g, _, _): (f32, f32, f32, f32)| v[p.y() * 8 + p.x()] = g,
        )
        .unwrap();
        (
            png.get_pixel(4, 4)[1],
            exr.layer_data.channel_data.pixels[36],
            stderr(&o),
        )
    };
    // Radiance 4: white at exposure 0, 0.5 (sRGB 188) at −3.
    let (v0, e0, log0) = render_png(&[]);
    assert_eq!(v0, 255);
    assert!(log0.contains("--exposure -2"), "{log0}");
    let (v3, e3, log3) = render_png(&["--exposure", "-3"]);
    assert_eq!(v3, 188);
    assert!(!log3.contains("clips"), "{log3}");
    assert_eq!((e0, e3), (4.0, 4.0), "the EXR stays in scene radiance");
}
