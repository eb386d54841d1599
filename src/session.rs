//! What a render keeps from one frame to the next (DESIGN.md, one owner of what survives):
//! [`FrameState`], everything a frame hands to the next and nothing else, serialisable so
//! that it can be written to disk and read back; and [`Resources`], what a render holds
//! that is not state — the static set with its BVH and the visibility implementation (a
//! GPU device, perhaps) — and is rebuilt, not saved.

use serde::{Deserialize, Serialize};

use crate::anchor::AnchorSet;
use crate::cache::IrradianceCache;
use crate::scene::StaticSet;
use crate::visibility::Visibility;

/// The state a frame hands to the next: the irradiance cache (records with their strata and
/// the record id counter) and, for the anchor method, the anchors (with their kd-tree, the
/// photon→anchor links, the previous frame's photon paths and the free-slot list).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameState {
    pub cache: IrradianceCache,
    pub anchors: Option<AnchorSet>,
}

impl FrameState {
    /// The state as bytes (postcard's compact binary encoding of the serde types), written
    /// into one allocation the size of the state's heap, so that hundreds of megabytes are
    /// not copied as the buffer grows.
    pub fn encode(&self) -> Vec<u8> {
        let room = Vec::with_capacity(self.heap_bytes() + (1 << 16));
        postcard::to_extend(self, room).expect("frame state serialises: no map keys, no I/O")
    }

    /// Bytes the state holds on the heap (an estimate from its lengths).
    pub fn heap_bytes(&self) -> usize {
        self.cache.heap_bytes() + self.anchors.as_ref().map_or(0, AnchorSet::heap_bytes)
    }

    /// Checks a state read from disk for a render whose records have `strata` strata each:
    /// every index it holds points into it, so that rendering from it cannot go out of
    /// bounds.
    pub fn check(&self, strata: usize) -> Result<(), String> {
        let anchors = match &self.anchors {
            Some(a) => {
                a.check()?;
                a.anchors.len()
            }
            None => 0,
        };
        self.cache.check(strata, anchors)
    }

    /// The state from [`FrameState::encode`]'s bytes.
    pub fn decode(bytes: &[u8]) -> Result<FrameState, postcard::Error> {
        postcard::from_bytes(bytes)
    }
}

/// What a render holds besides its state.
pub struct Resources {
    /// Static prims and their BVH, built once per render.
    pub statics: StaticSet,
    /// Where the anchor method's visibility detection runs (§3.2).
    pub visibility: Box<dyn Visibility>,
}
