//! [`super::PairTree::closest4`]'s tests in the eight lanes of AVX2, for rays from one point (a
//! record's gather rays): a pair's two boxes against the four rays at once, and a leaf's
//! blocks against two rays at once. Each lane computes what the four-lane tests compute
//! (the same IEEE operations on the same operands, none fused), so the hits are the same to
//! the bit. Used only where the CPU has AVX2 (`PairTree::new`), which the x86-64 baseline
//! that the crate is built for does not include. On Sponza's gather rays (`cargo bench
//! --bench rays`, `slow_build`, three alternating rounds, at `356019c`) the four-lane walk
//! traced 2.60–2.74 M rays a second, the box test in eight lanes 2.69–2.76 M, and both
//! tests in eight lanes 2.68–2.89 M (5 % more on average); in a render at the final preset,
//! the gather stage of Sponza's frame 2 took 0.69–0.71 s against 0.77 s.
//!
//! Written with `std::arch` rather than a portable SIMD crate: those pick their instructions
//! when the crate is compiled, for the baseline, and so would not use AVX2 here.

use std::arch::x86_64::*;
use std::ops::{Add, BitAnd, BitOr, Div, Mul, Neg, Sub};

use glam::{Vec3A, Vec4};

use super::{BlockLanes, Entered, Found4, FourRays, Link, Pair, block_test_in, set_bits};
use crate::accel::Lanes;

/// [`FourRays`] in eight lanes, for rays from `o`.
#[derive(Clone, Copy)]
pub(super) struct Wide {
    o: Vec3A,
    /// Each axis's reciprocal direction components, the four rays twice.
    inv: [__m256; 3],
}

impl Wide {
    /// For rays from `o` with reciprocal directions `inv` (a ray a lane). Only where the
    /// CPU has AVX2.
    #[inline(always)]
    pub(super) fn new(o: Vec3A, inv: [Vec4; 3]) -> Wide {
        Wide {
            o,
            inv: [
                W8::twice(inv[0]).0,
                W8::twice(inv[1]).0,
                W8::twice(inv[2]).0,
            ],
        }
    }
}

/// An axis's two slabs for both children: plane − origin for the pair's four `planes` (as
/// the four lanes subtract each), then each child's near plane in its four lanes and its far
/// plane in the same, times the rays' reciprocals `inv`.
#[inline(always)]
fn slab(planes: &Vec4, o: f32, inv: __m256) -> (__m256, __m256) {
    // SAFETY: called only by `Wide`'s tests (see `W8`).
    unsafe {
        // The four planes in each half (a load, no shuffle across the halves), less the
        // origin; then within each half the child's plane in every lane.
        let four = _mm256_broadcast_ps(&(*planes).into());
        let d = _mm256_sub_ps(four, _mm256_set1_ps(o));
        let lo = _mm256_permutevar_ps(d, _mm256_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1));
        let hi = _mm256_permutevar_ps(d, _mm256_setr_epi32(2, 2, 2, 2, 3, 3, 3, 3));
        (_mm256_mul_ps(lo, inv), _mm256_mul_ps(hi, inv))
    }
}

impl FourRays for Wide {
    /// Both children at once: lanes 0–3 the first child's for the four rays, 4–7 the second's.
    #[inline(always)]
    fn enter(self, p: &Pair, far_limit: Vec4, lanes: u32) -> Entered {
        // SAFETY: a `Wide` is made only where the CPU has AVX2 (`PairTree::new`).
        unsafe {
            let (x0, x1) = slab(&p.x, self.o.x, self.inv[0]);
            let (y0, y1) = slab(&p.y, self.o.y, self.inv[1]);
            let (z0, z1) = slab(&p.z, self.o.z, self.inv[2]);
            let near = _mm256_max_ps(
                _mm256_max_ps(_mm256_min_ps(x0, x1), _mm256_min_ps(y0, y1)),
                _mm256_min_ps(z0, z1),
            );
            let far = _mm256_min_ps(
                _mm256_min_ps(_mm256_max_ps(x0, x1), _mm256_max_ps(y0, y1)),
                _mm256_max_ps(z0, z1),
            );
            let hit = _mm256_and_ps(
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GE_OS>(far, near),
                    _mm256_cmp_ps::<_CMP_GE_OS>(far, _mm256_setzero_ps()),
                ),
                _mm256_cmp_ps::<_CMP_LT_OS>(near, W8::twice(far_limit).0),
            );
            let bits = _mm256_movemask_ps(hit) as u32;
            let (near0, near1) = (
                _mm256_castps256_ps128(near),
                _mm256_extractf128_ps::<1>(near),
            );
            Entered {
                lanes: [bits & lanes, (bits >> 4) & lanes],
                second_nearer: _mm_movemask_ps(_mm_cmplt_ps(near1, near0)) as u32,
            }
        }
    }

    /// The rays two at a time, where two share the axis their shear makes z (rays through
    /// neighbouring strata nearly always do); a ray left over alone in four lanes.
    #[inline(always)]
    fn leaf(self, found: &mut Found4, leaf: Link, lanes: u32) {
        let mut left = lanes;
        while left != 0 {
            let i = left.trailing_zeros() as usize;
            left &= left - 1;
            match set_bits(left).find(|&j| found.srs[j].kz == found.srs[i].kz) {
                Some(j) => {
                    left &= !(1 << j);
                    leaf_hits2(found, [i, j], leaf);
                }
                None => found.one(i, leaf),
            }
        }
    }
}

/// `leaf`'s triangles against the rays of lanes `i` and `j` (one origin, one `kz`), each
/// block tested for both at once: each ray's hits are those [`super::PairTree::leaf_hits`] finds
/// for it, kept in `best` in the same order.
#[inline(always)]
fn leaf_hits2(found: &mut Found4, [i, j]: [usize; 2], leaf: Link) {
    let Found4 {
        tree,
        g,
        srs,
        tmax,
        best,
    } = found;
    let (a, b) = (&srs[i], &srs[j]);
    let shear = [
        W8::halves(a.shear.x, b.shear.x),
        W8::halves(a.shear.y, b.shear.y),
        W8::halves(a.shear.z, b.shear.z),
    ];
    let first = leaf.index as usize;
    for block in 0..leaf.count.div_ceil(4) as usize {
        let base = first + 4 * block;
        let lanes = (leaf.count as usize - 4 * block).min(4);
        let masked = (tree.masked[base / 64] >> (base % 64)) as u32 & 0xf;
        let found = block_test_in(
            a.origin,
            a.kz,
            shear,
            &tree.quads[base / 4],
            W8::halves(tmax[i], tmax[j]),
            masked | masked << 4,
        );
        let t = found.t.to_array();
        for (shift, ray) in [(0, i), (4, j)] {
            let (hit, rest) = (found.hit >> shift, found.rest >> shift);
            for lane in set_bits((hit | rest) & ((1 << lanes) - 1)) {
                let t = if rest & (1 << lane) != 0 {
                    tree.distance(&srs[ray], g, base + lane, tmax[ray])
                } else {
                    t[shift + lane]
                };
                tree.keep_nearer(&mut best[ray], base + lane, t, &mut tmax[ray]);
            }
        }
    }
}

/// Eight f32 lanes. Made only where the CPU has AVX2 (in [`Wide`]'s tests), which is what
/// makes its operations' `unsafe` sound.
#[derive(Clone, Copy)]
pub(super) struct W8(__m256);

/// An eight-lane mask.
#[derive(Clone, Copy)]
pub(super) struct M8(__m256);

impl W8 {
    /// `v` in lanes 0–3 and again in 4–7.
    #[inline(always)]
    fn twice(v: Vec4) -> W8 {
        // SAFETY: see `W8`.
        W8(unsafe { _mm256_set_m128(v.into(), v.into()) })
    }

    /// `a` in lanes 0–3, `b` in 4–7.
    #[inline(always)]
    fn halves(a: f32, b: f32) -> W8 {
        // SAFETY: see `W8`.
        W8(unsafe { _mm256_setr_ps(a, a, a, a, b, b, b, b) })
    }

    #[inline(always)]
    fn to_array(self) -> [f32; 8] {
        let mut out = [0.0; 8];
        // SAFETY: see `W8`; `out` holds eight f32s.
        unsafe { _mm256_storeu_ps(out.as_mut_ptr(), self.0) };
        out
    }
}

/// `$op` of two `W8`s by the intrinsic `$f`.
macro_rules! binary {
    ($trait:ident, $op:ident, $f:ident) => {
        impl $trait for W8 {
            type Output = W8;
            #[inline(always)]
            fn $op(self, other: W8) -> W8 {
                // SAFETY: see `W8`.
                W8(unsafe { $f(self.0, other.0) })
            }
        }
    };
}
binary!(Add, add, _mm256_add_ps);
binary!(Sub, sub, _mm256_sub_ps);
binary!(Mul, mul, _mm256_mul_ps);
binary!(Div, div, _mm256_div_ps);

impl Mul<f32> for W8 {
    type Output = W8;
    #[inline(always)]
    fn mul(self, other: f32) -> W8 {
        // SAFETY: see `W8`.
        W8(unsafe { _mm256_mul_ps(self.0, _mm256_set1_ps(other)) })
    }
}

impl Neg for W8 {
    type Output = W8;
    /// The sign bit flipped, as glam's `Vec4` negates.
    #[inline(always)]
    fn neg(self) -> W8 {
        // SAFETY: see `W8`.
        W8(unsafe { _mm256_xor_ps(self.0, _mm256_set1_ps(-0.0)) })
    }
}

impl Lanes for W8 {
    /// The sign bit cleared, as glam's `Vec4::abs`.
    #[inline(always)]
    fn abs(self) -> W8 {
        // SAFETY: see `W8`.
        W8(unsafe { _mm256_andnot_ps(_mm256_set1_ps(-0.0), self.0) })
    }
    /// `maxps` with the operands in `Vec4::max`'s order (which decides a NaN's fate).
    #[inline(always)]
    fn max(self, other: W8) -> W8 {
        // SAFETY: see `W8`.
        W8(unsafe { _mm256_max_ps(self.0, other.0) })
    }
}

impl BitOr for M8 {
    type Output = M8;
    #[inline(always)]
    fn bitor(self, other: M8) -> M8 {
        // SAFETY: see `W8`.
        M8(unsafe { _mm256_or_ps(self.0, other.0) })
    }
}

impl BitAnd for M8 {
    type Output = M8;
    #[inline(always)]
    fn bitand(self, other: M8) -> M8 {
        // SAFETY: see `W8`.
        M8(unsafe { _mm256_and_ps(self.0, other.0) })
    }
}

/// A comparison of two `W8`s with predicate `$p` (ordered: false where either is NaN, as
/// SSE's comparisons; `ne` unordered, true there, as `cmpneq`).
macro_rules! compare {
    ($name:ident, $p:ident) => {
        #[inline(always)]
        fn $name(self, other: W8) -> M8 {
            // SAFETY: see `W8`.
            M8(unsafe { _mm256_cmp_ps::<$p>(self.0, other.0) })
        }
    };
}

impl BlockLanes for W8 {
    type Mask = M8;
    const ALL: u32 = 0xff;
    #[inline(always)]
    fn splat(x: f32) -> W8 {
        // SAFETY: see `W8`.
        W8(unsafe { _mm256_set1_ps(x) })
    }
    #[inline(always)]
    fn block(v: Vec4) -> W8 {
        W8::twice(v)
    }
    compare!(lt, _CMP_LT_OS);
    compare!(gt, _CMP_GT_OS);
    compare!(le, _CMP_LE_OS);
    compare!(eq, _CMP_EQ_OQ);
    compare!(ne, _CMP_NEQ_UQ);
    /// |x| < ∞, as glam's `Vec4::is_finite_mask`.
    #[inline(always)]
    fn finite(self) -> M8 {
        self.abs().lt(W8::splat(f32::INFINITY))
    }
    #[inline(always)]
    fn bits(m: M8) -> u32 {
        // SAFETY: see `W8`.
        unsafe { _mm256_movemask_ps(m.0) as u32 }
    }
}
