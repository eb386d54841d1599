//! Small animated scenes built in code for the anchor tests: prims made of quads, each
//! static or dynamic and optionally moved by a translation animation, and point lights,
//! optionally animated too, written as one glTF with an embedded buffer.

use super::scenes::base64_encode;

/// A prim: quads (four corners each, counter-clockwise), a grey albedo, its motion tag and
/// translation keys `(time s, translation)` (none: not animated).
pub struct Prim {
    pub name: &'static str,
    pub quads: Vec<[[f32; 3]; 4]>,
    pub albedo: f32,
    pub motion: &'static str,
    pub keys: Vec<(f32, [f32; 3])>,
}

/// A point light of `intensity` candela at translation keys (one key: fixed).
pub struct Light {
    pub intensity: f32,
    pub keys: Vec<(f32, [f32; 3])>,
}

/// An axis-aligned box's six faces, wound outwards.
pub fn box_quads(lo: [f32; 3], hi: [f32; 3]) -> Vec<[[f32; 3]; 4]> {
    let [x0, y0, z0] = lo;
    let [x1, y1, z1] = hi;
    vec![
        [[x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]],
        [[x1, y0, z0], [x0, y0, z0], [x0, y1, z0], [x1, y1, z0]],
        [[x0, y0, z0], [x0, y0, z1], [x0, y1, z1], [x0, y1, z0]],
        [[x1, y0, z1], [x1, y0, z0], [x1, y1, z0], [x1, y1, z1]],
        [[x0, y1, z1], [x1, y1, z1], [x1, y1, z0], [x0, y1, z0]],
        [[x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1]],
    ]
}

/// The inside of an axis-aligned box: [`box_quads`] wound inwards, as a room's walls face the
/// camera and the cache records inside it.
pub fn room_quads(lo: [f32; 3], hi: [f32; 3]) -> Vec<[[f32; 3]; 4]> {
    box_quads(lo, hi)
        .into_iter()
        .map(|[a, b, c, d]| [d, c, b, a])
        .collect()
}

/// The glTF text of `prims` and `lights` (double-sided grey Lambertian materials).
pub fn gltf(prims: &[Prim], lights: &[Light]) -> String {
    gltf_with(prims, lights, |p| {
        format!(
            r#"{{"pbrMetallicRoughness":{{"baseColorFactor":[{a},{a},{a},1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}},"doubleSided":true}}"#,
            a = p.albedo
        )
    })
}

/// [`gltf`] with each prim's material given as glTF JSON by `material`.
pub fn gltf_with(prims: &[Prim], lights: &[Light], material: impl Fn(&Prim) -> String) -> String {
    let mut bin: Vec<u8> = Vec::new();
    let mut accessors = Vec::new();
    let mut views = Vec::new();
    let mut push = |bin: &mut Vec<u8>, data: Vec<u8>| -> usize {
        let off = bin.len();
        bin.extend(data);
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        views.push(format!(
            r#"{{"buffer":0,"byteOffset":{off},"byteLength":{}}}"#,
            bin.len() - off
        ));
        views.len() - 1
    };
    let floats = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let mut nodes = Vec::new();
    let mut meshes = Vec::new();
    let mut materials = Vec::new();
    let mut channels = Vec::new();
    let mut samplers = Vec::new();
    let mut anim = |bin: &mut Vec<u8>,
                    accessors: &mut Vec<String>,
                    node: usize,
                    keys: &[(f32, [f32; 3])],
                    push: &mut dyn FnMut(&mut Vec<u8>, Vec<u8>) -> usize| {
        if keys.len() < 2 {
            return;
        }
        let t: Vec<f32> = keys.iter().map(|k| k.0).collect();
        let v: Vec<f32> = keys.iter().flat_map(|k| k.1).collect();
        let vt = push(bin, floats(&t));
        accessors.push(format!(
            r#"{{"bufferView":{vt},"componentType":5126,"count":{},"type":"SCALAR","min":[{}],"max":[{}]}}"#,
            t.len(),
            t[0],
            t[t.len() - 1]
        ));
        let vv = push(bin, floats(&v));
        accessors.push(format!(
            r#"{{"bufferView":{vv},"componentType":5126,"count":{},"type":"VEC3"}}"#,
            t.len()
        ));
        samplers.push(format!(
            r#"{{"input":{},"output":{}}}"#,
            accessors.len() - 2,
            accessors.len() - 1
        ));
        channels.push(format!(
            r#"{{"sampler":{},"target":{{"node":{node},"path":"translation"}}}}"#,
            samplers.len() - 1
        ));
    };
    for p in prims {
        let pos: Vec<f32> = p.quads.iter().flatten().flatten().copied().collect();
        let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
        for c in p.quads.iter().flatten() {
            for k in 0..3 {
                lo[k] = lo[k].min(c[k]);
                hi[k] = hi[k].max(c[k]);
            }
        }
        let idx: Vec<u32> = (0..p.quads.len() as u32)
            .flat_map(|q| [0, 1, 2, 0, 2, 3].map(|i| 4 * q + i))
            .collect();
        let vp = push(&mut bin, floats(&pos));
        accessors.push(format!(
            r#"{{"bufferView":{vp},"componentType":5126,"count":{},"type":"VEC3","min":{lo:?},"max":{hi:?}}}"#,
            pos.len() / 3
        ));
        let vi = push(&mut bin, idx.iter().flat_map(|i| i.to_le_bytes()).collect());
        accessors.push(format!(
            r#"{{"bufferView":{vi},"componentType":5125,"count":{},"type":"SCALAR"}}"#,
            idx.len()
        ));
        materials.push(material(p));
        meshes.push(format!(
            r#"{{"primitives":[{{"attributes":{{"POSITION":{}}},"indices":{},"material":{}}}]}}"#,
            accessors.len() - 2,
            accessors.len() - 1,
            materials.len() - 1
        ));
        let translation = p.keys.first().map_or([0.0; 3], |k| k.1);
        nodes.push(format!(
            r#"{{"name":"{}","mesh":{},"translation":{translation:?},"extras":{{"motion":"{}"}}}}"#,
            p.name,
            meshes.len() - 1,
            p.motion
        ));
        anim(
            &mut bin,
            &mut accessors,
            nodes.len() - 1,
            &p.keys,
            &mut push,
        );
    }
    let mut light_defs = Vec::new();
    for (i, l) in lights.iter().enumerate() {
        light_defs.push(format!(r#"{{"type":"point","intensity":{}}}"#, l.intensity));
        nodes.push(format!(
            r#"{{"name":"light{i}","translation":{:?},"extensions":{{"KHR_lights_punctual":{{"light":{i}}}}}}}"#,
            l.keys[0].1
        ));
        anim(
            &mut bin,
            &mut accessors,
            nodes.len() - 1,
            &l.keys,
            &mut push,
        );
    }
    let animations = if channels.is_empty() {
        String::new()
    } else {
        format!(
            r#","animations":[{{"name":"move","samplers":[{}],"channels":[{}]}}]"#,
            samplers.join(","),
            channels.join(",")
        )
    };
    format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_lights_punctual"],
        "extensions":{{"KHR_lights_punctual":{{"lights":[{}]}}}},
        "scenes":[{{"nodes":[{}]}}],"nodes":[{}],"materials":[{}],"meshes":[{}],
        "accessors":[{}],"bufferViews":[{}],
        "buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}]{animations}}}"#,
        light_defs.join(","),
        (0..nodes.len())
            .map(|i| i.to_string())
            .collect::<Vec<_>>()
            .join(","),
        nodes.join(","),
        materials.join(","),
        meshes.join(","),
        accessors.join(","),
        views.join(","),
        bin.len(),
        base64_encode(&bin)
    )
}
