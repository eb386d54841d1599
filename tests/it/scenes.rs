//! Every third-party scene loads with the triangle and node counts its file declares, and
//! animated ones evaluate to the right transforms (values computed here by hand from the
//! file's own keyframe data).

use glam::{Mat4, Quat, Vec3};

use super::common::*;
use anchorage::geom::Motion;
use anchorage::scene::Scene;

const SCENES: &[&str] = &[
    "AnimatedCube/AnimatedCube.gltf",
    "AnimatedTriangle/AnimatedTriangle.gltf",
    "BoxAnimated/BoxAnimated.gltf",
    "CesiumMan/CesiumMan.gltf",
    "CesiumMilkTruck/CesiumMilkTruck.gltf",
    "RiggedSimple/RiggedSimple.gltf",
    "bevy_Cubes/Cubes.glb",
    "bevy_DepthOfFieldExample/DepthOfFieldExample.glb",
    "bevy_gltf_extras/gltf_extras.glb",
    "blenderio_03_all_animations/03_all_animations.gltf",
    "blenderio_07_nla-anim/07_nla-anim.gltf",
    "cornellbox_bevy/CornellBox.glb",
    "cornellbox_wgpu_renderer/cornell-box.glb",
    "sponza_lod4_trimesh/sponza_s_lod4.glb",
];

fn scene_job(rel: &str) -> anchorage::job::Job {
    let path = shared_scene(rel);
    let job_path = path.parent().unwrap().join("job.json");
    let name = path.file_name().unwrap().to_str().unwrap();
    job_from_json(
        &job_path,
        &format!(r#"{{"scene":[{{"path":"{name}"}}],"camera":{{"position":[0,0,5],"look_at":[0,0,0],"yfov_deg":40}}}}"#),
    )
    .unwrap()
}

#[test]
fn every_shared_scene_loads_with_the_counts_of_its_file() {
    for rel in SCENES {
        let job = scene_job(rel);
        let scene = job
            .load_scene_layers()
            .unwrap_or_else(|e| panic!("{rel}: {e}"));
        let raw = RawGltf::open(&shared_scene(rel));
        let layer = &scene.layers[0];
        assert_eq!(
            layer.nodes.len(),
            raw.json["nodes"].as_array().map_or(0, |n| n.len()),
            "{rel}: nodes"
        );
        let t = scene.time_range().map_or(0.0, |r| r.0);
        let loaded =
            scene.geometry(t, Motion::Static).len() + scene.geometry(t, Motion::Dynamic).len();
        assert_eq!(
            loaded + layer.degenerate_triangles,
            raw.triangle_count(),
            "{rel}: triangles ({} degenerate)",
            layer.degenerate_triangles
        );
        assert!(loaded > 0, "{rel}: no triangles");
    }
}

#[test]
fn sponza_has_its_187k_triangles() {
    let job = scene_job("sponza_lod4_trimesh/sponza_s_lod4.glb");
    let scene = job.load_scene_layers().unwrap();
    let n = scene.geometry(0.0, Motion::Static).len() + scene.layers[0].degenerate_triangles;
    assert_eq!(n, 187_364);
}

fn local(scene: &Scene, node: usize, t: f32) -> Mat4 {
    let l = &scene.layers[0];
    let w = l.world_matrices(t);
    match l.nodes[node].parent {
        Some(p) => w[p].inverse() * w[node],
        None => w[node],
    }
}

/// BoxAnimated: node 0's translation (LINEAR, keys from accessor 9 at times from accessor
/// 8) and node 2's rotation (LINEAR slerp, 180° about X between t = 1.25 and 2.5).
#[test]
fn box_animated_matches_its_keyframes() {
    let rel = "BoxAnimated/BoxAnimated.gltf";
    let scene = scene_job(rel).load_scene_layers().unwrap();
    let raw = RawGltf::open(&shared_scene(rel));
    let times = raw.floats(8);
    let keys = raw.floats(9);
    for (k, &t) in times.iter().enumerate() {
        let got = scene.layers[0].world_matrices(t)[0].w_axis.truncate();
        let want = Vec3::new(keys[3 * k], keys[3 * k + 1], keys[3 * k + 2]);
        assert!(
            (got - want).length() < 1e-5,
            "key {k} at t={t}: {got} != {want}"
        );
    }
    // Halfway between keys 1 and 2: the average of the two translations.
    let tm = 0.5 * (times[1] + times[2]);
    let want = 0.5 * (Vec3::from_slice(&keys[3..6]) + Vec3::from_slice(&keys[6..9]));
    let got = scene.layers[0].world_matrices(tm)[0].w_axis.truncate();
    assert!((got - want).length() < 1e-5, "{got} != {want}");
    // Rotation of node 2 halfway through its 180° turn: 90° about +X, so +Y maps to +Z.
    let r = local(&scene, 2, 1.875);
    let y = r.transform_vector3(Vec3::Y);
    assert!((y - Vec3::Z).length() < 1e-5, "{y}");
    // Before the first key the rotation holds the first key (the identity).
    assert!(local(&scene, 2, 0.0).abs_diff_eq(Mat4::IDENTITY, 1e-6));
    // Animated nodes are dynamic; node 3 (a mesh under no animated node) is static.
    let l = &scene.layers[0];
    assert_eq!(l.nodes[2].motion, Motion::Dynamic);
}

/// blenderio_03: the Sphere's translation is CUBICSPLINE. Evaluate the Hermite basis by hand
/// from the file's in-tangent / value / out-tangent triplets.
#[test]
fn cubic_spline_translation_matches_hand_computed_hermite() {
    let rel = "blenderio_03_all_animations/03_all_animations.gltf";
    let scene = scene_job(rel).load_scene_layers().unwrap();
    let raw = RawGltf::open(&shared_scene(rel));
    let anim = raw.json["animations"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["name"] == "SphereAction")
        .unwrap();
    let sampler = &anim["samplers"][anim["channels"][0]["sampler"].as_u64().unwrap() as usize];
    assert_eq!(sampler["interpolation"], "CUBICSPLINE");
    let times = raw.floats(sampler["input"].as_u64().unwrap() as usize);
    let out = raw.floats(sampler["output"].as_u64().unwrap() as usize);
    let node = anim["channels"][0]["target"]["node"].as_u64().unwrap() as usize;
    // Element e of key k: in-tangent (e=0), value (1), out-tangent (2), each a Vec3.
    let el = |k: usize, e: usize| Vec3::from_slice(&out[(3 * k + e) * 3..(3 * k + e) * 3 + 3]);
    for k in 0..times.len() - 1 {
        for s in [0.25f32, 0.5, 0.8] {
            let td = times[k + 1] - times[k];
            let t = times[k] + s * td;
            let p = (2.0 * s.powi(3) - 3.0 * s * s + 1.0) * el(k, 1)
                + td * (s.powi(3) - 2.0 * s * s + s) * el(k, 2)
                + (-2.0 * s.powi(3) + 3.0 * s * s) * el(k + 1, 1)
                + td * (s.powi(3) - s * s) * el(k + 1, 0);
            let got = local(&scene, node, t).w_axis.truncate();
            assert!(
                (got - p).length() <= 1e-5 * p.length().max(1.0),
                "key {k} s {s}: {got} != {p}"
            );
        }
    }
    // At a key time the value itself.
    let got = local(&scene, node, times[1]).w_axis.truncate();
    assert!((got - el(1, 1)).length() < 1e-5);
}

/// Skinning moves vertices with the joints: CesiumMan's triangles differ between two times,
/// and stay finite.
#[test]
fn skinned_mesh_deforms_over_time() {
    let rel = "CesiumMan/CesiumMan.gltf";
    let scene = scene_job(rel).load_scene_layers().unwrap();
    let (t0, t1) = scene.time_range().unwrap();
    let a = scene.geometry(t0, Motion::Dynamic);
    let b = scene.geometry(0.5 * (t0 + t1), Motion::Dynamic);
    assert_eq!(a.len(), b.len());
    assert!(a.len() > 1000);
    let moved = a
        .triangles
        .iter()
        .zip(&b.triangles)
        .filter(|(p, q)| (p.v0 - q.v0).length() > 1e-4)
        .count();
    assert!(
        moved > a.len() / 4,
        "only {moved} of {} triangles moved",
        a.len()
    );
    assert!(
        b.triangles
            .iter()
            .all(|t| t.v0.is_finite() && t.v1.is_finite() && t.v2.is_finite())
    );
    // Skinned with the rest pose at identity joints: the mesh node's transform is ignored,
    // so the bind pose is what the inverse bind matrices undo; CesiumMan stands ~1.5 units.
    let (lo, hi) = a
        .triangles
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), t| {
            (lo.min(t.v0.y).min(t.v0.z), hi.max(t.v0.y).max(t.v0.z))
        });
    assert!(hi - lo > 1.0 && hi - lo < 3.0, "extent {lo}..{hi}");
}

/// A skinned character closes up at every pose: the triangles that meet at a vertex split
/// for its texture move with the same joints and weights, so they still share it bit for
/// bit, and visibility detection leaves out the triangles facing away from a record.
#[test]
fn a_skinned_character_stays_closed_as_it_moves() {
    let scene = scene_job("CesiumMan/CesiumMan.gltf")
        .load_scene_layers()
        .unwrap();
    let (t0, t1) = scene.time_range().unwrap();
    for t in [t0, 0.37 * (t0 + t1), 0.5 * (t0 + t1), t1] {
        let set = anchorage::visibility::DynamicSet::new(&scene.geometry(t, Motion::Dynamic));
        assert_eq!(set.closed, [true], "at t = {t}");
    }
}

/// Morph targets: a scene written here with one target animated from weight 0 to 1.
#[test]
fn morph_target_weights_move_vertices() {
    let dir = tempdir();
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    let mut bin = floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]); // positions
    bin.extend(floats(&[0.0, 0.0, 2.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0])); // target: +2 z
    bin.extend(floats(&[0.0, 1.0])); // times
    bin.extend(floats(&[0.0, 1.0])); // weights
    let b64 = base64_encode(&bin);
    let gltf = format!(
        r#"{{"asset":{{"version":"2.0"}},"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0,"name":"m"}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"targets":[{{"POSITION":1}}]}}],"weights":[0.0]}}],
        "animations":[{{"samplers":[{{"input":2,"output":3}}],"channels":[{{"sampler":0,"target":{{"node":0,"path":"weights"}}}}]}}],
        "accessors":[
          {{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
          {{"bufferView":0,"byteOffset":36,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,2],"max":[0,0,2]}},
          {{"bufferView":0,"byteOffset":72,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
          {{"bufferView":0,"byteOffset":80,"componentType":5126,"count":2,"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteLength":88}}],
        "buffers":[{{"byteLength":88,"uri":"data:application/octet-stream;base64,{b64}"}}]}}"#
    );
    std::fs::write(dir.path().join("m.gltf"), gltf).unwrap();
    let job = job_from_json(&dir.path().join("j.json"), r#"{"scene":[{"path":"m.gltf"}],"camera":{"position":[0,0,5],"look_at":[0,0,0],"yfov_deg":40}}"#).unwrap();
    let scene = job.load_scene_layers().unwrap();
    assert_eq!(scene.layers[0].nodes[0].motion, Motion::Dynamic);
    for (t, z) in [(0.0, 0.0), (0.25, 0.5), (1.0, 2.0)] {
        let g = scene.geometry(t, Motion::Dynamic);
        assert!(
            (g.triangles[0].v0.z - z).abs() < 1e-6,
            "t={t}: {}",
            g.triangles[0].v0.z
        );
    }
}

pub fn base64_encode(data: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in data.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                s.push(T[(n >> (18 - 6 * k)) as usize & 63] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

/// Layer transforms compose like USD references: a translated, scaled layer moves its prims.
#[test]
fn layer_transform_applies_to_prims() {
    let rel = "BoxAnimated/BoxAnimated.gltf";
    let path = shared_scene(rel);
    let job = job_from_json(
        &path.parent().unwrap().join("j.json"),
        r#"{"scene":[{"path":"BoxAnimated.gltf","transform":{"translation":[10,0,0],"scale":2}}],"camera":{"position":[0,0,5],"look_at":[0,0,0],"yfov_deg":40}}"#,
    )
    .unwrap();
    let moved = job.load_scene_layers().unwrap();
    let plain = scene_job(rel).load_scene_layers().unwrap();
    let a = plain.layers[0].world_matrices(1.0)[0];
    let b = moved.layers[0].world_matrices(1.0)[0];
    let expect = Mat4::from_scale_rotation_translation(
        Vec3::splat(2.0),
        Quat::IDENTITY,
        Vec3::new(10.0, 0.0, 0.0),
    ) * a;
    assert!(b.abs_diff_eq(expect, 1e-5));
}

#[test]
fn sha256_matches_the_standard_test_vectors() {
    // FIPS 180-4 examples: empty, one block, two blocks.
    assert_eq!(
        sha256_hex(b""),
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
    );
    assert_eq!(
        sha256_hex(b"abc"),
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    );
    assert_eq!(
        sha256_hex(b"abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
        "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1"
    );
}

/// Every scene file the tests and the Sponza benches (`benches/sponza/*.json`) read is in
/// `tests/scenes/manifest.tsv`, and every row says where the file comes from.
#[test]
fn scene_manifest_lists_every_scene_read_with_its_source() {
    let manifest = scene_manifest();
    let listed =
        |folder: &str, file: &str| manifest.iter().any(|e| e.scene == folder && e.file == file);
    for rel in SCENES {
        let (folder, file) = rel.split_once('/').unwrap();
        assert!(
            listed(folder, file),
            "{rel} is not in tests/scenes/manifest.tsv"
        );
    }
    let jobs = std::fs::read_dir(root().join("benches/sponza")).unwrap();
    for job in jobs.map(|e| e.unwrap().path()) {
        if job.extension().is_none_or(|e| e != "json") {
            continue;
        }
        let bench: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&job).unwrap()).unwrap();
        let Some(layers) = bench["scene"].as_array() else {
            continue;
        };
        for layer in layers {
            let path = layer["path"].as_str().unwrap();
            if let Some((_, rel)) = path.split_once("shared/scenes/") {
                let (folder, file) = rel.split_once('/').unwrap();
                assert!(
                    listed(folder, file),
                    "{}: bench scene {rel} is not in the manifest",
                    job.display()
                );
            }
        }
    }
    let hex = |s: &str, n: usize| s.len() == n && s.bytes().all(|b| b.is_ascii_hexdigit());
    for e in &manifest {
        let what = format!("{}/{}", e.scene, e.file);
        assert!(hex(&e.sha256, 64), "{what}: sha256");
        assert!(hex(&e.commit, 40), "{what}: commit");
        assert!(e.repository.split('/').count() == 2, "{what}: repository");
        assert!(
            !e.path.is_empty() && !e.licence.is_empty(),
            "{what}: path, licence"
        );
    }
}

/// The scenes found on disk are the ones the manifest pins, byte for byte.
#[test]
fn scene_files_match_the_manifest_hashes() {
    let dir = scenes_dir();
    if !dir.is_dir() {
        eprintln!(
            "skipped: no scenes at {} (fetch them with `{FETCH_SCENES}`)",
            dir.display()
        );
        return;
    }
    let mut wrong = Vec::new();
    for e in scene_manifest() {
        let path = dir.join(&e.scene).join(&e.file);
        match std::fs::read(&path) {
            Err(err) => wrong.push(format!("{}: {err}", path.display())),
            Ok(bytes) if bytes.len() as u64 != e.bytes => wrong.push(format!(
                "{}: {} bytes, the manifest says {}",
                path.display(),
                bytes.len(),
                e.bytes
            )),
            Ok(bytes) if sha256_hex(&bytes) != e.sha256 => wrong.push(format!(
                "{}: SHA-256 differs from the manifest",
                path.display()
            )),
            Ok(_) => {}
        }
    }
    assert!(
        wrong.is_empty(),
        "third-party scenes differ from tests/scenes/manifest.tsv (fetch them again with \
         `{FETCH_SCENES}`):\n  {}",
        wrong.join("\n  ")
    );
}

/// Regression: the glTF's `scene` was ignored and every node with a mesh, light or camera
/// was rendered. Only the subtrees of its default scene's root nodes are (glTF 2.0 §3.5):
/// here `scene` is 1, which holds "shown" (and its child "lamp") and "cam_in", and leaves out
/// "hidden", "lamp_out" and "cam_out" (listed first, so it was the default camera). An
/// animation of a left-out node still loads, and a file without `scenes` shows every
/// parentless node's subtree.
#[test]
fn only_the_nodes_of_the_default_scene_are_rendered() {
    let dir = tempdir();
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    let mut bin = floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]); // positions
    bin.extend(floats(&[0.0, 1.0])); // times
    bin.extend(floats(&[0.0, 0.0, 0.0, 0.0, 0.0, 1.0])); // translations
    let b64 = base64_encode(&bin);
    let gltf = |scenes: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},{scenes}"extensionsUsed":["KHR_lights_punctual"],
            "extensions":{{"KHR_lights_punctual":{{"lights":[{{"type":"point","intensity":5}}]}}}},
            "nodes":[{{"name":"cam_out","camera":0,"translation":[0,0,4]}},
                     {{"name":"hidden","mesh":0,"translation":[5,0,0]}},
                     {{"name":"lamp_out","extensions":{{"KHR_lights_punctual":{{"light":0}}}}}},
                     {{"name":"shown","mesh":0,"children":[4]}},
                     {{"name":"lamp","translation":[0,0,2],"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}},
                     {{"name":"cam_in","camera":0,"translation":[0,0,3]}}],
            "cameras":[{{"type":"perspective","perspective":{{"yfov":0.8,"znear":0.1}}}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
            "animations":[{{"name":"slide","samplers":[{{"input":1,"output":2}}],"channels":[{{"sampler":0,"target":{{"node":1,"path":"translation"}}}}]}}],
            "accessors":[
              {{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
              {{"bufferView":0,"byteOffset":36,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
              {{"bufferView":0,"byteOffset":44,"componentType":5126,"count":2,"type":"VEC3"}}],
            "bufferViews":[{{"buffer":0,"byteLength":68}}],
            "buffers":[{{"byteLength":68,"uri":"data:application/octet-stream;base64,{b64}"}}]}}"#
        )
    };
    let load = |name: &str, scenes: &str| {
        std::fs::write(dir.path().join(name), gltf(scenes)).unwrap();
        job_from_json(
            &dir.path().join("j.json"),
            &format!(r#"{{"scene":[{{"path":"{name}"}}]}}"#),
        )
        .unwrap()
        .load_scene()
        .unwrap_or_else(|e| panic!("{name}: {e}"))
    };
    let two = load(
        "two.gltf",
        r#""scene":1,"scenes":[{"nodes":[0,1,2,3,5]},{"nodes":[3,5]}],"#,
    );
    let t = 0.5;
    let triangles = two.geometry(t, Motion::Static).len() + two.geometry(t, Motion::Dynamic).len();
    assert_eq!(triangles, 1, "only \"shown\" is rendered, not \"hidden\"");
    let lights = two.lights(t);
    assert_eq!(lights.len(), 1, "only \"lamp\" lights the scene");
    assert!((lights[0].position.z - 2.0).abs() < 1e-6);
    assert!(
        matches!(
            two.camera,
            Some(anchorage::scene::CameraChoice::Node { node: 5, .. })
        ),
        "the default camera is \"cam_in\", not \"cam_out\": {:?}",
        two.camera
    );
    let warnings = two.warnings().join("\n");
    assert!(
        warnings.contains("\"cam_out\"")
            && warnings.contains("\"hidden\"")
            && warnings.contains("\"lamp_out\""),
        "{warnings}"
    );
    // A job naming a camera node outside the scene is told so.
    let e = job_from_json(
        &dir.path().join("j.json"),
        r#"{"scene":[{"path":"two.gltf"}],"camera":{"node":"cam_out"}}"#,
    )
    .unwrap()
    .load_scene()
    .expect_err("cam_out is outside the scene")
    .to_string();
    assert!(
        e.contains("camera.node") && e.contains("outside the file's scene"),
        "{e}"
    );
    let all = load("none.gltf", "");
    let triangles = all.geometry(t, Motion::Static).len() + all.geometry(t, Motion::Dynamic).len();
    assert_eq!(
        triangles, 2,
        "without scenes, every parentless node is shown"
    );
    assert_eq!(all.lights(t).len(), 2);
    assert!(
        all.warnings().iter().all(|w| !w.contains("scene")),
        "{:?}",
        all.warnings()
    );
}
