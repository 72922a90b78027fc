//! LOD space: boxes, the cutter, the multiple-storage quadtree and queries. Pure computation,
//! no I/O.

pub mod cover;
pub mod geom;
pub mod lod;
pub mod quadtree;
pub mod query;
