//! Checkpoints: the [`FrameState`] after a frame on disk (DESIGN.md, Shot state), so that a
//! render can stop and go on — `render --state-out DIR` writes them, `render --resume FILE`
//! starts from one — and farm chunks can hand the shot's state to each other.
//!
//! A checkpoint file is
//!
//! ```text
//! "ANCHSTAT"             8 bytes, the magic
//! format                 u32 little-endian, FORMAT
//! header                 postcard: anchorage's version and build, the job's content hash,
//!                        the frame, the state's checksum
//! state                  postcard of the FrameState, cut into chunks of CHUNK bytes (the
//!                        last may be shorter), each compressed on its own:
//!   raw length           u32 little-endian
//!   compressed length    u32 little-endian
//!   chunk                one Zstandard frame (level 1, with its content checksum)
//! ```
//!
//! The chunks are compressed and decompressed in parallel: a state at the final preset
//! holds hundreds of megabytes, and one zlib stream compressed it on one thread for about
//! half as long as the frame took to render. Zstandard at level 1 writes Sponza's state at
//! the final preset in 0.6–0.7 s, where the same chunks as zlib from libdeflate at level 1
//! took 1.0 s, into 3 % more bytes (README, "Checkpoints and farm chunks"). The state is
//! encoded and compressed, and read back and decoded, sixteen chunks at a time (`BATCH`;
//! `ChunkWriter`, `ChunkReader`): neither side holds the encoded state or the file
//! whole, which at the final preset took half as much memory again as the render.
//!
//! The magic and the format come first and fixed, so that a file of another format is named
//! as such before anything else is decoded. A checkpoint is only read back by the anchorage
//! build, job and scene content it was written for: the state links records and anchors
//! to the geometry, photon sequences and settings of one job, and reading it into another
//! would give a silently wrong image. The same holds across builds: a state made by a build
//! that places records, estimates or defaults a setting otherwise is not the state this
//! build would have made, and a shot resumed from it would differ from one rendered through
//! by either. The build is named by a hash of its sources (`build.rs`, `ANCHORAGE_BUILD`),
//! which every change to the renderer changes, where the crate's version does not.
//!
//! The content hash ([`job_hash`]) covers the job's settings (its JSON, less the keys that
//! only say which frames to render and where to write them, plus the command line's method
//! and visibility overrides) and the bytes of every file the scene was read from, so a farm
//! machine that mounts the shot at another path hashes the same. Files are written atomically ([`output::write_atomic`]).

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::job::Job;
use crate::output;
use crate::scene::Scene;
use crate::session::FrameState;

/// This build's identity, 64 hex digits: the hash of its sources (`build.rs`).
pub const BUILD: &str = env!("ANCHORAGE_BUILD");

/// The first bytes of every checkpoint.
pub const MAGIC: &[u8; 8] = b"ANCHSTAT";

/// The checkpoint format this build writes and reads. A change to [`FrameState`]'s serde
/// layout or to this file's layout increments it.
pub const FORMAT: u32 = 8;

/// Bytes of the encoded state per compressed chunk.
const CHUNK: usize = 4 << 20;

/// The most a chunk can expand to, as a multiple of its compressed length: a Zstandard
/// block holds at most 128 KiB and takes at least 4 bytes (an RLE block: its 3-byte header
/// and the byte). A chunk that claims more is damaged, and is refused before memory is
/// given to it.
const MAX_RATIO: u64 = 32 << 10;

/// The largest checkpoint read: a state holds the cache and the anchors, bounded by the
/// memory budget; a file beyond this is not one of ours.
const MAX_BYTES: u64 = 64 << 30;

/// What a checkpoint says about itself.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// The anchorage version that wrote it (`CARGO_PKG_VERSION`).
    pub version: String,
    /// The build that wrote it: the hash of its sources, [`BUILD`].
    pub build: String,
    /// [`job_hash`] of the job it belongs to.
    pub job: [u8; 32],
    /// The frame after which the state was taken.
    pub frame: i32,
    /// BLAKE3 of the compressed state that follows: a damaged file is named as such before
    /// it is decompressed.
    pub body: [u8; 32],
}

/// The content hash of a render's job and scene: what must match for a checkpoint to be
/// read back (see the module doc).
pub fn job_hash(job: &Job, scene: &Scene) -> Result<[u8; 32]> {
    let mut h = blake3::Hasher::new();
    h.update(b"anchorage job content\0");
    let text = std::fs::read(&job.path)
        .map_err(|e| Error::input(&job.path, "file", format!("cannot read: {e}")))?;
    // The job as JSON with sorted keys, less what does not reach the state. A job that is
    // not JSON here was a bare scene (`inspect`); its text then stands for itself.
    match serde_json::from_slice::<serde_json::Value>(&text) {
        Ok(serde_json::Value::Object(mut m)) => {
            m.remove("frames");
            m.remove("output");
            h.update(serde_json::Value::Object(m).to_string().as_bytes());
        }
        _ => {
            h.update(&text);
        }
    }
    h.update(format!("\0{:?}\0{:?}\0", job.method, job.render).as_bytes());
    for file in scene.files() {
        let bytes = std::fs::read(file)
            .map_err(|e| Error::input(file, "file", format!("cannot read: {e}")))?;
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(&bytes);
    }
    Ok(*h.finalize().as_bytes())
}

/// Where `--state-out DIR` puts the state after `frame`: `DIR/NAME.####.state`, beside the
/// frames' naming.
pub fn state_path(dir: &Path, job: &Job, frame: i32) -> PathBuf {
    dir.join(format!("{}.{:04}.state", job.name, frame))
}

/// Writes `state`, taken after `frame` of the job hashed `job`, to `path` atomically. The
/// state is encoded, compressed and written as it goes (`ChunkWriter`), so that the writer
/// holds a batch of chunks of it at a time, not the whole encoded state.
pub fn write(path: &Path, job: [u8; 32], frame: i32, state: &FrameState) -> Result<()> {
    write_with(path, job, frame, |w| {
        postcard::to_io(state, w)
            .map(drop)
            .map_err(|e| std::io::Error::other(format!("cannot encode the state: {e}")))
    })
}

/// [`write`] for a state already encoded ([`FrameState::encode`]).
#[cfg(test)]
fn write_encoded(path: &Path, job: [u8; 32], frame: i32, raw: &[u8]) -> Result<()> {
    write_with(path, job, frame, |w| w.write_all(raw))
}

/// Writes a checkpoint whose encoded state `encode` writes into the chunks: the header goes
/// first with its checksum of the chunks left blank, and is written again once the last
/// chunk is (its length does not depend on the checksum).
fn write_with(
    path: &Path,
    job: [u8; 32],
    frame: i32,
    encode: impl FnOnce(
        &mut ChunkWriter<&mut std::io::BufWriter<&mut std::fs::File>>,
    ) -> std::io::Result<()>,
) -> Result<()> {
    use std::io::{Seek, SeekFrom};
    let mut header = Header {
        version: env!("CARGO_PKG_VERSION").to_string(),
        build: BUILD.to_string(),
        job,
        frame,
        body: [0; 32],
    };
    output::write_atomic(path, |w| {
        let e = |e: std::io::Error| e.to_string();
        w.write_all(MAGIC).map_err(e)?;
        w.write_all(&FORMAT.to_le_bytes()).map_err(e)?;
        let head = postcard::to_stdvec(&header).expect("header serialises");
        w.write_all(&head).map_err(e)?;
        let mut chunks = ChunkWriter::new(&mut *w, CHUNK);
        encode(&mut chunks).map_err(e)?;
        header.body = chunks.finish().map_err(e)?;
        let again = postcard::to_stdvec(&header).expect("header serialises");
        if again.len() != head.len() {
            return Err("the header's length changed with its checksum".into());
        }
        let end = w.stream_position().map_err(e)?;
        w.seek(SeekFrom::Start((MAGIC.len() + 4) as u64))
            .map_err(e)?;
        w.write_all(&again).map_err(e)?;
        w.seek(SeekFrom::Start(end)).map_err(e)?;
        Ok(())
    })
}

/// Chunks compressed at once, in parallel, as a checkpoint is written or read: 64 MiB of
/// the encoded state held at a time (a state at the final preset holds hundreds of MB).
const BATCH: usize = 16;

/// The most a checkpoint's writing or reading holds beside the state itself: a batch of
/// chunks encoded and compressed, and the decoder's room for a record's strata (at most
/// 256 × 256 of 6 bytes).
pub const BUFFER_BYTES: u64 = (2 * BATCH * CHUNK) as u64 + (1 << 20);

/// The encoded state's bytes into compressed chunks (module doc), [`BATCH`] chunks at a
/// time, each written with its lengths before it and taken into the checksum.
struct ChunkWriter<W: Write> {
    out: W,
    chunk: usize,
    raw: Vec<u8>,
    hash: blake3::Hasher,
}

impl<W: Write> ChunkWriter<W> {
    fn new(out: W, chunk: usize) -> Self {
        ChunkWriter {
            out,
            chunk,
            raw: Vec::with_capacity(BATCH * chunk),
            hash: blake3::Hasher::new(),
        }
    }

    /// Compresses and writes the whole chunks held (`all`: and the last, short one).
    fn emit(&mut self, all: bool) -> std::io::Result<()> {
        let n = if all {
            self.raw.len()
        } else {
            self.raw.len() / self.chunk * self.chunk
        };
        for c in compress(&self.raw[..n], self.chunk)? {
            self.hash.update(&c);
            self.out.write_all(&c)?;
        }
        self.raw.drain(..n);
        Ok(())
    }

    /// Writes what is left; returns the checksum of every chunk written.
    fn finish(mut self) -> std::io::Result<[u8; 32]> {
        self.emit(true)?;
        Ok(*self.hash.finalize().as_bytes())
    }
}

impl<W: Write> Write for ChunkWriter<W> {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.raw.extend_from_slice(data);
        if self.raw.len() >= BATCH * self.chunk {
            self.emit(false)?;
        }
        Ok(data.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// `raw` in chunks of `chunk` bytes (the last may be shorter), compressed in parallel, each
/// with its lengths before it (module doc); `Err` where Zstandard fails (out of memory).
fn compress(raw: &[u8], chunk: usize) -> std::io::Result<Vec<Vec<u8>>> {
    use rayon::prelude::*;
    raw.par_chunks(chunk)
        .map(|part| {
            let mut out = vec![0u8; 8 + zstd::zstd_safe::compress_bound(part.len())];
            let mut z = zstd::bulk::Compressor::new(1)?;
            // Each frame checks its own content (XXH64), as zlib's Adler-32 did.
            z.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true))?;
            let n = z.compress_to_buffer(part, &mut out[8..])?;
            out[..4].copy_from_slice(&(part.len() as u32).to_le_bytes());
            out[4..8].copy_from_slice(&(n as u32).to_le_bytes());
            out.truncate(8 + n);
            Ok(out)
        })
        .collect()
}

/// The encoded state from a checkpoint's chunks (module doc), read [`BATCH`] chunks at a
/// time and decompressed in parallel, as the decoder asks for it. Damage (a chunk cut
/// short, claiming more than it may, holding other bytes than it claims, a short chunk
/// before the last) ends the reading, and `damage` says what it is.
struct ChunkReader<R: std::io::Read> {
    input: R,
    chunk: usize,
    /// The batch decompressed, and how much of it was read.
    ready: Vec<u8>,
    at: usize,
    /// Chunks read so far, and the first of them that was short.
    chunks: usize,
    short: Option<usize>,
    damage: Option<String>,
}

impl<R: std::io::Read> ChunkReader<R> {
    fn new(input: R, chunk: usize) -> Self {
        ChunkReader {
            input,
            chunk,
            ready: Vec::new(),
            at: 0,
            chunks: 0,
            short: None,
            damage: None,
        }
    }

    /// The next batch of chunks, decompressed (empty at the end of the chunks).
    fn next_batch(&mut self) -> std::result::Result<Vec<u8>, String> {
        use rayon::prelude::*;
        let mut batch: Vec<(usize, Vec<u8>)> = Vec::new();
        while batch.len() < BATCH {
            let i = self.chunks;
            let cut = || format!("chunk {i} is cut short");
            let mut lengths = [0u8; 8];
            match read_full(&mut self.input, &mut lengths) {
                Ok(0) => break,
                Ok(8) => {}
                Ok(_) => return Err(cut()),
                Err(e) => return Err(format!("chunk {i}: {e}")),
            }
            let word = |at: usize| {
                u32::from_le_bytes(lengths[at..at + 4].try_into().expect("4 bytes")) as u64
            };
            let (raw, packed) = (word(0), word(4));
            if raw == 0 || raw > self.chunk as u64 || raw > MAX_RATIO * packed {
                return Err(format!("chunk {i} claims {raw} bytes from {packed}"));
            }
            if let Some(s) = self.short {
                return Err(format!("chunk {s} is not the last and is short"));
            }
            let mut data = vec![0u8; packed as usize];
            match read_full(&mut self.input, &mut data) {
                Ok(n) if n == data.len() => {}
                Ok(_) => return Err(cut()),
                Err(e) => return Err(format!("chunk {i}: {e}")),
            }
            if raw != self.chunk as u64 {
                self.short = Some(i);
            }
            self.chunks += 1;
            batch.push((raw as usize, data));
        }
        let first = self.chunks - batch.len();
        let mut out = vec![0u8; batch.iter().map(|c| c.0).sum()];
        let mut places = Vec::with_capacity(batch.len());
        let mut rest = &mut out[..];
        for (raw, _) in &batch {
            let (place, tail) = rest.split_at_mut(*raw);
            places.push(place);
            rest = tail;
        }
        places
            .into_par_iter()
            .zip(&batch)
            .enumerate()
            .try_for_each(|(k, (place, (_, data)))| {
                let i = first + k;
                match zstd::bulk::decompress_to_buffer(data, place) {
                    Ok(n) if n == place.len() => Ok(()),
                    Ok(n) => Err(format!("chunk {i} holds {n} bytes, not {}", place.len())),
                    Err(e) => Err(format!("chunk {i}: {e}")),
                }
            })?;
        Ok(out)
    }
}

impl<R: std::io::Read> ChunkReader<R> {
    /// Makes the next batch ready once this one is read: false at the end of the chunks or
    /// where they are damaged (`damage` says how).
    fn refill(&mut self) -> bool {
        if self.at < self.ready.len() {
            return true;
        }
        if self.damage.is_some() {
            return false;
        }
        // The batch read is let go before the next is decompressed.
        (self.ready, self.at) = (Vec::new(), 0);
        match self.next_batch() {
            Ok(batch) => self.ready = batch,
            Err(m) => self.damage = Some(m),
        }
        !self.ready.is_empty()
    }
}

/// (For the tests, which read the chunks as bytes; the decoder reads them through
/// `Decoding`.)
#[cfg(test)]
impl<R: std::io::Read> std::io::Read for ChunkReader<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if !self.refill() {
            return match &self.damage {
                Some(m) => Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    m.clone(),
                )),
                None => Ok(0),
            };
        }
        let n = buf.len().min(self.ready.len() - self.at);
        buf[..n].copy_from_slice(&self.ready[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

/// The decoder's view of a [`ChunkReader`] (postcard's deserialisation `Flavor`): each byte
/// and each run of bytes straight from the batch decompressed, or, for a run that spans two
/// batches, copied into `joined` (at most `max` bytes: a record's strata). Byte strings
/// borrowed from the input are not given: the state's own are taken owned
/// (`cache::record`'s strata planes), and a request for one ends the decoding as damage.
struct Decoding<'r, R: std::io::Read> {
    chunks: &'r mut ChunkReader<R>,
    joined: Vec<u8>,
    max: usize,
}

impl<'de, R: std::io::Read + 'de> postcard::de_flavors::Flavor<'de> for Decoding<'de, R> {
    type Remainder = ();
    type Source = ();

    #[inline]
    fn pop(&mut self) -> postcard::Result<u8> {
        let c = &mut *self.chunks;
        if !c.refill() {
            return Err(postcard::Error::DeserializeUnexpectedEnd);
        }
        c.at += 1;
        Ok(c.ready[c.at - 1])
    }

    fn try_take_n(&mut self, _: usize) -> postcard::Result<&'de [u8]> {
        Err(postcard::Error::DeserializeUnexpectedEnd)
    }

    fn try_take_n_temp<'a>(&'a mut self, ct: usize) -> postcard::Result<&'a [u8]>
    where
        'de: 'a,
    {
        let c = &mut *self.chunks;
        if !c.refill() && ct > 0 {
            return Err(postcard::Error::DeserializeUnexpectedEnd);
        }
        if c.ready.len() - c.at >= ct {
            c.at += ct;
            return Ok(&c.ready[c.at - ct..c.at]);
        }
        if ct > self.max {
            return Err(postcard::Error::DeserializeUnexpectedEnd);
        }
        self.joined.clear();
        while self.joined.len() < ct {
            if !c.refill() {
                return Err(postcard::Error::DeserializeUnexpectedEnd);
            }
            let n = (ct - self.joined.len()).min(c.ready.len() - c.at);
            self.joined.extend_from_slice(&c.ready[c.at..c.at + n]);
            c.at += n;
        }
        Ok(&self.joined)
    }

    fn finalize(self) -> postcard::Result<()> {
        Ok(())
    }
}

/// Reads into `buf` until it is full or the input ends: the bytes read.
fn read_full(input: &mut impl std::io::Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match input.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// What [`compress`] made of bytes in chunks of `chunk`, decompressed; `Err` says how the
/// chunks are damaged.
#[cfg(test)]
fn decompress(body: &[u8], chunk: usize) -> std::result::Result<Vec<u8>, String> {
    use std::io::Read;
    let mut r = ChunkReader::new(body, chunk);
    let mut out = Vec::new();
    match r.read_to_end(&mut out) {
        Ok(_) => Ok(out),
        Err(e) => Err(r.damage.unwrap_or_else(|| e.to_string())),
    }
}

/// Reads the checkpoint at `path` for the job hashed `job`, whose records have `strata`
/// strata each: its frame and state. A file that is not a checkpoint, or one of another
/// format, anchorage build or job, or damaged, is refused with an input error that says
/// which.
pub fn read(path: &Path, job: [u8; 32], strata: usize) -> Result<(i32, FrameState)> {
    use std::io::{BufReader, Read, Seek, SeekFrom};
    let bad = |m: String| Error::input(path, "checkpoint", m);
    let unreadable = |e: std::io::Error| bad(format!("cannot read: {e}"));
    let (mut file, len) = crate::scene::gltf::open_limited(path, "checkpoint", MAX_BYTES)?;
    // The magic, the format and the header (a few hundred bytes) from the file's start.
    let mut start = vec![0u8; 4096];
    let got = read_full(&mut file, &mut start).map_err(unreadable)?;
    start.truncate(got);
    if start.len() < 12 || &start[..8] != MAGIC {
        return Err(bad(
            "is not an anchorage checkpoint (no ANCHSTAT header)".into()
        ));
    }
    let format = u32::from_le_bytes(start[8..12].try_into().expect("4 bytes"));
    if format != FORMAT {
        return Err(bad(format!(
            "is checkpoint format {format}; this anchorage reads format {FORMAT}"
        )));
    }
    let (header, rest): (Header, _) = postcard::take_from_bytes(&start[12..])
        .map_err(|e| bad(format!("has a damaged header: {e}")))?;
    let body_at = (start.len() - rest.len()) as u64;
    let ours = env!("CARGO_PKG_VERSION");
    if header.version != ours || header.build != BUILD {
        return Err(bad(format!(
            "was written by anchorage {} (build {}); this is {ours} (build {}), whose state \
             may differ: render the shot from its first frame, or with the build that wrote it",
            header.version,
            header.build.get(..12).unwrap_or(&header.build),
            &BUILD[..12]
        )));
    }
    if header.job != job {
        return Err(bad(format!(
            "belongs to another job or scene (content hash {} here {}): the job's settings or \
             a file it reads changed since frame {} was rendered",
            hex(&header.job[..6]),
            hex(&job[..6]),
            header.frame
        )));
    }
    // The chunks are checked against the header's checksum before any is decompressed, in
    // one pass over the file, then read again as they are decoded: neither pass holds the
    // file, nor the encoded state, whole.
    file.seek(SeekFrom::Start(body_at)).map_err(unreadable)?;
    let mut hash = blake3::Hasher::new();
    hash.update_reader(&mut file).map_err(unreadable)?;
    if *hash.finalize().as_bytes() != header.body {
        return Err(bad(
            "is damaged: its state does not match its checksum".into()
        ));
    }
    file.seek(SeekFrom::Start(body_at)).map_err(unreadable)?;
    let mut chunks = ChunkReader::new(BufReader::new(file.take(len)), CHUNK);
    let mut decoder = postcard::Deserializer::from_flavor(Decoding {
        chunks: &mut chunks,
        joined: Vec::new(),
        // The longest byte string the state holds: a record's strata.
        max: strata * size_of::<crate::cache::Stratum>() + (64 << 10),
    });
    let decoded = FrameState::deserialize(&mut decoder);
    drop(decoder);
    let state = match decoded {
        Ok(state) => state,
        Err(e) => {
            let why = chunks.damage.clone().unwrap_or_else(|| e.to_string());
            return Err(bad(format!("is damaged: {why}")));
        }
    };
    state
        .check(strata)
        .map_err(|e| bad(format!("is inconsistent: {e}")))?;
    Ok((header.frame, state))
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_damaged_or_foreign_file_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.state");
        let state = FrameState::default();
        write(&p, [7; 32], 4, &state).unwrap();
        let (frame, back) = read(&p, [7; 32], 64).unwrap();
        assert_eq!((frame, &back), (4, &state));
        let msg = |r: Result<(i32, FrameState)>| r.unwrap_err().to_string();
        assert!(msg(read(&p, [8; 32], 64)).contains("another job"));
        let mut bytes = std::fs::read(&p).unwrap();
        bytes[8] = 9;
        std::fs::write(&p, &bytes).unwrap();
        assert!(msg(read(&p, [7; 32], 64)).contains("format 9"));
        bytes[8] = FORMAT as u8;
        let n = bytes.len();
        bytes.truncate(n - 4);
        std::fs::write(&p, &bytes).unwrap();
        assert!(msg(read(&p, [7; 32], 64)).contains("damaged"));
        // Written by another build of the same version: refused, naming both builds.
        write(&p, [7; 32], 4, &state).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let (mut header, rest): (Header, _) = postcard::take_from_bytes(&bytes[12..]).unwrap();
        header.build = "0123456789ab".repeat(5) + "cdef";
        let mut other = bytes[..12].to_vec();
        other.extend(postcard::to_stdvec(&header).unwrap());
        other.extend(rest);
        std::fs::write(&p, &other).unwrap();
        let m = msg(read(&p, [7; 32], 64));
        assert!(m.contains("build 0123456789ab)"), "{m}");
        assert!(m.contains(&BUILD[..12]), "{m}");
        std::fs::write(&p, b"{\"not\": \"a state\"}").unwrap();
        assert!(msg(read(&p, [7; 32], 64)).contains("not an anchorage checkpoint"));
    }

    /// The state's chunks come back as they went in, in order; a chunk cut short, claiming
    /// more than a chunk, more than Zstandard can expand to or other bytes than it holds,
    /// or a short one before the last, is named as damaged.
    #[test]
    fn chunks_round_trip_and_damage_is_named() {
        let raw: Vec<u8> = (0..1000u32)
            .map(|i| (crate::sampling::hash(&[i / 3]) % 7) as u8)
            .collect();
        let chunks = compress(&raw, 64).unwrap();
        assert_eq!(chunks.len(), 16);
        let body = chunks.concat();
        assert_eq!(decompress(&body, 64).unwrap(), raw);
        assert_eq!(
            decompress(&compress(&raw[..64], 64).unwrap().concat(), 64).unwrap(),
            &raw[..64]
        );
        let damaged = |edit: &dyn Fn(&mut Vec<u8>)| {
            let mut b = body.clone();
            edit(&mut b);
            decompress(&b, 64).unwrap_err()
        };
        assert!(damaged(&|b| b.truncate(b.len() - 1)).contains("cut short"));
        assert!(damaged(&|b| b.truncate(b.len() - 9)).contains("cut short"));
        assert!(damaged(&|b| b[0] = 65).contains("claims 65 bytes"));
        assert!(damaged(&|b| b[4] = 0).contains("claims 64 bytes from 0"));
        let packed = u32::from_le_bytes(body[4..8].try_into().unwrap()) as usize;
        assert!(damaged(&|b| b[8 + packed / 2] ^= 0x55).contains("chunk 0"));
        // The first chunk re-made from 63 bytes: a short chunk that is not the last.
        let mut short = compress(&raw[..63], 64).unwrap();
        short.extend(compress(&raw[64..], 64).unwrap());
        assert!(
            decompress(&short.concat(), 64)
                .unwrap_err()
                .contains("chunk 0 is not the last")
        );
    }

    /// A checkpoint is written and read a batch of chunks at a time: the writer holds at
    /// most a batch of the encoded state (and the write that filled it), the reader one
    /// batch decompressed, and the chunks are those of the whole state compressed at once.
    #[test]
    fn chunks_stream_a_batch_at_a_time() {
        use std::io::Read;
        let chunk = 64;
        let raw: Vec<u8> = (0..(BATCH as u32 * 3 + 5) * chunk as u32 + 17)
            .map(|i| (crate::sampling::hash(&[i / 5]) % 11) as u8)
            .collect();
        let mut out = Vec::new();
        let mut w = ChunkWriter::new(&mut out, chunk);
        for piece in raw.chunks(100) {
            w.write_all(piece).unwrap();
            assert!(w.raw.len() < BATCH * chunk + piece.len(), "{}", w.raw.len());
        }
        let sum = w.finish().unwrap();
        let whole = compress(&raw, chunk).unwrap().concat();
        assert!(out == whole, "the chunks of the state compressed at once");
        assert_eq!(sum, *blake3::hash(&whole).as_bytes());
        let mut r = ChunkReader::new(&out[..], chunk);
        let mut back = Vec::new();
        let mut piece = [0u8; 10];
        loop {
            let n = r.read(&mut piece).unwrap();
            assert!(r.ready.len() <= BATCH * chunk);
            if n == 0 {
                break;
            }
            back.extend_from_slice(&piece[..n]);
        }
        assert!(back == raw, "the state read back");
    }

    /// A record's strata survive the byte planes they are stored in; a byte string that is
    /// not whole strata is refused.
    #[test]
    fn strata_are_stored_as_planes() {
        use crate::anchor::AnchorId;
        use crate::cache::Stratum;
        use crate::cache::record::Record;
        use glam::Vec3;

        let strata: Vec<Stratum> = (0..7u32)
            .map(|i| Stratum::new(Some(AnchorId(i * 40_000)), (i % 4) as u8, i as f32, 0.5))
            .collect();
        let record = Record {
            strata,
            ..Record::bare(Vec3::ZERO, Vec3::Y, 1.0)
        };
        let bytes = postcard::to_stdvec(&record).unwrap();
        let back: Record = postcard::from_bytes(&bytes).unwrap();
        assert_eq!(back.strata, record.strata);
        // The first of the strata's bytes, planes apart: every link's low byte, then every
        // link's second byte.
        let planes = 7 * 6;
        let at = bytes
            .windows(planes)
            .position(|w| w[..7] == [0, 64, 128, 192, 0, 64, 128])
            .expect("the planes are in the encoding");
        assert_eq!(
            bytes[at - 1] as usize,
            planes,
            "one byte string, its length before it"
        );
        let mut cut = bytes.clone();
        cut[at - 1] = planes as u8 - 1;
        cut.remove(at + planes - 1);
        assert!(postcard::from_bytes::<Record>(&cut).is_err());
    }

    /// A state of one record of four strata, linking the second of two anchors.
    fn small_state() -> FrameState {
        use crate::anchor::packed::Quantizer;
        use crate::anchor::{Anchor, AnchorId, AnchorSet};
        use crate::cache::Stratum;
        use crate::cache::record::Record;
        use glam::Vec3;

        let q = Quantizer::new(Vec3::ZERO, Vec3::ONE);
        let mut set = AnchorSet::new(q);
        for x in [0.2, 0.7] {
            set.add(Anchor::new(
                &q,
                Vec3::splat(x),
                Vec3::Y,
                Vec3::splat(0.5),
                Vec3::ONE,
            ));
        }
        let record = Record {
            strata: vec![Stratum::new(Some(AnchorId(1)), 0, 1.0, 0.01); 4],
            dominant_anchor: Some(AnchorId(1)),
            ..Record::bare(Vec3::ZERO, Vec3::Y, 1.0)
        };
        let mut state = FrameState::default();
        state.cache.records.push(record);
        state.anchors = Some(set);
        state
    }

    /// A checkpoint whose encoded state was altered and then compressed and checksummed
    /// anew (a file edited with care, or written by a faulty build) is read back whole or
    /// refused as damaged or inconsistent, and never panics: every byte of the state in
    /// turn set to four other values, and the state cut short at every length.
    #[test]
    fn an_altered_state_is_refused_or_read_never_panics() {
        let raw = small_state().encode();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.state");
        let (mut read_back, mut refused) = (0, 0);
        let mut variants: Vec<Vec<u8>> = (0..raw.len()).map(|n| raw[..n].to_vec()).collect();
        for i in 0..raw.len() {
            for v in [0x00, 0xff, raw[i] ^ 0x01, raw[i].wrapping_add(0x80)] {
                let mut bad = raw.clone();
                bad[i] = v;
                variants.push(bad);
            }
        }
        for bad in &variants {
            write_encoded(&p, [7; 32], 4, bad).unwrap();
            match read(&p, [7; 32], 4) {
                Ok((_, state)) => {
                    assert!(state.check(4).is_ok());
                    read_back += 1;
                }
                Err(e) => {
                    let m = e.to_string();
                    assert!(m.contains("damaged") || m.contains("inconsistent"), "{m}");
                    refused += 1;
                }
            }
        }
        assert!(
            refused > raw.len(),
            "{refused} of {} refused",
            variants.len()
        );
        assert!(read_back > 0, "no altered state read back");
    }

    /// A state whose indices point outside itself (a file written by a faulty build, or
    /// edited) is refused on reading, naming what is wrong, before anything renders from it.
    #[test]
    fn an_inconsistent_state_is_refused() {
        use crate::anchor::AnchorId;
        use crate::cache::Stratum;

        let good = small_state();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.state");
        write(&p, [7; 32], 4, &good).unwrap();
        assert_eq!(read(&p, [7; 32], 4).unwrap(), (4, good.clone()));

        // The set's private fields, through its serialised form.
        fn edit_anchors(s: &mut FrameState, key: &str, value: serde_json::Value) {
            let mut v = serde_json::to_value(s.anchors.as_ref().unwrap()).unwrap();
            v[key] = value;
            s.anchors = Some(serde_json::from_value(v).unwrap());
        }
        type Damage = fn(&mut FrameState);
        let cases: [(Damage, &str); 6] = [
            (
                |s| s.cache.records[0].strata[2] = Stratum::new(Some(AnchorId(2)), 0, 1.0, 0.01),
                "links an anchor that does not exist",
            ),
            (|s| s.cache.records[0].radius = f32::NAN, "non-finite"),
            (
                |s| s.cache.records[0].strata.pop().map(drop).unwrap_or(()),
                "has 3 strata",
            ),
            (
                |s| s.anchors.as_mut().unwrap().photon_links = vec![None, Some(AnchorId(5))],
                "a photon links to an anchor",
            ),
            (
                |s| edit_anchors(s, "free", serde_json::json!([9])),
                "free anchor slot",
            ),
            (
                |s| edit_anchors(s, "reach", serde_json::json!([0])),
                "reaches",
            ),
        ];
        for (damage, reason) in cases {
            let mut bad = good.clone();
            damage(&mut bad);
            write(&p, [7; 32], 4, &bad).unwrap();
            let err = read(&p, [7; 32], 4).unwrap_err().to_string();
            assert!(
                err.contains("inconsistent") && err.contains(reason),
                "{reason}: {err}"
            );
        }
    }
}
