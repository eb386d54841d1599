//! The editable scene description (STYLE.md §2, Tungsten's `Scene`): glTF layers composed
//! as a [`SceneDesc`] describes them (a job file's layers), with every prim's motion tag
//! resolved. [`Scene::evaluate`] is the one
//! function that turns it into the immutable, render-ready [`FrameScene`] at a time `t`.
//!
//! Motion tags (DESIGN.md, Scene conventions): a node's `extras.motion` (`"static"` or
//! `"dynamic"`) — what Blender writes for a custom property `motion` and what usd2gltf
//! writes for a USD attribute `gltf:motion` — is inherited by its children; the job file
//! overrides it by node name. An untagged prim is dynamic if an animation moves it,
//! otherwise static. A prim tagged static that an animation moves is an error. The anchor
//! method (paper §3) relies on the tag: only dynamic prims may change between frames.

pub mod anim;
pub mod frame;
pub mod gltf;
pub mod material;
pub mod validate;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use glam::{DMat4, DVec3, Mat4, Quat, Vec3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

pub use frame::{CameraRay, FrameCamera, FrameScene, PunctualLight, StaticSet};
pub use material::{Material, Surfaces, Texture, TextureRef};

use crate::error::{Error, Result};
use crate::geom::{Geometry, Motion};
use anim::{Animation, Property};

/// A glTF node's `extras` as far as anchorage reads them: the format of the motion tag
/// (`schemas/motion-tag.schema.json`, generated from this type; `gltf::motion_tag` reads it).
///
/// A glTF node's `extras` may carry `motion`. Blender writes it for an object custom
/// property named `motion` (glTF exporter with Custom Properties on); usd2gltf writes it for
/// a USD attribute `gltf:motion`. Children inherit the tag unless they carry their own; a
/// job file's `scene[i].tags` overrides it by node name. Untagged prims are `dynamic` if an
/// animation moves them, else `static`. Extras that are not an object, and every other
/// key, are ignored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct MotionTag {
    /// `static`: never moves (the paper's static objects; anchors and caches may live on
    /// it). `dynamic`: may move or deform between frames.
    pub motion: Option<Motion>,
}

impl MotionTag {
    /// The JSON Schema of the tag (`schemas/motion-tag.schema.json`).
    pub fn schema() -> schemars::Schema {
        let mut s = schemars::schema_for!(MotionTag);
        s.insert("$id".into(), "anchorage/motion-tag.schema.json".into());
        s.insert(
            "title".into(),
            "anchorage motion tag (glTF node extras)".into(),
        );
        s
    }
}

/// Why a node has the motion it has (reported by `anchorage inspect`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TagSource {
    /// The job file's `tags` for this node's name.
    Job,
    /// The node's own `extras.motion`.
    Extras,
    /// Inherited from the named ancestor's tag.
    Inherited(String),
    /// Untagged and moved by the named animation.
    DefaultAnimated(String),
    /// Untagged and not animated.
    DefaultStatic,
}

impl std::fmt::Display for TagSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TagSource::Job => write!(f, "job file override"),
            TagSource::Extras => write!(f, "tagged in extras"),
            TagSource::Inherited(n) => write!(f, "inherited from {n}"),
            TagSource::DefaultAnimated(a) => write!(f, "untagged, moved by animation {a}"),
            TagSource::DefaultStatic => write!(f, "untagged, not animated"),
        }
    }
}

#[derive(Debug, Clone)]
pub struct Node {
    pub name: String,
    pub parent: Option<usize>,
    pub children: Vec<usize>,
    pub translation: Vec3,
    pub rotation: Quat,
    pub scale: Vec3,
    pub mesh: Option<usize>,
    pub skin: Option<usize>,
    pub camera: Option<usize>,
    pub light: Option<usize>,
    /// The node's own default morph weights (else the mesh's apply).
    pub weights: Option<Vec<f32>>,
    pub extras_tag: Option<Motion>,
    /// Resolved motion (see the module doc).
    pub motion: Motion,
    pub why: TagSource,
}

#[derive(Debug, Clone)]
pub struct MorphTarget {
    /// Position displacements (empty when the target moves no positions).
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
}

#[derive(Debug, Clone)]
pub struct Primitive {
    pub positions: Vec<Vec3>,
    pub normals: Option<Vec<Vec3>>,
    pub uvs: Option<Vec<glam::Vec2>>,
    /// Linear RGBA vertex colours (`COLOR_0`), one per vertex.
    pub colors: Option<Vec<glam::Vec4>>,
    /// Tangents with the bitangent's sign in `w` (`TANGENT`), kept only when the material
    /// has a normal map.
    pub tangents: Option<Vec<glam::Vec4>>,
    /// Triangle list, degenerate triangles removed.
    pub indices: Vec<u32>,
    /// Index into [`Scene::materials`].
    pub material: usize,
    /// The material cuts the surface out (alpha `MASK` or `BLEND`): its triangles are
    /// alpha-tested by every ray.
    pub masked: bool,
    pub joints: Vec<[u16; 4]>,
    pub weights: Vec<[f32; 4]>,
    pub targets: Vec<MorphTarget>,
}

#[derive(Debug, Clone)]
pub struct Mesh {
    pub name: String,
    pub weights: Vec<f32>,
    pub primitives: Vec<Primitive>,
}

#[derive(Debug, Clone)]
pub struct Skin {
    pub joints: Vec<usize>,
    pub inverse_bind: Vec<Mat4>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LightKind {
    Point,
    /// Cone angles in radians from the light's −Z axis.
    Spot {
        inner: f32,
        outer: f32,
    },
    Directional,
}

/// A `KHR_lights_punctual` light: intensity in candela (point, spot) or lux (directional).
#[derive(Debug, Clone)]
pub struct Light {
    pub name: String,
    pub kind: LightKind,
    pub color: Vec3,
    pub intensity: f32,
    pub range: Option<f32>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Projection {
    /// Vertical field of view in radians.
    Perspective { yfov: f32 },
    /// Half the orthographic view height.
    Orthographic { ymag: f32 },
}

#[derive(Debug, Clone)]
pub struct Camera {
    pub name: String,
    pub projection: Projection,
    pub clip: Clip,
}

/// Clip depths along a camera's view axis: surfaces nearer than `near` or farther than `far`
/// are not seen by camera rays (glTF's `znear`/`zfar`). Light still reaches them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Clip {
    pub near: f32,
    /// `f32::INFINITY` for no far plane.
    pub far: f32,
}

impl Default for Clip {
    fn default() -> Self {
        Clip {
            near: 0.0,
            far: f32::INFINITY,
        }
    }
}

/// One glTF file placed in the scene.
#[derive(Debug, Clone)]
pub struct Layer {
    pub path: PathBuf,
    pub transform: DMat4,
    /// Every node of the file, by its index there. Only those of the file's scene (the
    /// subtrees of [`Self::roots`]) keep their mesh, camera and light once the scene is
    /// loaded ([`Scene::load_layers`]); the others still place what refers to them, such as
    /// a skin's joints.
    pub nodes: Vec<Node>,
    /// The root nodes of the scene the file shows (glTF 2.0 §3.5): its `scene`, else
    /// `scenes[0]`; every node without a parent when it has no `scenes`.
    pub roots: Vec<usize>,
    pub meshes: Vec<Mesh>,
    pub skins: Vec<Skin>,
    pub animations: Vec<Animation>,
    pub lights: Vec<Light>,
    pub cameras: Vec<Camera>,
    /// Zero-area triangles dropped on load (reported as a warning).
    pub degenerate_triangles: usize,
    /// The external files the layer's glTF refers to (buffers and images), resolved.
    pub files: Vec<PathBuf>,
    pub warnings: Vec<String>,
}

/// The composed scene: layers plus the global material and texture lists.
#[derive(Debug, Clone)]
pub struct Scene {
    pub layers: Vec<Layer>,
    /// Index 0 is glTF's default material.
    pub materials: Arc<[Material]>,
    pub textures: Arc<[Texture]>,
    /// The camera the job selects: (layer, node) of a glTF camera, or the job's own.
    /// Always present in a scene from [`Scene::load`].
    pub camera: Option<CameraChoice>,
    /// The power of two that every material's emission and every light's intensity in
    /// [`Self::materials`] and [`Self::layers`] has been multiplied by, so that the renderer
    /// works at a level f32 represents with room for squares and sums; a frame's radiance
    /// AOVs are divided by it ([`crate::integrator::FrameImage::unscale`]). 1 for a scene
    /// whose brightest emitter lies within 2^±40 of 1, as nearly every scene does (set by
    /// [`Scene::load`]).
    pub emission_scale: f32,
}

#[derive(Debug, Clone)]
pub enum CameraChoice {
    Node { layer: usize, node: usize },
    LookAt(LookAt),
}

/// A pinhole camera given by position, target and up vector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LookAt {
    /// World space, in f64 like every world transform.
    pub position: DVec3,
    pub look_at: DVec3,
    pub up: Vec3,
    /// Vertical field of view in radians.
    pub yfov: f32,
    pub clip: Clip,
}

/// The camera a scene description asks for.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraSpec {
    /// A glTF camera node by name, searched in layer order.
    Node(String),
    LookAt(LookAt),
}

/// One glTF file of a composition, as a job describes it (like a USD reference).
#[derive(Debug, Clone)]
pub struct LayerDesc {
    pub path: PathBuf,
    /// Applied to the whole layer, cameras and lights included.
    pub transform: DMat4,
    /// Motion tags by node name; they win over tags in the file.
    pub tags: BTreeMap<String, Motion>,
    /// The animation clips that play (names or `animations[i]`); `None`: all.
    pub animations: Option<Vec<String>>,
}

/// What to load: the layers, the camera, and the file that describes them (errors about
/// tags and cameras name it, with `scene[i]` and `camera` keys).
#[derive(Debug, Clone, Copy)]
pub struct SceneDesc<'a> {
    pub file: &'a Path,
    pub layers: &'a [LayerDesc],
    pub camera: Option<&'a CameraSpec>,
}

impl Layer {
    /// Display name of a node for messages: `"Name"` or `nodes[i]`.
    pub fn node_label(&self, i: usize) -> String {
        match self.nodes[i].name.as_str() {
            "" => format!("nodes[{i}]"),
            n => format!("\"{n}\""),
        }
    }

    /// A node as an element of its glTF, for errors and warnings: `nodes[i]`, with its name
    /// where it has one (`nodes[i] "Name"`).
    pub fn node_element(&self, i: usize) -> String {
        match self.nodes[i].name.as_str() {
            "" => format!("nodes[{i}]"),
            name => format!("nodes[{i}] \"{name}\""),
        }
    }

    /// The node a job file names, among those `accept`s: by its name, or as `nodes[i]` (for
    /// unnamed nodes, as `inspect` prints them) when no node has that name. An error text
    /// when there is none, or when several share the name.
    pub fn find_node(&self, name: &str, accept: impl Fn(&Node) -> bool) -> Result<usize, String> {
        let named: Vec<usize> = (0..self.nodes.len())
            .filter(|&i| self.nodes[i].name == name && accept(&self.nodes[i]))
            .collect();
        match named[..] {
            [i] => return Ok(i),
            [] => {}
            _ => {
                let list: Vec<String> = named.iter().map(|i| format!("nodes[{i}]")).collect();
                return Err(format!(
                    "{} nodes are named \"{name}\" in {} ({}); name one as nodes[i]",
                    named.len(),
                    self.path.display(),
                    list.join(", ")
                ));
            }
        }
        name.strip_prefix("nodes[")
            .and_then(|r| r.strip_suffix(']'))
            .and_then(|i| i.parse::<usize>().ok())
            .filter(|&i| i < self.nodes.len() && accept(&self.nodes[i]))
            .ok_or_else(|| format!("no node named \"{name}\" in {}", self.path.display()))
    }

    /// Whether each node is in the layer's scene: in the subtree of one of its
    /// [`Self::roots`] (glTF 2.0 §3.5: only the nodes of the scene are rendered).
    pub fn in_scene(&self) -> Vec<bool> {
        let mut seen = vec![false; self.nodes.len()];
        let mut stack: Vec<usize> = self.roots.clone();
        while let Some(i) = stack.pop() {
            match seen.get_mut(i) {
                Some(s) if !*s => *s = true,
                _ => continue,
            }
            stack.extend(self.nodes[i].children.iter().copied());
        }
        seen
    }

    /// Takes the mesh, camera and light off every node outside the layer's scene
    /// ([`Self::in_scene`]), so that nothing renders, lights the scene or views it from
    /// there, and warns which nodes lost them. The nodes themselves stay, at their indices:
    /// animations may target them and skins use them as joints.
    fn keep_scene(&mut self) {
        let in_scene = self.in_scene();
        let mut left_out = Vec::new();
        for (i, node) in self.nodes.iter_mut().enumerate() {
            if in_scene[i] || (node.mesh.is_none() && node.camera.is_none() && node.light.is_none())
            {
                continue;
            }
            node.mesh = None;
            node.camera = None;
            node.light = None;
            left_out.push(i);
        }
        if left_out.is_empty() {
            return;
        }
        const LISTED: usize = 5;
        let mut names: Vec<String> = left_out
            .iter()
            .take(LISTED)
            .map(|&i| self.node_element(i))
            .collect();
        if left_out.len() > LISTED {
            names.push(format!("{} more", left_out.len() - LISTED));
        }
        let n = left_out.len();
        self.warnings.push(format!(
            "{}: {n} node{} with a mesh, camera or light {} outside the file's scene (its \
             `scene`, else scenes[0]) and not rendered: {}",
            self.path.display(),
            if n == 1 { "" } else { "s" },
            if n == 1 { "is" } else { "are" },
            names.join(", ")
        ));
    }

    /// Keeps the clips a job chooses (all when it chooses none) and warns where kept clips
    /// drive the same property of a node, since only the first in the file can play there.
    fn select_animations(
        &mut self,
        chosen: Option<&[String]>,
        desc_file: &Path,
        layer: usize,
    ) -> Result<()> {
        if let Some(chosen) = chosen {
            let mut keep = vec![false; self.animations.len()];
            for (j, name) in chosen.iter().enumerate() {
                let at = || format!("scene[{layer}].animations[{j}]");
                let named: Vec<usize> = (0..self.animations.len())
                    .filter(|&i| self.animations[i].name == *name)
                    .collect();
                let i = match named[..] {
                    [i] => i,
                    [] => name
                        .strip_prefix("animations[")
                        .and_then(|r| r.strip_suffix(']'))
                        .and_then(|i| i.parse::<usize>().ok())
                        .filter(|&i| i < self.animations.len())
                        .ok_or_else(|| {
                            let all: Vec<&str> =
                                self.animations.iter().map(|a| a.name.as_str()).collect();
                            Error::input(
                                desc_file,
                                at(),
                                format!(
                                    "no animation named \"{name}\" in {} (it has: {})",
                                    self.path.display(),
                                    if all.is_empty() {
                                        "none".to_string()
                                    } else {
                                        all.join(", ")
                                    }
                                ),
                            )
                        })?,
                    _ => {
                        return Err(Error::input(
                            desc_file,
                            at(),
                            format!(
                                "{} animations are named \"{name}\" in {}; name one as animations[i]",
                                named.len(),
                                self.path.display()
                            ),
                        ));
                    }
                };
                keep[i] = true;
            }
            let mut i = 0;
            self.animations.retain(|_| {
                i += 1;
                keep[i - 1]
            });
        }
        let mut first: HashMap<(usize, u8), &str> = HashMap::new();
        let mut fights: BTreeMap<(usize, u8), Vec<&str>> = BTreeMap::new();
        for a in &self.animations {
            for c in &a.channels {
                let key = (c.node, c.property as u8);
                match first.get(&key) {
                    None => {
                        first.insert(key, &a.name);
                    }
                    Some(&f) if f != a.name => {
                        let v = fights.entry(key).or_insert_with(|| vec![f]);
                        if !v.contains(&a.name.as_str()) {
                            v.push(&a.name);
                        }
                    }
                    Some(_) => {}
                }
            }
        }
        let mut warnings = Vec::new();
        for ((node, prop), clips) in &fights {
            let prop = ["translation", "rotation", "scale", "weights"][*prop as usize];
            let node = self.node_element(*node);
            warnings.push(format!(
                "{}: animations {} all drive the {prop} of {node}; only \"{}\" (first in the \
                 file) plays there: choose clips with scene[{layer}].animations",
                self.path.display(),
                clips
                    .iter()
                    .map(|c| format!("\"{c}\""))
                    .collect::<Vec<_>>()
                    .join(", "),
                clips[0],
            ));
        }
        self.warnings.extend(warnings);
        Ok(())
    }

    /// For each node, the first animation that moves it (its own channels or an ancestor's,
    /// or for a skinned mesh, any of its joints).
    fn moved_by(&self) -> Vec<Option<String>> {
        let mut own: HashMap<usize, &str> = HashMap::new();
        for a in &self.animations {
            for c in &a.channels {
                own.entry(c.node).or_insert(&a.name);
            }
        }
        let n = self.nodes.len();
        let mut moved: Vec<Option<String>> = vec![None; n];
        // Top-down over the hierarchy from the roots (and any unparented node).
        let mut stack: Vec<usize> = (0..n).filter(|&i| self.nodes[i].parent.is_none()).collect();
        let mut seen = vec![false; n];
        while let Some(i) = stack.pop() {
            if std::mem::replace(&mut seen[i], true) {
                continue;
            }
            moved[i] = own
                .get(&i)
                .map(|s| s.to_string())
                .or_else(|| self.nodes[i].parent.and_then(|p| moved[p].clone()));
            stack.extend(self.nodes[i].children.iter().copied());
        }
        for i in 0..n {
            if moved[i].is_none()
                && let Some(s) = self.nodes[i].skin
            {
                moved[i] = self.skins[s]
                    .joints
                    .iter()
                    .find_map(|&j| moved.get(j).cloned().flatten());
            }
        }
        moved
    }

    /// Resolves every node's motion (module doc) and rejects static prims that move.
    fn resolve_tags(
        &mut self,
        overrides: &BTreeMap<String, Motion>,
        desc_file: &Path,
        layer: usize,
    ) -> Result<()> {
        let mut by_node: HashMap<usize, Motion> = HashMap::new();
        for (name, &m) in overrides {
            let i = self.find_node(name, |_| true).map_err(|msg| {
                Error::input(desc_file, format!("scene[{layer}].tags.{name}"), msg)
            })?;
            by_node.insert(i, m);
        }
        let moved = self.moved_by();
        let n = self.nodes.len();
        let mut stack: Vec<usize> = (0..n).filter(|&i| self.nodes[i].parent.is_none()).collect();
        // An explicit tag (job or extras) travels down to children: (motion, from whom).
        let mut explicit: Vec<Option<(Motion, String)>> = vec![None; n];
        let mut seen = vec![false; n];
        while let Some(i) = stack.pop() {
            if std::mem::replace(&mut seen[i], true) {
                continue;
            }
            let label = self.node_label(i);
            let node = &self.nodes[i];
            let (motion, why) = if let Some(&m) = by_node.get(&i) {
                (m, TagSource::Job)
            } else if let Some(m) = node.extras_tag {
                (m, TagSource::Extras)
            } else if let Some((m, from)) = node.parent.and_then(|p| explicit[p].clone()) {
                (m, TagSource::Inherited(from))
            } else if let Some(a) = &moved[i] {
                (Motion::Dynamic, TagSource::DefaultAnimated(a.clone()))
            } else {
                (Motion::Static, TagSource::DefaultStatic)
            };
            explicit[i] = match &why {
                TagSource::Job | TagSource::Extras => Some((motion, label.clone())),
                TagSource::Inherited(from) => Some((motion, from.clone())),
                _ => None,
            };
            if motion == Motion::Static
                && node.mesh.is_some()
                && let Some(a) = &moved[i]
            {
                return Err(Error::input(
                    &self.path,
                    format!("nodes[{i}] {label}"),
                    format!(
                        "is tagged static ({why}) but animation \"{a}\" moves it; tag it dynamic"
                    ),
                ));
            }
            let node = &mut self.nodes[i];
            node.motion = motion;
            node.why = why;
            stack.extend(node.children.iter().copied());
        }
        Ok(())
    }

    /// Local transform of node `i` at time `t` (rest TRS overridden by animation channels).
    fn local(&self, i: usize, t: f32, anim: &HashMap<(usize, u8), &anim::Sampler>) -> DMat4 {
        let n = &self.nodes[i];
        let tr = anim
            .get(&(i, 0))
            .map_or(n.translation, |s| s.sample_vec3(t));
        let ro = anim.get(&(i, 1)).map_or(n.rotation, |s| s.sample_quat(t));
        let sc = anim.get(&(i, 2)).map_or(n.scale, |s| s.sample_vec3(t));
        DMat4::from_scale_rotation_translation(sc.as_dvec3(), ro.as_dquat(), tr.as_dvec3())
    }

    fn samplers(&self) -> HashMap<(usize, u8), &anim::Sampler> {
        let mut m = HashMap::new();
        for a in &self.animations {
            for c in &a.channels {
                let key = match c.property {
                    Property::Translation => 0,
                    Property::Rotation => 1,
                    Property::Scale => 2,
                    Property::Weights => 3,
                };
                m.entry((c.node, key)).or_insert(&c.sampler);
            }
        }
        m
    }

    /// World matrix of every node at time `t`, the layer transform included, rounded to
    /// f32 (for reports and tests; rendering uses [`Self::world_matrices_f64`]).
    pub fn world_matrices(&self, t: f32) -> Vec<Mat4> {
        self.world_matrices_f64(t)
            .iter()
            .map(DMat4::as_mat4)
            .collect()
    }

    /// World matrix of every node at time `t`, the layer transform included, composed in
    /// f64: a node 1e6 from the origin keeps the precision of its local transform.
    pub fn world_matrices_f64(&self, t: f32) -> Vec<DMat4> {
        let anim = self.samplers();
        let n = self.nodes.len();
        let mut world = vec![DMat4::IDENTITY; n];
        let mut stack: Vec<(usize, DMat4)> = (0..n)
            .filter(|&i| self.nodes[i].parent.is_none())
            .map(|i| (i, self.transform))
            .collect();
        let mut seen = vec![false; n];
        while let Some((i, parent)) = stack.pop() {
            if std::mem::replace(&mut seen[i], true) {
                continue;
            }
            world[i] = parent * self.local(i, t, &anim);
            for &c in &self.nodes[i].children {
                stack.push((c, world[i]));
            }
        }
        world
    }

    /// World matrix of node `i` at time `t`, composed in f64 as [`Self::world_matrices_f64`]
    /// composes it, from the layer transform down its ancestors.
    fn world_matrix_f64(
        &self,
        i: usize,
        t: f32,
        anim: &HashMap<(usize, u8), &anim::Sampler>,
    ) -> DMat4 {
        let mut chain = vec![i];
        while let Some(p) = self.nodes[*chain.last().unwrap_or(&i)].parent {
            if chain.len() > self.nodes.len() {
                break;
            }
            chain.push(p);
        }
        chain
            .iter()
            .rev()
            .fold(self.transform, |parent, &n| parent * self.local(n, t, anim))
    }

    /// Morph weights of node `i` at time `t`.
    fn morph_weights(
        &self,
        i: usize,
        t: f32,
        anim: &HashMap<(usize, u8), &anim::Sampler>,
    ) -> Vec<f32> {
        let node = &self.nodes[i];
        let mesh = node.mesh.map(|m| &self.meshes[m]);
        let mut w = node
            .weights
            .clone()
            .or_else(|| mesh.map(|m| m.weights.clone()))
            .unwrap_or_default();
        if let Some(s) = anim.get(&(i, 3)) {
            w.resize(s.width, 0.0);
            s.sample(t, false, &mut w);
        }
        w
    }

    /// Animation time range over all channels, if any are animated.
    pub fn time_range(&self) -> Option<(f32, f32)> {
        self.animations
            .iter()
            .flat_map(|a| a.channels.iter())
            .map(|c| c.sampler.range())
            .reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)))
    }
}

impl Scene {
    /// Loads every layer, resolves tags and the camera: everything a render needs.
    pub fn load(desc: &SceneDesc) -> Result<Scene> {
        let mut scene = Scene::load_layers(desc)?;
        if scene.camera.is_none() {
            return Err(Error::input(
                desc.file,
                "camera",
                "the scene has no camera; name one or give one in the job file",
            ));
        }
        let extent = scene.check_extent(desc.file)?;
        scene.normalise_emission(extent);
        Ok(scene)
    }

    /// Sets [`Self::emission_scale`] and scales the emission by it. The level of the scene's
    /// light is its brightest emitter's: an emissive material's radiance, a directional
    /// light's illuminance, a point or spot light's intensity over the square of the scene's
    /// size `extent` (the illuminance it gives at that distance). Where that level lies
    /// beyond 2^±40 of 1 the scale is the power of two that brings it nearest 1, else 1,
    /// which leaves the emission, and the image, as they are.
    ///
    /// Light transport is linear in the emission, and multiplying by a power of two is exact
    /// in floating point (short of overflow and underflow), so the image is the same at any
    /// intensity. Without it, the photon estimates' squared powers overflow f32 once the
    /// light reaches about 2^64 (the example room's lamp at 1.7e21 nits: its indirect light
    /// 12 % off per pixel, at 1.7e38 all of it lost) and the anchors' estimates fail below
    /// about 1e-37.
    fn normalise_emission(&mut self, extent: f64) {
        let materials = self
            .materials
            .iter()
            .map(|m| f64::from(m.emission.max_element()));
        let lights = self.layers.iter().flat_map(|l| &l.lights).map(|l| {
            let level = f64::from(l.color.max_element()) * f64::from(l.intensity);
            match l.kind {
                LightKind::Directional => level,
                LightKind::Point | LightKind::Spot { .. } if extent > 0.0 => {
                    level / (extent * extent)
                }
                LightKind::Point | LightKind::Spot { .. } => level,
            }
        });
        let level = materials.chain(lights).fold(0.0f64, f64::max);
        let exponent = if level > 0.0 && level.is_finite() {
            -level.log2().round()
        } else {
            0.0
        };
        if exponent.abs() <= EMISSION_WINDOW {
            return;
        }
        let scale = 2f64.powf(exponent.clamp(-120.0, 120.0)) as f32;
        self.emission_scale = scale;
        self.materials = self
            .materials
            .iter()
            .map(|m| Material {
                emission: m.emission * scale,
                ..m.clone()
            })
            .collect();
        for light in self.layers.iter_mut().flat_map(|l| &mut l.lights) {
            light.intensity *= scale;
        }
    }

    /// Refuses a scene whose size f32 rendering cannot represent ([`EXTENT_LIMITS`]), or
    /// that lies too far from the world origin for its size to be placed in render space
    /// ([`DISTANCE_LIMIT`]). Its size is the largest side of the world-space box around its
    /// geometry (every prim, at the start of its animation), camera and punctual lights; its
    /// distance, the largest coordinate of that box. Render space is centred on the static
    /// set ([`Self::render_origin`]), so that up to that distance where the scene sits does
    /// not matter, only its size. Returns the size.
    pub fn check_extent(&self, file: &Path) -> Result<f64> {
        let t0 = self.time_range().map_or(0.0, |r| r.0);
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        // The largest coordinate, and the layer it is in (`None`: the job's camera).
        let mut farthest: (f64, Option<usize>) = (0.0, None);
        let mut geometry = false;
        let mut add = |p: DVec3, layer: Option<usize>| {
            lo = lo.min(p);
            hi = hi.max(p);
            let d = p.abs().max_element();
            if d > farthest.0 {
                farthest = (d, layer);
            }
        };
        for (li, layer) in self.layers.iter().enumerate() {
            let world = layer.world_matrices_f64(t0);
            for (i, node) in layer.nodes.iter().enumerate() {
                if let Some(m) = node.mesh {
                    for p in &layer.meshes[m].primitives {
                        geometry |= !p.indices.is_empty();
                        for v in &p.positions {
                            add(world[i].transform_point3(v.as_dvec3()), Some(li));
                        }
                    }
                }
                if node.light.is_some() || node.camera.is_some() {
                    add(world[i].w_axis.truncate(), Some(li));
                }
            }
        }
        if let Some(CameraChoice::LookAt(l)) = &self.camera {
            add(l.position, None);
        }
        let extent = (hi - lo).max_element();
        let (min, max) = EXTENT_LIMITS;
        let why = if !extent.is_finite() && lo.x <= hi.x {
            "is not finite"
        } else if extent > max {
            "is too large: squared distances would overflow f32"
        } else if extent > 0.0 && extent < min {
            "is too small: squared distances would underflow f32"
        } else {
            return self
                .check_distance(file, extent, farthest, geometry)
                .map(|()| extent);
        };
        Err(Error::input(
            file,
            "scene",
            format!(
                "the scene's size, {extent:.3e} units (largest side of the box around its \
                 geometry, camera and lights), {why}; anchorage renders sizes from {min:e} to \
                 {max:e} (wherever the scene sits): scale the layers' transforms into that range"
            ),
        ))
    }

    /// The part of [`Self::check_extent`] that refuses a scene of size `extent` whose
    /// largest coordinate, in the layer `farthest` names, is more than [`DISTANCE_LIMIT`]
    /// times that size; `geometry`: the scene has triangles, so that a size of zero means
    /// that f64 could not tell its points apart.
    fn check_distance(
        &self,
        file: &Path,
        extent: f64,
        farthest: (f64, Option<usize>),
        geometry: bool,
    ) -> Result<()> {
        let (distance, layer) = farthest;
        if !((extent > 0.0 || geometry) && distance > DISTANCE_LIMIT * extent) {
            return Ok(());
        }
        let (at, what) = match layer {
            Some(li) => (
                format!("scene[{li}]"),
                format!(
                    "move scene[{li}] ({}) nearer the origin: its transform's translation, or \
                     its glTF's root nodes",
                    self.layers[li].path.display()
                ),
            ),
            None => (
                "camera.position".to_string(),
                "move the camera nearer the scene".to_string(),
            ),
        };
        Err(Error::input(
            file,
            at,
            format!(
                "the scene lies {distance:.3e} units from the world origin, {:.1e} times its \
                 size ({extent:.3e} units, the largest side of the box around its geometry, \
                 camera and lights); beyond {DISTANCE_LIMIT:e} times its size its positions \
                 cannot be placed precisely in f32 render space: {what}",
                distance / extent,
            ),
        ))
    }

    /// Refuses a camera node that can place no view at one of `frames` (frame numbers with
    /// their times), as [`FrameCamera::placement_error`] says: one scaled to zero, for
    /// instance, would render the frame black. The error names the camera node in its glTF
    /// and the first such frame. A camera the job gives always places a view.
    pub fn check_camera(&self, frames: impl IntoIterator<Item = (i32, f32)>) -> Result<()> {
        let Some(CameraChoice::Node { layer, node }) = self.camera else {
            return Ok(());
        };
        let l = &self.layers[layer];
        let Some(c) = l.nodes[node].camera else {
            return Ok(());
        };
        let clip = l.cameras[c].clip;
        let anim = l.samplers();
        for (frame, t) in frames {
            if let Some(why) =
                FrameCamera::placement_error(l.world_matrix_f64(node, t, &anim), clip)
            {
                return Err(Error::input(
                    &l.path,
                    l.node_element(node),
                    format!("at frame {frame} (t = {t:.4} s): {why}"),
                ));
            }
        }
        Ok(())
    }

    /// Refuses a spot or directional light whose node maps its −Z axis, the way it points, to
    /// zero (a node scaled to zero along it) at one of `frames` (frame numbers with their
    /// times): it would light nothing. The error names the node and the first such frame. A
    /// point light has no direction and is left alone.
    pub fn check_lights(&self, frames: impl IntoIterator<Item = (i32, f32)> + Clone) -> Result<()> {
        for l in &self.layers {
            let anim = l.samplers();
            for (node, n) in l.nodes.iter().enumerate() {
                let Some(light) = n.light else { continue };
                if l.lights[light].kind == LightKind::Point {
                    continue;
                }
                for (frame, t) in frames.clone() {
                    let d = l
                        .world_matrix_f64(node, t, &anim)
                        .transform_vector3(DVec3::NEG_Z);
                    if d.length() > 0.0 && d.is_finite() {
                        continue;
                    }
                    return Err(Error::input(
                        &l.path,
                        l.node_element(node),
                        format!(
                            "at frame {frame} (t = {t:.4} s) this spot or directional light's \
                             node scales its −Z axis, the way the light points, to {d}: it would \
                             light nothing"
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Loads the layers and resolves tags; the camera is resolved where one exists (a camera
    /// the description names must exist). For `inspect`, which also reads scenes without
    /// cameras.
    pub fn load_layers(desc: &SceneDesc) -> Result<Scene> {
        let mut layers = Vec::new();
        let mut materials = vec![Material::default()];
        let mut textures = Vec::new();
        for (li, l) in desc.layers.iter().enumerate() {
            let loaded = gltf::load(
                &l.path,
                gltf::Offsets {
                    materials: materials.len() - 1,
                    textures: textures.len(),
                },
            )?;
            let mut layer = loaded.layer;
            layer.transform = l.transform;
            layer.keep_scene();
            layer.select_animations(l.animations.as_deref(), desc.file, li)?;
            layer.resolve_tags(&l.tags, desc.file, li)?;
            materials.extend(loaded.materials);
            textures.extend(loaded.textures);
            layers.push(layer);
        }
        let camera = match desc.camera {
            Some(CameraSpec::Node(node)) => Some(camera_node(&layers, node, desc.file)?),
            Some(CameraSpec::LookAt(l)) => Some(CameraChoice::LookAt(*l)),
            None => layers.iter().enumerate().find_map(|(li, l)| {
                l.nodes
                    .iter()
                    .position(|n| n.camera.is_some())
                    .map(|ni| CameraChoice::Node {
                        layer: li,
                        node: ni,
                    })
            }),
        };
        Ok(Scene {
            layers,
            materials: materials.into(),
            textures: textures.into(),
            camera,
            emission_scale: 1.0,
        })
    }

    /// Every file the scene was read from: each layer's glTF, then the buffers and images it
    /// refers to, in the order they were read.
    pub fn files(&self) -> impl Iterator<Item = &Path> {
        self.layers.iter().flat_map(|l| {
            std::iter::once(l.path.as_path()).chain(l.files.iter().map(PathBuf::as_path))
        })
    }

    /// All warnings gathered while loading.
    pub fn warnings(&self) -> Vec<String> {
        self.layers
            .iter()
            .flat_map(|l| l.warnings.iter().cloned())
            .collect()
    }

    /// Animation time range over all layers.
    pub fn time_range(&self) -> Option<(f32, f32)> {
        self.layers
            .iter()
            .filter_map(Layer::time_range)
            .reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)))
    }

    /// The materials and textures, shared (no copy).
    pub fn surfaces(&self) -> Surfaces {
        Surfaces {
            materials: self.materials.clone(),
            textures: self.textures.clone(),
        }
    }

    /// World-space triangles of every prim with the given motion at time `t`: skinning
    /// (glTF §3.7.3) and morph targets (§3.7.2.2) applied. Masked triangles are alpha-tested
    /// against the scene's materials.
    pub fn geometry(&self, t: f32, motion: Motion) -> Geometry {
        self.geometry_in(t, motion, DVec3::ZERO)
    }

    /// [`Self::geometry`] in the render space whose origin is the world point `origin`
    /// (transforms composed in f64, `origin` subtracted before rounding to f32).
    pub fn geometry_in(&self, t: f32, motion: Motion, origin: DVec3) -> Geometry {
        let mut g = Geometry {
            alpha: Some(Arc::new(self.surfaces())),
            ..Geometry::default()
        };
        let mut prim_base = 0u32;
        for layer in &self.layers {
            let world = layer.world_matrices_f64(t);
            let anim = layer.samplers();
            for (i, node) in layer.nodes.iter().enumerate() {
                let Some(m) = node.mesh else { continue };
                if node.motion != motion {
                    continue;
                }
                let weights = layer.morph_weights(i, t, &anim);
                let joints: Option<Vec<DMat4>> = node.skin.map(|s| {
                    let skin = &layer.skins[s];
                    skin.joints
                        .iter()
                        .zip(&skin.inverse_bind)
                        .map(|(&j, ib)| world[j] * ib.as_dmat4())
                        .collect()
                });
                for p in &layer.meshes[m].primitives {
                    g.push_primitive(
                        p,
                        world[i],
                        joints.as_deref(),
                        &weights,
                        prim_base + i as u32,
                        origin,
                    );
                }
            }
            prim_base += layer.nodes.len() as u32;
        }
        g
    }

    /// Punctual lights in world space at time `t`.
    pub fn lights(&self, t: f32) -> Vec<PunctualLight> {
        self.lights_in(t, DVec3::ZERO)
    }

    /// Punctual lights at time `t` in the render space whose origin is `origin`.
    pub fn lights_in(&self, t: f32, origin: DVec3) -> Vec<PunctualLight> {
        let mut out = Vec::new();
        for layer in &self.layers {
            let world = layer.world_matrices_f64(t);
            // The job's layer transform converts the file's units; a node's scale does not
            // change its light's range (`KHR_lights_punctual`), the layer's does.
            let units = layer.transform.determinant().abs().cbrt() as f32;
            for (i, node) in layer.nodes.iter().enumerate() {
                if let Some(l) = node.light {
                    out.push(PunctualLight::new(
                        &layer.lights[l],
                        world[i],
                        origin,
                        units,
                    ));
                }
            }
        }
        out
    }

    /// The job's camera at time `t` for an image of `aspect` = width / height, in world
    /// space.
    pub fn camera_at(&self, t: f32, aspect: f32) -> FrameCamera {
        self.camera_in(t, aspect, DVec3::ZERO)
    }

    /// The job's camera in the render space whose origin is `origin`.
    pub fn camera_in(&self, t: f32, aspect: f32, origin: DVec3) -> FrameCamera {
        match self.camera.as_ref().expect("Scene::load requires a camera") {
            CameraChoice::Node { layer, node } => {
                let l = &self.layers[*layer];
                let world = l.world_matrices_f64(t)[*node];
                let cam = &l.cameras[l.nodes[*node].camera.expect("camera node")];
                FrameCamera::from_matrix(world, origin, cam.projection, cam.clip, aspect)
            }
            CameraChoice::LookAt(l) => FrameCamera::look_at(
                (l.position - origin).as_vec3(),
                (l.look_at - origin).as_vec3(),
                l.up,
                l.yfov,
                aspect,
            )
            .with_clip(l.clip),
        }
    }

    /// The world point that is the origin of render space, fixed for a whole render: the
    /// centre of the static set's bounding box (the camera's position at time 0 when there
    /// is no static geometry).
    ///
    /// Vertices, lights and the camera are converted to f32 relative to it, so that a set
    /// 1e6 from the world origin has the precision of one at the origin (f32 spacing there
    /// is 0.0625: a room's lamp merges with its ceiling). It is fixed per render, not per
    /// frame, because the static BVH is built once and the state kept across frames
    /// (anchors, cache records, photons) is stored in render space. It is the static set's
    /// centre rather than the camera's position so that it depends on nothing but the
    /// static set — the same for every chunk of a shot whatever its frame range, unchanged
    /// by camera edits — which is also what invalidates that state when it changes. The
    /// static set is what the render's precision is spent on: its farthest point is its
    /// half-diagonal away, as for the same set modelled around the world origin.
    pub fn render_origin(&self) -> DVec3 {
        let g = self.geometry_in(0.0, Motion::Static, DVec3::ZERO);
        let mut lo = Vec3::splat(f32::MAX);
        let mut hi = Vec3::splat(f32::MIN);
        for t in &g.triangles {
            for v in [t.v0, t.v1, t.v2] {
                lo = lo.min(v.into());
                hi = hi.max(v.into());
            }
        }
        if lo.x > hi.x || !(lo.is_finite() && hi.is_finite()) {
            return match &self.camera {
                Some(_) => self.camera_in(0.0, 1.0, DVec3::ZERO).origin.as_dvec3(),
                None => DVec3::ZERO,
            };
        }
        0.5 * (lo.as_dvec3() + hi.as_dvec3())
    }

    /// Static prims with their BVH, in render space ([`Self::render_origin`]). Static prims
    /// do not move (tag resolution enforces it), so this is evaluated once per render, at any
    /// time.
    pub fn statics(&self) -> StaticSet {
        let origin = self.render_origin();
        StaticSet::with_origin(self.geometry_in(0.0, Motion::Static, origin), origin)
    }

    /// The render-ready scene at time `t`, sharing the static set: the one place a frame's
    /// scene is built. Also returns the seconds spent evaluating the dynamic prims and
    /// building the rest (the dynamic BVH above all).
    pub fn evaluate(
        &self,
        t: f32,
        aspect: f32,
        statics: &StaticSet,
    ) -> (FrameScene, EvaluateTimings) {
        let start = Instant::now();
        let dynamic = self.geometry_in(t, Motion::Dynamic, statics.origin);
        let animation = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let frame = FrameScene::new(
            statics,
            dynamic,
            self.lights_in(t, statics.origin),
            self.camera_in(t, aspect, statics.origin),
            &self.surfaces(),
        );
        let timings = EvaluateTimings {
            animation,
            dynamic_bvh: start.elapsed().as_secs_f64(),
        };
        (frame, timings)
    }
}

/// The camera node a job names, by name or as `nodes[i]`, over every layer: exactly one
/// layer may hold it.
fn camera_node(layers: &[Layer], name: &str, file: &Path) -> Result<CameraChoice> {
    let bad = |message: String| Error::input(file, "camera.node", message);
    let found: Vec<(usize, usize)> = layers
        .iter()
        .enumerate()
        .filter_map(|(li, l)| {
            l.find_node(name, |n| n.camera.is_some())
                .ok()
                .map(|ni| (li, ni))
        })
        .collect();
    match found[..] {
        [(layer, node)] => Ok(CameraChoice::Node { layer, node }),
        [] => {
            // A name shared inside one layer is reported as that layer's error.
            for l in layers {
                if let Err(e) = l.find_node(name, |n| n.camera.is_some())
                    && e.contains("nodes are named")
                {
                    return Err(bad(e));
                }
            }
            // A camera node outside its file's scene lost its camera ([`Layer::keep_scene`]).
            for l in layers {
                if let Ok(ni) = l.find_node(name, |_| true)
                    && !l.in_scene()[ni]
                {
                    return Err(bad(format!(
                        "nodes[{ni}] \"{name}\" of {} lies outside the file's scene (its \
                         `scene`, else scenes[0]), whose cameras are not used",
                        l.path.display()
                    )));
                }
            }
            Err(bad(format!("no camera node named \"{name}\" in the scene")))
        }
        _ => {
            let list: Vec<String> = found
                .iter()
                .map(|(li, ni)| format!("scene[{li}] nodes[{ni}]"))
                .collect();
            Err(bad(format!(
                "{} camera nodes match \"{name}\" ({}); give each a unique name",
                found.len(),
                list.join(", ")
            )))
        }
    }
}

/// Smallest and largest scene size [`Scene::check_extent`] accepts. Measured on the example
/// room (size 6.5, area-lit): it renders right from scale 1e-18 to 1e18 (sizes 6.5e-18 to
/// 6.5e18), and wrong at 1e-19 and 1e19, where squared distances leave f32's range; the
/// limits keep a factor of 1000 for scenes whose details or distances are far smaller or
/// larger than their size.
pub const EXTENT_LIMITS: (f64, f64) = (1e-15, 1e15);

/// How far from the world origin [`Scene::check_extent`] lets a scene lie: its largest
/// coordinate at most this many times its size.
///
/// World positions are composed in f64 and rounded to f32 relative to the render origin
/// ([`Scene::render_origin`]), the centre of the static set's box, which is itself taken
/// from f32 world positions: a scene at distance `d` has its render origin up to about
/// d·2⁻²⁴ off its centre, so its render-space positions are rounded to f32 at that
/// magnitude, an error of about d·2⁻⁴⁸ (f64's own rounding, d·2⁻⁵³, is far smaller). At the
/// limit that is 4e-5 of the scene's size. Measured on an 8-unit room (floor, cube, point
/// light, camera) moved along x, at scales 1e-3, 0.78, 1 and 1e3: the image differs from the
/// one at the origin by a relative RMS of 1e-7 to 1e-6 at 4e8 to 4e9 times its size, 5e-5 to
/// 1e-4 at 4e10, 1.5 % at 4e11 and 1e-4 to 3.5 % at 1.2e12 (the cube's edges move), 37 % at
/// 1.2e14 (the cube is partly lost), and it is black at 1.2e15 (f64's spacing there is a
/// quarter of the room).
/// The limit keeps a factor of 40 below where the error shows, and a factor of 10 above
/// the distance of 1e6 units for scenes 1e-3 units across (the example room at scale 1e-3,
/// 8.5e-3 units across, is 1.2e8 times its size away there).
pub const DISTANCE_LIMIT: f64 = 1e10;

/// The binary orders of magnitude either side of 1 within which a scene's light level
/// leaves its emission unscaled ([`Scene::emission_scale`]). Measured on the example
/// room at draft (its lamp 17 nits, scaled by powers of ten): the cached methods' images
/// are the same to 2e-4 (anchors) and 3e-7 (brute force) relative RMS up to 1e18 times and
/// down to 1e-35 times; squares of the level overflow f32 at 2^64.
pub const EMISSION_WINDOW: f64 = 40.0;

/// Seconds [`Scene::evaluate`] spent.
#[derive(Debug, Clone, Copy, Default)]
pub struct EvaluateTimings {
    /// Animation, skinning and morphing of the dynamic prims.
    pub animation: f64,
    /// Lights, camera, emitters and the dynamic BVH.
    pub dynamic_bvh: f64,
}
