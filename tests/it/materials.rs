//! Materials users export every day: alpha `MASK`/`BLEND` cut-outs, `COLOR_0`
//! vertex colours, normal maps, `KHR_texture_transform` and emissive textures. Each scene is a
//! small glTF built here, rendered (or traced) and checked against a closed form.

use std::f32::consts::PI;
use std::path::Path;

use anchorage::interaction::{Materials, trace};
use anchorage::photon::{GatherDirect, PhotonMap};
use anchorage::scene::{FrameScene, Scene};
use glam::{Vec2, Vec3};

use super::common::*;
use super::scenes::base64_encode;

/// A glTF under construction: one embedded buffer holding accessors and PNG images.
#[derive(Default)]
struct Gltf {
    bin: Vec<u8>,
    views: Vec<String>,
    accessors: Vec<String>,
    images: Vec<String>,
}

impl Gltf {
    fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.views.push(format!(
            r#"{{"buffer":0,"byteOffset":{offset},"byteLength":{}}}"#,
            bytes.len()
        ));
        self.views.len() - 1
    }

    /// An accessor over `bytes`; `extra` is appended to its JSON (min/max, normalized).
    fn accessor(
        &mut self,
        bytes: &[u8],
        component: u32,
        count: usize,
        ty: &str,
        extra: &str,
    ) -> usize {
        let v = self.view(bytes);
        self.accessors.push(format!(
            r#"{{"bufferView":{v},"componentType":{component},"count":{count},"type":"{ty}"{extra}}}"#
        ));
        self.accessors.len() - 1
    }

    fn floats(&mut self, data: &[f32], width: usize, ty: &str) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|f| f.to_le_bytes()).collect();
        self.accessor(&bytes, 5126, data.len() / width, ty, "")
    }

    fn positions(&mut self, p: &[Vec3]) -> usize {
        let lo = p.iter().fold(Vec3::splat(f32::MAX), |a, b| a.min(*b));
        let hi = p.iter().fold(Vec3::splat(f32::MIN), |a, b| a.max(*b));
        let bytes: Vec<u8> = p
            .iter()
            .flat_map(|v| v.to_array())
            .flat_map(|f| f.to_le_bytes())
            .collect();
        let extra = format!(
            r#","min":[{},{},{}],"max":[{},{},{}]"#,
            lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
        );
        self.accessor(&bytes, 5126, p.len(), "VEC3", &extra)
    }

    fn indices(&mut self, i: &[u32]) -> usize {
        let bytes: Vec<u8> = i.iter().flat_map(|x| x.to_le_bytes()).collect();
        self.accessor(&bytes, 5125, i.len(), "SCALAR", "")
    }

    /// An RGBA8 PNG image of `w`×`h` texels (rows top to bottom).
    fn png(&mut self, w: u32, h: u32, rgba: &[u8]) -> usize {
        let img = image::RgbaImage::from_raw(w, h, rgba.to_vec()).expect("texel count");
        let mut png = std::io::Cursor::new(Vec::new());
        img.write_to(&mut png, image::ImageFormat::Png)
            .expect("PNG encodes");
        let v = self.view(png.get_ref());
        self.images
            .push(format!(r#"{{"bufferView":{v},"mimeType":"image/png"}}"#));
        self.images.len() - 1
    }

    /// A quad primitive over `corners` (counter-clockwise seen from its front) with texture
    /// coordinates `uvs`, material `material` and extra attributes `attributes` (JSON
    /// members, e.g. `"COLOR_0":3`).
    fn quad(
        &mut self,
        corners: [Vec3; 4],
        uvs: [Vec2; 4],
        material: usize,
        attributes: &str,
    ) -> String {
        let p = self.positions(&corners);
        let uv: Vec<f32> = uvs.iter().flat_map(|u| u.to_array()).collect();
        let t = self.floats(&uv, 2, "VEC2");
        let i = self.indices(&[0, 1, 2, 0, 2, 3]);
        format!(
            r#"{{"attributes":{{"POSITION":{p},"TEXCOORD_0":{t}{attributes}}},"indices":{i},"material":{material}}}"#
        )
    }

    /// The whole file: `body` holds scenes, nodes, meshes, materials, textures, samplers and
    /// extensions; accessors, views, the buffer and images are added.
    fn finish(self, body: &str) -> String {
        let images = if self.images.is_empty() {
            String::new()
        } else {
            format!(r#","images":[{}]"#, self.images.join(","))
        };
        format!(
            r#"{{"asset":{{"version":"2.0"}},{body},"accessors":[{}],"bufferViews":[{}],
            "buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}]{images}}}"#,
            self.accessors.join(","),
            self.views.join(","),
            self.bin.len(),
            base64_encode(&self.bin)
        )
    }
}

/// A quad in the plane y = `y` over `x0..x1` × `z0..z1`, facing +y (`up`) or −y; texture
/// coordinates u along +x and v along +z, 0..1 over the quad.
fn flat_quad(y: f32, x: [f32; 2], z: [f32; 2], up: bool) -> ([Vec3; 4], [Vec2; 4]) {
    let c = [
        Vec3::new(x[0], y, z[0]),
        Vec3::new(x[0], y, z[1]),
        Vec3::new(x[1], y, z[1]),
        Vec3::new(x[1], y, z[0]),
    ];
    let uv = [
        Vec2::new(0.0, 0.0),
        Vec2::new(0.0, 1.0),
        Vec2::new(1.0, 1.0),
        Vec2::new(1.0, 0.0),
    ];
    if up {
        (c, uv)
    } else {
        ([c[0], c[3], c[2], c[1]], [uv[0], uv[3], uv[2], uv[1]])
    }
}

/// A directional light node whose light travels along (−sin φ, −cos φ, 0): from above,
/// tilted towards +x by φ.
fn sun_node(phi: f32) -> String {
    // Rotate −Z onto −Y (−90° about X), then by −φ about Z.
    let q = glam::Quat::from_rotation_z(-phi) * glam::Quat::from_rotation_x(-PI / 2.0);
    format!(
        r#"{{"name":"sun","rotation":[{},{},{},{}],"extensions":{{"KHR_lights_punctual":{{"light":0}}}}}}"#,
        q.x, q.y, q.z, q.w
    )
}

fn sun_light(lux: f32) -> String {
    format!(
        r#""extensionsUsed":["KHR_lights_punctual"],"extensions":{{"KHR_lights_punctual":{{"lights":[{{"type":"directional","intensity":{lux}}}]}}}}"#
    )
}

/// A job for `file` in `dir`: camera 5 units above the origin looking down (image right is
/// +x, image up is −z), `method`, `size`² pixels.
fn job(dir: &Path, file: &str, gltf: String, method: &str, size: u32) -> anchorage::job::Job {
    std::fs::write(dir.join(file), gltf).unwrap();
    job_from_json(
        &dir.join("job.json"),
        &format!(
            r#"{{"scene":[{{"path":"{file}"}}],
            "camera":{{"position":[0,5,0],"look_at":[0,0,0],"up":[0,0,-1],"yfov_deg":60}},
            "resolution":[{size},{size}],"render":{{"samples_per_pixel":4}},
            "method":{{"name":"{method}","preset":"draft"}}}}"#
        ),
    )
    .unwrap()
}

/// The scene at time 0 with its materials.
/// The scene at t = 0 and the world position of its render-space origin (frames are in
/// render space: world minus the static set's centre).
fn frame_of(scene: &Scene) -> (FrameScene, Vec3) {
    let statics = scene.statics();
    (
        scene.evaluate(0.0, 1.0, &statics).0,
        statics.origin.as_vec3(),
    )
}

fn materials(scene: &Scene) -> Materials<'_> {
    Materials {
        materials: &scene.materials,
        textures: &scene.textures,
    }
}

/// For every pixel centre: the pixel and the camera ray's points at y = 1 and y = 0.
fn pixels(job: &anchorage::job::Job, size: u32) -> Vec<(usize, Vec3, Vec3)> {
    let scene = job.load_scene().unwrap();
    let cam = scene.camera_at(0.0, 1.0);
    let mut out = Vec::new();
    for y in 0..size {
        for x in 0..size {
            let r = cam.ray(
                (x as f32 + 0.5) / size as f32,
                (y as f32 + 0.5) / size as f32,
            );
            let (o, d) = (r.origin, r.dir);
            let at = |h: f32| o + d * ((h - o.y) / d.y);
            out.push(((y * size + x) as usize, at(1.0), at(0.0)));
        }
    }
    out
}

fn close(got: f32, want: f32, tol: f32) -> bool {
    (got - want).abs() <= tol * want.abs().max(1e-3)
}

/// A 4×2 quad at y = 1 (x ∈ [−2, 2], z ∈ [−1, 1]) whose red base colour texture has alpha 0
/// in its left texel and 1 in its right one, over a grey floor, lit by a sun tilted 45°
/// towards +x. Bilinear alpha crosses the 0.5 cutoff at x = 0: the left half is cut out.
fn masked_quad_scene(g: &mut Gltf, alpha_mode: &str) -> String {
    let (c, uv) = flat_quad(0.0, [-10.0, 10.0], [-10.0, 10.0], true);
    let floor = g.quad(c, uv, 0, "");
    let (c, uv) = flat_quad(1.0, [-2.0, 2.0], [-1.0, 1.0], true);
    let quad = g.quad(c, uv, 1, "");
    let img = g.png(2, 1, &[255, 0, 0, 0, 255, 0, 0, 255]);
    format!(
        r#"{},"scenes":[{{"nodes":[0,1,2]}}],
        "nodes":[{{"mesh":0}},{{"mesh":1}},{}],
        "meshes":[{{"primitives":[{floor}]}},{{"primitives":[{quad}]}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}},
                     {{"name":"leaves","alphaMode":"{alpha_mode}","pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}},"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}],
        "samplers":[{{"wrapS":33071,"wrapT":33071}}],
        "textures":[{{"source":{img},"sampler":0}}]"#,
        sun_light(3.0),
        sun_node(PI / 4.0)
    )
}

/// The alpha-0 half of a masked quad is invisible to the camera and casts no shadow; the
/// alpha-1 half is seen (red) and shadows the floor. Sun of E lux at 45°: a lit floor point
/// reflects 0.5·E·cos45°/π, the lit red quad E·cos45°/π in red.
fn check_masked_quad(alpha_mode: &str) {
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = masked_quad_scene(&mut g, alpha_mode);
    let size = 64;
    let job = job(dir.path(), "masked.gltf", g.finish(&body), "direct", size);
    let img = render(&job, 0);
    let e = 3.0 * (PI / 4.0).cos();
    let (mut seen_through, mut shadowed, mut quad) = (0, 0, 0);
    for (i, q, p) in pixels(&job, size) {
        let got = img.beauty[i];
        let in_hole = (-1.85..=-0.15).contains(&q.x) && q.z.abs() < 0.85;
        let on_opaque = (0.15..=1.85).contains(&q.x) && q.z.abs() < 0.85;
        if on_opaque {
            quad += 1;
            assert!(
                close(got[0], e / PI, 0.01) && got[1] < 1e-4,
                "{alpha_mode}: pixel {i} sees the opaque half at {q}: {got:?}, want red {}",
                e / PI
            );
        } else if in_hole && (-2.85..=-1.15).contains(&p.x) && p.z.abs() < 0.85 {
            // The floor seen through the cut-out, lit through it (the sun's ray from the
            // floor meets y = 1 at x + 1, in the cut-out half).
            seen_through += 1;
            let want = 0.5 * e / PI;
            assert!(
                got.iter().take(3).all(|c| close(*c, want, 0.01)),
                "{alpha_mode}: pixel {i}, floor at {p} through the cut-out: {got:?}, want {want}"
            );
        } else if in_hole && (-0.85..=-0.15).contains(&p.x) && p.z.abs() < 0.85 {
            // The floor seen through the cut-out but shadowed by the opaque half.
            shadowed += 1;
            assert!(
                got.iter().take(3).all(|c| c.abs() < 1e-4),
                "{alpha_mode}: pixel {i}, floor at {p} in the opaque half's shadow: {got:?}"
            );
        }
    }
    assert!(
        seen_through > 20 && shadowed > 20 && quad > 20,
        "{seen_through} {shadowed} {quad}"
    );
}

#[test]
fn alpha_masked_quad_is_cut_out_for_camera_and_shadow_rays() {
    check_masked_quad("MASK");
}

/// BLEND renders as a cut-out at alpha 0.5 (README), with one warning naming the material.
#[test]
fn alpha_blend_renders_as_a_cut_out_with_a_warning() {
    check_masked_quad("BLEND");
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = masked_quad_scene(&mut g, "BLEND");
    let job = job(dir.path(), "blend.gltf", g.finish(&body), "direct", 8);
    let warnings = job.load_scene().unwrap().warnings();
    let blend: Vec<&String> = warnings.iter().filter(|w| w.contains("BLEND")).collect();
    assert_eq!(blend.len(), 1, "{warnings:?}");
    assert!(blend[0].contains("\"leaves\""), "{blend:?}");
}

/// Rough metals, whose reflection the cached methods shade from the irradiance cache
/// through its albedo (README, "What is modelled"), are warned about by name, and so are
/// primitives without a material (glTF's default is a white metal of roughness 1); a rough
/// dielectric, a smoother metal and a metal whose roughness comes from a texture are not.
#[test]
fn rough_metals_and_missing_materials_are_warned_about() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let mut prims = Vec::new();
    for m in 0..4 {
        let (c, uv) = flat_quad(m as f32, [-1.0, 1.0], [-1.0, 1.0], true);
        prims.push(g.quad(c, uv, m, ""));
    }
    let (c, uv) = flat_quad(5.0, [-1.0, 1.0], [-1.0, 1.0], true);
    prims.push(g.quad(c, uv, 0, "").replace(r#","material":0"#, ""));
    let img = g.png(1, 1, &[0, 255, 255, 255]);
    let body = format!(
        r#"{},"scenes":[{{"nodes":[0,1]}}],
        "nodes":[{{"mesh":0}},{}],
        "meshes":[{{"primitives":[{}]}}],
        "materials":[{{"name":"steel","pbrMetallicRoughness":{{"metallicFactor":1,"roughnessFactor":0.8}}}},
                     {{"name":"paint","pbrMetallicRoughness":{{"metallicFactor":0,"roughnessFactor":1}}}},
                     {{"name":"chrome","pbrMetallicRoughness":{{"metallicFactor":1,"roughnessFactor":0.3}}}},
                     {{"name":"mapped","pbrMetallicRoughness":{{"metallicFactor":1,"metallicRoughnessTexture":{{"index":0}}}}}}],
        "textures":[{{"source":{img}}}]"#,
        sun_light(3.0),
        sun_node(PI / 4.0),
        prims.join(",")
    );
    let job = job(dir.path(), "metals.gltf", g.finish(&body), "direct", 8);
    let warnings = job.load_scene().unwrap().warnings();
    let rough: Vec<&String> = warnings
        .iter()
        .filter(|w| w.contains("reflects onto others as diffuse"))
        .collect();
    assert_eq!(rough.len(), 2, "{warnings:?}");
    assert!(
        rough[0].contains("\"steel\"") && rough[0].contains("roughness 0.8"),
        "{rough:?}"
    );
    assert!(
        rough[1].contains("1 primitive(s) have no material"),
        "{rough:?}"
    );
}

/// Photons pass through the cut-out half and stop on the opaque one: of the photons' first
/// hits (straight from the sun), none lies on the cut-out half, none on the floor in the
/// opaque half's shadow, and many on the floor lit through the cut-out.
#[test]
fn photons_pass_through_the_cut_out() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = masked_quad_scene(&mut g, "MASK");
    let job = job(dir.path(), "masked.gltf", g.finish(&body), "direct", 8);
    let scene = job.load_scene().unwrap();
    let (frame, origin) = frame_of(&scene);
    let map = PhotonMap::trace(
        &frame,
        materials(&scene),
        &anchorage::photon::Emission {
            count: 200_000,
            seed: 7,
            max_bounces: 0,
            max_radius: 0.05,
            direct: GatherDirect::Photons,
        },
        None,
    );
    let first: Vec<Vec3> = map.path_start[..map.path_start.len() - 1]
        .iter()
        .zip(&map.path_start[1..])
        .filter(|(a, b)| b > a)
        .map(|(a, _)| map.photons[*a as usize].position + origin)
        .collect();
    assert!(first.len() > 1000, "{} photons", first.len());
    let on_hole = |p: &Vec3| (p.y - 1.0).abs() < 1e-3 && p.x < -0.05 && p.z.abs() < 1.0;
    let in_shadow = |p: &Vec3| p.y.abs() < 1e-3 && (-0.95..0.95).contains(&p.x) && p.z.abs() < 0.95;
    let through = |p: &Vec3| p.y.abs() < 1e-3 && (-2.95..-1.05).contains(&p.x) && p.z.abs() < 0.95;
    let on_opaque = |p: &Vec3| (p.y - 1.0).abs() < 1e-3 && p.x > 0.05 && p.z.abs() < 1.0;
    assert_eq!(first.iter().filter(|p| on_hole(p)).count(), 0);
    assert_eq!(first.iter().filter(|p| in_shadow(p)).count(), 0);
    assert!(first.iter().filter(|p| through(p)).count() > 100);
    assert!(first.iter().filter(|p| on_opaque(p)).count() > 100);
}

/// A floor of three quads with `COLOR_0` red (float VEC3), green (normalized u8 VEC4) and
/// blue (normalized u16 VEC3), base colour factor 0.5: under a sun of E lux from straight
/// above, each reflects 0.5·E/π in its colour alone.
#[test]
fn vertex_colours_multiply_the_base_colour() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let red: Vec<f32> = [1.0, 0.0, 0.0].repeat(4);
    let red = g.floats(&red, 3, "VEC3");
    let green: Vec<u8> = [0u8, 255, 0, 128].repeat(4);
    let green = g.accessor(&green, 5121, 4, "VEC4", r#","normalized":true"#);
    let blue: Vec<u8> = [0u16, 0, 65535, 0]
        .repeat(4)
        .iter()
        .flat_map(|c| c.to_le_bytes())
        .collect();
    // VEC3 u16 elements are 6 bytes; pad each to 8 with a byteStride.
    let v = g.view(&blue);
    g.views[v] = g.views[v].replace('}', r#","byteStride":8}"#);
    g.accessors.push(format!(
        r#"{{"bufferView":{v},"componentType":5123,"normalized":true,"count":4,"type":"VEC3"}}"#
    ));
    let blue = g.accessors.len() - 1;
    let (c, uv) = flat_quad(0.0, [-3.0, 0.0], [-3.0, 3.0], true);
    let a = g.quad(c, uv, 0, &format!(r#","COLOR_0":{red}"#));
    let (c, uv) = flat_quad(0.0, [0.0, 3.0], [0.0, 3.0], true);
    let b = g.quad(c, uv, 0, &format!(r#","COLOR_0":{green}"#));
    let (c, uv) = flat_quad(0.0, [0.0, 3.0], [-3.0, 0.0], true);
    let cq = g.quad(c, uv, 0, &format!(r#","COLOR_0":{blue}"#));
    let body = format!(
        r#"{},"scenes":[{{"nodes":[0,1]}}],"nodes":[{{"mesh":0}},{}],
        "meshes":[{{"primitives":[{a},{b},{cq}]}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}]"#,
        sun_light(2.0),
        sun_node(0.0)
    );
    let size = 32;
    let job = job(dir.path(), "colours.gltf", g.finish(&body), "direct", size);
    let img = render(&job, 0);
    let want = 0.5 * 2.0 / PI;
    let mut checked = [0; 3];
    for (i, _, p) in pixels(&job, size) {
        let (k, colour) = if p.x < -0.2 && p.z.abs() < 2.8 {
            (0, [want, 0.0, 0.0])
        } else if p.x > 0.2 && p.z > 0.2 && p.x < 2.8 {
            (1, [0.0, want, 0.0])
        } else if p.x > 0.2 && p.z < -0.2 && p.x < 2.8 {
            (2, [0.0, 0.0, want])
        } else {
            continue;
        };
        checked[k] += 1;
        let got = img.beauty[i];
        for ch in 0..3 {
            assert!(
                (got[ch] - colour[ch]).abs() < 0.01 * want,
                "pixel {i} at {p}: {got:?}, want {colour:?}"
            );
        }
    }
    assert!(checked.iter().all(|&n| n > 20), "{checked:?}");
}

/// The tangent-space normal (sin 30°, 0, cos 30°) in an 8-bit texel, decoded as the renderer
/// must: (2c − 1) per channel.
fn tilted_texel() -> ([u8; 4], Vec3) {
    let t = [191u8, 128, 238, 255];
    let n = Vec3::new(t[0] as f32, t[1] as f32, t[2] as f32) / 255.0 * 2.0 - Vec3::ONE;
    (t, n)
}

/// A floor with a normal map tilting it 30° (texel [`tilted_texel`]): the left half derives
/// its tangent from the UVs (T = ∂p/∂u = +x, B = −∂p/∂v = −z), the right half has
/// `TANGENT` (0, 0, 1, +1) (T = +z, B = N × T = +x). Sun from 30° towards +x.
fn normal_mapped_scene(g: &mut Gltf) -> String {
    normal_mapped_scene_with(g, 1.0)
}

/// [`normal_mapped_scene`] with the right half's `NORMAL` (0, `ny`, 0).
fn normal_mapped_scene_with(g: &mut Gltf, ny: f32) -> String {
    let (c, uv) = flat_quad(0.0, [-3.0, 0.0], [-3.0, 3.0], true);
    let left = g.quad(c, uv, 0, "");
    let tangents = g.floats(&[0.0, 0.0, 1.0, 1.0].repeat(4), 4, "VEC4");
    let normals = g.floats(&[0.0, ny, 0.0].repeat(4), 3, "VEC3");
    let (c, uv) = flat_quad(0.0, [0.0, 3.0], [-3.0, 3.0], true);
    let right = g.quad(
        c,
        uv,
        0,
        &format!(r#","TANGENT":{tangents},"NORMAL":{normals}"#),
    );
    let (texel, _) = tilted_texel();
    let img = g.png(1, 1, &texel);
    format!(
        r#"{},"scenes":[{{"nodes":[0,1]}}],"nodes":[{{"mesh":0}},{}],
        "meshes":[{{"primitives":[{left},{right}]}}],
        "materials":[{{"normalTexture":{{"index":0}},"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}],
        "textures":[{{"source":{img}}}]"#,
        sun_light(2.0),
        sun_node(PI / 6.0)
    )
}

/// Direct light follows the mapped normal: 0.5/π · E · (n_s · ω_i) with n_s = T·x + B·y +
/// N·z from the texel — not the geometric cos 30°.
#[test]
fn normal_maps_tilt_the_direct_shading_as_the_closed_form_predicts() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = normal_mapped_scene(&mut g);
    let size = 32;
    let job = job(dir.path(), "normals.gltf", g.finish(&body), "direct", size);
    let img = render(&job, 0);
    let (_, n) = tilted_texel();
    let wi = Vec3::new((PI / 6.0).sin(), (PI / 6.0).cos(), 0.0);
    let derived = (Vec3::X * n.x - Vec3::Z * n.y + Vec3::Y * n.z).normalize();
    let given = (Vec3::Z * n.x + Vec3::X * n.y + Vec3::Y * n.z).normalize();
    let radiance = |ns: Vec3| 0.5 / PI * 2.0 * ns.dot(wi);
    // The two differ from each other and from the unmapped floor by over 10 %.
    let flat = radiance(Vec3::Y);
    assert!((radiance(derived) / flat - 1.0).abs() > 0.1);
    assert!((radiance(given) / flat - 1.0).abs() > 0.1);
    let mut checked = [0; 2];
    for (i, _, p) in pixels(&job, size) {
        if p.z.abs() > 2.8 || p.x.abs() < 0.2 || p.x.abs() > 2.8 {
            continue;
        }
        let (k, want) = if p.x < 0.0 {
            (0, radiance(derived))
        } else {
            (1, radiance(given))
        };
        checked[k] += 1;
        let got = img.beauty[i][0];
        assert!(
            close(got, want, 0.005),
            "pixel {i} at {p}: {got}, want {want} (unmapped {flat})"
        );
    }
    assert!(checked.iter().all(|&n| n > 20), "{checked:?}");
}

/// Vertex normals against the winding (a mirrored export) keep their normal map: glTF builds
/// the frame from the file's normal N = −y (B = N × T = −x for `TANGENT` +z), and the mapped
/// normal is turned with N to the viewer's side, −(T·x + B·y + N·z). The map was dropped
/// there, the floor shaded as if unmapped.
#[test]
fn a_normal_map_applies_where_vertex_normals_oppose_the_winding() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = normal_mapped_scene_with(&mut g, -1.0);
    let size = 32;
    let job = job(dir.path(), "normals.gltf", g.finish(&body), "direct", size);
    let img = render(&job, 0);
    let (_, n) = tilted_texel();
    let wi = Vec3::new((PI / 6.0).sin(), (PI / 6.0).cos(), 0.0);
    let against = (-Vec3::Z * n.x + Vec3::X * n.y + Vec3::Y * n.z).normalize();
    let radiance = |ns: Vec3| 0.5 / PI * 2.0 * ns.dot(wi);
    let flat = radiance(Vec3::Y);
    assert!((radiance(against) / flat - 1.0).abs() > 0.1);
    let mut checked = 0;
    for (i, _, p) in pixels(&job, size) {
        if p.z.abs() > 2.8 || p.x < 0.2 || p.x > 2.8 {
            continue;
        }
        checked += 1;
        let (got, want) = (img.beauty[i][0], radiance(against));
        assert!(
            close(got, want, 0.005),
            "pixel {i} at {p}: {got}, want {want} (unmapped {flat})"
        );
    }
    assert!(checked > 20, "{checked}");
}

/// The mapped normal shades, the geometric normal still offsets rays: at a hit on the
/// normal-mapped floor, `ns` is tilted by the map while `ng` is the plane's normal and rays
/// leave along it.
#[test]
fn normal_maps_leave_the_geometric_normal_and_offsets_alone() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = normal_mapped_scene(&mut g);
    let job = job(dir.path(), "normals.gltf", g.finish(&body), "direct", 8);
    let scene = job.load_scene().unwrap();
    let (frame, origin) = frame_of(&scene);
    let (_, n) = tilted_texel();
    let derived = (Vec3::X * n.x - Vec3::Z * n.y + Vec3::Y * n.z).normalize();
    let sp = trace(&frame, Vec3::new(-1.5, 2.0, 0.5) - origin, -Vec3::Y).expect("hits the floor");
    assert!((sp.ng - Vec3::Y).length() < 1e-6, "ng {}", sp.ng);
    assert!(
        (sp.ns - derived).length() < 1e-3,
        "ns {} vs {derived}",
        sp.ns
    );
    // Along ng only (zero where the hit point is exact), and the ray leaving along the tilted
    // shading normal does not find the floor again.
    let off = sp.spawn() - sp.position;
    assert!(off.y >= 0.0 && off.x == 0.0 && off.z == 0.0, "offset {off}");
    let again = trace(&frame, sp.spawn(), sp.ns);
    assert!(
        again.is_none_or(|h| h.hit.triangle != sp.hit.triangle),
        "re-hit the floor"
    );
}

/// `KHR_texture_transform` (required by the file) changes which texel is seen: a 4×1
/// texture red, red, green, green; the left quad reads it as is (red over u < 0.375), the
/// right one with offset (0.75, 0) and scale (0.25, 1), so that u ∈ [0, 1] reads
/// u' ∈ [0.75, 1]: green everywhere.
#[test]
fn texture_transform_offset_and_scale_choose_the_texel() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let (c, uv) = flat_quad(0.0, [-2.5, 0.0], [-2.5, 2.5], true);
    let left = g.quad(c, uv, 0, "");
    let (c, uv) = flat_quad(0.0, [0.0, 2.5], [-2.5, 2.5], true);
    let right = g.quad(c, uv, 1, "");
    let img = g.png(
        4,
        1,
        &[
            255, 0, 0, 255, 255, 0, 0, 255, 0, 255, 0, 255, 0, 255, 0, 255,
        ],
    );
    let body = format!(
        r#""extensionsUsed":["KHR_lights_punctual","KHR_texture_transform"],
        "extensionsRequired":["KHR_texture_transform"],
        "extensions":{{"KHR_lights_punctual":{{"lights":[{{"type":"directional","intensity":2}}]}}}},
        "scenes":[{{"nodes":[0,1]}}],"nodes":[{{"mesh":0}},{}],
        "meshes":[{{"primitives":[{left},{right}]}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}},"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}},
                     {{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0,"extensions":{{"KHR_texture_transform":{{"offset":[0.75,0],"scale":[0.25,1]}}}}}},"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}],
        "samplers":[{{"wrapS":33071,"wrapT":33071}}],
        "textures":[{{"source":{img},"sampler":0}}]"#,
        sun_node(0.0)
    );
    let size = 32;
    let job = job(
        dir.path(),
        "transform.gltf",
        g.finish(&body),
        "direct",
        size,
    );
    let scene = job
        .load_scene()
        .expect("KHR_texture_transform is supported");
    assert!(
        !scene
            .warnings()
            .iter()
            .any(|w| w.contains("KHR_texture_transform")),
        "{:?}",
        scene.warnings()
    );
    let img = render(&job, 0);
    let want = 2.0 / PI;
    let mut checked = [0; 2];
    for (i, _, p) in pixels(&job, size) {
        if p.z.abs() > 2.3 {
            continue;
        }
        let got = img.beauty[i];
        // u ∈ [0.05, 0.28] on either quad (pixels are 0.07 wide in u).
        let u_left = (p.x + 2.5) / 2.5;
        let u_right = p.x / 2.5;
        if (0.05..0.28).contains(&u_left) {
            checked[0] += 1;
            assert!(
                close(got[0], want, 0.01) && got[1] < 1e-4,
                "pixel {i} at {p}: {got:?}"
            );
        } else if (0.05..0.28).contains(&u_right) {
            checked[1] += 1;
            assert!(
                close(got[1], want, 0.01) && got[0] < 1e-4,
                "pixel {i} at {p}: {got:?}"
            );
        }
    }
    assert!(checked.iter().all(|&n| n > 10), "{checked:?}");
}

/// An emitter 4×2 at y = `y` (x ∈ [−2, 2], z ∈ [−1, 1]) with emissive factor 1, strength
/// 2 and an emissive texture black in its left texel, white in its right one: radiance
/// 2·clamp((u − 0.25)/0.5, 0, 1), whose mean over the quad is 1.
fn emitter_scene(g: &mut Gltf, y: f32, up: bool, floor: bool) -> String {
    let (c, uv) = flat_quad(y, [-2.0, 2.0], [-1.0, 1.0], up);
    let lamp = g.quad(c, uv, 0, "");
    let (c, uv) = flat_quad(0.0, [-10.0, 10.0], [-10.0, 10.0], true);
    let ground = g.quad(c, uv, 1, "");
    let img = g.png(2, 1, &[0, 0, 0, 255, 255, 255, 255, 255]);
    let primitives = if floor {
        format!("{lamp},{ground}")
    } else {
        lamp
    };
    format!(
        r#""extensionsUsed":["KHR_materials_emissive_strength"],
        "scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
        "meshes":[{{"primitives":[{primitives}]}}],
        "materials":[{{"emissiveFactor":[1,1,1],"emissiveTexture":{{"index":0}},
                       "extensions":{{"KHR_materials_emissive_strength":{{"emissiveStrength":2}}}},
                       "pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1]}}}},
                     {{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}],
        "samplers":[{{"wrapS":33071,"wrapT":33071}}],
        "textures":[{{"source":{img},"sampler":0}}]"#
    )
}

/// Camera hits see the emissive texture: radiance 2·clamp((u − 0.25)/0.5, 0, 1).
#[test]
fn emissive_textures_are_seen_by_the_camera() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = emitter_scene(&mut g, 1.0, true, false);
    let size = 48;
    let job = job(dir.path(), "lamp.gltf", g.finish(&body), "direct", size);
    let scene = job.load_scene().unwrap();
    assert!(
        !scene.warnings().iter().any(|w| w.contains("emissive")),
        "{:?}",
        scene.warnings()
    );
    let img = render(&job, 0);
    let mut checked = [0; 3];
    for (i, q, _) in pixels(&job, size) {
        if q.x.abs() > 1.9 || q.z.abs() > 0.9 {
            continue;
        }
        let u = (q.x + 2.0) / 4.0;
        let want = 2.0 * ((u - 0.25) / 0.5).clamp(0.0, 1.0);
        checked[if u < 0.25 {
            0
        } else if u > 0.75 {
            2
        } else {
            1
        }] += 1;
        let got = img.beauty[i][0];
        // Four jittered samples over a pixel ~0.05 wide on a ramp of slope 4 per unit.
        assert!(
            (got - want).abs() < 0.12,
            "pixel {i} at {q}: {got}, want {want}"
        );
    }
    assert!(checked.iter().all(|&n| n > 20), "{checked:?}");
}

/// Photon emission integrates the texture: the power emitted is π·A·mean L = 8π, the
/// photons' first hits carry it all, and photons leave only where the texture emits — the
/// floor 0.01 under the black end receives almost nothing.
#[test]
fn photon_power_follows_the_emissive_texture() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let body = emitter_scene(&mut g, 0.01, false, true);
    let job = job(dir.path(), "lamp.gltf", g.finish(&body), "direct", 8);
    let scene = job.load_scene().unwrap();
    let (frame, origin) = frame_of(&scene);
    let map = PhotonMap::trace(
        &frame,
        materials(&scene),
        &anchorage::photon::Emission {
            count: 100_000,
            seed: 3,
            max_bounces: 0,
            max_radius: 0.05,
            direct: GatherDirect::Photons,
        },
        None,
    );
    let total = luminance(map.emitted_power);
    assert!(
        close(total, 8.0 * PI, 0.03),
        "emitted {total} vs {}",
        8.0 * PI
    );
    let first: Vec<_> = map.path_start[..map.path_start.len() - 1]
        .iter()
        .zip(&map.path_start[1..])
        .filter(|(a, b)| b > a)
        .map(|(a, _)| map.photons[*a as usize])
        .collect();
    let stored: f32 = first.iter().map(|p| luminance(p.power)).sum();
    assert!(
        close(stored, 8.0 * PI, 0.03),
        "stored {stored} vs {}",
        8.0 * PI
    );
    let power_where = |f: &dyn Fn(f32) -> bool| -> f32 {
        first
            .iter()
            .filter(|p| f(p.position.x + origin.x) && (p.position.z + origin.z).abs() < 0.9)
            .map(|p| luminance(p.power))
            .sum()
    };
    let dark = power_where(&|x| (-1.9..-1.1).contains(&x));
    let bright = power_where(&|x| (1.1..1.9).contains(&x));
    assert!(
        bright > 0.0 && dark < 0.02 * bright,
        "dark {dark}, bright {bright}"
    );
}

fn luminance(c: Vec3) -> f32 {
    anchorage::color::luminance(c)
}

/// What a file uses and anchorage does not model is named once per material; KHR material
/// extensions are named with their material and not again for the file.
#[test]
fn unmodelled_material_features_are_warned_about_once_each() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let (c, uv) = flat_quad(0.0, [-1.0, 1.0], [-1.0, 1.0], true);
    let q = g.quad(c, uv, 0, "");
    let img = g.png(1, 1, &[255, 255, 255, 255]);
    let body = format!(
        r#""extensionsUsed":["KHR_materials_transmission","KHR_materials_clearcoat","EXT_fancy"],
        "scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
        "meshes":[{{"primitives":[{q}]}}],
        "materials":[{{"name":"glass","occlusionTexture":{{"index":0}},
                       "emissiveTexture":{{"index":0,"texCoord":1}},"emissiveFactor":[1,1,1],
                       "extensions":{{"KHR_materials_transmission":{{"transmissionFactor":1}},
                                     "KHR_materials_clearcoat":{{"clearcoatFactor":1}}}}}}],
        "textures":[{{"source":{img}}}]"#
    );
    let job = job(dir.path(), "glass.gltf", g.finish(&body), "direct", 8);
    let w = job.load_scene().unwrap().warnings();
    let count = |s: &str| w.iter().filter(|x| x.contains(s)).count();
    for s in [
        "KHR_materials_transmission",
        "KHR_materials_clearcoat",
        "occlusionTexture",
        "TEXCOORD_1",
        "EXT_fancy",
    ] {
        assert_eq!(count(s), 1, "{s}: {w:?}");
    }
    for s in [
        "KHR_materials_transmission",
        "KHR_materials_clearcoat",
        "occlusionTexture",
        "TEXCOORD_1",
    ] {
        assert!(
            w.iter().any(|x| x.contains(s) && x.contains("\"glass\"")),
            "{s} names the material: {w:?}"
        );
    }
}

/// `anchorage validate` on a tiny job over the example room as `edit` changes its glTF:
/// the exit status and standard error.
fn validate_room(edit: impl FnOnce(&mut serde_json::Value)) -> (Option<i32>, String) {
    let dir = super::common::tempdir();
    let text =
        std::fs::read_to_string(super::common::root().join("examples/room/room.gltf")).unwrap();
    let mut doc: serde_json::Value = serde_json::from_str(&text).unwrap();
    edit(&mut doc);
    std::fs::write(dir.path().join("room.gltf"), doc.to_string()).unwrap();
    let job = dir.path().join("job.json");
    std::fs::write(
        &job,
        r#"{"scene":[{"path":"room.gltf"}],"resolution":[8,8]}"#,
    )
    .unwrap();
    let o = super::common::run(&["validate", job.to_str().unwrap()]);
    (o.status.code(), super::common::stderr(&o))
}

/// `KHR_materials_specular` is read (its `specularFactor`), so a file that declares it used
/// or required loads without the warning that it is ignored.
#[test]
fn khr_materials_specular_is_a_supported_extension() {
    // Listed as used, then as required (which the gltf crate's own validation refuses for
    // extensions it has no typed support for): both load without a word about it.
    for key in ["extensionsUsed", "extensionsRequired"] {
        let (code, err) = validate_room(|doc| {
            doc["extensionsUsed"] = serde_json::json!(["KHR_materials_specular"]);
            doc[key] = serde_json::json!(["KHR_materials_specular"]);
            doc["materials"][0]["extensions"] =
                serde_json::json!({"KHR_materials_specular": {"specularFactor": 0.5}});
        });
        assert_eq!(code, Some(0), "{key}: {err}");
        assert!(!err.contains("KHR_materials_specular"), "{key}: {err}");
    }
    // An extension the file requires and anchorage does not model is still refused.
    let (code, err) = validate_room(|doc| {
        doc["extensionsUsed"] = serde_json::json!(["KHR_materials_transmission"]);
        doc["extensionsRequired"] = serde_json::json!(["KHR_materials_transmission"]);
    });
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("extensionsRequired") && err.contains("KHR_materials_transmission"),
        "{err}"
    );
}

/// Watch mode: an edit of a cut-out material's texture changes the geometry rays see, so it
/// rebuilds the state; the same edit of an opaque material's texture changes colours only,
/// and relights.
#[test]
fn watch_rebuilds_after_an_edit_of_a_cut_out_texture() {
    use anchorage::watch::{Loaded, Rule, classify};
    let dir = tempdir();
    let write = |alpha: [u8; 2], mode: &str| {
        let mut g = Gltf::default();
        let body = masked_quad_scene(&mut g, mode);
        // The quad's texture is the scene's only image: rewrite its texels.
        g.images.clear();
        g.png(2, 1, &[255, 0, 0, alpha[0], 255, 0, 0, alpha[1]]);
        std::fs::write(dir.path().join("masked.gltf"), g.finish(&body)).unwrap();
        std::fs::write(
            dir.path().join("job.json"),
            r#"{"scene":[{"path":"masked.gltf"}],
            "camera":{"position":[0,5,0],"look_at":[0,0,0],"up":[0,0,-1],"yfov_deg":60},
            "resolution":[8,8],"method":{"name":"anchors","preset":"draft"}}"#,
        )
        .unwrap();
        Loaded::load(&dir.path().join("job.json"), &Default::default()).unwrap()
    };
    let rule = |mode: &str, a: [u8; 2], b: [u8; 2]| {
        let old = write(a, mode);
        let new = write(b, mode);
        let c = classify(&old, &new);
        (c.rule, c.what.join(", "))
    };
    let (r, what) = rule("MASK", [0, 255], [255, 255]);
    assert_eq!(r, Rule::Rebuild, "{what}");
    assert!(what.contains("alpha cut-out"), "{what}");
    // The same texture on an opaque material: only its colour changed for the renderer.
    let (r, what) = rule("OPAQUE", [0, 255], [255, 255]);
    assert_eq!(r, Rule::Relight, "{what}");
}

/// An emitter's alpha cut-out removes its light as well as its surface: a double-sided
/// emissive quad 1 above the floor whose left half has alpha 0 lights the floor as a quad
/// of its right half alone does (direct light sampled on it, and the photons that leave it).
/// Its removed half emitted as much as the rest: the floor got twice the direct light.
#[test]
fn a_cut_out_emitter_emits_only_where_its_surface_is() {
    let dir = tempdir();
    let render_with = |masked: bool, method: &str| {
        let mut g = Gltf::default();
        let (c, uv) = flat_quad(0.0, [-10.0, 10.0], [-10.0, 10.0], true);
        let floor = g.quad(c, uv, 0, "");
        let x = if masked { [-2.0, 2.0] } else { [0.0, 2.0] };
        let (c, uv) = flat_quad(1.0, x, [-1.0, 1.0], true);
        let lamp = g.quad(c, uv, 1, "");
        let img = g.png(2, 1, &[255, 255, 255, 0, 255, 255, 255, 255]);
        let cut = if masked {
            r#""alphaMode":"MASK","pbrMetallicRoughness":{"baseColorTexture":{"index":0},"baseColorFactor":[0.8,0.8,0.8,1],"metallicFactor":0},"#
        } else {
            r#""pbrMetallicRoughness":{"baseColorFactor":[0.8,0.8,0.8,1],"metallicFactor":0},"#
        };
        let body = format!(
            r#"{},"scenes":[{{"nodes":[0,1,2]}}],
            "nodes":[{{"mesh":0}},{{"mesh":1}},{}],
            "meshes":[{{"primitives":[{floor}]}},{{"primitives":[{lamp}]}}],
            "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}},
                         {{"name":"lamp",{cut}"emissiveFactor":[1,1,1],"doubleSided":true}}],
            "samplers":[{{"wrapS":33071,"wrapT":33071,"magFilter":9728}}],
            "textures":[{{"source":{img},"sampler":0}}]"#,
            sun_light(0.0),
            sun_node(PI / 4.0)
        );
        render(
            &job(dir.path(), "lamp.gltf", g.finish(&body), method, 48),
            0,
        )
    };
    let mean = |img: &anchorage::integrator::FrameImage,
                aov: fn(&anchorage::integrator::FrameImage, usize) -> f32| {
        (0..img.direct.len())
            .map(|i| f64::from(aov(img, i)))
            .sum::<f64>()
            / img.direct.len() as f64
    };
    for method in ["direct", "brute-force"] {
        let (cut, half) = (render_with(true, method), render_with(false, method));
        let direct = (
            mean(&cut, |m, i| m.direct[i][1]),
            mean(&half, |m, i| m.direct[i][1]),
        );
        eprintln!(
            "{method}: direct light {:.4} cut out, {:.4} half",
            direct.0, direct.1
        );
        assert!(
            direct.1 > 0.0 && (direct.0 / direct.1 - 1.0).abs() < 0.1,
            "{method}: {direct:?}"
        );
        if method == "brute-force" {
            let ind = (
                mean(&cut, |m, i| m.indirect[i][1]),
                mean(&half, |m, i| m.indirect[i][1]),
            );
            eprintln!(
                "{method}: indirect light {:.4} cut out, {:.4} half",
                ind.0, ind.1
            );
            assert!(
                ind.1 > 0.0 && (ind.0 / ind.1 - 1.0).abs() < 0.15,
                "{method}: {ind:?}"
            );
        }
    }
}

/// A textured emitter whose light lies only between the points its power is averaged at
/// (the 16 × 16 texture's corner texel, next to both triangles' first vertex, where no
/// point of the 8 × 8 grid falls) still lights the scene; it was dropped from the emitters.
#[test]
fn a_textured_emitter_lit_between_its_averaging_points_is_kept() {
    let dir = tempdir();
    let mut g = Gltf::default();
    let (c, uv) = flat_quad(0.0, [-10.0, 10.0], [-10.0, 10.0], true);
    let floor = g.quad(c, uv, 0, "");
    let (c, uv) = flat_quad(1.0, [-2.0, 2.0], [-2.0, 2.0], true);
    let lamp = g.quad(c, uv, 1, "");
    let mut texels = vec![0u8; 16 * 16 * 4];
    texels[..4].copy_from_slice(&[255, 255, 255, 255]);
    for t in texels.chunks_mut(4) {
        t[3] = 255;
    }
    let img = g.png(16, 16, &texels);
    let body = format!(
        r#"{},"scenes":[{{"nodes":[0,1,2]}}],
        "nodes":[{{"mesh":0}},{{"mesh":1}},{}],
        "meshes":[{{"primitives":[{floor}]}},{{"primitives":[{lamp}]}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.5,0.5,1],"metallicFactor":0}},"extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}},
                     {{"name":"lamp","pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1],"metallicFactor":0}},
                       "emissiveFactor":[1,1,1],"emissiveTexture":{{"index":0}},"doubleSided":true}}],
        "samplers":[{{"wrapS":33071,"wrapT":33071,"magFilter":9728}}],
        "textures":[{{"source":{img},"sampler":0}}]"#,
        sun_light(0.0),
        sun_node(PI / 4.0)
    );
    let gltf = g.finish(&body);
    for method in ["direct", "brute-force"] {
        let img = render(&job(dir.path(), "spot.gltf", gltf.clone(), method, 48), 0);
        let lit = img.direct.iter().filter(|d| d[1] > 0.0).count();
        eprintln!("{method}: {lit} pixels lit");
        assert!(lit > 0, "{method}: no pixel lit by the emitter");
    }
}
