//! The shading pass's rays, logged so that watch mode's relight need not trace them again
//! (`crate::watch`). After a light or material edit the geometry and the camera are those
//! of the render that left the frame's state, so every camera ray meets what it met then,
//! and every shadow ray cast again from the same point towards the same point of a light is
//! blocked or not as it was. The cached methods' shading pass logs, per camera sample, what
//! its camera ray hit and what its shadow rays answered ([`ShadingLog`], made row by row in
//! [`RowLog`]s); a relight of the same frame reads them back instead of tracing: camera hits
//! by place (the same pixel centre, the same sample), shadow answers by place and ray
//! ([`ShadowRays`]) — a light that moved, or an emitter picked by other powers, casts other
//! rays, which are traced. The image is the one tracing gives, bit for bit. The surface
//! point at each hit is evaluated again (a material edit may change its normal map), and
//! reflection rays (glossy lobes, the BRDF sample of multiple importance sampling) and
//! bucketing's depth queries are traced as before.
//!
//! The log also keeps each sample's direct light, and the content keys of the lights and of
//! every material it was computed with ([`DirectKeys`], which watch mode gives the render).
//! A relight whose lights are those of the log reuses the direct light of every sample on a
//! material whose key is unchanged — after a material edit, all samples but those on the
//! edited material — and computes the others (their shadow rays answered from the log).
//!
//! Where the lights changed but a sample's material did not (a light's intensity or colour
//! edited), or the material changed but not its surface's shading normals (a colour or a
//! roughness edited), its direct light is not reused whole but its emitter samples are
//! ([`EmitterSample`]): a relight picks each sample's emitter again, and where the pick is
//! the logged one (the same emitter with the same probability — the lights' powers decide
//! it), reads back the direction, the geometric factor and the shadow answer, and the BRDF
//! value if the material is unchanged (else evaluates the new BRDF in that direction); only
//! the emission is read again. Picks that moved are computed afresh. The emitters' key
//! ([`emitters_key`]) makes sure an index names the same triangle.
//!
//! And it keeps each cache read's valid records with their interpolation weights, under a
//! key of everything that decides them (`IrradianceCache::interpolation_key`: the records'
//! positions, normals, reaches and enclosure, and the error thresholds). A relight whose
//! cache has the key of the log reads the records' new values with the logged weights
//! instead of searching the cache — the same sums, in the same order.
//!
//! Size: 12 bytes per camera sample and pixel centre, 32 more per sample, 8 per shadow ray,
//! 64 per emitter sample, 4 per cache read and 8 per record valid there, kept as the rows
//! that logged it; watch mode keeps it beside the frame's
//! state within the state memory budget, and drops it where it does not fit.

use crate::accel::Hit;
use crate::bsdf::Lobes;
use crate::cache::Contribution;
use crate::interaction::{EmitterSample, Reuse, ShadowRays};

/// What a sample's direct light depends on besides the geometry, the camera and the
/// sampling (which a relight keeps): the lights — punctual lights, every material's
/// emission and emissive texture — as one key, and each material's content (the textures
/// it reads included) as another.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct DirectKeys {
    pub lights: u64,
    pub materials: Vec<u64>,
    /// Per material, what its surfaces' shading normals depend on (normal map, sidedness,
    /// cut-out): where it is unchanged, a logged emitter sample's direction and geometric
    /// factor still hold.
    pub surfaces: Vec<u64>,
}

/// One frame's logged camera hits and shadow answers (module doc), kept as the rows that
/// logged them (a row's log is read in place, never copied into one array).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ShadingLog {
    width: u32,
    height: u32,
    spp: u32,
    rows: Vec<RowLog>,
    /// What the direct light was computed with (`None`: unknown, never reused).
    keys: Option<DirectKeys>,
    /// The cache's interpolation key when the rows logged their cache reads
    /// (`IrradianceCache::interpolation_key`; `None`: unknown, never replayed).
    interpolation: Option<u64>,
    /// The emitters' key when the rows logged their emitter samples ([`emitters_key`]).
    emitters_key: Option<u64>,
}

/// A key of the frame's emitters as direct light samples them: each one's triangle, area
/// and sidedness, in order (the index an emitter sample names).
pub fn emitters_key(frame: &crate::scene::FrameScene) -> u64 {
    use std::hash::Hasher;
    let mut h = std::hash::DefaultHasher::new();
    h.write_usize(frame.emitters.list.len());
    for e in &frame.emitters.list {
        h.write_u8(e.motion as u8);
        h.write_u32(e.triangle);
        h.write_u32(e.area.to_bits());
        h.write_u8(u8::from(e.double_sided));
    }
    h.finish()
}

/// One row's part of a [`ShadingLog`], made as the row is shaded: its pixels in order,
/// each pixel's centre and then its samples.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RowLog {
    /// Per pixel, its centre's camera hit and then each sample's: pixel `x`'s centre at
    /// `x·(spp + 1)`, its sample `s` at `x·(spp + 1) + 1 + s`. Empty in a pass that replays
    /// a log: its camera hits are that log's ([`ShadingLog::join`]).
    camera: Vec<Option<Hit>>,
    /// Per camera sample (`x·spp + s`), where its shadow answers start in `shadow`, and,
    /// once joined, one more entry for the end.
    starts: Vec<u32>,
    /// Shadow answers ([`ShadowRays`]' log entries).
    shadow: Vec<u64>,
    /// Per camera sample, its direct light (zero where it hit nothing).
    direct: Vec<Lobes>,
    /// Per camera sample, where its emitter samples start in `emitters` (and, once joined,
    /// one more entry for the end).
    emitter_starts: Vec<u32>,
    /// The emitter samples of direct light ([`EmitterSample`]).
    emitters: Vec<EmitterSample>,
    /// Per cache read of the row, in order, where its valid records end in `interp`.
    interp_ends: Vec<u32>,
    /// The cache reads' valid records and weights (none: no record was valid).
    interp: Vec<(u32, f32)>,
}

impl RowLog {
    /// Room for a row of `width` pixels of `spp` samples, about `shadow` shadow answers and
    /// `emitters` emitter samples, and their camera hits unless `camera` is false.
    pub fn reserve(
        &mut self,
        width: u32,
        spp: u32,
        (shadow, emitters): (usize, usize),
        camera: bool,
    ) {
        let samples = width as usize * spp as usize;
        if camera {
            self.camera.reserve(samples + width as usize);
        }
        self.starts.reserve(samples + 1);
        self.emitter_starts.reserve(samples + 1);
        self.direct.reserve(samples);
        self.shadow.reserve(shadow);
        self.emitters.reserve(emitters);
    }

    /// Logs a pixel centre's camera hit.
    pub fn centre(&mut self, hit: Option<Hit>) {
        self.camera.push(hit);
    }

    /// Logs a camera sample's hit (`None`: a replayed hit, which the log it came from
    /// keeps); the shadow answers logged next are this sample's.
    pub fn sample(&mut self, hit: Option<Option<Hit>>) {
        if let Some(hit) = hit {
            self.camera.push(hit);
        }
        self.starts.push(self.shadow.len() as u32);
        self.emitter_starts.push(self.emitters.len() as u32);
        self.direct.push(Lobes::ZERO);
    }

    /// Where the current sample's shadow answers go.
    pub fn shadow(&mut self) -> &mut Vec<u64> {
        &mut self.shadow
    }

    /// Where the current sample's shadow answers and emitter samples go.
    fn shadow_and_emitters(&mut self) -> (&mut Vec<u64>, &mut Vec<EmitterSample>) {
        (&mut self.shadow, &mut self.emitters)
    }

    /// Logs the current sample's direct light.
    pub fn direct(&mut self, l: Lobes) {
        if let Some(last) = self.direct.last_mut() {
            *last = l;
        }
    }

    /// Logs a cache read's valid records and weights.
    pub fn interpolation(&mut self, parts: &[Contribution]) {
        self.interp
            .extend(parts.iter().map(|c| (c.record, c.weight)));
        self.interp_ends.push(self.interp.len() as u32);
    }

    /// Cache read `i`'s valid records and weights, if the row logged that many.
    fn read(&self, i: usize) -> Option<&[(u32, f32)]> {
        let end = *self.interp_ends.get(i)? as usize;
        let start = match i {
            0 => 0,
            _ => self.interp_ends[i - 1] as usize,
        };
        self.interp.get(start..end)
    }

    fn heap_bytes(&self) -> usize {
        self.camera.capacity() * size_of::<Option<Hit>>()
            + self.starts.capacity() * size_of::<u32>()
            + self.shadow.capacity() * size_of::<u64>()
            + self.direct.capacity() * size_of::<Lobes>()
            + self.emitter_starts.capacity() * size_of::<u32>()
            + self.emitters.capacity() * size_of::<EmitterSample>()
            + self.interp_ends.capacity() * size_of::<u32>()
            + self.interp.capacity() * size_of::<(u32, f32)>()
    }
}

impl ShadingLog {
    /// The log of a `width`×`height` image of `spp` samples per pixel from its rows' logs,
    /// top row first, its direct light computed with `keys`; rows that logged no camera
    /// hits take those of `replayed` (the log the pass replayed). `None` if they do not add
    /// up to it (a row logged nothing).
    pub fn join(
        width: u32,
        height: u32,
        spp: u32,
        rows: impl IntoIterator<Item = RowLog>,
        keys: Option<DirectKeys>,
        replayed: Option<ShadingLog>,
    ) -> Option<ShadingLog> {
        let samples = width as usize * spp as usize;
        let mut old = replayed
            .filter(|l| l.fits(width, height, spp))
            .map(|l| l.rows.into_iter());
        let mut log = ShadingLog {
            width,
            height,
            spp,
            rows: Vec::with_capacity(height as usize),
            keys,
            interpolation: None,
            emitters_key: None,
        };
        for mut row in rows {
            let old_row = old.as_mut().and_then(|o| o.next());
            if row.camera.is_empty() {
                row.camera = old_row?.camera;
            }
            let end = u32::try_from(row.shadow.len()).ok()?;
            let emitters_end = u32::try_from(row.emitters.len()).ok()?;
            let complete = row.camera.len() == samples + width as usize
                && row.starts.len() == samples
                && row.emitter_starts.len() == samples
                && row.direct.len() == samples;
            if !complete {
                return None;
            }
            row.starts.push(end);
            row.emitter_starts.push(emitters_end);
            log.rows.push(row);
        }
        (log.rows.len() == height as usize).then_some(log)
    }

    /// The log with its cache reads made where the cache's interpolation key was `key`.
    pub fn with_interpolation_key(self, key: Option<u64>) -> ShadingLog {
        ShadingLog {
            interpolation: key,
            ..self
        }
    }

    /// The log with its emitter samples made where the emitters' key was `key`.
    pub fn with_emitters_key(self, key: Option<u64>) -> ShadingLog {
        ShadingLog {
            emitters_key: key,
            ..self
        }
    }

    /// Whether the log is of a `width`×`height` image of `spp` samples per pixel.
    pub fn fits(&self, width: u32, height: u32, spp: u32) -> bool {
        (self.width, self.height, self.spp) == (width, height, spp)
            && self.rows.len() == height as usize
    }

    /// Pixel `pixel`'s row log and its place in the row.
    fn at(&self, pixel: u32) -> (&RowLog, usize) {
        let w = self.width.max(1);
        (&self.rows[(pixel / w) as usize], (pixel % w) as usize)
    }

    /// What pixel `pixel`'s centre ray hit.
    pub fn centre(&self, pixel: u32) -> Option<Hit> {
        let (row, x) = self.at(pixel);
        row.camera[x * (self.spp as usize + 1)]
    }

    /// What sample `s` of pixel `pixel` hit.
    pub fn sample(&self, pixel: u32, s: u32) -> Option<Hit> {
        let (row, x) = self.at(pixel);
        row.camera[x * (self.spp as usize + 1) + 1 + s as usize]
    }

    /// Sample `s` of pixel `pixel`'s shadow answers, for [`ShadowRays::logged`].
    pub fn shadow(&self, pixel: u32, s: u32) -> &[u64] {
        let (row, x) = self.at(pixel);
        let i = x * self.spp as usize + s as usize;
        &row.shadow[row.starts[i] as usize..row.starts[i + 1] as usize]
    }

    /// Sample `s` of pixel `pixel`'s emitter samples.
    pub fn emitters(&self, pixel: u32, s: u32) -> &[EmitterSample] {
        let (row, x) = self.at(pixel);
        let i = x * self.spp as usize + s as usize;
        &row.emitters[row.emitter_starts[i] as usize..row.emitter_starts[i + 1] as usize]
    }

    /// Sets every logged emitter sample's BRDF value to zero. Public for the test that a
    /// relight reads them.
    #[doc(hidden)]
    pub fn clear_emitter_brdfs(&mut self) {
        for e in self.rows.iter_mut().flat_map(|r| &mut r.emitters) {
            e.clear_brdf();
        }
    }

    /// Shadow answers and emitter samples logged in image row `y`.
    pub fn row_lengths(&self, y: u32) -> (usize, usize) {
        self.rows
            .get(y as usize)
            .map_or((0, 0), |r| (r.shadow.len(), r.emitters.len()))
    }

    /// Sample `s` of pixel `pixel`'s logged direct light.
    fn direct(&self, pixel: u32, s: u32) -> Lobes {
        let (row, x) = self.at(pixel);
        row.direct[x * self.spp as usize + s as usize]
    }

    /// Inverts every logged shadow answer. Public for the test that a relight reads them.
    #[doc(hidden)]
    pub fn invert_shadow_answers(&mut self) {
        for r in &mut self.rows {
            for e in &mut r.shadow {
                *e ^= 1;
            }
            for e in &mut r.emitters {
                e.invert_shadow();
            }
        }
    }

    /// Sets every logged direct light to zero. Public for the test that a relight reuses
    /// it where, and only where, its keys allow.
    #[doc(hidden)]
    pub fn clear_direct_light(&mut self) {
        for r in &mut self.rows {
            r.direct.fill(Lobes::ZERO);
        }
    }

    /// Sets every logged cache read's weights to 1. Public for the test that a relight
    /// reads them.
    #[doc(hidden)]
    pub fn flatten_interpolation_weights(&mut self) {
        for (_, w) in self.rows.iter_mut().flat_map(|r| &mut r.interp) {
            *w = 1.0;
        }
    }

    /// Bytes the log holds on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.rows.iter().map(RowLog::heap_bytes).sum::<usize>()
            + self.rows.capacity() * size_of::<RowLog>()
            + self.keys.as_ref().map_or(0, |k| {
                (k.materials.capacity() + k.surfaces.capacity()) * size_of::<u64>()
            })
    }
}

/// A shading pass's log: the one it replays (a relight's: the log of the render that left
/// the state), and whether it logs its own.
#[derive(Clone, Copy, Default)]
pub struct Replay<'a> {
    pub known: Option<&'a ShadingLog>,
    pub log: bool,
    /// The keys of this render's lights and materials (module doc), if known.
    pub keys: Option<&'a DirectKeys>,
    /// The pass's camera samples per pixel (what a row's log makes room for).
    pub spp: u32,
    /// The cache's interpolation key in this pass (`IrradianceCache::interpolation_key`):
    /// where it is the known log's, the cache reads are replayed.
    pub interpolation: Option<u64>,
    /// The emitters' key in this pass ([`emitters_key`]): where it is the known log's, its
    /// emitter samples may be reused.
    pub emitters: Option<u64>,
}

impl<'a> Replay<'a> {
    /// Whether the pass logs camera hits (not where it replays them: those are the known
    /// log's).
    pub fn logs_camera(&self) -> bool {
        self.log && self.known.is_none()
    }

    /// The centre of pixel `pixel`: its logged hit, if known.
    pub fn centre(&self, pixel: u32) -> Option<Option<Hit>> {
        self.known.map(|l| l.centre(pixel))
    }

    /// Sample `s` of pixel `pixel`: its logged hit, if known.
    pub fn sample(&self, pixel: u32, s: u32) -> Option<Option<Hit>> {
        self.known.map(|l| l.sample(pixel, s))
    }

    /// The valid records and weights of the `i`-th cache read of pixel `pixel`'s row, from
    /// the known log where the cache's records are valid where they were when it was
    /// logged (equal interpolation keys).
    pub fn interpolation(&self, pixel: u32, i: usize) -> Option<&'a [(u32, f32)]> {
        let known = self.known?;
        if known.interpolation.is_none() || known.interpolation != self.interpolation {
            return None;
        }
        known
            .rows
            .get((pixel / known.width.max(1)) as usize)?
            .read(i)
    }

    /// Sample `s` of pixel `pixel`'s direct light from the known log, on a surface of
    /// material `material`, where the lights and that material are those it was logged
    /// with; its logged shadow answers are logged again into `row` (if this pass logs) and
    /// counted in `cast`, as if cast.
    pub fn direct(
        &self,
        pixel: u32,
        s: u32,
        material: u32,
        cast: &mut u64,
        row: &mut RowLog,
    ) -> Option<Lobes> {
        let known = self.known?;
        let (then, now) = (known.keys.as_ref()?, self.keys?);
        let m = material as usize;
        let same = then.lights == now.lights
            && then
                .materials
                .get(m)
                .is_some_and(|k| now.materials.get(m) == Some(k));
        if !same {
            return None;
        }
        let answers = known.shadow(pixel, s);
        *cast += answers.len() as u64;
        if self.log {
            let (shadow, emitters) = row.shadow_and_emitters();
            shadow.extend_from_slice(answers);
            emitters.extend_from_slice(known.emitters(pixel, s));
        }
        Some(known.direct(pixel, s))
    }

    /// Sample `s` of pixel `pixel`'s shadow rays: answered from the known log, logged into
    /// `row` if this pass logs, counted in `cast`.
    /// Sample `s` of pixel `pixel`'s shadow rays: answered from the known log, logged into
    /// `row` if this pass logs, counted in `cast`; with the known log's emitter samples, as
    /// far as the keys of the lights and of the sample's material allow them.
    pub fn shadow_rays<'r>(
        &self,
        pixel: u32,
        s: u32,
        material: u32,
        cast: &'r mut u64,
        row: &'r mut RowLog,
    ) -> ShadowRays<'r>
    where
        'a: 'r,
    {
        let known = self.known.map_or(&[][..], |l| l.shadow(pixel, s));
        let m = material as usize;
        let reuse = match (self.known, self.keys) {
            (Some(l), Some(now)) if l.emitters_key.is_some() && l.emitters_key == self.emitters => {
                let then = l.keys.as_ref();
                let same = |k: fn(&DirectKeys) -> &Vec<u64>| {
                    then.and_then(|t| k(t).get(m))
                        .is_some_and(|v| k(now).get(m) == Some(v))
                };
                if same(|k| &k.materials) && same(|k| &k.surfaces) {
                    Reuse::Brdf
                } else if same(|k| &k.surfaces) {
                    Reuse::Surface
                } else {
                    Reuse::None
                }
            }
            _ => Reuse::None,
        };
        let emitters = match (self.known, reuse) {
            (Some(l), Reuse::Surface | Reuse::Brdf) => l.emitters(pixel, s),
            _ => &[][..],
        };
        if self.log {
            let (shadow, log) = row.shadow_and_emitters();
            ShadowRays::logged(cast, known, Some(shadow)).with_emitters(emitters, reuse, Some(log))
        } else {
            ShadowRays::logged(cast, known, None).with_emitters(emitters, reuse, None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Motion;

    fn hit(t: f32) -> Option<Hit> {
        Some(Hit {
            t,
            motion: Motion::Static,
            triangle: 7,
        })
    }

    #[test]
    fn rows_join_into_a_log_read_by_pixel_and_sample() {
        // 2×2 pixels, 2 samples each: row 0 then row 1.
        let mut rows = Vec::new();
        for y in 0..2u32 {
            let mut row = RowLog::default();
            for x in 0..2u32 {
                let p = (y * 2 + x) as f32;
                row.centre(hit(p));
                for s in 0..2u32 {
                    row.sample(Some(if s == 1 && x == 1 { None } else { hit(p + 0.5) }));
                    for r in 0..(x + s) {
                        row.shadow().push(u64::from(y * 100 + x * 10 + s + r));
                    }
                }
            }
            rows.push(row);
        }
        let log = ShadingLog::join(2, 2, 2, rows.clone(), None, None).expect("complete");
        assert!(log.fits(2, 2, 2));
        assert!(!log.fits(2, 2, 4));
        assert_eq!(log.centre(3), hit(3.0));
        assert_eq!(log.sample(2, 0), hit(2.5));
        assert_eq!(log.sample(3, 1), None);
        assert_eq!(log.shadow(0, 0), &[] as &[u64]);
        assert_eq!(log.shadow(3, 1), &[111, 112]);
        assert_eq!(log.shadow(2, 1), &[101]);
        // A row that logged nothing: no log.
        assert!(ShadingLog::join(2, 2, 2, [RowLog::default()], None, None).is_none());
        // Rows of a pass that replayed `log` keep its camera hits.
        let replaying = rows.into_iter().map(|mut r| {
            r.camera.clear();
            r
        });
        let again = ShadingLog::join(2, 2, 2, replaying, None, Some(log.clone()));
        assert_eq!(again.as_ref(), Some(&log));
    }
}
