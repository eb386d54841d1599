//! Malformed glTF: every index, type, count and size a file declares is checked before it is
//! read, and refused with exit 2 naming the file and the element; the fuzzer's crashers stay
//! fixed, and a short in-process fuzz finds no panic.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

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

/// An image within the texel limit whose decoded pixels exceed the decoder's allocation
/// limit is refused from its header, saying so: 16384² RGB8 takes 768 MiB. (It said "cannot
/// decode image: Memory limit exceeded".)
#[test]
fn an_image_too_large_to_decode_is_refused_saying_how_large() {
    let dir = tempdir();
    std::fs::write(dir.path().join("wide.png"), png_header(16384, 16384)).unwrap();
    let mut doc = triangle();
    doc["images"] = json!([{"uri": "wide.png"}]);
    doc["textures"] = json!([{"source": 0}]);
    doc["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
    doc["meshes"][0]["primitives"][0]["material"] = json!(0);
    assert_refused(
        &write(dir.path(), &doc),
        &["images[0]", "16384×16384", "Rgb8", "768 MiB", "512 MiB"],
    );
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

#[test]
fn a_byte_stride_shorter_than_an_element_is_refused_naming_the_view_and_the_accessor() {
    // Three 12-byte positions 8 bytes apart fit the 36-byte view; reading them panicked.
    refused_after(
        |d| d["bufferViews"][0]["byteStride"] = json!(8),
        &["bufferViews[0].byteStride", "accessors[0]", "12-byte"],
    );
    // The JSON schema's byteStride is a multiple of 4 (view 5 is used by no accessor).
    refused_after(
        |d| d["bufferViews"][5]["byteStride"] = json!(6),
        &["bufferViews[5].byteStride", "multiple of 4"],
    );
}

/// `triangle()` lit by `light`, the only `KHR_lights_punctual` light, on node 1.
fn lit(light: Value) -> impl FnOnce(&mut Value) {
    move |d| {
        d["extensionsUsed"] = json!(["KHR_lights_punctual"]);
        d["extensions"] = json!({"KHR_lights_punctual": {"lights": [light]}});
        d["nodes"][1]["extensions"] = json!({"KHR_lights_punctual": {"light": 0}});
    }
}

#[test]
fn a_light_colour_must_be_finite_and_non_negative() {
    let dir = tempdir();
    let mut doc = triangle();
    lit(json!({"type": "point", "intensity": 20, "color": [1, 0.5, 0.25]}))(&mut doc);
    let (code, err) = inspect(&write(dir.path(), &doc));
    assert_eq!(code, Some(0), "{err}");
    refused_after(
        lit(json!({"type": "point", "intensity": 20, "color": [1, 1, -1]})),
        &["extensions.KHR_lights_punctual.lights[0].color", "-1"],
    );
    // 1e39 is beyond f32 and reads as infinity.
    refused_after(
        lit(json!({"type": "point", "intensity": 20, "color": [1e39, 1, 1]})),
        &["extensions.KHR_lights_punctual.lights[0].color"],
    );
}

#[test]
fn a_light_whose_colour_times_intensity_overflows_f32_is_refused() {
    refused_after(
        lit(json!({"type": "point", "intensity": 20, "color": [1e38, 1, 1], "name": "sun"})),
        &[
            "extensions.KHR_lights_punctual.lights[0] \"sun\"",
            "colour × intensity overflows f32",
        ],
    );
    // 2e38 is finite; the point light's power, 4π times it, is not.
    refused_after(
        lit(json!({"type": "point", "intensity": 20, "color": [1e37, 1, 1]})),
        &["extensions.KHR_lights_punctual.lights[0]", "4π"],
    );
}

#[test]
fn spot_cone_angles_must_satisfy_0_le_inner_lt_outer_le_half_pi() {
    let spot = |inner: f64, outer: f64| {
        json!({"type": "spot", "intensity": 20,
               "spot": {"innerConeAngle": inner, "outerConeAngle": outer}})
    };
    let dir = tempdir();
    let mut doc = triangle();
    lit(spot(0.0, std::f64::consts::FRAC_PI_2))(&mut doc);
    let (code, err) = inspect(&write(dir.path(), &doc));
    assert_eq!(code, Some(0), "{err}");
    let key = "extensions.KHR_lights_punctual.lights[0].spot";
    for (inner, outer, at) in [
        (0.0, 0.0, "outerConeAngle"),
        (0.0, 1e-30, "outerConeAngle"),
        (0.0, 2.0, "outerConeAngle"),
        (0.6, 0.3, "innerConeAngle"),
        (0.3, 0.3, "innerConeAngle"),
        (-0.1, 0.3, "innerConeAngle"),
    ] {
        refused_after(lit(spot(inner, outer)), &[&format!("{key}.{at}")]);
    }
    refused_after(
        lit(json!({"type": "point", "range": -1})),
        &["extensions.KHR_lights_punctual.lights[0].range"],
    );
}

/// Appends `item` to the JSON array `array`.
fn push(array: &mut Value, item: Value) {
    array.as_array_mut().expect("a JSON array").push(item);
}

/// `triangle()` with the normals (accessor 1) replaced at the `sparse` indices, stored as
/// UNSIGNED_INT in `sparse.bin` beside it and followed by one normal per index.
fn sparse_normals(indices: &[u32], stride: Option<u32>) -> (TempDir, PathBuf) {
    let dir = tempdir();
    let n = indices.len();
    let mut bin: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
    for _ in 0..n {
        bin.extend([0f32, 1., 0.].iter().flat_map(|x| x.to_le_bytes()));
    }
    std::fs::write(dir.path().join("sparse.bin"), &bin).unwrap();
    let mut doc = triangle();
    push(
        &mut doc["buffers"],
        json!({"byteLength": bin.len(), "uri": "sparse.bin"}),
    );
    let mut view = json!({"buffer": 1, "byteOffset": 0, "byteLength": 4 * n});
    if let Some(s) = stride {
        view["byteStride"] = json!(s);
    }
    push(&mut doc["bufferViews"], view);
    push(
        &mut doc["bufferViews"],
        json!({"buffer": 1, "byteOffset": 4 * n, "byteLength": 12 * n}),
    );
    doc["accessors"][1]["sparse"] = json!({
        "count": n,
        "indices": {"bufferView": 6, "componentType": 5125},
        "values": {"bufferView": 7}
    });
    let path = write(dir.path(), &doc);
    (dir, path)
}

#[test]
fn sparse_indices_must_strictly_increase_below_the_count() {
    let (_dir, path) = sparse_normals(&[0, 2], None);
    let (code, err) = inspect(&path);
    assert_eq!(code, Some(0), "{err}");
    for (indices, what) in [
        (&[0, 3][..], "3, outside"),
        (&[1, 1][..], "strictly increase"),
        (&[2, 1][..], "strictly increase"),
    ] {
        let (_dir, path) = sparse_normals(indices, None);
        assert_refused(&path, &["accessors[1].sparse.indices", what]);
    }
    // Sparse storage is tightly packed: its views have no byteStride.
    let (_dir, path) = sparse_normals(&[0, 2], Some(4));
    assert_refused(&path, &["bufferViews[6].byteStride", "sparse.indices"]);
}

/// `triangle()` skinned by `skins[0]` (joint nodes[1]) on node 0, with the per-vertex
/// `joints` (UNSIGNED_BYTE VEC4), `weights` (FLOAT VEC4) and one inverse bind matrix `ibm`
/// in `skin.bin` beside it, and `edit` applied.
fn skinned(
    joints: [u8; 12],
    weights: [f32; 12],
    ibm: [f32; 16],
    edit: impl FnOnce(&mut Value),
) -> (TempDir, PathBuf) {
    let dir = tempdir();
    let mut bin = joints.to_vec();
    bin.extend(weights.iter().chain(&ibm).flat_map(|x| x.to_le_bytes()));
    std::fs::write(dir.path().join("skin.bin"), &bin).unwrap();
    let mut doc = triangle();
    push(
        &mut doc["buffers"],
        json!({"byteLength": 124, "uri": "skin.bin"}),
    );
    // Views 6, 7, 8 and accessors 5, 6, 7: joints, weights, inverse bind matrix.
    for (view, (off, len, ct, count, ty)) in [
        (0, 12, 5121, 3, "VEC4"),
        (12, 48, 5126, 3, "VEC4"),
        (60, 64, 5126, 1, "MAT4"),
    ]
    .into_iter()
    .enumerate()
    {
        push(
            &mut doc["bufferViews"],
            json!({"buffer": 1, "byteOffset": off, "byteLength": len}),
        );
        push(
            &mut doc["accessors"],
            json!({"bufferView": 6 + view, "componentType": ct, "count": count, "type": ty}),
        );
    }
    let attributes = &mut doc["meshes"][0]["primitives"][0]["attributes"];
    attributes["JOINTS_0"] = json!(5);
    attributes["WEIGHTS_0"] = json!(6);
    doc["skins"] = json!([{"joints": [1], "inverseBindMatrices": 7}]);
    doc["nodes"][0]["skin"] = json!(0);
    edit(&mut doc);
    let path = write(dir.path(), &doc);
    (dir, path)
}

const ONE_JOINT: [f32; 12] = [1., 0., 0., 0., 1., 0., 0., 0., 1., 0., 0., 0.];
const IDENTITY: [f32; 16] = [
    1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
];

#[test]
fn skin_joints_weights_and_inverse_bind_matrices_are_checked() {
    let (_dir, path) = skinned([0; 12], ONE_JOINT, IDENTITY, |_| {});
    let (code, err) = inspect(&path);
    assert_eq!(code, Some(0), "{err}");
    // Vertex 1 bound to joint 1 of a one-joint skin.
    let mut joints = [0; 12];
    joints[4] = 1;
    let (_dir, path) = skinned(joints, ONE_JOINT, IDENTITY, |_| {});
    assert_refused(
        &path,
        &[
            "meshes[0].primitives[0].attributes.JOINTS_0",
            "vertex 1 names joint 1",
            "skins[0]",
            "nodes[0]",
        ],
    );
    let (_dir, path) = skinned([0; 12], ONE_JOINT, IDENTITY, |d| {
        d["skins"][0]["joints"] = json!([]);
    });
    assert_refused(&path, &["skins[0].joints", "at least one"]);
    let mut ibm = IDENTITY;
    ibm[5] = f32::NAN;
    let (_dir, path) = skinned([0; 12], ONE_JOINT, ibm, |_| {});
    assert_refused(&path, &["skins[0].inverseBindMatrices", "not finite"]);
    let mut weights = ONE_JOINT;
    weights[8] = f32::INFINITY;
    let (_dir, path) = skinned([0; 12], weights, IDENTITY, |_| {});
    assert_refused(
        &path,
        &[
            "meshes[0].primitives[0].attributes.WEIGHTS_0",
            "vertex 2",
            "not finite",
        ],
    );
}

#[test]
fn a_fifo_is_refused_at_once_as_not_a_regular_file() {
    let dir = tempdir();
    let fifo = dir.path().join("fifo.gltf");
    let made = Command::new("mkfifo").arg(&fifo).status();
    if !made.is_ok_and(|s| s.success()) {
        eprintln!("skipped: mkfifo is not available");
        return;
    }
    let mut child = bin()
        .arg("inspect")
        .arg(&fifo)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run anchorage");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        if start.elapsed() > Duration::from_secs(20) {
            child.kill().unwrap();
            child.wait().unwrap();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    let status = status.expect("anchorage still waited on the FIFO after 20 s");
    assert_eq!(status.code(), Some(2), "{err}");
    assert!(
        err.contains("fifo.gltf") && err.contains("not a regular file"),
        "{err}"
    );
}

/// A node's transform is one glTF can give: a rotation that is not zero (it made the mesh
/// vanish, a directional light light nothing), and a matrix that is affine (a last row other
/// than 0 0 0 1 was ignored), does not shear (a shear was read as a rotated, stretched box)
/// and scales no axis to zero or past what f32 can square (both made the mesh vanish).
#[test]
fn node_transforms_gltf_cannot_give_are_refused() {
    refused_after(
        |d| d["nodes"][1]["rotation"] = json!([0, 0, 0, 0]),
        &["nodes[1].rotation", "not a rotation"],
    );
    for (matrix, why) in [
        (
            json!([1, 0, 0, 1, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
            "not affine",
        ),
        (
            json!([1, 0, 0, 0, 0.5, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
            "shears",
        ),
        (
            json!([1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
            "to zero",
        ),
        (
            json!([2e19, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
            "f32",
        ),
    ] {
        refused_after(
            |d| d["nodes"][1]["matrix"] = matrix,
            &["nodes[1].matrix", why],
        );
    }
    refused_after(
        |d| d["nodes"][1]["rotation"] = json!([1e-25, 0, 0, 1e-25]),
        &["nodes[1].rotation", "not a rotation"],
    );
    // A rotation and a mirroring scale as a matrix load, with a last row a tool's float
    // noise leaves, and so does a matrix that scales a node to nothing (hiding it).
    for matrix in [
        json!([0, 1, 0, 1e-9, -2, 0, 0, 0, 0, 0, -1, 0, 5, 0, 0, 0.9999999]),
        json!([0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 5, 0, 0, 1]),
    ] {
        let dir = tempdir();
        let mut doc = triangle();
        doc["nodes"][1]["matrix"] = matrix;
        let (code, err) = inspect(&write(dir.path(), &doc));
        assert_eq!(code, Some(0), "{err}");
    }
}

/// Animation samplers have keys (an empty one moved its node to the origin), rotation keys
/// are rotations (a zero quaternion was read as no rotation), and morph weights match the
/// mesh's targets: per key in a channel, in a mesh's and a node's default weights, and in
/// every primitive's target count (each mismatch was truncated or padded silently).
#[test]
fn animation_keys_and_morph_weights_are_checked_against_what_they_animate() {
    refused_after(
        |d| {
            d["accessors"][3]["count"] = json!(0);
            d["accessors"][4]["count"] = json!(0);
        },
        &["animations[0].channels[0]", "no keys"],
    );
    refused_after(
        |d| {
            // One key (t = 0) holding the zero quaternion (bufferView 5 is zeros).
            push(
                &mut d["accessors"],
                json!({"bufferView": 5, "componentType": 5126, "count": 1, "type": "VEC4"}),
            );
            push(
                &mut d["accessors"],
                json!({"bufferView": 3, "componentType": 5126, "count": 1, "type": "SCALAR",
                       "min": [0], "max": [0]}),
            );
            d["animations"][0]["samplers"] = json!([{"input": 6, "output": 5}]);
            d["animations"][0]["channels"][0]["target"]["path"] = json!("rotation");
        },
        &["animations[0].channels[0]", "zero quaternion"],
    );
    let two_targets = |d: &mut Value| {
        d["meshes"][0]["primitives"][0]["targets"] = json!([{"POSITION": 1}, {"POSITION": 1}]);
    };
    refused_after(
        |d| {
            two_targets(d);
            // One weight a key (accessor 3, two keys) for two targets.
            d["animations"][0]["samplers"] = json!([{"input": 3, "output": 3}]);
            d["animations"][0]["channels"][0]["target"]["path"] = json!("weights");
        },
        &["animations[0].channels[0]", "2 morph targets"],
    );
    refused_after(
        |d| {
            two_targets(d);
            d["meshes"][0]["weights"] = json!([0.5]);
        },
        &["meshes[0].weights", "2 morph targets"],
    );
    refused_after(
        |d| {
            two_targets(d);
            d["nodes"][0]["weights"] = json!([0.5, 0.5, 0.5]);
        },
        &["nodes[0].weights", "2 morph targets"],
    );
    refused_after(
        |d| {
            two_targets(d);
            let mut second = d["meshes"][0]["primitives"][0].clone();
            second["targets"] = json!([{"POSITION": 1}]);
            push(&mut d["meshes"][0]["primitives"], second);
        },
        &["meshes[0].primitives[1].targets", "primitives[0] has 2"],
    );
}

/// The node hierarchy's cycle check is linear: a chain of 300 000 nodes (an 11 MB file,
/// within the size limit) is checked in well under a second. It took 38 s for 200 000 nodes
/// when each node's chain of parents was walked to its root.
#[test]
fn a_deep_node_chain_is_checked_in_linear_time() {
    let dir = tempdir();
    let mut doc = triangle();
    let n = 300_000;
    let mut nodes: Vec<Value> = (0..n).map(|i| json!({"children": [i + 1]})).collect();
    nodes.push(json!({"mesh": 0, "name": "tri"}));
    doc["nodes"] = Value::Array(nodes);
    doc["scenes"] = json!([{"nodes": [0]}]);
    doc["animations"] = json!([]);
    let start = Instant::now();
    let (code, err) = inspect(&write(dir.path(), &doc));
    let took = start.elapsed();
    assert_eq!(code, Some(0), "{err}");
    assert!(took < Duration::from_secs(20), "took {took:?}");
}

/// An image in a buffer view without a `mimeType` (which glTF requires there) is refused;
/// the `gltf` crate panicked on it. A URI whose percent-escapes decode to bytes that are not
/// UTF-8 is refused naming it; the crate panicked on it where a file with the lossily
/// decoded name existed.
#[test]
fn images_and_uris_the_gltf_crate_panics_on_are_refused() {
    let textured = |d: &mut Value, image: Value| {
        d["images"] = json!([image]);
        d["textures"] = json!([{"source": 0}]);
        d["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
        d["meshes"][0]["primitives"][0]["material"] = json!(0);
    };
    refused_after(
        |d| textured(d, json!({"bufferView": 5})),
        &["images[0].mimeType", "missing"],
    );
    let dir = tempdir();
    let mut doc = triangle();
    textured(&mut doc, json!({"uri": "%FF.png"}));
    let path = write(dir.path(), &doc);
    std::fs::write(dir.path().join("\u{FFFD}.png"), png_header(1, 1)).unwrap();
    assert_refused(&path, &["images[0].uri", "not UTF-8"]);
    let dir = tempdir();
    let mut doc = triangle();
    doc["buffers"][0]["uri"] = json!("%FF.bin");
    let path = write(dir.path(), &doc);
    std::fs::copy(dir.path().join("tri.bin"), dir.path().join("\u{FFFD}.bin")).unwrap();
    assert_refused(&path, &["buffers[0].uri", "not UTF-8"]);
}

/// `TEXCOORD_0` is there and finite where a primitive's material has textures: a missing
/// one read every texture at (0, 0), and a NaN or infinite one read texel 0, silently.
#[test]
fn texture_coordinates_are_present_and_finite_where_textures_read_them() {
    let dir = tempdir();
    image::RgbImage::from_pixel(2, 2, image::Rgb([200, 100, 50]))
        .save(dir.path().join("tex.png"))
        .unwrap();
    let textured = |d: &mut Value| {
        d["images"] = json!([{"uri": "tex.png"}]);
        d["textures"] = json!([{"source": 0}]);
        d["materials"] = json!([{"name": "painted",
                                 "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
        d["meshes"][0]["primitives"][0]["material"] = json!(0);
    };
    let mut doc = triangle();
    textured(&mut doc);
    let (code, err) = inspect(&write(dir.path(), &doc));
    assert_eq!(code, Some(0), "{err}");
    let attributes = &mut doc["meshes"][0]["primitives"][0]["attributes"];
    attributes.as_object_mut().unwrap().remove("TEXCOORD_0");
    assert_refused(
        &write(dir.path(), &doc),
        &["attributes.TEXCOORD_0", "is missing", "\"painted\""],
    );
    // The UVs (accessor 2, at byte 72 of the buffer) with a NaN.
    let mut doc = triangle();
    textured(&mut doc);
    let path = write(dir.path(), &doc);
    let mut bin = std::fs::read(dir.path().join("tri.bin")).unwrap();
    bin[72..76].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(dir.path().join("tri.bin"), bin).unwrap();
    assert_refused(&path, &["attributes.TEXCOORD_0", "vertex 0", "not finite"]);
}

/// More of what glTF requires, each of which rendered silently wrong: a vertex's skin
/// weights sum to 1 (all zero collapsed it to the origin; a sum other than 1 is divided
/// out, so weights of 0.5 give the mesh that weights of 1 give), inverse bind matrices are
/// invertible, a skinned mesh has `JOINTS_0` and `WEIGHTS_0`, a node gives a matrix or TRS
/// but not both, an animated node has no matrix (both were ignored), `baseColorFactor` lies
/// in [0, 1] (it was clamped), and TRIANGLES come in threes (the rest was dropped).
#[test]
fn skins_matrices_colours_and_triangle_counts_are_as_gltf_requires() {
    let (_dir, path) = skinned([0; 12], [0.0; 12], IDENTITY, |_| {});
    assert_refused(&path, &["attributes.WEIGHTS_0", "vertex 0", "sum to 0"]);
    let mut ibm = IDENTITY;
    ibm[0] = 0.0;
    let (_dir, path) = skinned([0; 12], ONE_JOINT, ibm, |_| {});
    assert_refused(&path, &["skins[0].inverseBindMatrices", "singular"]);
    let (_dir, path) = skinned([0; 12], ONE_JOINT, IDENTITY, |d| {
        let attributes = &mut d["meshes"][0]["primitives"][0]["attributes"];
        attributes.as_object_mut().unwrap().remove("WEIGHTS_0");
    });
    assert_refused(
        &path,
        &[
            "meshes[0].primitives[0].attributes",
            "WEIGHTS_0",
            "nodes[0]",
        ],
    );
    // Half weights and whole ones place the same triangle.
    let triangles = |weights: [f32; 12]| {
        let (dir, path) = skinned([0; 12], weights, IDENTITY, |d| {
            d["nodes"][1]["translation"] = json!([0, 2, 0]);
        });
        let job = job_from_json(
            &dir.path().join("j.json"),
            &format!(
                r#"{{"scene":[{{"path":{:?}}}],"camera":{{"position":[0,0,5],"look_at":[0,0,0],"yfov_deg":40}}}}"#,
                path.display().to_string()
            ),
        )
        .unwrap();
        let scene = job.load_scene().unwrap();
        let g = scene.geometry(0.0, anchorage::geom::Motion::Dynamic);
        g.triangles
            .iter()
            .map(|t| [t.v0, t.v1, t.v2])
            .collect::<Vec<_>>()
    };
    let half = ONE_JOINT.map(|w| w * 0.5);
    let (whole, halved) = (triangles(ONE_JOINT), triangles(half));
    assert!(!whole.is_empty());
    assert_eq!(whole, halved);
    refused_after(
        |d| {
            d["nodes"][1]["matrix"] = json!([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
            d["nodes"][1]["translation"] = json!([0, 1, 0]);
        },
        &["nodes[1].matrix", "translation, rotation or scale"],
    );
    refused_after(
        |d| {
            d["nodes"][0]["matrix"] = json!([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
        },
        &[
            "animations[0].channels[0].target.node",
            "nodes[0] has a matrix",
        ],
    );
    // Morph weights animate no transform: a node with a matrix may have them animated.
    let dir = tempdir();
    let mut doc = triangle();
    doc["meshes"][0]["primitives"][0]["targets"] = json!([{"POSITION": 1}]);
    doc["nodes"][0]["matrix"] = json!([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
    doc["animations"][0]["samplers"] = json!([{"input": 3, "output": 3}]);
    doc["animations"][0]["channels"][0]["target"]["path"] = json!("weights");
    let (code, err) = inspect(&write(dir.path(), &doc));
    assert_eq!(code, Some(0), "{err}");
    refused_after(
        |d| {
            d["materials"] = json!([{"pbrMetallicRoughness": {"baseColorFactor": [2, 1, 1, 1]}}]);
            d["meshes"][0]["primitives"][0]["material"] = json!(0);
        },
        &[
            "materials[0].pbrMetallicRoughness.baseColorFactor",
            "outside [0, 1]",
        ],
    );
    refused_after(
        |d| {
            // Two of the three vertices' indices (accessor 3's view holds two floats; as
            // UNSIGNED_SHORT indices they read 0, 0, 0, 16256).
            push(
                &mut d["accessors"],
                json!({"bufferView": 3, "componentType": 5123, "count": 2, "type": "SCALAR"}),
            );
            d["meshes"][0]["primitives"][0]["indices"] = json!(5);
        },
        &["meshes[0].primitives[0].indices", "not a multiple of 3"],
    );
}
