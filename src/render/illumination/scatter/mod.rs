//! Multiple scattering (the paper's Algorithm 1, line 6; docs/illumination.md §4): the sweep
//! (`sweep.wgsl`), its closure (`closure.wgsl`), the coarse scattering grid (`coarse_grid`) and
//! the media of overlapping clouds (`overlap.wgsl`).

pub mod coarse_grid;
pub mod series;
