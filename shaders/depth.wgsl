// Hemisphere depth maps for anchor bucketing (the paper's §5.1): the closest hit of each
// query ray against the frame's static and dynamic BVH2s (obvhs's, flattened by
// src/visibility/depth_gpu.rs). The traversal mirrors obvhs's `ray_traverse_dynamic` and the
// triangle test mirrors `ShearedRay::intersect_barycentric` in src/accel.rs (Woop, Benthin &
// Wald's watertight test) in f32. A triangle the CPU decides in f64 (an edge function
// exactly zero, a t within its error bound of zero: a ray leaving the surface it starts on)
// is answered as PENDING, up to two per query: the CPU tests those triangles alone and keeps
// the nearer of their answers and the shader's. Where more are pending, where an
// alpha-tested triangle lies in front of the nearest hit (no textures here), and where the
// stack would overflow, the query is answered UNDECIDED and the CPU traces it
// (src/visibility/depth.rs, module doc).

struct Params {
    // Queries in this dispatch, starting at `offset`.
    queries: u32,
    offset: u32,
    // Workgroups along x (dispatches are 2D to pass the 65535 limit).
    groups_x: u32,
    has_static: u32,
    has_dynamic: u32,
    // γ(2), γ(3), γ(5) of src/accel.rs.
    gamma2: f32,
    gamma3: f32,
    gamma5: f32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Everything is stored as u32 words (floats by their bits), so that integers never pass
// through a float register that might flush them as denormals.
// Per node two vec4: (min, prim_count), (max, first_index).
@group(0) @binding(1) var<storage, read> static_nodes: array<vec4<u32>>;
// Per BVH primitive slot three vec4: v0 (w: the triangle's index), v1 (w: 1 when
// alpha-tested), v2.
@group(0) @binding(2) var<storage, read> static_tris: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> dynamic_nodes: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read> dynamic_tris: array<vec4<u32>>;
// Per query two vec4: origin, direction (w unused).
@group(0) @binding(5) var<storage, read> queries: array<vec4<f32>>;
// Per query: bits of t, and the triangle's index with bit 31 set for dynamic ones, or MISS
// or UNDECIDED; then the pending triangles, coded alike, MISS where there are none.
@group(0) @binding(6) var<storage, read_write> hits: array<vec4<u32>>;

const MISS: u32 = 0xffffffffu;
const UNDECIDED: u32 = 0xfffffffeu;
const STACK: u32 = 64u;
// Stands for infinity (WGSL has no infinite literal): no hit is this far.
const FAR: f32 = 3.4028235e38;
// f32::EPSILON, for obvhs's `safe_inverse`.
const EPS: f32 = 1.1920929e-7;

struct Ray {
    o: vec3<f32>,
    d: vec3<f32>,
    inv: vec3<f32>,
    kx: u32,
    ky: u32,
    kz: u32,
    shear: vec3<f32>,
}

// The state of one query's traversal.
struct Best {
    t: f32,
    code: u32,
    // The nearest t at which the answer is not decided here (FAR when none).
    undecided: f32,
    // Triangles left to the CPU's own test (MISS when none).
    pending0: u32,
    pending1: u32,
}

// The code of the triangle in BVH slot word `a` (its index) of the dynamic or static BVH.
fn code_of(a: vec4<u32>, dynamic: bool) -> u32 {
    if dynamic {
        return a.w | 0x80000000u;
    }
    return a.w;
}

// Leaves the triangle `code` to the CPU: a pending slot if one is free, else the whole query.
fn pend(best: ptr<function, Best>, code: u32) {
    if (*best).pending0 == MISS {
        (*best).pending0 = code;
    } else if (*best).pending1 == MISS {
        (*best).pending1 = code;
    } else {
        (*best).undecided = 0.0;
    }
}

// obvhs's `safe_inverse`, with Rust's `signum` (±1 by the sign bit, never 0: WGSL's `sign`
// would give 0 for a zero component and make every box miss along that axis).
fn safe_inverse(x: f32) -> f32 {
    if abs(x) <= EPS {
        return select(1.0, -1.0, (bitcast<u32>(x) & 0x80000000u) != 0u) / EPS;
    }
    return 1.0 / x;
}

fn make_ray(o: vec3<f32>, d: vec3<f32>) -> Ray {
    let a = abs(d);
    var kz = 2u;
    if a.x > a.y {
        if a.x > a.z {
            kz = 0u;
        }
    } else if a.y > a.z {
        kz = 1u;
    }
    let kx = (kz + 1u) % 3u;
    let ky = (kx + 1u) % 3u;
    let inv = vec3<f32>(safe_inverse(d.x), safe_inverse(d.y), safe_inverse(d.z));
    let shear = vec3<f32>(-d[kx] / d[kz], -d[ky] / d[kz], 1.0 / d[kz]);
    return Ray(o, d, inv, kx, ky, kz, shear);
}

fn node_lo(dynamic: bool, i: u32) -> vec4<u32> {
    if dynamic {
        return dynamic_nodes[2u * i];
    }
    return static_nodes[2u * i];
}

fn node_hi(dynamic: bool, i: u32) -> vec4<u32> {
    if dynamic {
        return dynamic_nodes[2u * i + 1u];
    }
    return static_nodes[2u * i + 1u];
}

fn vertex(dynamic: bool, i: u32) -> vec4<u32> {
    if dynamic {
        return dynamic_tris[i];
    }
    return static_tris[i];
}

// obvhs's `Aabb::intersect_ray`: the entry distance, or FAR.
fn box_t(r: Ray, lo: vec4<u32>, hi: vec4<u32>) -> f32 {
    let t1 = (bitcast<vec3<f32>>(lo.xyz) - r.o) * r.inv;
    let t2 = (bitcast<vec3<f32>>(hi.xyz) - r.o) * r.inv;
    let tmin = min(t1, t2);
    let tmax = max(t1, t2);
    let tmin_n = max(max(tmin.x, tmin.y), tmin.z);
    let tmax_n = min(min(tmax.x, tmax.y), tmax.z);
    if tmax_n >= tmin_n && tmax_n >= 0.0 {
        return tmin_n;
    }
    return FAR;
}

fn sheared(r: Ray, v: vec3<f32>) -> vec3<f32> {
    let p = v - r.o;
    let z = p[r.kz];
    return vec3<f32>(p[r.kx] + r.shear.x * z, p[r.ky] + r.shear.y * z, z * r.shear.z);
}

// The watertight test against the triangle in BVH slot `slot`, updating `best`.
fn intersect(r: Ray, dynamic: bool, slot: u32, best: ptr<function, Best>) {
    let a = vertex(dynamic, 3u * slot);
    let b = vertex(dynamic, 3u * slot + 1u);
    let c = vertex(dynamic, 3u * slot + 2u);
    let p0 = sheared(r, bitcast<vec3<f32>>(a.xyz));
    let p1 = sheared(r, bitcast<vec3<f32>>(b.xyz));
    let p2 = sheared(r, bitcast<vec3<f32>>(c.xyz));
    let e0 = p1.x * p2.y - p1.y * p2.x;
    let e1 = p2.x * p0.y - p2.y * p0.x;
    let e2 = p0.x * p1.y - p0.y * p1.x;
    if e0 == 0.0 || e1 == 0.0 || e2 == 0.0 {
        // The CPU decides this in f64 (an alpha-tested triangle needs its texture too).
        if b.w != 0u {
            (*best).undecided = 0.0;
        } else {
            pend(best, code_of(a, dynamic));
        }
        return;
    }
    if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
        return;
    }
    let det = e0 + e1 + e2;
    if det == 0.0 {
        return;
    }
    let inv_det = 1.0 / det;
    let b0 = e0 * inv_det;
    let b1 = e1 * inv_det;
    let b2 = e2 * inv_det;
    let t = b0 * p0.z + b1 * p1.z + b2 * p2.z;
    if !(t < (*best).t) {
        return;
    }
    let max_z = max(max(abs(p0.z), abs(p1.z)), abs(p2.z));
    let max_x = max(max(abs(p0.x), abs(p1.x)), abs(p2.x));
    let max_y = max(max(abs(p0.y), abs(p1.y)), abs(p2.y));
    let delta_z = params.gamma3 * max_z;
    let delta_x = params.gamma5 * (max_x + max_z);
    let delta_y = params.gamma5 * (max_y + max_z);
    let delta_e = 2.0 * (params.gamma2 * max_x * max_y + delta_y * max_x + delta_x * max_y);
    let max_b = max(max(abs(b0), abs(b1)), abs(b2));
    let delta_t = 3.0 * (params.gamma5 * max_b * max_z + delta_e * abs(inv_det) * max_z
        + delta_z * max_b);
    if t < -delta_t {
        return;
    }
    if t <= delta_t {
        // At the origin within rounding: the CPU decides this in f64.
        if b.w != 0u {
            (*best).undecided = 0.0;
        } else {
            pend(best, code_of(a, dynamic));
        }
        return;
    }
    if b.w != 0u {
        // Alpha-tested: the CPU reads the texture.
        (*best).undecided = min((*best).undecided, t);
        return;
    }
    (*best).t = t;
    (*best).code = code_of(a, dynamic);
}

fn leaf(r: Ray, dynamic: bool, hi: vec4<u32>, count: u32, best: ptr<function, Best>) {
    let first = hi.w;
    for (var i = 0u; i < count; i++) {
        intersect(r, dynamic, first + i, best);
    }
}

// obvhs's `ray_traverse_dynamic`: nearer child first, the other on the stack.
fn traverse(r: Ray, dynamic: bool, best: ptr<function, Best>) {
    var stack: array<u32, STACK>;
    var sp = 0u;
    let root_lo = node_lo(dynamic, 0u);
    let root_hi = node_hi(dynamic, 0u);
    if !(box_t(r, root_lo, root_hi) < (*best).t) {
        return;
    }
    let root_count = root_lo.w;
    if root_count > 0u {
        leaf(r, dynamic, root_hi, root_count, best);
        return;
    }
    var current = root_hi.w;
    loop {
        var left = current;
        var right = current + 1u;
        var left_lo = node_lo(dynamic, left);
        var left_hi = node_hi(dynamic, left);
        var right_lo = node_lo(dynamic, right);
        var right_hi = node_hi(dynamic, right);
        var left_t = box_t(r, left_lo, left_hi);
        var right_t = box_t(r, right_lo, right_hi);
        if left_t > right_t {
            let t = left_t;
            left_t = right_t;
            right_t = t;
            let lo = left_lo;
            left_lo = right_lo;
            right_lo = lo;
            let hi = left_hi;
            left_hi = right_hi;
            right_hi = hi;
        }
        var go_left = left_t < (*best).t;
        let left_count = left_lo.w;
        if go_left && left_count > 0u {
            leaf(r, dynamic, left_hi, left_count, best);
            go_left = false;
        }
        var go_right = right_t < (*best).t;
        let right_count = right_lo.w;
        if go_right && right_count > 0u {
            leaf(r, dynamic, right_hi, right_count, best);
            go_right = false;
        }
        if go_left && go_right {
            if sp == STACK {
                // Deeper than the stack: the CPU traces this query.
                (*best).undecided = 0.0;
                return;
            }
            current = left_hi.w;
            stack[sp] = right_hi.w;
            sp += 1u;
        } else if go_left {
            current = left_hi.w;
        } else if go_right {
            current = right_hi.w;
        } else {
            if sp == 0u {
                return;
            }
            sp -= 1u;
            current = stack[sp];
        }
    }
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let local = gid.x + gid.y * params.groups_x * 64u;
    if local >= params.queries {
        return;
    }
    let i = params.offset + local;
    let r = make_ray(queries[2u * i].xyz, queries[2u * i + 1u].xyz);
    var best = Best(FAR, MISS, FAR, MISS, MISS);
    // Static first, then dynamic, as `Accel::closest`: a dynamic hit must be strictly nearer.
    if params.has_static != 0u {
        traverse(r, false, &best);
    }
    if params.has_dynamic != 0u {
        traverse(r, true, &best);
    }
    if best.undecided < FAR && best.undecided <= best.t {
        hits[local] = vec4<u32>(0u, UNDECIDED, MISS, MISS);
    } else {
        hits[local] = vec4<u32>(bitcast<u32>(best.t), best.code, best.pending0, best.pending1);
    }
}
