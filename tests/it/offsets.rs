//! Ray offsets from floating-point error bounds and render-space precision: a horizon ground, a set far from the origin, and scenes from 1e-9 to 1e9 in
//! scale render like small ones at the origin; scales beyond what f32 can render are refused.

use super::common::*;
use super::scenes::base64_encode;
use anchorage::integrator::FrameImage;

/// A glTF of a square ground of half-size `ground` at y = 0, a 0.5-unit cube standing on it
/// at the origin, and a point light of 40 cd 2 units up (grey Lambertian everywhere).
fn ground_gltf(ground: f32) -> String {
    let g = ground;
    #[rustfmt::skip]
    let mut pos: Vec<f32> = vec![
        -g, 0.0, -g,  -g, 0.0, g,  g, 0.0, g,  g, 0.0, -g,
    ];
    let mut idx: Vec<u32> = vec![0, 1, 2, 0, 2, 3];
    // The cube's own accessor: corners x·4 + y·2 + z.
    let c = [-0.25f32, 0.25];
    for x in c {
        for y in [0.0f32, 0.5] {
            for z in c {
                pos.extend([x, y, z]);
            }
        }
    }
    // Faces wound counter-clockwise from outside.
    #[rustfmt::skip]
    let faces: [[u32; 4]; 6] = [
        [0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3],
    ];
    for f in faces {
        idx.extend([f[0], f[1], f[2], f[0], f[2], f[3]]);
    }
    let mut bin: Vec<u8> = pos.iter().flat_map(|f| f.to_le_bytes()).collect();
    let pos_len = bin.len();
    bin.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    let (lo, hi) = (
        [-g.max(0.25), 0.0, -g.max(0.25)],
        [g.max(0.25), 0.5, g.max(0.25)],
    );
    format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_lights_punctual"],
        "extensions":{{"KHR_lights_punctual":{{"lights":[{{"type":"point","intensity":40}}]}}}},
        "scenes":[{{"nodes":[0,1,2]}}],
        "nodes":[{{"name":"ground","mesh":0}},{{"name":"cube","mesh":1}},
                 {{"name":"light","translation":[-0.6,2,-0.2],"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.6,0.6,0.6,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":2,"material":0}}]}},
                  {{"primitives":[{{"attributes":{{"POSITION":1}},"indices":3,"material":0}}]}}],
        "accessors":[
          {{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":{lo:?},"max":{hi:?}}},
          {{"bufferView":0,"byteOffset":48,"componentType":5126,"count":8,"type":"VEC3","min":[-0.25,0,-0.25],"max":[0.25,0.5,0.25]}},
          {{"bufferView":1,"componentType":5125,"count":6,"type":"SCALAR"}},
          {{"bufferView":1,"byteOffset":24,"componentType":5125,"count":36,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteLength":{pos_len}}},{{"buffer":0,"byteOffset":{pos_len},"byteLength":{}}}],
        "buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}]}}"#,
        bin.len() - pos_len,
        bin.len(),
        base64_encode(&bin)
    )
}

/// The ground scene with the direct method, camera 3 units away looking at the cube.
fn ground_job(dir: &std::path::Path, ground: f32) -> anchorage::job::Job {
    let name = format!("ground_{ground:e}.gltf");
    std::fs::write(dir.join(&name), ground_gltf(ground)).unwrap();
    job_from_json(
        &dir.join("j.json"),
        &format!(
            r#"{{"scene":[{{"path":"{name}"}}],
            "camera":{{"position":[1.2,2.2,2.6],"look_at":[0,0.1,0],"yfov_deg":50}},
            "resolution":[64,48],"method":{{"name":"direct"}},
            "render":{{"samples_per_pixel":4}}}}"#
        ),
    )
    .unwrap()
}

/// A point light's level is its intensity over the square of the scene's size
/// ([`anchorage::scene::Scene::emission_scale`]): the ground scene 2e-4 units across, its
/// light at 40 cd and at 4e11 (within 2^40 of 1, but some 1e21 lux at the ground), gives
/// the same image by brute force, beauty and indirect light divided by 1e10. Before the
/// renderer worked at a level of its own the indirect light was 14 % off (relative RMS),
/// and it still is where the level leaves out the scene's size.
#[test]
fn a_bright_point_light_in_a_tiny_scene_renders_like_a_dim_one() {
    let dir = tempdir();
    let job = |intensity: &str| {
        let gltf =
            ground_gltf(10.0).replace(r#""intensity":40"#, &format!(r#""intensity":{intensity}"#));
        std::fs::write(dir.path().join(format!("g{intensity}.gltf")), gltf).unwrap();
        job_from_json(
            &dir.path().join("j.json"),
            &format!(
                r#"{{"scene":[{{"path":"g{intensity}.gltf","transform":{{"scale":1e-5}}}}],
                "camera":{{"position":[1.2e-5,2.2e-5,2.6e-5],"look_at":[0,1e-6,0],"yfov_deg":50}},
                "resolution":[32,24],"method":{{"name":"brute-force","preset":"draft"}},
                "render":{{"samples_per_pixel":4}}}}"#
            ),
        )
        .unwrap()
    };
    let (dim, bright) = (render(&job("40"), 0), render(&job("4e11"), 0));
    let rms = |f: &dyn Fn(&FrameImage, usize) -> [f32; 3]| {
        let (mut d, mut n) = (0.0f64, 0.0f64);
        for i in 0..dim.beauty.len() {
            let (a, b) = (f(&bright, i), f(&dim, i));
            for c in 0..3 {
                assert!(a[c].is_finite(), "pixel {i}: {}", a[c]);
                d += (f64::from(a[c]) / 1e10 - f64::from(b[c])).powi(2);
                n += f64::from(b[c]).powi(2);
            }
        }
        (d / n).sqrt()
    };
    let beauty = rms(&|m, i| [m.beauty[i][0], m.beauty[i][1], m.beauty[i][2]]);
    let indirect = rms(&|m, i| m.indirect[i]);
    eprintln!("relative RMS difference {beauty:.1e} beauty, {indirect:.1e} indirect");
    assert!(
        beauty < 1e-3 && indirect < 1e-3,
        "relative RMS difference {beauty} (beauty), {indirect} (indirect)"
    );
}

/// Pixels that see the ground or the cube (full coverage) with no direct light: shadow.
fn shadowed(img: &FrameImage) -> usize {
    img.beauty
        .iter()
        .zip(&img.direct)
        .filter(|(b, d)| b[3] == 1.0 && d[0] == 0.0)
        .count()
}

/// Regression: a point light 2 units over a ±1e6 ground lost every shadow, the
/// ray offset (2^-17 × 1e6 = 7.6 units) lifting shadow rays over the 0.5-unit cube. The
/// ±1e6 ground gives the same direct image as a ±10 one: every pixel within 1 % of its
/// value (plus 1e-6 of the image's maximum, for pixels at zero), and the same shadow.
#[test]
fn horizon_ground_keeps_its_shadows_and_matches_a_small_ground() {
    let dir = tempdir();
    let small = render(&ground_job(dir.path(), 10.0), 0);
    let huge = render(&ground_job(dir.path(), 1e6), 0);
    let max = small.direct.iter().map(|d| d[0]).fold(0.0f32, f32::max);
    assert!(max > 0.0);
    let mut worst = 0.0f32;
    for (i, (a, b)) in huge.direct.iter().zip(&small.direct).enumerate() {
        for c in 0..3 {
            let err = (a[c] - b[c]).abs() / (b[c] + 1e-6 * max);
            worst = worst.max(err);
            assert!(
                err <= 0.01,
                "pixel {i} channel {c}: {} on the ±1e6 ground vs {} on the ±10 one",
                a[c],
                b[c]
            );
        }
    }
    let (ns, nh) = (shadowed(&small), shadowed(&huge));
    eprintln!("worst relative difference {worst:.2e}; shadowed pixels {ns} (±10), {nh} (±1e6)");
    let n = (small.width * small.height) as usize;
    assert!(ns > n / 50, "the cube casts a shadow: {ns} of {n} pixels");
    assert_eq!(ns, nh, "the same pixels are in shadow");
}

/// The example room rendered with its layer moved 1e4, 1e5 and 1e6 from the origin gives
/// the images of the room at the origin within 1 % relative RMS (beauty and direct), on a
/// frame that reuses the anchors and cache records of the one before. It was 7.5 %, 89 % and
/// 100 % wrong in direct light: f32 spacing at 1e6 is 0.0625, and the lamp merged with the
/// ceiling. Render space is centred on the static set, in f64.
#[test]
fn example_far_from_the_origin_is_the_same_image() {
    let job_at = |t: [f64; 3]| {
        job_from_json(
            &example_job(),
            &format!(
                r#"{{"scene":[{{"path":"room.gltf","transform":{{"translation":[{:e},{:e},{:e}]}}}}],
                "resolution":[96,72],"frames":{{"start":0,"end":48}},"render":{{"samples_per_pixel":4}}}}"#,
                t[0], t[1], t[2]
            ),
        )
        .unwrap()
    };
    let frames = [11, 12];
    let base = render_frames(&job_at([0.0; 3]), &frames);
    for t in [
        [1e4, 0.0, 0.0],
        [0.0, -1e5, 1e5],
        [1e6, 1e6, -1e6],
        [-1e6, 0.0, 3e6],
    ] {
        let imgs = render_frames(&job_at(t), &frames);
        for ((img, base), f) in imgs.iter().zip(&base).zip(frames) {
            let rms = relative_rms(img, base);
            let direct = rms_of(&img.direct, &base.direct);
            eprintln!(
                "moved {t:?}, frame {f}: relative RMS difference {rms:.2e}, direct {direct:.2e}"
            );
            assert!(
                rms < 0.01,
                "moved {t:?}, frame {f}: relative RMS difference {rms}"
            );
            assert!(
                direct < 0.01,
                "moved {t:?}, frame {f}: direct relative RMS {direct}"
            );
        }
    }
}

/// RMS of `a - b` relative to the RMS of `b`, over RGB.
fn rms_of(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let (mut d, mut n) = (0.0f64, 0.0f64);
    for (p, q) in a.iter().zip(b) {
        for k in 0..3 {
            d += ((p[k] - q[k]) as f64).powi(2);
            n += (q[k] as f64).powi(2);
        }
    }
    (d / n.max(1e-300)).sqrt()
}

/// The true limits of scene size (measured: the example room renders right from scale 1e-18
/// to 1e18 and wrong at 1e-19 and 1e19): within [`anchorage::scene::EXTENT_LIMITS`] a
/// scene renders like the same one at scale 1 (the room at 1e-13 and 1e13, beyond the 1e-9
/// to 1e9 of `example_is_the_same_image_at_any_scene_scale`); beyond them `validate` and
/// `render` refuse it with exit 2 and say why. (At scale 1e10 it rendered black with exit 0:
/// every triangle's f32 normal overflowed and was dropped as degenerate.)
#[test]
fn scene_sizes_render_within_the_limits_and_are_refused_beyond() {
    let job_at = |s: f64| {
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
    for s in [1e-13, 1e13] {
        let img = render(&job_at(s), 12);
        let rms = relative_rms(&img, &base);
        eprintln!("scale {s:e}: relative RMS difference {rms:.2e}");
        assert!(rms < 2e-3, "scale {s:e}: relative RMS difference {rms}");
    }
    let (min, max) = anchorage::scene::EXTENT_LIMITS;
    assert!(
        min <= 1e-12 && max >= 1e12,
        "the limits cover 1e-9..1e9 with margin"
    );
    let dir = tempdir();
    let room = example_job().parent().unwrap().join("room.gltf");
    // The room is 8.5 units across (camera included).
    for (s, why) in [(1e16, "too large"), (1e-16, "too small")] {
        let job = dir.path().join(format!("j{s:e}.json"));
        std::fs::write(
            &job,
            format!(
                r#"{{"scene":[{{"path":{:?},"transform":{{"scale":{s:e}}}}}],
                "resolution":[8,6],"output":{{"directory":{:?}}}}}"#,
                room.to_str().unwrap(),
                dir.path().join("out").to_str().unwrap()
            ),
        )
        .unwrap();
        for cmd in ["validate", "render"] {
            let o = run(&[cmd, job.to_str().unwrap()]);
            let err = stderr(&o);
            assert_eq!(o.status.code(), Some(2), "{cmd} at scale {s:e}: {err}");
            assert!(
                err.contains("scene's size") && err.contains(why) && err.contains("1e15"),
                "{cmd} at scale {s:e}: {err}"
            );
        }
    }
    assert!(!dir.path().join("out").exists(), "nothing rendered");
}

/// Render space's origin is the centre of the static set's box, in f64: it moves with the
/// set (not with the camera or the frame range), and the static set in render space is
/// centred on zero wherever the set sits in the world.
#[test]
fn render_space_is_centred_on_the_static_set() {
    let job_at = |t: f64, frames: &str| {
        job_from_json(
            &example_job(),
            &format!(
                r#"{{"scene":[{{"path":"room.gltf","transform":{{"translation":[{t:e},0,0]}}}}],"frames":{frames}}}"#
            ),
        )
        .unwrap()
    };
    let at_origin = job_at(0.0, r#"{"start":0,"end":48}"#).load_scene().unwrap();
    let o0 = at_origin.render_origin();
    for (t, frames) in [
        (1e6, r#"{"start":0,"end":48}"#),
        (1e6, r#"{"start":30,"end":31}"#),
    ] {
        let scene = job_at(t, frames).load_scene().unwrap();
        let o = scene.render_origin();
        assert!(
            (o - o0 - glam::DVec3::new(t, 0.0, 0.0)).abs().max_element() < 1e-9,
            "origin {o} for the room moved {t} vs {o0} at the origin"
        );
        let (lo, hi) = scene.statics().bounds;
        assert!(
            (lo + hi).abs().max_element() < 1e-5 * (hi - lo).max_element(),
            "static box {lo}..{hi} is not centred on render space's origin"
        );
    }
}

/// A glTF of one triangle seen by the camera node "cam" 3 units away. The camera's scale is
/// `scale`; when `animated`, it goes linearly from 1 at t = 0 to `scale` at t = 1.
fn camera_gltf(scale: [f32; 3], animated: bool) -> String {
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    let mut bin = floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    bin.extend(floats(&[0.0, 1.0]));
    bin.extend(floats(&[1.0, 1.0, 1.0]));
    bin.extend(floats(&scale));
    let (rest, animations) = if animated {
        (
            [1.0f32; 3],
            r#","animations":[{"samplers":[{"input":1,"output":2}],"channels":[{"sampler":0,"target":{"node":1,"path":"scale"}}]}]"#,
        )
    } else {
        (scale, "")
    };
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scenes":[{{"nodes":[0,1]}}],
        "nodes":[{{"name":"tri","mesh":0}},{{"name":"cam","camera":0,"translation":[0.3,0.3,3],"scale":{rest:?}}}],
        "cameras":[{{"type":"perspective","perspective":{{"yfov":0.8,"znear":0.1}}}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
        "accessors":[
          {{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
          {{"bufferView":0,"byteOffset":36,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
          {{"bufferView":0,"byteOffset":44,"componentType":5126,"count":2,"type":"VEC3"}}],
        "bufferViews":[{{"buffer":0,"byteLength":68}}],
        "buffers":[{{"byteLength":68,"uri":"data:application/octet-stream;base64,{}"}}]{animations}}}"#,
        base64_encode(&bin)
    )
}

/// Regression: a camera node scaled to zero rendered black frames with exit 0 (its far
/// clip depth was ∞ × 0 and its view axes NaN). `validate` and `render` refuse it with
/// exit 2, naming the node and the frame, and render nothing; a scale animated to zero is
/// refused at the frame it reaches zero (frame 24 at 24 fps), while the frames before it
/// load; a non-uniform, mirroring scale still places a view.
#[test]
fn a_camera_scaled_to_zero_is_refused_at_its_frame() {
    let dir = tempdir();
    let out = dir.path().join("out");
    let job = |name: &str, scale: [f32; 3], animated: bool, end: i32| {
        std::fs::write(dir.path().join(name), camera_gltf(scale, animated)).unwrap();
        let path = dir.path().join(format!("{name}.json"));
        std::fs::write(
            &path,
            format!(
                r#"{{"scene":[{{"path":"{name}"}}],"resolution":[8,6],"frames":{{"start":0,"end":{end}}},
                "method":{{"name":"direct"}},"output":{{"directory":{:?}}}}}"#,
                out.to_str().unwrap()
            ),
        )
        .unwrap();
        path
    };
    let still = job("still.gltf", [0.0; 3], false, 0);
    for cmd in ["validate", "render"] {
        let o = run(&[cmd, still.to_str().unwrap()]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{cmd}: {err}");
        assert!(
            err.contains("still.gltf")
                && err.contains("nodes[1] \"cam\"")
                && err.contains("frame 0"),
            "{cmd}: {err}"
        );
    }
    assert!(!out.exists(), "nothing rendered");
    let animated = job("animated.gltf", [0.0, 1.0, 1.0], true, 24);
    let o = run(&["validate", animated.to_str().unwrap()]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("nodes[1] \"cam\"") && err.contains("frame 24"),
        "{err}"
    );
    let before = job("before.gltf", [0.0, 1.0, 1.0], true, 23);
    let o = run(&["validate", before.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let mirrored = job("mirrored.gltf", [-2.0, 0.5, 1.0], false, 0);
    let o = run(&["render", mirrored.to_str().unwrap(), "-q"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
}

/// Regression: the example room moved 1e16 from the origin (by its layer's transform or by
/// a glTF root node) rendered black with exit 0, and at 1e15 lost part of it: f64 and the
/// f32 render space cannot place it. Beyond [`anchorage::scene::DISTANCE_LIMIT`] times its
/// size `validate` and `render` refuse it with exit 2, naming the layer; 1e6 from the
/// origin at scale 1e-3 (1.2e8 times its size) and 1e9 at scale 1 load.
#[test]
fn a_scene_too_far_from_the_origin_for_its_size_is_refused() {
    let limit = anchorage::scene::DISTANCE_LIMIT;
    assert!(
        limit >= 10.0 * 1e6 / 8.5e-3,
        "the room 1e6 from the origin at scale 1e-3 is within the limit with margin"
    );
    let dir = tempdir();
    let room = example_job().parent().unwrap().join("room.gltf");
    let job = |t: f64, s: f64| {
        let path = dir.path().join(format!("j{t:e}_{s:e}.json"));
        std::fs::write(
            &path,
            format!(
                r#"{{"scene":[{{"path":{:?},"transform":{{"translation":[{t:e},0,0],"scale":{s:e}}}}}],
                "resolution":[8,6],"output":{{"directory":{:?}}}}}"#,
                room.to_str().unwrap(),
                dir.path().join("out").to_str().unwrap()
            ),
        )
        .unwrap();
        path
    };
    for (t, s) in [(1e16, 1.0), (-1e15, 1.0), (1e11, 1.0), (1e8, 1e-3)] {
        let job = job(t, s);
        for cmd in ["validate", "render"] {
            let o = run(&[cmd, job.to_str().unwrap()]);
            let err = stderr(&o);
            assert_eq!(
                o.status.code(),
                Some(2),
                "{cmd} {t:e} at scale {s:e}: {err}"
            );
            assert!(
                err.contains("scene[0]") && err.contains("from the world origin"),
                "{cmd} {t:e} at scale {s:e}: {err}"
            );
        }
    }
    assert!(!dir.path().join("out").exists(), "nothing rendered");
    for (t, s) in [(1e6, 1e-3), (-1e6, 1e-3), (1e9, 1.0)] {
        let o = run(&["validate", job(t, s).to_str().unwrap()]);
        assert_eq!(
            o.status.code(),
            Some(0),
            "{t:e} at scale {s:e}: {}",
            stderr(&o)
        );
    }
}

/// The ground scene with its light node replaced by `nodes`, one or more (the light's node
/// carries `"extensions":{"KHR_lights_punctual":{"light":0}}`; the scene lists nodes 0, 1
/// and 2, so a third is 2's child)
/// and its light by `light`, rendered by the direct method from the usual camera.
fn ground_lit(dir: &std::path::Path, nodes: &str, light: &str) -> FrameImage {
    ground_lit_by(dir, nodes, light, "direct", 1.0)
}

/// [`ground_lit`] by `method`, its layer scaled by `scale` (the camera with it).
fn ground_lit_by(
    dir: &std::path::Path,
    nodes: &str,
    light: &str,
    method: &str,
    scale: f32,
) -> FrameImage {
    let gltf = ground_gltf(10.0)
        .replace(r#"{"type":"point","intensity":40}"#, light)
        .replace(
            r#"{"name":"light","translation":[-0.6,2,-0.2],"extensions":{"KHR_lights_punctual":{"light":0}}}]"#,
            &format!("{nodes}]"),
        );
    assert!(gltf.contains(nodes) && gltf.contains(light));
    std::fs::write(dir.join("lit.gltf"), gltf).unwrap();
    let (p, l) = (
        [1.2, 2.2, 2.6].map(|c| c * scale),
        [0.0, 0.1, 0.0].map(|c| c * scale),
    );
    let job = job_from_json(
        &dir.join("j.json"),
        &format!(
            r#"{{"scene":[{{"path":"lit.gltf","transform":{{"scale":{scale}}}}}],
            "camera":{{"position":{p:?},"look_at":{l:?},"yfov_deg":50}},
            "resolution":[32,24],"method":{{"name":"{method}"}},"render":{{"samples_per_pixel":4}}}}"#
        ),
    )
    .unwrap();
    render(&job, 0)
}

fn mean_direct(img: &FrameImage) -> f64 {
    img.direct.iter().map(|d| f64::from(d[1])).sum::<f64>() / img.direct.len() as f64
}

/// `KHR_lights_punctual`: a light's range does not change with its node's scale (it was
/// multiplied by it) but follows the job's layer transform, which converts units, and a light points along its node's −Z axis as the node's world matrix
/// maps it, which a non-uniform scale above a rotated node turns (the rotation taken from
/// the matrix's decomposition lit the ground 0.80 times as brightly).
#[test]
fn light_range_ignores_node_scale_and_direction_follows_the_world_matrix() {
    let dir = tempdir();
    let point = |range: f32| format!(r#"{{"type":"point","intensity":40,"range":{range}}}"#);
    let node = |scale: f32| {
        format!(
            r#"{{"name":"light","translation":[-0.6,2,-0.2],"scale":[{scale},{scale},{scale}],"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}}"#
        )
    };
    // The ground is 2 below the light: within a range of 3, beyond one of 1.5, whatever
    // the scale.
    assert!(mean_direct(&ground_lit(dir.path(), &node(0.5), &point(3.0))) > 0.01);
    assert_eq!(
        mean_direct(&ground_lit(dir.path(), &node(2.0), &point(1.5))),
        0.0
    );
    // A directional light on a child rotated −60° about x under a parent scaled (1, 3, 1)
    // points along (0, −2.598, −0.5): the same as a single node rotated by −79.11°.
    let sun = r#"{"type":"directional","intensity":3}"#;
    let (s, c) = (-60f64.to_radians() / 2.0).sin_cos();
    let sheared = ground_lit(
        dir.path(),
        &format!(
            r#"{{"name":"light","scale":[1,3,1],"children":[3]}},{{"rotation":[{s},0,0,{c}],"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}}"#
        ),
        sun,
    );
    let angle = (-2.598_076_211f64).atan2(0.5);
    let (s, c) = (angle / 2.0).sin_cos();
    let single = ground_lit(
        dir.path(),
        &format!(
            r#"{{"name":"light","rotation":[{s},0,0,{c}],"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}}"#
        ),
        sun,
    );
    // The range is in the file's units, which the job's layer transform scales: at half
    // size the light is 1 above the ground, within a range of 3 (1.5), beyond one of 1.5.
    let light = r#"{"name":"light","translation":[-0.6,2,-0.2],"extensions":{"KHR_lights_punctual":{"light":0}}}"#;
    let half = |range: f32| ground_lit_by(dir.path(), light, &point(range), "direct", 0.5);
    assert!(mean_direct(&half(3.0)) > 0.01);
    assert_eq!(mean_direct(&half(1.5)), 0.0);
    // Photons stop at the range too: nothing within 1 of the light, no light at all (the
    // photon methods' indirect light ignored the range).
    for method in ["brute-force", "anchors"] {
        let img = ground_lit_by(dir.path(), light, &point(1.0), method, 1.0);
        let lit = |aov: &[[f32; 3]]| aov.iter().flatten().filter(|&&v| v != 0.0).count();
        assert_eq!((lit(&img.direct), lit(&img.indirect)), (0, 0), "{method}");
    }
    let (a, b) = (mean_direct(&sheared), mean_direct(&single));
    eprintln!("direct light: {a:.5} under the sheared parent, {b:.5} by one rotation");
    assert!(b > 0.01 && (a - b).abs() < 1e-3 * b, "{a} against {b}");
}

/// A spot or directional light whose node is scaled to zero points nowhere and would light
/// nothing (the frame rendered black with exit 0): `validate` and `render` refuse it, naming
/// the node and the frame. A point light, which has no direction, is rendered.
#[test]
fn a_spot_or_directional_light_scaled_to_zero_is_refused() {
    let dir = tempdir();
    let validate = |light: &str| {
        let gltf = ground_gltf(10.0)
            .replace(r#"{"type":"point","intensity":40}"#, light)
            .replace(
                r#""translation":[-0.6,2,-0.2]"#,
                r#""translation":[-0.6,2,-0.2],"scale":[0,0,0]"#,
            );
        std::fs::write(dir.path().join("zero.gltf"), gltf).unwrap();
        let job = dir.path().join("zero.json");
        std::fs::write(
            &job,
            r#"{"scene":[{"path":"zero.gltf"}],
            "camera":{"position":[1.2,2.2,2.6],"look_at":[0,0.1,0],"yfov_deg":50},
            "resolution":[32,24],"method":{"name":"direct"}}"#,
        )
        .unwrap();
        let o = run(&["validate", job.to_str().unwrap()]);
        (o.status.code(), stderr(&o))
    };
    for light in [
        r#"{"type":"directional","intensity":3}"#,
        r#"{"type":"spot","intensity":40,"spot":{"outerConeAngle":0.5}}"#,
    ] {
        let (code, err) = validate(light);
        assert_eq!(code, Some(2), "{light}: {err}");
        assert!(
            err.contains("zero.gltf")
                && err.contains("nodes[2] \"light\"")
                && err.contains("frame 0"),
            "{light}: {err}"
        );
    }
    let (code, err) = validate(r#"{"type":"point","intensity":40}"#);
    assert_eq!(code, Some(0), "{err}");
}
