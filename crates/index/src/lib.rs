//! LOD space (§4 of *Patchwork Terrains*): patches as boxes, the cutter that makes the index
//! order-independent, the coverage tests, the multiple-storage quadtree and the uniform and
//! view-dependent cuts. Pure computation, no I/O; it imports the model and the geometry below
//! it, and nothing above.

pub mod cover;
pub mod lod;
pub mod quadtree;
pub mod query;
