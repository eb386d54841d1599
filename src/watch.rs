//! `anchorage watch`: re-renders a job's frames whenever the job file or a file its scene
//! reads changes, keeping as much of the anchor method's state as the change leaves valid.
//!
//! The files are watched through `notify` with a debouncer: the parent directory of each
//! (non-recursively), filtered by path, so that editors' atomic saves (a delete and a
//! re-create, or a rename over the file) are seen like writes, and a burst of saves is one
//! reload. The set of files is read again after every reload (a glTF edit can add an image).
//!
//! After a reload the old and the new job and scene are compared ([`classify`]) and one rule
//! is chosen for the re-render, the cheapest that stays valid for every change:
//!
//! - **relight** — lights (punctual intensity, colour, placement; emissive materials) or
//!   materials changed: every record, stratum link and anchor is kept and only L_i is
//!   re-estimated from the new photons (§3.3.2); anchors read their albedo again after a
//!   material edit (they store it, §3, and reflect albedo × L_i / π). The state is the one
//!   the same frame left, so no visibility detection is needed and no gather ray is traced
//!   for the cache: strata whose ray hit a dynamic prim (no anchor holds their light) are
//!   estimated again at the hits that frame's render kept. Nor does the shading pass trace
//!   its camera rays and shadow rays again: it replays those that frame's render logged
//!   ([`crate::integrator::replay`]; the log is kept beside the state, within its budget).
//! - **dynamic** — a dynamic prim's geometry or animation changed: the state is kept and the
//!   visibility machinery (§3.2, Pseudocode 2) re-shoots the strata that see a dynamic prim
//!   now or saw one in the state's frame, as from one frame to the next.
//! - **camera** — the camera changed: static records are kept, new ones are placed where
//!   the new view needs them, and those the new view does not use are dropped.
//! - **rebuild** — static geometry, an alpha cut-out material (or its texture: alpha shapes
//!   the geometry rays see), or a setting the cache depends on (method, strata, photons,
//!   resolution, seed, ...), changed, or an edit of the light moved the scene's working
//!   level of emission ([`crate::scene::Scene::emission_scale`], only for light beyond
//!   2^±40 of 1): a fresh state, as `render` starts with.
//!
//! The state of every frame of the range is kept after its render, so that a frame is
//! re-rendered from the state it left itself. Methods without anchors (`brute-force`,
//! `precomputed`) keep no state that a light or material edit leaves valid (their records
//! hold irradiance of the old scene): every change rebuilds them.
//!
//! Bad input never ends the watch: a file that does not load (half-written, deleted) is
//! reported once, the last good scene stays, and the next change that loads renders again.
//! A save that stops a pass and does not load leaves the last good scene the one that pass
//! rendered: the frames it did not reach are rendered with it. A pass that fails (an
//! unwritable output directory) is reported, and the next save renders every frame again,
//! even a save that changes nothing.
//! SIGINT and SIGTERM end it ([`crate::output::install_signal_cleanup`] removes staged temp
//! files, so no signal, even during a render, leaves one behind).

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Debug;
use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use notify::{EventKind, RecursiveMode};
use notify_debouncer_full::{DebounceEventResult, new_debouncer};

use crate::error::{Error, Result};
use crate::geom::Motion;
use crate::integrator::cached::Refresh;
use crate::integrator::replay::{DirectKeys, ShadingLog};
use crate::job::{Job, Method, Overrides};
use crate::pipeline;
use crate::scene::Scene;
use crate::session::{FrameState, Resources};

/// How long a file must be quiet before its changes are acted on: an editor's burst of
/// saves is one reload.
const DEBOUNCE: Duration = Duration::from_millis(300);

/// What `anchorage watch` was asked to do.
#[derive(Debug, Clone)]
pub struct Options {
    pub job: PathBuf,
    pub overrides: Overrides,
    /// Also write a tone-mapped PNG per frame.
    pub preview: bool,
    /// No per-frame lines (the one line per re-render stays).
    pub quiet: bool,
    /// Most bytes the frame states kept between re-renders may hold (default: half of
    /// [`crate::budget::Limit::of_machine`]).
    pub state_memory: Option<u64>,
}

/// How a re-render treats the state, from cheapest to dearest (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Rule {
    Relight,
    Dynamic,
    Camera,
    Rebuild,
}

impl Rule {
    pub fn name(self) -> &'static str {
        match self {
            Rule::Relight => "relight",
            Rule::Dynamic => "dynamic",
            Rule::Camera => "camera",
            Rule::Rebuild => "rebuild",
        }
    }

    fn explain(self, method: Method) -> &'static str {
        match self {
            Rule::Relight => "records, strata links and anchors kept, L_i re-estimated",
            Rule::Dynamic => "state kept, the strata that see dynamic prims re-shot",
            Rule::Camera => "static records kept, new ones placed for the new view",
            Rule::Rebuild if method == Method::Anchors => "fresh state",
            Rule::Rebuild => "fresh state: this method keeps no anchors",
        }
    }
}

/// What changed between two loads of a job, and the rule that handles it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Changes {
    /// What changed, for the log: `light "Key" intensity`, `material "Floor"`, ...
    pub what: Vec<String>,
    pub rule: Rule,
    /// A material changed: anchors read their albedo again.
    pub materials: bool,
}

/// Content hashes of what [`classify`] compares and that is costly to compare otherwise:
/// evaluated geometry, lights and camera per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Signature {
    statics: u64,
    dynamic: BTreeMap<i32, u64>,
    lights: BTreeMap<i32, u64>,
    camera: BTreeMap<i32, u64>,
    textures: Vec<u64>,
}

/// A hasher fed by `Debug` formatting: content equality of the types the scene is made of
/// (which have no `Hash`), exact for floats (`Debug` prints them so that they round-trip).
struct DebugHasher(std::collections::hash_map::DefaultHasher);

impl std::fmt::Write for DebugHasher {
    fn write_str(&mut self, s: &str) -> std::fmt::Result {
        self.0.write(s.as_bytes());
        Ok(())
    }
}

/// Geometry's content: triangles, shading and attributes (its alpha test is the materials',
/// compared on their own).
fn geometry_hash(g: &crate::geom::Geometry) -> u64 {
    debug_hash(&(&g.triangles, &g.shading, &g.attributes))
}

fn debug_hash(v: &impl Debug) -> u64 {
    use std::fmt::Write;
    let mut h = DebugHasher(Default::default());
    let _ = write!(h, "{v:?}");
    h.0.finish()
}

impl Signature {
    pub fn of(job: &Job, scene: &Scene) -> Signature {
        let origin = scene.render_origin();
        let aspect = job.width as f32 / job.height as f32;
        let per_frame = |f: &dyn Fn(f32) -> u64| {
            (job.frames.start..=job.frames.end)
                .map(|fr| (fr, f(job.time_of(fr))))
                .collect::<BTreeMap<_, _>>()
        };
        Signature {
            statics: geometry_hash(&scene.geometry_in(0.0, Motion::Static, origin)),
            dynamic: per_frame(&|t| geometry_hash(&scene.geometry_in(t, Motion::Dynamic, origin))),
            lights: per_frame(&|t| debug_hash(&scene.lights_in(t, origin))),
            camera: per_frame(&|t| debug_hash(&scene.camera_in(t, aspect, origin))),
            textures: scene
                .textures
                .iter()
                .map(|t| {
                    let mut h = std::collections::hash_map::DefaultHasher::new();
                    (t.width, t.height).hash(&mut h);
                    for v in &t.texels {
                        v.to_array().map(f32::to_bits).hash(&mut h);
                    }
                    h.finish()
                })
                .collect(),
        }
    }
}

/// Whether two per-frame hash maps differ on a frame both have.
fn differ(a: &BTreeMap<i32, u64>, b: &BTreeMap<i32, u64>) -> bool {
    a.iter().any(|(f, h)| b.get(f).is_some_and(|g| g != h))
}

/// A job and its scene that loaded, with their signature.
pub struct Loaded {
    pub job: Job,
    pub scene: Scene,
    pub signature: Signature,
}

impl Loaded {
    /// Loads the job and its scene, and checks them as `render` does (the memory estimate
    /// included).
    pub fn load(path: &Path, overrides: &Overrides) -> Result<Loaded> {
        let job = Job::load(path, overrides)?;
        let scene = job.load_scene()?;
        crate::budget::check(&job, &scene, None)?;
        let signature = Signature::of(&job, &scene);
        Ok(Loaded {
            job,
            scene,
            signature,
        })
    }
}

/// The labels of the nodes (of any layer) that have a mesh, move as `motion` says, and
/// differ between the scenes (the node itself or its mesh).
fn changed_prims(old: &Scene, new: &Scene, motion: Motion) -> Vec<String> {
    let mut out = Vec::new();
    for (li, l) in new.layers.iter().enumerate() {
        let ol = old.layers.get(li);
        for (ni, n) in l.nodes.iter().enumerate() {
            let Some(m) = n.mesh else { continue };
            if n.motion != motion {
                continue;
            }
            let same = ol.and_then(|ol| ol.nodes.get(ni)).is_some_and(|on| {
                debug_hash(on) == debug_hash(n)
                    && on.mesh.and_then(|om| ol?.meshes.get(om)).map(debug_hash)
                        == l.meshes.get(m).map(debug_hash)
            });
            if !same {
                out.push(l.node_label(ni));
            }
        }
    }
    out
}

/// What changed from `old` to `new`, and the rule for it ([`Rule`]); `what` is empty when
/// nothing that the render reads changed.
pub fn classify(old: &Loaded, new: &Loaded) -> Changes {
    let (oj, nj) = (&old.job, &new.job);
    let (os, ns) = (&old.scene, &new.scene);
    let (osig, nsig) = (&old.signature, &new.signature);
    let mut what = Vec::new();
    let mut rule = Rule::Relight;
    let mut note = |w: String, r: Rule, rule: &mut Rule| {
        what.push(w);
        *rule = (*rule).max(r);
    };
    // Settings the cache depends on.
    let settings: [(&str, bool); 6] = [
        (
            "scene layers",
            debug_hash(&oj.layers) != debug_hash(&nj.layers),
        ),
        ("resolution", (oj.width, oj.height) != (nj.width, nj.height)),
        (
            "fps",
            (oj.fps, oj.frame_offset) != (nj.fps, nj.frame_offset),
        ),
        ("seed", oj.seed != nj.seed),
        (
            "render settings",
            debug_hash(&oj.render) != debug_hash(&nj.render),
        ),
        ("method", debug_hash(&oj.method) != debug_hash(&nj.method)),
    ];
    for (name, changed) in settings {
        if changed {
            note(format!("setting {name}"), Rule::Rebuild, &mut rule);
        }
    }
    // The state holds light at the old scene's working level.
    if os.emission_scale != ns.emission_scale {
        note(
            format!(
                "light level: emission scaled by {:e} for rendering, was {:e}",
                ns.emission_scale, os.emission_scale
            ),
            Rule::Rebuild,
            &mut rule,
        );
    }
    if osig.statics != nsig.statics {
        let prims = changed_prims(os, ns, Motion::Static);
        if prims.is_empty() {
            note("static geometry".into(), Rule::Rebuild, &mut rule);
        }
        for p in prims {
            note(format!("static prim {p}"), Rule::Rebuild, &mut rule);
        }
    }
    // Lights: the definitions, field by field, then their placement.
    let mut lights_named = false;
    for (li, l) in ns.layers.iter().enumerate() {
        for (i, light) in l.lights.iter().enumerate() {
            let Some(old) = os.layers.get(li).and_then(|ol| ol.lights.get(i)) else {
                note(
                    format!("light \"{}\" added", light.name),
                    Rule::Relight,
                    &mut rule,
                );
                lights_named = true;
                continue;
            };
            let fields = [
                ("intensity", old.intensity != light.intensity),
                ("colour", old.color != light.color),
                ("kind", old.kind != light.kind),
                ("range", old.range != light.range),
            ];
            for (field, changed) in fields {
                if changed {
                    note(
                        format!("light \"{}\" {field}", light.name),
                        Rule::Relight,
                        &mut rule,
                    );
                    lights_named = true;
                }
            }
        }
    }
    if differ(&osig.lights, &nsig.lights) && !lights_named {
        note("light placement".into(), Rule::Relight, &mut rule);
    }
    // Materials: an edit of emission alone is a light's.
    let mut materials = false;
    if os.materials.len() != ns.materials.len() {
        // Prims may have changed materials: where one is cut out, the geometry too.
        let cut_out = os
            .materials
            .iter()
            .chain(ns.materials.iter())
            .any(|m| m.alpha_cutoff.is_some());
        note(
            "materials added or removed".into(),
            if cut_out {
                Rule::Rebuild
            } else {
                Rule::Relight
            },
            &mut rule,
        );
        materials = true;
    } else {
        for (om, nm) in os.materials.iter().zip(ns.materials.iter()) {
            if debug_hash(om) == debug_hash(nm) {
                continue;
            }
            let mut emission_only = om.clone();
            emission_only.emission = nm.emission;
            emission_only.emissive_texture = nm.emissive_texture;
            if om.alpha_cutoff.is_some() || nm.alpha_cutoff.is_some() {
                // A cut-out material's alpha shapes geometry that rays see.
                note(
                    format!("material \"{}\" (alpha cut-out)", nm.name),
                    Rule::Rebuild,
                    &mut rule,
                );
            } else if debug_hash(&emission_only) == debug_hash(nm) {
                note(
                    format!("light \"{}\" (emissive material) emission", nm.name),
                    Rule::Relight,
                    &mut rule,
                );
            } else {
                note(
                    format!("material \"{}\"", nm.name),
                    Rule::Relight,
                    &mut rule,
                );
                materials = true;
            }
        }
    }
    if osig.textures != nsig.textures {
        // A cut-out material's alpha comes from its base colour texture: an edit of that
        // texture changes the geometry that rays see.
        let cut_out = |s: &Scene, t: usize| {
            s.materials.iter().any(|m| {
                m.alpha_cutoff.is_some() && m.base_color_texture.is_some_and(|r| r.texture == t)
            })
        };
        let changed = (0..osig.textures.len().max(nsig.textures.len()))
            .filter(|&t| osig.textures.get(t) != nsig.textures.get(t));
        if changed.clone().any(|t| cut_out(os, t) || cut_out(ns, t)) {
            note(
                "textures (of an alpha cut-out material)".into(),
                Rule::Rebuild,
                &mut rule,
            );
        } else {
            note("textures".into(), Rule::Relight, &mut rule);
        }
        materials = true;
    }
    if differ(&osig.dynamic, &nsig.dynamic) {
        let mut prims = changed_prims(os, ns, Motion::Dynamic);
        for (li, l) in ns.layers.iter().enumerate() {
            for (ai, a) in l.animations.iter().enumerate() {
                let same = os
                    .layers
                    .get(li)
                    .and_then(|ol| ol.animations.get(ai))
                    .is_some_and(|oa| debug_hash(oa) == debug_hash(a));
                if !same {
                    prims.push(format!("animation \"{}\"", a.name));
                }
            }
        }
        if prims.is_empty() {
            note("dynamic geometry".into(), Rule::Dynamic, &mut rule);
        }
        for p in prims {
            let p = if !p.starts_with("animation") {
                format!("dynamic prim {p}")
            } else {
                p
            };
            note(p, Rule::Dynamic, &mut rule);
        }
    }
    if differ(&osig.camera, &nsig.camera) {
        note("camera".into(), Rule::Camera, &mut rule);
    }
    if (oj.frames.start, oj.frames.end) != (nj.frames.start, nj.frames.end) {
        note(
            format!("frames {}-{}", nj.frames.start, nj.frames.end),
            Rule::Dynamic,
            &mut rule,
        );
    }
    let outputs = (&oj.out_dir, &oj.name, oj.exposure) != (&nj.out_dir, &nj.name, nj.exposure);
    if outputs {
        note("output settings".into(), Rule::Relight, &mut rule);
    }
    if nj.method.name != Method::Anchors {
        rule = Rule::Rebuild;
    }
    Changes {
        what,
        rule,
        materials,
    }
}

/// The totals of one pass over the frame range.
#[derive(Debug, Clone, Copy, Default)]
pub struct Pass {
    pub frames: usize,
    pub seconds: f64,
    pub gather_rays: u64,
    /// The last frame rendered when a newer change stopped the pass before the range's end.
    pub interrupted_after: Option<i32>,
    /// Frames whose state was not kept: the states kept already held the state budget.
    pub states_not_kept: usize,
}

/// The render side of a watch: resources and the state each frame left.
pub struct Renderer {
    resources: Option<Resources>,
    /// The state each frame of the range left after its last render, while they fit in
    /// `state_budget` bytes (in frame order: a frame whose state does not fit keeps none,
    /// and is made from the frame before it, as `render` makes it).
    states: BTreeMap<i32, Kept>,
    state_budget: u64,
    /// Seconds per frame of the last pass with a fresh state.
    pub cold_per_frame: Option<f64>,
    /// Counts the passes that changed materials: a kept state from an earlier count (a
    /// frame outside the range then) has anchors with the albedo of older materials.
    materials_epoch: u64,
}

/// A frame's state, the log of its shading pass's rays (which a relight of the frame
/// replays: [`ShadingLog`]; empty where it did not fit the budget), their size
/// ([`FrameState::heap_bytes`], [`ShadingLog::heap_bytes`]) and the materials they were made
/// with ([`Renderer::materials_epoch`]).
struct Kept {
    state: FrameState,
    log: ShadingLog,
    bytes: u64,
    materials_epoch: u64,
}

impl Renderer {
    /// A renderer that keeps frame states up to `state_budget` bytes.
    pub fn new(state_budget: u64) -> Renderer {
        Renderer {
            resources: None,
            states: BTreeMap::new(),
            state_budget,
            cold_per_frame: None,
            materials_epoch: 0,
        }
    }

    /// Renders and writes every frame of `new`'s range from `from` on under `rule` (`None`:
    /// the first render). `previous` is the job the resources were made for. After each frame but the
    /// last, `newer` says whether a newer change is waiting: the pass then stops, and the
    /// states of the frames it did not reach are dropped (they belong to the scene before
    /// this change; the next pass makes those frames from a neighbour's state).
    #[allow(clippy::too_many_arguments)] // the scenes, the rule and how to report
    pub fn pass(
        &mut self,
        previous: Option<&Job>,
        new: &Loaded,
        rule: Option<Rule>,
        materials: bool,
        from: i32,
        preview: bool,
        quiet: bool,
        newer: &mut dyn FnMut() -> bool,
    ) -> Result<Pass> {
        let (job, scene) = (&new.job, &new.scene);
        crate::output::check_output_dir(&job.out_dir)?;
        let fresh = rule.is_none_or(|r| r == Rule::Rebuild) || self.resources.is_none();
        // The rest of a stopped pass: the frames before `from` are this scene's already.
        let resuming = from > job.frames.start;
        if fresh {
            if !resuming {
                self.states.clear();
            }
            let same_visibility = previous.is_some_and(|p| {
                p.method.name == job.method.name && p.render.visibility == job.render.visibility
            });
            self.resources = match self.resources.take() {
                Some(r) if same_visibility => Some(Resources {
                    statics: scene.statics(),
                    visibility: r.visibility,
                }),
                _ => Some(pipeline::new_resources(job, scene)?),
            };
        }
        if materials {
            self.materials_epoch += 1;
        }
        let epoch = self.materials_epoch;
        let resources = self.resources.as_ref().expect("resources made above");
        let max_age = job.method.params().cache.max_age;
        let mut pass = Pass::default();
        // A fresh pass resumed goes on from the state its last frame left, as `render` does.
        let mut carried: Option<FrameState> = (fresh && resuming)
            .then(|| self.states.get(&(from - 1)).map(|k| k.state.clone()))
            .flatten();
        for frame in from.max(job.frames.start)..=job.frames.end {
            let t0 = Instant::now();
            let mut log = ShadingLog::default();
            let (mut state, refresh) = if fresh {
                (carried.take().unwrap_or_default(), Refresh::default())
            } else if let Some(kept) = self.states.remove(&frame) {
                // Taken, not copied: the render leaves the frame's new state (if it fails,
                // the frame has none kept, and its next render starts from a neighbour's).
                let refresh = Refresh {
                    relight_only: rule == Some(Rule::Relight),
                    albedo: kept.materials_epoch != epoch,
                };
                // The render replays the kept log and logs its rays afresh.
                log = kept.log;
                (kept.state, refresh)
            } else if let Some(s) = carried.take() {
                (s, Refresh::default())
            } else {
                // A frame new to the range: the nearest state another frame left.
                let near = self
                    .states
                    .range(..frame)
                    .next_back()
                    .or_else(|| self.states.range(frame..).next())
                    .map(|(_, kept)| kept);
                let albedo = near.is_some_and(|k| k.materials_epoch != epoch);
                (
                    near.map(|k| k.state.clone()).unwrap_or_default(),
                    Refresh {
                        relight_only: false,
                        albedo,
                    },
                )
            };
            let prune = rule == Some(Rule::Camera) && max_age > 0;
            if prune {
                // Unused records count as a frame old; the render marks the ones it uses.
                for r in &mut state.cache.records {
                    r.last_used = frame - 1;
                }
            }
            let mut stats = pipeline::new_stats(job, frame);
            let keys = direct_keys(new, frame);
            let img = pipeline::render_frame_with(
                job,
                scene,
                resources,
                &mut state,
                frame,
                &mut stats,
                refresh,
                Some((&mut log, &keys)),
            )?;
            if prune {
                // Drops the static records the new view did not use (and dynamic ones,
                // which the next update drops anyway).
                state.cache.expire(frame, 0);
            }
            stats.timings_s.total = t0.elapsed().as_secs_f64();
            let written = pipeline::write_frame(job, frame, &img, &mut stats, preview)?;
            pass.frames += 1;
            pass.seconds += stats.timings_s.total;
            pass.gather_rays += stats.counts.rays_shot;
            if !quiet {
                eprintln!(
                    "anchorage: watch: frame {frame}: {:.2} s, {} gather rays -> {}",
                    stats.timings_s.total,
                    stats.counts.rays_shot,
                    written.exr.display()
                );
            }
            let range = job.frames.start..=job.frames.end;
            if !keep(
                &mut self.states,
                self.state_budget,
                frame,
                (&state, log),
                range,
                epoch,
            ) {
                pass.states_not_kept += 1;
            }
            carried = Some(state);
            if frame < job.frames.end && newer() {
                self.states.retain(|&f, _| f <= frame || f > job.frames.end);
                pass.interrupted_after = Some(frame);
                break;
            }
        }
        // States of frames no longer in the range are kept: the range may come back (they
        // count against the budget, and go first when the range's own do not fit; their
        // anchors read their albedo again if materials changed meanwhile).
        if fresh && !resuming && pass.frames > 0 {
            self.cold_per_frame = Some(pass.seconds / pass.frames as f64);
        }
        Ok(pass)
    }
}

/// What frame `frame`'s direct light depends on in `new` besides geometry and camera
/// ([`DirectKeys`]): the lights (punctual lights' placement and definitions, every
/// material's emission, every texture) and each material.
pub fn direct_keys(new: &Loaded, frame: i32) -> DirectKeys {
    let textures = &new.signature.textures;
    // A texture reference with the content of the texture it names.
    let content = |t: &Option<crate::scene::TextureRef>| {
        t.as_ref()
            .map(|t| (format!("{t:?}"), textures.get(t.texture).copied()))
    };
    let emission: Vec<_> = new
        .scene
        .materials
        .iter()
        .map(|m| (m.emission, content(&m.emissive_texture)))
        .collect();
    let normals = |m: &crate::scene::Material| {
        m.normal_texture
            .as_ref()
            .map(|n| (format!("{n:?}"), textures.get(n.texture.texture).copied()))
    };
    DirectKeys {
        lights: debug_hash(&(new.signature.lights.get(&frame), emission)),
        materials: new
            .scene
            .materials
            .iter()
            .map(|m| {
                debug_hash(&(
                    m,
                    content(&m.base_color_texture),
                    content(&m.metallic_roughness_texture),
                    normals(m),
                ))
            })
            .collect(),
        surfaces: new
            .scene
            .materials
            .iter()
            .map(|m| debug_hash(&(normals(m), m.double_sided, m.alpha_cutoff)))
            .collect(),
    }
}

/// Keeps `state` and its shading `log` as `frame`'s in `states` if they fit in `budget`
/// bytes beside the states of the range's other frames, or else the state alone: the other
/// frames' logs make room first, then the states of frames outside `range`; returns
/// whether the state was kept.
/// A frame whose state does not fit keeps none (an older one would belong to another scene).
fn keep(
    states: &mut BTreeMap<i32, Kept>,
    budget: u64,
    frame: i32,
    (state, mut log): (&FrameState, ShadingLog),
    range: std::ops::RangeInclusive<i32>,
    materials_epoch: u64,
) -> bool {
    states.remove(&frame);
    let used = |states: &BTreeMap<i32, Kept>| states.values().map(|k| k.bytes).sum::<u64>();
    let mut bytes = (state.heap_bytes() + log.heap_bytes()) as u64;
    if used(states) + bytes > budget {
        // Logs go before any frame's state does: this frame's, then the others'.
        log = ShadingLog::default();
        bytes = state.heap_bytes() as u64;
        let mut total = used(states) + bytes;
        for k in states.values_mut() {
            if total <= budget {
                break;
            }
            let without = k.state.heap_bytes() as u64;
            total -= k.bytes.saturating_sub(without);
            k.log = ShadingLog::default();
            k.bytes = without;
        }
    }
    while used(states) + bytes > budget {
        match states.keys().copied().find(|f| !range.contains(f)) {
            Some(f) => {
                states.remove(&f);
            }
            None => break,
        }
    }
    let fits = used(states) + bytes <= budget;
    if fits {
        states.insert(
            frame,
            Kept {
                state: state.clone(),
                log,
                bytes,
                materials_epoch,
            },
        );
    }
    fits
}

/// `path` made absolute, its directory resolved (links, `..`) where it exists, so that it
/// compares equal to the paths the watcher reports.
fn normalize(path: &Path) -> PathBuf {
    let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    match (abs.parent(), abs.file_name()) {
        (Some(dir), Some(name)) => std::fs::canonicalize(dir)
            .map(|d| d.join(name))
            .unwrap_or(abs),
        _ => abs,
    }
}

/// Whether a watcher event may mean new content (reads and opens do not).
fn changes_content(kind: &EventKind) -> bool {
    use notify::event::{AccessKind, AccessMode, MetadataKind, ModifyKind};
    match kind {
        EventKind::Access(AccessKind::Close(AccessMode::Write)) => true,
        EventKind::Access(_) => false,
        EventKind::Modify(ModifyKind::Metadata(MetadataKind::AccessTime)) => false,
        _ => true,
    }
}

/// The files a watch follows, and the directories it watches to see them.
struct Watched {
    files: BTreeSet<PathBuf>,
    dirs: BTreeSet<PathBuf>,
}

/// Prints an error once: the same message again (a file still half-written after another
/// save) stays quiet.
#[derive(Default)]
struct Reporter {
    last: Option<String>,
}

impl Reporter {
    /// Errors about the same element of the same file count as one (a file truncated at
    /// another byte by the next save gives another message, not another error).
    fn error(&mut self, e: &Error) {
        let msg = e.to_string();
        let key = match e {
            Error::Input { file, at, .. } => format!("{}: {at}", file.display()),
            _ => msg.clone(),
        };
        if self.last.as_deref() != Some(key.as_str()) {
            eprintln!(
                "anchorage: watch: error: {msg}; keeping the last good scene until the file \
                 loads"
            );
            self.last = Some(key);
        }
    }

    /// A pass that failed (an unwritable output directory, a full disk): always printed,
    /// and the next scene error is printed again.
    fn failed(&mut self, e: &Error) {
        eprintln!("anchorage: watch: error: {e}; every frame is rendered again at the next save");
        self.last = None;
    }

    fn clear(&mut self) {
        self.last = None;
    }
}

/// The files to follow: the job, the layers it names (so that a missing one is seen when it
/// appears) and every file the scene was read from.
fn files_of(job_path: &Path, job: Option<&Job>, scene: Option<&Scene>) -> BTreeSet<PathBuf> {
    let mut files = BTreeSet::from([normalize(job_path)]);
    if let Some(job) = job {
        files.extend(job.layers.iter().map(|l| normalize(&l.path)));
    }
    if let Some(scene) = scene {
        files.extend(scene.files().map(normalize));
    }
    files
}

/// Runs the watch until a signal ends the process; returns only if the watcher itself
/// cannot run.
pub fn run(opts: &Options) -> Result<()> {
    let (tx, rx) = mpsc::channel::<DebounceEventResult>();
    let mut debouncer = new_debouncer(DEBOUNCE, None, tx)
        .map_err(|e| Error::Render(format!("cannot watch files: {e}")))?;
    let mut watched = Watched {
        files: BTreeSet::new(),
        dirs: BTreeSet::new(),
    };
    let mut rewatch = |files: BTreeSet<PathBuf>, watched: &mut Watched| {
        let dirs: BTreeSet<PathBuf> = files
            .iter()
            .filter_map(|f| f.parent().map(Path::to_path_buf))
            .collect();
        for d in watched.dirs.difference(&dirs) {
            let _ = debouncer.unwatch(d);
        }
        let mut now = BTreeSet::new();
        for d in &dirs {
            if watched.dirs.contains(d) || debouncer.watch(d, RecursiveMode::NonRecursive).is_ok() {
                now.insert(d.clone());
            }
        }
        watched.dirs = now;
        watched.files = files;
    };

    let mut reporter = Reporter::default();
    let state_budget = opts
        .state_memory
        .unwrap_or_else(|| crate::budget::Limit::of_machine().map_or(u64::MAX, |l| l.bytes / 2));
    let mut renderer = Renderer::new(state_budget);
    // The last good scene.
    let mut current: Option<Loaded> = None;
    // Frames the last good scene does not show yet.
    let mut owed: Option<Owed> = None;
    let mut reload = true;
    loop {
        if reload {
            reload = false;
            // The pass this reload calls for: its changes, first frame, and the job the
            // resources were made for (`None`: the first render).
            let mut pass: Option<(Option<Changes>, i32, Option<Job>)> = None;
            match Loaded::load(&opts.job, &opts.overrides) {
                Ok(new) => {
                    reporter.clear();
                    rewatch(
                        files_of(&opts.job, Some(&new.job), Some(&new.scene)),
                        &mut watched,
                    );
                    let changes = current.as_ref().map(|old| classify(old, &new));
                    let (changes, from) = match (changes, owed.take()) {
                        (changes, None) | (changes @ None, _) => (changes, new.job.frames.start),
                        // The save that stopped a pass changed nothing: the frames that pass
                        // did not reach still show the scene before it.
                        (Some(c), Some(Owed::Stopped { changes, from })) if c.what.is_empty() => {
                            (changes, from)
                        }
                        (Some(c), Some(Owed::Stopped { .. })) => (Some(c), new.job.frames.start),
                        // The last pass failed (its resources are gone): every frame again,
                        // from a fresh state.
                        (Some(mut c), Some(Owed::Failed)) => {
                            c.what.push("again after a failed pass".into());
                            c.rule = Rule::Rebuild;
                            (Some(c), new.job.frames.start)
                        }
                    };
                    if changes.as_ref().is_some_and(|c| c.what.is_empty()) {
                        eprintln!("anchorage: watch: saved without a change: no re-render");
                    } else {
                        if current.is_none() {
                            for w in new.scene.warnings() {
                                eprintln!("anchorage: warning: {w}");
                            }
                        }
                        pass = Some((changes, from, current.as_ref().map(|c| c.job.clone())));
                    }
                    current = Some(new);
                }
                Err(e) => {
                    reporter.error(&e);
                    // Keep following the last good scene's files, and the job's.
                    let job = Job::load(&opts.job, &opts.overrides).ok();
                    let mut files = files_of(
                        &opts.job,
                        job.as_ref().or(current.as_ref().map(|c| &c.job)),
                        current.as_ref().map(|c| &c.scene),
                    );
                    if let Some(c) = &current {
                        files.extend(files_of(&opts.job, Some(&c.job), None));
                    }
                    rewatch(files, &mut watched);
                    // A pass this save stopped: the last good scene is the one it rendered,
                    // so the frames it did not reach are rendered with that scene.
                    if let (Some(good), Some(Owed::Stopped { changes, from })) = (&current, &owed) {
                        pass = Some((changes.clone(), *from, Some(good.job.clone())));
                    }
                }
            }
            if let (Some((changes, from, previous)), Some(scene)) = (pass, &current) {
                let waiting = Waiting {
                    rx: &rx,
                    files: &watched.files,
                    reload: &mut reload,
                };
                owed = run_pass(
                    &mut renderer,
                    previous.as_ref(),
                    scene,
                    changes.as_ref(),
                    from,
                    opts,
                    waiting,
                    &mut reporter,
                );
            }
            if current.is_none() && watched.dirs.is_empty() {
                return Err(Error::Render(format!(
                    "cannot watch the directory of {}",
                    opts.job.display()
                )));
            }
        }
        if reload {
            continue; // a change came during the pass, which stopped for it
        }
        // Wait for a change to one of the files; drain what else came meanwhile.
        let Ok(first) = rx.recv() else {
            return Err(Error::Render("the file watcher stopped".into()));
        };
        reload = relevant(&first, &watched.files);
        for b in rx.try_iter() {
            reload |= relevant(&b, &watched.files);
        }
    }
}

/// Frames of the last good scene that do not show it yet.
enum Owed {
    /// A newer save stopped the pass for `changes` (`None`: the first render) before frame
    /// `from`.
    Stopped { changes: Option<Changes>, from: i32 },
    /// The last pass failed with an error: the next save renders every frame again, even
    /// one that changes nothing (the cause, such as an unwritable output directory, may lie
    /// outside the files watched).
    Failed,
}

/// Where a pass learns of a newer change: the watcher's events for the files followed; a
/// relevant one sets `reload`.
struct Waiting<'a> {
    rx: &'a mpsc::Receiver<DebounceEventResult>,
    files: &'a BTreeSet<PathBuf>,
    reload: &'a mut bool,
}

/// Renders `new`'s frames from `from` under `changes` ([`Renderer::pass`]), logs the pass
/// or reports its error; returns the frames it leaves owed.
#[allow(clippy::too_many_arguments)] // the scenes, the rule and how to report
fn run_pass(
    renderer: &mut Renderer,
    previous: Option<&Job>,
    new: &Loaded,
    changes: Option<&Changes>,
    from: i32,
    opts: &Options,
    waiting: Waiting,
    reporter: &mut Reporter,
) -> Option<Owed> {
    let mut newer = || {
        *waiting.reload |= waiting.rx.try_iter().any(|b| relevant(&b, waiting.files));
        *waiting.reload
    };
    let rule = changes.map(|c| c.rule);
    let materials = changes.is_some_and(|c| c.materials);
    match renderer.pass(
        previous,
        new,
        rule,
        materials,
        from,
        opts.preview,
        opts.quiet,
        &mut newer,
    ) {
        Ok(p) => {
            log_pass(&new.job, changes, from, &p, renderer);
            p.interrupted_after.map(|f| Owed::Stopped {
                changes: changes.cloned(),
                from: f + 1,
            })
        }
        Err(e) => {
            // The next pass renders from scratch.
            renderer.resources = None;
            reporter.failed(&e);
            Some(Owed::Failed)
        }
    }
}

/// Whether a batch of the watcher's events changed one of `files` (errors count as a
/// change, and are reported).
fn relevant(batch: &DebounceEventResult, files: &BTreeSet<PathBuf>) -> bool {
    match batch {
        Ok(events) => events.iter().any(|ev| {
            changes_content(&ev.event.kind)
                && ev
                    .event
                    .paths
                    .iter()
                    .any(|p| files.contains(p) || files.contains(&normalize(p)))
        }),
        Err(errors) => {
            for e in errors {
                eprintln!("anchorage: watch: warning: file watcher: {e}");
            }
            true
        }
    }
}

/// The one line per re-render: what changed, the rule, frames, seconds, gather rays and the
/// time as a share of a cold render.
fn log_pass(job: &Job, changes: Option<&Changes>, from: i32, p: &Pass, r: &Renderer) {
    let (what, rule) = match changes {
        None => ("first render".to_string(), Rule::Rebuild),
        Some(c) => (c.what.join(", "), c.rule),
    };
    let share = r
        .cold_per_frame
        .filter(|&c| c > 0.0 && p.frames > 0)
        .map(|c| format!("{:.0} %", 100.0 * p.seconds / p.frames as f64 / c))
        .unwrap_or_else(|| "-".into());
    let mut interrupted = p
        .interrupted_after
        .map(|f| format!("; interrupted after frame {f} by a newer change"))
        .unwrap_or_default();
    if p.states_not_kept > 0 {
        interrupted += &format!(
            "; the states of {} frame(s) not kept (over --state-memory)",
            p.states_not_kept
        );
    }
    eprintln!(
        "anchorage: watch: {what} -> rule {} ({}): frames {}-{}, {:.2} s, {} gather rays, {share} \
         of a cold render{interrupted}",
        rule.name(),
        rule.explain(job.method.name),
        from.max(job.frames.start),
        job.frames.end,
        p.seconds,
        p.gather_rays,
    );
}
