//! Motion tags: extras on nodes, inheritance, job overrides, the default for untagged prims,
//! and the static-but-animated error.

use super::common::*;
use super::scenes::base64_encode;
use anchorage::geom::Motion;
use anchorage::scene::{Scene, TagSource};

/// A scene of four nodes: parent(0) → child(1) → grandchild(2), and a separate node 3.
/// Every node instances one triangle. `extras` are JSON per node; `animated` is the node an
/// animation translates.
fn scene(extras: [&str; 4], animated: usize, tags: &str) -> anchorage::Result<Scene> {
    scene_named(["n0", "n1", "n2", "n3"], extras, animated, tags)
}

/// [`scene`] with the nodes' names given.
fn scene_named(
    names: [&str; 4],
    extras: [&str; 4],
    animated: usize,
    tags: &str,
) -> anchorage::Result<Scene> {
    let dir = tempdir();
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    let mut bin = floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    bin.extend(floats(&[0.0, 1.0]));
    bin.extend(floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0]));
    let b64 = base64_encode(&bin);
    let node = |i: usize, children: &str| {
        format!(
            r#"{{"name":"{}","mesh":0,"children":[{children}],"extras":{}}}"#,
            names[i], extras[i]
        )
    };
    let gltf = format!(
        r#"{{"asset":{{"version":"2.0"}},"scenes":[{{"nodes":[0,3]}}],
        "nodes":[{},{},{},{}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
        "animations":[{{"name":"slide","samplers":[{{"input":1,"output":2}}],"channels":[{{"sampler":0,"target":{{"node":{animated},"path":"translation"}}}}]}}],
        "accessors":[
          {{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
          {{"bufferView":0,"byteOffset":36,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
          {{"bufferView":0,"byteOffset":44,"componentType":5126,"count":2,"type":"VEC3"}}],
        "bufferViews":[{{"buffer":0,"byteLength":68}}],
        "buffers":[{{"byteLength":68,"uri":"data:application/octet-stream;base64,{b64}"}}]}}"#,
        node(0, "1"),
        node(1, "2"),
        node(2, ""),
        node(3, ""),
    );
    std::fs::write(dir.path().join("s.gltf"), gltf).unwrap();
    let job = job_from_json(
        &dir.path().join("j.json"),
        &format!(
            r#"{{"scene":[{{"path":"s.gltf","tags":{tags}}}],"camera":{{"position":[0,0,5],"look_at":[0,0,0],"yfov_deg":40}}}}"#
        ),
    )?;
    job.load_scene_layers()
}

fn motions(s: &Scene) -> Vec<Motion> {
    s.layers[0].nodes.iter().map(|n| n.motion).collect()
}

#[test]
fn untagged_prims_are_dynamic_when_animated_and_children_follow() {
    // Node 1 animated: it and its child move, so both default to dynamic.
    let s = scene(["null", "null", "null", "null"], 1, "{}").unwrap();
    assert_eq!(
        motions(&s),
        [
            Motion::Static,
            Motion::Dynamic,
            Motion::Dynamic,
            Motion::Static
        ]
    );
    assert_eq!(
        s.layers[0].nodes[1].why,
        TagSource::DefaultAnimated("slide".into())
    );
    assert_eq!(s.layers[0].nodes[0].why, TagSource::DefaultStatic);
}

#[test]
fn tags_are_inherited_by_children() {
    let s = scene([r#"{"motion":"dynamic"}"#, "null", "null", "null"], 3, "{}").unwrap();
    assert_eq!(
        motions(&s),
        [
            Motion::Dynamic,
            Motion::Dynamic,
            Motion::Dynamic,
            Motion::Dynamic
        ]
    );
    assert_eq!(
        s.layers[0].nodes[2].why,
        TagSource::Inherited("\"n0\"".into())
    );
    // A child's own tag wins over its parent's and passes on to its children.
    let s = scene(
        [
            r#"{"motion":"dynamic"}"#,
            r#"{"motion":"static"}"#,
            "null",
            "null",
        ],
        3,
        "{}",
    )
    .unwrap();
    assert_eq!(
        motions(&s)[..3],
        [Motion::Dynamic, Motion::Static, Motion::Static]
    );
}

#[test]
fn job_overrides_win_over_extras() {
    let s = scene(
        [r#"{"motion":"static"}"#, "null", "null", "null"],
        3,
        r#"{"n1":"dynamic"}"#,
    )
    .unwrap();
    assert_eq!(
        motions(&s)[..3],
        [Motion::Static, Motion::Dynamic, Motion::Dynamic]
    );
    assert_eq!(s.layers[0].nodes[1].why, TagSource::Job);
}

#[test]
fn static_tag_on_an_animated_prim_is_an_error_naming_node_and_animation() {
    let e = scene([r#"{"motion":"static"}"#, "null", "null", "null"], 1, "{}")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("\"n1\"") && e.contains("slide") && e.contains("static"),
        "{e}"
    );
    // Also when the static tag comes from the job file.
    let e = scene(["null", "null", "null", "null"], 2, r#"{"n2":"static"}"#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("\"n2\"") && e.contains("slide"), "{e}");
    // Fixing it with a job override works.
    assert!(
        scene(
            [r#"{"motion":"static"}"#, "null", "null", "null"],
            1,
            r#"{"n1":"dynamic"}"#
        )
        .is_ok()
    );
}

#[test]
fn extras_from_other_tools_are_ignored() {
    let s = scene(
        [
            r#"{"blender":{"nested":[1,2]}}"#,
            r#""a string""#,
            "{}",
            r#"{"my_custom_object_property":39}"#,
        ],
        3,
        "{}",
    )
    .unwrap();
    assert_eq!(
        motions(&s),
        [
            Motion::Static,
            Motion::Static,
            Motion::Static,
            Motion::Dynamic
        ]
    );
}

#[test]
fn bad_motion_values_and_unknown_override_nodes_are_errors() {
    let e = scene([r#"{"motion":"moving"}"#, "null", "null", "null"], 3, "{}")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("nodes[0] \"n0\"") && e.contains("extras.motion"),
        "{e}"
    );
    let e = scene(["null", "null", "null", "null"], 3, r#"{"nope":"dynamic"}"#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("tags.nope"), "{e}");
}

/// The example's tags: the room inherits static from its root; the cube is tagged dynamic.
#[test]
fn example_scene_tags() {
    let job = anchorage::job::Job::load(&example_job(), &Default::default()).unwrap();
    let s = job.load_scene().unwrap();
    let l = &s.layers[0];
    let by_name = |n: &str| l.nodes.iter().find(|x| x.name == n).unwrap();
    assert_eq!(by_name("walls").motion, Motion::Static);
    assert_eq!(
        by_name("block").why,
        TagSource::Inherited("\"room\"".into())
    );
    assert_eq!(by_name("cube").motion, Motion::Dynamic);
    assert_eq!(by_name("cube").why, TagSource::Extras);
}

/// A real Blender 3.4 export (`tests/data/blender/make.py`, run with `blender -b --python`):
/// object custom properties `motion` arrive as tags, other custom properties are ignored, and
/// Blender's frame numbers map to the animation's times with the default `frame_offset`.
#[test]
fn blender_export_custom_properties_are_tags() {
    let path = root().join("tests/data/blender/blend.gltf");
    let o = run(&["inspect", path.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    for want in [
        r#""Floor"                  static   2 triangles  (tagged in extras)"#,
        r#""Mover"                  dynamic  12 triangles  (tagged in extras)"#,
        r#""Untagged"               static   960 triangles  (untagged, not animated)"#,
        "frames 1..24 at 24 fps",
    ] {
        assert!(text.contains(want), "missing {want:?} in\n{text}");
    }
}

/// A key one letter off the motion tag is not a tag, but it is not silent either: the
/// loader warns, naming the node and the key.
#[test]
fn misspelt_motion_keys_are_warned_about() {
    let s = scene(
        [
            r#"{"Motion":"dynamic"}"#,
            r#"{"anchorage_motion":"static"}"#,
            r#"{"motion":"static","motion_note":"hand-tagged"}"#,
            r#"{"notes":"motionless"}"#,
        ],
        3,
        "{}",
    )
    .unwrap();
    // (The test scene's primitives have no material, which is warned about too.)
    let w: Vec<String> = s
        .warnings()
        .into_iter()
        .filter(|w| w.contains("nodes["))
        .collect();
    assert_eq!(w.len(), 2, "{w:?}");
    assert!(
        w[0].contains("nodes[0] \"n0\"") && w[0].contains("\"Motion\""),
        "{w:?}"
    );
    assert!(
        w[1].contains("nodes[1] \"n1\"") && w[1].contains("\"anchorage_motion\""),
        "{w:?}"
    );
    // Misspelt keys are not tags: node 0 falls back to the default (not animated: static).
    assert_eq!(s.layers[0].nodes[0].why, TagSource::DefaultStatic);
}

/// Unnamed nodes are addressed as `inspect` prints them, `nodes[i]`; a name several nodes
/// share is an error that lists them, not the first one silently.
#[test]
fn tag_overrides_address_nodes_by_index_and_refuse_ambiguous_names() {
    let s = scene_named(
        ["", "", "", ""],
        ["null"; 4],
        1,
        r#"{"nodes[3]":"dynamic"}"#,
    )
    .unwrap();
    assert_eq!(s.layers[0].nodes[3].motion, Motion::Dynamic);
    assert_eq!(s.layers[0].nodes[3].why, TagSource::Job);
    let e = scene_named(
        ["a", "b", "dup", "dup"],
        ["null"; 4],
        1,
        r#"{"dup":"dynamic"}"#,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("scene[0].tags.dup") && e.contains("nodes[2], nodes[3]"),
        "{e}"
    );
    let e = scene(["null"; 4], 1, r#"{"nodes[9]":"dynamic"}"#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no node named \"nodes[9]\""), "{e}");
}

/// Camera nodes too: an unnamed one as `nodes[i]`, and a name two cameras share refused.
#[test]
fn camera_nodes_by_index_and_ambiguous_names() {
    let dir = tempdir();
    std::fs::write(
        dir.path().join("c.gltf"),
        r#"{"asset":{"version":"2.0"},"scenes":[{"nodes":[0,1,2]}],
        "nodes":[{"camera":0},{"name":"cam","camera":0},{"name":"cam","camera":0}],
        "cameras":[{"type":"perspective","perspective":{"yfov":0.7,"znear":0.1}}]}"#,
    )
    .unwrap();
    let load = |node: &str| {
        job_from_json(
            &dir.path().join("j.json"),
            &format!(r#"{{"scene":[{{"path":"c.gltf"}}],"camera":{{"node":"{node}"}}}}"#),
        )
        .and_then(|job| job.load_scene_layers())
    };
    let s = load("nodes[0]").unwrap();
    assert!(matches!(
        s.camera,
        Some(anchorage::scene::CameraChoice::Node { layer: 0, node: 0 })
    ));
    let e = load("cam").unwrap_err().to_string();
    assert!(
        e.contains("camera.node") && e.contains("nodes[1], nodes[2]"),
        "{e}"
    );
}
