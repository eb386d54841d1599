// Visibility maps (the paper's §3.2): which strata of each static cache record may see a
// dynamic triangle. One invocation per (record, triangle) pair rasterises the triangle's
// cap onto the record's stratum grid and sets one bit per covered stratum. This mirrors
// `cover` and `sphere_cap` in src/visibility/mod.rs line by line; the module doc there
// states the rule and why it is conservative. It tests every triangle, also those of a
// closed prim and of a run of triangles that the CPU leaves out (`faces_away`,
// `adds_nothing`), so that its flags stay a superset.

struct Params {
    // Records in this dispatch, starting at `record_offset`.
    records: u32,
    record_offset: u32,
    triangles: u32,
    // Strata: M rows of N columns.
    m: u32,
    n: u32,
    // u32 words of flags per record.
    words: u32,
    // Workgroups along x (dispatches are 2D to pass the 65535 limit).
    groups_x: u32,
    slack: f32,
    min_cap_cos: f32,
    dphi: f32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Per record: position, tangent, bitangent, normal (w unused).
@group(0) @binding(1) var<storage, read> records: array<vec4<f32>>;
// Per triangle: three vertices (w unused).
@group(0) @binding(2) var<storage, read> triangles: array<vec4<f32>>;
// Per triangle: its prim.
@group(0) @binding(3) var<storage, read> tri_prim: array<u32>;
// Per prim: bounding-sphere centre and radius.
@group(0) @binding(4) var<storage, read> prims: array<vec4<f32>>;
// M rows (cos θ, sin θ, cos β, sin β), 2M half-rows (the same for a cell's quarters),
// then 4·M·N quarter centre directions (local frame): `Hemisphere`.
@group(0) @binding(5) var<storage, read> grid: array<vec4<f32>>;
// One bit per stratum, `words` per record.
@group(0) @binding(6) var<storage, read_write> flags: array<atomic<u32>>;

struct Cap {
    axis: vec3<f32>,
    cos: f32,
    sin: f32,
    valid: bool,
}

// cos(a + b) from the cosines and sines of a, b in [0, π]; -1 past π.
fn cos_sum(ca: f32, sa: f32, cb: f32, sb: f32) -> f32 {
    if sa * cb + ca * sb < 0.0 {
        return -1.0;
    }
    return ca * cb - sa * sb;
}

// Whether cell centre `c` of `row` lies within the cap grown by the row's β.
fn overlaps(cap: Cap, row: vec4<f32>, c: vec3<f32>) -> bool {
    return dot(c, cap.axis) >= cos_sum(cap.cos, cap.sin, row.z, row.w) - params.slack;
}

// A triangle projected onto the unit sphere (`SphericalTriangle`), unrolled: vertices,
// edge-plane normals n, and the lune tangents ta = n × a, tb = b × n of edges 01, 12, 20.
struct Spherical {
    u0: vec3<f32>,
    u1: vec3<f32>,
    u2: vec3<f32>,
    n0: vec3<f32>,
    n1: vec3<f32>,
    n2: vec3<f32>,
    ta0: vec3<f32>,
    ta1: vec3<f32>,
    ta2: vec3<f32>,
    tb0: vec3<f32>,
    tb1: vec3<f32>,
    tb2: vec3<f32>,
    inside_sign: f32,
    valid: bool,
}

fn spherical(u0: vec3<f32>, u1: vec3<f32>, u2: vec3<f32>) -> Spherical {
    var s: Spherical;
    s.valid = false;
    let c0 = cross(u0, u1);
    let c1 = cross(u1, u2);
    let c2 = cross(u2, u0);
    let l0 = length(c0);
    let l1 = length(c1);
    let l2 = length(c2);
    let limit = 10.0 * params.slack;
    if l0 < limit || l1 < limit || l2 < limit {
        return s;
    }
    s.u0 = u0;
    s.u1 = u1;
    s.u2 = u2;
    s.n0 = c0 / l0;
    s.n1 = c1 / l1;
    s.n2 = c2 / l2;
    s.ta0 = cross(s.n0, u0);
    s.tb0 = cross(u1, s.n0);
    s.ta1 = cross(s.n1, u1);
    s.tb1 = cross(u2, s.n1);
    s.ta2 = cross(s.n2, u2);
    s.tb2 = cross(u0, s.n2);
    let det = dot(u0, cross(u1, u2));
    s.inside_sign = select(select(0.0, -1.0, det < 0.0), 1.0, det > 0.0);
    s.valid = true;
    return s;
}

fn edge_near(ta: vec3<f32>, tb: vec3<f32>, n: vec3<f32>, c: vec3<f32>, sin_beta: f32) -> bool {
    let slack = params.slack;
    return dot(c, ta) >= -slack && dot(c, tb) >= -slack && abs(dot(c, n)) <= sin_beta + slack;
}

// Whether the cap of `row`'s β around `c` meets the spherical triangle (`near`).
fn near(s: Spherical, row: vec4<f32>, c: vec3<f32>) -> bool {
    let slack = params.slack;
    let cos_beta = row.z - slack;
    if dot(c, s.u0) >= cos_beta || dot(c, s.u1) >= cos_beta || dot(c, s.u2) >= cos_beta {
        return true;
    }
    let g = s.inside_sign;
    if g != 0.0 && g * dot(c, s.n0) >= -slack && g * dot(c, s.n1) >= -slack
        && g * dot(c, s.n2) >= -slack {
        return true;
    }
    if row.z <= 0.0 {
        return true;
    }
    return edge_near(s.ta0, s.tb0, s.n0, c, row.w) || edge_near(s.ta1, s.tb1, s.n1, c, row.w)
        || edge_near(s.ta2, s.tb2, s.n2, c, row.w);
}

fn mark(r: u32, cell: u32) {
    atomicOr(&flags[r * params.words + cell / 32u], 1u << (cell % 32u));
}

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let pair = (wg.y * params.groups_x + wg.x) * 64u + li;
    let local_record = pair / params.triangles;
    if local_record >= params.records {
        return;
    }
    let r = params.record_offset + local_record;
    let ti = pair % params.triangles;
    let x = records[4u * r].xyz;
    let t = records[4u * r + 1u].xyz;
    let b = records[4u * r + 2u].xyz;
    let n = records[4u * r + 3u].xyz;
    let slack = params.slack;

    // The prim's sphere cap (`sphere_cap`).
    let sph = prims[tri_prim[ti]];
    var sphere = Cap(vec3<f32>(0.0), 1.0, 0.0, false);
    let v = sph.xyz - x;
    let d = length(v);
    if d > sph.w * (1.0 + slack) {
        let s = sph.w / d;
        let a = v / d;
        sphere = Cap(vec3<f32>(dot(a, t), dot(a, b), dot(a, n)), sqrt(max(1.0 - s * s, 0.0)), s, true);
        if sphere.axis.z < -sphere.sin - slack {
            return;
        }
    }

    // The triangle's cap (`cover`).
    let p0 = triangles[3u * ti].xyz - x;
    let p1 = triangles[3u * ti + 1u].xyz - x;
    let p2 = triangles[3u * ti + 2u].xyz - x;
    let l0 = length(p0);
    let l1 = length(p1);
    let l2 = length(p2);
    if dot(p0, n) < -slack * l0 && dot(p1, n) < -slack * l1 && dot(p2, n) < -slack * l2 {
        return;
    }
    var tri = Cap(vec3<f32>(0.0), 1.0, 0.0, false);
    var exact: Spherical;
    exact.valid = false;
    if l0 > 0.0 && l1 > 0.0 && l2 > 0.0 {
        let u0 = p0 / l0;
        let u1 = p1 / l1;
        let u2 = p2 / l2;
        let w = u0 + u1 + u2;
        let wl = length(w);
        if wl > 0.0 {
            let a = w / wl;
            let c = min(min(dot(a, u0), dot(a, u1)), dot(a, u2));
            if c > params.min_cap_cos + slack {
                tri = Cap(vec3<f32>(dot(a, t), dot(a, b), dot(a, n)), c, sqrt(max(1.0 - c * c, 0.0)), true);
                exact = spherical(
                    vec3<f32>(dot(u0, t), dot(u0, b), dot(u0, n)),
                    vec3<f32>(dot(u1, t), dot(u1, b), dot(u1, n)),
                    vec3<f32>(dot(u2, t), dot(u2, b), dot(u2, n)),
                );
            }
        }
    }
    var cull = tri;
    if !tri.valid {
        cull = sphere;
    }
    if !cull.valid {
        for (var c = 0u; c < params.m * params.n; c++) {
            mark(r, c);
        }
        return;
    }

    // Rasterise: rows whose best cell can pass, then the columns around the cap's azimuth.
    let ni = i32(params.n);
    let rho = sqrt(cull.axis.x * cull.axis.x + cull.axis.y * cull.axis.y);
    let phi_w = atan2(cull.axis.y, cull.axis.x);
    for (var j = 0u; j < params.m; j++) {
        let row = grid[j];
        let k_min = cos_sum(cull.cos, cull.sin, row.z, row.w) - slack;
        let along = row.x * cull.axis.z;
        let across = row.y * rho;
        if along + across < k_min - 1e-4 {
            continue;
        }
        var k0 = 0;
        var k1 = ni - 1;
        if across > 1e-6 {
            let q = (k_min - along) / across;
            if q > -1.0 {
                let delta = acos(min(q, 1.0));
                k0 = i32(floor((phi_w - delta) / params.dphi - 0.5)) - 1;
                k1 = i32(ceil((phi_w + delta) / params.dphi - 0.5)) + 1;
                if k1 - k0 + 1 >= ni {
                    k0 = 0;
                    k1 = ni - 1;
                }
            }
        }
        for (var k = k0; k <= k1; k++) {
            let cell = j * params.n + u32(((k % ni) + ni) % ni);
            for (var i = 0u; i < 4u; i++) {
                let c = grid[3u * params.m + 4u * cell + i].xyz;
                let half = grid[params.m + 2u * j + i / 2u];
                if (!tri.valid || overlaps(tri, half, c)) && (!exact.valid || near(exact, half, c))
                    && (!sphere.valid || overlaps(sphere, half, c)) {
                    mark(r, cell);
                    break;
                }
            }
        }
    }
}
