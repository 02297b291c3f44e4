//! The draw (the paper's Algorithm 1, line 8, and its §4): billboards in the `Transparent3d` phase
//! (`billboards`, the raster path), the reduced-resolution cloud target upsampled by depth
//! (`cloud_target`), the draw by compute into it (`splat`, batched across clouds by
//! `splat_batch`), which frames redraw (`redraw`), each view's distance fog (`fog`) and the
//! clouds' place after Bevy's sky (`after_sky`).

pub(crate) mod after_sky;
pub mod billboard_groups;
pub mod billboard_queue;
pub mod billboards;
pub mod cloud_target;
pub mod fog;
pub(crate) mod redraw;
pub mod splat;
pub mod splat_batch;
pub mod target;

// The billboard draw was `render::draw` before the folders; its public paths stay.
pub use billboard_groups::*;
pub use billboard_queue::*;
pub use billboards::*;
