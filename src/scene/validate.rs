//! Validation of everything a glTF document declares, before any of it is read.
//!
//! The `gltf` crate trusts the indices, component types and counts a file declares: an
//! animation channel naming a node the file lacks, an index accessor of type FLOAT or a
//! primitive naming a missing accessor panic inside it, and a count of 2³¹ is allocated as
//! given. [`check`] walks the unvalidated JSON (glTF 2.0 §3 and §5) and refuses, as an
//! [`Error::Input`] naming the element (`meshes[3].primitives[0].attributes.NORMAL`,
//! `animations[1].channels[4].target.node`, `accessors[2].count`), every index out of range,
//! every component type or element type a semantic does not allow, every count that does not
//! fit its buffer view and buffer (in overflow-free `u64` arithmetic), every `byteStride`
//! shorter than the elements it strides (the crate asserts on one), and a node graph that is
//! not a forest. Only then is the document handed to the crate.

use std::path::Path;

use gltf::json;
use json::accessor::{ComponentType, Type};
use json::animation::{Interpolation, Property};
use json::mesh::Semantic;
use json::validation::Checked;

use crate::error::{Error, Result};

/// The most elements an accessor without a buffer view may declare: such an accessor is all
/// zeros (plus its sparse values), and reading it allocates `count` elements.
pub const MAX_ZERO_ACCESSOR_BYTES: u64 = 256 << 20;

/// What the accessor at `at` must be: the allowed element types and component types, and
/// whether integer components must be `normalized`.
struct Want<'s> {
    types: &'s [Type],
    floats: bool,
    /// Integer component types allowed (normalized unless `raw_ints`).
    ints: &'s [ComponentType],
    raw_ints: bool,
}

const F32_VEC3: Want<'static> = Want {
    types: &[Type::Vec3],
    floats: true,
    ints: &[],
    raw_ints: false,
};

/// Checks the document `root` of file `path` (see the module documentation).
pub fn check(path: &Path, root: &json::Root) -> Result<()> {
    V { path, root }.all()
}

struct V<'a> {
    path: &'a Path,
    root: &'a json::Root,
}

/// The element size in bytes and the number of components of an accessor's elements.
fn component_count(t: Type) -> u64 {
    t.multiplicity() as u64
}

fn type_name(t: Type) -> &'static str {
    match t {
        Type::Scalar => "SCALAR",
        Type::Vec2 => "VEC2",
        Type::Vec3 => "VEC3",
        Type::Vec4 => "VEC4",
        Type::Mat2 => "MAT2",
        Type::Mat3 => "MAT3",
        Type::Mat4 => "MAT4",
    }
}

fn component_name(c: ComponentType) -> &'static str {
    match c {
        ComponentType::I8 => "BYTE (5120)",
        ComponentType::U8 => "UNSIGNED_BYTE (5121)",
        ComponentType::I16 => "SHORT (5122)",
        ComponentType::U16 => "UNSIGNED_SHORT (5123)",
        ComponentType::U32 => "UNSIGNED_INT (5125)",
        ComponentType::F32 => "FLOAT (5126)",
    }
}

impl V<'_> {
    fn bad(&self, at: impl Into<String>, message: impl Into<String>) -> Error {
        Error::input(self.path, at, message)
    }

    /// Index `i` at `at` must name one of the `len` elements of the array `what`.
    fn index(&self, at: &str, i: usize, len: usize, what: &str) -> Result<()> {
        if i < len {
            Ok(())
        } else {
            Err(self.bad(
                at,
                format!("names {what}[{i}] but the file has {len} {what}"),
            ))
        }
    }

    fn all(&self) -> Result<()> {
        self.views()?;
        self.accessors()?;
        self.images_textures_materials()?;
        self.meshes()?;
        self.nodes()?;
        self.skins()?;
        self.animations()?;
        Ok(())
    }

    /// Buffer views (glTF 2.0 §3.6.2): the buffer exists and the bytes lie inside it; a
    /// `byteStride` is a multiple of 4 in 4..=252 (§3.6.2.4, §5.11.4).
    fn views(&self) -> Result<()> {
        let buffers = &self.root.buffers;
        for (i, v) in self.root.buffer_views.iter().enumerate() {
            let at = format!("bufferViews[{i}]");
            self.index(
                &format!("{at}.buffer"),
                v.buffer.value(),
                buffers.len(),
                "buffers",
            )?;
            let len = buffers[v.buffer.value()].byte_length.0;
            let off = v.byte_offset.map_or(0, |o| o.0);
            if off.checked_add(v.byte_length.0).is_none_or(|end| end > len) {
                return Err(self.bad(
                    format!("{at}.byteLength"),
                    format!(
                        "bytes {off} + {} lie outside buffers[{}] ({len} bytes)",
                        v.byte_length.0,
                        v.buffer.value()
                    ),
                ));
            }
            if let Some(s) = v.byte_stride
                && !((4..=252).contains(&s.0) && s.0 % 4 == 0)
            {
                return Err(self.bad(
                    format!("{at}.byteStride"),
                    format!("{} must be a multiple of 4 in 4..=252", s.0),
                ));
            }
        }
        Ok(())
    }

    /// Accessors (glTF 2.0 §3.6.2, §3.6.2.3): valid types, elements no longer than their
    /// view's `byteStride` and inside the view, sparse storage inside views without a
    /// `byteStride` (§5.3, §5.4: it is tightly packed), and no more zero elements than can be
    /// allocated.
    fn accessors(&self) -> Result<()> {
        let views = &self.root.buffer_views;
        for (i, a) in self.root.accessors.iter().enumerate() {
            let at = format!("accessors[{i}]");
            let Checked::Valid(ct) = a.component_type else {
                return Err(self.bad(
                    format!("{at}.componentType"),
                    "is not a valid component type",
                ));
            };
            let ct = ct.0;
            let Checked::Valid(ty) = a.type_ else {
                return Err(self.bad(format!("{at}.type"), "is not a valid accessor type"));
            };
            let elem = ct.size() as u64 * component_count(ty);
            let count = a.count.0;
            if let Some(view) = a.buffer_view {
                self.index(
                    &format!("{at}.bufferView"),
                    view.value(),
                    views.len(),
                    "bufferViews",
                )?;
                let v = &views[view.value()];
                if let Some(s) = v.byte_stride
                    && (s.0 as u64) < elem
                {
                    return Err(self.bad(
                        format!("bufferViews[{}].byteStride", view.value()),
                        format!(
                            "{} bytes is less than the {elem}-byte elements ({} {}) of {at}, which uses the view",
                            s.0,
                            component_name(ct),
                            type_name(ty)
                        ),
                    ));
                }
                let stride = v.byte_stride.map_or(elem, |s| s.0 as u64);
                let off = a.byte_offset.map_or(0, |o| o.0);
                let need = if count == 0 {
                    Some(0)
                } else {
                    (count - 1)
                        .checked_mul(stride)
                        .and_then(|n| n.checked_add(elem))
                        .and_then(|n| n.checked_add(off))
                };
                if need.is_none_or(|n| n > v.byte_length.0) {
                    return Err(self.bad(
                        format!("{at}.count"),
                        format!(
                            "{count} elements of {elem} bytes from byte {off} do not fit bufferViews[{}] ({} bytes)",
                            view.value(),
                            v.byte_length.0
                        ),
                    ));
                }
            } else if count
                .checked_mul(elem)
                .is_none_or(|n| n > MAX_ZERO_ACCESSOR_BYTES)
            {
                return Err(self.bad(
                    format!("{at}.count"),
                    format!(
                        "{count} elements without a buffer view exceed the limit of {} MiB",
                        MAX_ZERO_ACCESSOR_BYTES >> 20
                    ),
                ));
            }
            if let Some(s) = &a.sparse {
                let sat = format!("{at}.sparse");
                let n = s.count.0;
                if n == 0 || n > count {
                    return Err(self.bad(
                        format!("{sat}.count"),
                        format!("{n} must be in 1..={count} (the accessor's count)"),
                    ));
                }
                let Checked::Valid(ict) = s.indices.component_type else {
                    return Err(self.bad(
                        format!("{sat}.indices.componentType"),
                        "is not a valid index component type",
                    ));
                };
                for (key, view, off, size) in [
                    (
                        "indices",
                        s.indices.buffer_view,
                        s.indices.byte_offset.0,
                        ict.0.size() as u64,
                    ),
                    ("values", s.values.buffer_view, s.values.byte_offset.0, elem),
                ] {
                    let kat = format!("{sat}.{key}");
                    self.index(
                        &format!("{kat}.bufferView"),
                        view.value(),
                        views.len(),
                        "bufferViews",
                    )?;
                    if views[view.value()].byte_stride.is_some() {
                        return Err(self.bad(
                            format!("bufferViews[{}].byteStride", view.value()),
                            format!(
                                "must not be defined: {kat} uses the view, and sparse {key} are tightly packed"
                            ),
                        ));
                    }
                    let len = views[view.value()].byte_length.0;
                    if n.checked_mul(size)
                        .and_then(|b| b.checked_add(off))
                        .is_none_or(|b| b > len)
                    {
                        return Err(self.bad(
                            format!("{sat}.count"),
                            format!(
                                "{n} sparse {key} of {size} bytes from byte {off} do not fit bufferViews[{}] ({len} bytes)",
                                view.value()
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// The accessor `index` named at `at` exists and has a type `want` allows; returns its
    /// element count.
    fn accessor(&self, at: &str, index: usize, want: &Want<'_>) -> Result<u64> {
        self.index(at, index, self.root.accessors.len(), "accessors")?;
        let a = &self.root.accessors[index];
        let (Checked::Valid(ct), Checked::Valid(ty)) = (a.component_type, a.type_) else {
            return Err(self.bad(at, format!("accessors[{index}] has no valid type")));
        };
        let ct = ct.0;
        let type_ok = want.types.contains(&ty);
        let comp_ok = if ct == ComponentType::F32 {
            want.floats
        } else {
            want.ints.contains(&ct) && (want.raw_ints || a.normalized)
        };
        if !(type_ok && comp_ok) {
            let types: Vec<&str> = want.types.iter().map(|&t| type_name(t)).collect();
            let mut comps: Vec<String> = Vec::new();
            if want.floats {
                comps.push("FLOAT".into());
            }
            for &c in want.ints {
                let c = component_name(c).split(' ').next().unwrap_or("");
                comps.push(if want.raw_ints {
                    c.to_owned()
                } else {
                    format!("normalized {c}")
                });
            }
            return Err(self.bad(
                at,
                format!(
                    "accessors[{index}] is {}{} {}; allowed: {} of {}",
                    if a.normalized { "normalized " } else { "" },
                    component_name(ct),
                    type_name(ty),
                    types.join(" or "),
                    comps.join(", ")
                ),
            ));
        }
        Ok(a.count.0)
    }

    /// Images, textures and materials (glTF 2.0 §3.8, §3.9): every index in range.
    fn images_textures_materials(&self) -> Result<()> {
        let r = self.root;
        for (i, im) in r.images.iter().enumerate() {
            if let Some(v) = im.buffer_view {
                self.index(
                    &format!("images[{i}].bufferView"),
                    v.value(),
                    r.buffer_views.len(),
                    "bufferViews",
                )?;
                if im.mime_type.is_none() {
                    return Err(self.bad(
                        format!("images[{i}].mimeType"),
                        "is missing: an image in a bufferView must give it (glTF 2.0 §5.17)",
                    ));
                }
            } else if im.uri.is_none() {
                return Err(self.bad(format!("images[{i}]"), "has neither a uri nor a bufferView"));
            }
        }
        for (i, t) in r.textures.iter().enumerate() {
            self.index(
                &format!("textures[{i}].source"),
                t.source.value(),
                r.images.len(),
                "images",
            )?;
            if let Some(s) = t.sampler {
                self.index(
                    &format!("textures[{i}].sampler"),
                    s.value(),
                    r.samplers.len(),
                    "samplers",
                )?;
            }
        }
        for (i, m) in r.materials.iter().enumerate() {
            let pbr = &m.pbr_metallic_roughness;
            for (key, tex) in [
                (
                    "pbrMetallicRoughness.baseColorTexture",
                    pbr.base_color_texture.as_ref().map(|t| t.index.value()),
                ),
                (
                    "pbrMetallicRoughness.metallicRoughnessTexture",
                    pbr.metallic_roughness_texture
                        .as_ref()
                        .map(|t| t.index.value()),
                ),
                (
                    "normalTexture",
                    m.normal_texture.as_ref().map(|t| t.index.value()),
                ),
                (
                    "occlusionTexture",
                    m.occlusion_texture.as_ref().map(|t| t.index.value()),
                ),
                (
                    "emissiveTexture",
                    m.emissive_texture.as_ref().map(|t| t.index.value()),
                ),
            ] {
                if let Some(t) = tex {
                    self.index(
                        &format!("materials[{i}].{key}.index"),
                        t,
                        r.textures.len(),
                        "textures",
                    )?;
                }
            }
        }
        Ok(())
    }

    /// Meshes (glTF 2.0 §3.7.2): attribute, index and morph target accessors exist, have the
    /// types their semantic allows and one element per vertex; materials exist.
    fn meshes(&self) -> Result<()> {
        use ComponentType::*;
        let uv = Want {
            types: &[Type::Vec2],
            floats: true,
            ints: &[U8, U16],
            raw_ints: false,
        };
        let color = Want {
            types: &[Type::Vec3, Type::Vec4],
            floats: true,
            ints: &[U8, U16],
            raw_ints: false,
        };
        let joints = Want {
            types: &[Type::Vec4],
            floats: false,
            ints: &[U8, U16],
            raw_ints: true,
        };
        let weights = Want {
            types: &[Type::Vec4],
            floats: true,
            ints: &[U8, U16],
            raw_ints: false,
        };
        let tangent = Want {
            types: &[Type::Vec4],
            floats: true,
            ints: &[],
            raw_ints: false,
        };
        let indices = Want {
            types: &[Type::Scalar],
            floats: false,
            ints: &[U8, U16, U32],
            raw_ints: true,
        };
        for (m, mesh) in self.root.meshes.iter().enumerate() {
            for (p, prim) in mesh.primitives.iter().enumerate() {
                let at = format!("meshes[{m}].primitives[{p}]");
                if let Checked::Invalid = prim.mode {
                    return Err(self.bad(format!("{at}.mode"), "is not a valid primitive mode"));
                }
                if let Some(mat) = prim.material {
                    self.index(
                        &format!("{at}.material"),
                        mat.value(),
                        self.root.materials.len(),
                        "materials",
                    )?;
                }
                let position = prim
                    .attributes
                    .iter()
                    .find(|(s, _)| matches!(s, Checked::Valid(Semantic::Positions)));
                let vertices = match position {
                    Some((_, a)) => Some(self.accessor(
                        &format!("{at}.attributes.POSITION"),
                        a.value(),
                        &F32_VEC3,
                    )?),
                    None => None,
                };
                for (semantic, a) in &prim.attributes {
                    let Checked::Valid(semantic) = semantic else {
                        continue;
                    };
                    let key = semantic.to_string();
                    let aat = format!("{at}.attributes.{key}");
                    let want = match semantic {
                        Semantic::Positions | Semantic::Normals => &F32_VEC3,
                        Semantic::Tangents => &tangent,
                        Semantic::Colors(_) => &color,
                        Semantic::TexCoords(_) => &uv,
                        Semantic::Joints(_) => &joints,
                        Semantic::Weights(_) => &weights,
                        #[allow(unreachable_patterns)]
                        _ => {
                            self.index(&aat, a.value(), self.root.accessors.len(), "accessors")?;
                            continue;
                        }
                    };
                    let count = self.accessor(&aat, a.value(), want)?;
                    if let Some(v) = vertices
                        && count != v
                    {
                        return Err(
                            self.bad(aat, format!("has {count} elements but POSITION has {v}"))
                        );
                    }
                }
                if let Some(i) = prim.indices {
                    self.accessor(&format!("{at}.indices"), i.value(), &indices)?;
                }
                let targets = prim.targets.as_ref().map_or(0, Vec::len);
                let first = mesh.primitives[0].targets.as_ref().map_or(0, Vec::len);
                if targets != first {
                    return Err(self.bad(
                        format!("{at}.targets"),
                        format!(
                            "has {targets} morph targets where primitives[0] has {first}; every \
                             primitive of a mesh must have the same (glTF 2.0 §3.7.2.2)"
                        ),
                    ));
                }
                for (t, target) in prim.targets.iter().flatten().enumerate() {
                    for (key, a) in [
                        ("POSITION", target.positions),
                        ("NORMAL", target.normals),
                        ("TANGENT", target.tangents),
                    ] {
                        let Some(a) = a else { continue };
                        let tat = format!("{at}.targets[{t}].{key}");
                        let count = self.accessor(&tat, a.value(), &F32_VEC3)?;
                        if let Some(v) = vertices
                            && count != v
                        {
                            return Err(
                                self.bad(tat, format!("has {count} elements but POSITION has {v}"))
                            );
                        }
                    }
                }
            }
            let targets = self.targets(m);
            if let Some(w) = &mesh.weights
                && w.len() != targets
            {
                return Err(self.bad(
                    format!("meshes[{m}].weights"),
                    format!("has {} weights for {targets} morph targets", w.len()),
                ));
            }
        }
        Ok(())
    }

    /// The number of morph targets of mesh `m` (its first primitive's; [`V::meshes`] checks
    /// that every primitive has as many).
    fn targets(&self, m: usize) -> usize {
        self.root.meshes[m]
            .primitives
            .first()
            .and_then(|p| p.targets.as_ref())
            .map_or(0, Vec::len)
    }

    /// A node's `rotation` and `matrix` (glTF 2.0 §5.25): a rotation that is not zero, and a
    /// matrix that is finite, affine, and a rotation and a scale (each axis's squared length
    /// finite in f32, none zero, the axes at right angles), which is how it is read.
    fn transform(&self, at: &str, node: &json::Node) -> Result<()> {
        if node.matrix.is_some()
            && (node.translation.is_some() || node.rotation.is_some() || node.scale.is_some())
        {
            return Err(self.bad(
                format!("{at}.matrix"),
                "is given beside translation, rotation or scale; glTF allows one or the other",
            ));
        }
        if let Some(q) = &node.rotation {
            let q = q.0;
            let length = q.iter().map(|&c| f64::from(c).powi(2)).sum::<f64>().sqrt();
            // glTF's is a unit quaternion; one far from it (zero, or small or large enough to
            // underflow or overflow when normalised in f32) is not a rotation.
            if !(1e-3..=1e3).contains(&length) {
                return Err(self.bad(
                    format!("{at}.rotation"),
                    format!("{q:?} is not a rotation (a unit quaternion)"),
                ));
            }
        }
        let Some(m) = &node.matrix else {
            return Ok(());
        };
        let why = if !m.iter().all(|c| c.is_finite()) {
            Some("is not finite")
        } else if [m[3], m[7], m[11], m[15] - 1.0]
            .iter()
            .any(|c| c.abs() > 1e-5)
        {
            Some("is not affine (its last row must be 0, 0, 0, 1)")
        } else {
            let axes: Vec<[f64; 3]> = (0..3)
                .map(|c| std::array::from_fn(|r| f64::from(m[4 * c + r])))
                .collect();
            let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
            let len2: Vec<f64> = axes.iter().map(|a| dot(a, a)).collect();
            if len2.iter().all(|&l| l == 0.0) {
                // Scaled to nothing, a common way to hide a node: nothing of it is rendered.
                None
            } else if len2.contains(&0.0) {
                Some(
                    "scales an axis to zero: give such a transform as translation, rotation and scale",
                )
            } else if len2.iter().any(|&l| l > f64::from(f32::MAX)) {
                Some("scales an axis beyond what f32 can square")
            } else if (0..3).any(|i| {
                let j = (i + 1) % 3;
                dot(&axes[i], &axes[j]).abs() > 1e-3 * (len2[i] * len2[j]).sqrt()
            }) {
                Some("shears: it is not a rotation and a scale, which glTF requires of a matrix")
            } else {
                None
            }
        };
        match why {
            Some(why) => Err(self.bad(format!("{at}.matrix"), why)),
            None => Ok(()),
        }
    }

    /// Nodes and scenes (glTF 2.0 §3.5): every index in range, and the node hierarchy a
    /// forest: no node is its own ancestor and none has two parents.
    fn nodes(&self) -> Result<()> {
        let r = self.root;
        let n = r.nodes.len();
        let lights = r
            .extensions
            .as_ref()
            .and_then(|e| e.khr_lights_punctual.as_ref())
            .map_or(0, |l| l.lights.len());
        let mut parent: Vec<Option<usize>> = vec![None; n];
        for (i, node) in r.nodes.iter().enumerate() {
            let at = format!("nodes[{i}]");
            self.transform(&at, node)?;
            if let Some(m) = node.mesh {
                self.index(&format!("{at}.mesh"), m.value(), r.meshes.len(), "meshes")?;
                let targets = self.targets(m.value());
                if let Some(w) = &node.weights
                    && w.len() != targets
                {
                    return Err(self.bad(
                        format!("{at}.weights"),
                        format!("has {} weights for {targets} morph targets", w.len()),
                    ));
                }
            }
            if let Some(c) = node.camera {
                self.index(
                    &format!("{at}.camera"),
                    c.value(),
                    r.cameras.len(),
                    "cameras",
                )?;
            }
            if let Some(s) = node.skin {
                self.index(&format!("{at}.skin"), s.value(), r.skins.len(), "skins")?;
                if let Some(m) = node.mesh {
                    for (p, prim) in r.meshes[m.value()].primitives.iter().enumerate() {
                        for (semantic, key) in [
                            (Semantic::Joints(0), "JOINTS_0"),
                            (Semantic::Weights(0), "WEIGHTS_0"),
                        ] {
                            if !prim
                                .attributes
                                .keys()
                                .any(|k| *k == Checked::Valid(semantic.clone()))
                            {
                                return Err(self.bad(
                                    format!("meshes[{}].primitives[{p}].attributes", m.value()),
                                    format!(
                                        "has no {key}, which the skin of {at}, its node, needs"
                                    ),
                                ));
                            }
                        }
                    }
                }
            }
            if let Some(l) = node
                .extensions
                .as_ref()
                .and_then(|e| e.khr_lights_punctual.as_ref())
            {
                self.index(
                    &format!("{at}.extensions.KHR_lights_punctual.light"),
                    l.light.value(),
                    lights,
                    "KHR_lights_punctual.lights",
                )?;
            }
            for (k, c) in node.children.iter().flatten().enumerate() {
                let c = c.value();
                self.index(&format!("{at}.children[{k}]"), c, n, "nodes")?;
                if c == i {
                    return Err(self.bad(
                        format!("{at}.children[{k}]"),
                        format!("nodes[{i}] is its own child"),
                    ));
                }
                if let Some(p) = parent[c] {
                    return Err(self.bad(
                        format!("{at}.children[{k}]"),
                        format!("nodes[{c}] has two parents, nodes[{p}] and nodes[{i}]; the node hierarchy must be a tree"),
                    ));
                }
                parent[c] = Some(i);
            }
        }
        // With one parent each, a cycle is a chain of parents that comes back to a node on
        // it. Each node's chain is walked once, up to a node already known to lead to a root.
        let mut done = vec![false; n];
        let mut on_chain = vec![false; n];
        for start in 0..n {
            let mut chain = Vec::new();
            let mut at = Some(start);
            while let Some(a) = at.filter(|&a| !done[a]) {
                if on_chain[a] {
                    // The cycle: `a` and its ancestors up to `a` again, from the lowest index.
                    let from = chain.iter().position(|&c| c == a).unwrap_or(0);
                    let mut cycle = chain[from..].to_vec();
                    let low = (0..cycle.len()).min_by_key(|&k| cycle[k]).unwrap_or(0);
                    cycle.rotate_left(low);
                    let names: Vec<String> = cycle.iter().map(|c| format!("nodes[{c}]")).collect();
                    return Err(self.bad(
                        format!("nodes[{}]", cycle[0]),
                        format!(
                            "is its own ancestor (parents {} → nodes[{}])",
                            names.join(" → "),
                            cycle[0]
                        ),
                    ));
                }
                on_chain[a] = true;
                chain.push(a);
                at = parent[a];
            }
            for c in chain {
                done[c] = true;
            }
        }
        for (s, scene) in r.scenes.iter().enumerate() {
            for (k, node) in scene.nodes.iter().enumerate() {
                self.index(&format!("scenes[{s}].nodes[{k}]"), node.value(), n, "nodes")?;
            }
        }
        if let Some(s) = r.scene {
            self.index("scene", s.value(), r.scenes.len(), "scenes")?;
        }
        Ok(())
    }

    /// Skins (glTF 2.0 §3.7.3): at least one joint (the schema's `minItems`), joints and
    /// skeleton exist; inverse bind matrices are float MAT4, one per joint.
    fn skins(&self) -> Result<()> {
        let n = self.root.nodes.len();
        let mat4 = Want {
            types: &[Type::Mat4],
            floats: true,
            ints: &[],
            raw_ints: false,
        };
        for (i, s) in self.root.skins.iter().enumerate() {
            let at = format!("skins[{i}]");
            if s.joints.is_empty() {
                return Err(self.bad(format!("{at}.joints"), "must name at least one node"));
            }
            for (k, j) in s.joints.iter().enumerate() {
                self.index(&format!("{at}.joints[{k}]"), j.value(), n, "nodes")?;
            }
            if let Some(k) = s.skeleton {
                self.index(&format!("{at}.skeleton"), k.value(), n, "nodes")?;
            }
            if let Some(m) = s.inverse_bind_matrices {
                let mat = format!("{at}.inverseBindMatrices");
                let count = self.accessor(&mat, m.value(), &mat4)?;
                if count < s.joints.len() as u64 {
                    return Err(self.bad(
                        mat,
                        format!("has {count} matrices for {} joints", s.joints.len()),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Animations (glTF 2.0 §3.11): samplers and targets exist, inputs are float scalars,
    /// outputs have the type their target path allows and one value per key (three for cubic
    /// splines; times the number of morph targets for weights).
    fn animations(&self) -> Result<()> {
        use ComponentType::*;
        let r = self.root;
        let input = Want {
            types: &[Type::Scalar],
            floats: true,
            ints: &[],
            raw_ints: false,
        };
        let rotation = Want {
            types: &[Type::Vec4],
            floats: true,
            ints: &[I8, U8, I16, U16],
            raw_ints: false,
        };
        let weights = Want {
            types: &[Type::Scalar],
            floats: true,
            ints: &[I8, U8, I16, U16],
            raw_ints: false,
        };
        for (a, anim) in r.animations.iter().enumerate() {
            let aat = format!("animations[{a}]");
            for (s, sampler) in anim.samplers.iter().enumerate() {
                let sat = format!("{aat}.samplers[{s}]");
                if let Checked::Invalid = sampler.interpolation {
                    return Err(self.bad(
                        format!("{sat}.interpolation"),
                        "is not a valid interpolation",
                    ));
                }
                self.accessor(&format!("{sat}.input"), sampler.input.value(), &input)?;
                self.index(
                    &format!("{sat}.output"),
                    sampler.output.value(),
                    r.accessors.len(),
                    "accessors",
                )?;
            }
            for (c, ch) in anim.channels.iter().enumerate() {
                let cat = format!("{aat}.channels[{c}]");
                self.index(
                    &format!("{cat}.sampler"),
                    ch.sampler.value(),
                    anim.samplers.len(),
                    "samplers",
                )?;
                let node = ch.target.node.value();
                self.index(&format!("{cat}.target.node"), node, r.nodes.len(), "nodes")?;
                if r.nodes[node].matrix.is_some()
                    && ch.target.path != Checked::Valid(Property::MorphTargetWeights)
                {
                    return Err(self.bad(
                        format!("{cat}.target.node"),
                        format!(
                            "nodes[{node}] has a matrix; an animated node must give \
                             translation, rotation and scale instead (glTF 2.0 §3.11)"
                        ),
                    ));
                }
                let Checked::Valid(path) = ch.target.path else {
                    return Err(self.bad(
                        format!("{cat}.target.path"),
                        "is not a valid animation path",
                    ));
                };
                let sampler = &anim.samplers[ch.sampler.value()];
                let want = match path {
                    Property::Translation | Property::Scale => &F32_VEC3,
                    Property::Rotation => &rotation,
                    Property::MorphTargetWeights => &weights,
                };
                let oat = format!("{aat}.samplers[{}].output", ch.sampler.value());
                let outputs = self.accessor(&oat, sampler.output.value(), want)?;
                let keys = r.accessors[sampler.input.value()].count.0;
                let per_key = if sampler.interpolation == Checked::Valid(Interpolation::CubicSpline)
                {
                    3
                } else {
                    1
                };
                // Weights have one value per morph target and key; the reader checks those.
                if path != Property::MorphTargetWeights
                    && keys.checked_mul(per_key) != Some(outputs)
                {
                    return Err(self.bad(
                        oat,
                        format!(
                            "has {outputs} values for {keys} keys (expected {}) as {cat} uses it",
                            keys.saturating_mul(per_key)
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}
