//! The CPU implementation of visibility detection (§3.2).

use glam::Vec3;
use rayon::prelude::*;

use super::{
    CPU_SLACK, DynamicSet, Error, Hemisphere, Node, RecordFrame, SphereCap, StrataBits, Visibility,
    adds_nothing, cover, faces_away, sphere_cap, sphere_cells,
};

/// The CPU implementation: [`cover`] per record and triangle, records in parallel. A
/// prim's triangles stop once the record's bits hold every cell its bounding sphere may
/// reach ([`sphere_cells`]), and [`cover`] skips the cells already set: on Sponza (a
/// 62-triangle box) the stage took 0.34 s a frame instead of 0.53 s at 640 × 360 and the
/// production preset (32 k records, 12 × 36 strata), 0.52 s instead of 0.60 s at 320 × 180
/// and the final preset (30 × 60 strata), the same bits.
///
/// A closed prim's triangles that face away from a record outside its sphere are left out,
/// and runs of triangles whose cells are all set already are passed over (module doc).
/// With CesiumMan (4 672 triangles) walking in Sponza (`benches/sponza/job_character.json`,
/// production, 320 × 180) the stage took 5.3–6.2 s a frame with every triangle tested,
/// 2.9–3.5 s with the triangles facing away left out, 1.5–1.8 s with runs of 32 passed
/// over as well, and 1.1–1.2 s with runs of 8 ([`super::CLUSTER`]); the example room's
/// cube 0.26, 0.21 and 0.17–0.18 s over frames 1–8. The same EXRs; one stratum fewer
/// flagged in five of the character's frames. With the character's runs taken along a
/// Morton curve and walked as a tree (module doc, "Clusters"), 0.31–0.44 s against
/// 1.02–1.33 s in three rounds of a slower spell (0.77–0.94 s with the tree alone), the
/// same EXRs and flags. With a cell's four quarters tested at once in SIMD lanes, and the
/// enumeration's rows and their columns four at a time (`QuarterLanes`, `RowLanes`),
/// 0.23–0.35 s against 0.31–0.47 s (frames 1–4, three rounds), and 0.99–1.41 s against
/// 1.31–1.86 s at the final preset (frames 1–2, three rounds); the same flags and EXRs.
pub struct CpuVisibility;

impl Visibility for CpuVisibility {
    fn name(&self) -> String {
        "cpu".into()
    }

    fn flag(
        &self,
        records: &[(Vec3, Vec3)],
        strata: [u32; 2],
        set: &DynamicSet,
    ) -> Result<Vec<StrataBits>, Error> {
        let h = Hemisphere::new(strata);
        Ok(records
            .par_iter()
            .map(|&(x, normal)| {
                let mut bits = StrataBits::new(h.len());
                let f = RecordFrame::new(x, normal);
                let prims = set.prims.iter().zip(&set.ranges).zip(&set.closed);
                for (((prim, range), closed), clusters) in prims.zip(&set.clusters) {
                    let Some(sphere) = sphere_cap(&f, *prim, CPU_SLACK).visible() else {
                        continue;
                    };
                    // Where the prim has more than a few triangles, they stop once every
                    // cell its sphere may reach is set (the bits are the same).
                    let reach = sphere
                        .filter(|_| range.len() > 4)
                        .map(|s| sphere_cells(&h, s, CPU_SLACK));
                    // Outside a closed prim's sphere, the triangles that face the record
                    // cover whatever the others do (`closes_up`).
                    let facing_only = *closed && sphere.is_some();
                    let mut walk = Walk {
                        set,
                        h: &h,
                        f: &f,
                        sphere,
                        reach: reach.as_ref(),
                        facing_only,
                        bits: &mut bits,
                    };
                    let top = clusters.len() - 1;
                    walk.visit(clusters, top, 0..clusters[top].len());
                }
                bits
            })
            .collect())
    }

    fn depth_maps(&self) -> &dyn super::depth::DepthMaps {
        &super::depth::CpuDepthMaps
    }
}

/// One record's walk down a prim's tree of clusters ([`DynamicSet::clusters`]).
struct Walk<'a> {
    set: &'a DynamicSet,
    h: &'a Hemisphere,
    f: &'a RecordFrame,
    sphere: Option<SphereCap>,
    /// The cells the prim's sphere may reach, where it has more than a few triangles.
    reach: Option<&'a StrataBits>,
    facing_only: bool,
    bits: &'a mut StrataBits,
}

impl Walk<'_> {
    /// Covers the triangles of `nodes` of `tree[level]`; false once the bits hold `reach`.
    fn visit(&mut self, tree: &[Vec<Node>], level: usize, nodes: std::ops::Range<usize>) -> bool {
        for (ball, below) in &tree[level][nodes] {
            // A node whose cells are all set already is passed over.
            if adds_nothing(self.h, self.f, *ball, CPU_SLACK, self.bits) {
                continue;
            }
            if level > 0 {
                if !self.visit(tree, level - 1, below.clone()) {
                    return false;
                }
                continue;
            }
            let faces = &self.set.faces[below.clone()];
            for (tri, face) in self.set.triangles[below.clone()].iter().zip(faces) {
                if self.reach.is_some_and(|r| self.bits.contains(r)) {
                    return false;
                }
                if self.facing_only && faces_away(self.f.x, face) {
                    continue;
                }
                cover(self.h, self.f, self.sphere, tri, CPU_SLACK, self.bits);
            }
        }
        true
    }
}
