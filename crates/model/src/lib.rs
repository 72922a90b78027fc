//! The model: grids, mipmaps and patches. Pure computation, no I/O.

pub mod accuracy;
pub mod change;
pub mod coreg;
pub mod detail;
pub mod edge;
pub mod epoch;
pub mod evidence;
pub mod geoid;
pub mod grid;
pub mod ids;
pub mod lattice;
pub mod lines;
pub mod mipmap;
pub mod patch;
pub mod place;
pub mod source;
pub mod spline;
pub mod survey;
pub mod transfer;
