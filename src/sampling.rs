//! Deterministic sampling (DESIGN.md, Numerics; STYLE.md §9): every random number is a pure
//! function of (seed, frame, pixel or photon index, sample index, dimension), never of thread
//! order, so any thread count gives the same image.
//!
//! Samples come from Burley's Owen-scrambled Sobol sequence (`sobol_burley`, "Practical
//! Hash-based Owen Scrambling", JCGT 2020): a quasi-Monte Carlo sequence with good
//! stratification in every 4-D slice, decorrelated per pixel by the scramble seed.
//!
//! The crate's sampler walks the sample index's bits (up to 16 steps per value); for the
//! first `TABLE_DIMS` dimensions — camera jitter, light samples, the first bounces — this
//! module reads the same Sobol values from two 256-entry tables per dimension instead (a
//! Sobol value is the XOR of the direction vectors of the index's set bits, so it is the
//! XOR of its two index bytes' partial values). The values are the crate's, bit for bit.

/// A 32-bit avalanche mix (the finaliser of MurmurHash3 applied over `values`).
pub fn hash(values: &[u32]) -> u32 {
    let mut h: u32 = 0x9e37_79b9;
    for &v in values {
        let mut k = v.wrapping_mul(0xcc9e_2d51);
        k = k.rotate_left(15).wrapping_mul(0x1b87_3593);
        h ^= k;
        h = h.rotate_left(13).wrapping_mul(5).wrapping_add(0xe654_6b64);
    }
    h ^= h >> 16;
    h = h.wrapping_mul(0x85eb_ca6b);
    h ^= h >> 13;
    h = h.wrapping_mul(0xc2b2_ae35);
    h ^ (h >> 16)
}

/// The independent uses of random numbers. Each has its own scramble seed, so that no two
/// uses ever read correlated samples; the values are part of the output's definition (they
/// seed every image ever rendered) and must not change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum Stream {
    /// Camera paths, per pixel and frame: pixel jitter, light samples, path-tracer bounces.
    Camera = 0,
    /// Global importons (Suykens 2002), per importon.
    Importons = 0x1a90_0001,
    /// Photon paths, per photon: the same in every frame (the paper's §4.2).
    Photons = 0x5eed_0001,
    /// Jitter inside a cache record's strata, per record id: the same in every frame.
    Strata = 0x6a7e_0001,
}

/// Hands out consecutive sample dimensions, so that the uses of one stream never overlap:
/// `take(n)` returns the first of `n` dimensions no earlier call returned.
#[derive(Debug, Clone, Copy, Default)]
pub struct Dims(u32);

impl Dims {
    pub const fn new() -> Self {
        Dims(0)
    }

    pub fn take(&mut self, n: u32) -> u32 {
        let first = self.0;
        self.0 += n;
        first
    }
}

/// One scrambled sequence: the samples of one pixel (or photon, or record) of one frame.
#[derive(Debug, Clone, Copy)]
pub struct Sampler {
    seed: u32,
}

impl Sampler {
    /// The sequence of `stream` for element `index` (pixel, importon) of `frame`.
    pub fn new(seed: u32, frame: i32, stream: Stream, index: u32) -> Self {
        Sampler {
            seed: hash(&[seed, frame as u32, stream as u32, index]),
        }
    }

    /// The photons' sequence: sample `i` is photon `i`. Depends on the job's seed only, not on
    /// the frame, so that photons follow the same paths wherever nothing moved (§4.2).
    pub fn photons(seed: u32) -> Self {
        Sampler {
            seed: hash(&[seed, Stream::Photons as u32]),
        }
    }

    /// The stratum jitter of the cache record `id`: sample `s` is stratum `s`.
    pub fn strata(id: u32) -> Self {
        Sampler {
            seed: hash(&[id, Stream::Strata as u32]),
        }
    }

    /// Sample `index`, dimension `dim`, in `[0, 1)`. Dimensions past the sequence's 256 are
    /// re-seeded so they stay decorrelated, and so are indices past its 2^16 samples: each
    /// block of 2^16 samples (photons beyond the first 65 536, for one) is its own
    /// independently scrambled sequence. Without that, the sequence repeats itself: sample
    /// `i + 2^16` would share its first dimensions with an earlier one.
    pub fn get(&self, index: u32, dim: u32) -> f32 {
        let (index, seed) = self.block(index, dim);
        let within = dim % sobol_burley::NUM_DIMENSIONS;
        scrambled(shuffle(index, seed), within, seed)
    }

    /// The index within its block of 2^16 samples, and the seed of the block and of the
    /// dimension's set of 256.
    fn block(&self, index: u32, dim: u32) -> (u32, u32) {
        let set = dim / sobol_burley::NUM_DIMENSIONS;
        let seed = if set == 0 {
            self.seed
        } else {
            hash(&[self.seed, set])
        };
        match index >> 16 {
            0 => (index, seed),
            block => (index & 0xffff, hash(&[seed, block, 0xb10c_5eed])),
        }
    }

    /// Dimensions `dim` and `dim + 1` of sample `index`: the same values as two
    /// [`Sampler::get`] calls, computed four dimensions at a time (SIMD) where both lie in
    /// one of the sequence's sets of four.
    pub fn get2(&self, index: u32, dim: u32) -> [f32; 2] {
        let within = dim % sobol_burley::NUM_DIMENSIONS;
        if dim % 4 == 3 {
            return [self.get(index, dim), self.get(index, dim + 1)];
        }
        let (index, seed) = self.block(index, dim);
        if within + 1 < TABLE_DIMS {
            let shuffled = shuffle(index, seed);
            return [
                scrambled(shuffled, within, seed),
                scrambled(shuffled, within + 1, seed),
            ];
        }
        let four = sobol_burley::sample_4d(index, within / 4, seed);
        let k = (within % 4) as usize;
        [four[k], four[k + 1]]
    }
}

/// Dimensions whose Sobol values come from tables (module doc).
const TABLE_DIMS: u32 = 32;

/// Per table dimension, the bit-reversed Sobol values of the index's top byte and of its
/// second byte (the sequence uses the reversed index's top 16 bits).
static SOBOL_TABLES: std::sync::LazyLock<Vec<[[u32; 256]; 2]>> = std::sync::LazyLock::new(|| {
    use sobol_burley::parts::sobol_rev;
    (0..TABLE_DIMS)
        .map(|d| {
            [
                std::array::from_fn(|b| sobol_rev((b as u32) << 24, d)),
                std::array::from_fn(|b| sobol_rev((b as u32) << 16, d)),
            ]
        })
        .collect()
});

/// The sample's index shuffled by the sequence's seed, bit-reversed (as
/// `sobol_burley::sample` does before reading the Sobol value).
fn shuffle(index: u32, seed: u32) -> u32 {
    use sobol_burley::parts::{hash, owen_scramble_rev};
    owen_scramble_rev(index.reverse_bits(), hash(seed ^ 0x79c6_8e4a))
}

/// `sobol_burley::sample(index, dim, seed)` from the shuffled index `shuffled_rev`, with
/// the Sobol value read from the tables where `dim` has them.
fn scrambled(shuffled_rev: u32, dim: u32, seed: u32) -> f32 {
    use sobol_burley::parts::{hash, owen_scramble_rev, sobol_rev, u32_to_f32_norm};
    let sobol = match SOBOL_TABLES.get(dim as usize) {
        Some(t) => {
            t[0][(shuffled_rev >> 24) as usize] ^ t[1][((shuffled_rev >> 16) & 0xff) as usize]
        }
        None => sobol_rev(shuffled_rev, dim),
    };
    let scramble = (dim >> 2)
        ^ seed.wrapping_mul(0x9c8f_2d3b)
        ^ [0x912f_69ba, 0x174f_18ab, 0x691e_72ca, 0xb40c_c1b8][dim as usize & 3];
    u32_to_f32_norm(owen_scramble_rev(sobol, hash(scramble)).reverse_bits())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_are_pure_functions_of_their_inputs() {
        let a = Sampler::new(1, 2, Stream::Camera, 3);
        let b = Sampler::new(1, 2, Stream::Camera, 3);
        assert_eq!(a.get(5, 7), b.get(5, 7));
        assert_ne!(a.get(5, 7), Sampler::new(1, 3, Stream::Camera, 3).get(5, 7));
    }

    /// The tables give the crate's samples, bit for bit.
    #[test]
    fn samples_are_the_crates() {
        let mut h = 1u32;
        for _ in 0..200_000 {
            h = hash(&[h]);
            let (index, seed, dim) = (h & 0xffff, hash(&[h, 1]), hash(&[h, 2]) % 256);
            assert_eq!(
                scrambled(shuffle(index, seed), dim, seed).to_bits(),
                sobol_burley::sample(index, dim, seed).to_bits(),
                "index {index} seed {seed} dim {dim}"
            );
        }
    }

    #[test]
    fn pairs_are_the_single_dimensions() {
        for (seed, frame) in [(0, 0), (7, -3), (123_456, 99)] {
            let s = Sampler::new(seed, frame, Stream::Strata, 5);
            for index in [0, 1, 2, 17, 255, 4095, 65_536, 200_001] {
                for dim in 0..600 {
                    assert_eq!(
                        s.get2(index, dim).map(f32::to_bits),
                        [s.get(index, dim), s.get(index, dim + 1)].map(f32::to_bits),
                        "seed {seed} index {index} dim {dim}"
                    );
                }
            }
        }
    }

    /// Photons are numbered past the sequence's 2^16 samples: every one must get its own
    /// sample, not repeat the one 2^16 earlier.
    #[test]
    fn samples_past_two_to_the_sixteen_do_not_repeat() {
        let s = Sampler::photons(1);
        let mut seen = std::collections::HashSet::new();
        let repeats = (0..300_000u32)
            .filter(|&i| !seen.insert([s.get(i, 0), s.get(i, 1), s.get(i, 2)].map(f32::to_bits)))
            .count();
        assert_eq!(repeats, 0);
        // The next block is stratified in its own right.
        let mut hit = [false; 16];
        for i in 0..16 {
            hit[(s.get(3 * 65_536 + i, 3) * 16.0) as usize] = true;
        }
        assert!(hit.iter().all(|&h| h));
    }

    #[test]
    fn one_dimension_is_stratified() {
        // Owen-scrambled Sobol: the first 16 samples put one point in each 1/16 stratum.
        let s = Sampler::new(0, 0, Stream::Camera, 42);
        let mut hit = [false; 16];
        for i in 0..16 {
            hit[(s.get(i, 3) * 16.0) as usize] = true;
        }
        assert!(hit.iter().all(|&h| h));
    }
}
