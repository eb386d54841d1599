//! Which strata of a static cache record may see a dynamic prim this frame (the paper's
//! §3.2). The paper rasterises the dynamic objects onto a hemisphere map around every cache
//! on the GPU and maps the map's pixels to strata; here the "map" is the stratum grid itself
//! and coverage is decided per (record, triangle) by one conservative rule, [`cover`], that
//! both implementations of [`Visibility`] run: [`CpuVisibility`] in Rust and
//! [`gpu::GpuVisibility`] in WGSL (`shaders/visibility.wgsl`, which mirrors [`cover`]'s
//! tests line by line, one quarter of a cell at a time where the CPU tests a cell's four
//! in SIMD lanes with the same arithmetic).
//!
//! The rule. From the record at x, a triangle's vertices project to unit vectors u₀, u₁, u₂;
//! the projected triangle is the spherical triangle they span (its edges are minor arcs).
//! A stratum (row j of sin²θ ∈ [j/M, (j+1)/M], column k of N) is split 2×2 in θ and φ, and
//! each quarter lies within the cap of half-angle β around its centre direction (Δθ/2 along
//! the meridian plus sin θ₁ · Δφ/2 along the parallel). The stratum is flagged when the cap
//! of one of its quarters meets the spherical triangle: its centre lies inside it, or within
//! β of a vertex, or within β of an edge (the distance to a minor arc is the distance to its
//! great circle inside the arc's lune, else to an end) — and that cap also meets the cap of
//! the prim's bounding sphere. Every direction that hits a triangle lies in a quarter whose
//! cap meets both, so nothing is missed (tested with random rays). A triangle two of whose
//! vertices lie in nearly the same direction from x falls back to its bounding cap (the cap
//! around the vertices' mean direction that reaches the farthest one, convex and so holding
//! the triangle while narrower than 87°), and a wider one to its prim's sphere. Cells are enumerated like a
//! rasteriser's bounding box: rows whose best cell cannot reach the triangle's bounding cap
//! are skipped, and within a row only the columns whose azimuth can reach it are visited
//! (with one column of margin, so the enumeration never decides; the tests do).
//!
//! Closed prims. Where a prim's triangles close up ([`closes_up`]: every edge, named by
//! its ends' positions, walked as often one way as the other), the CPU tests only the
//! triangles that face a record outside the prim's bounding sphere ([`faces_away`]).
//! Crossing such a surface through a triangle that faces the ray's origin adds one to the
//! winding number, through one that faces away takes one off, and the winding number is
//! zero both outside the sphere and beyond the prim's far side: a ray from there that
//! meets a triangle facing away meets one facing the record as well, and the rule flags
//! that one's strata. No orientation, manifold or non-intersecting mesh is assumed. A
//! record inside the sphere (under a box resting on the floor) may see only triangles
//! facing away, and tests them all. Real characters and props close up — CesiumMan,
//! skinned, at every pose (tested), RiggedSimple, AnimatedCube, the Blender exporter's
//! meshes — where Sponza's BoxAnimated does not (46 of its inner box's edges have one
//! side only). The flags are the same or a subset of those every triangle gives, and
//! stay conservative (tested on concave prims wound either way, some around records).
//! The GPU tests every triangle.
//!
//! Clusters. The CPU takes a prim's triangles in runs of [`CLUSTER`], each with a bounding
//! sphere, and passes over a run when the record's bits hold every cell through which it
//! can see a point of that sphere ([`adds_nothing`]): from far away a character's
//! thousands of triangles fall into a few cells, which its first triangles set. The
//! flags stay conservative; beyond the cells a run can be seen through, its triangles
//! could add only cells their bounding caps reach and no ray of the run's meets. A prim of
//! more than [`CLUSTERED`] triangles is taken along a Morton curve through its box, not in
//! the order its mesh lists them, so that a run's triangles lie near one another, and its
//! runs form a tree ([`DynamicSet::clusters`]: [`FAN_OUT`] nodes to a node, each with a
//! sphere) that the CPU walks from the top, passing over a whole node in the same way: a
//! character's far side and the parts its first triangles hid cost one test a node
//! rather than one a run. The same argument keeps the flags conservative.
//!
//! Both implementations share the rule with a *slack* that loosens every comparison (in
//! cosine units, so it must stay small against 1 − cos β of the narrowest quarter): the
//! GPU's slack is three times the CPU's, larger than the rounding differences between the
//! two (fused multiply-add, approximate square roots), so the GPU flags a superset of the
//! CPU's strata that can differ only in cells whose caps graze a triangle within ~3·10⁻⁶
//! (tested: a superset, at most 1 % larger; on the test scenes the same strata or one more
//! in twenty thousand).
//!
//! Alpha cut-outs (glTF `MASK`, and `BLEND` rendered as one) are not seen here: both
//! implementations flag the strata a dynamic triangle covers as if the whole triangle were
//! opaque. That is conservative and changes no pixel: the flags only choose which strata are
//! re-traced, a stratum a cut-out part covers is at worst re-traced needlessly (with the
//! alpha test, which the ray tracer applies to every ray), and a stratum no dynamic triangle
//! covers at all cannot see a dynamic prim through or around a cut-out either.
//!
//! The hemisphere depth maps of anchor bucketing on glossy surfaces (§5.1) live beside it
//! ([`depth`]): the same two implementations on the same device, one closest-hit query per
//! mapped cell instead of one bit per stratum. Every [`Visibility`] hands out its
//! [`depth::DepthMaps`], so depth maps run where visibility runs.

pub mod cpu;
pub mod depth;
pub mod depth_gpu;
pub mod gpu;

use glam::{BVec4A, Vec3, Vec4};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::geom::{Geometry, basis};
pub use cpu::CpuVisibility;
use obvhs::ploc::morton::morton_encode_u64;
use rayon::prelude::*;

/// Why visibility detection could not run.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// No GPU adapter could be opened: the reason, for the log line or the error.
    #[error("{0}")]
    NoAdapter(String),
    /// The adapter opened, but its device could not be created.
    #[error("{adapter}: cannot open the device: {message}")]
    Device { adapter: String, message: String },
    /// The frame's records or dynamic triangles need a buffer larger than the adapter allows.
    #[error(
        "{records} records and {triangles} dynamic triangles exceed the adapter's storage buffer size ({limit} bytes)"
    )]
    TooLarge {
        records: usize,
        triangles: usize,
        limit: u64,
    },
    /// A buffer the GPU needs (named) exceeds the adapter's storage binding size.
    #[error(
        "{what} need {bytes} bytes, more than the adapter's storage buffer binding size ({limit} bytes); --visibility cpu has no such limit"
    )]
    BufferTooLarge {
        what: String,
        bytes: u64,
        limit: u64,
    },
    /// Running the shader or reading its flags back failed.
    #[error("{adapter}: {message}")]
    Gpu { adapter: String, message: String },
}

/// Where visibility detection (§3.2) runs.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema, clap::ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
pub enum VisibilityChoice {
    /// A hardware GPU adapter when there is one, else the CPU (one log line says why).
    #[default]
    Auto,
    /// Any GPU adapter, software ones included; an error when there is none.
    Gpu,
    /// The CPU implementation.
    Cpu,
}

/// The slack of [`CpuVisibility`] (module doc).
pub const CPU_SLACK: f32 = 1e-6;
/// The slack of the GPU implementation: three times the CPU's.
pub const GPU_SLACK: f32 = 3e-6;
/// A triangle's cap is used when its half-angle's cosine exceeds this (about 87°): wider
/// caps are not convex enough to bound the triangle, and its prim's sphere alone decides.
pub const MIN_CAP_COS: f32 = 0.05;

/// A bounding sphere of one dynamic prim.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bound {
    pub centre: Vec3,
    pub radius: f32,
}

/// The dynamic geometry of a frame as visibility sees it: triangles grouped by prim (one
/// glTF node), each prim with a bounding sphere.
#[derive(Debug, Clone, Default)]
pub struct DynamicSet {
    pub prims: Vec<Bound>,
    /// Triangle ranges of the prims, in `triangles`.
    pub ranges: Vec<std::ops::Range<usize>>,
    pub triangles: Vec<[Vec3; 3]>,
    /// Per prim, whether its triangles close up ([`closes_up`]), so that a record outside
    /// its sphere need not test the ones facing away ([`faces_away`]).
    pub closed: Vec<bool>,
    /// Per triangle, its plane for [`faces_away`].
    pub faces: Vec<Face>,
    /// Per prim, a tree of its triangles' runs, each node with a bounding sphere
    /// ([`adds_nothing`]), by levels from the leaves up: level 0 holds runs of at most
    /// [`CLUSTER`] triangles (ranges in `triangles`), each level above runs of at most
    /// [`FAN_OUT`] nodes of the level below (ranges in it), up to a level of at most
    /// [`FAN_OUT`] nodes.
    pub clusters: Vec<Vec<Vec<Node>>>,
}

/// A node of [`DynamicSet::clusters`]: its bounding sphere and what it holds, triangles
/// (level 0) or nodes of the level below.
pub type Node = (Bound, std::ops::Range<usize>);

/// Nodes of the level below that a node of [`DynamicSet::clusters`] above level 0 holds at
/// most. On CesiumMan in Sponza (below, runs of 8) 2 to a node took the stage about as long
/// as 4 (0.33–0.38 s a frame against 0.30–0.38 s, two rounds), where runs alone, along the
/// same curve, took 0.61–0.88 s.
pub const FAN_OUT: usize = 4;

/// Triangles a cluster of [`DynamicSet::clusters`] holds at most: consecutive ones of a
/// prim (along its Morton curve where it has more than [`CLUSTERED`]). A prim of at most
/// [`CLUSTERED`] triangles is one cluster. On CesiumMan in Sponza
/// (`benches/sponza/job_character.json`, frames 1–4, builds alternating), in the order its
/// mesh lists them and without the tree above the runs, runs of 8 took the stage
/// 1.09–1.34 s a frame, of 4 1.37–1.68 s, of 16 1.20–1.54 s and of 32 1.46–2.15 s; runs of
/// 64, 4.2–4.4 s against 32's 3.0–3.9 s in a slower spell. Along the Morton curve, in a tree,
/// runs of 4, 8 and 16 took 0.30–0.42, 0.30–0.38 and 0.34–0.41 s. Sponza's own
/// 62-triangle box in runs of 8 took 0.115–0.125 s a frame against 0.105–0.113 s in runs
/// of 32, and 0.104–0.118 s as one.
pub const CLUSTER: usize = 8;

/// Prims with more triangles than this are split into clusters of [`CLUSTER`].
pub const CLUSTERED: usize = 64;

/// Cells along each axis of the Morton curve that orders a clustered prim's triangles
/// (obvhs's 21-bit codes).
const MORTON_CELLS: u32 = 1 << 21;

/// A bounding sphere of `points`, padded so that rounding cannot shrink it.
fn bound(points: impl Iterator<Item = Vec3>) -> Bound {
    let (lo, hi) = points.fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(lo, hi), v| (lo.min(v), hi.max(v)),
    );
    let centre = 0.5 * (lo + hi);
    let radius = 0.5 * (hi - lo).length() * (1.0 + 1e-5) + centre.abs().max_element() * 1e-6;
    Bound { centre, radius }
}

impl DynamicSet {
    pub fn new(g: &Geometry) -> Self {
        let mut by_prim: std::collections::BTreeMap<u32, Vec<[Vec3; 3]>> =
            std::collections::BTreeMap::new();
        for (t, s) in g.triangles.iter().zip(&g.shading) {
            by_prim
                .entry(s.prim)
                .or_default()
                .push([t.v0.into(), t.v1.into(), t.v2.into()]);
        }
        let mut set = DynamicSet::default();
        for mut tris in by_prim.into_values() {
            let prim = bound(tris.iter().flatten().copied());
            if tris.len() > CLUSTERED {
                // Along a Morton curve through the prim's box, so that each run and each
                // node above it holds triangles near one another.
                let lo = prim.centre - Vec3::splat(prim.radius);
                let scale = MORTON_CELLS as f32 / (2.0 * prim.radius);
                let cell = |v: f32| (v as u32).min(MORTON_CELLS - 1);
                tris.sort_by_cached_key(|t| {
                    let c = ((t[0] + t[1] + t[2]) / 3.0 - lo) * scale;
                    morton_encode_u64(cell(c.x), cell(c.y), cell(c.z))
                });
            }
            set.prims.push(prim);
            set.closed.push(closes_up(&tris));
            set.faces.extend(tris.iter().map(Face::of));
            let start = set.triangles.len();
            let run = if tris.len() > CLUSTERED {
                CLUSTER
            } else {
                tris.len().max(1)
            };
            let mut levels = vec![
                tris.chunks(run)
                    .enumerate()
                    .map(|(i, c)| {
                        let first = start + i * run;
                        (bound(c.iter().flatten().copied()), first..first + c.len())
                    })
                    .collect::<Vec<_>>(),
            ];
            // Triangles a node of the level being made holds (`run` for each cluster).
            let mut size = run;
            while let Some(below) = levels.last().filter(|l| l.len() > FAN_OUT) {
                size *= FAN_OUT;
                let level = (0..below.len())
                    .step_by(FAN_OUT)
                    .enumerate()
                    .map(|(i, first)| {
                        let t = &tris[i * size..((i + 1) * size).min(tris.len())];
                        let last = (first + FAN_OUT).min(below.len());
                        (bound(t.iter().flatten().copied()), first..last)
                    })
                    .collect();
                levels.push(level);
            }
            set.clusters.push(levels);
            set.triangles.extend(tris);
            set.ranges.push(start..set.triangles.len());
        }
        set
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }
}

/// Whether `tris` close up: every edge, as a pair of vertex positions (bit for bit, so
/// that vertices split at seams still join), is traversed as often from one end as from
/// the other, and none has two equal ends. Then the triangles bound their inside
/// consistently (as an integer chain their boundary is zero, whatever the vertex indices,
/// and even where they intersect one another): along a ray from a point outside their
/// bounding sphere, the signed crossings — +1 through a triangle that faces the point,
/// −1 through one that faces away — sum to zero, so a ray that meets one that faces away
/// also meets one that faces the point ([`faces_away`]).
pub fn closes_up(tris: &[[Vec3; 3]]) -> bool {
    // (+ 0.0 turns −0 into +0: the same point.)
    let key = |v: Vec3| v.to_array().map(|c| (c + 0.0).to_bits());
    // Each edge by its ends in order, +1 walked from the lesser end, −1 from the greater,
    // summed over runs of equal ends once sorted (a million triangles: 0.17 s on two cores,
    // where a hash map of the edges took 0.88 s and the whole set 1.12 s a frame).
    let mut edges: Vec<([u32; 6], i32)> = Vec::with_capacity(3 * tris.len());
    for t in tris {
        for e in 0..3 {
            let (a, b) = (key(t[e]), key(t[(e + 1) % 3]));
            let (lo, hi, walk) = match a.cmp(&b) {
                std::cmp::Ordering::Less => (a, b, 1),
                std::cmp::Ordering::Greater => (b, a, -1),
                std::cmp::Ordering::Equal => return false,
            };
            edges.push(([lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]], walk));
        }
    }
    edges.par_sort_unstable_by_key(|e| e.0);
    !tris.is_empty()
        && edges
            .chunk_by(|a, b| a.0 == b.0)
            .all(|same| same.iter().map(|e| e.1).sum::<i32>() == 0)
}

/// What [`faces_away`] reads of a triangle, in f64, made once a frame
/// ([`DynamicSet::faces`]) rather than for every record.
#[derive(Debug, Clone, Copy)]
pub struct Face {
    /// The first corner, and its largest coordinate's magnitude.
    a: glam::DVec3,
    a_max: f32,
    /// The winding's normal (e₁ × e₂, not normalised) and its length.
    n: glam::DVec3,
    n_len: f64,
    /// |e₁|·|e₂|, which bounds the normal's rounding.
    edges: f64,
}

impl Face {
    pub fn of(tri: &[Vec3; 3]) -> Face {
        let [a, b, c] = tri.map(|p| p.as_dvec3());
        let (e1, e2) = (b - a, c - a);
        let n = e1.cross(e2);
        Face {
            a,
            a_max: tri[0].abs().max_element(),
            n,
            n_len: n.length(),
            edges: e1.length() * e2.length(),
        }
    }
}

/// Whether triangle `face` faces away from `x`: `x` lies behind its plane (the side its
/// winding's normal does not point to) by more than rounding could move it, in f64, and
/// by more than the offset a record's rays leave its surface with (`SurfacePoint::spawn`,
/// about 10⁻⁶ of the coordinates; the margin is ten times that). A triangle seen edge-on
/// does not face away.
pub fn faces_away(x: Vec3, face: &Face) -> bool {
    let v = x.as_dvec3() - face.a;
    let margin = 1e-5 * (x.abs().max_element() + face.a_max) as f64;
    v.dot(face.n) < -(margin * face.n_len + 1e-9 * v.length() * face.edges)
}

/// One bit per stratum, index `j·N + k` (θ row j, φ column k), as the gather lays them out.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct StrataBits(pub Vec<u64>);

impl StrataBits {
    pub fn new(n: usize) -> Self {
        StrataBits(vec![0; n.div_ceil(64)])
    }

    pub fn set(&mut self, i: usize) {
        self.0[i / 64] |= 1 << (i % 64);
    }

    pub fn get(&self, i: usize) -> bool {
        self.0.get(i / 64).is_some_and(|w| w >> (i % 64) & 1 == 1)
    }

    pub fn count(&self) -> usize {
        self.0.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// Whether every bit of `other` is set here too.
    pub fn contains(&self, other: &StrataBits) -> bool {
        self.0.iter().zip(&other.0).all(|(a, b)| b & !a == 0)
    }
}

/// Flags strata that may see dynamic prims. Implementations must be conservative (module
/// doc) and lay strata out as the gather does ([`Hemisphere`]).
pub trait Visibility: Send + Sync {
    /// The implementation and, for the GPU, its adapter.
    fn name(&self) -> String;

    /// For each record (position, normal), the strata whose directions may meet a dynamic
    /// triangle.
    fn flag(
        &self,
        records: &[(Vec3, Vec3)],
        strata: [u32; 2],
        set: &DynamicSet,
    ) -> Result<Vec<StrataBits>, Error>;

    /// The depth maps of anchor bucketing (§5.1) on the same device ([`depth`]).
    fn depth_maps(&self) -> &dyn depth::DepthMaps;
}

/// θ limits of row j of M cosine-weighted strata: sin²θ from j/M to (j+1)/M.
fn theta_limits(j: u32, m: u32) -> (f32, f32) {
    (
        (j as f32 / m as f32).sqrt().asin(),
        ((j + 1) as f32 / m as f32).min(1.0).sqrt().asin(),
    )
}

/// A row of strata: its centre elevation and the half-angle β of the cap around any of its
/// cells' centres that holds the whole cell (module doc).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Row {
    pub cos_theta: f32,
    pub sin_theta: f32,
    pub cos_beta: f32,
    pub sin_beta: f32,
}

/// The stratum layout of a record's hemisphere in its local frame (z along the normal,
/// x and y along [`basis`]). Each cell is also split 2×2 (halves in θ and in φ): a cell is
/// flagged when the cap of one of its quarters, half as wide as the cell's, meets a triangle.
#[derive(Debug, Clone)]
pub struct Hemisphere {
    pub m: u32,
    pub n: u32,
    /// Per row: its centre elevation and the half-angle of a cell's cap (for enumeration).
    pub rows: Vec<Row>,
    /// Per half-row `2j + r`: its centre elevation and the half-angle of a quarter's cap.
    pub half_rows: Vec<Row>,
    /// Centre direction of quarter `4(j·N + k) + 2r + q` (θ half r, φ half q), local.
    pub quarters: Vec<Vec3>,
    /// The same four quarters of each cell side by side in SIMD lanes ([`QuarterLanes`]),
    /// for the CPU's tests.
    quarter_lanes: Vec<QuarterLanes>,
    /// Per row: cos β and sin β of the half-row of each of its cells' quarters, in their
    /// lanes (its first half-row's twice, then its second's).
    half_row_lanes: Vec<[Vec4; 2]>,
    /// The rows four at a time in SIMD lanes ([`RowLanes`]), for [`cells_near`].
    row_lanes: Vec<RowLanes>,
}

/// Four rows' [`Row`] values side by side (cos θ, sin θ, cos β, sin β), the last group
/// padded with copies of the last row: [`cells_near`] tests four rows at once, each lane
/// with the arithmetic of the one-row test, so it skips the same rows.
#[derive(Debug, Clone, Copy)]
struct RowLanes([Vec4; 4]);

/// The centres of a cell's four quarters in SIMD lanes: x, y and z, each in the order of
/// [`Hemisphere::quarters`]. [`cover`] and [`adds_nothing`] test the four at once, each
/// lane with the arithmetic the one-quarter test uses (the same products and sums in the
/// same order, so the same bits). Four quarters cost about what one costs in scalar, where
/// a scalar loop saves only the quarters after the first that passes.
#[derive(Debug, Clone, Copy)]
struct QuarterLanes([Vec4; 3]);

impl QuarterLanes {
    /// Each quarter's centre dotted with `v`, as `Vec3::dot` sums it.
    #[inline(always)]
    fn dot(&self, v: Vec3) -> Vec4 {
        self.0[0] * Vec4::splat(v.x) + self.0[1] * Vec4::splat(v.y) + self.0[2] * Vec4::splat(v.z)
    }
}

fn row(theta: f32, beta: f32) -> Row {
    Row {
        cos_theta: theta.cos(),
        sin_theta: theta.sin(),
        cos_beta: beta.cos(),
        sin_beta: beta.sin(),
    }
}

fn direction(theta: f32, phi: f32) -> Vec3 {
    Vec3::new(
        theta.sin() * phi.cos(),
        theta.sin() * phi.sin(),
        theta.cos(),
    )
}

impl Hemisphere {
    pub fn new([m, n]: [u32; 2]) -> Self {
        let dphi = 2.0 * std::f32::consts::PI / n as f32;
        let mut h = Hemisphere {
            m,
            n,
            rows: Vec::new(),
            half_rows: Vec::new(),
            quarters: Vec::new(),
            quarter_lanes: Vec::new(),
            half_row_lanes: Vec::new(),
            row_lanes: Vec::new(),
        };
        for j in 0..m {
            let (t0, t1) = theta_limits(j, m);
            h.rows.push(row(
                0.5 * (t0 + t1),
                0.5 * (t1 - t0) + t1.sin() * 0.5 * dphi,
            ));
            let tm = 0.5 * (t0 + t1);
            for (a, b) in [(t0, tm), (tm, t1)] {
                h.half_rows
                    .push(row(0.5 * (a + b), 0.5 * (b - a) + b.sin() * 0.25 * dphi));
            }
            for k in 0..n {
                for (a, b) in [(t0, tm), (tm, t1)] {
                    for q in 0..2 {
                        let phi = (k as f32 + 0.25 + 0.5 * q as f32) * dphi;
                        h.quarters.push(direction(0.5 * (a + b), phi));
                    }
                }
            }
            let [r0, r1] = [
                &h.half_rows[2 * j as usize],
                &h.half_rows[2 * j as usize + 1],
            ];
            h.half_row_lanes.push([
                Vec4::new(r0.cos_beta, r0.cos_beta, r1.cos_beta, r1.cos_beta),
                Vec4::new(r0.sin_beta, r0.sin_beta, r1.sin_beta, r1.sin_beta),
            ]);
        }
        h.row_lanes = (0..h.rows.len().div_ceil(4))
            .map(|g| {
                let row = |i: usize| h.rows[(4 * g + i).min(h.rows.len() - 1)];
                let lanes = [0, 1, 2, 3].map(row);
                RowLanes([
                    Vec4::from_array(lanes.map(|r| r.cos_theta)),
                    Vec4::from_array(lanes.map(|r| r.sin_theta)),
                    Vec4::from_array(lanes.map(|r| r.cos_beta)),
                    Vec4::from_array(lanes.map(|r| r.sin_beta)),
                ])
            })
            .collect();
        h.quarter_lanes = h
            .quarters
            .chunks_exact(4)
            .map(|q| {
                QuarterLanes([0, 1, 2].map(|a| Vec4::from_array([0, 1, 2, 3].map(|i| q[i][a]))))
            })
            .collect();
        h
    }

    /// Cells (strata).
    pub fn len(&self) -> usize {
        (self.m * self.n) as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A record's position and tangent frame.
#[derive(Debug, Clone, Copy)]
pub struct RecordFrame {
    pub x: Vec3,
    pub t: Vec3,
    pub b: Vec3,
    pub n: Vec3,
}

impl RecordFrame {
    pub fn new(x: Vec3, n: Vec3) -> Self {
        let (t, b) = basis(n);
        RecordFrame { x, t, b, n }
    }

    fn local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.t), v.dot(self.b), v.dot(self.n))
    }
}

/// A cap of directions: local axis and the cosine and sine of its half-angle.
#[derive(Debug, Clone, Copy)]
struct Cap {
    axis: Vec3,
    cos: f32,
    sin: f32,
}

/// cos(a + b) from the cosines and sines of a, b ∈ [0, π]; −1 past π.
fn cos_sum(ca: f32, sa: f32, cb: f32, sb: f32) -> f32 {
    if sa * cb + ca * sb < 0.0 {
        -1.0
    } else {
        ca * cb - sa * sb
    }
}

/// [`cos_sum`] of one angle's cosine and sine against four others', lane by lane (the
/// same operations, so the same values).
#[inline(always)]
fn cos_sum4(ca: f32, sa: f32, cb: Vec4, sb: Vec4) -> Vec4 {
    let (ca, sa) = (Vec4::splat(ca), Vec4::splat(sa));
    Vec4::select(
        (sa * cb + ca * sb).cmplt(Vec4::ZERO),
        Vec4::splat(-1.0),
        ca * cb - sa * sb,
    )
}

/// Whether a cell centre `c` of `row` lies within the cap grown by the row's β.
fn overlaps(cap: &Cap, row: &Row, c: Vec3, slack: f32) -> bool {
    c.dot(cap.axis) >= cos_sum(cap.cos, cap.sin, row.cos_beta, row.sin_beta) - slack
}

/// [`overlaps`] for the four quarters of a cell, in their lanes: the cap, and the
/// thresholds [`RowCap::of`] found for the cell's row.
#[derive(Debug, Clone, Copy)]
struct RowCap {
    axis: Vec3,
    at_least: Vec4,
}

impl RowCap {
    /// `cap` in row `j`: the threshold of [`overlaps`] for each quarter's half-row.
    #[inline(always)]
    fn of(cap: &Cap, h: &Hemisphere, j: usize, slack: f32) -> RowCap {
        let [cos_beta, sin_beta] = h.half_row_lanes[j];
        RowCap {
            axis: cap.axis,
            at_least: cos_sum4(cap.cos, cap.sin, cos_beta, sin_beta) - Vec4::splat(slack),
        }
    }

    /// The quarters of `q` that [`overlaps`] passes.
    #[inline(always)]
    fn overlaps(&self, q: &QuarterLanes) -> BVec4A {
        q.dot(self.axis).cmpge(self.at_least)
    }
}

/// What a prim's bounding sphere looks like from a record ([`sphere_cap`]).
#[derive(Debug, Clone, Copy)]
pub enum PrimCap {
    /// Wholly below the record's horizon: the prim cannot be seen.
    Below,
    /// The record lies inside the sphere: no cap bounds the prim.
    Around,
    /// The cap of directions the sphere spans.
    Cap(SphereCap),
}

impl PrimCap {
    /// The cap [`cover`] takes, or `None` when the prim cannot be seen at all.
    pub fn visible(self) -> Option<Option<SphereCap>> {
        match self {
            PrimCap::Below => None,
            PrimCap::Around => Some(None),
            PrimCap::Cap(c) => Some(Some(c)),
        }
    }
}

/// The cap of a prim's bounding sphere seen from `f`.
pub fn sphere_cap(f: &RecordFrame, prim: Bound, slack: f32) -> PrimCap {
    let v = prim.centre - f.x;
    let d = v.length();
    if d <= prim.radius * (1.0 + slack) {
        return PrimCap::Around;
    }
    let sin = prim.radius / d;
    let cap = Cap {
        axis: f.local(v / d),
        cos: (1.0 - sin * sin).max(0.0).sqrt(),
        sin,
    };
    if cap.axis.z < -cap.sin - slack {
        return PrimCap::Below;
    }
    PrimCap::Cap(SphereCap(cap))
}

/// A triangle projected onto the unit sphere around a record (local frame), for the exact
/// test of a cell's cap against it: vertices, edge-plane normals and the tangents that bound
/// each edge's lune.
#[derive(Debug, Clone, Copy)]
struct SphericalTriangle {
    u: [Vec3; 3],
    /// Unit normal of each edge's great circle, signed so that the triangle lies on its
    /// positive side (zero sign when the triangle is seen edge-on: no interior).
    normal: [Vec3; 3],
    inside_sign: f32,
    /// n × a and b × n for edge (a, b): c lies in the edge's lune when both dot c ≥ 0.
    tangents: [[Vec3; 2]; 3],
}

impl SphericalTriangle {
    /// `None` when two vertices project to nearly the same direction (no reliable edge
    /// plane; the threshold grows with the slack so that the GPU gives up whenever the CPU
    /// does).
    fn new(u: [Vec3; 3], slack: f32) -> Option<Self> {
        let mut normal = [Vec3::ZERO; 3];
        let mut tangents = [[Vec3::ZERO; 2]; 3];
        for e in 0..3 {
            let (a, b) = (u[e], u[(e + 1) % 3]);
            let cross = a.cross(b);
            let l = cross.length();
            if l < 10.0 * slack {
                return None;
            }
            normal[e] = cross / l;
            tangents[e] = [normal[e].cross(a), b.cross(normal[e])];
        }
        let det = u[0].dot(u[1].cross(u[2]));
        let inside_sign = if det > 0.0 {
            1.0
        } else if det < 0.0 {
            -1.0
        } else {
            0.0
        };
        Some(SphericalTriangle {
            u,
            normal,
            inside_sign,
            tangents,
        })
    }

    /// Whether the cap of `row`'s β around cell centre `c` meets the spherical triangle: `c`
    /// inside it, a vertex within β, or an edge within β (the distance to a minor arc is to
    /// its great circle inside the arc's lune, else to an end). The CPU runs
    /// [`SphericalTriangle::near4`], four quarters at once; this one quarter at a time, as
    /// the shader does, is the tests' reference for it.
    #[cfg(test)]
    fn near(&self, row: &Row, c: Vec3, slack: f32) -> bool {
        if self.u.iter().any(|&u| c.dot(u) >= row.cos_beta - slack) {
            return true;
        }
        if self.inside_sign != 0.0
            && self
                .normal
                .iter()
                .all(|&n| self.inside_sign * c.dot(n) >= -slack)
        {
            return true;
        }
        if row.cos_beta <= 0.0 {
            return true;
        }
        (0..3).any(|e| {
            c.dot(self.tangents[e][0]) >= -slack
                && c.dot(self.tangents[e][1]) >= -slack
                && c.dot(self.normal[e]).abs() <= row.sin_beta + slack
        })
    }

    /// Whether `SphericalTriangle::near` (the tests' one-quarter reference) holds for one
    /// of the `active` quarters of a cell of row `j`: the same tests in the quarters' lanes,
    /// in stages, each stage skipped once one passes.
    #[inline(always)]
    fn near4(
        &self,
        h: &Hemisphere,
        j: usize,
        q: &QuarterLanes,
        slack: f32,
        active: BVec4A,
    ) -> bool {
        let [cos_beta, sin_beta] = h.half_row_lanes[j];
        let reach = cos_beta - Vec4::splat(slack);
        let vertex = self
            .u
            .iter()
            .fold(BVec4A::splat(false), |m, &u| m | q.dot(u).cmpge(reach));
        if (vertex & active).any() {
            return true;
        }
        let out = Vec4::splat(-slack);
        if self.inside_sign != 0.0 {
            let sign = Vec4::splat(self.inside_sign);
            let inside = self
                .normal
                .iter()
                .fold(active, |m, &n| m & (sign * q.dot(n)).cmpge(out));
            if inside.any() {
                return true;
            }
        }
        if (cos_beta.cmple(Vec4::ZERO) & active).any() {
            return true;
        }
        let width = sin_beta + Vec4::splat(slack);
        (0..3).any(|e| {
            let [ta, tb] = self.tangents[e];
            (active
                & q.dot(ta).cmpge(out)
                & q.dot(tb).cmpge(out)
                & q.dot(self.normal[e]).abs().cmple(width))
            .any()
        })
    }
}

/// A prim's sphere cap, from [`sphere_cap`].
#[derive(Debug, Clone, Copy)]
pub struct SphereCap(Cap);

/// The tests [`cover`] runs on a triangle's cells (module doc): the cells a quarter of
/// which passes every test that is there, among those [`cells_near`] enumerates around
/// `cull`.
struct CellTests {
    cull: Cap,
    tri_cap: Option<Cap>,
    exact: Option<SphericalTriangle>,
    sphere: Option<Cap>,
}

impl CellTests {
    /// The tests of triangle `tri` seen from `f`, its prim's cap `sphere`; `None` where no
    /// cell needs one: the triangle lies wholly below the tangent plane (no direction of
    /// the hemisphere reaches it), or neither cap bounds it (every cell may see it, and
    /// this sets every cell of `bits`).
    #[inline(always)]
    fn of(
        h: &Hemisphere,
        f: &RecordFrame,
        sphere: Option<SphereCap>,
        tri: &[Vec3; 3],
        slack: f32,
        bits: &mut StrataBits,
    ) -> Option<CellTests> {
        let sphere = sphere.map(|s| s.0);
        let rel = tri.map(|p| p - f.x);
        let len = rel.map(Vec3::length);
        if (0..3).all(|i| rel[i].dot(f.n) < -slack * len[i]) {
            return None;
        }
        let mut tri_cap = None;
        let mut exact = None;
        if len.iter().all(|&l| l > 0.0) {
            let u = [rel[0] / len[0], rel[1] / len[1], rel[2] / len[2]];
            let w = u[0] + u[1] + u[2];
            let wl = w.length();
            if wl > 0.0 {
                let a = w / wl;
                let cos = a.dot(u[0]).min(a.dot(u[1])).min(a.dot(u[2]));
                if cos > MIN_CAP_COS + slack {
                    tri_cap = Some(Cap {
                        axis: f.local(a),
                        cos,
                        sin: (1.0 - cos * cos).max(0.0).sqrt(),
                    });
                    exact = SphericalTriangle::new(u.map(|v| f.local(v)), slack);
                }
            }
        }
        let Some(cull) = tri_cap.or(sphere) else {
            (0..h.len()).for_each(|c| bits.set(c));
            return None;
        };
        Some(CellTests {
            cull,
            tri_cap,
            exact,
            sphere,
        })
    }
}

/// Sets the bit of every cell of `h` that triangle `tri` may cover from `f` (module doc),
/// given its prim's cap from [`sphere_cap`]. A cell already set (by an earlier triangle of
/// the record) is not tested again: the bits are the union over the triangles either way,
/// and a closed mesh's triangles overlap in projection, its far side behind its near side.
/// A cell's four quarters are tested at once, in SIMD lanes.
pub fn cover(
    h: &Hemisphere,
    f: &RecordFrame,
    sphere: Option<SphereCap>,
    tri: &[Vec3; 3],
    slack: f32,
    bits: &mut StrataBits,
) {
    let Some(CellTests {
        cull,
        tri_cap,
        exact,
        sphere,
    }) = CellTests::of(h, f, sphere, tri, slack, bits)
    else {
        return;
    };
    // The caps' thresholds in the row being visited (cells come row by row).
    let mut row = usize::MAX;
    let (mut tri_row, mut sphere_row) = (None, None);
    cells_near(h, &cull, slack, |j, cell| {
        if bits.get(cell) {
            return true;
        }
        if j != row {
            row = j;
            tri_row = tri_cap.map(|c| RowCap::of(&c, h, j, slack));
            sphere_row = sphere.map(|c| RowCap::of(&c, h, j, slack));
        }
        // The quarters that pass every test (a cap that is not there passes them all).
        let q = &h.quarter_lanes[cell];
        let mut pass = BVec4A::splat(true);
        if let Some(cap) = &tri_row {
            pass &= cap.overlaps(q);
            if !pass.any() {
                return true;
            }
        }
        if let Some(cap) = &sphere_row {
            pass &= cap.overlaps(q);
            if !pass.any() {
                return true;
            }
        }
        if exact.as_ref().is_none_or(|t| t.near4(h, j, q, slack, pass)) {
            bits.set(cell);
        }
        true
    });
}

/// [`cover`]'s tests `t` as the GPU runs them: every cell of `h`, one quarter at a time,
/// each test in scalar arithmetic. [`cover`] must set the same bits.
#[cfg(test)]
fn cover_every_cell(h: &Hemisphere, t: &CellTests, slack: f32, bits: &mut StrataBits) {
    for cell in 0..h.len() {
        let j = cell / h.n as usize;
        if (0..4).any(|i| {
            let c = h.quarters[4 * cell + i];
            let half = &h.half_rows[2 * j + i / 2];
            t.tri_cap.is_none_or(|cap| overlaps(&cap, half, c, slack))
                && t.exact.as_ref().is_none_or(|e| e.near(half, c, slack))
                && t.sphere.is_none_or(|cap| overlaps(&cap, half, c, slack))
        }) {
            bits.set(cell);
        }
    }
}

/// Whether `bits` already holds every cell through which `f` can see a point of `ball`
/// (so that [`CpuVisibility`] passes over the triangles within it): the cells with a
/// quarter whose cap (module doc: it holds the whole quarter) meets the ball's cap of
/// directions, grown by about 10⁻³ (at least 9.4·10⁻⁴ in f32, far more than rounding
/// moves either side). What [`cover`] would add for those triangles beyond them lies
/// outside every direction that meets one, so the flags stay conservative. Only for balls
/// seen narrower than 60°.
pub fn adds_nothing(
    h: &Hemisphere,
    f: &RecordFrame,
    ball: Bound,
    slack: f32,
    bits: &StrataBits,
) -> bool {
    let Some(cap) = ball_cap(f, ball) else {
        return false;
    };
    let mut adds = false;
    // The cap's thresholds in the row being visited.
    let mut row: Option<(usize, RowCap)> = None;
    cells_near(h, &cap, slack, |j, cell| {
        if !bits.get(cell) {
            let at = match row {
                Some((r, at)) if r == j => at,
                _ => row.insert((j, RowCap::of(&cap, h, j, slack))).1,
            };
            adds = at.overlaps(&h.quarter_lanes[cell]).any();
        }
        !adds
    });
    !adds
}

/// The cap of directions from `f` to `ball`, grown as [`adds_nothing`] grows it; `None`
/// where the ball is seen 60° wide or more.
#[inline(always)]
fn ball_cap(f: &RecordFrame, ball: Bound) -> Option<Cap> {
    let v = ball.centre - f.x;
    let d = v.length();
    let sin = ball.radius / d;
    // (Also `None` where the record lies in the ball, or d is zero or not finite.)
    if !(sin < 0.5) {
        return None;
    }
    // The ball's half-angle α grown by g = 10⁻³: cos(α + g) and sin(α + g) from cos α and
    // sin α (cos g rounds to cos 9.8·10⁻⁴ in f32).
    let (cos_g, sin_g) = (0.999_999_5_f32, 0.000_999_999_8_f32);
    let cos = (1.0 - sin * sin).sqrt();
    Some(Cap {
        axis: f.local(v / d),
        cos: cos * cos_g - sin * sin_g,
        sin: sin * cos_g + cos * sin_g,
    })
}

/// [`adds_nothing`]'s test over every cell of `h`, one quarter at a time in scalar
/// arithmetic, for the ball's grown `cap` ([`ball_cap`]).
#[cfg(test)]
fn cap_adds_nothing(h: &Hemisphere, cap: &Cap, slack: f32, bits: &StrataBits) -> bool {
    (0..h.len()).all(|cell| {
        let j = cell / h.n as usize;
        bits.get(cell)
            || !(0..4).any(|i| {
                let half = &h.half_rows[2 * j + i / 2];
                overlaps(cap, half, h.quarters[4 * cell + i], slack)
            })
    })
}

/// `x.acos()` for `x` in [-1, 1] or a little more, never less (within 2·10⁻⁴): Abramowitz
/// and Stegun's 4.4.45, √(1 − |x|) times a cubic, off by at most 6.7·10⁻⁵, plus 10⁻⁴ for
/// that and for rounding. [`cells_near`] widens a row's columns by it, which only adds
/// columns its visitor tests (`acosf` took a tenth of `cover`'s samples on a character's
/// triangles; CesiumMan in Sponza: the stage 1.02–1.16 s a frame against 1.11–1.37 s, the
/// same flags). Lane by lane, for the four rows [`cells_near`] takes at once.
fn acos_above(x: Vec4) -> Vec4 {
    let a = x.abs();
    let r = (Vec4::ONE - a).max(Vec4::ZERO).sqrt()
        * (((Vec4::splat(-0.018_729_3) * a + Vec4::splat(0.074_261)) * a
            - Vec4::splat(0.212_114_4))
            * a
            + Vec4::splat(1.570_728_8));
    Vec4::select(
        x.cmplt(Vec4::ZERO),
        Vec4::splat(std::f32::consts::PI) - r,
        r,
    ) + Vec4::splat(1e-4)
}

/// The most [`atan2_near`] lies from `atan2`, with room for rounding.
const ATAN2_ERROR: f32 = 2e-5;

/// `y.atan2(x)` within [`ATAN2_ERROR`] (0 where both are 0): Abramowitz and Stegun's
/// 4.4.47, a polynomial off by at most 10⁻⁵ on [0, 1], of the tangent of the angle to the
/// nearer axis. [`cells_near`] widens a row's columns by the error, which only adds
/// columns its visitor tests; it replaces `atan2f`, which the stage called once per record
/// and triangle or run.
fn atan2_near(y: f32, x: f32) -> f32 {
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = (ax.min(ay), ax.max(ay));
    let t = if hi > 0.0 { lo / hi } else { 0.0 };
    let t2 = t * t;
    let mut a = t
        * (0.999_866
            + t2 * (-0.330_299_5 + t2 * (0.180_141 + t2 * (-0.085_133 + t2 * 0.020_835_1))));
    if ay > ax {
        a = std::f32::consts::FRAC_PI_2 - a;
    }
    if x < 0.0 {
        a = std::f32::consts::PI - a;
    }
    if y < 0.0 { -a } else { a }
}

/// `x.floor() as i32` for `|x|` below 2³¹, without the call to `floorf` that `f32::floor`
/// compiles to where SSE4.1 is not assumed.
fn floor(x: f32) -> i32 {
    let t = x as i32;
    if (t as f32) > x { t - 1 } else { t }
}

/// `x.ceil() as i32` for `|x|` below 2³¹, as [`floor`].
fn ceil(x: f32) -> i32 {
    let t = x as i32;
    if (t as f32) < x { t + 1 } else { t }
}

/// Visits `(row, cell)` for the cells of `h` that a quarter's cap meeting `cull` may lie
/// in, row by row like a rasteriser's bounding box (module doc): the rows whose best cell
/// can reach the cap, and in each the columns whose azimuth can, with one column of margin
/// (the visitor's tests decide). `visit` returns false to stop.
#[inline(always)]
fn cells_near(h: &Hemisphere, cull: &Cap, slack: f32, mut visit: impl FnMut(usize, usize) -> bool) {
    let n = h.n as i32;
    let dphi = 2.0 * std::f32::consts::PI / h.n as f32;
    let rho = (cull.axis.x * cull.axis.x + cull.axis.y * cull.axis.y).sqrt();
    let phi_w = atan2_near(cull.axis.y, cull.axis.x);
    // Four rows at a time: the rows whose best cell can reach the cap (with margin beyond
    // the cell test's), each with its first and last column.
    let rows = h.row_lanes.iter().enumerate().flat_map(|(g, lanes)| {
        let [cos_theta, sin_theta, cos_beta, sin_beta] = lanes.0;
        let k_min = cos_sum4(cull.cos, cull.sin, cos_beta, sin_beta) - Vec4::splat(slack);
        let along = cos_theta * Vec4::splat(cull.axis.z);
        let across = sin_theta * Vec4::splat(rho);
        let skip = (along + across).cmplt(k_min - Vec4::splat(1e-4)).bitmask();
        let rows = (0..4).filter(move |&i| skip & (1 << i) == 0 && 4 * g + i < h.rows.len());
        // Azimuths within ±delta of the cap's axis can pass; one column of margin. Every
        // column where azimuth bounds nothing (`across`, the row's reach across the axis,
        // 10⁻⁶ or less) or where every azimuth can pass (q −1 or less).
        let q = (k_min - along) / across;
        let every = (across.cmple(Vec4::splat(1e-6)) | q.cmple(Vec4::splat(-1.0))).bitmask();
        let delta = acos_above(q.min(Vec4::ONE)) + Vec4::splat(ATAN2_ERROR);
        let (phi_w, dphi, half) = (Vec4::splat(phi_w), Vec4::splat(dphi), Vec4::splat(0.5));
        let lo = ((phi_w - delta) / dphi - half).to_array();
        let hi = ((phi_w + delta) / dphi - half).to_array();
        rows.map(move |i| {
            let (k0, k1) = if every & (1 << i) != 0 {
                (0, n - 1)
            } else {
                (floor(lo[i]) - 1, ceil(hi[i]) + 1)
            };
            (4 * g + i, k0, k1)
        })
    });
    for (j, k0, k1) in rows {
        let (k0, k1) = if k1 - k0 + 1 >= n {
            (0, n - 1)
        } else {
            (k0, k1)
        };
        let first = j * h.n as usize;
        let mut k = k0.rem_euclid(n) as usize;
        for _ in k0..=k1 {
            if !visit(j, first + k) {
                return;
            }
            k += 1;
            if k == h.n as usize {
                k = 0;
            }
        }
    }
}

/// The cells [`cover`] may set for any triangle of a prim whose sphere cap is `sphere`: those
/// with a quarter whose cap meets the sphere's, the test every cell [`cover`] sets has passed.
/// The cells are not those an enumeration reaches but all of them, less the half-rows that
/// cannot pass (below), so the set holds whatever [`cover`] sets. Once a record's bits hold
/// all of them, the prim's other triangles can set nothing more ([`CpuVisibility`] stops
/// there).
///
/// A half-row none of whose quarters can pass is skipped whole: its quarters' centres share
/// its elevation θ, so none is nearer the cap's axis than cos θ·z + sin θ·ρ allows (z and ρ
/// the axis's height and horizontal length), which must reach the test's threshold; a
/// margin of 10⁻⁴, far above the rounding of either side, keeps the skip from deciding.
pub fn sphere_cells(h: &Hemisphere, sphere: SphereCap, slack: f32) -> StrataBits {
    let cap = sphere.0;
    let rho = (cap.axis.x * cap.axis.x + cap.axis.y * cap.axis.y).sqrt();
    let mut bits = StrataBits::new(h.len());
    let n = h.n as usize;
    for (half, row) in h.half_rows.iter().enumerate() {
        let best = row.cos_theta * cap.axis.z + row.sin_theta * rho;
        if best < cos_sum(cap.cos, cap.sin, row.cos_beta, row.sin_beta) - slack - 1e-4 {
            continue;
        }
        let (j, r) = (half / 2, half % 2);
        for cell in j * n..(j + 1) * n {
            if !bits.get(cell)
                && (0..2).any(|q| overlaps(&cap, row, h.quarters[4 * cell + 2 * r + q], slack))
            {
                bits.set(cell);
            }
        }
    }
    bits
}

/// Random dynamic scenes and the conservativeness check, shared by both implementations'
/// tests.
#[cfg(test)]
pub(crate) mod testing {
    use super::*;
    use crate::accel::Accel;
    use crate::geom::{TriangleShading, triangle};
    use glam::Vec2;

    fn r(seed: u32, i: u32, d: u32) -> f32 {
        crate::sampling::hash(&[seed, i, d]) as f32 / u32::MAX as f32
    }

    /// Prim `p`'s centre: x and z in [-2, 2], y `height[1]` + up to `height[0]`.
    fn prim_centre(seed: u32, p: u32, height: [f32; 2]) -> Vec3 {
        Vec3::new(
            r(seed, p, 0) * 4.0 - 2.0,
            r(seed, p, 1) * height[0] + height[1],
            r(seed, p, 2) * 4.0 - 2.0,
        )
    }

    /// Adds a triangle of prim `prim` to `g`, facing up for shading.
    pub fn push_triangle(g: &mut Geometry, [a, b, c]: [Vec3; 3], prim: u32) {
        g.triangles.push(triangle(a, b, c));
        g.shading.push(TriangleShading {
            normals: [Vec3::Y; 3],
            uvs: [Vec2::ZERO; 3],
            material: 0,
            prim,
            masked: false,
            attributes: crate::geom::NO_ATTRIBUTES,
        });
    }

    /// `prims` random prims of `tris` triangles each above (and some through) the floor
    /// y = 0, and `records` records on the floor with tilted normals, all in [-2, 2]².
    pub fn random_scene(
        seed: u32,
        prims: u32,
        tris: u32,
        records: u32,
    ) -> (Geometry, Vec<(Vec3, Vec3)>) {
        let r = |i, d| r(seed, i, d);
        let mut g = Geometry::default();
        for p in 0..prims {
            let c = prim_centre(seed, p, [2.0, -0.1]);
            let size = 0.2 + r(p, 3);
            for t in 0..tris {
                let i = p * 1000 + t;
                let v = |k: u32| {
                    c + Vec3::new(r(i, 10 + k) - 0.5, r(i, 20 + k) - 0.5, r(i, 30 + k) - 0.5) * size
                };
                push_triangle(&mut g, [v(0), v(1), v(2)], p);
            }
        }
        let recs = (0..records)
            .map(|i| {
                let nrm = Vec3::new(r(i, 40) - 0.5, 1.0, r(i, 41) - 0.5).normalize();
                (
                    Vec3::new(r(i, 42) * 4.0 - 2.0, 0.0, r(i, 43) * 4.0 - 2.0),
                    nrm,
                )
            })
            .collect();
        (g, recs)
    }

    /// `prims` closed prims — star-shaped polyhedra (a sphere of 6 rings of 8 quads, each
    /// vertex at its own random radius, so most are concave), half of them wound inwards —
    /// around the floor y = 0 (some through it, so that records lie inside them), and
    /// `records` records on the floor as in [`random_scene`], all in [-2, 2]². Each vertex
    /// is computed once per position, so that the triangles meeting there share it bit for
    /// bit, as a mesh's split vertices do.
    pub fn closed_scene(seed: u32, prims: u32, records: u32) -> (Geometry, Vec<(Vec3, Vec3)>) {
        closed_scene_of(seed, prims, [6, 8], records)
    }

    /// [`closed_scene`] with spheres of `rings` rings of `around` quads.
    pub fn closed_scene_of(
        seed: u32,
        prims: u32,
        [rings, around]: [u32; 2],
        records: u32,
    ) -> (Geometry, Vec<(Vec3, Vec3)>) {
        let r = |i, d| r(seed, i, d);
        let mut g = Geometry::default();
        for p in 0..prims {
            let c = prim_centre(seed, p, [1.2, -0.4]);
            let size = 0.3 + 0.5 * r(p, 3);
            // Ring 0 and ring `rings` are the poles.
            let vertex = |ring: u32, k: u32| {
                let k = if ring == 0 || ring == rings {
                    0
                } else {
                    k % around
                };
                let theta = ring as f32 / rings as f32 * std::f32::consts::PI;
                let phi = k as f32 / around as f32 * 2.0 * std::f32::consts::PI;
                let i = p * 100_000 + ring * around + k;
                let radius = size * (0.4 + 0.6 * r(i, 10));
                c + radius
                    * Vec3::new(
                        theta.sin() * phi.cos(),
                        theta.cos(),
                        theta.sin() * phi.sin(),
                    )
            };
            let inwards = p % 2 == 1;
            let mut push = |a: Vec3, b: Vec3, d: Vec3| {
                let (b, d) = if inwards { (d, b) } else { (b, d) };
                push_triangle(&mut g, [a, b, d], p);
            };
            for ring in 0..rings {
                for k in 0..around {
                    let (a, b) = (vertex(ring, k), vertex(ring, k + 1));
                    let (cc, d) = (vertex(ring + 1, k), vertex(ring + 1, k + 1));
                    if ring > 0 {
                        push(a, b, cc);
                    }
                    if ring + 1 < rings {
                        push(b, d, cc);
                    }
                }
            }
        }
        let (_, recs) = random_scene(seed, 0, 0, records);
        (g, recs)
    }

    /// Asserts that every ray through a stratum (64 directions anywhere in it, corners
    /// included) that hits a dynamic triangle belongs to a flagged stratum; returns the hits.
    pub fn assert_conservative(
        g: &Geometry,
        records: &[(Vec3, Vec3)],
        [m, n]: [u32; 2],
        flags: &[StrataBits],
    ) -> usize {
        let r = |i, d| r(7, i, d);
        let empty = Geometry::default();
        let accel = Accel::build(&empty, g);
        let mut hits = 0;
        for (ri, &(x, nrm)) in records.iter().enumerate() {
            let (t, b) = basis(nrm);
            for j in 0..m {
                let (t0, t1) = theta_limits(j, m);
                for k in 0..n {
                    for s in 0..64u32 {
                        let u = if s < 4 {
                            (s & 1) as f32
                        } else {
                            r(s, 50 + j * n + k)
                        };
                        let v = if s < 4 {
                            (s >> 1) as f32
                        } else {
                            r(s, 90_000 + j * n + k)
                        };
                        let theta = t0 + (t1 - t0) * u;
                        let phi = (k as f32 + v) / n as f32 * 2.0 * std::f32::consts::PI;
                        let dir = t * (theta.sin() * phi.cos())
                            + b * (theta.sin() * phi.sin())
                            + nrm * theta.cos();
                        if accel.closest(&empty, g, x, dir, f32::INFINITY).is_some() {
                            hits += 1;
                            assert!(
                                flags[ri].get((j * n + k) as usize),
                                "record {ri}, stratum ({j},{k}) sees a dynamic triangle but is not flagged"
                            );
                        }
                    }
                }
            }
        }
        hits
    }
}

#[cfg(test)]
mod tests {
    use super::testing::*;
    use super::*;

    /// Every direction inside a stratum that hits a dynamic triangle lies in a flagged
    /// stratum, and the flags stay tight: most strata are not flagged.
    #[test]
    fn cpu_visibility_is_conservative() {
        for (seed, strata) in [(1, [8u32, 24u32]), (2, [12, 36]), (3, [4, 8])] {
            let (g, records) = random_scene(seed, 4, 6, 24);
            let set = DynamicSet::new(&g);
            let flags = CpuVisibility.flag(&records, strata, &set).unwrap();
            let hits = assert_conservative(&g, &records, strata, &flags);
            assert!(hits > 100, "the test must exercise hits ({hits})");
            let flagged: usize = flags.iter().map(StrataBits::count).sum();
            let all = records.len() * (strata[0] * strata[1]) as usize;
            // Coarse strata are wide; at the presets' resolutions most stay unflagged.
            if strata[0] * strata[1] >= 192 {
                assert!(flagged < all / 2, "{flagged} of {all} flagged");
            }
        }
    }

    /// [`cover`] and [`adds_nothing`], which enumerate cells around a cap and test a
    /// cell's four quarters in SIMD lanes, decide as the scalar tests of every cell and
    /// quarter do, bit for bit: on random and closed prims at both presets' strata, from
    /// records beside them and inside their spheres, with partly set bits.
    #[test]
    fn quarter_lanes_decide_as_the_scalar_tests() {
        let scenes = [
            random_scene(21, 4, 8, 16),
            closed_scene(22, 4, 16),
            closed_scene_of(23, 3, [16, 24], 8),
        ];
        let (mut cells, mut passed) = (0, 0);
        for (g, records) in &scenes {
            let set = DynamicSet::new(g);
            for strata in [[12u32, 36u32], [30, 60], [4, 8]] {
                let h = Hemisphere::new(strata);
                for &(x, n) in records {
                    let f = RecordFrame::new(x, n);
                    let (mut bits, mut want) = (StrataBits::new(h.len()), StrataBits::new(h.len()));
                    for (prim, range) in set.prims.iter().zip(&set.ranges) {
                        let Some(sphere) = sphere_cap(&f, *prim, CPU_SLACK).visible() else {
                            continue;
                        };
                        for tri in &set.triangles[range.clone()] {
                            cover(&h, &f, sphere, tri, CPU_SLACK, &mut bits);
                            if let Some(t) =
                                CellTests::of(&h, &f, sphere, tri, CPU_SLACK, &mut want)
                            {
                                cover_every_cell(&h, &t, CPU_SLACK, &mut want);
                            }
                            assert_eq!(bits, want, "{strata:?}, record at {x}");
                        }
                    }
                    cells += bits.count();
                    // Every run's ball against these bits, and against the bits of the
                    // prims' first half of the triangles only.
                    let mut half = StrataBits::new(h.len());
                    for (prim, range) in set.prims.iter().zip(&set.ranges) {
                        if let Some(sphere) = sphere_cap(&f, *prim, CPU_SLACK).visible() {
                            for tri in &set.triangles[range.start..range.start + range.len() / 2] {
                                cover(&h, &f, sphere, tri, CPU_SLACK, &mut half);
                            }
                        }
                    }
                    for (ball, _) in set.clusters.iter().flat_map(|t| t.iter().flatten()) {
                        for b in [&bits, &half] {
                            let got = adds_nothing(&h, &f, *ball, CPU_SLACK, b);
                            let want = ball_cap(&f, *ball)
                                .is_some_and(|cap| cap_adds_nothing(&h, &cap, CPU_SLACK, b));
                            assert_eq!(got, want);
                            passed += got as usize;
                        }
                    }
                }
            }
        }
        assert!(
            cells > 1000 && passed > 100,
            "{cells} cells, {passed} balls pass"
        );
    }

    /// `acos_above` lies above `acos` by at most 2·10⁻⁴ over [-1, 1].
    #[test]
    fn acos_above_bounds_acos_from_above() {
        for i in 0..=20_000 {
            let x = -1.0 + i as f32 / 10_000.0;
            let d = acos_above(Vec4::splat(x)).x as f64 - (x as f64).acos();
            assert!((0.0..2e-4).contains(&d), "acos({x}): {d}");
        }
    }

    /// Triangles close up where every edge is walked once each way, by position: a
    /// tetrahedron, whose split vertices join; not with a face missing, turned over, or
    /// with two equal corners.
    #[test]
    fn closed_prims_are_recognised_by_their_edges() {
        let v = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(0.0, 0.0, 1.0),
        ];
        let tet = [
            [v[0], v[2], v[1]],
            [v[0], v[1], v[3]],
            [v[0], v[3], v[2]],
            [v[1], v[2], v[3]],
        ];
        assert!(closes_up(&tet));
        // −0 and +0 are the same corner.
        let mut signed = tet;
        signed[3][0] = Vec3::new(1.0, -0.0, 0.0);
        assert!(closes_up(&signed));
        assert!(!closes_up(&tet[..3]));
        let mut turned = tet;
        turned[1] = [v[0], v[3], v[1]];
        assert!(!closes_up(&turned));
        let mut pinched = tet;
        pinched[3] = [v[1], v[1], v[3]];
        assert!(!closes_up(&pinched));
        assert!(!closes_up(&[]));
        // A point beyond the face x + y + z = 1 sees that face only: the other three face
        // away from it.
        let far = Vec3::splat(2.0);
        let away: Vec<bool> = tet.iter().map(|t| faces_away(far, &Face::of(t))).collect();
        assert_eq!(away, [true, true, true, false]);
        // A point in a face's plane is not behind it.
        assert!(!faces_away(Vec3::new(3.0, -2.0, 0.0), &Face::of(&tet[0])));
    }

    /// Closed prims (concave, some wound inwards, some around records): the CPU leaves out
    /// the triangles facing away from a record outside a prim's sphere, and its flags stay
    /// conservative and within those of every triangle tested.
    #[test]
    fn closed_prims_skip_the_triangles_facing_away() {
        for (seed, strata) in [(11, [8u32, 24u32]), (12, [12, 36])] {
            let (g, records) = closed_scene(seed, 5, 32);
            let set = DynamicSet::new(&g);
            assert!(set.closed.iter().all(|&c| c), "{:?}", set.closed);
            // Some records lie inside a prim's sphere, where every triangle is tested.
            let inside = records
                .iter()
                .filter(|&&(x, n)| {
                    let f = RecordFrame::new(x, n);
                    set.prims
                        .iter()
                        .any(|&p| matches!(sphere_cap(&f, p, CPU_SLACK), PrimCap::Around))
                })
                .count();
            assert!(inside > 0, "no record inside a prim's sphere");
            let skipped = records
                .iter()
                .flat_map(|&(x, _)| set.faces.iter().map(move |f| faces_away(x, f)))
                .filter(|&a| a)
                .count();
            assert!(skipped * 3 > set.triangles.len() * records.len());
            let flags = CpuVisibility.flag(&records, strata, &set).unwrap();
            let hits = assert_conservative(&g, &records, strata, &flags);
            assert!(hits > 100, "the test must exercise hits ({hits})");
            let every = DynamicSet {
                closed: vec![false; set.closed.len()],
                ..set.clone()
            };
            let all = CpuVisibility.flag(&records, strata, &every).unwrap();
            assert!(flags.iter().zip(&all).all(|(f, a)| a.contains(f)));
        }
    }

    /// Finely meshed prims (720 triangles each, 90 clusters) seen from up to a few sizes
    /// away: the CPU passes over the clusters whose cells are set already, and its flags
    /// stay conservative and the same as those of every triangle tested one by one.
    #[test]
    fn clusters_whose_cells_are_set_are_passed_over() {
        let strata = [12u32, 36u32];
        let (g, records) = closed_scene_of(13, 4, [16, 24], 24);
        let set = DynamicSet::new(&g);
        assert!(set.clusters.iter().all(|c| c[0].len() == 720 / CLUSTER));
        let flags = CpuVisibility.flag(&records, strata, &set).unwrap();
        assert!(assert_conservative(&g, &records, strata, &flags) > 100);
        // Every triangle its own cluster, each of which adds something where it is tested.
        let h = Hemisphere::new(strata);
        let one_by_one = records
            .iter()
            .map(|&(x, n)| {
                let f = RecordFrame::new(x, n);
                let mut bits = StrataBits::new(h.len());
                for (prim, range) in set.prims.iter().zip(&set.ranges) {
                    if let Some(sphere) = sphere_cap(&f, *prim, CPU_SLACK).visible() {
                        for tri in &set.triangles[range.clone()] {
                            cover(&h, &f, sphere, tri, CPU_SLACK, &mut bits);
                        }
                    }
                }
                bits
            })
            .collect::<Vec<_>>();
        assert_eq!(flags, one_by_one);
        // The clusters are narrow enough to be passed over from most records, and the
        // final flags hold every cell of most of them.
        let passed = records
            .iter()
            .zip(&flags)
            .flat_map(|(&(x, n), bits)| {
                let f = RecordFrame::new(x, n);
                let h = &h;
                set.clusters
                    .iter()
                    .flat_map(|tree| &tree[0])
                    .map(move |(ball, _)| adds_nothing(h, &f, *ball, CPU_SLACK, bits))
            })
            .filter(|&a| a)
            .count();
        let all = records.len() * set.clusters.iter().map(|t| t[0].len()).sum::<usize>();
        assert!(passed * 2 > all, "{passed} of {all} clusters add nothing");
    }

    /// A clustered prim's triangles, listed in a scrambled order, are taken along a Morton
    /// curve: its runs stay narrow. Each level of its tree of runs covers the level below in
    /// order, in nodes of at most [`CLUSTER`] triangles or [`FAN_OUT`] nodes, up to a level
    /// of at most [`FAN_OUT`], and every node's sphere holds its triangles.
    #[test]
    fn cluster_trees_are_narrow_and_bound_their_triangles() {
        let (g, _) = closed_scene_of(14, 3, [16, 24], 0);
        let n = g.triangles.len();
        let mut scrambled = Geometry::default();
        for i in (0..n).map(|i| i * 7919 % n) {
            let t = &g.triangles[i];
            let tri = [t.v0, t.v1, t.v2].map(Vec3::from);
            push_triangle(&mut scrambled, tri, g.shading[i].prim);
        }
        let set = DynamicSet::new(&scrambled);
        assert_eq!(set.clusters.len(), 3);
        for ((prim, range), tree) in set.prims.iter().zip(&set.ranges).zip(&set.clusters) {
            let mut below = range.clone();
            for (level, nodes) in tree.iter().enumerate() {
                let most = if level == 0 { CLUSTER } else { FAN_OUT };
                let mut next = below.start;
                for (_, r) in nodes {
                    assert!(r.start == next && !r.is_empty() && r.len() <= most);
                    next = r.end;
                }
                assert_eq!(next, below.end, "level {level}");
                below = 0..nodes.len();
            }
            assert!(tree.last().unwrap().len() <= FAN_OUT);
            // Each node's triangles, down the tree.
            let triangles = |level: usize, node: usize| {
                let mut r = node..node + 1;
                for l in (0..=level).rev() {
                    r = tree[l][r.start].1.start..tree[l][r.end - 1].1.end;
                }
                r
            };
            for (level, nodes) in tree.iter().enumerate() {
                for (node, (ball, _)) in nodes.iter().enumerate() {
                    for v in set.triangles[triangles(level, node)].iter().flatten() {
                        assert!(v.distance(ball.centre) <= ball.radius, "level {level}");
                    }
                }
            }
            let mean = tree[0].iter().map(|(b, _)| b.radius).sum::<f32>() / tree[0].len() as f32;
            assert!(mean < 0.35 * prim.radius, "{mean} against {}", prim.radius);
        }
    }

    /// `atan2_near` lies within [`ATAN2_ERROR`] of `atan2` all round, and `floor` and
    /// `ceil` are `f32`'s.
    #[test]
    fn atan2_near_and_floor_match_the_library() {
        for i in 0..=20_000 {
            let a = i as f64 / 20_000.0 * std::f64::consts::TAU;
            for r in [1e-30, 1e-3, 1.0, 1e20] {
                let (y, x) = ((r * a.sin()) as f32, (r * a.cos()) as f32);
                let d = atan2_near(y, x) as f64 - (y as f64).atan2(x as f64);
                assert!(d.abs() <= ATAN2_ERROR as f64, "atan2({y}, {x}): {d}");
            }
        }
        for (y, x) in [
            (0.0, 0.0),
            (0.0, -1.0),
            (-0.0, 1.0),
            (1.0, 0.0),
            (-1.0, 0.0),
        ] {
            let d = atan2_near(y, x) as f64 - (y as f64).atan2(x as f64);
            assert!(d.abs() <= ATAN2_ERROR as f64, "atan2({y}, {x}): {d}");
        }
        for i in -4000..=4000 {
            for x in [i as f32 / 64.0, i as f32 / 7.0, i as f32 * 1e5] {
                assert_eq!(floor(x), x.floor() as i32, "{x}");
                assert_eq!(ceil(x), x.ceil() as i32, "{x}");
            }
        }
    }

    /// A record beside a small triangle: only the strata around its direction are flagged,
    /// far fewer than its prim's bounding sphere would flag.
    #[test]
    fn triangles_flag_fewer_strata_than_their_spheres() {
        let (g, records) = random_scene(4, 3, 12, 24);
        let set = DynamicSet::new(&g);
        let strata = [12, 36];
        let flags = CpuVisibility.flag(&records, strata, &set).unwrap();
        let h = Hemisphere::new(strata);
        let spheres: usize = records
            .iter()
            .map(|&(x, n)| {
                let f = RecordFrame::new(x, n);
                let mut bits = StrataBits::new(h.len());
                for &prim in &set.prims {
                    match sphere_cap(&f, prim, CPU_SLACK) {
                        PrimCap::Below => {}
                        PrimCap::Around => (0..h.len()).for_each(|c| bits.set(c)),
                        PrimCap::Cap(cap) => (0..h.len()).for_each(|c| {
                            let j = c / h.n as usize;
                            if (0..4).any(|i| {
                                let half = &h.half_rows[2 * j + i / 2];
                                overlaps(&cap.0, half, h.quarters[4 * c + i], CPU_SLACK)
                            }) {
                                bits.set(c)
                            }
                        }),
                    }
                }
                bits.count()
            })
            .sum();
        let flagged: usize = flags.iter().map(StrataBits::count).sum();
        assert!(
            flagged * 10 < spheres * 9,
            "triangles flag {flagged}, spheres {spheres}"
        );
    }
}
