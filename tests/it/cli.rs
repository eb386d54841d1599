//! The command line: exit codes, messages naming the culprit, no output on bad input,
//! identical bytes for any thread count.

use std::path::Path;

use super::common::*;
use super::scenes::base64_encode;

fn exr_files(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// One triangle mesh (plus a light and camera) with the given positions and indices.
fn tiny_gltf(positions: &[f32], indices: &[u32]) -> String {
    let mut bin: Vec<u8> = positions.iter().flat_map(|f| f.to_le_bytes()).collect();
    let pos_len = bin.len();
    let bound = |k: usize, f: fn(f32, f32) -> f32| {
        positions
            .iter()
            .skip(k)
            .step_by(3)
            .filter(|v| v.is_finite())
            .copied()
            .reduce(f)
            .unwrap_or(0.0)
    };
    let (min, max) = (
        [0, 1, 2].map(|k| bound(k, f32::min)),
        [0, 1, 2].map(|k| bound(k, f32::max)),
    );
    bin.extend(indices.iter().flat_map(|i| i.to_le_bytes()));
    format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_lights_punctual"],
        "extensions":{{"KHR_lights_punctual":{{"lights":[{{"type":"point","intensity":10}}]}}}},
        "scenes":[{{"nodes":[0,1,2]}}],
        "nodes":[{{"name":"tri","mesh":0}},{{"name":"lamp","translation":[0,0,2],"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}},
                 {{"name":"cam","camera":0,"translation":[0,0,3]}}],
        "cameras":[{{"type":"perspective","perspective":{{"yfov":0.8,"znear":0.1}}}}],
        "meshes":[{{"name":"trimesh","primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":{min:?},"max":{max:?}}},
                     {{"bufferView":0,"byteOffset":{pos_len},"componentType":5125,"count":{},"type":"SCALAR"}}],
        "bufferViews":[{{"buffer":0,"byteLength":{}}}],
        "buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}]}}"#,
        positions.len() / 3,
        indices.len(),
        bin.len(),
        bin.len(),
        base64_encode(&bin)
    )
}

/// Renders `job_text` (scene files already in `dir`) and returns (exit code, stderr).
fn render_in(dir: &Path, job_text: &str, extra: &[&str]) -> (i32, String) {
    let job = dir.join("job.json");
    std::fs::write(&job, job_text).unwrap();
    let mut args = vec!["render", job.to_str().unwrap(), "--quiet"];
    args.extend(extra);
    let o = run(&args);
    (o.status.code().unwrap_or(-1), stderr(&o))
}

/// One triangle's positions.
const TRIANGLE: [f32; 9] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// Writes `s.gltf`, one triangle, into `dir` (the scene of [`JOB`]).
fn write_triangle(dir: &Path) {
    std::fs::write(dir.join("s.gltf"), tiny_gltf(&TRIANGLE, &[0, 1, 2])).unwrap();
}

const JOB: &str =
    r#"{"scene":[{"path":"s.gltf"}],"resolution":[16,16],"output":{"directory":"out"}}"#;

fn assert_bad_input(dir: &Path, code: i32, err: &str, culprits: &[&str]) {
    assert_eq!(code, 2, "exit code; stderr: {err}");
    for c in culprits {
        assert!(err.contains(c), "message should name {c:?}: {err}");
    }
    assert!(
        exr_files(&dir.join("out"))
            .iter()
            .all(|f| !f.ends_with(".exr")),
        "no output on bad input"
    );
}

#[test]
fn truncated_glb_is_bad_input() {
    let dir = tempdir();
    let glb = std::fs::read(shared_scene("bevy_Cubes/Cubes.glb")).unwrap();
    std::fs::write(dir.path().join("s.glb"), &glb[..glb.len() / 2]).unwrap();
    let (code, err) = render_in(dir.path(), &JOB.replace("s.gltf", "s.glb"), &[]);
    assert_bad_input(dir.path(), code, &err, &["s.glb"]);
}

#[test]
fn missing_bin_is_bad_input() {
    let dir = tempdir();
    std::fs::copy(
        shared_scene("BoxAnimated/BoxAnimated.gltf"),
        dir.path().join("s.gltf"),
    )
    .unwrap();
    let (code, err) = render_in(dir.path(), JOB, &[]);
    assert_bad_input(
        dir.path(),
        code,
        &err,
        &["s.gltf", "buffers[0]", "BoxAnimated0.bin"],
    );
}

#[test]
fn nan_positions_are_bad_input() {
    let dir = tempdir();
    std::fs::write(
        dir.path().join("s.gltf"),
        tiny_gltf(
            &[0.0, 0.0, 0.0, 1.0, f32::NAN, 0.0, 0.0, 1.0, 0.0],
            &[0, 1, 2],
        ),
    )
    .unwrap();
    let (code, err) = render_in(dir.path(), JOB, &[]);
    assert_bad_input(
        dir.path(),
        code,
        &err,
        &["s.gltf", "meshes[0] \"trimesh\"", "POSITION 1"],
    );
}

#[test]
fn out_of_range_indices_are_bad_input() {
    let dir = tempdir();
    std::fs::write(
        dir.path().join("s.gltf"),
        tiny_gltf(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0], &[0, 1, 7]),
    )
    .unwrap();
    let (code, err) = render_in(dir.path(), JOB, &[]);
    assert_bad_input(dir.path(), code, &err, &["index 7"]);
}

#[test]
fn degenerate_triangles_are_skipped_with_a_warning() {
    let dir = tempdir();
    // A good triangle, a collinear one, and one with a repeated vertex.
    let p = [
        -1.0, -1.0, 0.0, 1.0, -1.0, 0.0, 0.0, 1.0, 0.0, 2.0, 2.0, 0.0, 3.0, 3.0, 0.0,
    ];
    std::fs::write(
        dir.path().join("s.gltf"),
        tiny_gltf(&p, &[0, 1, 2, 0, 3, 4, 1, 1, 2]),
    )
    .unwrap();
    let (code, err) = render_in(dir.path(), JOB, &[]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("2 degenerate (zero-area) triangles skipped"),
        "{err}"
    );
    assert!(dir.path().join("out/job.0000.exr").is_file());
}

#[test]
fn unknown_job_keys_are_bad_input() {
    let dir = tempdir();
    write_triangle(dir.path());
    let (code, err) = render_in(
        dir.path(),
        &JOB.replace(r#""resolution""#, r#""resolutoin""#),
        &[],
    );
    assert_bad_input(dir.path(), code, &err, &["job.json", "resolutoin"]);
    let (code, err) = render_in(
        dir.path(),
        &JOB.replace(
            r#""directory":"out""#,
            r#""directory":"out","fromat":"exr""#,
        ),
        &[],
    );
    assert_bad_input(dir.path(), code, &err, &["fromat"]);
}

#[test]
fn frame_range_outside_the_animation_is_bad_input() {
    let dir = tempdir();
    for f in ["BoxAnimated.gltf", "BoxAnimated0.bin"] {
        std::fs::copy(shared_scene("BoxAnimated").join(f), dir.path().join(f)).unwrap();
    }
    let job = r#"{"scene":[{"path":"BoxAnimated.gltf"}],"camera":{"position":[0,0,8],"look_at":[0,0,0],"yfov_deg":40},
        "resolution":[16,16],"frames":{"start":0,"end":200},"output":{"directory":"out"}}"#;
    let (code, err) = render_in(dir.path(), job, &[]);
    assert_bad_input(
        dir.path(),
        code,
        &err,
        &["frames.end", "frame 200", "outside the animation"],
    );
    // --frames overrides the job and is checked the same way.
    let (code, err) = render_in(dir.path(), job, &["--frames=-50--40"]);
    assert_bad_input(dir.path(), code, &err, &["frames.start"]);
    let (code, _) = render_in(dir.path(), job, &["--frames", "10-11"]);
    assert_eq!(code, 0);
}

#[test]
fn unwritable_output_directory_is_bad_input() {
    let dir = tempdir();
    write_triangle(dir.path());
    // A path below a regular file can never be created, not even by root.
    std::fs::write(dir.path().join("file"), b"").unwrap();
    let bad = dir.path().join("file/frames");
    let (code, err) = render_in(dir.path(), JOB, &["--out", bad.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("file/frames"), "{err}");
}

#[test]
fn required_unsupported_extension_is_bad_input() {
    let dir = tempdir();
    let g = tiny_gltf(&TRIANGLE, &[0, 1, 2]).replace(r#""extensionsUsed":["KHR_lights_punctual"]"#, r#""extensionsUsed":["KHR_lights_punctual","KHR_draco_mesh_compression","EXT_fancy"],"extensionsRequired":["KHR_draco_mesh_compression"]"#);
    std::fs::write(dir.path().join("s.gltf"), &g).unwrap();
    let (code, err) = render_in(dir.path(), JOB, &[]);
    assert_bad_input(
        dir.path(),
        code,
        &err,
        &["extensionsRequired", "KHR_draco_mesh_compression"],
    );
    // Only used (optional): a warning listing it.
    std::fs::write(
        dir.path().join("s.gltf"),
        g.replace(
            r#","extensionsRequired":["KHR_draco_mesh_compression"]"#,
            "",
        ),
    )
    .unwrap();
    let (code, err) = render_in(dir.path(), JOB, &[]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("optional extensions ignored: KHR_draco_mesh_compression, EXT_fancy"),
        "{err}"
    );
}

#[test]
fn same_bytes_with_one_and_two_threads() {
    let names: Vec<String> = (3..=5)
        .flat_map(|f| ["exr", "png"].map(|ext| format!("room.{f:04}.{ext}")))
        .collect();
    assert_same_bytes_with_1_and_2_threads(
        &example_job(),
        &["--frames", "3-5", "--preview"],
        &names,
    );
}

#[test]
fn stats_json_has_the_documented_keys() {
    let dir = tempdir();
    let o = run(&[
        "render",
        example_job().to_str().unwrap(),
        "--frames",
        "2",
        "--out",
        dir.path().to_str().unwrap(),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("room.0002.json")).unwrap()).unwrap();
    let schema: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root().join("schemas/stats.schema.json")).unwrap())
            .unwrap();
    // Every key the schema requires is present, recursively, and nothing else.
    fn check(v: &serde_json::Value, s: &serde_json::Value, at: &str) {
        if let Some(props) = s["properties"].as_object() {
            let obj = v
                .as_object()
                .unwrap_or_else(|| panic!("{at} is not an object"));
            for r in s["required"].as_array().unwrap() {
                assert!(obj.contains_key(r.as_str().unwrap()), "{at}.{r} missing");
            }
            for (k, x) in obj {
                let sub = props
                    .get(k)
                    .unwrap_or_else(|| panic!("{at}.{k} not in the schema"));
                check(x, sub, &format!("{at}.{k}"));
            }
        }
    }
    check(&v, &schema, "stats");
    assert_eq!(v["frame"], 2);
    assert!(v["counts"]["camera_rays"].as_u64().unwrap() == 320 * 240 * 16);
}

#[test]
fn inspect_and_validate() {
    let o = run(&[
        "inspect",
        shared_scene("BoxAnimated/BoxAnimated.gltf")
            .to_str()
            .unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("dynamic") && text.contains("untagged, moved by animation"),
        "{text}"
    );
    assert!(text.contains("time range: 0.0000..3.7083 s"), "{text}");
    let o = run(&["validate", example_job().to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = run(&["render", "/nonexistent/job.json"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("/nonexistent/job.json"));
}

#[test]
fn out_of_range_method_settings_are_bad_input() {
    let dir = tempdir();
    write_triangle(dir.path());
    let (code, err) = render_in(
        dir.path(),
        &JOB.replace(
            r#""resolution""#,
            r#""method":{"neighbour_clamp":-1},"resolution""#,
        ),
        &[],
    );
    assert_bad_input(dir.path(), code, &err, &["job.json", "neighbour_clamp"]);
}
