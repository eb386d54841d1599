//! Malformed glTF: every index, type, count and size a file declares is checked before it is
//! read, and refused with exit 2 naming the file and the element; the fuzzer's crashers stay
//! fixed, and a short in-process fuzz finds no panic.

use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use super::common::*;

#[allow(dead_code)]
#[path = "../../examples/fuzz.rs"]
mod fuzz;

/// `anchorage inspect FILE`: its exit code and stderr.
fn inspect(file: &Path) -> (Option<i32>, String) {
    let o = bin()
        .arg("inspect")
        .arg(file)
        .output()
        .expect("run anchorage");
    (o.status.code(), stderr(&o))
}

/// Inspecting `file` fails with exit 2 and a message naming the file and containing every
/// one of `names`.
fn assert_refused(file: &Path, names: &[&str]) {
    let (code, err) = inspect(file);
    assert_eq!(
        code,
        Some(2),
        "{}: exit {code:?}, stderr:\n{err}",
        file.display()
    );
    let stem = file.file_name().unwrap().to_string_lossy();
    assert!(err.contains(&*stem), "error does not name {stem}: {err}");
    for n in names {
        assert!(err.contains(n), "error does not name {n}: {err}");
    }
    assert!(!err.contains("internal error"), "{err}");
}

fn data(name: &str) -> PathBuf {
    root().join("tests/data/malformed").join(name)
}

#[test]
fn reproducer_p1_animation_target_node_out_of_range() {
    assert_refused(
        &data("P1_anim_target_node_oob.gltf"),
        &["animations[0].channels[0].target.node", "nodes[5]"],
    );
}

#[test]
fn reproducer_p3_primitive_naming_missing_accessor() {
    assert_refused(
        &data("P3_primitive_without_accessors.gltf"),
        &[
            "meshes[0].primitives[0].attributes.POSITION",
            "accessors[2]",
        ],
    );
}

#[test]
fn reproducer_p4_float_index_accessor() {
    assert_refused(
        &data("P4_indices_float_accessor.gltf"),
        &["meshes[0].primitives[0].indices", "FLOAT"],
    );
}

#[test]
fn reproducer_c1_sparse_count_2_pow_31_fails_before_allocating() {
    assert_refused(
        &data("C1_sparse_accessor_2pow31.gltf"),
        &["accessors[0].count", "2147483648"],
    );
}

/// A valid one-triangle scene: positions (accessor 0), normals (1), texture coordinates (2),
/// an animated node (input 3, translation output 4), all in `tri.bin` beside it.
fn triangle() -> Value {
    json!({
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": 156, "uri": "tri.bin"}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 36},
            {"buffer": 0, "byteOffset": 36, "byteLength": 36},
            {"buffer": 0, "byteOffset": 72, "byteLength": 24},
            {"buffer": 0, "byteOffset": 96, "byteLength": 8},
            {"buffer": 0, "byteOffset": 104, "byteLength": 24},
            {"buffer": 0, "byteOffset": 128, "byteLength": 28}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC2"},
            {"bufferView": 3, "componentType": 5126, "count": 2, "type": "SCALAR",
             "min": [0], "max": [1]},
            {"bufferView": 4, "componentType": 5126, "count": 2, "type": "VEC3"}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}}]}],
        "nodes": [{"mesh": 0, "name": "tri"}, {"name": "empty"}, {"name": "other"}],
        "scenes": [{"nodes": [0, 1, 2]}],
        "scene": 0,
        "animations": [{
            "samplers": [{"input": 3, "output": 4}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}]
        }]
    })
}

/// Writes `doc` as `scene.gltf` with its buffer into `dir`.
fn write(dir: &Path, doc: &Value) -> PathBuf {
    let mut bin: Vec<u8> = Vec::new();
    let f = |v: &[f32], bin: &mut Vec<u8>| bin.extend(v.iter().flat_map(|x| x.to_le_bytes()));
    f(&[0., 0., 0., 1., 0., 0., 0., 1., 0.], &mut bin);
    f(&[0., 0., 1., 0., 0., 1., 0., 0., 1.], &mut bin);
    f(&[0., 0., 1., 0., 0., 1.], &mut bin);
    f(&[0., 1.], &mut bin);
    f(&[0., 0., 0., 1., 0., 0.], &mut bin);
    bin.resize(156, 0);
    std::fs::write(dir.join("tri.bin"), bin).unwrap();
    let path = dir.join("scene.gltf");
    std::fs::write(&path, serde_json::to_vec_pretty(doc).unwrap()).unwrap();
    path
}

/// `triangle()` changed by `edit` is refused naming `names`.
fn refused_after(edit: impl FnOnce(&mut Value), names: &[&str]) {
    let dir = tempdir();
    let mut doc = triangle();
    edit(&mut doc);
    assert_refused(&write(dir.path(), &doc), names);
}

#[test]
fn the_unchanged_triangle_loads() {
    let dir = tempdir();
    let (code, err) = inspect(&write(dir.path(), &triangle()));
    assert_eq!(code, Some(0), "{err}");
}

#[test]
fn a_count_of_2_pow_62_does_not_overflow_and_blames_the_accessor() {
    refused_after(
        |d| d["accessors"][1]["count"] = json!(1u64 << 62),
        &["accessors[1].count", "4611686018427387904"],
    );
}

#[test]
fn attribute_counts_must_match_position() {
    refused_after(
        |d| d["accessors"][2]["count"] = json!(2),
        &[
            "meshes[0].primitives[0].attributes.TEXCOORD_0",
            "POSITION has 3",
        ],
    );
}

#[test]
fn attribute_component_types_are_checked_per_semantic() {
    // Normals as unsigned ints.
    refused_after(
        |d| d["accessors"][1]["componentType"] = json!(5125),
        &["meshes[0].primitives[0].attributes.NORMAL", "UNSIGNED_INT"],
    );
    // Texture coordinates as integers that are not normalized.
    refused_after(
        |d| {
            d["accessors"][2]["componentType"] = json!(5121);
        },
        &["attributes.TEXCOORD_0", "normalized UNSIGNED_BYTE"],
    );
    // Joints as floats.
    refused_after(
        |d| {
            d["accessors"][2]["type"] = json!("VEC4");
            d["accessors"][2]["count"] = json!(1);
            d["meshes"][0]["primitives"][0]["attributes"] = json!({"POSITION": 0, "JOINTS_0": 2});
        },
        &["attributes.JOINTS_0", "FLOAT (5126) VEC4"],
    );
}

#[test]
fn indices_in_range_for_every_kind_of_element() {
    refused_after(
        |d| d["meshes"][0]["primitives"][0]["material"] = json!(4),
        &["meshes[0].primitives[0].material", "materials[4]"],
    );
    refused_after(
        |d| d["bufferViews"][2]["buffer"] = json!(3),
        &["bufferViews[2].buffer"],
    );
    refused_after(|d| d["nodes"][1]["camera"] = json!(0), &["nodes[1].camera"]);
    refused_after(
        |d| d["nodes"][1]["children"] = json!([7]),
        &["nodes[1].children[0]", "nodes[7]"],
    );
    refused_after(
        |d| d["animations"][0]["channels"][0]["sampler"] = json!(1),
        &["animations[0].channels[0].sampler"],
    );
    refused_after(
        |d| {
            d["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 2}}}]);
        },
        &[
            "materials[0].pbrMetallicRoughness.baseColorTexture.index",
            "textures[2]",
        ],
    );
    refused_after(
        |d| {
            d["textures"] = json!([{"source": 1}]);
        },
        &["textures[0].source", "images[1]"],
    );
}

#[test]
fn buffer_views_must_lie_inside_their_buffer() {
    refused_after(
        |d| d["bufferViews"][4]["byteOffset"] = json!(u64::MAX - 4),
        &["bufferViews[4]"],
    );
}

#[test]
fn animation_inputs_and_outputs_are_typed_and_counted() {
    refused_after(
        |d| d["accessors"][3]["componentType"] = json!(5121),
        &["animations[0].samplers[0].input", "UNSIGNED_BYTE"],
    );
    refused_after(
        |d| d["animations"][0]["channels"][0]["target"]["path"] = json!("rotation"),
        &["animations[0].samplers[0].output", "VEC3"],
    );
    refused_after(
        |d| d["animations"][0]["samplers"][0]["interpolation"] = json!("CUBICSPLINE"),
        &["animations[0].samplers[0].output", "2 values for 2 keys"],
    );
}

#[test]
fn node_cycles_are_refused_naming_the_nodes() {
    refused_after(
        |d| {
            d["nodes"][1]["children"] = json!([2]);
            d["nodes"][2]["children"] = json!([1]);
        },
        &["nodes[1]", "nodes[2]", "own ancestor"],
    );
    refused_after(
        |d| d["nodes"][1]["children"] = json!([1]),
        &["nodes[1].children[0]", "its own child"],
    );
}

#[test]
fn a_node_with_two_parents_is_refused_naming_the_nodes() {
    refused_after(
        |d| {
            d["nodes"][1]["children"] = json!([0]);
            d["nodes"][2]["children"] = json!([0]);
        },
        &[
            "nodes[2].children[0]",
            "nodes[0] has two parents",
            "nodes[1]",
        ],
    );
}

#[test]
fn a_motion_tag_beside_deeply_nested_extras_is_not_dropped_silently() {
    let deep = (0..200).fold(json!(1), |v, _| json!([v]));
    refused_after(
        |d| d["nodes"][0]["extras"] = json!({"motion": "dynamic", "deep": deep}),
        &["nodes[0]", "motion"],
    );
}

#[test]
fn only_images_a_material_uses_are_decoded_and_errors_name_the_image() {
    let dir = tempdir();
    std::fs::write(dir.path().join("junk.png"), b"this is not a PNG").unwrap();
    let mut doc = triangle();
    doc["images"] = json!([{"uri": "junk.png"}, {"uri": "junk.png", "name": "used"}]);
    doc["textures"] = json!([{"source": 1}]);
    let path = write(dir.path(), &doc);
    let (code, err) = inspect(&path);
    assert_eq!(
        code,
        Some(0),
        "unused broken images must not be decoded: {err}"
    );
    doc["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
    doc["meshes"][0]["primitives"][0]["material"] = json!(0);
    let path = write(dir.path(), &doc);
    assert_refused(&path, &["images[1] \"used\"", "cannot decode"]);
}

#[test]
fn files_that_are_not_regular_files_are_refused_without_reading_them() {
    let dir = tempdir();
    let link = dir.path().join("zero.gltf");
    std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
    let start = std::time::Instant::now();
    assert_refused(&link, &["not a regular file"]);
    assert!(start.elapsed().as_secs() < 20);
    refused_after(
        |d| d["buffers"][0]["uri"] = json!("/dev/zero"),
        &["buffers[0]", "/dev/zero"],
    );
}

/// The kind the fuzzer loads a kept input as, from its extension.
fn kind_of(path: &Path) -> Option<fuzz::Kind> {
    match path.extension()?.to_str()? {
        "gltf" => Some(fuzz::Kind::Gltf),
        "glb" => Some(fuzz::Kind::Glb),
        "json" => Some(fuzz::Kind::Job),
        _ => None,
    }
}

/// A directory the fuzzer's `check` can work in: jobs name the example's scene beside them.
fn fuzz_dir() -> TempDir {
    let dir = tempdir();
    std::fs::copy(
        root().join("examples/room/room.gltf"),
        dir.path().join("room.gltf"),
    )
    .unwrap();
    dir
}

#[test]
fn every_kept_fuzz_crasher_loads_without_panic() {
    let dir = fuzz_dir();
    let mut files: Vec<PathBuf> = std::fs::read_dir(root().join("tests/fuzz-crashers"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert!(!files.is_empty());
    let mut failures = Vec::new();
    for f in &files {
        let Some(kind) = kind_of(f) else { continue };
        let bytes = std::fs::read(f).unwrap();
        if let Err(msg) = fuzz::check(dir.path(), kind, &bytes) {
            failures.push(format!("{}: {msg}", f.display()));
        }
    }
    assert!(failures.is_empty(), "panics:\n{}", failures.join("\n"));
}

/// A CI-sized run of the fuzzer (examples/fuzz.rs) in-process: 3000 mutated glTF, GLB and job
/// inputs, no panic.
#[test]
fn a_short_fuzz_finds_no_panic() {
    let seeds = fuzz::seeds(&root(), &scenes_dir());
    assert!(!seeds.is_empty());
    let dir = fuzz_dir();
    let mut failures = Vec::new();
    for i in 0..3000 {
        let (s, bytes) = fuzz::input(&seeds, 1, i);
        if let Err(msg) = fuzz::check(dir.path(), s.kind, &bytes) {
            failures.push(format!("input {i} ({}): {msg}", s.name));
        }
    }
    assert!(failures.is_empty(), "panics:\n{}", failures.join("\n"));
}

/// A PNG header declaring `w`×`h` texels, with no pixel data.
fn png_header(w: u32, h: u32) -> Vec<u8> {
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    png.extend(13u32.to_be_bytes());
    png.extend(&ihdr);
    png.extend(crc32(&ihdr).to_be_bytes());
    // An empty IDAT: decoders read the header up to the first data chunk.
    png.extend(0u32.to_be_bytes());
    png.extend(b"IDAT");
    png.extend(crc32(b"IDAT").to_be_bytes());
    png
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in data {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

#[test]
fn an_image_larger_than_16384_squared_is_refused_before_decoding() {
    let dir = tempdir();
    std::fs::write(dir.path().join("huge.png"), png_header(20000, 20000)).unwrap();
    let mut doc = triangle();
    doc["images"] = json!([{"uri": "huge.png"}]);
    doc["textures"] = json!([{"source": 0}]);
    doc["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
    doc["meshes"][0]["primitives"][0]["material"] = json!(0);
    assert_refused(&write(dir.path(), &doc), &["images[0]", "20000×20000"]);
}

#[test]
fn sparse_storage_must_fit_its_buffer_views() {
    refused_after(
        |d| {
            d["accessors"][1]["sparse"] = json!({
                "count": 3,
                "indices": {"bufferView": 3, "componentType": 5125},
                "values": {"bufferView": 0}
            });
        },
        &["accessors[1].sparse.count", "sparse indices"],
    );
}
