//! The model: grids, mipmaps and patches. Pure computation, no I/O.

pub mod grid;
pub mod ids;
pub mod mipmap;
pub mod patch;
pub mod survey;
