//! glTF 2.0 import: `.gltf` with external or embedded buffers and images, and `.glb`.
//!
//! The `gltf` crate parses and validates; this module checks what the crate leaves to the
//! caller (extensions, files that exist, accessor bounds, sparse indices, finite positions,
//! weights and inverse bind matrices, index and joint ranges, light values) so that bad input
//! is an [`Error::Input`] naming the file and the element at fault, never a panic, and
//! converts the document into the renderer's own [`Layer`] description.

use std::path::{Path, PathBuf};

use glam::{Mat4, Quat, Vec2, Vec3, Vec4};
use gltf::animation::util::ReadOutputs;
use gltf::khr_lights_punctual::Kind;
use gltf::mesh::Mode;
use gltf::mesh::util::{
    ReadNormalDisplacements, ReadPositionDisplacements, ReadTangentDisplacements,
};

use super::anim::{Animation, Channel, Interpolation, Property, Sampler};
use super::material::{Material, NormalMap, Texture, TextureRef, UvTransform, Wrap};
use super::{
    Camera, Clip, Layer, Light, LightKind, Mesh, MorphTarget, Motion, Node, Primitive, Projection,
    Skin,
};
use crate::color::srgb_to_linear;
use crate::error::{Error, Result};

/// Extensions whose meaning the renderer implements.
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "KHR_lights_punctual",
    "KHR_materials_emissive_strength",
    "KHR_texture_transform",
    "KHR_materials_specular",
];

/// What a rough metal's warning says: its reflection is shaded by an approximation whose
/// error `README.md` measures (§ "What is modelled").
const ROUGH_METAL: &str = "the cached methods (anchors, brute-force, precomputed) treat \
     the light such a surface reflects onto others as diffuse (its hemispherical albedo times \
     its irradiance) and light its glossy lobe from a fit of the cache's incident light \
     (Sponza in white metal of roughness 1 reads its indirect light about 9 % low against \
     the path tracer at the production preset's photon count, 1 % with 64 times the photons; \
     with method.gather_direct \"photons\", 25 %)";

/// The `alphaCutoff` a `BLEND` material is cut out at: BLEND is rendered as a cut-out
/// (deterministic, noise-free), with a warning per material.
pub const BLEND_CUTOFF: f32 = 0.5;

/// The extras key that carries a prim's motion tag (schemas/motion-tag.schema.json).
pub const MOTION_KEY: &str = "motion";

/// Where a layer's global material and texture indices start.
pub struct Offsets {
    pub materials: usize,
    pub textures: usize,
}

/// What [`load`] returns besides the layer: materials and textures for the global lists.
pub struct Loaded {
    pub layer: Layer,
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
}

/// How errors and warnings name element `index` of the document's `kind` array.
fn name_of(kind: &str, index: usize, name: Option<&str>) -> String {
    match name {
        Some(n) if !n.is_empty() => format!("{kind}[{index}] \"{n}\""),
        _ => format!("{kind}[{index}]"),
    }
}

/// Loads one glTF file. `offsets` are where this layer's materials and textures will sit in
/// the scene's global lists.
pub fn load(path: &Path, offsets: Offsets) -> Result<Loaded> {
    let (gltf, optional) = open(path)?;
    let base = path.parent().unwrap_or(Path::new("."));
    let doc = &gltf.document;
    let files = check_files(path, doc, base)?;
    let buffers = gltf::import_buffers(doc, Some(base), gltf.blob.clone())
        .map_err(|e| Error::input(path, "buffers", format!("cannot load buffer data: {e}")))?;
    check_accessors(path, doc, &buffers)?;

    let mut r = Reader {
        path,
        doc,
        buffers: &buffers,
        base,
        offsets,
        warnings: Vec::new(),
        reported: Vec::new(),
    };
    let (materials, textures) = r.materials()?;
    // Extensions a material uses were named with that material; the others once here.
    let optional: Vec<&str> = optional
        .iter()
        .map(String::as_str)
        .filter(|e| !r.reported.iter().any(|x| x == e))
        .collect();
    if !optional.is_empty() {
        r.warnings.insert(
            0,
            format!(
                "{}: optional extensions ignored: {}",
                path.display(),
                optional.join(", ")
            ),
        );
    }
    let (meshes, degenerate_triangles) = r.meshes(&materials)?;
    let unset = r
        .doc
        .meshes()
        .flat_map(|m| m.primitives())
        .filter(|p| p.material().index().is_none())
        .count();
    if unset > 0 {
        r.warn(format_args!(
            "{unset} primitive(s) have no material: glTF's default applies, a white metal of \
             roughness 1; {ROUGH_METAL}"
        ));
    }
    let skins = r.skins()?;
    r.check_joints()?;
    let lights = r.lights()?;
    let cameras = r.cameras()?;
    let (nodes, roots) = r.nodes()?;
    let animations = r.animations()?;
    Ok(Loaded {
        layer: Layer {
            path: path.to_path_buf(),
            transform: glam::DMat4::IDENTITY,
            nodes,
            roots,
            meshes,
            skins,
            animations,
            lights,
            cameras,
            degenerate_triangles,
            files,
            warnings: r.warnings,
        },
        materials,
        textures,
    })
}

/// Reads and parses the file; the extensions are checked before the full parse, so that a
/// file needing an unsupported extension is reported as such rather than as invalid. Also
/// returns the unsupported optional extensions.
fn open(path: &Path) -> Result<(gltf::Gltf, Vec<String>)> {
    let glb = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("glb"));
    let limit = if glb { MAX_GLB_BYTES } else { MAX_GLTF_BYTES };
    let bytes = read_limited(path, "file", limit)?;
    let unchecked = gltf::Gltf::from_slice_without_validation(&bytes)
        .map_err(|e| Error::input(path, "file", format!("not a valid glTF or GLB file: {e}")))?;
    let optional = check_extensions(path, &unchecked)?;
    super::validate::check(path, unchecked.document.as_json())?;
    crate_validation(path, &unchecked)?;
    Ok((unchecked, optional))
}

/// The `gltf` crate's own validation (what `Gltf::from_slice` runs), except its refusal of
/// required extensions it has no typed support for: [`check_extensions`] decided those, and
/// the ones we support without the crate's feature (`KHR_materials_specular`, read from the
/// raw extension map) are fine.
fn crate_validation(path: &Path, gltf: &gltf::Gltf) -> Result<()> {
    use gltf::json::validation::{Error as Invalid, Validate};
    let root = gltf.document.as_json();
    let mut errors = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |at, e| {
        let at = at();
        let required_extension =
            matches!(e, Invalid::Unsupported) && at.as_str().starts_with("extensionsRequired[");
        if !required_extension {
            errors.push((at, e));
        }
    });
    if errors.is_empty() {
        Ok(())
    } else {
        Err(Error::input(
            path,
            "file",
            gltf::Error::Validation(errors).to_string(),
        ))
    }
}

/// Why `file`, which is not a regular file, cannot be read: it is missing, or it is
/// something else (a FIFO, a device, a directory).
fn missing(file: &Path) -> &'static str {
    if file.exists() {
        "is not a regular file"
    } else {
        "not found"
    }
}

/// The largest `.gltf` (JSON) file read: 256 MiB.
pub const MAX_GLTF_BYTES: u64 = 256 << 20;
/// The largest `.glb` file read: a GLB's length is a `u32` (glTF 2.0 §4.4.2).
pub const MAX_GLB_BYTES: u64 = u32::MAX as u64;
/// The largest external buffer or image file read (the size a GLB could hold).
pub const MAX_RESOURCE_BYTES: u64 = u32::MAX as u64;
/// The most texels a decoded image may have (16384²).
pub const MAX_IMAGE_TEXELS: u64 = 16384 * 16384;
/// The most bytes an image's decoded pixels may take: the `image` crate's default limit on
/// an allocation, which the `gltf` crate's decoder keeps (a 16384² image within it has one
/// or two 8-bit channels; RGBA8 reaches it at 16384 × 8192).
pub const MAX_IMAGE_BYTES: u64 = 512 * 1024 * 1024;

/// What an image's header declares ([`Reader::encoded_header`]).
struct ImageHeader {
    dimensions: (u32, u32),
    color: image::ColorType,
    /// The bytes of its decoded pixels.
    bytes: u64,
}

/// Opens `file` (element `at` of the input), which must be a regular file of at most `limit`
/// bytes: the file and its length, or an error naming it, before anything is read. A FIFO,
/// socket or device is refused from its metadata before it is opened (opening a FIFO for
/// reading waits for a writer), and the opened file is checked again.
pub fn open_limited(file: &Path, at: &str, limit: u64) -> Result<(std::fs::File, u64)> {
    let bad = |m: String| Error::input(file, at, m);
    let meta = std::fs::metadata(file).map_err(|e| bad(format!("cannot read: {e}")))?;
    if !meta.is_file() {
        return Err(bad("is not a regular file".into()));
    }
    let f = std::fs::File::open(file).map_err(|e| bad(format!("cannot read: {e}")))?;
    let meta = f.metadata().map_err(|e| bad(format!("cannot read: {e}")))?;
    if !meta.is_file() {
        return Err(bad("is not a regular file".into()));
    }
    if meta.len() > limit {
        return Err(bad(format!(
            "is {} bytes, more than the {limit} bytes allowed",
            meta.len()
        )));
    }
    Ok((f, meta.len()))
}

/// Reads `file` (element `at` of the input), which must be a regular file of at most
/// `limit` bytes: a device such as `/dev/zero` or an oversized file is refused before it is
/// read, and reading stops at the limit should the file grow meanwhile.
pub fn read_limited(file: &Path, at: &str, limit: u64) -> Result<Vec<u8>> {
    use std::io::Read;
    let bad = |m: String| Error::input(file, at, m);
    let (f, len) = open_limited(file, at, limit)?;
    let mut bytes = Vec::with_capacity(len as usize);
    f.take(limit + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| bad(format!("cannot read: {e}")))?;
    if bytes.len() as u64 > limit {
        return Err(bad(format!("is more than the {limit} bytes allowed")));
    }
    Ok(bytes)
}

/// Reads `extensionsRequired` and `extensionsUsed` (glTF 2.0 §3.12): a required extension
/// outside [`SUPPORTED_EXTENSIONS`] is an error; the optional ones are returned, to be
/// warned about (by the material that uses them, or once for the file).
fn check_extensions(path: &Path, unchecked: &gltf::Gltf) -> Result<Vec<String>> {
    let required: Vec<String> = unchecked
        .extensions_required()
        .filter(|e| !SUPPORTED_EXTENSIONS.contains(e))
        .map(str::to_owned)
        .collect();
    if !required.is_empty() {
        return Err(Error::input(
            path,
            "extensionsRequired",
            format!(
                "the file requires {} which anchorage does not support (supported: {})",
                required.join(", "),
                SUPPORTED_EXTENSIONS.join(", ")
            ),
        ));
    }
    Ok(unchecked
        .extensions_used()
        .filter(|e| !SUPPORTED_EXTENSIONS.contains(e))
        .map(str::to_owned)
        .collect())
}

/// Checks that the files named by external buffer and image URIs (glTF 2.0 §3.6.1, §3.8.3)
/// exist beside the glTF file, buffers first.
fn check_files(path: &Path, doc: &gltf::Document, base: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for b in doc.buffers() {
        if let gltf::buffer::Source::Uri(uri) = b.source()
            && !uri.starts_with("data:")
        {
            let at = name_of("buffers", b.index(), b.name());
            let file = uri_file(path, &at, base, uri)?;
            if let Ok(m) = std::fs::metadata(&file)
                && m.is_file()
                && m.len() > MAX_RESOURCE_BYTES
            {
                return Err(Error::input(
                    path,
                    name_of("buffers", b.index(), b.name()),
                    format!(
                        "buffer file {} is larger than {MAX_RESOURCE_BYTES} bytes",
                        file.display()
                    ),
                ));
            }
            if !file.is_file() {
                return Err(Error::input(
                    path,
                    name_of("buffers", b.index(), b.name()),
                    format!("buffer file {} {}", file.display(), missing(&file)),
                ));
            }
            files.push(file);
        }
    }
    for im in doc.images() {
        if let gltf::image::Source::Uri { uri, .. } = im.source()
            && !uri.starts_with("data:")
        {
            let at = name_of("images", im.index(), im.name());
            let file = uri_file(path, &at, base, uri)?;
            if !file.is_file() {
                return Err(Error::input(
                    path,
                    at,
                    format!("image file {} {}", base.join(uri).display(), missing(&file)),
                ));
            }
            if std::fs::metadata(&file).is_ok_and(|m| m.len() > MAX_RESOURCE_BYTES) {
                return Err(Error::input(
                    path,
                    at,
                    format!(
                        "image file {} is larger than {MAX_RESOURCE_BYTES} bytes",
                        file.display()
                    ),
                ));
            }
            files.push(file);
        }
    }
    Ok(files)
}

/// What gltf's reader yields for one morph target: position, normal and tangent displacements.
type MorphTargetReads<'s> = (
    Option<ReadPositionDisplacements<'s>>,
    Option<ReadNormalDisplacements<'s>>,
    Option<ReadTangentDisplacements<'s>>,
);

/// A parsed document whose files and accessors have been checked, read one section at a time.
/// Each section method returns the renderer's description of that section; `warnings`
/// collects what is ignored, in document order.
struct Reader<'a> {
    path: &'a Path,
    doc: &'a gltf::Document,
    buffers: &'a [gltf::buffer::Data],
    /// The folder that relative URIs start from.
    base: &'a Path,
    offsets: Offsets,
    warnings: Vec<String>,
    /// Extensions already named in a material's warning.
    reported: Vec<String>,
}

/// The textures decoded so far: each glTF image becomes one [`Texture`] per colour space it
/// is read in (sRGB for colour, linear for normal maps), decoded the first time a material
/// uses it so.
struct Textures {
    /// The images decoded so far, each the first time a material uses it.
    images: Vec<Option<gltf::image::Data>>,
    /// The global texture index of each image already converted, linear then sRGB.
    of_image: Vec<[Option<usize>; 2]>,
    list: Vec<Texture>,
}

/// Which texture slot of a material a [`TextureRef`] is read for (messages, colour space).
#[derive(Clone, Copy)]
enum Slot {
    BaseColor,
    MetallicRoughness,
    Emissive,
    Normal,
}

impl Slot {
    fn key(self) -> &'static str {
        match self {
            Slot::BaseColor => "pbrMetallicRoughness.baseColorTexture",
            Slot::MetallicRoughness => "pbrMetallicRoughness.metallicRoughnessTexture",
            Slot::Emissive => "emissiveTexture",
            Slot::Normal => "normalTexture",
        }
    }

    fn srgb(self) -> bool {
        !matches!(self, Slot::Normal | Slot::MetallicRoughness)
    }
}

impl<'a> Reader<'a> {
    /// An input error at element `at` of this file.
    fn bad(&self, at: &str, message: impl Into<String>) -> Error {
        Error::input(self.path, at, message)
    }

    /// Adds a warning about this file.
    fn warn(&mut self, what: std::fmt::Arguments<'_>) {
        self.warnings
            .push(format!("{}: {what}", self.path.display()));
    }

    /// The buffer data that gltf's accessor readers ask for.
    fn data(&self) -> impl Fn(gltf::Buffer<'_>) -> Option<&'a [u8]> + Clone + use<'a> {
        let buffers = self.buffers;
        move |b| Some(&buffers[b.index()].0[..])
    }

    /// Reads `materials` (glTF 2.0 §3.9) and the textures they use: base colour and emissive
    /// textures (sRGB → linear) and normal maps (linear).
    fn materials(&mut self) -> Result<(Vec<Material>, Vec<Texture>)> {
        let mut textures = Textures {
            images: (0..self.doc.images().len()).map(|_| None).collect(),
            of_image: vec![[None; 2]; self.doc.images().len()],
            list: Vec::new(),
        };
        let mut materials = Vec::new();
        for m in self.doc.materials() {
            materials.push(self.material(&m, &mut textures)?);
        }
        Ok((materials, textures.list))
    }

    /// Reads one material: base colour (factor, texture), alpha mode, normal map, emission
    /// (factor, texture, strength) and the metallic-roughness factors. What it uses and
    /// anchorage does not model is named in one warning each.
    fn material(&mut self, m: &gltf::Material<'_>, textures: &mut Textures) -> Result<Material> {
        let at = name_of("materials", m.index().unwrap_or(0), m.name());
        let pbr = m.pbr_metallic_roughness();
        let base_color_texture = pbr
            .base_color_texture()
            .map(|info| self.info_ref(&at, Slot::BaseColor, &info, textures))
            .transpose()?;
        let metallic_roughness_texture = pbr
            .metallic_roughness_texture()
            .map(|info| self.info_ref(&at, Slot::MetallicRoughness, &info, textures))
            .transpose()?;
        let emissive_texture = m
            .emissive_texture()
            .map(|info| self.info_ref(&at, Slot::Emissive, &info, textures))
            .transpose()?;
        let normal_texture = match m.normal_texture() {
            Some(n) => {
                if !n.scale().is_finite() {
                    return Err(self.bad(&format!("{at}.normalTexture.scale"), "must be finite"));
                }
                Some(NormalMap {
                    texture: self.texture_ref(
                        &at,
                        Slot::Normal,
                        &n.texture(),
                        n.tex_coord(),
                        n.extension_value("KHR_texture_transform")
                            .map(texture_transform)
                            .transpose(),
                        textures,
                    )?,
                    scale: n.scale(),
                })
            }
            None => None,
        };
        let alpha_cutoff = match m.alpha_mode() {
            gltf::material::AlphaMode::Opaque => None,
            gltf::material::AlphaMode::Mask => {
                let c = m.alpha_cutoff().unwrap_or(0.5);
                if !(c.is_finite() && c >= 0.0) {
                    return Err(self.bad(
                        &format!("{at}.alphaCutoff"),
                        "must be finite and non-negative",
                    ));
                }
                Some(c)
            }
            gltf::material::AlphaMode::Blend => {
                self.warn(format_args!(
                    "{at}: alphaMode BLEND is rendered as a cut-out at alpha {BLEND_CUTOFF} (no partial transparency)"
                ));
                Some(BLEND_CUTOFF)
            }
        };
        if m.occlusion_texture().is_some() {
            self.warn(format_args!(
                "{at}: occlusionTexture is ignored (global illumination computes occlusion)"
            ));
        }
        let mut specular = 1.0;
        if let Some(ext) = m.extensions() {
            for (name, value) in ext {
                if name == "KHR_materials_specular" {
                    specular = self.specular_factor(&at, value)?;
                    continue;
                }
                self.warn(format_args!(
                    "{at}: {name} is not modelled; the material renders without it"
                ));
                if !self.reported.contains(name) {
                    self.reported.push(name.clone());
                }
            }
        }
        let (roughness, metallic) = (pbr.roughness_factor(), pbr.metallic_factor());
        for (key, v) in [("roughnessFactor", roughness), ("metallicFactor", metallic)] {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return Err(self.bad(
                    &format!("{at}.pbrMetallicRoughness.{key}"),
                    format!("{v} is outside [0, 1]"),
                ));
            }
        }
        if metallic >= 0.5
            && roughness >= crate::bsdf::CACHE_LIT_ROUGHNESS
            && metallic_roughness_texture.is_none()
        {
            self.warn(format_args!(
                "{at}: a metal of roughness {roughness}; {ROUGH_METAL}"
            ));
        }
        let base = pbr.base_color_factor();
        if !base.iter().all(|c| (0.0..=1.0).contains(c)) {
            return Err(self.bad(
                &format!("{at}.pbrMetallicRoughness.baseColorFactor"),
                format!("{base:?} has a component outside [0, 1]"),
            ));
        }
        let emission = Vec3::from(m.emissive_factor()) * m.emissive_strength().unwrap_or(1.0);
        if !emission.is_finite() || emission.min_element() < 0.0 {
            return Err(self.bad(&at, "emission must be finite and non-negative"));
        }
        Ok(Material {
            name: m.name().unwrap_or("").to_owned(),
            base_color: Vec4::from(pbr.base_color_factor()),
            base_color_texture,
            alpha_cutoff,
            normal_texture,
            emission,
            emissive_texture,
            double_sided: m.double_sided(),
            roughness,
            metallic,
            metallic_roughness_texture,
            specular,
        })
    }

    /// `KHR_materials_specular`: the dielectric specular factor is modelled (0 turns the
    /// dielectric's glossy layer off, leaving a Lambertian); a specular colour or textures
    /// are not, and are named in a warning.
    fn specular_factor(&mut self, at: &str, value: &serde_json::Value) -> Result<f32> {
        let key = format!("{at}.extensions.KHR_materials_specular");
        let factor = match value.get("specularFactor") {
            None => 1.0,
            Some(v) => match v.as_f64() {
                Some(f) if (0.0..=1.0).contains(&f) => f as f32,
                _ => {
                    return Err(self.bad(
                        &format!("{key}.specularFactor"),
                        "must be a number in [0, 1]",
                    ));
                }
            },
        };
        let unmodelled: Vec<&str> = ["specularTexture", "specularColorTexture"]
            .into_iter()
            .filter(|k| value.get(*k).is_some())
            .chain(
                value
                    .get("specularColorFactor")
                    .and_then(|c| c.as_array())
                    .filter(|c| c.iter().any(|v| v.as_f64() != Some(1.0)))
                    .map(|_| "specularColorFactor"),
            )
            .collect();
        if !unmodelled.is_empty() {
            self.warn(format_args!(
                "{key}: {} not modelled; only specularFactor is",
                unmodelled.join(", ")
            ));
        }
        Ok(factor)
    }

    /// Reads a texture reference of material `at` (glTF 2.0 §3.8): its image, decoded once
    /// per colour space, its sampler's wrap modes and its `KHR_texture_transform`
    /// (`transform`: the extension read, if present, or what is wrong with it), whose
    /// `texCoord` overrides the reference's. Every texture reads `TEXCOORD_0`; another set
    /// is read as set 0 with a warning.
    /// [`Self::texture_ref`] for a plain `textureInfo` (base colour, emission).
    fn info_ref(
        &mut self,
        at: &str,
        slot: Slot,
        info: &gltf::texture::Info<'_>,
        textures: &mut Textures,
    ) -> Result<TextureRef> {
        let transform = Ok(info_transform(info));
        self.texture_ref(
            at,
            slot,
            &info.texture(),
            info.tex_coord(),
            transform,
            textures,
        )
    }

    fn texture_ref(
        &mut self,
        at: &str,
        slot: Slot,
        tex: &gltf::Texture<'_>,
        tex_coord: u32,
        transform: std::result::Result<Option<TransformRead>, String>,
        textures: &mut Textures,
    ) -> Result<TextureRef> {
        let key = format!("{at}.{}", slot.key());
        let (transform, override_coord) = transform
            .map_err(|m| self.bad(&format!("{key}.extensions.KHR_texture_transform"), m))?
            .unwrap_or((UvTransform::IDENTITY, None));
        if !transform.is_finite() {
            return Err(self.bad(
                &format!("{key}.extensions.KHR_texture_transform"),
                "offset, rotation and scale must be finite",
            ));
        }
        let set = override_coord.unwrap_or(tex_coord);
        if set != 0 {
            self.warn(format_args!(
                "{key} uses TEXCOORD_{set}, which anchorage does not read; TEXCOORD_0 is used instead"
            ));
        }
        let texture = self.texture_of_image(tex.source().index(), slot.srgb(), textures)?;
        let s = tex.sampler();
        Ok(TextureRef {
            texture,
            wrap: [wrap(s.wrap_s()), wrap(s.wrap_t())],
            transform,
        })
    }

    /// The global texture index of `image` (glTF 2.0 §3.8.3) in the colour space `srgb`
    /// says: the file's images are imported when a texture is first needed, and each is
    /// converted the first time it is used in that space.
    fn texture_of_image(&self, image: usize, srgb: bool, textures: &mut Textures) -> Result<usize> {
        if let Some(i) = textures.of_image[image][srgb as usize] {
            return Ok(i);
        }
        let at = name_of("images", image, None);
        let Some(im) = self.doc.images().nth(image) else {
            return Err(self.bad(&at, "does not exist"));
        };
        let at = name_of("images", image, im.name());
        if textures.images[image].is_none() {
            if let Some(header) = self.encoded_header(&im)? {
                let (w, h) = header.dimensions;
                if w as u64 * h as u64 > MAX_IMAGE_TEXELS {
                    return Err(self.bad(
                        &at,
                        format!("{w}×{h} texels exceed the limit of {MAX_IMAGE_TEXELS} (16384²)"),
                    ));
                }
                if header.bytes > MAX_IMAGE_BYTES {
                    return Err(self.bad(
                        &at,
                        format!(
                            "{w}×{h} texels of {:?} take {} MiB decoded, beyond the decoder's \
                             limit of {} MiB: save it smaller, or with fewer channels or bits",
                            header.color,
                            header.bytes.div_ceil(1 << 20),
                            MAX_IMAGE_BYTES >> 20
                        ),
                    ));
                }
            }
            let data = gltf::image::Data::from_source(im.source(), Some(self.base), self.buffers)
                .map_err(|e| self.bad(&at, format!("cannot decode image: {e}")))?;
            let texels = data.width as u64 * data.height as u64;
            if texels > MAX_IMAGE_TEXELS {
                return Err(self.bad(
                    &at,
                    format!(
                        "{}×{} texels exceed the limit of {MAX_IMAGE_TEXELS} (16384²)",
                        data.width, data.height
                    ),
                ));
            }
            textures.images[image] = Some(data);
        }
        let Some(data) = textures.images[image].as_ref() else {
            return Err(self.bad(&at, "could not be decoded"));
        };
        let t = decode_texture(data, srgb)
            .ok_or_else(|| self.bad(&at, format!("unsupported pixel format {:?}", data.format)))?;
        textures.list.push(t);
        let i = self.offsets.textures + textures.list.len() - 1;
        textures.of_image[image][srgb as usize] = Some(i);
        Ok(i)
    }

    /// What an image's header declares, read before it is decoded so that an oversized
    /// image is refused without allocating its texels; `None` where the header cannot be
    /// read (decoding then reports the error).
    fn encoded_header(&self, im: &gltf::Image<'_>) -> Result<Option<ImageHeader>> {
        let at = name_of("images", im.index(), im.name());
        let owned;
        let bytes: &[u8] = match im.source() {
            gltf::image::Source::View { view, .. } => {
                let data = &self.buffers[view.buffer().index()].0;
                match view
                    .offset()
                    .checked_add(view.length())
                    .and_then(|end| data.get(view.offset()..end))
                {
                    Some(b) => b,
                    None => return Ok(None),
                }
            }
            gltf::image::Source::Uri { uri, .. } => {
                if let Some(rest) = uri.strip_prefix("data:") {
                    let Some((_, b64)) = rest.split_once(";base64,") else {
                        return Ok(None);
                    };
                    let Some(b) = base64_decode(b64) else {
                        return Ok(None);
                    };
                    owned = b;
                } else {
                    let Some(uri) = urlencoding_decode(uri) else {
                        return Ok(None);
                    };
                    let file = self.base.join(uri);
                    owned = read_limited(&file, &at, MAX_RESOURCE_BYTES)?;
                }
                &owned
            }
        };
        use image::ImageDecoder;
        Ok(image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .ok()
            .and_then(|r| r.into_decoder().ok())
            .map(|d| ImageHeader {
                dimensions: d.dimensions(),
                color: d.color_type(),
                bytes: d.total_bytes(),
            }))
    }

    /// Reads `meshes` (glTF 2.0 §3.7.2) whose primitives use this file's `materials`; also
    /// returns how many degenerate triangles were dropped, and warns once if any were.
    fn meshes(&mut self, materials: &[Material]) -> Result<(Vec<Mesh>, usize)> {
        let mut meshes = Vec::new();
        let mut degenerate = 0usize;
        for mesh in self.doc.meshes() {
            let mesh_at = name_of("meshes", mesh.index(), mesh.name());
            let mut primitives = Vec::new();
            for p in mesh.primitives() {
                let at = format!("{mesh_at}.primitives[{}]", p.index());
                if let Some((primitive, dropped)) = self.primitive(&at, &p, materials)? {
                    degenerate += dropped;
                    primitives.push(primitive);
                }
            }
            meshes.push(Mesh {
                name: mesh.name().unwrap_or("").to_owned(),
                weights: mesh.weights().map(<[f32]>::to_vec).unwrap_or_default(),
                primitives,
            });
        }
        if degenerate > 0 {
            self.warn(format_args!(
                "{degenerate} degenerate (zero-area) triangles skipped"
            ));
        }
        Ok((meshes, degenerate))
    }

    /// Reads one primitive (glTF 2.0 §3.7.2.1) with the number of degenerate triangles
    /// dropped from it; points and lines are skipped with a warning (`None`). `COLOR_0` is
    /// read as linear RGBA (normalized integers scaled to [0, 1]); `TANGENT` only where the
    /// material has a normal map.
    fn primitive(
        &mut self,
        at: &str,
        p: &gltf::Primitive<'_>,
        materials: &[Material],
    ) -> Result<Option<(Primitive, usize)>> {
        let mode = p.mode();
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            self.warn(format_args!("{at}: {mode:?} primitives are not rendered"));
            return Ok(None);
        }
        let r = p.reader(self.data());
        let positions = self.positions(at, r.read_positions())?;
        let normals: Option<Vec<Vec3>> = r.read_normals().map(|n| n.map(Vec3::from).collect());
        let uvs: Option<Vec<Vec2>> = r
            .read_tex_coords(0)
            .map(|t| t.into_f32().map(Vec2::from).collect());
        let raw: Vec<u32> = match r.read_indices() {
            Some(i) => i.into_u32().collect(),
            None => (0..positions.len() as u32).collect(),
        };
        self.check_indices(at, &raw, positions.len())?;
        if mode == Mode::Triangles && !raw.len().is_multiple_of(3) {
            let key = if p.indices().is_some() {
                "indices"
            } else {
                "attributes.POSITION"
            };
            return Err(self.bad(
                &format!("{at}.{key}"),
                format!(
                    "has {} elements, not a multiple of 3, for TRIANGLES",
                    raw.len()
                ),
            ));
        }
        let indices = triangulate(mode, &raw);
        let before = indices.len() / 3;
        let indices = drop_degenerate(&positions, indices);
        let degenerate = before - indices.len() / 3;
        let joints: Vec<[u16; 4]> = r
            .read_joints(0)
            .map(|j| j.into_u16().collect())
            .unwrap_or_default();
        let weights: Vec<[f32; 4]> = r
            .read_weights(0)
            .map(|w| w.into_f32().collect())
            .unwrap_or_default();
        if let Some(v) = weights
            .iter()
            .position(|w| !w.iter().all(|x| x.is_finite()))
        {
            return Err(self.bad(
                &format!("{at}.attributes.WEIGHTS_0"),
                format!("vertex {v}'s weights {:?} are not finite", weights[v]),
            ));
        }
        // glTF 2.0 §3.7.3.1: a vertex's weights sum to 1. Weights of a vertex a triangle uses
        // summing to zero bind it to nothing (it collapsed to the origin); a sum off by more
        // than rounding is divided out (weights of 0.5 in all pulled the vertex halfway to
        // the origin), as other loaders do.
        // With a second set (`WEIGHTS_1`, not read) the first sums to less than 1 by design.
        let second_set = r.read_weights(1).is_some();
        let mut used = vec![false; weights.len()];
        for &i in &raw {
            if let Some(u) = used.get_mut(i as usize) {
                *u = true;
            }
        }
        let mut weights = weights;
        for (v, w) in weights.iter_mut().enumerate() {
            let sum: f32 = w.iter().sum();
            if second_set || !used[v] {
                continue;
            }
            if !(sum > 0.0) {
                return Err(self.bad(
                    &format!("{at}.attributes.WEIGHTS_0"),
                    format!("vertex {v}'s weights {w:?} sum to {sum}, not 1"),
                ));
            }
            if (sum - 1.0).abs() > 1e-3 {
                for x in w.iter_mut() {
                    *x /= sum;
                }
            }
        }
        let targets = self.morph_targets(at, r.read_morph_targets(), positions.len())?;
        let local = p.material().index().and_then(|i| materials.get(i));
        let uv_at = format!("{at}.attributes.TEXCOORD_0");
        match &uvs {
            Some(uvs) => {
                if let Some(v) = uvs.iter().position(|t| !t.is_finite()) {
                    return Err(self.bad(&uv_at, format!("vertex {v}'s {} is not finite", uvs[v])));
                }
            }
            None => {
                if let Some(m) = local.filter(|m| {
                    m.base_color_texture.is_some()
                        || m.normal_texture.is_some()
                        || m.emissive_texture.is_some()
                        || m.metallic_roughness_texture.is_some()
                }) {
                    return Err(self.bad(
                        &uv_at,
                        format!(
                            "is missing, but the primitive's material {} has textures, which \
                             are read through it",
                            name_of(
                                "materials",
                                p.material().index().unwrap_or(0),
                                Some(&m.name)
                            ),
                        ),
                    ));
                }
            }
        }
        let material = match p.material().index() {
            Some(i) => self.offsets.materials + 1 + i,
            None => 0,
        };
        let colors: Option<Vec<Vec4>> = r
            .read_colors(0)
            .map(|c| c.into_rgba_f32().map(Vec4::from).collect());
        if let Some(c) = &colors
            && (c.len() != positions.len() || c.iter().any(|v| !v.is_finite()))
        {
            return Err(self.bad(at, "COLOR_0 must be finite and one per vertex"));
        }
        let tangents: Option<Vec<Vec4>> = if local.is_some_and(|m| m.normal_texture.is_some()) {
            r.read_tangents()
                .map(|t| t.map(Vec4::from).collect::<Vec<_>>())
                .filter(|t| t.len() == positions.len() && t.iter().all(|v| v.is_finite()))
        } else {
            None
        };
        let primitive = Primitive {
            positions,
            normals: normals.filter(|n| n.iter().all(|v| v.is_finite())),
            uvs,
            colors,
            tangents,
            indices,
            material,
            masked: local.is_some_and(|m| m.alpha_cutoff.is_some()),
            joints,
            weights,
            targets,
        };
        Ok(Some((primitive, degenerate)))
    }

    /// Reads primitive `at`'s POSITION attribute, which must be present and finite.
    fn positions(
        &self,
        at: &str,
        read: Option<gltf::mesh::util::ReadPositions<'_>>,
    ) -> Result<Vec<Vec3>> {
        let positions: Vec<Vec3> = read
            .ok_or_else(|| self.bad(at, "has no POSITION attribute"))?
            .map(Vec3::from)
            .collect();
        if let Some(i) = positions.iter().position(|v| !v.is_finite()) {
            return Err(self.bad(at, format!("POSITION {i} is not finite ({})", positions[i])));
        }
        Ok(positions)
    }

    /// Checks that primitive `at`'s indices name one of its `vertices`.
    fn check_indices(&self, at: &str, raw: &[u32], vertices: usize) -> Result<()> {
        match raw.iter().find(|&&i| i as usize >= vertices) {
            Some(&i) => Err(self.bad(
                at,
                format!("index {i} is out of range ({vertices} vertices)"),
            )),
            None => Ok(()),
        }
    }

    /// Reads primitive `at`'s morph targets (glTF 2.0 §3.7.2.2): a target's positions, if
    /// any, must be finite and one per vertex.
    fn morph_targets(
        &self,
        at: &str,
        read: impl Iterator<Item = MorphTargetReads<'a>>,
        vertices: usize,
    ) -> Result<Vec<MorphTarget>> {
        let targets = read
            .map(|(pos, nrm, _)| MorphTarget {
                positions: pos.map(|i| i.map(Vec3::from).collect()).unwrap_or_default(),
                normals: nrm.map(|i| i.map(Vec3::from).collect()).unwrap_or_default(),
            })
            .collect::<Vec<_>>();
        for (ti, t) in targets.iter().enumerate() {
            if (!t.positions.is_empty() && t.positions.len() != vertices)
                || t.positions.iter().any(|v| !v.is_finite())
            {
                return Err(self.bad(
                    &format!("{at}.targets[{ti}]"),
                    "POSITION must be finite and match the vertex count",
                ));
            }
        }
        Ok(targets)
    }

    /// Reads `skins` (glTF 2.0 §3.7.3): joints and inverse bind matrices, identity where the
    /// file gives none; the matrices must be finite.
    fn skins(&self) -> Result<Vec<Skin>> {
        self.doc
            .skins()
            .map(|s| {
                let r = s.reader(self.data());
                let joints: Vec<usize> = s.joints().map(|j| j.index()).collect();
                let inverse_bind: Vec<Mat4> = match r.read_inverse_bind_matrices() {
                    Some(m) => m.map(|c| Mat4::from_cols_array_2d(&c)).collect(),
                    None => vec![Mat4::IDENTITY; joints.len()],
                };
                let at = format!(
                    "{}.inverseBindMatrices",
                    name_of("skins", s.index(), s.name())
                );
                if let Some(k) = inverse_bind.iter().position(|m| !m.is_finite()) {
                    return Err(self.bad(&at, format!("matrix {k} is not finite")));
                }
                // A singular one collapses every vertex bound to its joint into a point.
                if let Some(k) = inverse_bind
                    .iter()
                    .position(|m| !(m.as_dmat4().determinant().abs() > 0.0))
                {
                    return Err(self.bad(&at, format!("matrix {k} is singular")));
                }
                Ok(Skin {
                    joints,
                    inverse_bind,
                })
            })
            .collect()
    }

    /// Checks that the primitives of every node with a skin name, in `JOINTS_0`, only joints
    /// that skin has (glTF 2.0 §3.7.3): a vertex bound to a joint past the skin's `joints`
    /// would follow no joint.
    fn check_joints(&self) -> Result<()> {
        // The largest joint index each primitive names, with the vertex that names it.
        let largest: Vec<Vec<Option<(usize, u16)>>> = self
            .doc
            .meshes()
            .map(|m| {
                m.primitives()
                    .map(|p| {
                        p.reader(self.data())
                            .read_joints(0)?
                            .into_u16()
                            .enumerate()
                            .map(|(v, j)| (v, j.into_iter().max().unwrap_or(0)))
                            .max_by_key(|&(_, j)| j)
                    })
                    .collect()
            })
            .collect();
        for n in self.doc.nodes() {
            let (Some(mesh), Some(skin)) = (n.mesh(), n.skin()) else {
                continue;
            };
            let joints = skin.joints().len();
            for (p, max) in largest[mesh.index()].iter().enumerate() {
                if let Some((v, j)) = *max
                    && j as usize >= joints
                {
                    return Err(self.bad(
                        &format!(
                            "{}.primitives[{p}].attributes.JOINTS_0",
                            name_of("meshes", mesh.index(), mesh.name())
                        ),
                        format!(
                            "vertex {v} names joint {j}, but {}, the skin of {}, has {joints} joints",
                            name_of("skins", skin.index(), skin.name()),
                            name_of("nodes", n.index(), n.name())
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Reads the `KHR_lights_punctual` lights. Values the extension's specification forbids
    /// are errors: a colour or intensity negative or not finite, a range not positive, spot
    /// cone angles outside 0 ≤ inner < outer ≤ π/2. So is a light the renderer cannot
    /// represent in f32: colour × intensity (the intensity it renders per channel) or a point
    /// or spot light's power bound 4π × colour × intensity not finite, or an outer cone angle
    /// whose cosine rounds to 1 (a cone that lights nothing).
    fn lights(&self) -> Result<Vec<Light>> {
        let lights: Vec<Light> = self
            .doc
            .lights()
            .map(|ls| ls.map(light).collect())
            .unwrap_or_default();
        for (i, l) in lights.iter().enumerate() {
            let at = name_of("extensions.KHR_lights_punctual.lights", i, Some(&l.name));
            let bad = |key: &str, m: String| self.bad(&format!("{at}.{key}"), m);
            if !(l.intensity.is_finite() && l.intensity >= 0.0) {
                return Err(bad(
                    "intensity",
                    format!("{:?} must be finite and non-negative", l.intensity),
                ));
            }
            let color = l.color.to_array();
            if !(l.color.is_finite() && l.color.min_element() >= 0.0) {
                return Err(bad(
                    "color",
                    format!("{color:?} must be finite and non-negative"),
                ));
            }
            let radiant = l.color * l.intensity;
            let power = 4.0 * std::f32::consts::PI * radiant;
            let point = matches!(l.kind, LightKind::Point | LightKind::Spot { .. });
            if !radiant.is_finite() || (point && !power.is_finite()) {
                let what = if radiant.is_finite() {
                    "the power bound 4π × colour × intensity"
                } else {
                    "colour × intensity"
                };
                return Err(self.bad(
                    &at,
                    format!(
                        "{what} overflows f32 (colour {color:?}, intensity {:?})",
                        l.intensity
                    ),
                ));
            }
            if let Some(r) = l.range
                && !(r.is_finite() && r > 0.0)
            {
                return Err(bad("range", format!("{r:?} must be finite and positive")));
            }
            if let LightKind::Spot { inner, outer } = l.kind {
                if !(outer > 0.0 && outer <= std::f32::consts::FRAC_PI_2) {
                    return Err(bad(
                        "spot.outerConeAngle",
                        format!("{outer:?} must be in (0, π/2] radians"),
                    ));
                }
                if outer.cos() >= 1.0 {
                    return Err(bad(
                        "spot.outerConeAngle",
                        format!(
                            "{outer:?} radians is a cone too narrow to light anything: its cosine rounds to 1 in f32"
                        ),
                    ));
                }
                if !(inner >= 0.0 && inner < outer) {
                    return Err(bad(
                        "spot.innerConeAngle",
                        format!("{inner:?} must be in [0, outerConeAngle = {outer:?}) radians"),
                    ));
                }
            }
        }
        Ok(lights)
    }

    /// Reads `cameras` (glTF 2.0 §3.10): the projection's vertical field of view or
    /// magnification, and its clip depths. Values no camera can have are errors.
    fn cameras(&self) -> Result<Vec<Camera>> {
        self.doc
            .cameras()
            .map(|c| {
                let at = |key: &str| format!("{}.{key}", name_of("cameras", c.index(), c.name()));
                let bad = |key: &str, msg: &str| Error::input(self.path, at(key), msg.to_string());
                let (projection, clip) = match c.projection() {
                    gltf::camera::Projection::Perspective(p) => {
                        let yfov = p.yfov();
                        if !(yfov > 0.0 && yfov < std::f32::consts::PI) {
                            return Err(bad("perspective.yfov", "must be in (0, π) radians"));
                        }
                        let near = p.znear();
                        if !(near.is_finite() && near > 0.0) {
                            return Err(bad("perspective.znear", "must be finite and > 0"));
                        }
                        let far = p.zfar().unwrap_or(f32::INFINITY);
                        if far.is_nan() || far <= near {
                            return Err(bad("perspective.zfar", "must be greater than znear"));
                        }
                        (Projection::Perspective { yfov }, Clip { near, far })
                    }
                    gltf::camera::Projection::Orthographic(o) => {
                        let ymag = o.ymag();
                        if !(ymag.is_finite() && ymag != 0.0) {
                            return Err(bad("orthographic.ymag", "must be finite and non-zero"));
                        }
                        let near = o.znear();
                        if !(near.is_finite() && near >= 0.0) {
                            return Err(bad("orthographic.znear", "must be finite and ≥ 0"));
                        }
                        let far = o.zfar();
                        if !(far.is_finite() && far > near) {
                            return Err(bad(
                                "orthographic.zfar",
                                "must be finite and greater than znear",
                            ));
                        }
                        (
                            Projection::Orthographic { ymag: ymag.abs() },
                            Clip { near, far },
                        )
                    }
                };
                Ok(Camera {
                    name: c.name().unwrap_or("").to_owned(),
                    projection,
                    clip,
                })
            })
            .collect()
    }

    /// Reads `nodes` (glTF 2.0 §3.5.2), links each to its parent, and returns them with the
    /// roots of the default scene (or of the first scene, or the parentless nodes).
    fn nodes(&mut self) -> Result<(Vec<Node>, Vec<usize>)> {
        let mut nodes: Vec<Node> = Vec::new();
        for n in self.doc.nodes() {
            let node = self.node(&n)?;
            if node.extras_tag.is_none()
                && let Some(key) = misspelt_motion_key(n.extras())
            {
                let at = name_of("nodes", n.index(), n.name());
                self.warn(format_args!(
                    "{at}: extras key \"{key}\" is ignored; the motion tag's key is \"{MOTION_KEY}\""
                ));
            }
            nodes.push(node);
        }
        for i in 0..nodes.len() {
            for c in nodes[i].children.clone() {
                nodes[c].parent = Some(i);
            }
        }
        let roots: Vec<usize> = match self
            .doc
            .default_scene()
            .or_else(|| self.doc.scenes().next())
        {
            Some(s) => s.nodes().map(|n| n.index()).collect(),
            None => (0..nodes.len())
                .filter(|&i| nodes[i].parent.is_none())
                .collect(),
        };
        Ok((nodes, roots))
    }

    /// Reads one node's transform, attachments and the motion tag in its extras (see
    /// [`motion_tag`]); `parent` is filled in by [`Reader::nodes`].
    fn node(&self, n: &gltf::Node<'_>) -> Result<Node> {
        let (t, r, s) = n.transform().decomposed();
        let at = name_of("nodes", n.index(), n.name());
        let tag = motion_tag(n.extras())
            .map_err(|m| self.bad(&format!("{at}.extras.{MOTION_KEY}"), m))?;
        Ok(Node {
            name: n.name().unwrap_or("").to_owned(),
            parent: None,
            children: n.children().map(|c| c.index()).collect(),
            translation: Vec3::from(t),
            rotation: Quat::from_array(r).normalize(),
            scale: Vec3::from(s),
            mesh: n.mesh().map(|m| m.index()),
            skin: n.skin().map(|s| s.index()),
            camera: n.camera().map(|c| c.index()),
            light: n.light().map(|l| l.index()),
            weights: n.weights().map(<[f32]>::to_vec),
            extras_tag: tag,
            motion: Motion::Static,
            why: super::TagSource::DefaultStatic,
        })
    }

    /// Reads `animations` (glTF 2.0 §3.11); an unnamed animation is named after its index.
    fn animations(&self) -> Result<Vec<Animation>> {
        let mut animations = Vec::new();
        for a in self.doc.animations() {
            let mut channels = Vec::new();
            for ch in a.channels() {
                let at = format!(
                    "{}.channels[{}]",
                    name_of("animations", a.index(), a.name()),
                    ch.index()
                );
                channels.push(self.channel(&at, &ch)?);
            }
            animations.push(Animation {
                name: match a.name() {
                    Some(n) if !n.is_empty() => n.to_owned(),
                    _ => format!("animations[{}]", a.index()),
                },
                channels,
            });
        }
        Ok(animations)
    }

    /// Reads one channel and its sampler: key times finite and increasing, and one finite
    /// value (three for cubic splines: in-tangent, value, out-tangent) per key and component.
    fn channel(&self, at: &str, ch: &gltf::animation::Channel<'_>) -> Result<Channel> {
        let r = ch.reader(self.data());
        let times: Vec<f32> = r
            .read_inputs()
            .ok_or_else(|| self.bad(at, "sampler has no input"))?
            .collect();
        if times.is_empty() {
            return Err(self.bad(at, "sampler has no keys (its input accessor's count is 0)"));
        }
        if times.iter().any(|t| !t.is_finite()) || times.windows(2).any(|w| w[1] < w[0]) {
            return Err(self.bad(at, "key times must be finite and increasing"));
        }
        let outputs = r
            .read_outputs()
            .ok_or_else(|| self.bad(at, "sampler has no output"))?;
        let (property, width, values) = sampler_values(ch, outputs, times.len());
        let interpolation = match ch.sampler().interpolation() {
            gltf::animation::Interpolation::Step => Interpolation::Step,
            gltf::animation::Interpolation::Linear => Interpolation::Linear,
            gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
        };
        let stride = if interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        if width == 0
            || values.len() != times.len() * stride * width
            || values.iter().any(|v| !v.is_finite())
        {
            return Err(self.bad(
                at,
                format!(
                    "sampler output has {} values for {} keys (expected {} finite values)",
                    values.len(),
                    times.len(),
                    times.len() * stride * width
                ),
            ));
        }
        let node = ch.target().node();
        if property == Property::Weights
            && let Some(mesh) = node.mesh()
        {
            let targets = mesh
                .primitives()
                .next()
                .map_or(0, |p| p.morph_targets().len());
            if targets > 0 && width != targets {
                return Err(self.bad(
                    at,
                    format!(
                        "sampler output has {} weights a key for {} ({}), which has {targets} morph targets",
                        width,
                        name_of("nodes", node.index(), node.name()),
                        name_of("meshes", mesh.index(), mesh.name()),
                    ),
                ));
            }
        }
        if property == Property::Rotation {
            // A key's value (a cubic spline's middle element): a rotation, not zero.
            let zero = (0..times.len()).find(|&k| {
                let i = (k * stride + stride / 2) * width;
                let q = Vec4::from_slice(&values[i..i + 4]);
                !(q.abs().max_element() > 0.0)
            });
            if let Some(k) = zero {
                return Err(self.bad(
                    at,
                    format!(
                        "rotation key {k} (t = {}) is the zero quaternion, not a rotation",
                        times[k]
                    ),
                ));
            }
        }
        Ok(Channel {
            node: node.index(),
            property,
            sampler: Sampler {
                interpolation,
                times,
                values,
                width,
            },
        })
    }
}

/// Converts one `KHR_lights_punctual` light; the cone angles of a spot light are in radians.
fn light(l: gltf::khr_lights_punctual::Light<'_>) -> Light {
    Light {
        name: l.name().unwrap_or("").to_owned(),
        color: Vec3::from(l.color()),
        intensity: l.intensity(),
        range: l.range(),
        kind: match l.kind() {
            Kind::Directional => LightKind::Directional,
            Kind::Point => LightKind::Point,
            Kind::Spot {
                inner_cone_angle,
                outer_cone_angle,
            } => LightKind::Spot {
                inner: inner_cone_angle,
                outer: outer_cone_angle,
            },
        },
    }
}

/// Reads a channel's sampler output as the property it animates, the number of components
/// per value (`width`) and the flat values. Morph target weights have one component per
/// target: the values per key over `keys` key times, divided by three for cubic splines.
fn sampler_values(
    ch: &gltf::animation::Channel<'_>,
    outputs: ReadOutputs<'_>,
    keys: usize,
) -> (Property, usize, Vec<f32>) {
    match outputs {
        ReadOutputs::Translations(v) => (Property::Translation, 3, v.flatten().collect()),
        ReadOutputs::Rotations(v) => (Property::Rotation, 4, v.into_f32().flatten().collect()),
        ReadOutputs::Scales(v) => (Property::Scale, 3, v.flatten().collect()),
        ReadOutputs::MorphTargetWeights(v) => {
            let all: Vec<f32> = v.into_f32().collect();
            let per_key = all.len().checked_div(keys).unwrap_or(0);
            let stride =
                if ch.sampler().interpolation() == gltf::animation::Interpolation::CubicSpline {
                    3
                } else {
                    1
                };
            (Property::Weights, per_key / stride, all)
        }
    }
}

/// Reads the motion tag from a node's extras. Extras that are not an object, objects without
/// the key, and any other keys are ignored (other tools write their own extras); the key
/// itself must hold `"static"` or `"dynamic"`.
pub fn motion_tag(extras: &gltf::json::Extras) -> std::result::Result<Option<Motion>, String> {
    let Some(raw) = extras else { return Ok(None) };
    let map = match serde_json::from_str::<serde_json::Value>(raw.get()) {
        Ok(serde_json::Value::Object(map)) => map,
        // The crate parsed these extras, so only a limit of serde_json's (nesting deeper than
        // 128 levels) fails here: a motion tag there must not be dropped silently.
        Err(e) if raw.get().contains(&format!("\"{MOTION_KEY}\"")) => {
            return Err(format!(
                "the extras hold a \"{MOTION_KEY}\" key but cannot be read: {e}"
            ));
        }
        _ => return Ok(None),
    };
    match map.get(MOTION_KEY) {
        None => Ok(None),
        Some(serde_json::Value::String(s)) if s == "static" => Ok(Some(Motion::Static)),
        Some(serde_json::Value::String(s)) if s == "dynamic" => Ok(Some(Motion::Dynamic)),
        Some(v) => Err(format!("must be \"static\" or \"dynamic\", got {v}")),
    }
}

/// An extras key that looks like a misspelt motion tag (`Motion`, `anchorage_motion`,
/// `motion ` ...): the key, when the extras hold no `motion` key but one containing it,
/// case and surrounding characters aside.
fn misspelt_motion_key(extras: &gltf::json::Extras) -> Option<String> {
    let raw = extras.as_ref()?;
    let serde_json::Value::Object(map) = serde_json::from_str(raw.get()).ok()? else {
        return None;
    };
    if map.contains_key(MOTION_KEY) {
        return None;
    }
    map.keys()
        .find(|k| k.to_lowercase().contains(MOTION_KEY))
        .cloned()
}

/// Standard base64 (RFC 4648 §4, padding optional) as data URIs carry it; `None` if invalid.
fn base64_decode(text: &str) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let (mut acc, mut bits) = (0u32, 0u32);
    for c in text.bytes() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            b'=' => break,
            _ => return None,
        };
        acc = (acc << 6) | v as u32;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    Some(out)
}

/// Percent-decoding of relative URIs (glTF URIs are RFC 3986): `None` where the bytes it
/// decodes to are not UTF-8 (the `gltf` crate, which decodes the URI again to read the file,
/// would panic on them). A `%` not followed by two hex digits stays as it is.
fn urlencoding_decode(uri: &str) -> Option<String> {
    let b = uri.as_bytes();
    let hex = |c: u8| (c as char).to_digit(16);
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%'
            && i + 2 < b.len()
            && let (Some(high), Some(low)) = (hex(b[i + 1]), hex(b[i + 2]))
        {
            out.push((high * 16 + low) as u8);
            i += 3;
            continue;
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8(out).ok()
}

/// The file a relative URI names beside the glTF file: `base` joined with the decoded URI,
/// or the error naming element `at` of `path` when the URI does not decode to UTF-8.
fn uri_file(path: &Path, at: &str, base: &Path, uri: &str) -> Result<PathBuf> {
    urlencoding_decode(uri)
        .map(|u| base.join(u))
        .ok_or_else(|| {
            Error::input(
                path,
                format!("{at}.uri"),
                format!("{uri:?} percent-decodes to bytes that are not UTF-8"),
            )
        })
}

/// Checks that every accessor's elements lie inside its buffer view and every view inside its
/// buffer's data, so that reading can never go out of bounds, and that a sparse accessor's
/// indices are strictly increasing and below its count (glTF 2.0 §3.6.2.3), so that none of
/// its values is dropped.
fn check_accessors(
    path: &Path,
    doc: &gltf::Document,
    buffers: &[gltf::buffer::Data],
) -> Result<()> {
    for v in doc.views() {
        let len = buffers[v.buffer().index()].0.len();
        if v.offset()
            .checked_add(v.length())
            .is_none_or(|end| end > len)
        {
            return Err(Error::input(
                path,
                name_of("bufferViews", v.index(), v.name()),
                format!(
                    "bytes {} + {} lie outside its buffer ({len} bytes)",
                    v.offset(),
                    v.length()
                ),
            ));
        }
    }
    for a in doc.accessors() {
        let Some(v) = a.view() else { continue };
        let elem = a.size();
        let stride = v.stride().unwrap_or(elem);
        let need = if a.count() == 0 {
            Some(0)
        } else {
            (a.count() - 1)
                .checked_mul(stride)
                .and_then(|n| n.checked_add(elem))
                .and_then(|n| n.checked_add(a.offset()))
        };
        if need.is_none_or(|n| n > v.length()) {
            return Err(Error::input(
                path,
                name_of("accessors", a.index(), a.name()),
                format!(
                    "{} elements need more bytes than its buffer view holds ({})",
                    a.count(),
                    v.length()
                ),
            ));
        }
    }
    for a in doc.accessors() {
        if let Some(s) = a.sparse() {
            check_sparse_indices(path, &a, &s, buffers)?;
        }
    }
    Ok(())
}

/// Checks that the sparse `indices` of accessor `a` are strictly increasing and below its
/// count (glTF 2.0 §3.6.2.3). [`super::validate`] has checked that they fit their buffer view
/// and that the view has no `byteStride`; [`check_accessors`], that the view fits its buffer.
fn check_sparse_indices(
    path: &Path,
    a: &gltf::Accessor<'_>,
    s: &gltf::accessor::sparse::Sparse<'_>,
    buffers: &[gltf::buffer::Data],
) -> Result<()> {
    use gltf::accessor::sparse::IndexType;
    let at = format!(
        "{}.sparse.indices",
        name_of("accessors", a.index(), a.name())
    );
    let indices = s.indices();
    let size = match indices.index_type() {
        IndexType::U8 => 1,
        IndexType::U16 => 2,
        IndexType::U32 => 4,
    };
    let view = indices.view();
    let bytes = view
        .offset()
        .checked_add(indices.offset())
        .and_then(|start| Some((start, start.checked_add(s.count().checked_mul(size)?)?)))
        .and_then(|(start, end)| buffers[view.buffer().index()].0.get(start..end))
        .ok_or_else(|| {
            Error::input(
                path,
                &at,
                format!("{} indices do not fit their buffer view", s.count()),
            )
        })?;
    let mut previous: Option<u32> = None;
    for (k, b) in bytes.chunks_exact(size).enumerate() {
        // Little-endian, of 1, 2 or 4 bytes.
        let i = b.iter().rev().fold(0u32, |i, &x| (i << 8) | x as u32);
        if i as usize >= a.count() {
            return Err(Error::input(
                path,
                &at,
                format!(
                    "index {k} is {i}, outside the accessor's {} elements",
                    a.count()
                ),
            ));
        }
        if let Some(p) = previous
            && i <= p
        {
            return Err(Error::input(
                path,
                &at,
                format!(
                    "index {k} is {i}, not above the one before it ({p}); sparse indices must strictly increase"
                ),
            ));
        }
        previous = Some(i);
    }
    Ok(())
}

fn wrap(w: gltf::texture::WrappingMode) -> Wrap {
    match w {
        gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
        gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
        gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
    }
}

/// A `KHR_texture_transform` as read: the transform and the `texCoord` it overrides, if any.
type TransformRead = (UvTransform, Option<u32>);

/// The `KHR_texture_transform` of a texture info (which the gltf crate parses).
fn info_transform(info: &gltf::texture::Info<'_>) -> Option<TransformRead> {
    info.texture_transform().map(|t| {
        (
            UvTransform::new(Vec2::from(t.offset()), t.rotation(), Vec2::from(t.scale())),
            t.tex_coord(),
        )
    })
}

/// Reads a `KHR_texture_transform` object from its JSON (for `normalTexture`, whose
/// extensions the gltf crate leaves as JSON). Offsets, rotation and scale must be finite
/// numbers.
fn texture_transform(v: &serde_json::Value) -> std::result::Result<TransformRead, String> {
    let num = |key: &str, default: f32| -> std::result::Result<f32, String> {
        match v.get(key) {
            None => Ok(default),
            Some(x) => x
                .as_f64()
                .map(|f| f as f32)
                .filter(|f| f.is_finite())
                .ok_or_else(|| format!("{key} must be a finite number, got {x}")),
        }
    };
    let pair = |key: &str, default: f32| -> std::result::Result<Vec2, String> {
        match v.get(key) {
            None => Ok(Vec2::splat(default)),
            Some(serde_json::Value::Array(a)) if a.len() == 2 => {
                let c: Vec<Option<f32>> = a
                    .iter()
                    .map(|x| x.as_f64().map(|f| f as f32).filter(|f| f.is_finite()))
                    .collect();
                match c[..] {
                    [Some(x), Some(y)] => Ok(Vec2::new(x, y)),
                    _ => Err(format!("{key} must be two finite numbers")),
                }
            }
            Some(x) => Err(format!("{key} must be two finite numbers, got {x}")),
        }
    };
    let offset = pair("offset", 0.0)?;
    let scale = pair("scale", 1.0)?;
    let rotation = num("rotation", 0.0)?;
    let tex_coord = match v.get("texCoord") {
        None => None,
        Some(x) => Some(
            x.as_u64()
                .and_then(|n| u32::try_from(n).ok())
                .ok_or_else(|| format!("texCoord must be a non-negative integer, got {x}"))?,
        ),
    };
    Ok((UvTransform::new(offset, rotation, scale), tex_coord))
}

/// Decodes an 8- or 16-bit image to linear RGBA: colour channels sRGB-decoded when `srgb`
/// (base colour, emission), else read as they are (normal maps); alpha always linear.
fn decode_texture(data: &gltf::image::Data, srgb: bool) -> Option<Texture> {
    use gltf::image::Format::*;
    let (channels, wide) = match data.format {
        R8 => (1, false),
        R8G8 => (2, false),
        R8G8B8 => (3, false),
        R8G8B8A8 => (4, false),
        R16 => (1, true),
        R16G16 => (2, true),
        R16G16B16 => (3, true),
        R16G16B16A16 => (4, true),
        _ => return None,
    };
    let count = (data.width * data.height) as usize;
    let value = |i: usize| -> f32 {
        if wide {
            u16::from_le_bytes([data.pixels[2 * i], data.pixels[2 * i + 1]]) as f32 / 65535.0
        } else {
            data.pixels[i] as f32 / 255.0
        }
    };
    let decode = |c: f32| {
        if !srgb {
            c
        } else if wide {
            srgb_to_linear(c)
        } else {
            crate::color::srgb8_to_linear((c * 255.0).round() as u8)
        }
    };
    let texels = (0..count)
        .map(|p| {
            let c = |k: usize| value(p * channels + k);
            match channels {
                1 => Vec4::new(decode(c(0)), decode(c(0)), decode(c(0)), 1.0),
                2 => Vec4::new(decode(c(0)), decode(c(0)), decode(c(0)), c(1)),
                3 => Vec4::new(decode(c(0)), decode(c(1)), decode(c(2)), 1.0),
                _ => Vec4::new(decode(c(0)), decode(c(1)), decode(c(2)), c(3)),
            }
        })
        .collect();
    Some(Texture {
        width: data.width,
        height: data.height,
        texels,
    })
}

/// Triangle list indices for any triangle mode (strips alternate winding; fans share vertex 0).
fn triangulate(mode: Mode, raw: &[u32]) -> Vec<u32> {
    match mode {
        Mode::TriangleStrip => (0..raw.len().saturating_sub(2))
            .flat_map(|i| {
                if i % 2 == 0 {
                    [raw[i], raw[i + 1], raw[i + 2]]
                } else {
                    [raw[i + 1], raw[i], raw[i + 2]]
                }
            })
            .collect(),
        Mode::TriangleFan => (1..raw.len().saturating_sub(1))
            .flat_map(|i| [raw[0], raw[i], raw[i + 1]])
            .collect(),
        _ => raw[..raw.len() / 3 * 3].to_vec(),
    }
}

/// Removes zero-area triangles (repeated vertices or collinear corners): they cannot be hit
/// and carry no normal.
fn drop_degenerate(p: &[Vec3], indices: Vec<u32>) -> Vec<u32> {
    indices
        .chunks_exact(3)
        .filter(|t| {
            let (a, b, c) = (p[t[0] as usize], p[t[1] as usize], p[t[2] as usize]);
            let n = (b - a).cross(c - a);
            let scale = (b - a).length_squared().max((c - a).length_squared());
            n.length_squared() > scale * scale * 1e-14 && n.is_finite()
        })
        .flatten()
        .copied()
        .collect()
}
