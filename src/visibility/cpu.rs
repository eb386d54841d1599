//! The CPU implementation of visibility detection (§3.2).

use glam::Vec3;
use rayon::prelude::*;

use super::{
    CPU_SLACK, DynamicSet, Error, Hemisphere, RecordFrame, StrataBits, Visibility, cover,
    sphere_cap,
};

/// The CPU implementation: [`cover`] per record and triangle, records in parallel.
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
                for (prim, range) in set.prims.iter().zip(&set.ranges) {
                    let Some(sphere) = sphere_cap(&f, *prim, CPU_SLACK).visible() else {
                        continue;
                    };
                    for tri in &set.triangles[range.clone()] {
                        cover(&h, &f, sphere, tri, CPU_SLACK, |c| bits.set(c));
                    }
                }
                bits
            })
            .collect())
    }

    fn depth_maps(&self) -> &dyn super::depth::DepthMaps {
        &super::depth::CpuDepthMaps
    }
}
