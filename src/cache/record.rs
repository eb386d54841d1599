//! Cache records and their strata (Ward, Rubinstein & Clear 1988; the paper's §4.1): a
//! record holds the irradiance of a stratified final gather over its hemisphere, Ward's
//! radius, Ward & Heckbert gradients, and its strata — distance, flags and anchor link per
//! direction (§4.1 `RadianceSample`).
//!
//! Gradients follow the stratified formulation of Ward & Heckbert for cosine-weighted
//! strata (as given in Křivánek & Gautron, "Practical Global Illumination with Irradiance
//! Caching", 2009, §2.2).

use std::f32::consts::PI;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::CacheParams;
use super::directional::Directional;
use crate::accel::Hit;
use crate::anchor::AnchorId;
use crate::geom::{Motion, basis};
use crate::interaction::SurfacePoint;

/// Stratum flag: the gather ray hit a dynamic prim (its radiance was estimated directly).
pub const HIT_DYNAMIC: u8 = 1;

/// Stratum flag: the gather ray hit the back of a surface. A record most of whose rays hit
/// unlit back faces lies inside closed geometry (see [`Record::enclosed`]).
pub const HIT_BACK: u8 = 2;

/// The share of a record's strata that must hit unlit back faces for the record to count as
/// enclosed. Inside a closed object every ray does; above a single-sided lamp panel or
/// behind a lone wall only the rays towards it do, and the rest escape or meet front faces.
pub const ENCLOSED_SHARE: f32 = 0.5;

/// One gather direction of a record (the paper's `RadianceSample`, §4.1) in 6 bytes: a
/// 30-bit anchor link with two flag bits, and the hit distance as an f16 in units of the
/// record's pixel footprint (scale-free: the same bits at 1e−3 and 1e4; infinite on a miss).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[repr(C)]
pub struct Stratum([u16; 3]);

impl Stratum {
    pub fn new(link: Option<AnchorId>, flags: u8, distance: f32, scale: f32) -> Self {
        let link = link.map_or(NO_LINK, |a| a.0).min(NO_LINK);
        let d = if distance.is_finite() {
            half::f16::from_f32((distance / scale).min(65504.0)).to_bits()
        } else {
            half::f16::INFINITY.to_bits()
        };
        Stratum([
            link as u16,
            (link >> 16) as u16 | (flags as u16 & 3) << 14,
            d,
        ])
    }

    /// The anchor the stratum's ray reaches, if it hit static geometry in the anchor method.
    pub fn link(&self) -> Option<AnchorId> {
        let l = self.0[0] as u32 | ((self.0[1] as u32) & 0x3fff) << 16;
        (l != NO_LINK).then_some(AnchorId(l))
    }

    pub fn flags(&self) -> u8 {
        (self.0[1] >> 14) as u8
    }

    pub fn set_flags(&mut self, flags: u8) {
        self.0[1] = (self.0[1] & 0x3fff) | (flags as u16 & 3) << 14;
    }

    /// Hit distance given the record's footprint `scale`; infinite on a miss.
    pub fn distance(&self, scale: f32) -> f32 {
        half::f16::from_bits(self.0[2]).to_f32() * scale
    }

    pub fn hit(&self) -> bool {
        half::f16::from_bits(self.0[2]).is_finite()
    }

    /// A distance no nearer than the one the stratum's ray hit at (infinite on a miss, and
    /// where the f16 saturated): the stored distance rounded to nearest is within 2⁻¹¹ of
    /// it relatively, and within 2⁻²⁵·`scale` among the subnormals; the bound allows twice
    /// both (`scale`: the record's footprint).
    pub fn distance_bound(&self, scale: f32) -> f32 {
        let d = half::f16::from_bits(self.0[2]);
        if !d.is_finite() || d >= half::f16::MAX {
            return f32::INFINITY;
        }
        d.to_f32() * scale * (1.0 + 2f32.powi(-10)) + 2f32.powi(-24) * scale
    }
}

/// A record's strata serialised as one byte string of their six bytes each, byte plane by
/// byte plane (every stratum's first byte, then every second byte, ...): a checkpoint's
/// strata are most of its bytes, and as one string they encode with a copy, where varints
/// took about 8.4 bytes a stratum; as planes, the bytes that vary little across a
/// hemisphere (the links' high bytes, the distances' exponents) lie together for the
/// compressor. Read back from a byte string only: checkpoints are postcard, which has one.
mod strata_planes {
    use serde::de::{Error, Visitor};
    use serde::{Deserializer, Serializer};

    use super::Stratum;

    const BYTES: usize = std::mem::size_of::<Stratum>();

    pub fn serialize<S: Serializer>(strata: &[Stratum], s: S) -> Result<S::Ok, S::Error> {
        let n = strata.len();
        let mut planes = vec![0u8; n * BYTES];
        for (i, st) in strata.iter().enumerate() {
            for (w, word) in st.0.iter().enumerate() {
                let [lo, hi] = word.to_le_bytes();
                planes[2 * w * n + i] = lo;
                planes[(2 * w + 1) * n + i] = hi;
            }
        }
        s.serialize_bytes(&planes)
    }

    /// (As an owned byte string: a checkpoint is decoded as it is read, a chunk at a time,
    /// and a borrowed one would have to stay in the decoder's buffer until the end.)
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Stratum>, D::Error> {
        d.deserialize_byte_buf(Planes)
    }

    struct Planes;

    impl<'de> Visitor<'de> for Planes {
        type Value = Vec<Stratum>;

        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            write!(f, "a byte string of {BYTES} planes of strata bytes")
        }

        fn visit_bytes<E: Error>(self, planes: &[u8]) -> Result<Vec<Stratum>, E> {
            if !planes.len().is_multiple_of(BYTES) {
                return Err(E::invalid_length(planes.len(), &self));
            }
            let n = planes.len() / BYTES;
            let byte = |b: usize, i: usize| planes[b * n + i];
            Ok((0..n)
                .map(|i| {
                    Stratum(std::array::from_fn(|w| {
                        u16::from_le_bytes([byte(2 * w, i), byte(2 * w + 1, i)])
                    }))
                })
                .collect())
        }
    }
}

/// "No anchor" in a stratum's 30-bit link.
const NO_LINK: u32 = (1 << 30) - 1;

/// An irradiance cache record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub position: Vec3,
    pub normal: Vec3,
    pub irradiance: Vec3,
    /// Ward's R_i: harmonic-mean hit distance, clamped so that a·R_i lies between the
    /// minimum and maximum spacing in pixel footprints.
    pub radius: f32,
    /// R_i as the cache uses it: [`Record::radius`] clamped by the neighbouring records'
    /// (`IrradianceCache`'s neighbour clamping, Křivánek et al. 2006). Derived from the
    /// records whenever the cache's records change, so neither serialised nor set anywhere
    /// else.
    #[serde(skip)]
    pub reach_radius: f32,
    /// Rotational and translational gradients, per colour channel (R, G, B).
    pub grad_r: [Vec3; 3],
    pub grad_t: [Vec3; 3],
    pub motion: Motion,
    /// Seeds the record's stratum jitter: the same directions every frame.
    pub id: u32,
    /// Last frame in which the record contributed to a pixel (§4.3).
    pub last_used: i32,
    /// Pixel footprint at creation, for clamping the radius when re-gathered.
    pub footprint: f32,
    /// Error bound of the position (for ray offsets, pbrt-v4 §6.8) and geometric normal of
    /// the surface the record sits on.
    pub error: Vec3,
    pub ng: Vec3,
    #[serde(with = "strata_planes")]
    pub strata: Vec<Stratum>,
    /// The incident radiance's direction, fitted to the strata (module
    /// [`super::directional`]): what lights glossy lobes read from the cache. `None` where
    /// the strata are too few to fit it.
    pub directional: Option<Directional>,
    /// Fraction of the strata traced this frame (1 for brute force and new records).
    pub reshot: f32,
    /// The anchor contributing most of the record's irradiance.
    pub dominant_anchor: Option<AnchorId>,
    /// More than [`ENCLOSED_SHARE`] of the strata hit back faces that reflect no light: the
    /// record's gather started inside closed geometry — a static record on a floor that a
    /// dynamic prim now stands on, or a point whose ray origin lies past a contact. Its
    /// irradiance (zero, or what the inside of a prim reflects) is not the surface's, so
    /// interpolation and the coverage tests ignore it: it is not used. A record placed where
    /// it is valid would come out enclosed as well, so placement puts none there and keeps
    /// it (marks it used) in each frame it does so; otherwise it expires after `max_age`
    /// frames (§4.3). It is re-made from its strata as any record is, so once what enclosed
    /// it moves away it is an open record again. Back faces that reflect light are not the
    /// inside of anything: meshes wound the other way from their neighbours (decimated or
    /// mirrored exports, Sponza's LOD among them) show them to the room, and photons land on
    /// them from that side.
    pub enclosed: bool,
    /// A spot record ([`super::IrradianceCache::interpolate_spot`]): made for a camera
    /// sample that no other record covers, valid out to its own Ward radius (not widened to
    /// the minimum spacing), and read only by such samples. Interpolation, placement, neighbour
    /// clamping and the Weber rule ignore it, as they ignore enclosed records.
    pub spot: bool,
}

#[cfg(test)]
impl Record {
    /// A record without strata at `position` facing `normal`, with Ward radius `radius`.
    pub(crate) fn bare(position: Vec3, normal: Vec3, radius: f32) -> Record {
        Record {
            position,
            normal,
            irradiance: Vec3::ONE,
            radius,
            reach_radius: radius,
            grad_r: [Vec3::ZERO; 3],
            grad_t: [Vec3::ZERO; 3],
            motion: Motion::Static,
            id: 0,
            last_used: 0,
            footprint: 0.01,
            error: Vec3::ZERO,
            ng: normal,
            strata: Vec::new(),
            directional: None,
            reshot: 0.0,
            dominant_anchor: None,
            enclosed: false,
            spot: false,
        }
    }
}

impl Record {
    /// True for a record that lookups, placement and neighbour clamping use: neither
    /// enclosed nor a spot record.
    pub fn is_open(&self) -> bool {
        !self.enclosed && !self.spot
    }

    /// First-order irradiance at (x, n) from the record's gradients (Ward & Heckbert 1992):
    /// E_i + (n × n_i)·∇_r E_i + (x − x_i)·∇_t E_i, with ∇_r as `gradients` computes it.
    pub fn extrapolate(&self, x: Vec3, n: Vec3) -> Vec3 {
        let rot = n.cross(self.normal);
        let dx = x - self.position;
        self.irradiance
            + Vec3::from_array(std::array::from_fn(|c| {
                rot.dot(self.grad_r[c]) + dx.dot(self.grad_t[c])
            }))
    }
}

/// Completes a record from its strata: irradiance E = π/(MN) Σ L, harmonic-mean radius
/// clamped to [min, max] footprints (a spot record's, to the max only), and gradients.
#[allow(clippy::too_many_arguments)] // a record's every part
pub fn finish_record(
    sp: &SurfacePoint,
    motion: Motion,
    id: u32,
    footprint: f32,
    strata: Vec<Stratum>,
    radiance: &[Vec3],
    p: &CacheParams,
    frame: i32,
    spot: bool,
) -> Record {
    let [m, n] = p.strata;
    let scale = PI / (m * n) as f32;
    let irradiance = radiance.iter().sum::<Vec3>() * scale;
    let back = strata
        .iter()
        .zip(radiance)
        .filter(|(s, l)| s.flags() & HIT_BACK != 0 && l.max_element() <= 0.0)
        .count();
    let enclosed = back as f32 > ENCLOSED_SHARE * strata.len() as f32;
    // Every stratum's distance in footprints, decoded once for the radius and the gradients.
    let stored = stored_distances(&strata);
    let inv: f32 = stored
        .iter()
        .filter(|d| d.is_finite())
        .map(|&d| 1.0 / (d * footprint).max(f32::MIN_POSITIVE))
        .sum();
    let harmonic = if inv > 0.0 {
        (m * n) as f32 / inv
    } else {
        f32::INFINITY
    };
    // Clamp so that the region where the record is valid (distance < a·R) spans between
    // min and max pixel footprints (Tabellion & Lamorlette 2004). A spot record serves
    // only the samples its own Ward radius covers: not widened to the minimum.
    let r_max = p.max_spacing_px * footprint / p.error;
    let radius = if spot {
        harmonic.min(r_max)
    } else {
        harmonic.clamp(p.min_spacing_px * footprint / p.error, r_max)
    };
    let r_min = p.min_spacing_px * footprint / p.error;
    let distances: Vec<f32> = stored.iter().map(|&d| d * footprint).collect();
    let (grad_r, mut grad_t) = gradients(&distances, radiance, sp.ns, m, n, r_min);
    // Gradient limiting (Křivánek et al. 2006): extrapolation across the region where the
    // record is valid (a·R_i) may change each channel by at most its own value, so noisy
    // radiance next to a corner cannot turn into a large gradient.
    for c in 0..3 {
        let limit = irradiance[c] / (p.error * radius).max(f32::MIN_POSITIVE);
        let g = grad_t[c].length();
        if g > limit {
            grad_t[c] *= limit / g;
        }
    }
    Record {
        position: sp.position,
        normal: sp.ns,
        irradiance,
        radius,
        reach_radius: radius,
        grad_r,
        grad_t,
        motion,
        id,
        last_used: frame,
        footprint,
        error: sp.error,
        ng: sp.ng,
        directional: Directional::fit(sp.ns, radiance, p.strata),
        strata,
        reshot: 1.0,
        dominant_anchor: None,
        enclosed,
        spot,
    }
}

impl Record {
    /// The record re-made from new strata at its own position; id, footprint and last use
    /// are kept.
    pub fn with_strata(
        &self,
        strata: Vec<Stratum>,
        radiance: &[Vec3],
        p: &CacheParams,
        frame: i32,
    ) -> Record {
        let mut new = finish_record(
            &self.surface_point(),
            self.motion,
            self.id,
            self.footprint,
            strata,
            radiance,
            p,
            frame,
            self.spot,
        );
        new.last_used = self.last_used;
        new
    }

    /// The surface point of the record, for re-gathering from its own position and normal.
    pub fn surface_point(&self) -> SurfacePoint {
        SurfacePoint {
            position: self.position,
            ng: self.ng,
            ns: self.normal,
            uv: glam::Vec2::ZERO,
            color: [1.0; 4],
            error: self.error,
            material: 0,
            front: true,
            hit: Hit {
                t: 0.0,
                motion: self.motion,
                triangle: 0,
            },
        }
    }
}

/// The strata's hit distances in units of the record's footprint ([`Stratum::distance`]
/// with a scale of 1; infinite on a miss), converted together: half's slice conversion uses
/// the CPU's f16 instructions where it has them, eight at a time, and the values are exact
/// either way (every f16 is an f32).
fn stored_distances(strata: &[Stratum]) -> Vec<f32> {
    use half::slice::HalfFloatSliceExt;
    let bits: Vec<half::f16> = strata
        .iter()
        .map(|s| half::f16::from_bits(s.0[2]))
        .collect();
    let mut d = vec![0.0f32; bits.len()];
    bits.convert_to_f32_slice(&mut d);
    d
}

/// Sector `k` of `nn` in the tangent plane (`t`, `b`): its radial direction u_k and its
/// tangential direction v_k at its centre, and v_k− at its lower edge (Křivánek & Gautron
/// 2009, §2.2).
fn sector_axes(t: Vec3, b: Vec3, k: u32, nn: u32) -> [Vec3; 3] {
    let phi_c = 2.0 * PI * (k as f32 + 0.5) / nn as f32;
    let phi_m = 2.0 * PI * k as f32 / nn as f32;
    [
        t * phi_c.cos() + b * phi_c.sin(),
        -t * phi_c.sin() + b * phi_c.cos(),
        -t * phi_m.sin() + b * phi_m.cos(),
    ]
}

/// Rotational and translational irradiance gradients from cosine-weighted strata (Ward &
/// Heckbert 1992, in the form of Křivánek & Gautron 2009, eqs. 2.13–2.14):
///
/// ∇_r E = π/(MN) Σ_k v_k Σ_j −tan θ_j L_jk
/// ∇_t E = Σ_k [ u_k (2π/N) Σ_{j≥1} sin θ_j− cos² θ_j− / min(r_{j−1,k}, r_jk) (L_jk − L_{j−1,k})
///             + v_k− Σ_j (sin θ_j+ − sin θ_j−) / min(r_jk, r_{j,k−1}) (L_jk − L_{j,k−1}) ]
///
/// from the strata's `distances` (world units, infinite on a miss) and `radiance`, both in
/// stratum order (ring j, then sector k). Distances below `r_min` (the record's smallest
/// radius) count as `r_min`: a gather ray that grazes a corner says little about how
/// irradiance changes over the record's extent.
///
/// The inner sums over j run for all sectors at once, ring by ring, each sector's sums in
/// arrays of their own (one per colour channel), so that the compiler runs them four
/// sectors to an instruction. Each sector's sums still add ring by ring and the sectors then
/// add in order, so the gradients are the same to the bit as sector by sector (test
/// `gradients_are_the_same_to_the_bit_as_sector_by_sector`). A steady frame re-makes almost
/// every record from its anchors' new L_i; on Sponza at 1 800 strata, decoding the distances
/// and the gradients take about 30 % less time this way than sector by sector (README).
fn gradients(
    distances: &[f32],
    radiance: &[Vec3],
    n: Vec3,
    m: u32,
    nn: u32,
    r_min: f32,
) -> ([Vec3; 3], [Vec3; 3]) {
    let (t, b) = basis(n);
    let mut gr = [Vec3::ZERO; 3];
    let mut gt = [Vec3::ZERO; 3];
    let cols = nn as usize;
    let cells = (m * nn) as usize;
    let (distances, radiance) = (&distances[..cells], &radiance[..cells]);
    // The radiance channel by channel, and per sector its three sums over the rings
    // (rotational, θ and φ terms), channel by channel.
    let channel = |c: usize| -> Vec<f32> { radiance.iter().map(|l| l[c]).collect() };
    let l = [channel(0), channel(1), channel(2)];
    let mut rot = [vec![0.0f32; cols], vec![0.0; cols], vec![0.0; cols]];
    let mut theta = rot.clone();
    let mut phi = rot.clone();
    // Per sector of the ring at hand: the weights of its θ and φ differences, and whether
    // each difference counts (a finite, positive distance).
    let mut w_theta = vec![0.0f32; cols];
    let mut w_phi = vec![0.0f32; cols];
    // (As 0 or 1 in 32 bits: lanes as wide as the weights' select faster than bytes.)
    let mut ok_theta = vec![0u32; cols];
    let mut ok_phi = vec![0u32; cols];
    for j in 0..m as usize {
        // tan θ at the ring's centre, sin θ at its lower and upper edges.
        let sin_c = ((j as f32 + 0.5) / m as f32).sqrt();
        let tan_c = sin_c / (1.0 - sin_c * sin_c).max(1e-12).sqrt();
        let sin_m = (j as f32 / m as f32).sqrt();
        let sin_p = ((j + 1) as f32 / m as f32).sqrt();
        let cos2 = 1.0 - sin_m * sin_m;
        let row = j * cols..(j + 1) * cols;
        let d = &distances[row.clone()];
        // Towards the ring below (none for the first), and towards the sector before (the
        // last, for the first).
        let below = (j > 0).then(|| (j - 1) * cols..j * cols);
        // A difference's weight `top / r`, r the nearer of the two strata's distances (the
        // neighbour's `dn`, this one's `ds`) but no nearer than `r_min`, and whether it counts.
        let weight = |w: &mut f32, ok: &mut u32, top: f32, dn: f32, ds: f32| {
            let r = dn.min(ds).max(r_min);
            *w = top / r;
            *ok = u32::from(r.is_finite() & (r > 0.0));
        };
        if let Some(below) = below.clone() {
            let db = &distances[below];
            for (((w, ok), &ds), &dsb) in w_theta.iter_mut().zip(&mut ok_theta).zip(d).zip(db) {
                weight(w, ok, sin_m * cos2, dsb, ds);
            }
        }
        if cols > 0 {
            weight(
                &mut w_phi[0],
                &mut ok_phi[0],
                sin_p - sin_m,
                d[cols - 1],
                d[0],
            );
            for (((w, ok), &ds), &dl) in w_phi[1..]
                .iter_mut()
                .zip(&mut ok_phi[1..])
                .zip(&d[1..])
                .zip(d)
            {
                weight(w, ok, sin_p - sin_m, dl, ds);
            }
        }
        let add = |acc: &mut f32, ok: u32, w: f32, x: f32, y: f32| {
            let sum = *acc + w * (x - y);
            *acc = if ok != 0 { sum } else { *acc };
        };
        for c in 0..3 {
            let lr = &l[c][row.clone()];
            for (acc, &x) in rot[c].iter_mut().zip(lr) {
                *acc -= tan_c * x;
            }
            if let Some(below) = below.clone() {
                let lb = &l[c][below];
                for ((((acc, &ok), &w), &x), &y) in theta[c]
                    .iter_mut()
                    .zip(&ok_theta)
                    .zip(&w_theta)
                    .zip(lr)
                    .zip(lb)
                {
                    add(acc, ok, w, x, y);
                }
            }
            if cols > 0 {
                add(&mut phi[c][0], ok_phi[0], w_phi[0], lr[0], lr[cols - 1]);
                for ((((acc, &ok), &w), &x), &y) in phi[c][1..]
                    .iter_mut()
                    .zip(&ok_phi[1..])
                    .zip(&w_phi[1..])
                    .zip(&lr[1..])
                    .zip(lr)
                {
                    add(acc, ok, w, x, y);
                }
            }
        }
    }
    for k in 0..nn {
        let [u_k, v_k, v_km] = sector_axes(t, b, k, nn);
        let at = |sums: &[Vec<f32>; 3]| Vec3::from_array(sums.each_ref().map(|s| s[k as usize]));
        let rot = at(&rot) * (PI / (m * nn) as f32);
        let theta_term = at(&theta) * (2.0 * PI / nn as f32);
        let phi_term = at(&phi);
        for c in 0..3 {
            gr[c] += v_k * rot[c];
            gt[c] += u_k * theta_term[c] + v_km * phi_term[c];
        }
    }
    (gr, gt)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// [`gradients`] as the formula reads (Ward & Heckbert; Křivánek & Gautron, eqs.
    /// 2.13–2.14), sector by sector, each stratum's distance decoded on its own.
    fn gradients_by_sector(
        strata: &[Stratum],
        radiance: &[Vec3],
        scale: f32,
        n: Vec3,
        m: u32,
        nn: u32,
        r_min: f32,
    ) -> ([Vec3; 3], [Vec3; 3]) {
        let (t, b) = basis(n);
        let mut gr = [Vec3::ZERO; 3];
        let mut gt = [Vec3::ZERO; 3];
        let idx = |j: u32, k: u32| (j * nn + (k % nn)) as usize;
        let distances: Vec<f32> = strata.iter().map(|s| s.distance(scale)).collect();
        let dist = |i: usize| distances[i];
        // Per ring j: tan θ at its centre, sin θ at its lower and upper edges.
        let rings: Vec<[f32; 3]> = (0..m)
            .map(|j| {
                let sin_c = ((j as f32 + 0.5) / m as f32).sqrt();
                let tan_c = sin_c / (1.0 - sin_c * sin_c).max(1e-12).sqrt();
                let sin_m = (j as f32 / m as f32).sqrt();
                let sin_p = ((j + 1) as f32 / m as f32).sqrt();
                [tan_c, sin_m, sin_p]
            })
            .collect();
        for k in 0..nn {
            let [u_k, v_k, v_km] = sector_axes(t, b, k, nn);
            let mut rot = Vec3::ZERO;
            let mut theta_term = Vec3::ZERO;
            let mut phi_term = Vec3::ZERO;
            for j in 0..m {
                let s = idx(j, k);
                let [tan_c, sin_m, sin_p] = rings[j as usize];
                rot -= tan_c * radiance[s];
                if j > 0 {
                    let prev = idx(j - 1, k);
                    let r = dist(prev).min(dist(s)).max(r_min);
                    if r.is_finite() && r > 0.0 {
                        let cos2 = 1.0 - sin_m * sin_m;
                        theta_term += (sin_m * cos2 / r) * (radiance[s] - radiance[prev]);
                    }
                }
                let left = idx(j, k + nn - 1);
                let r = dist(left).min(dist(s)).max(r_min);
                if r.is_finite() && r > 0.0 {
                    phi_term += ((sin_p - sin_m) / r) * (radiance[s] - radiance[left]);
                }
            }
            rot *= PI / (m * nn) as f32;
            theta_term *= 2.0 * PI / nn as f32;
            for c in 0..3 {
                gr[c] += v_k * rot[c];
                gt[c] += u_k * theta_term[c] + v_km * phi_term[c];
            }
        }
        (gr, gt)
    }

    /// Records' worth of strata on several layouts — hits near and far, misses, distances
    /// below the minimum radius and zero ones, radiance of every size — give the same
    /// gradients to the bit as the reference, through the same decoding of the distances.
    /// Seen failing with the differences' product regrouped, and with misses' differences
    /// added (times a weight of zero).
    #[test]
    fn gradients_are_the_same_to_the_bit_as_sector_by_sector() {
        let mut state = 11u32;
        let mut unit = || {
            state = crate::sampling::hash(&[state]);
            state as f32 / u32::MAX as f32
        };
        for case in 0..300 {
            let [m, nn] = [[1, 1], [2, 3], [4, 16], [12, 36], [30, 60], [3, 1]][case % 6];
            let footprint = [1e-3f32, 0.02, 7.0][case % 3];
            let strata: Vec<Stratum> = (0..m * nn)
                .map(|_| {
                    let d = match (unit() * 8.0) as u32 {
                        0 => f32::INFINITY,
                        1 => 0.0,
                        2 => footprint * unit() * 0.5,
                        _ => footprint * (unit() * 200.0).exp2().min(1e30),
                    };
                    Stratum::new(None, 0, d, footprint)
                })
                .collect();
            // Now and then an infinite channel: a difference across a miss must not count
            // (its weight is zero, but zero times infinity is not).
            let radiance: Vec<Vec3> = (0..m * nn)
                .map(|_| match (unit() * 50.0) as u32 {
                    0 => Vec3::new(f32::INFINITY, 1.0, 0.0),
                    _ => Vec3::new(unit(), unit(), unit()) * (unit() * 20.0 - 10.0).exp2(),
                })
                .collect();
            let n = Vec3::new(unit() - 0.5, unit() - 0.5, unit() - 0.5).normalize();
            let r_min = footprint * [0.0, 0.5, 3.0][case % 3];
            let distances: Vec<f32> = stored_distances(&strata)
                .iter()
                .map(|&d| d * footprint)
                .collect();
            let by_stratum: Vec<f32> = strata.iter().map(|s| s.distance(footprint)).collect();
            assert_eq!(
                distances.iter().map(|d| d.to_bits()).collect::<Vec<_>>(),
                by_stratum.iter().map(|d| d.to_bits()).collect::<Vec<_>>(),
                "case {case}"
            );
            let bits = |g: ([Vec3; 3], [Vec3; 3])| {
                [g.0, g.1].map(|v| v.map(|v| v.to_array().map(f32::to_bits)))
            };
            assert_eq!(
                bits(gradients(&distances, &radiance, n, m, nn, r_min)),
                bits(gradients_by_sector(
                    &strata, &radiance, footprint, n, m, nn, r_min
                )),
                "case {case}"
            );
        }
    }
}
